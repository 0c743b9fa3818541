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

from eventcap.body.kinematics import joint_positions
from eventcap.body.skeleton import NUM_JOINTS, NUM_POSE_PARAMS
from eventcap.body.template import Template
from eventcap.camera import Camera
from eventcap.energy.cor import CorrespondenceEnergy as _NumericEnergy
from eventcap.energy.correspondences import (
    EDGE_MARGIN_PX,
    PHI_SCOPES,
    Correspondences,
    check_tracks,
    find_correspondences,
    temporal_indicator,
)
from eventcap.energy.detections import (
    FrameDetections,
    FrameFitter,
    det_symbols,
    det_values,
    detection_terms,
    initial_guess,
    interpolate_poses,
    select_detections,
    unwrap_root,
)
from eventcap.energy.ipopt import (
    PARAM_NAMES,
    SUCCESS_STATUSES,
    IpoptSettings,
    NumpyCallback,
    SolveStats,
    checked_bounds,
    run_ipopt,
)
from eventcap.energy.ipopt import block_tridiagonal_triu as _block_tridiagonal_triu
from eventcap.energy.kernels import Buffered, SkinningKernels, premultiplied_weights, project_derivatives
from eventcap.stage import StageFailed

MODES = ("batch", "per_frame", "linear", "all", "odometry")
#: How a batch treats its first and last frame (shared with the neighbouring batches): see solve_batch.
BOUNDARIES = ("fixed", "free")
#: Default of solve_batch's still_m: joints whose end fits moved more than this are not held still by E_temp.
STILL_M = 0.03
#: IPOPT return statuses accepted as success.
_NP = NUM_POSE_PARAMS


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
class BatchResult:
    """Poses of a batch and how they were obtained."""

    poses: np.ndarray  #: (N+1, 33) S_0..S_N
    t_prime: np.ndarray  #: (2, 3) metres, t' of E_3D at frames 0 and N (fits for linear/all)
    status: str  #: status of the last solve
    iterations: int  #: IPOPT iterations summed over all solves of the batch
    energies: dict  #: unweighted value of each term at the result (and the weighted total)
    solves: tuple[SolveStats, ...] = ()
    seconds: dict = field(default_factory=dict)  #: wall time per phase


# --------------------------------------------------------------------------------------------- the problem
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
        """E_2D and E_3D of one frame (SX): :func:`eventcap.energy.detections.detection_terms`."""
        return detection_terms(self.template, self.camera, S, tp, kp, c2, j3, c3, self.robust_px)

    _det_symbols = staticmethod(det_symbols)
    _det_values = staticmethod(det_values)

    def _build_fit(self) -> None:
        self._fitter = FrameFitter(self.template, self.camera, self.settings, self.lower, self.upper, self.robust_px)
        self._fit_solver, self._fit_terms = self._fitter.solver, self._fitter.terms

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
        return run_ipopt(solver, x0, p, lbx, ubx, what)

    def fit_frame(self, det: FrameDetections, d: int, weights: EnergyWeights = EnergyWeights(),
                  start: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray, SolveStats]:
        """Fit one pose to detection frame d (E_2D + E_3D): (S (33,), t' (3,), stats).

        start: (S, t') warm start; default :func:`initial_guess`.
        """
        return self._fitter.fit(det, d, weights.d2, weights.d3, weights.damp, start)

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
    "MODES", "PARAM_NAMES", "SUCCESS_STATUSES", "BatchProblem", "BatchResult", "Buffered", "EnergyWeights", "FrameDetections",
    "IpoptSettings", "NumpyCallback", "SkinningKernels", "premultiplied_weights",
    "SolveStats", "check_batch_inputs", "checked_bounds", "initial_guess", "interpolate_poses",
    "project_derivatives", "select_detections", "solve_batch", "unwrap_root",
]
