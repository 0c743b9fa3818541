"""Body segments' masses and the inertia each joint angle turns, for a motion prior that lets light parts move fast.

The motion prior of the spline solve penalises each pose parameter's angular acceleration. With one weight for all,
the forearm (1.6% of the body's mass, a few cm from the elbow) is held back as hard as the trunk: a 3.5 Hz wave of
the elbow loses half its speed. Human movement is smooth in the torques that drive it, not in the angles (the
minimum torque-change model of Uno, Kawato and Suzuki, 1989), and a torque is the inertia a joint turns times its
angular acceleration. :func:`dof_inertia` gives that inertia per pose parameter at the rest pose, from segment mass
fractions and centres of mass of the anthropometric tables of de Leva (1996, adult male; the adjustments of
Zatsiorsky-Seluyanov's parameters) placed on the actor's own bones: point masses at the segments' centres plus a
thin rod's own inertia (m L² / 12) about each centre. No mesh is needed, so any template gets the same model.

Units: fractions of the body's mass times m² (multiply by the body's mass for kg m²).
"""

from __future__ import annotations

import numpy as np

from eventcap.body.skeleton import (
    DOF_JOINT,
    JOINT_INDEX,
    NUM_JOINTS,
    PARENTS,
    check_rest_joints,
)

#: (name, proximal joint, distal joint, mass fraction, centre of mass as a fraction of the way from proximal to
#: distal). de Leva (1996), male: the trunk in three parts, the head with the neck; the hand and the foot, whose
#: SMPL end joints are not de Leva's landmarks, get their centres halfway.
_SIDED = (
    ("upper_arm", "shoulder", "elbow", 0.0271, 0.5772),
    ("forearm", "elbow", "wrist", 0.0162, 0.4574),
    ("hand", "wrist", "hand", 0.0061, 0.5),
    ("thigh", "hip", "knee", 0.1416, 0.4095),
    ("shank", "knee", "ankle", 0.0433, 0.4459),
    ("foot", "ankle", "foot", 0.0137, 0.5),
)
_CENTRAL = (
    ("lower_trunk", "pelvis", "spine1", 0.1117, 0.5),
    ("middle_trunk", "spine1", "spine3", 0.1633, 0.5),
    ("upper_trunk", "spine3", "neck", 0.1596, 0.5),
    ("head_neck", "neck", "head", 0.0694, 1.0),
)
SEGMENTS: tuple[tuple[str, int, int, float, float], ...] = tuple(
    [(n, JOINT_INDEX[p], JOINT_INDEX[d], m, c) for n, p, d, m, c in _CENTRAL]
    + [(f"{s}_{n}", JOINT_INDEX[f"{s}_{p}"], JOINT_INDEX[f"{s}_{d}"], m, c) for s in ("l", "r")
       for n, p, d, m, c in _SIDED]
)
assert abs(sum(s[3] for s in SEGMENTS) - 1.0) < 1e-3


def _descendants() -> np.ndarray:
    """(24, 24) bool: [j, k] is True when joint k is j or lies below j in the kinematic tree."""
    below = np.eye(NUM_JOINTS, dtype=bool)
    for k in range(NUM_JOINTS):  # parents precede children
        p = PARENTS[k]
        while p >= 0:
            below[p, k] = True
            p = PARENTS[p]
    return below


_BELOW = _descendants()
_BELOW.setflags(write=False)


def joint_inertia(rest_joints: np.ndarray) -> np.ndarray:
    """(24,) the moment of inertia of the body below each joint about that joint, at the rest pose, in fractions
    of the body's mass times m²: Σ over the segments whose proximal joint is the joint or below it of
    m_s (|c_s - x_j|² + L_s² / 12) (a polar measure, the same for every axis through the joint)."""
    x = check_rest_joints(rest_joints)
    out = np.zeros(NUM_JOINTS)
    for _, p, d, m, c in SEGMENTS:
        centre = x[p] + c * (x[d] - x[p])
        length2 = float(np.sum((x[d] - x[p]) ** 2))
        holders = _BELOW[:, p]  # joints that turn this segment
        out[holders] += m * (np.sum((centre - x[holders]) ** 2, axis=1) + length2 / 12.0)
    return out


def dof_inertia(rest_joints: np.ndarray) -> np.ndarray:
    """(30,) the inertia each rotational pose parameter turns (:func:`joint_inertia` of its joint): the 27 joint
    angles, then the root's 3 rotations (the whole body about the pelvis). Fractions of the body's mass times m²."""
    I = joint_inertia(rest_joints)
    return np.concatenate([I[DOF_JOINT], np.full(3, I[0])])


__all__ = ["SEGMENTS", "dof_inertia", "joint_inertia"]
