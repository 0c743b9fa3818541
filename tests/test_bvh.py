"""BVH export: files written by eventcap.export.bvh, read back by independent parsers from PyPI (``bvh``: a plain
tokenizer, positions by a small float64 forward kinematics here; ``bvhio``: its own hierarchy and forward
kinematics, in float32), give the joint positions of eventcap's forward kinematics."""

from __future__ import annotations

import warnings

import bvh
import numpy as np
import pytest

with warnings.catch_warnings():  # bvhio imports PyGLM the way PyGLM now deprecates; not ours to fix
    warnings.simplefilter("ignore", PendingDeprecationWarning)
    import bvhio

from eventcap.body.kinematics import joint_positions
from eventcap.body.motions import motion_poses
from eventcap.body.skeleton import (
    DEFAULT_REST_JOINTS,
    DOF_AXIS,
    DOF_JOINT,
    DOF_NAMES,
    JOINT_NAMES,
    PARENTS,
    pose_bounds,
)
from eventcap.export.bvh import (
    bvh_channels,
    bvh_layout,
    euler_from_matrix,
    matrix_from_euler,
    read_motion_npz,
    write_bvh,
    write_motion_npz,
)
from helpers.bvh_reference import axis_rotation, positions_via_bvh_package, stacked

TOL_M = 1e-6


def random_poses(n: int, seed: int = 0) -> np.ndarray:
    """Poses within the joint-angle bounds, any root rotation, root within a few metres (seeded)."""
    rng = np.random.default_rng(seed)
    lo, hi = pose_bounds()
    S = np.empty((n, 33))
    S[:, :27] = rng.uniform(lo[:27], hi[:27], (n, 27))
    S[:, 27:30] = rng.uniform(-np.pi, np.pi, (n, 3))
    S[:, 30:33] = rng.uniform(-3.0, 3.0, (n, 3))
    return S


def odd_skeleton() -> np.ndarray:
    """A rest skeleton unlike the default one (scaled, bones not axis-aligned), seeded."""
    rng = np.random.default_rng(7)
    return DEFAULT_REST_JOINTS * 1.08 + rng.normal(0.0, 0.01, DEFAULT_REST_JOINTS.shape)


def test_random_poses_round_trip_through_an_independent_parser(tmp_path):
    S = random_poses(200)
    for rest in (DEFAULT_REST_JOINTS, odd_skeleton()):
        path = write_bvh(tmp_path / "random.bvh", S, rest)
        got = stacked(positions_via_bvh_package(path))
        assert np.abs(got - joint_positions(S, rest)).max() < TOL_M


def test_centimetres_and_frame_time(tmp_path):
    S = random_poses(20, seed=1)
    path = write_bvh(tmp_path / "cm.bvh", S, DEFAULT_REST_JOINTS, frame_time_s=1 / 240, scale=100.0)
    mocap = bvh.Bvh(open(path).read())
    assert mocap.frame_time == pytest.approx(1 / 240, rel=1e-12) and mocap.nframes == 20
    assert np.allclose(mocap.joint_offset("l_knee"), 100 * (DEFAULT_REST_JOINTS[4] - DEFAULT_REST_JOINTS[1]))
    got = stacked(positions_via_bvh_package(path)) / 100.0
    assert np.abs(got - joint_positions(S, DEFAULT_REST_JOINTS)).max() < TOL_M


def test_simulated_motion_round_trip(tmp_path):
    """Half a second of a fast, spinning motion at 1000 fps; channels stay continuous (no 360° jumps)."""
    t = np.arange(500) * 1e-3
    S = motion_poses("dance_spin", t, seed=1, speed=2.0)
    path = write_bvh(tmp_path / "spin.bvh", S, DEFAULT_REST_JOINTS)
    got = stacked(positions_via_bvh_package(path))
    assert np.abs(got - joint_positions(S, DEFAULT_REST_JOINTS)).max() < TOL_M
    rows = np.array(bvh.Bvh(open(path).read()).frames, dtype=np.float64)
    assert np.abs(np.diff(rows[:, 3:], axis=0)).max() < 30.0  # degrees per millisecond: no wrap-around jumps


def test_bvhio_forward_kinematics_agrees(tmp_path):
    """bvhio builds its own transform hierarchy (float32: PyGLM), so agreement is to float32 rounding."""
    S = random_poses(30, seed=2)
    S[:, 30:33] *= 0.3  # float32 positions: keep the actor near the origin
    rest = odd_skeleton()
    path = write_bvh(tmp_path / "bvhio.bvh", S, rest, scale=100.0)
    root = bvhio.readAsHierarchy(str(path))
    joints = {j.Name: j for j, _, _ in root.layout()}
    assert set(joints) == set(JOINT_NAMES)
    want = joint_positions(S, rest)
    for f in range(S.shape[0]):
        root.loadPose(f)
        got = np.array([list(joints[n].PositionWorld) for n in JOINT_NAMES]) / 100.0
        assert np.abs(got - want[f]).max() < 5e-6


def test_hierarchy_layout(tmp_path):
    path = write_bvh(tmp_path / "h.bvh", random_poses(3), DEFAULT_REST_JOINTS)
    mocap = bvh.Bvh(open(path).read())
    names = mocap.get_joints_names()
    assert sorted(names) == sorted(JOINT_NAMES) and names[0] == "pelvis"
    for j, name in enumerate(JOINT_NAMES[1:], start=1):
        assert mocap.joint_parent(name).name == JOINT_NAMES[PARENTS[j]]
        want = DEFAULT_REST_JOINTS[j] - DEFAULT_REST_JOINTS[PARENTS[j]]
        assert np.allclose(mocap.joint_offset(name), want, atol=1e-12)
        assert len(mocap.joint_channels(name)) == 3
    assert mocap.joint_channels("pelvis")[:3] == ["Xposition", "Yposition", "Zposition"]
    assert mocap.joint_offset("pelvis") == (0.0, 0.0, 0.0)
    leaves = {JOINT_NAMES[j] for j in range(24) if j not in PARENTS}
    assert leaves == {"l_foot", "r_foot", "head", "l_hand", "r_hand"}
    ends = mocap.search("End", "Site")
    assert len(ends) == 5 and {e.parent.name for e in ends} == leaves


def test_channels_are_the_joint_angles():
    """With the per-joint orders chosen from the DOF table, each rotation channel is a joint angle in degrees
    (signed by its axis' direction) and the root's are yaw, pitch, roll."""
    S = random_poses(50, seed=3)
    S[:, 28] = np.clip(S[:, 28], -1.5, 1.5)  # root pitch within ±90°: the principal Euler branch
    rows = bvh_channels(S, DEFAULT_REST_JOINTS, unwrap=False)
    layout = bvh_layout()
    column = {c: i for i, c in enumerate(layout.channels)}
    for i, name in enumerate(DOF_NAMES):
        k = int(np.flatnonzero(DOF_AXIS[i])[0])
        joint = JOINT_NAMES[DOF_JOINT[i]]
        got = rows[:, column[(joint, f"{'XYZ'[k]}rotation")]]
        assert np.allclose(got, np.degrees(S[:, i]) * DOF_AXIS[i, k], atol=1e-9), name
    for i, axis in ((27, "Y"), (28, "X"), (29, "Z")):
        got = rows[:, column[("pelvis", f"{axis}rotation")]]
        assert np.allclose(got, np.degrees(S[:, i]), atol=1e-9)
    assert np.allclose(rows[:, :3], DEFAULT_REST_JOINTS[0] + S[:, 30:33])


def test_unwrapped_spin():
    S = np.zeros((400, 33))
    S[:, 27] = np.linspace(0, 4 * np.pi, 400)  # two full turns about the vertical
    rows = bvh_channels(S, DEFAULT_REST_JOINTS)
    yaw = rows[:, bvh_layout().channels.index(("pelvis", "Yrotation"))]
    assert np.allclose(yaw, np.degrees(S[:, 27]), atol=1e-9)
    # chunked conversion continues the unwrapping from the previous chunk's last row
    tail = bvh_channels(S[200:], DEFAULT_REST_JOINTS, previous=rows[199])
    assert np.allclose(tail, rows[200:], atol=1e-9)


@pytest.mark.parametrize("order", ["XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX"])
def test_euler_round_trip_and_gimbal_lock(order):
    rng = np.random.default_rng(4)
    a = rng.uniform(-np.pi, np.pi, (400, 3))
    a[:, 1] /= 2
    a[:50, 1] = np.pi / 2
    a[50:100, 1] = -np.pi / 2
    a[100:150, 1] = np.pi / 2 - 1e-9  # nearly locked
    R = matrix_from_euler(a, order)
    b = euler_from_matrix(R, order)
    assert np.abs(matrix_from_euler(b, order) - R).max() < 1e-12
    assert np.allclose(b[150:], a[150:], atol=1e-12)  # away from the lock: the angles themselves
    assert np.all(b[:100, 2] == 0.0) and np.allclose(np.abs(b[:100, 1]), np.pi / 2)  # locked: third angle 0
    # the intrinsic convention: R_a(a0) @ R_b(a1) @ R_c(a2)
    x = np.array([0.3, -0.2, 0.5])
    want = axis_rotation(order[0], np.degrees(x[0])) @ axis_rotation(order[1], np.degrees(x[1])) @ axis_rotation(order[2], np.degrees(x[2]))
    assert np.allclose(matrix_from_euler(x, order), want, atol=1e-15)


def test_gimbal_locked_root_still_exact(tmp_path):
    S = random_poses(10, seed=5)
    S[:, 28] = np.pi / 2  # root pitched to the horizontal: lying on the back, yaw and roll share an axis
    path = write_bvh(tmp_path / "lock.bvh", S, DEFAULT_REST_JOINTS)
    got = stacked(positions_via_bvh_package(path))
    assert np.abs(got - joint_positions(S, DEFAULT_REST_JOINTS)).max() < TOL_M


def test_bad_input_raises_and_leaves_nothing(tmp_path, monkeypatch):
    S = random_poses(4)
    with pytest.raises(ValueError, match=r"poses S: expected shape \(T, 33\).*got \(4, 32\)"):
        write_bvh(tmp_path / "x.bvh", S[:, :32], DEFAULT_REST_JOINTS)
    with pytest.raises(ValueError, match=r"poses S: expected shape \(T, 33\).*got \(0, 33\)"):
        write_bvh(tmp_path / "x.bvh", S[:0], DEFAULT_REST_JOINTS)
    bad = S.copy()
    bad[2, 4] = np.nan
    with pytest.raises(ValueError, match=r"poses S: expected finite values, got nan at frame 2, parameter 4 "
                                         r"\(r_hip_abd\)"):
        write_bvh(tmp_path / "x.bvh", bad, DEFAULT_REST_JOINTS)
    with pytest.raises(ValueError, match=r"rest joints: expected shape \(24, 3\)"):
        write_bvh(tmp_path / "x.bvh", S, DEFAULT_REST_JOINTS[:23])
    with pytest.raises(ValueError, match=r"frame_time_s: expected a positive finite number, got 0"):
        write_bvh(tmp_path / "x.bvh", S, DEFAULT_REST_JOINTS, frame_time_s=0)
    with pytest.raises(ValueError, match=r"scale: expected a positive finite number"):
        write_bvh(tmp_path / "x.bvh", S, DEFAULT_REST_JOINTS, scale=float("inf"))
    assert list(tmp_path.iterdir()) == []
    # a write that fails half-way leaves the previous file as it was and no partial file
    path = write_bvh(tmp_path / "keep.bvh", S, DEFAULT_REST_JOINTS)
    before = path.read_bytes()

    def boom(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(np, "savetxt", boom)
    with pytest.raises(OSError, match="disk full"):
        write_bvh(path, random_poses(4, seed=9), DEFAULT_REST_JOINTS)
    assert path.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["keep.bvh"]


def test_motion_npz(tmp_path):
    t = 1000 * np.arange(30, dtype=np.int64)
    S = random_poses(30)
    J = joint_positions(S, DEFAULT_REST_JOINTS)
    path = write_motion_npz(tmp_path / "motion.npz", t, S, J, extra={"fps": 1000.0})
    back = read_motion_npz(path)
    assert np.array_equal(back["t_us"], t) and back["t_us"].dtype == np.int64
    assert np.array_equal(back["poses"], S) and np.array_equal(back["joints"], J)
    assert tuple(back["joint_names"]) == JOINT_NAMES and back["param_names"][27] == "root_yaw"
    assert float(back["fps"]) == 1000.0
    with pytest.raises(ValueError, match=r"joints: expected shape \(30, 24, 3\)"):
        write_motion_npz(tmp_path / "bad.npz", t, S, J[:, :23])
    with pytest.raises(ValueError, match=r"poses: expected one row per time \(30\), got shape \(29, 33\)"):
        write_motion_npz(tmp_path / "bad.npz", t, S[:29], J)
    with pytest.raises(ValueError, match=r"t_us: expected strictly increasing times, frame 3"):
        write_motion_npz(tmp_path / "bad.npz", np.r_[t[:3], t[2:29]], S, J)
    bad = J.copy()
    bad[0, 0, 0] = np.inf
    with pytest.raises(ValueError, match=r"joints: expected finite values"):
        write_motion_npz(tmp_path / "bad.npz", t, S, bad)
    with pytest.raises(ValueError, match=r"extra: array name 'poses' is taken"):
        write_motion_npz(tmp_path / "bad.npz", t, S, J, extra={"poses": S})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["motion.npz"]


@pytest.mark.parametrize("up_axis, scale", [("y", 100.0), ("z", 1000.0)])
def test_up_axis_units_and_time_origin_read_by_both_parsers(tmp_path, up_axis, scale):
    """z up: every position rotated (x, y, z) -> (x, -z, y); the head above the pelvis along the file's up axis; the
    first line states the frame and the time of the first frame, and both parsers still read the file."""
    S = random_poses(12, seed=4)
    S[:, 30:33] *= 0.3
    rest = odd_skeleton()
    path = write_bvh(tmp_path / "f.bvh", S, rest, scale=scale, up_axis=up_axis, t0_us=5000)
    first = open(path).readline()
    assert first.startswith("HIERARCHY  # eventcap: right-handed, " + up_axis + " up, lengths in "
                            + {100.0: "cm", 1000.0: "mm"}[scale])
    assert "first frame at t = 5000 us on the run's time axis, then every 1000 us" in first
    want = joint_positions(S, rest)
    if up_axis == "z":
        want = np.stack([want[..., 0], -want[..., 2], want[..., 1]], axis=-1)
    got = stacked(positions_via_bvh_package(path)) / scale
    assert np.abs(got - want).max() < TOL_M
    root = bvhio.readAsHierarchy(str(path))
    joints = {j.Name: j for j, _, _ in root.layout()}
    root.loadPose(0)
    head = np.array(list(joints["head"].PositionWorld)) / scale
    assert np.abs(head - want[0, JOINT_NAMES.index("head")]).max() < 5e-5
    rest_up = np.zeros((1, 33))
    upright = stacked(positions_via_bvh_package(write_bvh(tmp_path / "r.bvh", rest_up, rest, up_axis=up_axis)))
    axis = "xyz".index(up_axis)
    assert upright[0, JOINT_NAMES.index("head"), axis] - upright[0, 0, axis] > 0.4
