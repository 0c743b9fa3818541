"""C3D export (eventcap/c3d.py, outputs.c3d=true): read back with ezc3d and with the independent pure-Python `c3d`
package: labels, rate, units, values equal to motion.npz within 0.01 mm, gaps marked invalid."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

from eventcap.body.skeleton import JOINT_NAMES, LANDMARK_NAMES
from eventcap.bvh import read_motion_npz
from eventcap.c3d import c3d_labels, write_c3d

ezc3d = pytest.importorskip("ezc3d")
c3d = pytest.importorskip("c3d")

TOL_MM = 0.01


def read_with_ezc3d(path) -> dict:
    f = ezc3d.c3d(str(path))
    point = f["parameters"]["POINT"]
    return {"labels": list(point["LABELS"]["value"]), "rate": float(point["RATE"]["value"][0]),
            "units": point["UNITS"]["value"][0], "points": f["data"]["points"][:3],  # (3, n, frames), NaN = invalid
            "t0_us": int(f["parameters"]["EVENTCAP"]["T0_US"]["value"][0]),
            "descriptions": list(point["DESCRIPTIONS"]["value"])}


def read_with_c3d(path) -> dict:
    with open(path, "rb") as fh, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "No analog data found in file."
        r = c3d.Reader(fh)
        labels = [s.strip() for s in r.point_labels]
        units = r.get("POINT:UNITS").string_value.strip()
        frames = [(i, p.copy()) for i, p, _ in r.read_frames()]
        rate = float(r.point_rate)
    xyz = np.stack([p[:, :3] for _, p in frames])  # (frames, n, 3)
    residual = np.stack([p[:, 3] for _, p in frames])  # -1: invalid
    return {"labels": labels, "units": units, "rate": rate, "xyz": xyz, "residual": residual,
            "first": frames[0][0]}


def test_joints_and_landmarks_read_back_by_two_readers(tmp_path):
    rng = np.random.default_rng(0)
    t = np.r_[np.arange(0, 20_000, 1000), np.arange(25_000, 40_000, 1000)].astype(np.int64) + 12_000  # a 4-frame gap
    J = rng.normal(0.0, 1.5, (t.size, 24, 3))
    L = rng.normal(0.0, 1.5, (t.size, 25, 3))
    path = write_c3d(tmp_path / "m.c3d", t, J, L)
    assert path == tmp_path / "m.c3d" and not list(tmp_path.glob("*.partial*"))
    want = np.concatenate([J, L], axis=1) * 1000.0  # mm
    k = (t - t[0]) // 1000  # grid frame of each estimated frame
    n_frames = int(k[-1]) + 1  # 12 ms .. 51 ms
    assert n_frames == t.size + 5

    e = read_with_ezc3d(path)
    assert e["labels"] == list(JOINT_NAMES) + [f"lm_{n}" for n in LANDMARK_NAMES] == c3d_labels(True)
    assert e["labels"][20] == "l_wrist" and e["labels"][24] == "lm_nose"
    assert (e["rate"], e["units"], e["t0_us"]) == (1000.0, "mm", 12_000)
    assert e["descriptions"][0] == "SMPL joint pelvis" and "BODY_25" in e["descriptions"][24]
    P = np.transpose(e["points"], (2, 1, 0))  # (frames, n, 3)
    assert P.shape == (n_frames, 49, 3)
    assert np.abs(P[k] - want).max() < TOL_MM
    gap = np.setdiff1d(np.arange(n_frames), k)
    assert gap.size == 5 and np.all(np.isnan(P[gap]))  # not estimated: invalid, not made up

    r = read_with_c3d(path)
    assert r["labels"] == e["labels"] and r["units"] == "mm" and r["rate"] == 1000.0 and r["first"] == 1
    assert r["xyz"].shape == (n_frames, 49, 3)
    assert np.abs(r["xyz"][k] - want).max() < TOL_MM
    assert np.all(r["residual"][gap] == -1) and np.all(r["residual"][k] >= 0)


def test_bad_input_is_refused_with_a_message_and_leaves_nothing(tmp_path):
    t = np.arange(0, 5000, 1000, dtype=np.int64)
    J = np.zeros((5, 24, 3))
    with pytest.raises(ValueError, match=r"joints: expected shape \(5, 24, 3\) \(T, joints, xyz metres\), got "
                                         r"\(5, 23, 3\)"):
        write_c3d(tmp_path / "a.c3d", t, J[:, :23])
    with pytest.raises(ValueError, match=r"frame 2 \(2500 us\) is not on the 1000 us grid starting at 0 us"):
        write_c3d(tmp_path / "a.c3d", np.array([0, 1000, 2500, 3000, 4000]), J, step_us=1000)
    with pytest.raises(ValueError, match=r"strictly increasing times, frame 1 is at 0 us after 0 us"):
        write_c3d(tmp_path / "a.c3d", np.zeros(5, np.int64), J)
    J[3, 4, 1] = np.nan
    with pytest.raises(ValueError, match="expected finite values"):
        write_c3d(tmp_path / "a.c3d", t, J)
    with pytest.raises(ValueError, match=r"landmarks: expected shape \(5, 25, 3\)"):
        write_c3d(tmp_path / "a.c3d", t, np.zeros((5, 24, 3)), np.zeros((5, 24, 3)))
    assert list(tmp_path.iterdir()) == []


@pytest.mark.usefixtures("known_poses")
def test_a_run_writes_motion_c3d_equal_to_motion_npz(tmp_path):
    """outputs.c3d=true on a tiny run (tests/test_outputs.py's known-poses capture): the file's joints are motion.npz's
    joints in mm, its landmarks the template's landmarks of the same poses, at the tracking rate."""
    from test_outputs import config, run

    from eventcap.body.kinematics import landmark_positions

    runner, result, summary = run(config(tmp_path / "cache", c3d=True, bvh=False, video=False), tmp_path / "run")
    assert summary["problems"] == [] and set(summary["written"]) == {"npz", "c3d", "plausibility"}
    assert json.loads((tmp_path / "run" / "run.json").read_text())["outputs"]["written"]["c3d"].endswith("motion.c3d")
    m = read_motion_npz(tmp_path / "run" / "motion.npz")
    tpl = runner.load_output(result, "template.template")[None]
    want = np.concatenate([m["joints"], landmark_positions(m["poses"], tpl)], axis=1) * 1000.0
    assert m["t_us"].size == 81 and np.all(np.diff(m["t_us"]) == 1000)
    e = read_with_ezc3d(tmp_path / "run" / "motion.c3d")
    r = read_with_c3d(tmp_path / "run" / "motion.c3d")
    for got in (np.transpose(e["points"], (2, 1, 0)), r["xyz"]):
        assert got.shape == (81, 49, 3)
        assert np.abs(got - want).max() < TOL_MM
    assert e["labels"] == r["labels"] == c3d_labels(True)
    assert e["rate"] == r["rate"] == 1000.0 and e["units"] == r["units"] == "mm" and e["t0_us"] == m["t_us"][0]


@pytest.mark.usefixtures("known_poses")
def test_outputs_c3d_needs_ezc3d(tmp_path, monkeypatch):
    import importlib.util

    from test_outputs import config

    from eventcap.outputs import OutputsConfig, check_outputs_config
    from eventcap.runner import Runner

    with pytest.raises(ValueError, match=r"outputs\.c3d: expected true or false, got 'yes'"):
        OutputsConfig.from_mapping({"c3d": "yes"})
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "ezc3d" else real(name, *a))
    with pytest.raises(ValueError, match=r"outputs\.c3d=true needs the ezc3d package: pip install ezc3d"):
        check_outputs_config(Runner(config(tmp_path, c3d=True)))
