"""Foreshortening (not in the paper): each bone's depth extent from its known length and its 2D projection.

A bone of length L whose ends the detector sees at the normalised image points n_i, n_j (rays (x, y, 1)) spans,
with its near end at depth z_i, a far end at one of two depths: |n_j z_j - n_i z_i| = L has the roots

    z_j = (n_i·n_j z_i ± sqrt((n_i·n_j)² z_i² - |n_j|² (|n_i|² z_i² - L²))) / |n_j|²

(Taylor, CVIU 2000: the bone's depth extent up to its sign). The 2D points are the detector's most accurate output
(~2 px); its 3D points are ~7 cm off in metric depth but far more often right about which end is nearer. So the
target of each bone's depth extent Δz = z_j - z_i is the root whose sign the 3D detection gives, its magnitude from
the template's bone length and the 2D points, its parent end's depth z_i from the current estimate; where the
discriminant is negative (the 2D points further apart than the bone can reach) the bone lies in the image plane's
direction (Δz at the double root). Each bone's weight is the product of its ends' confidences (2D and 3D), how
sure the sign is: 1 - exp(-(Δz_3D / σ)²) with σ = ``bones_sign_m``, unless both roots are within σ of each other
(then the sign hardly matters), and how well the 2D points tell the magnitude: |Δz| = sqrt(L² - l²) is steep where
the bone lies across the line of sight (l ≈ L), so a bone's 2D noise (``bones_2d_px``) spreads its target by
σ_Δz ≈ l σ_l / |Δz|, weighed 1 / (1 + (σ_Δz / σ)²): the cue speaks for bones that point towards or away from the
camera, where it is sharp, and is silent for bones across it.

:class:`BoneDepth` (``bones``): λ_bones Σ_d Σ_b w_db (Δz_b(S_d) - Δz*_db)² at the detection frames, Δz_b(S) the
camera-depth difference of the bone's ends (metres²). A weak prior, not a metric target: the targets move with
the estimate's depth (data of one solve, like E_cor's correspondences).
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from eventcap.body.kinematics import joint_positions
from eventcap.body.skeleton import JOINT_INDEX, LANDMARK_INDEX, NUM_POSE_PARAMS

from .detections import _MappedTerm, detections_missing
from .errors import EnergyError
from .factor import Factor, Linearization, Missing
from .settings import BonesNoise

_NP = NUM_POSE_PARAMS
#: Joint pairs at a distance the template fixes, both ends seen by the 2D detector (landmarks on the joints):
#: the limbs' bones and the pelvis's width (which way the hips face).
BONES = (("l_shoulder", "l_elbow"), ("l_elbow", "l_wrist"), ("r_shoulder", "r_elbow"), ("r_elbow", "r_wrist"),
         ("l_hip", "l_knee"), ("l_knee", "l_ankle"), ("r_hip", "r_knee"), ("r_knee", "r_ankle"), ("l_hip", "r_hip"))
_J = np.array([[JOINT_INDEX[a], JOINT_INDEX[b]] for a, b in BONES])
_L = np.array([[LANDMARK_INDEX[a], LANDMARK_INDEX[b]] for a, b in BONES])


def depth_extent_targets(n_i: np.ndarray, n_j: np.ndarray, z_i: np.ndarray, length: np.ndarray, dz_3d: np.ndarray,
                         sign_m: float, noise_2d: float) -> tuple[np.ndarray, np.ndarray]:
    """(Δz* (...,), confidence (...,)) of bones (module doc): n_i, n_j (..., 2) normalised image points of their
    ends, z_i (...,) the first end's depth, length (...,) the bone's length, dz_3d (...,) the 3D detection's depth
    extent (camera axes), sign_m the 3D detection's depth noise (σ), noise_2d the 2D points' noise (normalised
    image units). The confidence is the sign's times the magnitude's, 1 / (1 + (σ_Δz / sign_m)²), σ_Δz ≈ l σ_l / |Δz|
    the target's spread by the 2D noise (l the bone's extent across the line of sight, σ_l = noise_2d z_i): a bone
    nearly across the line of sight has a depth extent its 2D points cannot tell."""
    if not sign_m > 0:
        raise EnergyError(f"bones_sign_m: expected a depth > 0, got {sign_m!r}")
    a = np.concatenate([n_i, np.ones(n_i.shape[:-1] + (1,))], axis=-1)
    b = np.concatenate([n_j, np.ones(n_j.shape[:-1] + (1,))], axis=-1)
    ab, aa, bb = np.sum(a * b, -1), np.sum(a * a, -1), np.sum(b * b, -1)
    disc = (ab * z_i) ** 2 - bb * (aa * z_i ** 2 - length ** 2)
    root = np.sqrt(np.maximum(disc, 0.0))
    near, far = (ab * z_i - root) / bb - z_i, (ab * z_i + root) / bb - z_i  # Δz of the two roots, near <= far
    # the root on the 3D detection's side (which end is nearer); both on one side (a bone off the optical axis, seen
    # obliquely): the one nearer the detection's extent
    pick_far = np.where(np.sign(near) == np.sign(far), np.abs(far - dz_3d) < np.abs(near - dz_3d), dz_3d >= 0)
    dz = np.where(pick_far, far, near)
    spread = far - near  # the two roots' distance
    sure = np.where(spread < sign_m, 1.0, 1.0 - np.exp(-(dz_3d / sign_m) ** 2))
    across = np.sqrt(np.maximum(length ** 2 - dz ** 2, 0.0))
    sigma = across * noise_2d * z_i / np.maximum(np.abs(dz), 1e-3)
    return dz, sure / (1.0 + (sigma / sign_m) ** 2)


class BoneDepth(Factor):
    """λ_bones Σ_d Σ_b w_db (Δz_b(S_d) - Δz*_db)² at the detection frames (module doc), the targets from the
    detections and the current estimate's depths at each round. Exact Hessian (CasADi)."""

    name = "bones"
    needs = ("t_det_us", "detections")
    Config = None
    Noise = BonesNoise

    def __init__(self, config, template, camera, n):
        super().__init__(config, template, camera, n)
        self.sign_m = float(config.sign_m)
        self.noise_2d = float(config.noise_2d_px) / np.sqrt(camera.fx * camera.fy)
        rest = template.rest_joints
        self.length = np.linalg.norm(rest[_J[:, 1]] - rest[_J[:, 0]], axis=1)
        S = ca.SX.sym("S", _NP)
        target, w = ca.SX.sym("target", len(BONES)), ca.SX.sym("w", len(BONES))
        J = joint_positions(S, rest)
        r2 = ca.DM(camera.R[2]).T
        dz = ca.vertcat(*[ca.mtimes(J[int(j), :] - J[int(i), :], r2.T) for i, j in _J])
        e = ca.sum1(w * (dz - target) ** 2)
        self._fn = _MappedTerm("E_bones", e, S, [target, w], self.n) if self.n else None
        self.target = np.zeros((self.n, len(BONES)))
        self.w = np.zeros((self.n, len(BONES)))

    @classmethod
    def samples(cls, inputs, config) -> np.ndarray:
        t = inputs.t_det_us
        return np.zeros(0, dtype=np.int64) if t is None else t

    @classmethod
    def missing(cls, inputs, config) -> Missing | None:
        return (super().missing(inputs, config)
                or detections_missing(inputs, config, ("2D landmarks", "3D joints"), noise=False))

    def collect(self, inputs) -> None:
        super().collect(inputs)
        det = inputs.need("detections", "the bones term")
        if det.n != self.n:
            raise EnergyError(f"the bones term: expected {self.n} detection frames, got {det.n}")
        self.det = det

    def relinearize(self, estimate) -> None:
        det, cam = self.det, self.camera
        Jc = cam.to_camera(joint_positions(estimate.poses(self.t_us), self.template.rest_joints))  # (D, 24, 3)
        c2 = det.confidence_2d[:, _L]  # (D, B, 2)
        kp = np.where(c2[..., None] > 0, det.keypoints_2d[:, _L], 0.0)
        n = cam.undistort_points(kp)  # (D, B, 2, 2)
        d3 = np.nan_to_num(det.joints_3d[:, _J[:, 1]] - det.joints_3d[:, _J[:, 0]]) @ cam.R[2]
        target, sure = depth_extent_targets(n[:, :, 0], n[:, :, 1], Jc[:, _J[:, 0], 2],
                                            np.broadcast_to(self.length, d3.shape), d3, self.sign_m,
                                            self.noise_2d)
        c3 = det.confidence_3d[:, _J]
        self.target = target
        self.w = np.prod(c2, axis=-1) * np.prod(c3, axis=-1) * sure

    def linearize(self, S, aux, order):
        e, g, H = self._fn(S, [self.target.ravel(), self.w.ravel()], order)
        w = self.weight
        return Linearization(w * float(e.sum()), None if g is None else w * g, None if H is None else w * H)


__all__ = ["BONES", "BoneDepth", "BonesNoise", "depth_extent_targets"]
