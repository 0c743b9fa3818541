"""The fixed skeleton every body template shares: SMPL's 24 joints, 27 bounded joint angles, landmarks.

World frame (the same everywhere in eventcap; camera axes in eventcap/camera.py): right-handed, metres, y up. In
the rest pose the actor stands at the origin with the feet on y=0, faces +z, and the actor's left is +x. The rest
pose is a T-pose (arms horizontal along ±x) and all-zero parameters reproduce it exactly.

Pose vector ``S`` (33 values per frame, the paper's S = [θ, R, t]):

- ``S[0:27]``  θ, joint angles in radians, one per row of :data:`DOFS` (order of :data:`DOF_NAMES`);
- ``S[27:30]`` root rotation (yaw, pitch, roll) in radians, ``R_root = R_y(yaw) @ R_x(pitch) @ R_z(roll)``:
  yaw about the world vertical is applied last, so spins about y are a single smooth, unbounded angle;
  positive yaw turns the actor to its left (facing +z turns towards +x), positive pitch leans forward (head
  towards +z), positive roll leans to the actor's right (head towards -x). Singular only when lying flat.
- ``S[30:33]`` root translation in metres: the pelvis moves from its rest position by ``t``.

Joint angles. Every joint frame is aligned with the world axes in the rest pose; a DOF rotates its joint's
subtree about a fixed axis of that frame (i.e. expressed in the parent's posed frame) by the right-hand rule.
A joint with several DOFs composes them in table order: ``R_local = R(dof_1) @ R(dof_2) @ R(dof_3)``.
Right-side axes are the mirror images (pseudo-vectors: ``(ax, -ay, -az)``) of the left-side ones, so every
named DOF means the same anatomical motion on both sides, and swapping left/right values mirrors a pose.
Sign convention (positive direction) of each DOF kind:

==================  ==========================================================================
``*_hip_flex``      thigh swings forward/up (knee towards +z)
``*_hip_abd``       leg moves sideways away from the midline
``*_hip_rot``       internal rotation (toes turn towards the midline)
``*_knee_flex``     shank swings backward (ankle towards -z): flexion
``*_ankle_flex``    dorsiflexion (toes up)
``*_ankle_inv``     inversion (sole turns towards the midline)
``spine_flex``      forward bend (head towards +z)
``spine_lat``       side bend to the actor's left (head towards +x)
``spine_twist``     torso turns to the actor's left (chest towards +x)
``neck_flex``       nod forward (chin down)
``neck_twist``      head turns to the actor's left
``*_collar_elev``   shoulder shrug up
``*_shoulder_flex`` arm swings forward in the horizontal plane (towards +z)
``*_shoulder_elev`` arm rises (0 = horizontal T-pose, about -1.5 = hanging at the side)
``*_shoulder_twist`` internal rotation of the upper arm about its own axis
``*_elbow_flex``    forearm swings forward (towards +z in the T-pose): flexion
==================  ==========================================================================

Landmarks are the points 2D/3D detectors report: the OpenPose BODY_25 key points in BODY_25 order (whose
indices 15–18 are the four face landmarks of the paper: eyes and ears). Each landmark is a joint index plus an
offset in rest space, so it follows that joint rigidly.
"""

from __future__ import annotations

import numpy as np

#: SMPL's 24 joints in SMPL order.
JOINT_NAMES: tuple[str, ...] = (
    "pelvis",
    "l_hip",
    "r_hip",
    "spine1",
    "l_knee",
    "r_knee",
    "spine2",
    "l_ankle",
    "r_ankle",
    "spine3",
    "l_foot",
    "r_foot",
    "neck",
    "l_collar",
    "r_collar",
    "head",
    "l_shoulder",
    "r_shoulder",
    "l_elbow",
    "r_elbow",
    "l_wrist",
    "r_wrist",
    "l_hand",
    "r_hand",
)
NUM_JOINTS = 24
JOINT_INDEX: dict[str, int] = {name: i for i, name in enumerate(JOINT_NAMES)}

#: SMPL kinematic tree: parent index of every joint (pelvis, the root, has -1). Parents precede children.
PARENTS: np.ndarray = np.array(
    [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21], dtype=np.int64
)
PARENTS.setflags(write=False)


#: Joint index of each joint's mirror image (left <-> right).
def _swap_side(name: str) -> str:
    """'l_x' <-> 'r_x'; central names unchanged."""
    if name.startswith("l_"):
        return "r_" + name[2:]
    if name.startswith("r_"):
        return "l_" + name[2:]
    return name


MIRROR_JOINTS: np.ndarray = np.array([JOINT_INDEX[_swap_side(n)] for n in JOINT_NAMES], dtype=np.int64)
MIRROR_JOINTS.setflags(write=False)

NUM_DOFS = 27
NUM_POSE_PARAMS = 33
THETA_SLICE = slice(0, 27)
ROOT_ROTATION_SLICE = slice(27, 30)
ROOT_TRANSLATION_SLICE = slice(30, 33)
ROOT_ROTATION_NAMES: tuple[str, ...] = ("root_yaw", "root_pitch", "root_roll")
ROOT_TRANSLATION_NAMES: tuple[str, ...] = ("root_tx", "root_ty", "root_tz")

_X = (1.0, 0.0, 0.0)
_Y = (0.0, 1.0, 0.0)
_Z = (0.0, 0.0, 1.0)


def _neg(a):
    return tuple(-v for v in a)


def _mirror_axis(a):
    # Rotation axes are pseudo-vectors: reflecting x -> -x maps (ax, ay, az) to (ax, -ay, -az).
    return (a[0], -a[1], -a[2])


# Left-side (and central) definitions: (dof suffix, joint, axis of the left/central joint, lower, upper).
# Bounds are anatomically plausible ranges of motion for an adult, in radians.
_SIDED = {
    "hip": [("hip_flex", _neg(_X), -0.50, 2.10), ("hip_abd", _Z, -0.45, 1.00), ("hip_rot", _neg(_Y), -0.70, 0.70)],
    "knee": [("knee_flex", _X, -0.05, 2.40)],
    "ankle": [("ankle_flex", _neg(_X), -0.90, 0.45), ("ankle_inv", _neg(_Z), -0.35, 0.45)],
    "collar": [("collar_elev", _Z, -0.25, 0.45)],
    "shoulder": [
        ("shoulder_flex", _neg(_Y), -0.90, 2.30),
        ("shoulder_elev", _Z, -1.55, 1.50),
        ("shoulder_twist", _X, -1.60, 1.30),
    ],
    "elbow": [("elbow_flex", _neg(_Y), -0.05, 2.50)],
}
_CENTRAL = {
    "spine1": [("spine_flex", _X, -0.50, 1.20), ("spine_lat", _neg(_Z), -0.55, 0.55), ("spine_twist", _Y, -0.90, 0.90)],
    "neck": [("neck_flex", _X, -0.60, 0.80), ("neck_twist", _Y, -1.20, 1.20)],
}


def _build_dofs():
    rows = []
    for j, jname in enumerate(JOINT_NAMES):
        if jname in _CENTRAL:
            for name, axis, lo, hi in _CENTRAL[jname]:
                rows.append((name, j, axis, lo, hi))
        elif jname[:2] in ("l_", "r_") and jname[2:] in _SIDED:
            for suffix, axis, lo, hi in _SIDED[jname[2:]]:
                ax = axis if jname[0] == "l" else _mirror_axis(axis)
                rows.append((f"{jname[:2]}{suffix}", j, ax, lo, hi))
    return rows


_DOF_ROWS = _build_dofs()
assert len(_DOF_ROWS) == NUM_DOFS

#: Name of each of the 27 joint angles, in θ order (grouped by joint, joints in SMPL order).
DOF_NAMES: tuple[str, ...] = tuple(r[0] for r in _DOF_ROWS)
DOF_INDEX: dict[str, int] = {n: i for i, n in enumerate(DOF_NAMES)}
#: Joint each DOF rotates, (27,) int64.
DOF_JOINT: np.ndarray = np.array([r[1] for r in _DOF_ROWS], dtype=np.int64)
#: Unit rotation axis of each DOF in its joint's rest frame (= world axes at rest), (27, 3).
DOF_AXIS: np.ndarray = np.array([r[2] for r in _DOF_ROWS], dtype=np.float64) + 0.0  # no -0.0
#: Lower / upper joint-angle bounds θ_min, θ_max in radians, (27,).
THETA_LOWER: np.ndarray = np.array([r[3] for r in _DOF_ROWS], dtype=np.float64)
THETA_UPPER: np.ndarray = np.array([r[4] for r in _DOF_ROWS], dtype=np.float64)
for _a in (DOF_JOINT, DOF_AXIS, THETA_LOWER, THETA_UPPER):
    _a.setflags(write=False)

#: Per-DOF permutation and sign that mirror a pose left <-> right (see :func:`mirror_pose`).
_MIRROR_DOF = np.array([DOF_INDEX[_swap_side(n)] for n in DOF_NAMES], dtype=np.int64)
_MIRROR_DOF_SIGN = np.array(
    [1.0 if DOF_NAMES[i][:2] in ("l_", "r_") or abs(DOF_AXIS[i, 0]) == 1.0 else -1.0 for i in range(NUM_DOFS)]
)


def pose_bounds() -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper bounds of the full 33-vector S: θ bounds, ±inf for root rotation and translation."""
    lo = np.full(NUM_POSE_PARAMS, -np.inf)
    hi = np.full(NUM_POSE_PARAMS, np.inf)
    lo[THETA_SLICE] = THETA_LOWER
    hi[THETA_SLICE] = THETA_UPPER
    return lo, hi


def mirror_pose(S: np.ndarray) -> np.ndarray:
    """Mirror poses left <-> right about the x=0 plane; S (..., 33) -> (..., 33).

    Exact for a left/right-symmetric rest skeleton: swaps paired DOFs, negates the central DOFs about y/z
    axes, root yaw, root roll and root x translation.
    """
    S = np.asarray(S, dtype=np.float64)
    if S.shape[-1] != NUM_POSE_PARAMS:
        raise ValueError(f"mirror_pose: expected S of shape (..., 33), got {S.shape}")
    out = S.copy()
    out[..., THETA_SLICE] = S[..., THETA_SLICE][..., _MIRROR_DOF] * _MIRROR_DOF_SIGN
    out[..., 27] = -S[..., 27]
    out[..., 29] = -S[..., 29]
    out[..., 30] = -S[..., 30]
    return out


#: Default rest skeleton of an adult about 1.75 m tall, T-pose, feet on y=0, (24, 3) metres.
DEFAULT_REST_JOINTS: np.ndarray = np.array(
    [
        [0.00, 0.97, 0.00],  # pelvis
        [0.09, 0.90, 0.00],  # l_hip
        [-0.09, 0.90, 0.00],  # r_hip
        [0.00, 1.08, -0.02],  # spine1
        [0.10, 0.49, 0.01],  # l_knee
        [-0.10, 0.49, 0.01],  # r_knee
        [0.00, 1.20, -0.01],  # spine2
        [0.10, 0.08, -0.03],  # l_ankle
        [-0.10, 0.08, -0.03],  # r_ankle
        [0.00, 1.26, 0.00],  # spine3
        [0.11, 0.02, 0.10],  # l_foot (ball of the foot)
        [-0.11, 0.02, 0.10],  # r_foot
        [0.00, 1.48, -0.02],  # neck
        [0.07, 1.41, -0.01],  # l_collar
        [-0.07, 1.41, -0.01],  # r_collar
        [0.00, 1.56, 0.01],  # head
        [0.19, 1.42, -0.02],  # l_shoulder
        [-0.19, 1.42, -0.02],  # r_shoulder
        [0.46, 1.42, -0.03],  # l_elbow
        [-0.46, 1.42, -0.03],  # r_elbow
        [0.71, 1.42, -0.02],  # l_wrist
        [-0.71, 1.42, -0.02],  # r_wrist
        [0.80, 1.42, -0.02],  # l_hand
        [-0.80, 1.42, -0.02],  # r_hand
    ],
    dtype=np.float64,
)
DEFAULT_REST_JOINTS.setflags(write=False)
DEFAULT_HEIGHT_M = 1.75

#: Landmarks: OpenPose BODY_25 key points, in BODY_25 order.
LANDMARK_NAMES: tuple[str, ...] = (
    "nose",
    "neck",
    "r_shoulder",
    "r_elbow",
    "r_wrist",
    "l_shoulder",
    "l_elbow",
    "l_wrist",
    "mid_hip",
    "r_hip",
    "r_knee",
    "r_ankle",
    "l_hip",
    "l_knee",
    "l_ankle",
    "r_eye",
    "l_eye",
    "r_ear",
    "l_ear",
    "l_big_toe",
    "l_small_toe",
    "l_heel",
    "r_big_toe",
    "r_small_toe",
    "r_heel",
)
NUM_LANDMARKS = len(LANDMARK_NAMES)
LANDMARK_INDEX: dict[str, int] = {n: i for i, n in enumerate(LANDMARK_NAMES)}
#: Landmark index of each landmark's mirror image (left <-> right).
MIRROR_LANDMARKS: np.ndarray = np.array([LANDMARK_INDEX[_swap_side(n)] for n in LANDMARK_NAMES], dtype=np.int64)
MIRROR_LANDMARKS.setflags(write=False)
#: The paper's four face landmarks (Eq. 6), as indices into LANDMARK_NAMES.
FACE_LANDMARKS: tuple[int, ...] = tuple(LANDMARK_INDEX[n] for n in ("l_eye", "r_eye", "l_ear", "r_ear"))
#: Landmarks that sit exactly on a skeleton joint: landmark name -> joint name.
LANDMARK_ON_JOINT: dict[str, str] = {
    n: n
    for n in (
        "neck",
        "r_shoulder",
        "r_elbow",
        "r_wrist",
        "l_shoulder",
        "l_elbow",
        "l_wrist",
        "r_hip",
        "r_knee",
        "r_ankle",
        "l_hip",
        "l_knee",
        "l_ankle",
    )
}
#: Joint every landmark is attached to (rigidly follows), by name.
LANDMARK_PARENT: dict[str, str] = {
    **LANDMARK_ON_JOINT,
    "nose": "head",
    "mid_hip": "pelvis",
    "r_eye": "head",
    "l_eye": "head",
    "r_ear": "head",
    "l_ear": "head",
    "l_big_toe": "l_foot",
    "l_small_toe": "l_foot",
    "l_heel": "l_ankle",
    "r_big_toe": "r_foot",
    "r_small_toe": "r_foot",
    "r_heel": "r_ankle",
}
#: Joint index of every landmark, (L,) int64, shared by all templates.
LANDMARK_JOINT: np.ndarray = np.array([JOINT_INDEX[LANDMARK_PARENT[n]] for n in LANDMARK_NAMES], dtype=np.int64)
LANDMARK_JOINT.setflags(write=False)

# Offsets (metres, for the 1.75 m default skeleton) of the landmarks that are not joints, relative to their
# parent joint, for the left side; right side mirrored. Scaled by stature in default_landmarks().
_LEFT_OFFSETS = {
    "nose": (0.0, 0.06, 0.105),
    "l_eye": (0.032, 0.085, 0.085),
    "l_ear": (0.075, 0.065, -0.005),
    "l_big_toe": (-0.025, -0.01, 0.09),
    "l_small_toe": (0.035, -0.01, 0.055),
    "l_heel": (0.0, -0.07, -0.06),
}


def stature(rest_joints: np.ndarray) -> float:
    """Approximate standing height in metres of a rest skeleton (scaled from head-to-ankle distance)."""
    rest_joints = check_rest_joints(rest_joints)
    ref = DEFAULT_REST_JOINTS[JOINT_INDEX["head"], 1] - DEFAULT_REST_JOINTS[[7, 8], 1].mean()
    got = rest_joints[JOINT_INDEX["head"], 1] - rest_joints[[7, 8], 1].mean()
    return DEFAULT_HEIGHT_M * float(got / ref)


def default_landmarks(rest_joints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Landmark joints (L,) int64 and rest-space offsets (L, 3) metres for a rest skeleton without a mesh.

    Joint landmarks get zero offsets; mid_hip is the midpoint of the hips; face and foot landmarks use fixed
    offsets of an average adult scaled by the skeleton's stature. Templates with a mesh may replace the face
    and foot offsets with surface points.
    """
    rest_joints = check_rest_joints(rest_joints)
    scale = stature(rest_joints) / DEFAULT_HEIGHT_M
    offsets = np.zeros((NUM_LANDMARKS, 3))
    for i, name in enumerate(LANDMARK_NAMES):
        if name == "mid_hip":
            offsets[i] = 0.5 * (rest_joints[1] + rest_joints[2]) - rest_joints[0]
        elif name in _LEFT_OFFSETS:
            offsets[i] = np.asarray(_LEFT_OFFSETS[name]) * scale
        elif name.startswith("r_") and "l_" + name[2:] in _LEFT_OFFSETS:
            o = np.asarray(_LEFT_OFFSETS["l_" + name[2:]]) * scale
            offsets[i] = (-o[0], o[1], o[2])
    return LANDMARK_JOINT.copy(), offsets


def check_rest_joints(rest_joints) -> np.ndarray:
    """Return rest joints as a (24, 3) float64 array, or raise a ValueError naming the problem."""
    a = np.asarray(rest_joints, dtype=np.float64)
    if a.shape != (NUM_JOINTS, 3):
        raise ValueError(f"rest joints: expected shape (24, 3) in SMPL joint order, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError("rest joints: contain NaN or inf")
    return a


def bone_lengths(joints: np.ndarray) -> np.ndarray:
    """Length of the bone from each non-root joint to its parent; joints (..., 24, 3) -> (..., 23) metres."""
    joints = np.asarray(joints, dtype=np.float64)
    return np.linalg.norm(joints[..., 1:, :] - joints[..., PARENTS[1:], :], axis=-1)
