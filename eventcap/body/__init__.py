"""The actor's body model: the shared skeleton, rigged templates, kinematics/skinning and synthetic motions.

Modules: ``skeleton`` (joints, DOFs, bounds, landmarks), ``template`` (the Template dataclass),
``kinematics`` (forward kinematics and skinning in numpy and CasADi), ``smpl`` / ``mesh`` (template loaders),
``procedural`` (a generated template), ``motions`` (simulated fast motions for the synthetic capture).
"""

from eventcap.body.skeleton import (
    DOF_NAMES,
    JOINT_NAMES,
    LANDMARK_NAMES,
    NUM_DOFS,
    NUM_POSE_PARAMS,
    PARENTS,
    THETA_LOWER,
    THETA_UPPER,
)
from eventcap.body.template import Template

__all__ = [
    "DOF_NAMES",
    "JOINT_NAMES",
    "LANDMARK_NAMES",
    "NUM_DOFS",
    "NUM_POSE_PARAMS",
    "PARENTS",
    "THETA_LOWER",
    "THETA_UPPER",
    "Template",
]
