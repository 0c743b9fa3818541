"""C3D export (eventcap/export/c3d.py, outputs.c3d=true), written with the `c3d` package and read back by it and by the
independent C++ library ezc3d: labels, rate, units, up axis, time origin, values equal to motion.npz within
0.01 mm, gaps marked invalid, files of any length read whole by both."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

from eventcap.body.markers import MARKER_NAMES
from eventcap.body.skeleton import JOINT_INDEX, JOINT_NAMES
from eventcap.export.bvh import read_motion_npz
from eventcap.export.c3d import c3d_labels, point_residuals, write_c3d

ezc3d = pytest.importorskip("ezc3d")
c3d = pytest.importorskip("c3d")

TOL_MM = 0.01


def read_with_ezc3d(path) -> dict:
    f = ezc3d.c3d(str(path))
    point = f["parameters"]["POINT"]
    return {"labels": list(point["LABELS"]["value"]), "rate": float(point["RATE"]["value"][0]),
            "units": point["UNITS"]["value"][0], "points": f["data"]["points"][:3],  # (3, n, frames), NaN = invalid
            "t0_us": int(f["parameters"]["EVENTCAP"]["T0_US"]["value"][0]),
            "first": int(f["header"]["points"]["first_frame"]) + 1,  # ezc3d counts from 0
            "screen": (point["X_SCREEN"]["value"][0], point["Y_SCREEN"]["value"][0]),
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
            "first": frames[0][0], "last": frames[-1][0]}


def test_joints_and_markers_read_back_by_two_readers(tmp_path):
    rng = np.random.default_rng(0)
    t = np.r_[np.arange(0, 20_000, 1000), np.arange(25_000, 40_000, 1000)].astype(np.int64) + 12_000  # a 4-frame gap
    J = rng.normal(0.0, 1.5, (t.size, 24, 3))
    M = rng.normal(0.0, 1.5, (t.size, 3, 3))
    path = write_c3d(tmp_path / "m.c3d", t, J, M, marker_names=["LKNE", "RKNE", "C7"],
                     marker_descriptions=["left knee", "right knee", "7th cervical vertebra"])
    assert path == tmp_path / "m.c3d" and not list(tmp_path.glob("*.partial*"))
    want = np.concatenate([J, M], axis=1) * 1000.0  # mm, y up as inside
    k = (t - t[0]) // 1000  # grid frame of each estimated frame
    n_frames = int(k[-1]) + 1  # 12 ms .. 51 ms
    assert n_frames == t.size + 5

    e = read_with_ezc3d(path)
    assert e["labels"] == list(JOINT_NAMES) + ["LKNE", "RKNE", "C7"] == c3d_labels(["LKNE", "RKNE", "C7"])
    assert (e["rate"], e["units"], e["t0_us"], e["screen"]) == (1000.0, "mm", 12_000, ("+X", "+Y"))
    assert e["first"] == 13  # frame n lies at (n - 1) ms: the first frame is at 12 ms on the run's time axis
    assert e["descriptions"][0] == "SMPL joint centre pelvis" and e["descriptions"][24] == "left knee"
    P = np.transpose(e["points"], (2, 1, 0))  # (frames, n, 3)
    assert P.shape == (n_frames, 27, 3)
    assert np.abs(P[k] - want).max() < TOL_MM
    gap = np.setdiff1d(np.arange(n_frames), k)
    assert gap.size == 5 and np.all(np.isnan(P[gap]))  # not estimated: invalid, not made up

    r = read_with_c3d(path)
    assert r["labels"] == e["labels"] and r["units"] == "mm" and r["rate"] == 1000.0 and r["first"] == 13
    assert r["xyz"].shape == (n_frames, 27, 3)
    assert np.abs(r["xyz"][k] - want).max() < TOL_MM
    assert np.all(r["residual"][gap] == -1) and np.all(r["residual"][k] == 0)


@pytest.mark.parametrize("n_frames, n_markers", [pytest.param(70_000, 39, marks=pytest.mark.slow), (70_003, 0)])
def test_files_past_65535_frames_are_read_whole_by_both_readers(tmp_path, n_frames, n_markers):
    """70 s at 1 kHz. With 24 points a frame is 384 bytes and 70,003 frames leave 384 bytes of block padding: a whole
    frame that ezc3d (which reads long files to their end) would take for a 70,004th frame."""
    t = (5000 + 1000 * np.arange(n_frames)).astype(np.int64)
    J = np.zeros((n_frames, 24, 3))
    J[:, :, 0] = np.arange(n_frames)[:, None] * 1e-4  # a ramp: each frame its own x
    M = np.ones((n_frames, n_markers, 3)) if n_markers else None
    path = write_c3d(tmp_path / "long.c3d", t, J, M, marker_names=list(MARKER_NAMES[:n_markers]))
    e = read_with_ezc3d(path)
    assert e["points"].shape == (3, 24 + n_markers, n_frames)
    assert np.allclose(e["points"][0, 0, [0, 65_535, -1]], [0.0, 6553.5, (n_frames - 1) * 0.1], atol=1e-3)
    r = read_with_c3d(path)
    assert r["xyz"].shape == (n_frames, 24 + n_markers, 3) and (r["first"], r["last"]) == (6, n_frames + 5)
    assert np.allclose(r["xyz"][-1, 0, 0], (n_frames - 1) * 0.1, atol=1e-3)
    with open(path, "rb") as fh, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        reader = c3d.Reader(fh)
        assert reader.header.last_frame == 65535 and reader.get("POINT:FRAMES").uint16_value == 65535
        assert int(reader.get("POINT:LONG_FRAMES").float_value) == n_frames
        words = reader.get("TRIAL:ACTUAL_END_FIELD").uint16_array
        assert int(words[0]) + 65536 * int(words[1]) == n_frames + 5


@pytest.mark.parametrize("up_axis, units, scale", [("y", "m", 1.0), ("z", "mm", 1000.0), ("z", "cm", 100.0)])
def test_up_axis_and_units(tmp_path, up_axis, units, scale):
    """The head above the pelvis along the file's up axis, lengths in its unit, as both readers see it."""
    from eventcap.body.kinematics import joint_positions
    from eventcap.body.skeleton import DEFAULT_REST_JOINTS

    S = np.zeros((3, 33))
    S[:, 27] = [0.0, 0.5, 1.0]  # the actor turns about the vertical
    S[:, 30:33] = [1.0, 0.2, -2.0]
    J = joint_positions(S, DEFAULT_REST_JOINTS)
    path = write_c3d(tmp_path / "f.c3d", np.arange(3, dtype=np.int64) * 1000, J, up_axis=up_axis, units=units)
    up = "xyz".index(up_axis)
    head, pelvis = JOINT_INDEX["head"], JOINT_INDEX["pelvis"]
    e, r = read_with_ezc3d(path), read_with_c3d(path)
    assert e["units"] == r["units"] == units and e["screen"] == ("+X", "+Z" if up_axis == "z" else "+Y")
    for P in (np.transpose(e["points"], (2, 1, 0)), r["xyz"]):
        rise = P[:, head, up] - P[:, pelvis, up]
        assert np.all(rise > 0.5 * scale)  # ~0.6 m of the 1.75 m default skeleton
        side = [i for i in range(3) if i != up]
        assert np.all(np.abs(P[:, head, side] - P[:, pelvis, side]) < 0.05 * scale)
        want = J * scale if up_axis == "y" else np.stack([J[..., 0], -J[..., 2], J[..., 1]], -1) * scale
        assert np.abs(P - want).max() < 1e-4 * scale


def test_point_residuals_take_a_confidence():
    valid = np.array([[True, True, False], [True, True, True]])
    assert point_residuals(valid).tolist() == [[0, 0, -1], [0, 0, 0]]
    conf = np.array([[0.9, np.nan, 1.0], [0.0, 0.4, 1.0]])
    assert point_residuals(valid, conf).tolist() == [[0, -1, -1], [-1, 0, 0]]  # unobserved: -1, as gaps
    with pytest.raises(ValueError, match=r"confidence: expected shape \(2, 3\) \(frames, points\), got \(3,\)"):
        point_residuals(valid, np.ones(3))
    with pytest.raises(ValueError, match=r"confidence: expected values in \[0, 1\] \(NaN: not observed\), got "
                                         r"\[0, 2\]"):
        point_residuals(valid, np.array([[0, 1, 2], [1, 1, 1.0]]))


def test_a_confidence_marks_unobserved_points_invalid_in_the_file(tmp_path):
    t = np.arange(4, dtype=np.int64) * 1000
    conf = np.ones((4, 24))
    conf[2, JOINT_INDEX["l_wrist"]] = np.nan
    path = write_c3d(tmp_path / "c.c3d", t, np.zeros((4, 24, 3)), confidence=conf)
    r = read_with_c3d(path)
    assert r["residual"][2, JOINT_INDEX["l_wrist"]] == -1 and (r["residual"] == -1).sum() == 1


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
    with pytest.raises(ValueError, match=r"up_axis: expected one of y \| z, got 'x'"):
        write_c3d(tmp_path / "a.c3d", t, J, up_axis="x")
    with pytest.raises(ValueError, match=r"units: expected one of m \| cm \| mm, got 'in'"):
        write_c3d(tmp_path / "a.c3d", t, J, units="in")
    J[3, 4, 1] = np.nan
    with pytest.raises(ValueError, match="expected finite values"):
        write_c3d(tmp_path / "a.c3d", t, J)
    with pytest.raises(ValueError, match=r"markers: expected shape \(5, 2, 3\)"):
        write_c3d(tmp_path / "a.c3d", t, np.zeros((5, 24, 3)), np.zeros((5, 3, 3)), marker_names=["A", "B"])
    assert list(tmp_path.iterdir()) == []


@pytest.mark.usefixtures("known_poses")
def test_a_run_writes_motion_c3d_equal_to_motion_npz(tmp_path):
    """outputs.c3d=true on a tiny run (tests/test_outputs.py's known-poses capture): the file's joints are motion.npz's
    joints in mm, its markers the template's Plug-in Gait markers skinned with the same poses, at the tracking rate;
    none of the markers is a joint centre."""
    from helpers.runs import known_poses_config, run_with_outputs

    from eventcap.body.markers import plug_in_gait_markers

    runner, result, summary = run_with_outputs(known_poses_config(tmp_path / "cache", c3d=True, bvh=False, video=False), tmp_path / "run")
    assert summary["problems"] == [] and set(summary["written"]) == {"npz", "c3d", "plausibility"}
    assert json.loads((tmp_path / "run" / "run.json").read_text())["outputs"]["written"]["c3d"].endswith("motion.c3d")
    m = read_motion_npz(tmp_path / "run" / "motion.npz")
    tpl = runner.load_output(result, "template.template")[None]
    markers = plug_in_gait_markers(tpl).positions(m["poses"], tpl)
    want = np.concatenate([m["joints"], markers], axis=1) * 1000.0
    assert m["t_us"].size == 81 and np.all(np.diff(m["t_us"]) == 1000) and int(m["t0_us"]) == m["t_us"][0]
    e = read_with_ezc3d(tmp_path / "run" / "motion.c3d")
    r = read_with_c3d(tmp_path / "run" / "motion.c3d")
    for got in (np.transpose(e["points"], (2, 1, 0)), r["xyz"]):
        assert got.shape == (81, 24 + 39, 3)
        assert np.abs(got - want).max() < TOL_MM
    assert e["labels"] == r["labels"] == c3d_labels(MARKER_NAMES)
    assert e["rate"] == r["rate"] == 1000.0 and e["units"] == r["units"] == "mm" and e["t0_us"] == m["t_us"][0]
    assert e["first"] == r["first"] == m["t_us"][0] // 1000 + 1
    gap = np.linalg.norm(want[:, 24:, None] - want[:, None, :24], axis=-1).min()
    assert gap > 10.0  # mm: every marker lies on the skin, at least a centimetre from any joint centre


@pytest.mark.usefixtures("known_poses")
def test_outputs_c3d_needs_the_c3d_package(tmp_path, monkeypatch):
    import importlib.util

    from helpers.runs import known_poses_config

    from eventcap.apps.outputs import OutputsConfig, check_outputs_config
    from eventcap.core.runner import Runner

    with pytest.raises(ValueError, match=r"outputs\.c3d: expected true or false, got 'maybe'"):
        OutputsConfig.from_mapping({"c3d": "maybe"})
    with pytest.raises(ValueError, match=r"outputs\.up_axis: expected one of y \| z, got 'x'"):
        OutputsConfig.from_mapping({"up_axis": "x"})
    with pytest.raises(ValueError, match=r"outputs\.units: expected one of m \| cm \| mm \| None, got 'ft'"):
        OutputsConfig.from_mapping({"units": "ft"})
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "c3d" else real(name, *a))
    with pytest.raises(ValueError, match=r"outputs\.c3d=true needs the c3d package: pip install c3d"):
        check_outputs_config(Runner(known_poses_config(tmp_path, c3d=True)))
