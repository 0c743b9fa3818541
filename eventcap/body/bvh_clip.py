"""Reading a recorded motion (a BVH file) and evaluating its own skeleton: forward kinematics and resampling.

The text is parsed by ``pybvh`` (hierarchy, offsets, per-joint channel orders, the MOTION rows; it checks counts and
numbers and names the file and line of a bad hierarchy line); this module adds the line of a bad MOTION row, the
file's conventions as data, and the kinematics in numpy:

- each joint's rotation channels are intrinsic Euler angles in channel order (``Zrotation Yrotation Xrotation`` is
  ``R_z @ R_y @ R_x``), relative to its parent: ``world_j = world_parent @ local_j``,
  ``pos_j = pos_parent + world_parent @ offset_j`` (the BVH convention, as :mod:`eventcap.export.bvh` writes it);
- the root's position channels are its position; a non-zero root OFFSET is added to them (files disagree on this;
  the retargeting places the clip on the floor and at the origin, so a constant offset never matters);
- lengths stay in the file's units (see :func:`infer_units`), angles become rotations.

:func:`resample` evaluates a clip at arbitrary times: each joint's local rotation is interpolated by spherical
linear interpolation between the two frames around the time (scipy's ``Slerp``), the root position linearly.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp


class BvhError(ValueError):
    """A BVH file cannot be read or used; the message names the file and, where known, the line or joint."""


@dataclass(frozen=True)
class BvhClip:
    """A motion clip of its own skeleton. J joints (End Sites excluded), F frames.

    ``parents[j]`` precedes j (-1 for the root); ``offsets`` (J, 3) and ``root_positions`` (F, 3) are in the file's
    units; ``rotations`` (F, J, 4) are the local rotations as scipy quaternions (x, y, z, w); ``end_sites[j]`` is the
    offset of joint j's End Site, if it has one. Frame k is at time ``k * frame_time_s``.
    """

    path: str
    joint_names: tuple[str, ...]
    parents: np.ndarray
    offsets: np.ndarray
    end_sites: dict[int, np.ndarray]
    rotations: np.ndarray
    root_positions: np.ndarray
    frame_time_s: float

    @property
    def n_frames(self) -> int:
        return int(self.rotations.shape[0])

    @property
    def duration_s(self) -> float:
        """Time from the first to the last frame."""
        return (self.n_frames - 1) * self.frame_time_s

    @property
    def fps(self) -> float:
        return 1.0 / self.frame_time_s

    def rest_positions(self) -> np.ndarray:
        """Joint positions (J, 3) of the rest pose (all rotations zero), root at the origin."""
        pos = np.zeros((len(self.joint_names), 3))
        for j in range(1, len(self.joint_names)):
            pos[j] = pos[self.parents[j]] + self.offsets[j]
        return pos


def _bad_row(path: Path, message: str) -> str:
    """On a MOTION block numpy could not read, find the first line that is not a row of numbers like the first."""
    with open(path, errors="replace") as fh:
        lines = fh.read().splitlines()
    start = next((n + 1 for n, line in enumerate(lines) if line.lstrip().startswith("Frame Time")), None)
    if start is None or start >= len(lines):
        return message
    width = len(lines[start].split())
    for n in range(start, len(lines)):
        tokens = lines[n].split()
        if not tokens:
            continue
        try:
            [float(v) for v in tokens]
        except ValueError:
            return f"line {n + 1}: MOTION row {n - start + 1} holds a value that is not a number ({message})"
        if len(tokens) != width:
            return (f"line {n + 1}: MOTION row {n - start + 1} has {len(tokens)} values, the rows before it "
                    f"{width}")
    return message


def read_bvh(path) -> BvhClip:
    """Read a BVH file; :class:`BvhError` names the file and the line (or what is missing) when it is malformed."""
    import warnings

    import pybvh

    path = Path(path)
    if not path.is_file():
        raise BvhError(f"{path}: BVH file not found")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # pybvh's guesses (world up, left/right pairs) are not used here
            bvh = pybvh.read_bvh_file(path, world_up="+y", warn_on_world_up_disagreement=False)
    except (ValueError, IndexError, UnicodeDecodeError) as exc:
        raise BvhError(f"{path}: {_bad_row(path, str(exc))}") from None
    nodes = [n for n in bvh.nodes if not n.is_end_site()]
    index = {id(n): i for i, n in enumerate(nodes)}
    parents = np.array([-1 if n.parent is None else index[id(n.parent)] for n in nodes], dtype=np.int64)
    offsets = np.array([n.offset for n in nodes], dtype=np.float64)
    end_sites = {index[id(n.parent)]: np.asarray(n.offset, dtype=np.float64)
                 for n in bvh.nodes if n.is_end_site() and id(n.parent) in index}
    orders = ["".join(n.rot_channels).upper() for n in nodes]
    angles = np.asarray(bvh.joint_angles, dtype=np.float64)  # (F, J, 3) radians, channel order
    if not np.all(np.isfinite(angles)) or not np.all(np.isfinite(bvh.root_pos)):
        raise BvhError(f"{path}: the MOTION rows hold values that are not finite numbers")
    quats = np.empty(angles.shape[:2] + (4,))
    for j, order in enumerate(orders):
        quats[:, j] = Rotation.from_euler(order, angles[:, j]).as_quat()
    root = np.empty_like(bvh.root_pos, dtype=np.float64)
    for k, axis in enumerate(nodes[0].pos_channels):
        root[:, "XYZ".index(axis.upper())] = bvh.root_pos[:, k]
    root = root + offsets[0]
    return BvhClip(path=str(path), joint_names=tuple(n.name for n in nodes), parents=parents, offsets=offsets,
                   end_sites=end_sites, rotations=quats, root_positions=root, frame_time_s=float(bvh.frame_time))


def forward_kinematics(clip: BvhClip, quats: np.ndarray, root: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World joint positions (T, J, 3) and rotations (T, J, 3, 3) of local rotations (T, J, 4) and root (T, 3)."""
    T, J = quats.shape[:2]
    local = Rotation.from_quat(quats.reshape(-1, 4)).as_matrix().reshape(T, J, 3, 3)
    rot = np.empty_like(local)
    pos = np.empty((T, J, 3))
    rot[:, 0] = local[:, 0]
    pos[:, 0] = root
    for j in range(1, J):
        p = clip.parents[j]
        rot[:, j] = rot[:, p] @ local[:, j]
        pos[:, j] = pos[:, p] + rot[:, p] @ clip.offsets[j]
    return pos, rot


def end_site_positions(clip: BvhClip, pos: np.ndarray, rot: np.ndarray, joint: int) -> np.ndarray:
    """World position (T, 3) of joint ``joint``'s End Site."""
    return pos[:, joint] + rot[:, joint] @ clip.end_sites[joint]


def resample(clip: BvhClip, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Local rotations (T, J, 4) by slerp and root positions (T, 3) linearly, at times t_s (seconds from frame 0).

    Times must lie within the clip, [0, duration_s]."""
    t = np.asarray(t_s, dtype=np.float64)
    frames_t = np.arange(clip.n_frames) * clip.frame_time_s
    if t.size and (t.min() < -1e-9 or t.max() > frames_t[-1] + 1e-9):
        raise BvhError(f"{clip.path}: times {t.min():.4f}-{t.max():.4f} s lie outside the clip (0-{frames_t[-1]:.4f} s)")
    t = np.clip(t, 0.0, frames_t[-1])
    quats = np.empty((t.size, len(clip.joint_names), 4))
    if clip.n_frames == 1:
        quats[:] = clip.rotations[0]
        return quats, np.repeat(clip.root_positions[:1], t.size, axis=0)
    for j in range(len(clip.joint_names)):
        quats[:, j] = Slerp(frames_t, Rotation.from_quat(clip.rotations[:, j]))(t).as_quat()
    root = np.stack([np.interp(t, frames_t, clip.root_positions[:, k]) for k in range(3)], axis=1)
    return quats, root


#: Length units a BVH file may use, metres per unit. "cmu" is the unit of the CMU database and its BVH conversions:
#: the ASF files declare ``length 0.45``, i.e. 1 unit = 1/0.45 inch = 0.05644 m: in the shipped clips a leg (hip to
#: ankle) is 13.6-14.5 units, 0.77-0.82 m in that unit, a standing subject's hips 16-18 units high.
UNITS_M: dict[str, float] = {"m": 1.0, "dm": 0.1, "cm": 0.01, "mm": 0.001, "inch": 0.0254, "cmu": 0.0254 / 0.45}
#: Typical adult leg length, hip joint to ankle, that unit inference compares with (metres).
_TYPICAL_LEG_M = 0.82


def infer_units(leg_length: float) -> tuple[str, float]:
    """The unit (name, metres per unit) that makes a leg of ``leg_length`` file units closest to an adult's leg."""
    if not (np.isfinite(leg_length) and leg_length > 0):
        raise ValueError(f"leg length: expected a positive number of file units, got {leg_length!r}")
    name = min(UNITS_M, key=lambda u: abs(np.log(leg_length * UNITS_M[u] / _TYPICAL_LEG_M)))
    return name, UNITS_M[name]


#: Rotation taking a file whose up axis is the key to y up (right-handed, applied as ``A @ x``).
_UP_TO_Y: dict[str, np.ndarray] = {
    "+y": np.eye(3),
    "-y": np.diag([-1.0, -1.0, 1.0]),
    "+z": np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]]),
    "-z": np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]]),
    "+x": np.array([[0, 1.0, 0], [-1.0, 0, 0], [0, 0, 1.0]]),
    "-x": np.array([[0, -1.0, 0], [1.0, 0, 0], [0, 0, 1.0]]),
}


def up_axis(vector: np.ndarray) -> str:
    """The signed axis ('+y', '-z', ...) a hips-to-head vector points along."""
    v = np.asarray(vector, dtype=np.float64)
    k = int(np.argmax(np.abs(v)))
    return ("+" if v[k] > 0 else "-") + "xyz"[k]


def to_y_up(axis: str) -> np.ndarray:
    """The rotation (3, 3) that turns a file's up axis into +y."""
    return _UP_TO_Y[axis]
