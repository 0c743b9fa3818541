"""Export of an estimated skeletal motion: a Biovision BVH file of the 24-joint skeleton and a motion npz.

The BVH hierarchy is the shared skeleton (:mod:`eventcap.body.skeleton`): SMPL's 24 joints in depth-first order of
the kinematic tree, each ``OFFSET`` the rest-pose vector from the parent joint (metres times ``scale``, e.g.
``scale=100`` for centimetres), an ``End Site`` after each leaf (foot, head, hand) extending its last bone by half.
The root (pelvis) has six channels, every other joint three rotation channels in degrees.

Conventions, chosen so that any BVH reader reproduces :func:`eventcap.body.kinematics.joint_positions` exactly:

- Root position channels hold the pelvis' *world* position and the root ``OFFSET`` is zero, so readers that add
  the offset to the position channels and readers that replace it agree.
- Rotation channels are intrinsic Euler angles in the order they are listed (the BVH convention): a joint listing
  ``Xrotation Zrotation Yrotation`` has the local rotation ``R_x(a) @ R_z(b) @ R_y(c)`` relative to its parent,
  positive angles by the right-hand rule, and ``world_j = world_parent @ local_j``,
  ``pos_j = pos_parent + world_parent @ offset_j``. The rest pose (all channels zero) is the template's T-pose.
- Each joint's order follows its degrees of freedom in the skeleton's DOF table (e.g. a hip: flexion about x,
  abduction about z, rotation about y -> ``XZY``; a shoulder ``YZX``), completed by the missing axes; the root
  uses the pose vector's ``YXZ`` (yaw, pitch, roll). With these orders a joint's channels are its joint angles
  (signed by the DOF axes' directions, in degrees), and the middle angle, the one that can reach the ±90° gimbal
  lock, is a bounded DOF (hip abduction, shoulder elevation, lateral spine bend) or the root pitch.

The rotations written are not the joint angles copied but each joint's local rotation taken from the forward
kinematics (``R_parent^T R_joint``) and converted to Euler angles (:func:`euler_from_matrix`), so the file is exact
whatever the pose vector holds. Each channel is unwrapped over time (a spin gives a growing yaw, not a jump of
360°); angles a multiple of 360° apart are the same rotation. Euler angles take the branch whose middle angle lies
in [-90°, 90°]: a root pitched past ±90° (a somersault) flips its yaw and roll by 180° there, still exactly the
same rotation; at ±90° itself (gimbal lock) the third angle is 0.

World frame and time origin (:mod:`eventcap.worldframe`): y up by default; ``up_axis="z"`` rotates everything by
+90° about x, ``(x, y, z) -> (x, -z, y)`` (offsets, root positions, and every joint's rotation conjugated), and
renames each joint's rotation axes to match (y <-> z), so the channels stay the joint angles up to sign.
``scale`` sets the length unit (1 m, 100 cm, 1000 mm). BVH has no metadata field, so the first line carries a
comment after ``HIERARCHY``: the frame and, when given, the time of the first frame on the run's time axis
(``t0_us``). Readers take the first word of that line (checked with the ``bvh`` and ``bvhio`` packages; Blender's
importer reads the same way).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from eventcap.body.kinematics import global_transforms
from eventcap.body.skeleton import (
    DOF_AXIS,
    DOF_JOINT,
    DOF_NAMES,
    JOINT_NAMES,
    NUM_JOINTS,
    NUM_POSE_PARAMS,
    PARENTS,
    ROOT_ROTATION_NAMES,
    ROOT_TRANSLATION_NAMES,
    check_rest_joints,
)
from eventcap.body.template import Template
from eventcap.worldframe import check_frame, describe, rotation

_AXIS_LETTERS = "XYZ"
#: Order of the root rotation channels: the pose vector's R_root = R_y(yaw) @ R_x(pitch) @ R_z(roll).
ROOT_ROTATION_ORDER = "YXZ"
#: Axes appended (in this order) to complete a joint's rotation order when it has fewer than three DOFs.
_COMPLETION = "ZXY"
#: Frames converted at once while writing (bounds the temporaries to a few tens of MB).
_CHUNK_FRAMES = 2048
#: Below this |cos(middle angle)| a joint is treated as in gimbal lock: the third angle is set to 0.
_GIMBAL_EPS = 1e-10
#: Name of each of the 33 pose parameters.
_PARAM_NAMES = DOF_NAMES + ROOT_ROTATION_NAMES + ROOT_TRANSLATION_NAMES


@dataclass(frozen=True)
class BvhLayout:
    """How the skeleton is laid out in a BVH file.

    ``order``: joint indices (SMPL order) in file order (depth first); ``rotation_orders[j]``: the three axis letters
    of joint j's rotation channels, in channel order; ``channels``: the channel names of the MOTION rows, in column
    order, as ``(joint name, channel)`` pairs.
    """

    order: tuple[int, ...]
    rotation_orders: tuple[str, ...]

    @property
    def channels(self) -> tuple[tuple[str, str], ...]:
        out: list[tuple[str, str]] = []
        for j in self.order:
            if j == 0:
                out += [(JOINT_NAMES[0], f"{a}position") for a in _AXIS_LETTERS]
            out += [(JOINT_NAMES[j], f"{a}rotation") for a in self.rotation_orders[j]]
        return tuple(out)

    @property
    def num_channels(self) -> int:
        return 3 + 3 * NUM_JOINTS


def _depth_first() -> tuple[int, ...]:
    children: list[list[int]] = [[] for _ in range(NUM_JOINTS)]
    for j in range(1, NUM_JOINTS):
        children[int(PARENTS[j])].append(j)
    out: list[int] = []
    stack = [0]
    while stack:
        j = stack.pop()
        out.append(j)
        stack.extend(reversed(children[j]))
    return tuple(out)


def _rotation_order(joint: int) -> str:
    if joint == 0:
        return ROOT_ROTATION_ORDER
    axes = [_AXIS_LETTERS[int(np.flatnonzero(DOF_AXIS[i])[0])] for i in np.flatnonzero(DOF_JOINT == joint)]
    order = "".join(dict.fromkeys(axes))  # first occurrence of each axis, in DOF order
    return order + "".join(a for a in _COMPLETION if a not in order)


def bvh_layout(up_axis: str = "y") -> BvhLayout:
    """The skeleton's BVH layout (joint order and per-joint rotation orders) in the ``up_axis`` frame: z up renames
    each order's axes y <-> z (the rotation x -> x, y -> z, z -> -y turns a rotation about y into one about z)."""
    orders = tuple(_rotation_order(j) for j in range(NUM_JOINTS))
    if up_axis == "z":
        orders = tuple(o.translate(str.maketrans("YZ", "ZY")) for o in orders)
    return BvhLayout(order=_depth_first(), rotation_orders=orders)


# -- rotations ------------------------------------------------------------------------------------------------------
def _check_order(order: str) -> tuple[int, int, int, float]:
    if not (isinstance(order, str) and len(order) == 3 and set(order.upper()) == set(_AXIS_LETTERS)):
        raise ValueError(f"Euler order: expected a permutation of 'XYZ' such as 'ZXY', got {order!r}")
    i, j, k = (_AXIS_LETTERS.index(c) for c in order.upper())
    parity = 1.0 if (j - i) % 3 == 1 else -1.0  # +1 for XYZ, YZX, ZXY; -1 for the others
    return i, j, k, parity


def _axis_rotation(axis: int, angle: np.ndarray) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    u, v = (axis + 1) % 3, (axis + 2) % 3
    R = np.zeros(angle.shape + (3, 3))
    R[..., axis, axis] = 1.0
    R[..., u, u] = c
    R[..., v, v] = c
    R[..., u, v] = -s
    R[..., v, u] = s
    return R


def matrix_from_euler(angles: np.ndarray, order: str) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of intrinsic Euler angles (..., 3) in radians: ``R_a(a0) @ R_b(a1) @ R_c(a2)``
    for ``order = "abc"`` (the BVH channel convention)."""
    i, j, k, _ = _check_order(order)
    a = np.asarray(angles, dtype=np.float64)
    if a.shape[-1:] != (3,):
        raise ValueError(f"Euler angles: expected shape (..., 3), got {a.shape}")
    return _axis_rotation(i, a[..., 0]) @ _axis_rotation(j, a[..., 1]) @ _axis_rotation(k, a[..., 2])


def euler_from_matrix(R: np.ndarray, order: str) -> np.ndarray:
    """Intrinsic Euler angles (..., 3) in radians, channel order, of rotation matrices (..., 3, 3).

    Inverse of :func:`matrix_from_euler`: the middle angle lies in [-90°, 90°], the others in (-180°, 180°]. The
    third angle is computed first; the first angle is then solved from the matrix *given* the other two, so the
    angles reproduce ``R`` to rounding even near the gimbal lock (middle angle ±90°), where the split between the
    first and the third angle is arbitrary: there the third is set to 0.
    """
    i, j, k, s = _check_order(order)
    R = np.asarray(R, dtype=np.float64)
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"rotation matrices: expected shape (..., 3, 3), got {R.shape}")
    # R = R_i(a) R_j(b) R_k(c):  row i is [cb cc, -s cb sc, s sb] in the (i, j, k) columns.
    cos_b = np.hypot(R[..., i, i], R[..., i, j])
    b = np.arctan2(s * R[..., i, k], cos_b)
    c = np.where(cos_b > _GIMBAL_EPS, np.arctan2(-s * R[..., i, j], R[..., i, i]), 0.0)
    # Column j of R @ R_k(-c) = R_i(a) @ e_j = cos(a) e_j + s sin(a) e_k.
    v_j = np.cos(c) * R[..., j, j] + s * np.sin(c) * R[..., j, i]
    v_k = np.cos(c) * R[..., k, j] + s * np.sin(c) * R[..., k, i]
    a = np.arctan2(s * v_k, v_j)
    return np.stack([a, b, c], axis=-1)


def _rest_of(rest_joints) -> np.ndarray:
    if isinstance(rest_joints, Template):
        return rest_joints.rest_joints
    return check_rest_joints(rest_joints)


def check_poses(poses, what: str = "poses S") -> np.ndarray:
    """Poses as a (T, 33) float64 array with T >= 1 and finite values, or a ValueError naming the problem."""
    S = np.asarray(poses, dtype=np.float64)
    if S.ndim != 2 or S.shape[1] != NUM_POSE_PARAMS or S.shape[0] < 1:
        raise ValueError(f"{what}: expected shape (T, {NUM_POSE_PARAMS}) with T >= 1 (27 joint angles, root "
                         f"yaw/pitch/roll, root translation), got {S.shape}")
    bad = ~np.isfinite(S)
    if bad.any():
        t, p = np.argwhere(bad)[0]
        name = _PARAM_NAMES[p]
        raise ValueError(f"{what}: expected finite values, got {S[t, p]} at frame {t}, parameter {p} ({name}); "
                         f"{int(bad.any(axis=1).sum())} frame(s) affected")
    return S


def local_rotations(S: np.ndarray, rest_joints, up_axis: str = "y") -> tuple[np.ndarray, np.ndarray]:
    """Each joint's rotation relative to its parent, from the forward kinematics, and the pelvis' world position.

    S (T, 33); rest_joints (24, 3) metres or a Template. Returns (T, 24, 3, 3) (the root's is its world rotation)
    and (T, 3) metres, in the ``up_axis`` frame (z up: positions rotated by Q, rotations conjugated Q R Q^T).
    """
    rest = _rest_of(rest_joints)
    S = check_poses(S)
    G = global_transforms(S, rest)
    world = G[..., :3, :3]
    local = np.empty_like(world)
    local[:, 0] = world[:, 0]
    local[:, 1:] = np.swapaxes(world[:, PARENTS[1:]], -1, -2) @ world[:, 1:]
    pelvis = G[:, 0, :3, 3] + world[:, 0] @ rest[0]  # skinning transform: p = R r + b
    if up_axis != "y":
        Q = rotation(up_axis)
        local = Q @ local @ Q.T
        pelvis = pelvis @ Q.T
    return local, pelvis


def bvh_channels(S: np.ndarray, rest_joints, scale: float = 1.0, unwrap: bool = True,
                 previous: np.ndarray | None = None, up_axis: str = "y") -> np.ndarray:
    """The MOTION rows of the BVH file of poses S (T, 33): (T, 75), columns as in ``bvh_layout().channels``
    (root position in metres times ``scale``, rotations in degrees).

    ``unwrap``: remove 360° jumps of each channel over time (starting from row ``previous`` (75,) if given, the
    last row of a preceding chunk).
    """
    layout = bvh_layout(up_axis)
    local, pelvis = local_rotations(S, rest_joints, up_axis)
    T = local.shape[0]
    out = np.empty((T, layout.num_channels))
    out[:, 0:3] = pelvis * scale
    col = 3
    for j in layout.order:
        out[:, col:col + 3] = np.degrees(euler_from_matrix(local[:, j], layout.rotation_orders[j]))
        col += 3
    if unwrap:
        rot = out[:, 3:]
        if previous is not None:
            rot = np.concatenate([np.asarray(previous, dtype=np.float64)[None, 3:], rot])
        rot = np.unwrap(rot, period=360.0, axis=0)
        out[:, 3:] = rot[-T:]
    return out


# -- writing --------------------------------------------------------------------------------------------------------
def _check_positive(name: str, value: Any) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a positive number, got {value!r}") from None
    if not (np.isfinite(v) and v > 0):
        raise ValueError(f"{name}: expected a positive finite number, got {value!r}")
    return v


def _fmt(v: np.ndarray, decimals: int) -> str:
    return " ".join(f"{x:.{decimals}f}" for x in np.round(v, decimals) + 0.0)  # + 0.0: no "-0.000"


def _end_site(rest: np.ndarray, j: int) -> np.ndarray:
    """A leaf's End Site: its last bone continued by half its length (fingertips, toe tips, top of the head)."""
    return 0.5 * (rest[j] - rest[int(PARENTS[j])])


def hierarchy_text(rest_joints, scale: float = 1.0, decimals: int = 8, up_axis: str = "y",
                   comment: str = "") -> str:
    """The HIERARCHY section of the skeleton (24 joints, offsets from the rest joints times ``scale``, in the
    ``up_axis`` frame); ``comment`` follows ``HIERARCHY`` on the first line after a ``#``."""
    rest = _rest_of(rest_joints) @ rotation(up_axis).T
    scale = _check_positive("scale", scale)
    layout = bvh_layout(up_axis)
    children: dict[int, list[int]] = {j: [] for j in range(NUM_JOINTS)}
    for j in range(1, NUM_JOINTS):
        children[int(PARENTS[j])].append(j)
    lines = ["HIERARCHY" + (f"  # {comment}" if comment else "")]

    def emit(j: int, depth: int) -> None:
        pad = "  " * depth
        rot = " ".join(f"{a}rotation" for a in layout.rotation_orders[j])
        if j == 0:
            lines.append(f"ROOT {JOINT_NAMES[j]}")
            offset = np.zeros(3)  # root position channels are absolute (see the module docstring)
            channels = f"CHANNELS 6 Xposition Yposition Zposition {rot}"
        else:
            lines.append(f"{pad}JOINT {JOINT_NAMES[j]}")
            offset = (rest[j] - rest[int(PARENTS[j])]) * scale
            channels = f"CHANNELS 3 {rot}"
        lines.extend([f"{pad}{{", f"{pad}  OFFSET {_fmt(offset, decimals)}", f"{pad}  {channels}"])
        for c in children[j]:
            emit(c, depth + 1)
        if not children[j]:
            end = _fmt(_end_site(rest, j) * scale, decimals)
            lines.extend([f"{pad}  End Site", f"{pad}  {{", f"{pad}    OFFSET {end}", f"{pad}  }}"])
        lines.append(f"{pad}}}")

    emit(0, 0)
    return "\n".join(lines) + "\n"


def _partial(path: Path) -> Path:
    return path.with_name(path.name + ".partial")


def _remove(p: Path) -> None:
    try:
        p.unlink()
    except FileNotFoundError:
        pass


def write_bvh(path, poses, rest_joints, frame_time_s: float = 0.001, scale: float = 1.0, decimals: int = 8,
              unwrap: bool = True, up_axis: str = "y", t0_us: int | None = None, note: str = "") -> Path:
    """Write a skeletal motion as a BVH file; returns the path.

    poses: S (T, 33) in the skeleton layout (default: one pose every millisecond, ``frame_time_s = 0.001``).
    rest_joints: the template's rest joints (24, 3) metres, or the Template. ``scale``: factor on all lengths
    (1 = metres, 100 = centimetres). ``decimals``: digits after the point of every number. ``up_axis``: y | z.
    ``t0_us``: time of the first frame on the run's time axis, stated in the first line's comment; ``note``: more of
    that comment (one line: where the motion's per-joint uncertainty is, which BVH cannot hold). The file appears
    atomically (written beside it as ``<name>.partial``, then renamed); on error nothing is left behind.
    """
    path = Path(path)
    S = check_poses(poses)
    rest = _rest_of(rest_joints)
    frame_time_s = _check_positive("frame_time_s", frame_time_s)
    scale = _check_positive("scale", scale)
    if not (isinstance(decimals, (int, np.integer)) and 1 <= decimals <= 15):
        raise ValueError(f"decimals: expected an int in [1, 15], got {decimals!r}")
    check_frame(up_axis, "m")
    unit = {1.0: "m", 100.0: "cm", 1000.0: "mm"}.get(scale, f"1/{scale:g} m")
    comment = f"eventcap: {describe(up_axis, unit)}"
    if t0_us is not None:
        comment += f"; first frame at t = {int(t0_us)} us on the run's time axis, then every {frame_time_s * 1e6:g} us"
    if note:
        if "\n" in note or "\r" in note:
            raise ValueError("note: expected one line (it goes into the first line's comment)")
        comment += f"; {note}"
    header = (hierarchy_text(rest, scale, decimals, up_axis, comment)
              + f"MOTION\nFrames: {S.shape[0]}\nFrame Time: {frame_time_s!r}\n")
    tmp = _partial(path)
    _remove(tmp)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        with open(tmp, "w", encoding="ascii", newline="\n") as fh:
            fh.write(header)
            previous = None
            for a in range(0, S.shape[0], _CHUNK_FRAMES):
                rows = bvh_channels(S[a:a + _CHUNK_FRAMES], rest, scale, unwrap, previous, up_axis)
                np.savetxt(fh, np.round(rows, decimals) + 0.0, fmt=f"%.{int(decimals)}f", delimiter=" ")
                previous = rows[-1]
        os.replace(tmp, path)
    except BaseException:
        _remove(tmp)
        raise
    return path


def write_motion_npz(path, t_us, poses, joints, extra: Mapping[str, Any] | None = None,
                     estimated: np.ndarray | None = None) -> Path:
    """Write a skeletal motion as an npz file; returns the path.

    Arrays: ``t_us`` (T,) int64 microseconds, strictly increasing; ``poses`` (T, 33) float64 (S = [θ, root
    rotation, root translation], radians and metres); ``joints`` (T, 24, 3) float64 metres; ``param_names`` (33,)
    and ``joint_names`` (24,) strings naming the columns; plus any ``extra`` arrays (names must not clash).
    ``estimated`` (T,) bool: the frames that have an estimate; the others (gaps) are NaN, every estimated frame
    finite (None: every frame is estimated). Written atomically (``<name>.partial``, then renamed).
    """
    path = Path(path)
    t = np.asarray(t_us)
    if t.ndim != 1 or t.shape[0] < 1:
        raise ValueError(f"t_us: expected shape (T,) with T >= 1, got {t.shape}")
    if not np.issubdtype(t.dtype, np.integer):
        if not (np.all(np.isfinite(t)) and np.all(t == np.round(t))):
            raise ValueError("t_us: expected integer microseconds")
    t = t.astype(np.int64)
    if t.size > 1 and np.any(np.diff(t) <= 0):
        i = int(np.argmax(np.diff(t) <= 0)) + 1
        raise ValueError(f"t_us: expected strictly increasing times, frame {i} is at {t[i]} us after {t[i - 1]} us")
    est = np.ones(t.shape[0], dtype=bool) if estimated is None else np.asarray(estimated, dtype=bool)
    if est.shape != t.shape or not est.any():
        raise ValueError(f"estimated: expected one flag per time ({t.shape[0]}), at least one true, got "
                         f"{int(est.sum())} of shape {est.shape}")
    S = np.asarray(poses, dtype=np.float64)
    if S.ndim != 2 or S.shape[0] != t.shape[0]:
        check_poses(S)  # names the shape it expected
        raise ValueError(f"poses: expected one row per time ({t.shape[0]}), got shape {S.shape}")
    check_poses(S[est])  # a gap is NaN; every estimated frame finite
    J = np.asarray(joints, dtype=np.float64)
    if J.shape != (t.shape[0], NUM_JOINTS, 3):
        raise ValueError(f"joints: expected shape ({t.shape[0]}, {NUM_JOINTS}, 3) (T, SMPL joints, xyz metres), "
                         f"got {J.shape}")
    if not np.all(np.isfinite(J[est])):
        raise ValueError("joints: expected finite values at every estimated frame, got NaN or inf")
    arrays: dict[str, np.ndarray] = {"t_us": t, "poses": S, "joints": J, "param_names": np.array(_PARAM_NAMES),
                                     "joint_names": np.array(JOINT_NAMES)}
    for k, v in (extra or {}).items():
        if k in arrays:
            raise ValueError(f"extra: array name {k!r} is taken by the motion itself")
        arrays[k] = np.asarray(v)
    tmp = _partial(path)
    _remove(tmp)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        with open(tmp, "wb") as fh:  # a file object: numpy would append ".npz" to a path
            np.savez_compressed(fh, **arrays)
        os.replace(tmp, path)
    except BaseException:
        _remove(tmp)
        raise
    return path


def read_motion_npz(path) -> dict[str, np.ndarray]:
    """The arrays of a motion npz written by :func:`write_motion_npz`."""
    with np.load(Path(path), allow_pickle=False) as z:
        return {k: z[k] for k in z.files}
