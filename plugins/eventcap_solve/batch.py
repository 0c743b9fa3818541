"""Hybrid pose batch optimisation (paper Sec. 3.2, Eq. 3-8): all skeleton poses S_0..S_N of a batch, jointly.

    min  λ_cor E_cor + λ_2D E_2D + λ_3D E_3D + λ_temp E_temp (+ λ_damp E_damp)   s.t.  θ_min <= θ_f <= θ_max  ∀f

solved with IPOPT (interior point, exact Hessian, MUMPS) through CasADi. A :class:`BatchProblem` is built once per
(template, camera, number of tracking frames) — ~0.4 s — and then solves every batch: the batch data are inputs of
the built problem, never part of its construction. :func:`solve_batch` runs one batch in any of the modes below.

Energies (sums, as in the paper):

- E_cor (Eq. 5): Σ τ ‖π(v_{i,h}(S_j)) - p_{j,h}‖² over correspondences (i, j = i±1, h) found by rasterising the
  current estimate (:mod:`.correspondences`). v_{i,h} is the surface point under p_{i,h} *in the pose S_i*, so
  π(v_{i,h}(S_i)) = p_{i,h} whatever S_i is, and the residual is evaluated as
  (π(v(S_j)) - π(v(S_i))) - (p_{j,h} - p_{i,h}) with v the point found at the current S_i (a rest point with
  blended skinning weights, posed by LBS): it couples S_i and S_j. Holding the point's frame-i side fixed instead
  (the literal reading with v frozen) anchors every frame to the estimate the points were found on: measured on
  synthetic fast motion, batch solves then stayed at the linear interpolation (error 9.7 mm → 9.7 mm), while the
  coupled form integrates the tracks' motion between the detections (→ 5.0 mm). The frozen form is kept as the
  ``per_frame`` baseline, where it is exactly what is wanted.
- E_2D (Eq. 6): Σ_f Σ_l c_{f,l} ‖π(L_l(S_f)) - P2D_{f,l}‖² over the BODY_25 landmarks (joints and the four face
  landmarks the paper adds, plus nose and feet), at frames 0 and N, weighted by the detector's confidence c.
  With ``robust_px`` > 0 (the stage's ``robust_2d_px``, default 2 px) each landmark's squared error e² is replaced
  by the Cauchy loss σ² log(1 + e²/σ²), σ = robust_px: quadratic for errors below σ, logarithmic for outliers and
  left/right flips, which a CNN makes (not in the paper). Measured on the default simulated detector (2 px noise,
  2% outliers, 2% flips), speed-2 motions, per-frame fits: mean error 70.5 / 69.4 / 50.5 mm (plain least squares,
  jumping_jack / dance_spin / karate_kick; single flipped frames reach 300 mm) → 40.8 / 36.8 / 36.7 mm.
- E_3D (Eq. 7): Σ_f Σ_l c_{f,l} ‖J_l(S_f) - (P3D_{f,l} + t'_f)‖² over the 24 joints at frames 0 and N; P3D is
  root-relative, t'_f an auxiliary translation per detection frame (the paper writes one t'; the root moves
  within a batch, so each detection frame gets its own).
- E_temp (Eq. 8): Σ_i Σ_l φ_{i,l} ‖J_l(S_i) - J_l(S_{i+1})‖², φ from :func:`.correspondences.temporal_indicator`:
  1 for joints whose body part has no correspondence — the paper's "non-moving body parts". With sparse tracks a
  part can lack correspondences and still move; holding it still then contradicts the detections (measured with
  exact detections and boundary=free: end-frame error 0.1 → 5 mm). So φ is also 0 for joints whose two end fits
  lie more than ``still_m`` (3 cm) apart; ``still_m=0`` is the literal indicator.
- E_damp (not in the paper): Σ_f ‖S_f - S_f^start‖² with λ_damp = 1e-3, a proximal pull towards the solve's start
  (rad and m alike). Without it the joint angles nothing observes in a frame (a straight arm's twist, parts
  without tracks) are flat directions: IPOPT crawled along them and hit 100+ iterations. Levenberg-Marquardt,
  the paper's solver, damps the same way. It is 1e-4 to 1e-5 of the data terms' curvature.

Units. 3D residuals are in metres. Image residuals (E_cor, E_2D) are divided by the focal length
f = sqrt(fx·fy) in pixels: focal-normalised image units (≈ radians; 1 px ≈ 5 mrad for the DAVIS240C). With them the
paper's weights balance sensibly: λ_2D = 200 makes a 1 px landmark error cost as much as a 7 cm 3D joint error
(λ_3D = 1), so the 3D detections fix depth and orientation while 2D detections fix the image position.
λ_cor defaults to 50, the paper's "λ_adj" (the only listed weight without a term of that name: the adjacent-frame
correspondence term). Defaults: :class:`EnergyWeights`.

How it is computed. E_2D, E_3D and E_damp are CasADi SX expressions built with the project's FK
(:mod:`eventcap.body.kinematics`, the same code as numpy), differentiated by CasADi. E_cor has thousands of
points, each blended from 24 joint transforms: a symbolic SX Hessian of it takes minutes to build and gigabytes of
memory (measured: 29 s build and 95 ms per Hessian with 20 points per frame; killed at 200). So E_cor and E_temp
are evaluated by numpy in :class:`_NumericEnergy`, exactly (value, gradient and exact Hessian, checked against
CasADi's AD in the tests): per frame, the 24 skinning transforms G(S) (96×3), their Jacobian and the contraction of
their second derivatives come from small CasADi functions (called through zero-copy buffers); per point, posed
position = WX·G and Jacobian = WX·∂G (one BLAS product per frame); projection derivatives in closed form. IPOPT
sees them through CasADi callbacks, plugged in as custom ``grad_f`` / ``hess_lag`` functions next to the SX terms.
E_cor's data (points, weights, pixels) are handed to the callbacks per solve rather than through the NLP's
parameter vector: ~300k numbers through CasADi's parameter conversion cost ~16 ms per call, several calls per
IPOPT iteration. Everything else (λ, detections, φ, E_damp's reference) is an NLP parameter.

Initialisation (paper): S_0 and S_N are fitted to E_2D + E_3D (a one-frame problem, built once as well). The fit
starts from a closed-form guess (T-pose with the root rotation from a Kabsch fit of the detected 3D torso, the
pelvis from a linear fit of the 2D rays) and first fits E_3D alone, then both: from a T-pose the projection term
has poor local minima (limbs swung to the wrong side; measured 50-150 mm errors with exact detections, 0.3 mm
staged). S_1..S_{N-1} are interpolated linearly in time, after unwrapping S_N's root angles to the nearest
2π-equivalent of S_0's. Then correspondence search and solve alternate (``icp_rounds``, as in ICP), each solve
warm-started from the previous estimate.

Batch boundaries. Neighbouring batches share an intensity frame. With ``boundary="fixed"`` (default) S_0 and S_N
keep their fits to the detections (a deterministic function of that frame's detections), so batch k's last pose
is batch k+1's first and the joined 1 kHz motion is continuous, while every batch still solves on its own (in
parallel, cached per batch). ``free`` lets the solve move them (the batches then disagree at the shared frame).

Correspondences near silhouette or self-occlusion edges of the current estimate (``edge_margin_px``, 1 px) are
left out: there a feature is on an occluding contour, not on one surface point, and the estimate's edge is off by
its own error. Measured: with EKLT tracks on fast synthetic motion, 0 → 1 → 2 px margin gave 5.2 → 4.0 → 3.2 mm;
with exact tracks on a 240×180 image, where limbs are a few pixels wide, 3.8 → 5.1 → 8.5 mm. 1 px is the default.

Modes (baselines of the paper's evaluation, from the same code):

- ``batch``: the method above.
- ``linear``: fit only S_0 and S_N to the detections, interpolate linearly (the paper's *_linear).
- ``per_frame`` (w/o_batch): every frame is fitted on its own — E_cor with the neighbours' side held where the
  points were found (Eq. 5 with v frozen), no E_temp; the detection terms stay at frames 0 and N. Nothing couples
  frames, so the joint solve is the independent per-frame solves, initialised by the linear interpolation.
- ``all``: fit every tracking frame to its own detections (E_2D + E_3D), each warm-started from the previous frame
  (the paper's *_all); needs detections at all N+1 frames.
- ``odometry`` (not in the paper; for the ``fuse`` stage, see fusion.py): the motion the events alone give from
  S_0's fit. The detection at frame N is switched off, every frame starts at S_0's fit, and E_temp holds every
  part without correspondences (the paper's literal φ), so nothing of frame N's detection enters. The result is
  shifted so that S_0 is exactly the fit.

Reproducibility: IPOPT options are pinned (:class:`IpoptSettings`: iteration limit, tolerances, barrier strategy,
MUMPS pivot order, no option file); the same inputs give bit-identical poses. Every solve's status is checked and
anything but success raises :class:`eventcap.stage.StageFailed` with IPOPT's status; unusable data (NaN/inf where
valid, bad confidences) raise it before IPOPT runs.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

import casadi as ca
import numpy as np

from eventcap.body.kinematics import global_transforms, joint_positions, landmark_positions
from eventcap.body.skeleton import (
    DOF_NAMES,
    JOINT_INDEX,
    LANDMARK_INDEX,
    LANDMARK_ON_JOINT,
    NUM_JOINTS,
    NUM_LANDMARKS,
    NUM_POSE_PARAMS,
    ROOT_ROTATION_NAMES,
    ROOT_TRANSLATION_NAMES,
    pose_bounds,
)
from eventcap.body.template import Template
from eventcap.camera import Camera
from eventcap.stage import StageFailed

from .correspondences import EDGE_MARGIN_PX, PHI_SCOPES, Correspondences, find_correspondences, temporal_indicator

MODES = ("batch", "per_frame", "linear", "all", "odometry")
#: How a batch treats its first and last frame (shared with the neighbouring batches): see solve_batch.
BOUNDARIES = ("fixed", "free")
#: Default of solve_batch's still_m: joints whose end fits moved more than this are not held still by E_temp.
STILL_M = 0.03
#: IPOPT return statuses accepted as success.
SUCCESS_STATUSES = ("Solve_Succeeded", "Solved_To_Acceptable_Level")
_NP = NUM_POSE_PARAMS
PARAM_NAMES = DOF_NAMES + ROOT_ROTATION_NAMES + ROOT_TRANSLATION_NAMES
#: Torso joints whose 3D detections fix the initial root rotation (rigid enough in any pose).
_TORSO = tuple(JOINT_INDEX[n] for n in ("pelvis", "l_hip", "r_hip", "spine1", "spine2", "spine3", "neck",
                                         "l_collar", "r_collar", "l_shoulder", "r_shoulder"))
#: (landmark index, joint index) pairs of landmarks that sit on a joint: the 2D/3D detections they share.
_ON_JOINT = tuple((LANDMARK_INDEX[lm], JOINT_INDEX[j]) for lm, j in LANDMARK_ON_JOINT.items())


# --------------------------------------------------------------------------------------------- settings and data
@dataclass(frozen=True)
class EnergyWeights:
    """λ of Eq. 4 (defaults: the paper's values; λ_cor is its λ_adj). Units: module doc."""

    cor: float = 50.0
    d2: float = 200.0
    d3: float = 1.0
    temp: float = 80.0
    damp: float = 1e-3  # E_damp, proximal term (not in the paper; module doc)

    def __post_init__(self) -> None:
        for name in ("cor", "d2", "d3", "temp", "damp"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"EnergyWeights.{name}: expected a finite number >= 0, got {v!r}")

    def as_array(self) -> np.ndarray:
        return np.array([self.cor, self.d2, self.d3, self.temp, self.damp], dtype=np.float64)


@dataclass(frozen=True)
class IpoptSettings:
    """IPOPT options that are pinned for speed and reproducibility (fixed when the problem is built).

    Batch solves start from good estimates (interpolation, previous ICP round): a monotone barrier starting at a
    tiny ``mu_init`` keeps IPOPT from first pushing the many joint angles that sit on their limits into the
    interior (measured on synthetic batches: 8-10 iterations per solve instead of 20-28 with the adaptive
    default). Detection fits start from a crude guess and use IPOPT's adaptive barrier.
    """

    max_iter: int = 100  # iteration limit per solve; reaching it is a failure
    tol: float = 1e-6  # IPOPT's (scaled) convergence tolerance
    acceptable_tol: float = 1e-4  # "solved to acceptable level" after acceptable_iter iterations below it
    acceptable_iter: int = 10
    mumps_pivot_order: int = 0  # AMD: pinned (MUMPS' automatic choice may differ between machines)
    mu_init: float = 1e-7  # initial barrier parameter of the (warm-started) batch solves
    bound_push: float = 1e-4  # how far batch solves move the warm start away from the bounds (relative)

    def __post_init__(self) -> None:
        if isinstance(self.max_iter, bool) or int(self.max_iter) != self.max_iter or self.max_iter < 0:
            raise ValueError(f"IpoptSettings.max_iter: expected an integer >= 0, got {self.max_iter!r}")
        for name in ("tol", "acceptable_tol", "mu_init", "bound_push"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"IpoptSettings.{name}: expected a number > 0, got {v!r}")
        if self.mumps_pivot_order not in range(8):
            raise ValueError(f"IpoptSettings.mumps_pivot_order: expected 0..7, got {self.mumps_pivot_order!r}")

    def options(self, warm: bool) -> dict:
        """nlpsol options; ``warm``: for the warm-started batch solves (else: the detection fits)."""
        opts = {
            "ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes",
            # An ipopt.opt in the working directory would silently override everything below.
            "ipopt.option_file_name": "",
            "ipopt.linear_solver": "mumps", "ipopt.hessian_approximation": "exact",
            "ipopt.mumps_pivot_order": int(self.mumps_pivot_order),
            "ipopt.max_iter": int(self.max_iter), "ipopt.tol": float(self.tol),
            "ipopt.acceptable_tol": float(self.acceptable_tol), "ipopt.acceptable_iter": int(self.acceptable_iter),
            "calc_lam_p": False, "no_nlp_grad": True, "error_on_fail": False,
        }
        if warm:
            opts.update({"ipopt.mu_strategy": "monotone", "ipopt.mu_init": float(self.mu_init),
                         "ipopt.bound_push": float(self.bound_push), "ipopt.bound_frac": float(self.bound_push)})
        return opts


@dataclass(frozen=True)
class FrameDetections:
    """Detections at D frames (2D landmarks in BODY_25 order, root-relative 3D joints in SMPL order).

    keypoints_2d (D, 25, 2) pixels; confidence_2d (D, 25) in [0, 1]; joints_3d (D, 24, 3) metres relative to the
    pelvis; confidence_3d (D, 24) in [0, 1]. Confidence 0 = not detected (the value is then ignored, NaN allowed).
    """

    keypoints_2d: np.ndarray
    confidence_2d: np.ndarray
    joints_3d: np.ndarray
    confidence_3d: np.ndarray

    def __post_init__(self) -> None:
        kp = np.asarray(self.keypoints_2d, dtype=np.float64)
        D = kp.shape[0] if kp.ndim == 3 else -1
        shapes = {"keypoints_2d": (D, NUM_LANDMARKS, 2), "confidence_2d": (D, NUM_LANDMARKS),
                  "joints_3d": (D, NUM_JOINTS, 3), "confidence_3d": (D, NUM_JOINTS)}
        for name, shape in shapes.items():
            a = np.asarray(getattr(self, name), dtype=np.float64)
            if a.shape != shape or D < 1:
                raise ValueError(f"FrameDetections.{name}: expected shape {shape} (D frames, BODY_25 landmarks, "
                                 f"SMPL joints), got {a.shape}")
            object.__setattr__(self, name, a)

    @property
    def n(self) -> int:
        return int(self.keypoints_2d.shape[0])

    def rows(self, idx) -> FrameDetections:
        idx = np.atleast_1d(np.asarray(idx))
        return FrameDetections(self.keypoints_2d[idx], self.confidence_2d[idx], self.joints_3d[idx],
                               self.confidence_3d[idx])

    def problems(self) -> list[str]:
        """What makes these detections unusable (non-finite values where confidence > 0, bad confidences)."""
        out = []
        for name, cname in (("keypoints_2d", "confidence_2d"), ("joints_3d", "confidence_3d")):
            c = getattr(self, cname)
            if not np.all(np.isfinite(c)) or c.min() < 0 or c.max() > 1:
                out.append(f"{cname} must be finite values in [0, 1]")
                continue
            bad = (c > 0) & ~np.all(np.isfinite(getattr(self, name)), axis=-1)
            if bad.any():
                d, k = (int(v[0]) for v in np.nonzero(bad))
                out.append(f"{name} is not finite at detection frame {d}, entry {k} (confidence {c[d, k]:.2f})")
        return out


def select_detections(detections, times_us) -> FrameDetections:
    """Rows of a Detections artifact at the given times (exact match), as FrameDetections; ValueError if missing."""
    t = np.asarray(detections.t_us, dtype=np.int64)
    want = np.asarray(times_us, dtype=np.int64).ravel()
    idx = np.searchsorted(t, want)
    ok = (idx < t.size) & (t[np.minimum(idx, max(t.size - 1, 0))] == want) if t.size else np.zeros(want.size, bool)
    if not ok.all():
        missing = want[~ok]
        raise ValueError(f"detections: no detection row at t = {missing[:5].tolist()} us "
                         f"({missing.size} of {want.size} times missing; detections cover {t.size} frames)")
    return FrameDetections(detections.keypoints_2d[idx], detections.confidence_2d[idx], detections.joints_3d[idx],
                           detections.confidence_3d[idx])


@dataclass(frozen=True)
class SolveStats:
    """One IPOPT solve."""

    status: str
    iterations: int
    seconds: float
    n_correspondences: int = 0


@dataclass(frozen=True)
class BatchResult:
    """Poses of a batch and how they were obtained."""

    poses: np.ndarray  #: (N+1, 33) S_0..S_N
    t_prime: np.ndarray  #: (2, 3) metres, t' of E_3D at frames 0 and N (fits for linear/all)
    status: str  #: status of the last solve
    iterations: int  #: IPOPT iterations summed over all solves of the batch
    energies: dict  #: unweighted value of each term at the result (and the weighted total)
    solves: tuple[SolveStats, ...] = ()
    seconds: dict = field(default_factory=dict)  #: wall time per phase


# --------------------------------------------------------------------------------------------- projection (numpy)
def project_derivatives(camera: Camera, points: np.ndarray, order: int = 2):
    """Camera projection of world points with its derivatives, numpy, in closed form (same model as
    :meth:`Camera.project`: pinhole + OpenCV distortion).

    points (P, 3) metres. Returns pixels (P, 2); with order >= 1 also the Jacobian (P, 2, 3) px/m; with order 2
    also the Hessian (P, 2, 3, 3). Points must be in front of the camera.
    """
    p = np.asarray(points, dtype=np.float64)
    c = p @ camera.R.T + camera.t
    iz = 1.0 / c[:, 2]
    x, y = c[:, 0] * iz, c[:, 1] * iz
    k1, k2, p1, p2, k3 = camera.dist
    r2 = x * x + y * y
    rad = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * rad + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * rad + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    uv = np.stack([camera.fx * xd + camera.cx, camera.fy * yd + camera.cy], axis=1)
    if order == 0:
        return uv
    n = p.shape[0]
    drad = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d rad / d r2
    Dd = np.empty((n, 2, 2))  # d (xd, yd) / d (x, y)
    Dd[:, 0, 0] = rad + 2.0 * x * x * drad + 2.0 * p1 * y + 6.0 * p2 * x
    Dd[:, 0, 1] = 2.0 * x * y * drad + 2.0 * p1 * x + 2.0 * p2 * y
    Dd[:, 1, 0] = Dd[:, 0, 1]
    Dd[:, 1, 1] = rad + 2.0 * y * y * drad + 6.0 * p1 * y + 2.0 * p2 * x
    Dn = np.zeros((n, 2, 3))  # d (x, y) / d camera coordinates
    Dn[:, 0, 0] = iz
    Dn[:, 0, 2] = -x * iz
    Dn[:, 1, 1] = iz
    Dn[:, 1, 2] = -y * iz
    f = np.array([camera.fx, camera.fy])
    FDd = f[None, :, None] * Dd
    J = np.matmul(FDd, Dn) @ camera.R
    if order == 1:
        return uv, J
    d2rad = 2.0 * k2 + 6.0 * k3 * r2
    # Second derivatives of xd (a = 0) and yd (a = 1) w.r.t. (x, y).
    xd_xx = 6.0 * x * drad + 4.0 * x**3 * d2rad + 6.0 * p2
    xd_xy = yd_xx = 2.0 * y * drad + 4.0 * x * x * y * d2rad + 2.0 * p1
    xd_yy = yd_xy = 2.0 * x * drad + 4.0 * x * y * y * d2rad + 2.0 * p2
    yd_yy = 6.0 * y * drad + 4.0 * y**3 * d2rad + 6.0 * p1
    Hd = np.stack([np.stack([xd_xx, xd_xy, xd_xy, xd_yy], axis=1), np.stack([yd_xx, yd_xy, yd_xy, yd_yy], axis=1)],
                  axis=1).reshape(n, 2, 2, 2)
    # Second derivatives of x = cx/cz and y = cy/cz w.r.t. camera coordinates: only the z row/column.
    iz2 = iz * iz
    Hn = np.zeros((n, 2, 3, 3))
    Hn[:, 0, 0, 2] = Hn[:, 0, 2, 0] = -iz2
    Hn[:, 0, 2, 2] = 2.0 * x * iz2
    Hn[:, 1, 1, 2] = Hn[:, 1, 2, 1] = -iz2
    Hn[:, 1, 2, 2] = 2.0 * y * iz2
    DnT = np.swapaxes(Dn, 1, 2)
    H_cam = np.empty((n, 2, 3, 3))
    for a in range(2):
        H_cam[:, a] = (FDd[:, a, 0, None, None] * Hn[:, 0] + FDd[:, a, 1, None, None] * Hn[:, 1]
                       + f[a] * np.matmul(np.matmul(DnT, Hd[:, a]), Dn))
    H = np.matmul(np.matmul(camera.R.T, H_cam), camera.R)
    return uv, J, H


# --------------------------------------------------------------------------------------------- FK kernels
class Buffered:
    """A CasADi function evaluated on numpy arrays through its zero-copy buffer (no DM conversion per call)."""

    def __init__(self, fn: ca.Function):
        self.fn = fn
        self.args = [np.zeros(fn.sparsity_in(i).nnz()) for i in range(fn.n_in())]
        self.res = [np.zeros(fn.sparsity_out(i).nnz()) for i in range(fn.n_out())]
        self._buf, self._eval = fn.buffer()
        for i, a in enumerate(self.args):
            self._buf.set_arg(i, memoryview(a))
        for i, r in enumerate(self.res):
            self._buf.set_res(i, memoryview(r))

    def __call__(self, *args: np.ndarray) -> list[np.ndarray]:
        for dst, src in zip(self.args, args):
            dst[:] = np.asarray(src, dtype=np.float64).ravel()
        self._eval()
        if self._buf.ret() != 0:
            raise FloatingPointError(f"CasADi function {self.fn.name()} failed to evaluate")
        return [r.copy() for r in self.res]


class SkinningKernels:
    """Per frame, the 24 skinning transforms as a (96, 3) matrix G with posed point = WX · G (WX the premultiplied
    weights of a point, see :func:`premultiplied_weights`), their Jacobian and contracted second derivatives.

    All mapped over the F frames of a batch (one call each). Layouts (numpy, C order):
    ``G (F, 96, 3)``, ``dG (F, 96, 3, 33)``, ``hess (F, 33, 33)`` of Σ_{a,c} Λ[f, a, c] G[f, a, c].
    """

    def __init__(self, rest_joints: np.ndarray, n_frames: int):
        S = ca.SX.sym("S", _NP)
        T = global_transforms(S, rest_joints)
        G = ca.vertcat(*[T[j][:3, :].T for j in range(NUM_JOINTS)])  # (96, 3): [R^T; b^T] per joint
        g = ca.vec(G.T)  # index a*3 + c
        dg = ca.densify(ca.jacobian(g, S).T)  # (33, 288): column-major gives (a, c, s) C order
        lam = ca.SX.sym("lam", 3, 4 * NUM_JOINTS)
        hess = ca.densify(ca.hessian(ca.dot(ca.vec(lam), g), S)[0])
        self.F = n_frames
        self._g = Buffered(ca.Function("skin_G", [S], [g]).map(n_frames))
        self._dg = Buffered(ca.Function("skin_dG", [S], [g, dg]).map(n_frames))
        self._h = Buffered(ca.Function("skin_d2G", [S, lam], [hess]).map(n_frames))

    def transforms(self, S: np.ndarray) -> np.ndarray:
        return self._g(S)[0].reshape(self.F, 4 * NUM_JOINTS, 3)

    def transforms_jac(self, S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        g, dg = self._dg(S)
        return g.reshape(self.F, 4 * NUM_JOINTS, 3), dg.reshape(self.F, 4 * NUM_JOINTS, 3, _NP)

    def contracted_hessian(self, S: np.ndarray, lam: np.ndarray) -> np.ndarray:
        return self._h(S, lam)[0].reshape(self.F, _NP, _NP)


def premultiplied_weights(rest_points: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(P, 96) products w_pj · [x_p, 1]_k at index 4j + k: posed points are ``WX @ G`` for the G above."""
    X = np.concatenate([rest_points, np.ones((rest_points.shape[0], 1))], axis=1)
    return (weights[:, :, None] * X[:, None, :]).reshape(rest_points.shape[0], 4 * NUM_JOINTS)


# --------------------------------------------------------------------------------------------- E_cor (numpy)
class _NumericEnergy:
    """λ_cor E_cor + λ_temp E_temp as functions of the poses S (F, 33): value, gradient and exact Hessian.

    E_cor = Σ_c w_c ‖(π(v_c(S_j)) - π(v_c(S_i)) - (p_{j,h} - p_{i,h})) / f‖² over correspondences c = (i, j, h),
    v_c(S) = WX_c · G(S) (data: :meth:`set_correspondences`). This is Eq. 5 with the surface point v_{i,h} tied to
    the pose S_i it was found with (π(v_{i,h}(S_i)) = p_{i,h} by construction; module doc).
    E_temp = Σ_i Σ_l φ_{i,l} ‖J_l(S_i) - J_l(S_{i+1})‖², with joint positions J_l = WXJ_l · G (linear in G too).
    Both go through the same per-frame skinning transforms G(S), their Jacobian and one contraction of their
    second derivatives. Both couple only neighbouring frames: the Hessian is block-tridiagonal.
    """

    def __init__(self, camera: Camera, kernels: SkinningKernels, rest_joints: np.ndarray):
        self.camera = camera
        self.kernels = kernels
        self.F = kernels.F
        self.scale = 1.0 / math.sqrt(camera.fx * camera.fy)
        self.WXJ = premultiplied_weights(rest_joints, np.eye(NUM_JOINTS))  # (24, 96): J_l = WXJ_l · G
        self.set_correspondences(Correspondences.empty())

    def set_correspondences(self, corr: Correspondences, relative: bool = True, point_weight=None) -> None:
        """Load E_cor's data. Point instances: each correspondence's point at its frame j, and each distinct
        source point (i, h) once at its frame i; they are sorted by frame for one matrix product per frame.

        relative=False: the source side is held at where it was found (π(v(S_i)) = p_{i,h}), so each residual
        depends on S_j alone — every frame is fitted on its own to its neighbours' points (the w/o_batch mode).
        """
        self.relative = bool(relative)
        P = corr.n
        j, i = corr.frame, corr.source
        if P and (min(j.min(), i.min()) < 0 or max(j.max(), i.max()) >= self.F):
            raise ValueError(f"correspondence frames must lie in [0, {self.F}), got [{min(j.min(), i.min())}, "
                             f"{max(j.max(), i.max())}]")
        WX = premultiplied_weights(corr.rest_points, corr.weights)
        key = i * (int(corr.track.max()) + 1 if P else 1) + corr.track
        _, first, src_of = np.unique(key, return_index=True, return_inverse=True)
        if not self.relative:
            first, src_of = first[:0], src_of[:0]
        inst_frame = np.concatenate([j, i[first]])
        order = np.argsort(inst_frame, kind="stable")
        rank = np.empty_like(order)
        rank[order] = np.arange(order.size)
        self.frame = inst_frame[order]
        self.WX = np.concatenate([WX, WX[first]])[order]
        self.t_idx = rank[:P]  # instance of each correspondence's point at frame j
        self.s_idx = rank[P + src_of.ravel()]  # ... and at its source frame i (relative form only)
        self.dq = corr.target_px - corr.source_px  # the track's displacement p_j - p_i
        self.target = corr.target_px
        self.w = np.ones(P) if point_weight is None else np.asarray(point_weight, np.float64)
        self.P = P
        bounds = np.searchsorted(self.frame, np.arange(self.F + 1))
        self.slices = [(f, slice(bounds[f], bounds[f + 1])) for f in range(self.F) if bounds[f + 1] > bounds[f]]
        # Cross-frame Hessian blocks (k, k+1): the instance at the lower and at the higher frame of each pair.
        if self.relative:
            low_first = i < j
            self.lo = np.where(low_first, self.s_idx, self.t_idx)
            self.hi = np.where(low_first, self.t_idx, self.s_idx)
            pair = np.minimum(i, j)
        else:
            self.lo = self.hi = pair = np.zeros(0, np.int64)
        porder = np.argsort(pair, kind="stable")
        self.pair_order = porder
        pb = np.searchsorted(pair[porder], np.arange(self.F))
        self.pair_slices = [(k, slice(pb[k], pb[k + 1])) for k in range(self.F - 1) if pb[k + 1] > pb[k]]
        self._cache = {}

    @property
    def n(self) -> int:
        """Number of correspondences."""
        return self.P

    # -------------------------------------------------------------- pieces
    def _points(self, G: np.ndarray) -> np.ndarray:
        pts = np.empty((self.frame.size, 3))
        for f, sl in self.slices:
            pts[sl] = self.WX[sl] @ G[f]
        return pts

    def _values(self, S: np.ndarray, phi: np.ndarray, G: np.ndarray):
        """E_cor, E_temp, normalised residuals r (P, 2), joint differences d (F-1, 24, 3), instance points."""
        pts = self._points(G)
        uv = project_derivatives(self.camera, pts, 0)
        if self.relative:
            r = (uv[self.t_idx] - uv[self.s_idx] - self.dq) * self.scale
        else:
            r = (uv[self.t_idx] - self.target) * self.scale
        e_cor = float(np.sum(self.w * np.sum(r * r, axis=1)))
        J = self.WXJ @ G  # (F, 24, 3)
        d = J[:-1] - J[1:]
        e_temp = float(np.sum(phi * np.sum(d * d, axis=2)))
        return e_cor, e_temp, r, d, pts

    def terms(self, S: np.ndarray, phi: np.ndarray) -> tuple[float, float]:
        """Unweighted (E_cor, E_temp)."""
        return self._values(S, phi, self.kernels.transforms(S))[:2]

    def _first_order(self, S, phi, lam):
        key = (S.tobytes(), phi.tobytes(), lam.tobytes())
        if self._cache.get("key") != key:
            G, dG = self.kernels.transforms_jac(S)
            e_cor, e_temp, r, d, pts = self._values(S, phi, G)
            dGm = dG.reshape(self.F, 4 * NUM_JOINTS, 3 * _NP)
            # E_cor: gradient w.r.t. each instance point (u), and d(point)/dS (J3).
            _, Jp = project_derivatives(self.camera, pts, 1)
            Jp *= self.scale
            wr = (2.0 * lam[0]) * self.w[:, None] * r  # (P, 2)
            u = np.zeros((pts.shape[0], 3))
            u[self.t_idx] += np.matmul(wr[:, None, :], Jp[self.t_idx])[:, 0, :]
            if self.relative:
                np.add.at(u, self.s_idx, -np.matmul(wr[:, None, :], Jp[self.s_idx])[:, 0, :])
            J3 = np.empty((pts.shape[0], 3, _NP))
            for f, sl in self.slices:
                J3[sl] = (self.WX[sl] @ dGm[f]).reshape(-1, 3, _NP)
            # E_temp: gradient w.r.t. each joint position, and d(joint)/dS.
            pd = (2.0 * lam[1]) * phi[:, :, None] * d  # (F-1, 24, 3)
            uJ = np.zeros((self.F, NUM_JOINTS, 3))
            uJ[:-1] += pd
            uJ[1:] -= pd
            JJ = (self.WXJ @ dGm).reshape(self.F, NUM_JOINTS, 3, _NP)
            g = np.matmul(uJ.reshape(self.F, 1, -1), JJ.reshape(self.F, -1, _NP))[:, 0, :]
            for f, sl in self.slices:
                g[f] += u[sl].reshape(-1) @ J3[sl].reshape(-1, _NP)
            value = lam[0] * e_cor + lam[1] * e_temp
            self._cache = {"key": key, "value": value, "g": g, "pts": pts, "r": r, "u": u, "J3": J3, "JJ": JJ,
                           "uJ": uJ, "Jp": Jp}
        return self._cache

    # -------------------------------------------------------------- what IPOPT calls
    def value(self, S, phi, lam) -> float:
        c = self._cache
        if c.get("key") == (S.tobytes(), phi.tobytes(), lam.tobytes()):
            return c["value"]
        e_cor, e_temp = self._values(S, phi, self.kernels.transforms(S))[:2]
        return float(lam[0] * e_cor + lam[1] * e_temp)

    def gradient(self, S, phi, lam) -> tuple[float, np.ndarray]:
        c = self._first_order(S, phi, lam)
        return c["value"], c["g"]

    def hessian(self, S, phi, lam) -> tuple[np.ndarray, np.ndarray]:
        """Exact Hessian as diagonal blocks (F, 33, 33) and super-diagonal blocks (F-1, 33, 33) [(i, i+1)]."""
        c = self._first_order(S, phi, lam)
        F1 = self.F - 1
        diag = np.zeros((self.F, _NP, _NP))
        upper = np.zeros((F1, _NP, _NP))
        lamG = np.zeros((self.F, 4 * NUM_JOINTS, 3))  # Λ: gradient w.r.t. G, contracted with ∂²G below
        if self.P:
            _, _, Hp = project_derivatives(self.camera, c["pts"], 2)
            Hp *= self.scale
            Jp, r, J3, u = c["Jp"], c["r"], c["J3"], c["u"]
            wr = (2.0 * lam[0]) * self.w[:, None] * r
            w2 = (2.0 * lam[0]) * self.w[:, None, None]
            t, s_ = self.t_idx, self.s_idx
            # Point-space Hessian per instance: 2λw (JᵀJ ± Σ_a r_a H_a) (+ at frame j, - at frame i).
            Jt, Js = Jp[t], Jp[s_]
            Bp = np.zeros((Jp.shape[0], 3, 3))
            Bp[t] += w2 * np.matmul(np.swapaxes(Jt, 1, 2), Jt) + wr[:, 0, None, None] * Hp[t, 0] \
                + wr[:, 1, None, None] * Hp[t, 1]
            if self.relative:
                np.add.at(Bp, s_, w2 * np.matmul(np.swapaxes(Js, 1, 2), Js) - wr[:, 0, None, None] * Hp[s_, 0]
                          - wr[:, 1, None, None] * Hp[s_, 1])
            for f, sl in self.slices:
                Jf = J3[sl]
                diag[f] = Jf.reshape(-1, _NP).T @ np.matmul(Bp[sl], Jf).reshape(-1, _NP)
                lamG[f] = self.WX[sl].T @ u[sl]
            # Cross-frame blocks: d²/dp_lo dp_hi of w‖r‖² = -2w J_loᵀ J_hi (r is a difference of the two).
            lo, hi = self.lo[self.pair_order], self.hi[self.pair_order]
            C = -w2[self.pair_order] * np.matmul(np.swapaxes(Jp[lo], 1, 2), Jp[hi])
            R = np.matmul(C, J3[hi])
            L = J3[lo]
            for k, sl in self.pair_slices:
                upper[k] = L[sl].reshape(-1, _NP).T @ R[sl].reshape(-1, _NP)
        # E_temp (its residuals are linear in the joint positions).
        JJ = c["JJ"]
        w2t = (2.0 * lam[1]) * phi  # (F-1, 24)
        A, Bn = JJ[:-1], JJ[1:]  # d(J_l(S_i))/dS_i and d(J_l(S_{i+1}))/dS_{i+1}
        Aw = (A * w2t[:, :, None, None]).reshape(F1, -1, _NP)
        Bw = (Bn * w2t[:, :, None, None]).reshape(F1, -1, _NP)
        A, Bn = A.reshape(F1, -1, _NP), Bn.reshape(F1, -1, _NP)
        AwT = np.swapaxes(Aw, 1, 2)
        diag[:-1] += AwT @ A
        diag[1:] += np.swapaxes(Bw, 1, 2) @ Bn
        upper -= AwT @ Bn
        lamG += self.WXJ.T @ c["uJ"]
        diag += self.kernels.contracted_hessian(S, lamG)
        return diag, upper


class NumpyCallback(ca.Callback):
    """A CasADi function of one dense vector evaluated by numpy (IPOPT calls it through CasADi).

    Inputs and outputs are exchanged through CasADi's buffers (no DM conversion: ~3 ms per Hessian saved).
    ``fn(v)`` returns one array per output: its nonzeros in CasADi's (column-major) order.
    """

    def __init__(self, name: str, n_in: int, sparsity_out: list, fn):
        ca.Callback.__init__(self)
        self._n_in, self._sp_out, self._fn = n_in, sparsity_out, fn
        self.construct(name, {})

    def get_n_in(self):
        return 1

    def get_n_out(self):
        return len(self._sp_out)

    def get_sparsity_in(self, i):
        return ca.Sparsity.dense(self._n_in, 1)

    def get_sparsity_out(self, i):
        return self._sp_out[i]

    def has_eval_buffer(self):
        return True

    def eval_buffer(self, arg, res):
        outs = self._fn(np.frombuffer(arg[0], dtype=np.float64))
        for r, o in zip(res, outs):
            np.frombuffer(r, dtype=np.float64)[:] = o
        return 0


def _block_tridiagonal_triu(n_blocks: int, size: int):
    """Sparsity of the upper triangle of a block-tridiagonal matrix, and how to fill it from numpy blocks.

    Returns (sparsity, (diag_index, upper_index, order)): with ``v = concat(diag[diag_index], upper[upper_index])``
    for diag (B, size, size) and upper (B-1, size, size) [block (i, i+1)], ``v[order]`` are the nonzeros in
    CasADi's (column-major) order.
    """
    rows, cols, src = [], [], []
    n_diag = 0
    diag_idx = ([], [], [])
    up_idx = ([], [], [])
    for b in range(n_blocks):
        for c in range(size):
            for r in range(c + 1):
                rows.append(b * size + r), cols.append(b * size + c), src.append(n_diag)
                diag_idx[0].append(b), diag_idx[1].append(r), diag_idx[2].append(c)
                n_diag += 1
    n_up = 0
    for b in range(n_blocks - 1):
        for c in range(size):
            for r in range(size):
                rows.append(b * size + r), cols.append((b + 1) * size + c), src.append(-1 - n_up)
                up_idx[0].append(b), up_idx[1].append(r), up_idx[2].append(c)
                n_up += 1
    rows, cols, src = np.array(rows), np.array(cols), np.array(src)
    src = np.where(src >= 0, src, n_diag - 1 - src)
    order = np.lexsort((rows, cols))  # column-major: by column, then row
    sp = ca.Sparsity.triplet(n_blocks * size, n_blocks * size, rows[order].tolist(), cols[order].tolist())
    return sp, (tuple(np.array(i) for i in diag_idx), tuple(np.array(i) for i in up_idx), src[order])


# --------------------------------------------------------------------------------------------- closed-form guess
def _euler_from_matrix(R: np.ndarray) -> np.ndarray:
    """(yaw, pitch, roll) with R = R_y(yaw) R_x(pitch) R_z(roll) (skeleton convention)."""
    pitch = math.asin(float(np.clip(-R[1, 2], -1.0, 1.0)))
    yaw = math.atan2(R[0, 2], R[2, 2])
    roll = math.atan2(R[1, 0], R[1, 1])
    return np.array([yaw, pitch, roll])


def initial_guess(template: Template, camera: Camera, det: FrameDetections, d: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Closed-form start (S (33,), t' (3,)) for fitting detection frame d: joint angles zero (clipped into the
    bounds), root rotation by weighted Kabsch of the torso joints of the 3D detection against the rest skeleton,
    pelvis position by linear least squares on the rays of the 2D detections of joints (with their 3D offsets).
    """
    lo, hi = pose_bounds()
    S = np.clip(np.zeros(_NP), lo, hi)
    rest = template.rest_joints - template.rest_joints[0]
    P3, c3 = det.joints_3d[d], det.confidence_3d[d]
    idx = np.array([j for j in _TORSO if c3[j] > 0])
    R = np.eye(3)
    if idx.size >= 3:
        w = c3[idx]
        A, B = rest[idx], P3[idx]
        A0 = A - np.average(A, axis=0, weights=w)
        B0 = B - np.average(B, axis=0, weights=w)
        U, _, Vt = np.linalg.svd((B0 * w[:, None]).T @ A0)
        D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
        R = U @ D @ Vt
    S[27:30] = _euler_from_matrix(R)
    # Pelvis position T: rays of detected 2D joints through (R-posed or detected) 3D offsets from the pelvis.
    offsets = np.where(c3[:, None] > 0, np.nan_to_num(P3), rest @ R.T)
    rows, rhs, wts = [], [], []
    kp, c2 = det.keypoints_2d[d], det.confidence_2d[d]
    for lm, j in _ON_JOINT:
        if c2[lm] <= 0:
            continue
        xn, yn = camera.undistort_points(kp[lm][None])[0]
        for k, v in ((0, xn), (1, yn)):
            a = camera.R[k] - v * camera.R[2]
            rows.append(a)
            rhs.append(-(a @ offsets[j]) - (camera.t[k] - v * camera.t[2]))
            wts.append(c2[lm])
    if len(rows) >= 3:
        sw = np.sqrt(np.asarray(wts))[:, None]
        T = np.linalg.lstsq(np.asarray(rows) * sw, np.asarray(rhs) * sw[:, 0], rcond=None)[0]
    else:
        T = template.rest_joints[0].copy()
    S[30:33] = T - template.rest_joints[0]
    return S, T


# --------------------------------------------------------------------------------------------- the problem
def checked_bounds(lower, upper, who: str) -> tuple[np.ndarray, np.ndarray]:
    """Bounds (33,) of the pose parameters: the given ones, or :func:`skeleton.pose_bounds` for None; checked for
    shape and order (errors name ``who`` and the first offending parameter)."""
    lo, hi = pose_bounds()
    lower = lo if lower is None else np.asarray(lower, dtype=np.float64)
    upper = hi if upper is None else np.asarray(upper, dtype=np.float64)
    if lower.shape != (_NP,) or upper.shape != (_NP,):
        raise ValueError(f"{who}: lower/upper bounds must have shape (33,), got {lower.shape}, {upper.shape}")
    bad = np.flatnonzero(~(lower <= upper))
    if bad.size:
        k = int(bad[0])
        raise ValueError(f"{who}: lower bound above upper bound for pose parameter {k} ({PARAM_NAMES[k]}): "
                         f"{lower[k]} > {upper[k]}")
    return lower, upper


class BatchProblem:
    """The batch NLP of Eq. 3-8 and the one-frame detection fit of the initialisation, built once.

    template, camera: the actor and the event camera. frames: number of tracking frames of a batch, N+1 (41 for a
    40 ms batch sliced at 1 ms). settings: pinned IPOPT options. lower/upper: bounds of the 33 pose parameters
    (default :func:`skeleton.pose_bounds`: θ_min/θ_max, free root).
    """

    def __init__(self, template: Template, camera: Camera, frames: int, settings: IpoptSettings = IpoptSettings(),
                 lower: np.ndarray | None = None, upper: np.ndarray | None = None, robust_px: float = 0.0):
        if not isinstance(template, Template):
            raise ValueError(f"BatchProblem: expected a Template, got {type(template).__name__}")
        if not isinstance(camera, Camera):
            raise ValueError(f"BatchProblem: expected a Camera, got {type(camera).__name__}")
        if int(frames) != frames or frames < 2:
            raise ValueError(f"BatchProblem: frames (N+1 tracking frames per batch) must be an integer >= 2, "
                             f"got {frames!r}")
        if not (math.isfinite(robust_px) and robust_px >= 0):
            raise ValueError(f"BatchProblem: robust_px must be >= 0 (0 = plain least squares), got {robust_px!r}")
        t0 = time.perf_counter()
        self.template, self.camera, self.F, self.settings = template, camera, int(frames), settings
        self.robust_px = float(robust_px)
        self.lower, self.upper = checked_bounds(lower, upper, "BatchProblem")
        self.scale = 1.0 / math.sqrt(camera.fx * camera.fy)
        self.kernels = SkinningKernels(template.rest_joints, self.F)
        self.numeric = _NumericEnergy(camera, self.kernels, template.rest_joints)
        self._build_fit()
        self._build_batch()
        self.build_seconds = time.perf_counter() - t0

    # ------------------------------------------------------------------ symbolic pieces
    def _frame_terms(self, S, tp, kp, c2, j3, c3):
        """E_2D and E_3D of one frame (SX)."""
        L = landmark_positions(S, self.template)  # (25, 3)
        uv = self.camera.project_sym(L.T)  # (2, 25)
        r2 = (uv - kp.T) * self.scale
        sq = ca.sum1(r2 * r2)  # (1, 25) squared landmark errors, focal-normalised
        if self.robust_px > 0:  # Cauchy: ≈ ‖r‖² for small errors, grows only logarithmically for outliers
            s2 = (self.robust_px * self.scale) ** 2
            sq = s2 * ca.log1p(sq / s2)
        e2 = ca.sum2(c2.T * sq)
        J = joint_positions(S, self.template.rest_joints)  # (24, 3)
        r3 = J - (j3 + ca.repmat(tp.T, NUM_JOINTS, 1))
        e3 = ca.sum1(c3 * ca.sum2(r3 * r3))
        return e2, e3

    @staticmethod
    def _det_symbols(prefix: str):
        return (ca.SX.sym(f"{prefix}kp", NUM_LANDMARKS, 2), ca.SX.sym(f"{prefix}c2", NUM_LANDMARKS, 1),
                ca.SX.sym(f"{prefix}j3", NUM_JOINTS, 3), ca.SX.sym(f"{prefix}c3", NUM_JOINTS, 1))

    @staticmethod
    def _det_values(det: FrameDetections, d: int) -> list[np.ndarray]:
        c2, c3 = det.confidence_2d[d], det.confidence_3d[d]
        # Undetected entries carry confidence 0; their (possibly NaN) values must not poison the sums.
        kp = np.where(c2[:, None] > 0, det.keypoints_2d[d], 0.0)
        j3 = np.where(c3[:, None] > 0, det.joints_3d[d], 0.0)
        return [kp.ravel(order="F"), c2, j3.ravel(order="F"), c3]

    def _build_fit(self) -> None:
        S = ca.SX.sym("S", _NP)
        tp = ca.SX.sym("tp", 3)
        lam = ca.SX.sym("lam", 3)  # 2D, 3D, damp
        ref = ca.SX.sym("ref", _NP)
        det = self._det_symbols("")
        e2, e3 = self._frame_terms(S, tp, *det)
        p = ca.vertcat(lam, ref, *[ca.vec(d) for d in det])
        x = ca.vertcat(S, tp)
        f = lam[0] * e2 + lam[1] * e3 + lam[2] * ca.sumsqr(S - ref)
        self._fit_solver = ca.nlpsol("fit_frame", "ipopt", {"x": x, "p": p, "f": f}, self.settings.options(False))
        self._fit_terms = ca.Function("fit_terms", [x, p], [e2, e3])

    def _build_batch(self) -> None:
        F, N = self.F, self.F - 1
        nS = _NP * F
        # --- decision variables: the poses S_0..S_N, t' of E_3D at frames 0 and N
        Svars = ca.SX.sym("S", _NP, F)
        tp = ca.SX.sym("tp", 3, 2)
        x = ca.vertcat(ca.vec(Svars), ca.vec(tp))
        # --- parameters: λ (cor, 2D, 3D, temp, damp), E_damp's reference poses, detections, φ
        lam = ca.SX.sym("lam", 5)
        ref = ca.SX.sym("ref", _NP, F)
        dets = [self._det_symbols(f"d{d}_") for d in range(2)]
        phi = ca.SX.sym("phi", NUM_JOINTS * N)
        p = ca.vertcat(lam, ca.vec(ref), *[ca.vec(s) for det in dets for s in det], phi)
        self.nx, self.np_ = x.numel(), p.numel()
        self._phi_offset = self.np_ - NUM_JOINTS * N
        # --- symbolic terms (SX, differentiated by CasADi): E_2D, E_3D at frames 0 and N, E_damp
        e2 = e3 = 0
        for d, f in enumerate((0, N)):
            a, b = self._frame_terms(Svars[:, f], tp[:, d], *dets[d])
            e2, e3 = e2 + a, e3 + b
        f_sx = lam[1] * e2 + lam[2] * e3 + lam[4] * ca.sumsqr(Svars - ref)
        self._terms = ca.Function("batch_terms", [x, p], [e2, e3])
        sx_f = ca.Function("E_sx", [x, p], [f_sx])
        sx_g = ca.Function("E_sx_grad", [x, p], [ca.gradient(f_sx, x)])
        sx_h = ca.Function("E_sx_hess", [x, p], [ca.triu(ca.hessian(f_sx, x)[0])])
        # --- numeric terms (numpy via callbacks): λ_cor E_cor + λ_temp E_temp, input [S; λ_cor; λ_temp; φ]
        ne = self.numeric
        n_in = nS + 2 + NUM_JOINTS * N

        def split(v):
            return v[:nS].reshape(F, _NP), v[nS + 2:].reshape(N, NUM_JOINTS), v[nS:nS + 2]

        sp_h, nz = _block_tridiagonal_triu(F, _NP)

        def hess(v):
            diag, upper = ne.hessian(*split(v))
            return [np.concatenate([diag[nz[0]], upper[nz[1]]])[nz[2]]]

        def grad(v):
            value, g = ne.gradient(*split(v))
            return [value, g.ravel()]

        self._callbacks = [
            NumpyCallback("E_num", n_in, [ca.Sparsity.dense(1, 1)], lambda v: [ne.value(*split(v))]),
            NumpyCallback("E_num_grad", n_in, [ca.Sparsity.dense(1, 1), ca.Sparsity.dense(nS, 1)], grad),
            NumpyCallback("E_num_hess", n_in, [sp_h], hess),
        ]
        cb_f, cb_g, cb_h = self._callbacks
        X, P = ca.MX.sym("x", self.nx), ca.MX.sym("p", self.np_)
        lam_f, lam_g = ca.MX.sym("lam_f"), ca.MX.sym("lam_g", 0)
        V = ca.vertcat(X[:nS], P[0], P[3], P[self._phi_offset:])
        nt = self.nx - nS
        f_mx = sx_f(X, P) + cb_f(V)
        num_v, num_g = cb_g(V)
        grad_f = ca.Function("grad_f", [X, P], [sx_f(X, P) + num_v, sx_g(X, P) + ca.vertcat(num_g, ca.MX(nt, 1))],
                             ["x", "p"], ["f", "grad_f_x"])
        hess_lag = ca.Function("hess_lag", [X, P, lam_f, lam_g],
                               [lam_f * (sx_h(X, P) + ca.diagcat(cb_h(V), ca.MX(nt, nt)))],
                               ["x", "p", "lam_f", "lam_g"], ["hess_gamma_x_x"])
        #: The objective, its gradient and the (upper-triangular) Hessian exactly as IPOPT sees them, as functions
        #: of (x, p) — for derivative checks. x = [vec(S) (33·F, frame-major); t' (6)].
        self.objective = ca.Function("objective", [X, P], [f_mx])
        self.gradient, self.hessian = grad_f, ca.Function("hessian_f", [X, P], [hess_lag(X, P, 1.0, ca.MX(0, 1))])
        opts = dict(self.settings.options(True), grad_f=grad_f, hess_lag=hess_lag)
        self._batch_solver = ca.nlpsol("batch", "ipopt", {"x": X, "p": P, "f": f_mx}, opts)

    # ------------------------------------------------------------------ solves
    def _run(self, solver, x0, p, lbx, ubx, what: str):
        t0 = time.perf_counter()
        try:
            res = solver(x0=x0, p=p, lbx=lbx, ubx=ubx)
        except RuntimeError as exc:  # CasADi refuses ill-posed input (e.g. lbx > ubx) before IPOPT runs
            raise StageFailed(f"{what}: the solver refused the problem: {exc}", status="Invalid_Problem_Definition",
                              details={"error": str(exc)}) from exc
        st = solver.stats()
        status = str(st.get("return_status", "unknown"))
        stats = SolveStats(status=status, iterations=int(st.get("iter_count", 0)),
                           seconds=time.perf_counter() - t0)
        if status not in SUCCESS_STATUSES:
            raise StageFailed(f"{what}: IPOPT did not converge (status {status} after {stats.iterations} "
                              f"iterations)", status=status, details={"iterations": stats.iterations})
        x = np.asarray(res["x"], dtype=np.float64).ravel()
        if not np.all(np.isfinite(x)):
            raise StageFailed(f"{what}: IPOPT returned non-finite poses (status {status})", status="non_finite")
        return x, stats

    def fit_frame(self, det: FrameDetections, d: int, weights: EnergyWeights = EnergyWeights(),
                  start: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray, SolveStats]:
        """Fit one pose to detection frame d (E_2D + E_3D): (S (33,), t' (3,), stats).

        start: (S, t') warm start; default :func:`initial_guess`.
        """
        if det.confidence_2d[d].max() <= 0 and det.confidence_3d[d].max() <= 0:
            raise StageFailed(f"detection frame {d}: nothing detected (all confidences 0): cannot fit a pose",
                              status="no_detections")
        lbx = np.concatenate([self.lower, np.full(3, -np.inf)])
        ubx = np.concatenate([self.upper, np.full(3, np.inf)])
        stages = [(weights.d2, weights.d3)]
        if start is None:
            start = initial_guess(self.template, self.camera, det, d)
            # From the closed-form guess (a T-pose), the projection term has many poor local minima (limbs
            # swung to the wrong side); the 3D term alone has few. Fit it first, then everything.
            if det.confidence_3d[d].max() > 0 and weights.d3 > 0:
                stages.insert(0, (0.0, weights.d3))
        x = np.concatenate([np.clip(start[0], self.lower, self.upper), start[1]])
        its, secs = 0, 0.0
        for d2, d3 in stages:
            p = np.concatenate([[d2, d3, weights.damp], x[:_NP], *self._det_values(det, d)])
            x, stats = self._run(self._fit_solver, x, p, lbx, ubx, f"fit of detection frame {d}")
            its, secs = its + stats.iterations, secs + stats.seconds
        return x[:_NP], x[_NP:], replace(stats, iterations=its, seconds=secs)

    def batch_params(self, ref: np.ndarray, det: FrameDetections, phi: np.ndarray,
                     weights: EnergyWeights) -> np.ndarray:
        """The NLP parameter vector: λ, reference poses of E_damp (N+1, 33), detections at frames 0 and N, φ (N, 24)."""
        return np.concatenate([weights.as_array(), np.asarray(ref, dtype=np.float64).ravel(),
                               *self._det_values(det, 0), *self._det_values(det, 1),
                               np.asarray(phi, dtype=np.float64).ravel()])

    def solve(self, poses0: np.ndarray, t_prime0: np.ndarray, det: FrameDetections, corr: Correspondences,
              phi: np.ndarray, weights: EnergyWeights = EnergyWeights(), relative: bool = True,
              fix_ends: bool = False) -> tuple[np.ndarray, np.ndarray, SolveStats]:
        """One solve of Eq. 3 with fixed correspondences, warm-started at poses0 (N+1, 33) and t_prime0 (2, 3).

        det: detections at frames 0 and N (2 rows). phi: (N, 24). relative=False holds each correspondence's
        source side where it was found (per-frame fits, the w/o_batch mode). fix_ends: S_0 and S_N stay at
        poses0's (bounds lbx = ubx). Returns (poses, t', stats).
        """
        F = self.F
        poses0 = np.asarray(poses0, dtype=np.float64)
        if poses0.shape != (F, _NP):
            raise ValueError(f"solve: expected poses0 of shape ({F}, 33), got {poses0.shape}")
        if det.n != 2:
            raise ValueError(f"solve: expected detections at frames 0 and N (2 rows), got {det.n}")
        if np.asarray(phi).shape != (F - 1, NUM_JOINTS):
            raise ValueError(f"solve: expected phi of shape ({F - 1}, 24), got {np.asarray(phi).shape}")
        self.numeric.set_correspondences(corr, relative)
        start = np.clip(poses0, self.lower, self.upper)
        x0 = np.concatenate([start.ravel(), np.asarray(t_prime0, float).ravel()])
        lbx = np.concatenate([np.tile(self.lower, F), np.full(6, -np.inf)])
        ubx = np.concatenate([np.tile(self.upper, F), np.full(6, np.inf)])
        if fix_ends:
            for f in (0, F - 1):
                lbx[_NP * f:_NP * (f + 1)] = ubx[_NP * f:_NP * (f + 1)] = start[f]
        p = self.batch_params(start, det, phi, weights)
        x, stats = self._run(self._batch_solver, x0, p, lbx, ubx, "batch solve")
        stats = replace(stats, n_correspondences=corr.n)
        return x[: _NP * F].reshape(F, _NP), x[_NP * F:].reshape(2, 3), stats

    def energies(self, poses: np.ndarray, t_prime: np.ndarray, det: FrameDetections, corr: Correspondences,
                 phi: np.ndarray, weights: EnergyWeights = EnergyWeights(), relative: bool = True) -> dict:
        """Unweighted value of each term of Eq. 4 at the given poses, and the weighted total."""
        x = np.concatenate([np.asarray(poses, float).ravel(), np.asarray(t_prime, float).ravel()])
        e2, e3 = (float(v) for v in self._terms(x, self.batch_params(poses, det, phi, weights)))
        self.numeric.set_correspondences(corr, relative)
        ec, et = self.numeric.terms(np.asarray(poses, float), np.asarray(phi, float))
        total = weights.cor * ec + weights.d2 * e2 + weights.d3 * e3 + weights.temp * et
        return {"cor": ec, "2d": e2, "3d": e3, "temp": et, "total": total}


# --------------------------------------------------------------------------------------------- a batch
def interpolate_poses(S0: np.ndarray, SN: np.ndarray, t_us: np.ndarray) -> np.ndarray:
    """Linear interpolation of S_0 and S_N at the tracking frame times (N+1, 33), proportional to time."""
    t = np.asarray(t_us, dtype=np.float64)
    a = ((t - t[0]) / (t[-1] - t[0]))[:, None]
    return (1.0 - a) * S0[None, :] + a * SN[None, :]


def unwrap_root(S: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """S with its root Euler angles moved by multiples of 2π to the nearest equivalent of ref's."""
    out = S.copy()
    d = out[27:30] - ref[27:30]
    out[27:30] -= 2.0 * np.pi * np.round(d / (2.0 * np.pi))
    return out


def check_batch_inputs(t_us, xy, valid, det: FrameDetections) -> None:
    """Raise StageFailed naming the first problem that would reach the solver as NaN/inf (before IPOPT runs)."""
    t = np.asarray(t_us)
    if not np.issubdtype(t.dtype, np.integer) or t.ndim != 1 or t.size < 2 or np.any(np.diff(t) <= 0):
        raise StageFailed("batch input: tracking frame times t_us must be increasing integers (microseconds), "
                          f"got {t.dtype} {t.shape}", status="invalid_input")
    bad = np.asarray(valid) & ~np.all(np.isfinite(np.asarray(xy, dtype=np.float64)), axis=-1)
    if bad.any():
        f, h = (int(v[0]) for v in np.nonzero(bad))
        raise StageFailed(f"batch input: track {h} has a non-finite position at tracking frame {f} where it is "
                          f"marked valid ({int(bad.sum())} such samples)", status="invalid_input")
    problems = det.problems()
    if problems:
        raise StageFailed("batch input: detections unusable: " + "; ".join(problems), status="invalid_input")


def solve_batch(problem: BatchProblem, t_us: np.ndarray, xy: np.ndarray, valid: np.ndarray, det: FrameDetections,
                mode: str = "batch", icp_rounds: int = 2, weights: EnergyWeights = EnergyWeights(),
                phi_scope: str = "batch", max_tracks: int = 0, edge_margin_px: float = EDGE_MARGIN_PX,
                still_m: float = STILL_M, boundary: str = "fixed") -> BatchResult:
    """Poses of one batch (see module doc for the modes).

    t_us: (N+1,) tracking frame times, µs. xy (N+1, H, 2) pixels and valid (N+1, H): sliced event tracks.
    det: detections at frames 0 and N (2 rows), or at every tracking frame (N+1 rows; required by ``all``).
    icp_rounds: alternations of correspondence search and solve (>= 1) for ``batch`` and ``per_frame``.
    max_tracks: use at most this many tracks (those valid at the most frames; 0 = all): bounds the solve time.
    still_m: E_temp applies only to joints that moved less than this between the end fits (metres; 0 = to every
    joint without correspondences, the paper's literal φ).
    boundary: "fixed" — S_0 and S_N stay at their fits to the detections, which neighbouring batches share
    (batch k's S_N and batch k+1's S_0 are the same fit of the same detections, so the joined sequence is
    continuous); "free" — the solve moves them too (then neighbouring batches disagree at their shared frame).
    edge_margin_px: tracks this close to a silhouette/self-occlusion edge give no correspondence (0 = keep all).
    Raises StageFailed on unusable data (before any solve) or an unsuccessful IPOPT solve.
    """
    if mode not in MODES:
        raise ValueError(f"solve mode: expected one of {MODES}, got {mode!r}")
    if boundary not in BOUNDARIES:
        raise ValueError(f"boundary: expected one of {BOUNDARIES}, got {boundary!r}")
    if phi_scope not in PHI_SCOPES:
        raise ValueError(f"phi scope: expected one of {PHI_SCOPES}, got {phi_scope!r}")
    if int(icp_rounds) != icp_rounds or icp_rounds < 1:
        raise ValueError(f"icp_rounds: expected an integer >= 1, got {icp_rounds!r}")
    F = problem.F
    t_us = np.asarray(t_us)
    if t_us.shape != (F,):
        raise ValueError(f"t_us: the problem was built for {F} tracking frames per batch, got {t_us.shape}")
    from .correspondences import check_tracks

    xy, valid = check_tracks(xy, valid, F)
    if int(max_tracks) != max_tracks or max_tracks < 0:
        raise ValueError(f"max_tracks: expected an integer >= 0 (0 = all), got {max_tracks!r}")
    if max_tracks and xy.shape[1] > max_tracks:
        keep = np.sort(np.argsort(-valid.sum(axis=0), kind="stable")[: int(max_tracks)])
        xy, valid = xy[:, keep], valid[:, keep]
    if det.n == F and F > 2:
        ends = det.rows([0, F - 1])
    elif det.n == 2:
        ends = det
    else:
        raise ValueError(f"detections: expected 2 rows (frames 0 and N) or {F} (every tracking frame), got {det.n}")
    if mode == "all" and det.n != F:
        raise ValueError(f"mode 'all' needs detections at all {F} tracking frames, got {det.n} rows")
    check_batch_inputs(t_us, xy, valid, det)

    seconds: dict[str, float] = {}
    solves: list[SolveStats] = []
    t0 = time.perf_counter()
    if mode == "all":
        poses, tps = np.zeros((F, _NP)), np.zeros((F, 3))
        start = None
        for f in range(F):
            S, T, st = problem.fit_frame(det, f, weights, start)
            poses[f], tps[f] = unwrap_root(S, poses[f - 1]) if f else S, T
            start = (poses[f], T)
            solves.append(st)
        seconds["fit"] = time.perf_counter() - t0
        t_prime = tps[[0, F - 1]]
        return _result(problem, poses, t_prime, ends, Correspondences.empty(), np.zeros((F - 1, NUM_JOINTS)),
                       weights, solves, seconds)

    if mode == "odometry":  # frame N's detection off: S_N follows from S_0's fit and the events alone
        S0, T0, st0 = problem.fit_frame(ends, 0, weights)
        solves.append(st0)
        c2, c3 = ends.confidence_2d.copy(), ends.confidence_3d.copy()
        c2[1] = c3[1] = 0.0
        ends = FrameDetections(ends.keypoints_2d, c2, ends.joints_3d, c3)
        poses, t_prime = np.repeat(S0[None, :], F, axis=0), np.stack([T0, T0])
    else:
        S0, T0, st0 = problem.fit_frame(ends, 0, weights)
        SN, TN, stN = problem.fit_frame(ends, 1, weights)
        SN = unwrap_root(SN, S0)
        solves += [st0, stN]
        poses = interpolate_poses(S0, SN, t_us)
        t_prime = np.stack([T0, TN])
    seconds["init"] = time.perf_counter() - t0
    corr, phi = Correspondences.empty(), np.zeros((F - 1, NUM_JOINTS))
    if mode == "linear":
        return _result(problem, poses, t_prime, ends, corr, phi, weights, solves, seconds)

    coupled = mode != "per_frame"  # batch and odometry: E_cor relative, E_temp on
    w = weights if coupled else replace(weights, temp=0.0)
    # E_temp holds still the parts without correspondences, "non-moving" in the paper's words; a joint whose end
    # fits moved more than still_m over the batch is not still, and holding it contradicts the detections.
    # (odometry has no second fit: the paper's literal φ.)
    moved = None
    if still_m > 0 and mode != "odometry":
        Jends = joint_positions(np.stack([S0, SN]), problem.template.rest_joints)
        moved = np.linalg.norm(Jends[1] - Jends[0], axis=1) > still_m
    seconds["correspondences"] = seconds["solve"] = 0.0
    for _ in range(int(icp_rounds)):
        t1 = time.perf_counter()
        corr = find_correspondences(problem.template, problem.camera, poses, xy, valid, edge_margin_px)
        phi = temporal_indicator(corr, F, phi_scope) if coupled else np.zeros((F - 1, NUM_JOINTS))
        if moved is not None:
            phi[:, moved] = 0.0
        t2 = time.perf_counter()
        poses, t_prime, st = problem.solve(poses, t_prime, ends, corr, phi, w, relative=coupled,
                                           fix_ends=boundary == "fixed" and mode != "odometry")
        seconds["correspondences"] += t2 - t1
        seconds["solve"] += time.perf_counter() - t2
        solves.append(st)
    if mode == "odometry":
        poses = S0[None, :] + (poses - poses[0])  # anchored exactly at S_0's fit
    return _result(problem, poses, t_prime, ends, corr, phi, w, solves, seconds, relative=coupled)


def _result(problem, poses, t_prime, ends, corr, phi, weights, solves, seconds, relative=True) -> BatchResult:
    energies = problem.energies(poses, t_prime, ends, corr, phi, weights, relative)
    energies["n_correspondences"] = corr.n
    return BatchResult(poses=poses, t_prime=np.asarray(t_prime), status=solves[-1].status,
                       iterations=int(sum(s.iterations for s in solves)), energies=energies, solves=tuple(solves),
                       seconds=seconds)


__all__ = [
    "MODES", "PARAM_NAMES", "BatchProblem", "BatchResult", "Buffered", "EnergyWeights", "FrameDetections",
    "IpoptSettings", "NumpyCallback", "SkinningKernels", "premultiplied_weights",
    "SolveStats", "check_batch_inputs", "checked_bounds", "initial_guess", "interpolate_poses",
    "project_derivatives", "select_detections", "solve_batch", "unwrap_root",
]
