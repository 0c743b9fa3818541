"""An upright world (issue 35, item 5): y is up for every recording. A recording without extrinsics gets a camera
assumed level at the origin (or tilted as given), said in the log; the detect stage measures the person's vertical
and says how the camera would have to be tilted for the two to agree."""

from __future__ import annotations

import logging
import re

import numpy as np
import pytest

from eventcap.body.skeleton import JOINT_INDEX
from eventcap.camera import Camera, level_rotation, tilt_from_up
from eventcap.core.config import build_config
from eventcap.core.registry import load_registry
from eventcap.core.stage import StageContext

from helpers.poses import detect, posed_recording


@pytest.fixture(autouse=True)
def stages(monkeypatch):
    from eventcap.core.runner import reset_process_caches

    monkeypatch.setenv("EVENTCAP_STAGES", "eventcap_detect.spec:FILE,eventcap_recording.spec:RECORDING")
    reset_process_caches()
    yield
    reset_process_caches()


def project(R, p):
    cam = Camera(240, 180, 200.0, 200.0, 119.5, 89.5, np.zeros(5), R, np.zeros(3))
    return cam.project(np.asarray(p, float)[None])[0]


def test_level_camera_looks_along_minus_z_with_image_up_as_world_up():
    R = level_rotation()
    assert np.allclose(R, np.diag([1.0, -1.0, -1.0]))
    assert np.allclose(project(R, (0, 0, -3)), (119.5, 89.5))  # straight ahead: the image centre
    assert project(R, (0, 1, -3))[1] < 89.5 and project(R, (1, 0, -3))[0] > 119.5  # up is up, x is right
    # looking 30 degrees down: a point 30 degrees below the horizon is at the centre
    down = (0.0, -np.sin(np.radians(30)), -np.cos(np.radians(30)))
    assert np.allclose(project(level_rotation(pitch_deg=-30), down), (119.5, 89.5))
    # roll +10: the world's up appears turned clockwise (its image direction leans right)
    up = level_rotation(roll_deg=10) @ (0.0, 1.0, 0.0)
    assert np.degrees(np.arctan2(up[0], -up[1])) == pytest.approx(10.0)


@pytest.mark.parametrize("pitch,roll", [(0, 0), (-30, 0), (15, -20), (-60, 45)])
def test_tilt_from_up_inverts_level_rotation(pitch, roll):
    up = level_rotation(pitch, roll) @ (0.0, 1.0, 0.0)
    assert tilt_from_up(up) == pytest.approx((pitch, roll), abs=1e-9)


def read_npz_recording(tmp_path, **config):
    rng = np.random.default_rng(0)
    n = 500
    path = tmp_path / "ev.npz"
    np.savez(path, t=np.sort(rng.integers(0, 100_000, n)), x=rng.integers(0, 240, n), y=rng.integers(0, 180, n),
             p=rng.choice([0, 1], n))
    spec = load_registry().get("recording")
    cfg = build_config(spec, {"path": str(path), **config}, "source")
    return spec.load_run()({}, cfg, StageContext(node="source", stage="recording"))["recording"]


def test_a_recording_without_extrinsics_gets_a_level_y_up_world(tmp_path, caplog):
    caplog.set_level(logging.INFO)
    rec = read_npz_recording(tmp_path)
    assert np.allclose(rec.camera.R, level_rotation()) and not rec.camera.t.any()
    assert rec.world == "assumed_level"  # source.up=person: detect may turn it to the person's vertical
    assert "world frame: y up, the camera at the origin looking along -z, assumed level until the detect stage " \
           "measures the person's vertical" in caplog.text
    tilted = read_npz_recording(tmp_path, camera_pitch_deg=-20.0, camera_roll_deg=5.0)
    assert np.allclose(tilted.camera.R, level_rotation(-20.0, 5.0)) and tilted.world == "level"  # given: kept
    assert read_npz_recording(tmp_path, up="level").world == "level"
    caplog.clear()
    own = read_npz_recording(tmp_path, up="camera")
    assert np.allclose(own.camera.R, np.eye(3)) and own.world == "camera" and "y points DOWN" in caplog.text
    with pytest.raises(ValueError, match="source.camera_pitch_deg / camera_roll_deg: level_rotation: expected"):
        read_npz_recording(tmp_path, camera_pitch_deg=95.0)


def test_a_synthetic_capture_keeps_its_extrinsics(tmp_path, caplog):
    import zarr

    rec = posed_recording("stand", 3)
    rec.to_zarr(zarr.open_group(str(tmp_path / "rec.zarr"), mode="w"))
    spec = load_registry().get("recording")
    cfg = build_config(spec, {"path": str(tmp_path / "rec.zarr")}, "source")
    caplog.set_level(logging.INFO)
    back = spec.load_run()({}, cfg, StageContext(node="source", stage="recording"))["recording"]
    assert np.array_equal(back.camera.R, rec.camera.R) and "from the recording's camera extrinsics" in caplog.text


def test_detections_in_camera_axes_stand_upright_in_the_level_world(tmp_path, caplog):
    """A standing person seen by a level camera, 3D joints given in camera axes (y down): in the world of an
    uncalibrated recording the head is above the pelvis, and the person's vertical agrees with the world's y."""
    import dataclasses

    truth = posed_recording("stand", 5)
    level = truth.camera.with_pose(level_rotation(), np.zeros(3))
    # the same person seen by a level camera at the origin: move the world so the camera sits there
    eye = truth.camera.center
    joints_cam = (truth.ground_truth.frame_joints - eye) @ level.R.T  # what a camera-axes detector would give
    rel = joints_cam - joints_cam[:, :1]
    rec = dataclasses.replace(truth, camera=level, ground_truth=None)
    kp = level.project((truth.ground_truth.landmarks[np.searchsorted(truth.ground_truth.t_us, truth.frames.t_us)]
                        - eye))
    np.savez(tmp_path / "d.npz", t_us=rec.frames.t_us, keypoints_2d=kp, confidence_2d=np.full(kp.shape[:2], 0.9),
             joints_3d=rel, confidence_3d=np.full((5, 24), 0.9))
    caplog.set_level(logging.INFO)
    d = detect("detections_file", rec, path=str(tmp_path / "d.npz"), frame_3d="camera")
    head, pelvis = JOINT_INDEX["head"], JOINT_INDEX["pelvis"]
    assert (d.joints_3d[:, head, 1] - d.joints_3d[:, pelvis, 1] > 0.4).all()  # the head 0.4+ m above the pelvis
    pitch, roll = tilt_from_up(d.person_up)
    assert abs(pitch) < 3.0 and abs(roll) < 1.0  # the camera is level: the shoulders are 2.5 deg behind the pelvis
    assert "world up: the person's mean vertical (pelvis to shoulders, 5 images) is 3 deg from the world's y" in \
        caplog.text
    # the same detections from a camera that truly looked 35 degrees down, the recording assuming it level: the
    # log says the world's y is off and which tilt to give
    tilt = level_rotation(pitch_deg=-35.0)
    joints_tilted = (truth.ground_truth.frame_joints - eye) @ tilt.T
    np.savez(tmp_path / "t.npz", t_us=rec.frames.t_us, keypoints_2d=kp, confidence_2d=np.full(kp.shape[:2], 0.9),
             joints_3d=joints_tilted - joints_tilted[:, :1], confidence_3d=np.full((5, 24), 0.9))
    caplog.clear()
    d = detect("detections_file", rec, path=str(tmp_path / "t.npz"), frame_3d="camera", checks=[])
    assert tilt_from_up(d.person_up)[0] == pytest.approx(-35.0 + 2.5, abs=1.0)
    assert re.search(r"is 3\d deg from the world's y.*source.camera_pitch_deg=-3[23] source.camera_roll_deg=0",
                     caplog.text)


def tilted_detections(tmp_path, truth, pitch_deg: float, n: int | None = None, lie: bool = False):
    """A recording without extrinsics (world assumed level) of a person seen by a camera that truly looked
    ``pitch_deg`` down (lie: the person lying on the floor, turned 90 degrees about the camera's x axis), and a
    detections file of that camera's 3D joints in camera axes. Returns (recording, the true world->camera rotation,
    file)."""
    import dataclasses

    level = truth.camera.with_pose(level_rotation(), np.zeros(3))
    eye = truth.camera.center
    tilt = level_rotation(pitch_deg=pitch_deg)
    body = truth.ground_truth.frame_joints - eye
    if lie:
        c, s = np.cos(np.pi / 2), np.sin(np.pi / 2)
        body = body @ np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]]).T
    joints = body @ tilt.T
    k = slice(None) if n is None else slice(0, n)
    rec = dataclasses.replace(truth, camera=level, ground_truth=None, world="assumed_level")
    if n is not None:
        rec = dataclasses.replace(rec, frames=dataclasses.replace(
            rec.frames, images=rec.frames.images[k], t_us=rec.frames.t_us[k], exposure_us=rec.frames.exposure_us[k]))
    kp = level.project(truth.ground_truth.landmarks[np.searchsorted(truth.ground_truth.t_us, rec.frames.t_us)] - eye)
    m = kp.shape[0]
    np.savez(tmp_path / "d.npz", t_us=rec.frames.t_us, keypoints_2d=kp, confidence_2d=np.full(kp.shape[:2], 0.9),
             joints_3d=(joints - joints[:, :1])[k], confidence_3d=np.full((m, 24), 0.9))
    return rec, tilt, str(tmp_path / "d.npz")


def test_an_assumed_level_world_is_turned_to_the_persons_vertical(tmp_path, caplog):
    """The camera truly looked 35 degrees down; the recording has no extrinsics. The detect stage measures the
    person's vertical, turns the world to it (Detections.world_R), gives the 3D joints in that world, and every stage
    reading the recording through eventcap.worldframe.upright sees the turned camera."""
    from eventcap.worldframe import upright

    truth = posed_recording("stand", 8)
    rec, tilt, path = tilted_detections(tmp_path, truth, -35.0)
    caplog.set_level(logging.INFO)
    d = detect("detections_file", rec, path=path, frame_3d="camera", checks=[])
    assert d.world_R is not None
    assert "world frame: y up along the person's vertical (pelvis to shoulders, mean over 8 images" in caplog.text
    true_up, new_up = tilt @ (0.0, 1.0, 0.0), d.world_R @ (0.0, 1.0, 0.0)  # both in camera axes
    assert np.degrees(np.arccos(true_up @ new_up)) < 3.5  # the standing person leans 2.5 degrees
    assert tilt_from_up(new_up)[0] == pytest.approx(-32.5, abs=1.0)
    head, pelvis = JOINT_INDEX["head"], JOINT_INDEX["pelvis"]
    rise = d.joints_3d[:, head] - d.joints_3d[:, pelvis]
    assert (rise[:, 1] > 0.5).all() and (np.abs(rise[:, [0, 2]]) < 0.12).all()  # upright in the turned world
    up_rec = upright(rec, d)
    assert np.allclose(up_rec.camera.R, d.world_R) and np.array_equal(up_rec.camera.t, rec.camera.t)
    assert up_rec.events is rec.events and upright(rec, None) is rec
    # the 3D joints stay the same points in front of the camera: their camera-axes directions are unchanged
    same = d.joints_3d @ d.world_R.T
    back = np.load(path)["joints_3d"]
    assert np.allclose(same, back - back[:, :1], atol=1e-9)


def test_too_few_images_or_a_person_not_upright_keep_the_assumed_level_world(tmp_path, caplog):
    truth = posed_recording("stand", 8)
    caplog.set_level(logging.INFO)
    rec, _, path = tilted_detections(tmp_path, truth, -20.0, n=3)
    d = detect("detections_file", rec, path=path, frame_3d="camera", checks=[], min_found=0.1)
    assert d.world_R is None
    assert "kept the camera assumed level (pitch 0, roll 0): the person's vertical was measured in 3 accepted " \
           "images, fewer than 5" in caplog.text
    caplog.clear()
    rec, _, path = tilted_detections(tmp_path, truth, -20.0, lie=True)
    d = detect("detections_file", rec, path=path, frame_3d="camera", checks=[])
    assert d.world_R is None and re.search(r"did not stay upright enough .* it would tilt the camera pitch -?\d+ "
                                           r"deg", caplog.text)
    assert np.allclose(d.joints_3d, np.load(path)["joints_3d"] @ rec.camera.R)  # the assumed level world's axes
    caplog.clear()
    rec, _, path = tilted_detections(tmp_path, truth, 0.0)  # truly level: the standing person leans 2.5 degrees
    d = detect("detections_file", rec, path=path, frame_3d="camera", checks=[])
    assert d.world_R is None and re.search(r"the person's vertical \(mean over 8 images\) is 2\.\d deg from it, "
                                           r"within the measurement's own error \(5 deg\)", caplog.text)
