"""Retargeting a recorded motion (a BVH clip) onto the shared skeleton: the pose S (33) that best matches each sample.

A BVH skeleton has free 3-DOF joints, other bone lengths and another rest pose than ours (27 bounded joint angles
about fixed axes + root rotation and translation, :mod:`eventcap.body.skeleton`), so its rotations cannot be copied.
Each sample is fitted instead, a bounded least-squares problem over S:

- **directions** of lines that are the same anatomical line on any skeleton, compared as unit vectors (so bone
  lengths and proportions do not matter): thighs, shanks, upper arms, forearms, the hip line, the shoulder line,
  and (weakly) neck-to-shoulder lines for shrugs;
- **orientations** of segments whose joints sit at skeleton-specific places, and of twists that lines leave open:
  pelvis, chest and head (forward and up axes), each foot (its left axis and ankle-to-ball line) and each upper
  arm (forward axis, weakly), taken from the clip's own segment rotations relative to its rest pose, which is taken
  as neutral (standing, T- or A-pose);
- **position** of the mid-hip point (the clip's, scaled to our leg length and placed, see below);
- a weak pull towards the warm start, which keeps what the data leaves undetermined (an upper arm's twist while the
  elbow is straight) where it was.

Twists the data determines are matched: the upper arm's by the bent forearm, the thigh's by the shank and foot,
the spine's by the shoulder and hip lines and the chest. The joint limits (THETA_LOWER/UPPER) bound every step
(projected steps). A sample counts as clipped when the limits cost its fit as much as a segment 2 degrees off the
clip (:data:`CLIP_COST`); the log gives their number and the joints held.

Placement: lengths are scaled by ``s = our leg length / the clip's leg length`` (hip to ankle, rest poses). The
file's up axis (+y, +z, ...) is read from its rest pose (hips to head) and turned into +y. At the clip's first
played sample the mid-hip point is moved to x = z = 0 and the body turned about the vertical so that it faces +z
(the camera), its facing taken as the cross product of its left-to-right hip line and up; the feet must point the
same way (else the file's left and right are swapped and it is refused). The floor is the lowest height the clip's
feet reach in the whole file: the retargeted motion is shifted vertically so that our soles touch y = 0 at that
moment.

Resampling and the two passes: the clip's local joint rotations are interpolated by slerp and its root position
linearly (:func:`eventcap.body.bvh_clip.resample`) onto the sample times, a grid at ``rate_hz`` (the ground-truth
rate, 1 kHz by default). Pass 1 fits the clip's own frames in the played window one after the other, each
warm-started from the previous one (Levenberg-Marquardt; residuals and Jacobians from the CasADi forward kinematics
of :mod:`eventcap.body.kinematics`). Its poses, interpolated linearly to the grid, start pass 2: every grid sample at
once, the fit plus a penalty on the poses' acceleration (a banded Gauss-Newton over the whole grid), because
samples fitted on their own jump between near-equivalent poses (see :func:`_smooth`). The capture then
interpolates the grid's poses linearly (it tabulates them every 50 us).
"""

from __future__ import annotations

import logging
import re
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from eventcap.body import kinematics
from eventcap.body.bvh_clip import (
    BvhClip,
    BvhError,
    end_site_positions,
    forward_kinematics,
    infer_units,
    read_bvh,
    resample,
    to_y_up,
    up_axis,
)
from eventcap.body.skeleton import (
    DEFAULT_REST_JOINTS,
    DOF_NAMES,
    JOINT_INDEX,
    JOINT_NAMES,
    LANDMARK_INDEX,
    NUM_POSE_PARAMS,
    default_landmarks,
    pose_bounds,
)
from eventcap.body.template import Template

log = logging.getLogger(__name__)

#: Our joints a clip must provide (by name convention or mapping file). spine3 (the chest) is, unless mapped, the
#: clip joint both shoulders hang from; l_foot/r_foot (the ball of the foot) are optional (for the floor and the
#: facing check; without them the ankle's End Site stands in); so is the neck (:data:`FROM_NEIGHBOURS`).
REQUIRED_JOINTS: tuple[str, ...] = ("pelvis", "spine3", "l_hip", "r_hip", "l_knee", "r_knee", "l_ankle", "r_ankle",
                                    "head", "l_shoulder", "r_shoulder", "l_elbow", "r_elbow", "l_wrist", "r_wrist")
OPTIONAL_JOINTS: tuple[str, ...] = ("l_foot", "r_foot", "neck")
#: Joints a skeleton may lack (15-joint rigs: no neck, or no chest), and what stands in for them: the neck is the
#: midpoint of the shoulders (it carries only the weak shrug lines); the chest (spine3) the clip joint both
#: shoulders hang from (map_joints), its rotation the chest's.
FROM_NEIGHBOURS = {"neck": "the midpoint of the shoulders", "spine3": "the joint both shoulders hang from"}

# Names of a joint in the common conventions, normalised (lower case, letters and digits only, side removed),
# in order of preference. CMU/cgspeed and Mixamo: Hips, LeftUpLeg, LeftLeg, LeftFoot, LeftToeBase, Neck(1), Head,
# LeftShoulder (the clavicle), LeftArm, LeftForeArm, LeftHand. Where "shoulder" names the clavicle beside an "arm",
# the arm wins; where there is no arm, the shoulder is the shoulder joint.
_CENTRAL_ALIASES = {"pelvis": ("hips", "hip", "pelvis", "root"), "neck": ("neck1", "upperneck", "neck"),
                    "head": ("head",)}
_SIDED_ALIASES = {
    "hip": ("hip", "upleg", "upperleg", "thigh", "femur"),
    "knee": ("knee", "leg", "lowerleg", "lowleg", "shin", "calf", "tibia"),
    "ankle": ("ankle", "foot"),
    "foot": ("toebase", "toe", "toes", "ball", "foot"),
    "shoulder": ("arm", "uparm", "upperarm", "humerus", "shoulder"),
    "elbow": ("elbow", "forearm", "lowerarm", "lowarm", "radius"),
    "wrist": ("wrist", "hand"),
}
_SIDE_WORDS = {"left": "l", "right": "r"}

# The fit's terms: (from, to, weight) unit directions of lines that are the same anatomical line on any skeleton
# (limbs, the hip and shoulder lines; a neck-to-shoulder line weakly, for shrugs).
_DIRECTIONS = (
    ("l_hip", "l_knee", 1.0), ("r_hip", "r_knee", 1.0), ("l_knee", "l_ankle", 1.0), ("r_knee", "r_ankle", 1.0),
    ("l_shoulder", "l_elbow", 1.0), ("r_shoulder", "r_elbow", 1.0), ("l_elbow", "l_wrist", 1.0),
    ("r_elbow", "r_wrist", 1.0), ("r_hip", "l_hip", 1.0), ("r_shoulder", "l_shoulder", 1.0),
    ("neck", "l_shoulder", 0.2), ("neck", "r_shoulder", 0.2),
    # shoulder to wrist: where a hanging arm's direction lies beyond the elevation bound (next to the shoulder's
    # gimbal pole), near-equivalent poses differ in where they put the hand; this keeps it where the clip's is
    ("l_shoulder", "l_wrist", 1.0), ("r_shoulder", "r_wrist", 1.0),
)
#: (our joint, vector, weight): the joint's rotation since the rest pose applied to a vector of our rest body frame,
#: matched against the clip's segment rotation applied to the same vector (both rest poses taken as neutral). This
#: orients the segments whose joint positions differ between skeletons (where a pelvis, chest or head joint sits
#: depends on the marker set: line-matching them tilted the trunk by 5-10 degrees on CMU clips) and fixes the twists
#: lines leave open: pelvis, chest (spine3: the clip's joint the shoulders hang from) and head by their forward and
#: up axes, each foot by its left axis and its ankle-to-ball line (CMU's foot points 13 degrees down at rest, ours
#: 25: matched by positions it would tilt every foot by the difference).
_ROTATED = (("pelvis", "forward", 0.7), ("pelvis", "up", 0.7), ("spine3", "forward", 0.7), ("spine3", "up", 0.7),
            ("head", "forward", 0.5), ("head", "up", 0.5), ("l_ankle", "left", 0.3), ("r_ankle", "left", 0.3),
            ("l_ankle", "l_foot", 0.7), ("r_ankle", "r_foot", 0.7), ("l_shoulder", "forward", 0.2),
            ("r_shoulder", "forward", 0.2))
_BODY_AXES = {"left": (1.0, 0.0, 0.0), "up": (0.0, 1.0, 0.0), "forward": (0.0, 0.0, 1.0)}
_POSITION_WEIGHT = 10.0  # per metre of mid-hip error (10 cm weighs like 0.1 rad of a segment's direction)
_PRIOR_WEIGHT = 0.1  # per radian away from the warm start (joint angles, root rotation): resolves what data leaves open
#: Weight (s^2) of the acceleration penalty of pass 2: a joint accelerating at 1000 rad/s^2 (a fast punch's elbow)
#: costs like a segment 0.6 degrees off the clip; a jump of 50 degrees within a millisecond like 8 radians off.
_ACCEL_S2 = 1e-5
#: The whole body turns and moves more slowly than a limb: its rotation and translation weigh 20 times more (a dancer
#: whose leg is beyond its limits otherwise swaps hip rotation for pelvis yaw within a few milliseconds).
_ACCEL_SCALE = np.r_[np.ones(27), np.full(6, 20.0)]
_SOLE_LANDMARKS = ("l_big_toe", "l_small_toe", "l_heel", "r_big_toe", "r_small_toe", "r_heel")


def _rest_vectors(rest: np.ndarray) -> np.ndarray:
    """(len(_ROTATED), 3) unit vectors of our rest body frame that the rotation terms carry."""
    out = []
    for joint, vec, _ in _ROTATED:
        v = np.asarray(_BODY_AXES[vec]) if vec in _BODY_AXES else rest[JOINT_INDEX[vec]] - rest[JOINT_INDEX[joint]]
        out.append(v / np.linalg.norm(v))
    return np.array(out)


# ---------------------------------------------------------------------------------------------------------------
# Joint names


def _split_side(name: str) -> tuple[str, str]:
    """(side 'l' | 'r' | '', normalised base) of a joint name; namespaces ('mixamorig:') are dropped."""
    raw = name.split(":")[-1].strip().lower()
    for word, side in _SIDE_WORDS.items():
        if raw.startswith(word):
            return side, re.sub(r"[^a-z0-9]", "", raw[len(word):])
        if raw.endswith(word):
            return side, re.sub(r"[^a-z0-9]", "", raw[: -len(word)])
    m = re.fullmatch(r"([lr])[_.\- ](.+)", raw) or re.fullmatch(r"(.+)[_.\- ]([lr])", raw)
    if m:
        side, base = (m.group(1), m.group(2)) if len(m.group(1)) == 1 else (m.group(2), m.group(1))
        return side, re.sub(r"[^a-z0-9]", "", base)
    flat = re.sub(r"[^a-z0-9]", "", raw)
    if flat[:1] in ("l", "r") and any(flat[1:] == a for names in _SIDED_ALIASES.values() for a in names):
        return flat[0], flat[1:]
    return "", flat


def _auto_mapping(joint_names: tuple[str, ...]) -> dict[str, int]:
    """Our joint name -> clip joint index, from the naming conventions: the first alias found wins, and a clip
    joint serves one of our joints only (so 'LeftFoot' is the ankle beside 'LeftToeBase', but 'l_foot' the ball of
    the foot beside 'l_ankle')."""
    by_key: dict[tuple[str, str], int] = {}
    for i, n in enumerate(joint_names):
        by_key.setdefault(_split_side(n), i)
    out: dict[str, int] = {}
    wanted = [(ours, "", aliases) for ours, aliases in _CENTRAL_ALIASES.items()]
    wanted += [(f"{side}_{ours}", side, aliases) for side in ("l", "r") for ours, aliases in _SIDED_ALIASES.items()]
    for ours, side, aliases in wanted:
        hit = next((by_key[(side, a)] for a in aliases if (side, a) in by_key and by_key[(side, a)] not in
                    out.values()), None)
        if hit is not None:
            out[ours] = hit
    return out


def read_mapping(path) -> dict[str, str]:
    """A mapping file (YAML or JSON): {BVH joint name: our joint name}; errors name the file and the entry."""
    import yaml

    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise BvhError(f"{path}: mapping file not found") from None
    except yaml.YAMLError as exc:
        raise BvhError(f"{path}: not valid YAML/JSON ({str(exc).splitlines()[0]})") from None
    if not isinstance(data, dict) or not data:
        raise BvhError(f"{path}: expected a mapping 'BVH joint name: our joint name', got {type(data).__name__}")
    for k, v in data.items():
        if v not in JOINT_NAMES:
            raise BvhError(f"{path}: entry {k!r}: {v!r} is not one of our joints ({', '.join(JOINT_NAMES)})")
    return {str(k): str(v) for k, v in data.items()}


def _common_ancestor(parents: np.ndarray, a: int, b: int) -> int:
    chain = set()
    while a >= 0:
        chain.add(a)
        a = int(parents[a])
    while b not in chain:
        b = int(parents[b])
    return b


def map_joints(clip: BvhClip, mapping_path: str | None = None, derived: list | None = None) -> dict[str, int]:
    """Our joint name -> clip joint index: the conventions, overridden by a mapping file; clear errors otherwise.
    The joints the clip lacks that stand in from their neighbours (:data:`FROM_NEIGHBOURS`) are appended to
    ``derived`` (the neck has no index then)."""
    mapping = _auto_mapping(clip.joint_names)
    if mapping_path:
        index = {n: i for i, n in enumerate(clip.joint_names)}
        for bvh_name, ours in read_mapping(mapping_path).items():
            if bvh_name not in index:
                raise BvhError(f"{mapping_path}: BVH joint {bvh_name!r} is not in {clip.path} "
                               f"(its joints: {', '.join(clip.joint_names)})")
            mapping[ours] = index[bvh_name]
    derived = [] if derived is None else derived
    if "spine3" not in mapping and "l_shoulder" in mapping and "r_shoulder" in mapping:
        mapping["spine3"] = _common_ancestor(clip.parents, mapping["l_shoulder"], mapping["r_shoulder"])
        derived.append("spine3")
    if "neck" not in mapping:
        derived.append("neck")
    missing = [j for j in REQUIRED_JOINTS if j not in mapping]
    if missing:
        raise BvhError(f"{clip.path}: no joint found for {', '.join(missing)} (BVH joints: "
                       f"{', '.join(clip.joint_names)}); give a mapping file, source.motion_map=<yaml|json> with "
                       f"lines 'BVH joint name: our joint name'")
    named = {j: clip.joint_names[mapping[j]] for j in derived if j in mapping}
    log.info("%s: joints taken from their neighbours: %s", clip.path, "; ".join(
        f"{j}: {FROM_NEIGHBOURS[j]}" + (f" ({named[j]})" if j in named else "") for j in derived) or "none")
    return mapping


# ---------------------------------------------------------------------------------------------------------------
# The clip in our frame


@dataclass
class ClipTargets:
    """What the fit matches, per sample (T): mid-hip (T, 3) metres, unit directions (T, D, 3), axes (T, A, 3)."""

    midhip: np.ndarray
    directions: np.ndarray
    axes: np.ndarray
    direction_weight: np.ndarray  # (D,) weights, 0 where the clip lacks the segment

    def flat(self) -> np.ndarray:
        """(T, 3 + 3D + 3A): the fit's target vector per sample."""
        T = self.midhip.shape[0]
        return np.concatenate([self.midhip, self.directions.reshape(T, -1), self.axes.reshape(T, -1)], axis=1)


@dataclass(frozen=True)
class _Frame:
    """How the clip is put into our world: x_ours = yaw @ (scale * A @ x_file) + shift; rotations by yaw @ A."""

    A: np.ndarray
    yaw: np.ndarray
    scale: float
    shift: np.ndarray
    rest_axes: np.ndarray  # (3, 3) the clip's rest body frame in A-coordinates: columns left, up, forward


def _toe_points(clip, mapping, pos, rot, side):
    """World points (T, 3) standing for our l_foot / r_foot, or None."""
    if f"{side}_foot" in mapping:
        return pos[:, mapping[f"{side}_foot"]]
    ankle = mapping[f"{side}_ankle"]
    if ankle in clip.end_sites:
        return end_site_positions(clip, pos, rot, ankle)
    return None


def _rest_frame(clip: BvhClip, mapping: dict[str, int]) -> tuple[str, np.ndarray, np.ndarray]:
    """Up axis (and what told it), the rotation A to y up and the rest body frame (columns left, up, forward) after
    A. The up axis is where the rest pose's hips-to-head line points, or the first frame's if the rest pose's is
    not clearly along one axis."""
    rest = clip.rest_positions()
    v = rest[mapping["head"]] - rest[mapping["pelvis"]]
    source = "the rest pose"
    if np.max(np.abs(v)) < 0.8 * np.linalg.norm(v):  # a rest pose lying or leaning: ask the first frame
        pos, _ = forward_kinematics(clip, clip.rotations[:1], clip.root_positions[:1])
        v, source = pos[0, mapping["head"]] - pos[0, mapping["pelvis"]], "the first frame"
    axis = up_axis(v)
    A = to_y_up(axis)
    left = A @ (rest[mapping["l_hip"]] - rest[mapping["r_hip"]])
    left[1] = 0.0
    if np.linalg.norm(left) < 1e-9:
        raise BvhError(f"{clip.path}: the rest pose's hips coincide; cannot tell left from right")
    left /= np.linalg.norm(left)
    up = np.array([0.0, 1.0, 0.0])
    return f"{axis} (from {source})", A, np.stack([left, up, np.cross(left, up)], axis=1)


def _leg_length(clip: BvhClip, mapping: dict[str, int]) -> float:
    rest = clip.rest_positions()
    legs = [np.linalg.norm(rest[mapping[f"{s}_knee"]] - rest[mapping[f"{s}_hip"]])
            + np.linalg.norm(rest[mapping[f"{s}_ankle"]] - rest[mapping[f"{s}_knee"]]) for s in "lr"]
    return float(np.mean(legs))


def _foot_heights(clip, mapping, pos, rot) -> np.ndarray:
    """Heights (T,) of the clip's lowest foot point (ankles, toes), in file units after A (y up)."""
    pts = [pos[:, mapping[f"{s}_ankle"]] for s in "lr"]
    pts += [p for p in (_toe_points(clip, mapping, pos, rot, s) for s in "lr") if p is not None]
    return np.min(np.stack(pts, axis=1)[..., 1], axis=1)


def _place(clip, mapping, body_leg_m, start_s) -> tuple[_Frame, dict]:
    """The clip's frame in our world (scale, up axis, facing +z at start_s, mid-hip at x = z = 0) and the floor."""
    axis, A, rest_axes = _rest_frame(clip, mapping)
    leg = _leg_length(clip, mapping)
    unit, metres = infer_units(leg)
    scale = body_leg_m / leg
    q, r = resample(clip, np.array([start_s]))
    pos, rot = forward_kinematics(clip, q, r)
    pos = pos @ A.T
    rot = A @ rot
    left = pos[0, mapping["l_hip"]] - pos[0, mapping["r_hip"]]
    forward = np.cross(left, [0.0, 1.0, 0.0])
    forward[1] = 0.0
    forward /= np.linalg.norm(forward)
    toes = [_toe_points(clip, mapping, pos, rot, s) for s in "lr"]
    if all(t is not None for t in toes):
        feet = sum(t[0] - pos[0, mapping[f"{s}_ankle"]] for t, s in zip(toes, "lr"))
        if float(feet @ forward) < 0:
            raise BvhError(f"{clip.path}: the feet point backwards from the facing its left/right hips give; the "
                           f"file's left and right look swapped (a mirrored skeleton)")
    ang = np.arctan2(forward[0], forward[2])  # turn by -ang about y: forward -> +z
    c, s_ = np.cos(-ang), np.sin(-ang)
    yaw = np.array([[c, 0.0, s_], [0.0, 1.0, 0.0], [-s_, 0.0, c]])
    pos_all, rot_all = forward_kinematics(clip, clip.rotations, clip.root_positions)
    floor = float(np.min(_foot_heights(clip, mapping, pos_all @ A.T, A @ rot_all)))
    floor_frame = int(np.argmin(_foot_heights(clip, mapping, pos_all @ A.T, A @ rot_all)))
    mid = 0.5 * (pos[0, mapping["l_hip"]] + pos[0, mapping["r_hip"]]) * scale
    shift = -(yaw @ mid)
    shift[1] = -floor * scale
    info = {"up_axis": axis, "units": unit, "metres_per_unit": metres, "leg_length_units": leg, "scale": scale,
            "floor_frame": floor_frame}
    return _Frame(A=A, yaw=yaw, scale=scale, shift=shift, rest_axes=rest_axes), info


def clip_targets(clip: BvhClip, mapping: dict[str, int], frame: _Frame, t_s: np.ndarray,
                 rest: np.ndarray) -> ClipTargets:
    """The fit's targets at times t_s (seconds from the clip's frame 0), in our world, for our rest joints."""
    q, r = resample(clip, t_s)
    pos, rot = forward_kinematics(clip, q, r)
    R = frame.yaw @ frame.A
    pos = frame.scale * pos @ R.T + frame.shift
    rot = R @ rot
    pts = {name: pos[:, j] for name, j in mapping.items()}
    for s in "lr":
        toe = _toe_points(clip, mapping, pos, rot, s)
        if toe is not None:
            pts[f"{s}_foot"] = toe
    pts["midhip"] = 0.5 * (pts["l_hip"] + pts["r_hip"])
    if "neck" not in pts:  # a rig without a neck (FROM_NEIGHBOURS)
        pts["neck"] = 0.5 * (pts["l_shoulder"] + pts["r_shoulder"])
    dirs, weights = [], []
    for a, b, w in _DIRECTIONS:
        if a in pts and b in pts:
            d = pts[b] - pts[a]
            dirs.append(d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12))
            weights.append(w)
        else:
            dirs.append(np.zeros_like(pts["midhip"]))
            weights.append(0.0)
    # a segment's frame now = its rotation since the rest pose applied to the clip's rest body frame
    # our rest vector in the clip's rest frame, then turned by the clip segment's rotation since its rest pose
    vecs = _rest_vectors(rest) @ frame.rest_axes.T @ frame.A
    axes = [rot[:, mapping[j]] @ v for (j, _, _), v in zip(_ROTATED, vecs)]
    return ClipTargets(midhip=pts["midhip"], directions=np.stack(dirs, axis=1), axes=np.stack(axes, axis=1),
                       direction_weight=np.array(weights))


# ---------------------------------------------------------------------------------------------------------------
# The fit


class _Residuals:
    """The fit's residuals r(S, target) and their Jacobian for one rest skeleton: a CasADi function of one sample
    (the forward kinematics of :mod:`eventcap.body.kinematics`, differentiated by CasADi), evaluated for one sample
    or, mapped, for many at once."""

    def __init__(self, rest: np.ndarray, direction_weight: np.ndarray):
        import casadi as ca

        S = ca.SX.sym("S", NUM_POSE_PARAMS)
        tgt = ca.SX.sym("tgt", 3 + 3 * len(_DIRECTIONS) + 3 * len(_ROTATED))
        J = kinematics.joint_positions(S, rest)
        G = kinematics.global_transforms(S, rest)

        def point(name):
            return J[JOINT_INDEX[name], :].T

        res = [_POSITION_WEIGHT * (0.5 * (point("l_hip") + point("r_hip")) - tgt[0:3])]
        for k, (a, b, _) in enumerate(_DIRECTIONS):
            d = point(b) - point(a)
            res.append(direction_weight[k] * (d / ca.norm_2(d) - tgt[3 + 3 * k: 6 + 3 * k]))
        base = 3 + 3 * len(_DIRECTIONS)
        for k, ((j, _, w), v) in enumerate(zip(_ROTATED, _rest_vectors(rest))):
            res.append(w * (ca.mtimes(G[JOINT_INDEX[j]][0:3, 0:3], ca.DM(v)) - tgt[base + 3 * k: base + 3 * k + 3]))
        r = ca.vertcat(*res)
        self.n_res = int(r.shape[0])
        self.fun = ca.Function("retarget_residuals", [S, tgt], [r, ca.densify(ca.jacobian(r, S))])
        self._mapped: dict[int, object] = {}

    def __call__(self, S: np.ndarray, tgt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """r (N, m) and J (N, m, 33) for poses S (N, 33) and targets (N, n_t)."""
        N = S.shape[0]
        f = self._mapped.get(N)
        if f is None:
            f = self._mapped[N] = self.fun if N == 1 else self.fun.map(N, "serial")
        r, J = f(S.T, tgt.T)
        return r.full().T, J.full().reshape(self.n_res, N, NUM_POSE_PARAMS).transpose(1, 0, 2)


def _lm(res: _Residuals, S0: np.ndarray, tgt: np.ndarray, iters: int, tol: float = 1e-7) -> np.ndarray:
    """Levenberg-Marquardt within the joint limits for N independent samples at once, S (N, 33), pulled weakly
    towards S0 (projected steps: a joint at a bound with the gradient pushing outwards is held)."""
    lo, hi = pose_bounds()
    prior = np.zeros(NUM_POSE_PARAMS)
    prior[:30] = _PRIOR_WEIGHT
    S = np.clip(S0, lo, hi)
    lam = np.full(S.shape[0], 1e-3)
    eye = np.eye(NUM_POSE_PARAMS)

    def normal_equations(S_, r_, J_):
        Jt = J_.transpose(0, 2, 1)
        return (Jt @ r_[..., None])[..., 0] + prior ** 2 * (S_ - S0), Jt @ J_ + np.diag(prior ** 2)

    def cost_of(S_, r_):
        return np.sum(r_ * r_, axis=1) + np.sum((prior * (S_ - S0)) ** 2, axis=1)

    r, J = res(S, tgt)
    cost = cost_of(S, r)
    for _ in range(iters):
        g, H = normal_equations(S, r, J)
        free = ~(((S <= lo + 1e-12) & (g > 0)) | ((S >= hi - 1e-12) & (g < 0)))
        H = H + (lam[:, None] * (np.einsum("nkk->nk", H) + 1e-9))[:, :, None] * eye
        H = H * (free[:, :, None] & free[:, None, :]) + (~free)[:, :, None] * eye
        step = -np.linalg.solve(H, (g * free)[..., None])[..., 0]
        S_new = np.clip(S + step, lo, hi)
        r_new, J_new = res(S_new, tgt)
        cost_new = cost_of(S_new, r_new)
        ok = cost_new < cost
        S[ok], r[ok], J[ok], cost[ok] = S_new[ok], r_new[ok], J_new[ok], cost_new[ok]
        lam = np.where(ok, lam * 0.3, lam * 10.0)
        if np.max(np.abs(step[ok]), initial=0.0) < tol and np.all(ok | (lam > 1e6)):
            break
    return S


def _limits(res: _Residuals, S: np.ndarray, tgt: np.ndarray, chunk: int = 500) -> tuple[np.ndarray, np.ndarray]:
    """What the joint limits cost each sample's fit: the decrease of its residuals that one damped Gauss-Newton step
    without the limits would bring (T,), and which joint angles are held at a bound (T, 27)."""
    lo, hi = pose_bounds()
    gains, helds = [], []
    for a in range(0, S.shape[0], chunk):
        Sa = S[a:a + chunk]
        r, J = res(Sa, tgt[a:a + chunk])
        Jt = J.transpose(0, 2, 1)
        g, H = (Jt @ r[..., None])[..., 0], Jt @ J
        eye = np.eye(NUM_POSE_PARAMS)
        step = -np.linalg.solve(H + 1e-2 * np.einsum("nkk->nk", H)[:, :, None] * eye + 1e-9 * eye, g[..., None])[..., 0]
        gains.append(-(np.sum(g * step, axis=1) + 0.5 * np.einsum("nk,nkl,nl->n", step, H, step)))
        helds.append((((Sa <= lo + 1e-9) & (g > 0)) | ((Sa >= hi - 1e-9) & (g < 0)))[:, :27])
    return np.concatenate(gains), np.concatenate(helds)


@dataclass
class RetargetResult:
    """Poses S (T, 33) at the sample times and what the log reports."""

    poses: np.ndarray
    stats: dict


def _initial_pose(tg: ClipTargets) -> np.ndarray:
    """Rest pose turned to the clip's facing at the first sample (root yaw from the hip line), at its mid-hip."""
    S = np.zeros(NUM_POSE_PARAMS)
    hip = tg.directions[0, [a == "r_hip" and b == "l_hip" for a, b, _ in _DIRECTIONS].index(True)]
    S[27] = np.arctan2(-hip[2], hip[0])
    S[30:33] = tg.midhip[0] - 0.5 * (DEFAULT_REST_JOINTS[1] + DEFAULT_REST_JOINTS[2])
    return S


def _sequential(res, flat: np.ndarray, S_start: np.ndarray) -> np.ndarray:
    """Pass 1: every sample in turn, warm-started from the one before (the first from the rest pose, solved again
    from its own solution until the pull towards the start has no say)."""
    out = np.empty((flat.shape[0], NUM_POSE_PARAMS))
    S = S_start
    for _ in range(10):
        S_next = _lm(res, S[None], flat[:1], iters=60)[0]
        done = np.abs(S_next - S).max() < 1e-6
        S = S_next
        if done:
            break
    for i in range(flat.shape[0]):
        S = out[i] = _lm(res, S[None], flat[i:i + 1], iters=15)[0]
    return out


def _second_difference_gram(T: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """D^T D of the second difference over T samples, as its diagonals: [t, t], [t, t + 1], [t, t + 2] (each (T,))."""
    c = (1.0, -2.0, 1.0)
    d0, d1, d2 = np.zeros(T), np.zeros(T), np.zeros(T)
    for i in range(3):
        d0[i:T - 2 + i] += c[i] ** 2
    for i in range(2):
        d1[i:T - 2 + i] += c[i] * c[i + 1]
    d2[:T - 2] += c[0] * c[2]
    return d0, d1, d2


def _banded_system(JtJ: np.ndarray, gram, w2: np.ndarray, mu: float, held: np.ndarray) -> np.ndarray:
    """Upper banded form (u = 66) of blockdiag(JtJ) + D^T D kron diag(w2) + mu * diag, held variables decoupled."""
    T, n = JtJ.shape[0], NUM_POSE_PARAMS
    u = 2 * n
    ab = np.zeros((u + 1, T * n))
    cols = np.arange(T) * n
    for a in range(n):
        for b in range(a, n):
            ab[u + a - b, cols + b] = JtJ[:, a, b]
    for off, dk in enumerate(gram):
        ab[u - off * n, off * n:] += (dk[:T - off, None] * w2[None, :]).ravel()
    ab[u] += mu * (ab[u] + 1e-9)
    idx = np.flatnonzero(held.ravel())
    for k in range(1, u + 1):  # zero the held variables' rows and columns, keep them on the diagonal
        j = idx + k
        ab[u - k, j[j < T * n]] = 0.0
        j = idx[idx >= k]
        ab[u - k, j] = 0.0
    ab[u, idx] = 1.0
    return ab


def _smooth(res, S: np.ndarray, tgt: np.ndarray, dt: float, iters: int = 4, chunk: int = 500) -> np.ndarray:
    """Pass 2: all samples at once, the fit plus an acceleration penalty (a banded Gauss-Newton, within the limits).

    Warm-started samples still jump where the fit has near-equivalent poses (a hanging arm sits next to the
    shoulder's gimbal pole, a dancer's leg beyond its limits): up to 100 degrees of shoulder flexion and twist and
    80 m/s at the wrists from one millisecond to the next. Penalising ``_ACCEL_S2 * (second difference) / dt^2``
    spreads such a change over tens of milliseconds while human accelerations pass nearly untouched."""
    from scipy.linalg import solveh_banded

    lo, hi = pose_bounds()
    T, n = S.shape
    if T < 3:
        return S
    w2 = (_ACCEL_S2 * _ACCEL_SCALE / dt ** 2) ** 2
    gram = _second_difference_gram(T)

    def evaluate(S_):
        parts = [res(S_[a:a + chunk], tgt[a:a + chunk]) for a in range(0, T, chunk)]
        r = np.concatenate([p[0] for p in parts])
        J = np.concatenate([p[1] for p in parts])
        acc = S_[2:] - 2 * S_[1:-1] + S_[:-2]
        return r, J, float(np.sum(r * r) + np.sum(w2 * acc * acc))

    def smooth_gradient(S_):
        acc = S_[2:] - 2 * S_[1:-1] + S_[:-2]
        g = np.zeros_like(S_)
        g[:-2] += acc
        g[1:-1] -= 2 * acc
        g[2:] += acc
        return w2 * g

    r, J, cost = evaluate(S)
    mu = 1e-3
    for _ in range(iters):
        Jt = J.transpose(0, 2, 1)
        g = (Jt @ r[..., None])[..., 0] + smooth_gradient(S)
        held = ((S <= lo + 1e-12) & (g > 0)) | ((S >= hi - 1e-12) & (g < 0))
        step = solveh_banded(_banded_system(Jt @ J, gram, w2, mu, held), -np.where(held, 0.0, g).ravel())
        S_new = np.clip(S + step.reshape(T, n), lo, hi)
        r_new, J_new, cost_new = evaluate(S_new)
        if cost_new < cost:
            S, r, J, cost, mu = S_new, r_new, J_new, cost_new, mu * 0.3
        else:
            mu *= 10.0
    return S


def _body(template: Template | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rest joints and the sole landmarks' joints and offsets of a template (default skeleton for None)."""
    if template is None:
        rest = np.asarray(DEFAULT_REST_JOINTS)
        lj, lo = default_landmarks(rest)
    else:
        rest, lj, lo = template.rest_joints, template.landmark_joint, template.landmark_offset
    sole = [LANDMARK_INDEX[n] for n in _SOLE_LANDMARKS]
    return rest, lj[sole], lo[sole]


def _sole_height(S: np.ndarray, rest, lj, lo) -> np.ndarray:
    """Height (T,) of the lowest sole point of poses S (T, 33)."""
    return kinematics.landmark_positions(S, rest, lj, lo)[..., 1].min(axis=-1)


#: A sample counts as clipped when the joint limits cost its fit as much as a segment turned 2 degrees away from
#: the clip would (a straight knee that the fit would bend 1 degree backwards is a straight knee, not a clip).
CLIP_COST = np.radians(2.0) ** 2


def _clipped(gain: np.ndarray, held: np.ndarray) -> tuple[int, dict[str, int]]:
    """Samples clipped by the joint limits, and per joint angle in how many of them it was held at a bound."""
    clipped = (gain > CLIP_COST) & held.any(axis=1)
    per = {DOF_NAMES[k]: int(n) for k, n in enumerate(held[clipped].sum(axis=0)) if n}
    return int(clipped.sum()), dict(sorted(per.items(), key=lambda kv: -kv[1]))


def retarget(clip: BvhClip, t_s, template: Template | None = None, mapping_path: str | None = None) -> RetargetResult:
    """Poses S (T, 33) of the template's skeleton following ``clip`` at times t_s (seconds from the clip's frame 0,
    increasing); the first time is placed at the origin facing +z (see the module docstring)."""
    t0 = time.perf_counter()
    t = np.asarray(t_s, dtype=np.float64)
    if t.ndim != 1 or t.size == 0 or np.any(np.diff(t) < 0):
        raise ValueError(f"t_s: expected increasing times in seconds, got shape {t.shape}")
    derived: list[str] = []
    mapping = map_joints(clip, mapping_path, derived)
    rest, sole_j, sole_o = _body(template)
    leg_m = float(np.mean([np.linalg.norm(rest[JOINT_INDEX[f"{s}_knee"]] - rest[JOINT_INDEX[f"{s}_hip"]])
                           + np.linalg.norm(rest[JOINT_INDEX[f"{s}_ankle"]] - rest[JOINT_INDEX[f"{s}_knee"]])
                           for s in "lr"]))
    frame, info = _place(clip, mapping, leg_m, float(t[0]))
    targets = clip_targets(clip, mapping, frame, t, rest)
    res = _Residuals(rest, targets.direction_weight)
    flat = targets.flat()
    # Pass 1 at the clip's own frames in the played window, then linearly to the samples; pass 2 on the samples.
    ft = clip.frame_time_s
    native_t = np.arange(int(np.floor(t[0] / ft + 1e-9)), min(int(np.ceil(t[-1] / ft - 1e-9)), clip.n_frames - 1) + 1) * ft
    native = clip_targets(clip, mapping, frame, native_t, rest)
    S_native = _sequential(res, native.flat(), _initial_pose(native))
    S = np.stack([np.interp(t, native_t, S_native[:, k]) for k in range(NUM_POSE_PARAMS)], axis=1)
    if t.size >= 3:
        S = _smooth(res, S, flat, dt=float(np.median(np.diff(t))))
    gain, held = _limits(res, S, flat)
    # The floor: our soles touch y = 0 when the clip's feet are lowest in the whole file.
    floor_tg = clip_targets(clip, mapping, frame, np.array([info["floor_frame"] * clip.frame_time_s]), rest)
    S_floor = _sequential(res, floor_tg.flat(), _initial_pose(floor_tg))
    S[:, 31] -= float(_sole_height(S_floor, rest, sole_j, sole_o)[0])
    n_clipped, per_dof = _clipped(gain, held)
    info.update(from_neighbours=derived, samples=int(t.size), clipped_samples=n_clipped, clipped_dofs=per_dof, lowest_sole_m=float(_sole_height(S, rest, sole_j, sole_o).min()),
                retarget_s=time.perf_counter() - t0)
    return RetargetResult(poses=S, stats=info)


def clip_motion(name: str, template: Template | None, duration_s: float, start_s: float = 0.0,
                mapping_path: str | None = None, rate_hz: float = 1000.0) -> Callable[[np.ndarray], np.ndarray]:
    """Poses S (T, 33) at times t (seconds from the capture's start) of a BVH clip or shipped CMU clip (``name``),
    played from ``start_s`` into the clip; retargeted once on a grid at ``rate_hz``, linear in S between samples."""
    from eventcap.body.clips import clip_path

    try:
        path = clip_path(name)
    except FileNotFoundError as exc:
        raise BvhError(str(exc)) from None
    clip = read_bvh(path)
    if not (np.isfinite(start_s) and 0.0 <= start_s < clip.duration_s):
        raise BvhError(f"{path}: source.motion_start_s={start_s} lies outside the clip, which lasts "
                       f"{clip.duration_s:.3f} s ({clip.n_frames} frames at {clip.fps:.1f} fps)")
    if start_s + duration_s > clip.duration_s + 1e-9:
        raise BvhError(f"{path}: a capture of {duration_s} s from {start_s} s is longer than the clip "
                       f"({clip.duration_s:.3f} s, {clip.n_frames} frames at {clip.fps:.1f} fps): at most "
                       f"{clip.duration_s - start_s:.3f} s from there")
    n = int(np.ceil(duration_s * rate_hz - 1e-9)) + 1
    grid = np.minimum(np.arange(n) / rate_hz, duration_s)
    out = retarget(clip, start_s + grid, template=template, mapping_path=mapping_path)
    st = out.stats
    log.info("motion %s: %d frames at %.1f fps, units %s (leg %.2f units = %.3f m; scaled by %.4f to the template), "
             "up axis %s; played from %.3f s for %.3f s; joint rotations slerped and root linearly interpolated to "
             "%d samples at %.0f Hz, retargeted in %.2f s; joint limits clipped %d of %d samples (costing more than a 2-degree miss%s); "
             "lowest sole %.3f m",
             name, clip.n_frames, clip.fps, st["units"], st["leg_length_units"],
             st["leg_length_units"] * st["metres_per_unit"], st["scale"], st["up_axis"], start_s, duration_s,
             st["samples"], rate_hz, st["retarget_s"], st["clipped_samples"], st["samples"],
             ("; most: " + ", ".join(f"{k} {v}" for k, v in list(st["clipped_dofs"].items())[:4]))
             if st["clipped_dofs"] else "", st["lowest_sole_m"])
    S_grid = out.poses

    def poses(t_s: np.ndarray) -> np.ndarray:
        tt = np.clip(np.asarray(t_s, dtype=np.float64), 0.0, grid[-1])
        return np.stack([np.interp(tt, grid, S_grid[:, k]) for k in range(NUM_POSE_PARAMS)], axis=1)

    return poses
