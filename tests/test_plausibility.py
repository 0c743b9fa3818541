"""Plausibility warnings (issue 35, item 4): speeds beyond human limits, joints behind the camera, sudden flips and
the head below the pelvis, each named with its frames; none on the synthetic motions' ground truth."""

from __future__ import annotations

import functools
import json
import logging

import numpy as np
import pytest

from eventcap.body.kinematics import joint_positions
from eventcap.body.motions import MOTIONS, sequence_poses
from eventcap.body.procedural import procedural_template
from eventcap.camera import davis240c_default
from eventcap.analysis.plausibility import check_motion, log_findings, write_plausibility

T_US = np.arange(0, 1_000_001, 1000)


@functools.lru_cache(maxsize=None)
def truth(motion: str = "karate_kick", seed: int = 0) -> np.ndarray:
    tpl = procedural_template(seed=0, height_m=1.75, target_faces=2000)
    return joint_positions(sequence_poses([(motion, 1.0)], T_US / 1e6, seed=seed, template=tpl), tpl)


@pytest.mark.parametrize("motion", sorted(MOTIONS))
def test_the_synthetic_motions_are_plausible(motion):
    # the fastest joint of these motions reaches 43% of its limit (karate_kick's foot, 12.8 m/s of 30)
    assert check_motion(T_US, truth(motion), davis240c_default()) == []


def test_a_pelvis_jumping_a_metre_is_too_fast_with_its_frames():
    J = truth().copy()
    J[400:405] += np.array([1.0, 0.0, 0.0])  # the whole body 1 m to the side for 5 ms, at 0.400-0.404 s
    [f] = check_motion(T_US, J)
    assert f.kind == "speed" and f.joints[0] in ("pelvis", "spine1", "spine2", "spine3", "neck", "head")
    # 10 ms central differences see each end of the jump from the 5 ms before it (395-399: away, 405-409: back)
    assert f.frames == ((395, 399), (405, 409)) and f.times_us == ((395_000, 399_000), (405_000, 409_000))
    assert f.peak == pytest.approx(1.0 / 0.010, rel=0.01)  # 1 m within one 10 ms window: 100 m/s
    assert "speed beyond human limits: " in f.message and "(limit 12.5)" in f.message


def test_a_body_turned_upside_down_midway_is_a_flip_and_head_below_pelvis():
    J = truth().copy()
    pelvis = J[:, :1]
    flip = np.diag([-1.0, -1.0, 1.0])  # 180 degrees about the camera's axis (z)
    J[600:] = (J[600:] - pelvis[600:]) @ flip.T + pelvis[600:]
    kinds = {f.kind: f for f in check_motion(T_US, J)}
    assert set(kinds) == {"root_flip", "head_below_pelvis", "speed"}
    assert kinds["root_flip"].frames == ((595, 604),)  # the windows that straddle the flip
    assert kinds["root_flip"].peak == pytest.approx(np.pi / 0.010, rel=0.01)
    assert kinds["head_below_pelvis"].frames == ((600, 1000),) and kinds["head_below_pelvis"].count == 401
    assert kinds["head_below_pelvis"].times_us == ((600_000, 1_000_000),)


def test_joints_behind_the_camera_are_named():
    cam = davis240c_default()  # 4 m in front of the actor, at z = 4
    J = truth().copy()
    J[:100, :, 2] += 4.2  # the first 0.1 s: the body 4.2 m nearer, past the camera
    kinds = {f.kind: f for f in check_motion(T_US, J, cam)}
    f = kinds["behind_camera"]
    assert f.frames == ((0, 99),) and "head" in f.joints and f.peak < -0.05
    assert check_motion(T_US, truth(), None) == []  # without a camera the check is left out


def test_findings_are_logged_one_line_per_kind_and_written_as_json(tmp_path, caplog):
    J = truth().copy()
    J[:, :, 1] *= -1  # upside down the whole time
    caplog.set_level(logging.INFO, logger="eventcap.analysis.plausibility")
    path = write_plausibility(tmp_path / "plausibility.json", T_US, J, davis240c_default())
    lines = [r.getMessage() for r in caplog.records if r.name == "eventcap.analysis.plausibility"]
    assert len(lines) == 1 and lines[0].startswith("plausibility: the head below the pelvis (by up to ")
    assert "in 1001 of 1001 frames (0.000-1.000 s)" in lines[0]
    doc = json.loads(path.read_text())
    assert doc["frames"] == 1001 and doc["camera_checked"] and doc["limits"]["speed_mps"]["pelvis"] == 12.5
    [f] = doc["findings"]
    assert f["kind"] == "head_below_pelvis" and f["frames"] == [[0, 1000]]
    caplog.clear()
    log_findings([])
    assert "no speed beyond human limits" in caplog.text


def test_bad_shapes_are_refused():
    with pytest.raises(ValueError, match=r"expected joints \(1001, 24, 3\)"):
        check_motion(T_US, truth()[:, :10])
