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

How it is computed. Every term is a factor of :mod:`eventcap.energy` (E_2D and E_3D:
:class:`eventcap.energy.detections.Keypoints2D` / ``Joints3D``, CasADi expressions of one frame mapped over the two
detection frames; E_cor and E_temp: :class:`eventcap.energy.cor.EventCorrespondences` / ``TemporalStability``,
numpy with exact derivatives), summed over one pose per tracking frame by
:class:`eventcap.energy.problem.FactorProblem` (E_damp is its proximal term). E_cor has thousands of points, each
blended from 24 joint transforms: a symbolic SX Hessian of it takes minutes to build and gigabytes of memory
(measured: 29 s build and 95 ms per Hessian with 20 points per frame; killed at 200). So E_cor and E_temp are
evaluated by numpy, exactly (value, gradient and exact Hessian, checked against finite differences in the tests):
per frame, the 24 skinning transforms G(S) (96×3), their Jacobian and the contraction of their second derivatives
come from small CasADi functions (called through zero-copy buffers); per point, posed position = WX·G and Jacobian
= WX·∂G (one BLAS product per frame); projection derivatives in closed form. IPOPT sees the sum through numpy
callbacks; each batch's data (points, weights, pixels, detections, φ) are handed to the factors per solve, never
built into the NLP.

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
anything but success raises :class:`eventcap.core.stage.StageFailed` with IPOPT's status; unusable data (NaN/inf where
valid, bad confidences) raise it before IPOPT runs.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from eventcap.body.skeleton import NUM_POSE_PARAMS
from eventcap.body.template import Template
from eventcap.camera import Camera
from eventcap.energy.correspondences import check_tracks
from eventcap.energy.detections import (
    DetectionWeights,
    FrameDetections,
    FrameFitter,
    interpolate_poses,
    select_detections,
    unwrap_root,
)
from eventcap.energy.errors import EnergyError
from eventcap.energy.ipopt import IpoptSettings, SolveStats, bounds_with
from eventcap.energy.problem import FactorProblem, FramePoses
from eventcap.energy.terms import factors_from_config, sample_times
from eventcap.energy.window import Estimate, Tracks, WindowInputs

MODES = ("batch", "per_frame", "linear", "all", "odometry")
#: How a batch treats its first and last frame (shared with the neighbouring batches): see solve_batch.
BOUNDARIES = ("fixed", "free")
_NP = NUM_POSE_PARAMS


@dataclass(frozen=True)
class BatchResult:
    """Poses of a batch and how they were obtained."""

    poses: np.ndarray  #: (N+1, 33) S_0..S_N
    aux: dict  #: each factor's auxiliary variables at the result, by name (E_3D's t' at frames 0 and N)
    status: str  #: status of the last solve
    iterations: int  #: IPOPT iterations summed over all solves of the batch
    energies: dict  #: unweighted value of each term at the result (and the weighted total)
    solves: tuple[SolveStats, ...] = ()
    seconds: dict = field(default_factory=dict)  #: wall time per phase


# --------------------------------------------------------------------------------------------- the problem
def batch_window(t_us, ends: FrameDetections, xy=None, valid=None, edge_margin_px: float = 1.0) -> WindowInputs:
    """A batch's inputs for its factors: one pose per tracking frame t_us (F,), the detections at frames 0 and N,
    the tracks (F, H, 2) / (F, H) at every frame (none: no tracks)."""
    t_us = np.asarray(t_us, dtype=np.int64)
    if xy is None:
        xy, valid = np.zeros((t_us.size, 0, 2)), np.zeros((t_us.size, 0), dtype=bool)
    return WindowInputs(int(t_us[0]), int(t_us[-1]), frames_us=t_us, t_det_us=t_us[[0, -1]], detections=ends,
                        tracks=Tracks(t_us, np.asarray(xy, dtype=np.float64), np.asarray(valid, dtype=bool),
                                      float(edge_margin_px)))


def _frames(t_us: np.ndarray, poses: np.ndarray):
    """The poses (F, 33) at their frames t_us as a function of times (which must be frames)."""
    rows = {int(t): i for i, t in enumerate(np.asarray(t_us, dtype=np.int64))}
    P = np.array(poses, dtype=np.float64)

    def at(t, deriv=0):
        if deriv:
            raise EnergyError("per-frame poses have no derivative")
        return P[[rows[int(v)] for v in np.asarray(t).ravel()]]
    return at


class BatchProblem:
    """The batch NLP of Eq. 3-8 and the one-frame detection fit of the initialisation, built once.

    template, camera: the actor and the event camera. frames: number of tracking frames of a batch, N+1 (41 for a
    40 ms batch sliced at 1 ms). config: the stage's config (plugins/eventcap_solve/spec.py, BatchSolveConfig), the
    one source of every setting: the terms (E_2D, E_3D at frames 0 and N, E_cor and E_temp between every two
    frames), the joint limits, the IPOPT options.
    """

    def __init__(self, template: Template, camera: Camera, frames: int, config):
        if not isinstance(template, Template):
            raise EnergyError(f"BatchProblem: expected a Template, got {type(template).__name__}")
        if not isinstance(camera, Camera):
            raise EnergyError(f"BatchProblem: expected a Camera, got {type(camera).__name__}")
        if isinstance(frames, bool) or int(frames) != frames or frames < 2:
            raise EnergyError(f"BatchProblem: frames (N+1 tracking frames per batch) must be an integer >= 2, "
                              f"got {frames!r}")
        if config.mode not in MODES:
            raise EnergyError(f"solve mode: expected one of {MODES}, got {config.mode!r}")
        t0 = time.perf_counter()
        self.template, self.camera, self.F, self.config = template, camera, int(frames), config
        lo, hi = bounds_with(config.limits, "stages.solve.limits")
        self.settings = IpoptSettings.from_config(config.ipopt)
        shape = batch_window(np.arange(self.F), None)  # the sizes: a batch's frames, its two detection frames
        sizes = {k: t.size for k, t in sample_times(config.terms, shape).items()}
        self.factors = factors_from_config(config.terms, template, camera, sizes)
        self.problem = FactorProblem(FramePoses(self.F), self.factors, self.settings, lo, hi,
                                     damp=config.damp, damp_aux=False, name="batch")
        self.lower, self.upper = self.problem.lower, self.problem.upper
        self.fit_weights = DetectionWeights.from_terms(config.terms, camera)
        self.fitter = FrameFitter(template, camera, self.settings, lo, hi)
        self.build_seconds = time.perf_counter() - t0

    def fit_frame(self, det: FrameDetections, d: int,
                  start: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray, SolveStats]:
        """Fit one pose to detection frame d (the detection terms' weights and the damping): (S (33,), t' (3,),
        stats). start: (S, t') warm start; default :func:`eventcap.energy.detections.initial_guess`."""
        return self.fitter.fit(det, d, self.fit_weights, self.config.damp, start)

    def collect(self, inputs: WindowInputs) -> None:
        """Every factor's data of this batch, and the span of the poses."""
        for f in self.factors:
            f.collect(inputs)
        self.problem.set_window(inputs.frames_us)

    def solve(self, x0: np.ndarray, estimate: Estimate, fix_ends: bool = False) -> tuple[np.ndarray, SolveStats]:
        """One solve of Eq. 3, the factors relinearised at ``estimate``, warm-started at x0 (poses clipped into their
        bounds): (x, stats). fix_ends: S_0 and S_N stay at x0's."""
        F, nU = self.F, self.problem.nU
        x0 = np.array(x0, dtype=np.float64)
        x0[:nU] = np.clip(x0[:nU].reshape(F, _NP), self.lower, self.upper).ravel()
        for f in self.factors:
            f.relinearize(estimate)
        self.problem.set_reference(x0)
        x, stats = self.problem.solve(x0, "batch solve", fixed_units=(0, F - 1) if fix_ends else ())
        n_cor = sum(int(f.report().get("n_correspondences", 0)) for f in self.factors)
        return x, replace(stats, n_correspondences=n_cor)

    def poses_of(self, x: np.ndarray) -> np.ndarray:
        return np.asarray(x[:self.problem.nU]).reshape(self.F, _NP).copy()

    def energies(self, x: np.ndarray) -> dict:
        """Unweighted value of each term of Eq. 4 at x (the factors' current data), the weighted total (without
        E_damp), and the factors' counts (n_*)."""
        terms = self.problem.terms(x)
        out = dict(terms)
        out["total"] = float(sum(f.weight * terms[f.name] for f in self.factors))
        for f in self.factors:
            out.update({k: v for k, v in f.report().items() if k.startswith("n_")})
        return out


# --------------------------------------------------------------------------------------------- a batch
def check_batch_inputs(t_us, xy, valid, det: FrameDetections) -> None:
    """Raise EnergyError naming the first problem that would reach the solver as NaN/inf (before IPOPT runs)."""
    t = np.asarray(t_us)
    if not np.issubdtype(t.dtype, np.integer) or t.ndim != 1 or t.size < 2 or np.any(np.diff(t) <= 0):
        raise EnergyError("batch input: tracking frame times t_us must be increasing integers (microseconds), "
                          f"got {t.dtype} {t.shape}")
    bad = np.asarray(valid) & ~np.all(np.isfinite(np.asarray(xy, dtype=np.float64)), axis=-1)
    if bad.any():
        f, h = (int(v[0]) for v in np.nonzero(bad))
        raise EnergyError(f"batch input: track {h} has a non-finite position at tracking frame {f} where it is "
                          f"marked valid ({int(bad.sum())} such samples)")
    problems = det.problems()
    if problems:
        raise EnergyError("batch input: detections unusable: " + "; ".join(problems))


def batch_inputs(problem: BatchProblem, t_us, xy, valid, det: FrameDetections):
    """Checked inputs of a batch: (t_us, xy, valid, detections at frames 0 and N); the longest ``max_tracks``."""
    c, F = problem.config, problem.F
    if c.boundary not in BOUNDARIES:
        raise EnergyError(f"boundary: expected one of {BOUNDARIES}, got {c.boundary!r}")
    if isinstance(c.icp_rounds, bool) or int(c.icp_rounds) != c.icp_rounds or c.icp_rounds < 1:
        raise EnergyError(f"icp_rounds: expected an integer >= 1, got {c.icp_rounds!r}")
    t_us = np.asarray(t_us)
    if t_us.shape != (F,):
        raise EnergyError(f"t_us: the problem was built for {F} tracking frames per batch, got {t_us.shape}")
    xy, valid = check_tracks(xy, valid, F)
    most = c.tracks.max_tracks
    if most and xy.shape[1] > most:
        keep = np.sort(np.argsort(-valid.sum(axis=0), kind="stable")[: int(most)])
        xy, valid = xy[:, keep], valid[:, keep]
    if det.n == F and F > 2:
        ends = det.rows([0, F - 1])
    elif det.n == 2:
        ends = det
    else:
        raise EnergyError(f"detections: expected 2 rows (frames 0 and N) or {F} (every tracking frame), got {det.n}")
    if c.mode == "all" and det.n != F:
        raise EnergyError(f"mode 'all' needs detections at all {F} tracking frames, got {det.n} rows")
    check_batch_inputs(t_us, xy, valid, det)
    return t_us, xy, valid, ends


def solve_batch(problem: BatchProblem, t_us: np.ndarray, xy: np.ndarray, valid: np.ndarray,
                det: FrameDetections) -> BatchResult:
    """Poses of one batch in the problem's config's mode (module doc).

    t_us: (N+1,) tracking frame times, µs. xy (N+1, H, 2) pixels and valid (N+1, H): sliced event tracks.
    det: detections at frames 0 and N (2 rows), or at every tracking frame (N+1 rows; required by ``all``).
    The config's icp_rounds (alternations of relinearising, i.e. correspondence search, and solve, >= 1),
    tracks.max_tracks (use at most this many tracks, those valid at the most frames; 0 = all), tracks.edge_margin_px
    (tracks this close to a silhouette/self-occlusion edge give no correspondence), boundary ("fixed": S_0 and S_N
    stay at their fits to the detections, which neighbouring batches share, so the joined sequence is continuous;
    "free": the solve moves them too) and the terms' settings apply. Raises EnergyError on unusable data (before
    any solve), SolveFailed on an unsuccessful IPOPT solve.
    """
    t_us, xy, valid, ends = batch_inputs(problem, t_us, xy, valid, det)
    mode, F = problem.config.mode, problem.F
    seconds: dict[str, float] = {}
    t0 = time.perf_counter()
    if mode == "all":
        poses, tps, solves = _fit_every_frame(problem, det)
        seconds["fit"] = time.perf_counter() - t0
        inputs = batch_window(t_us, ends)
        problem.collect(inputs)
        x = _with_start(problem, poses, tps[[0, F - 1]], inputs)
        return _result(problem, poses, x, solves, seconds)
    poses, t_prime, ends, solves = _initial_poses(problem, t_us, ends)
    seconds["init"] = time.perf_counter() - t0
    inputs = batch_window(t_us, ends, xy, valid, problem.config.tracks.edge_margin_px)
    problem.collect(inputs)
    x = _with_start(problem, poses, t_prime, inputs)
    if mode == "linear":
        return _result(problem, poses, x, solves, seconds)
    return _icp_batch(problem, t_us, inputs, poses, x, solves, seconds)


def _with_start(problem: BatchProblem, poses: np.ndarray, t_prime: np.ndarray, inputs: WindowInputs) -> np.ndarray:
    """The decision vector of the poses, the factors' auxiliary variables at their start (E_3D's t': the fits')."""
    inputs.offer("fit_translation", lambda: np.asarray(t_prime, dtype=np.float64))
    inputs.start = _frames(inputs.frames_us, poses)
    x = problem.problem.start(np.zeros((problem.F, _NP)), inputs)
    x[:problem.problem.nU] = np.asarray(poses, dtype=np.float64).ravel()
    return x


def _fit_every_frame(problem: BatchProblem, det: FrameDetections):
    """Mode all: every tracking frame fitted to its own detections, each warm-started from the previous frame."""
    F = problem.F
    poses, tps, solves = np.zeros((F, _NP)), np.zeros((F, 3)), []
    start = None
    for f in range(F):
        S, T, st = problem.fit_frame(det, f, start)
        poses[f], tps[f] = unwrap_root(S, poses[f - 1]) if f else S, T
        start = (poses[f], T)
        solves.append(st)
    return poses, tps, solves


def _initial_poses(problem: BatchProblem, t_us, ends: FrameDetections):
    """The paper's initialisation: S_0 and S_N fitted to their detections, the frames between interpolated
    linearly. Mode odometry switches frame N's detection off: S_N follows from S_0's fit and the events alone.
    Returns (poses, t', the detections the solve uses, fit stats)."""
    F = problem.F
    S0, T0, st0 = problem.fit_frame(ends, 0)
    if problem.config.mode == "odometry":
        c2, c3 = ends.confidence_2d.copy(), ends.confidence_3d.copy()
        c2[1] = c3[1] = 0.0
        ends = FrameDetections(ends.keypoints_2d, c2, ends.joints_3d, c3)
        return np.repeat(S0[None, :], F, axis=0), np.stack([T0, T0]), ends, [st0]
    SN, TN, stN = problem.fit_frame(ends, 1)
    SN = unwrap_root(SN, S0)
    return interpolate_poses(S0, SN, t_us), np.stack([T0, TN]), ends, [st0, stN]


def _icp_batch(problem: BatchProblem, t_us, inputs: WindowInputs, poses, x, solves, seconds) -> BatchResult:
    """Modes batch, per_frame and odometry: ``icp_rounds`` alternations of relinearising every factor (the tracks'
    correspondences at the current poses, E_temp's indicator) and solving. per_frame: every frame on its own (each
    correspondence's source side held, nothing couples frames)."""
    c = problem.config
    coupled = c.mode != "per_frame"
    seconds["correspondences"] = seconds["solve"] = 0.0
    S0 = poses[0].copy()
    for r in range(int(c.icp_rounds)):
        t1 = time.perf_counter()
        est = Estimate(_frames(t_us, problem.poses_of(x)), r, inputs, problem.template, problem.camera,
                       coupled=coupled)
        x, st = problem.solve(x, est, fix_ends=c.boundary == "fixed" and c.mode != "odometry")
        seconds["solve"] += st.seconds
        seconds["correspondences"] += time.perf_counter() - t1 - st.seconds
        solves.append(st)
    poses = problem.poses_of(x)
    if c.mode == "odometry":
        poses = S0[None, :] + (poses - poses[0])  # anchored exactly at S_0's fit
    return _result(problem, poses, x, solves, seconds)


def _result(problem, poses, x, solves, seconds) -> BatchResult:
    energies = problem.energies(x)
    return BatchResult(poses=poses, aux=problem.problem.aux(x), status=solves[-1].status,
                       iterations=int(sum(s.iterations for s in solves)), energies=energies, solves=tuple(solves),
                       seconds=seconds)


__all__ = ["BOUNDARIES", "MODES", "BatchProblem", "BatchResult", "FrameDetections", "IpoptSettings",
           "check_batch_inputs", "interpolate_poses", "select_detections", "solve_batch", "unwrap_root"]
