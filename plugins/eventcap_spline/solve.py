"""The spline solve (not in the paper): one continuous-time pose trajectory over a window of several batches.

    min_C,x_f  Σ_f f(S(t_f), x_f) + damp ‖x - x_start‖²      over the factors f of the config's terms
    s.t.       θ_min <= C_i <= θ_max  for every control point i   (exact joint limits on S(t))

S(t) = Σ_i B_i(t) C_i is a uniform cubic B-spline in the 33 pose parameters (:mod:`eventcap.energy.spline`), so
the unknowns are the n_seg + 3 control points instead of 1,000 poses per second, and the motion is C² at any rate.

The terms are factors of :mod:`eventcap.energy` (the table in :mod:`eventcap.energy.terms`): every term of the
stage's ``terms`` group whose weight is > 0 takes part, summed in the group's order. The solve never names one: each
factor takes its own data from the window's inputs (:class:`eventcap.energy.window.WindowInputs`: detections at
every intensity frame of the window, the event tracks of the solved batches, the events) and from the evidence the
solve measures once for all of them (the per-frame fits, the smoothing the fits around the window call for, the
joints' stillness in the events, the floor), and relinearises at each ICP round against the current estimate
(:class:`eventcap.energy.window.Estimate`: the tracks' correspondences, the silhouette's events, the contacts).

Why. The paper's batches are pinned at both ends to per-frame detection fits that are 3-7 cm off, independently
from frame to frame: the 1 kHz motion between them cannot be smooth, and no batch can average that noise. Here
detections enter as soft, robust observations at every intensity frame of the window, the events add the relative
motion within the batch, and the prior keeps velocities smooth; averaging the detector's noise over several frames
is where the accuracy comes from.

A window's solve: per-frame fits at its detection frames (the paper's initialisation, shared between windows of
one process), every factor's data, a penalised spline through the fits as the start (its roughness penalty is the
factors' :meth:`eventcap.energy.factor.Factor.start_penalty`: the motion prior's), then ``icp_rounds`` alternations
of relinearising every factor at the current spline and IPOPT, fewer when every factor's association settled
(``icp_settle_px``). Built once per process for a window layout (:class:`SplineSolver`); every IPOPT status is
checked.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from eventcap.body.skeleton import NUM_POSE_PARAMS
from eventcap.body.template import Template
from eventcap.camera import Camera
from eventcap.energy.detections import FIT_DAMP, FrameDetections, FrameFitter, unwrap_root
from eventcap.energy.errors import EnergyError, SolveFailed
from eventcap.energy.factor import Layout
from eventcap.energy.floor import floor_height, sole_points
from eventcap.energy.ipopt import IpoptSettings, SolveStats, bounds_with
from eventcap.energy.laplace import UnitCovariance, laplace_covariance, limits_precision
from eventcap.energy.prior import context_smoothing
from eventcap.energy.problem import FactorProblem, SplinePoses
from eventcap.energy.silence import Silence, measure_stillness
from eventcap.energy.spline import UniformCubicBSpline
from eventcap.energy.terms import TermSet
from eventcap.energy.window import Estimate, WindowInputs, detection_curvature
from eventcap.memo import ProcessCache

_NP = NUM_POSE_PARAMS
#: Per-frame fits of this process, by (fitter, detections of the frame): each frame is in several windows.
_FITS = ProcessCache("eventcap_spline.frame_fits", maxsize=512)


@dataclass(frozen=True)
class WindowResult:
    """The solved spline of one window and how it was obtained."""

    spline: UniformCubicBSpline
    control: np.ndarray  #: (n_ctrl, 33) control points
    aux: dict  #: each factor's auxiliary variables at the solution, by name (E_3D's t' per detection frame)
    fits: np.ndarray  #: (D, 33) the per-frame fits (root angles unwrapped along the window) it started from
    energies: dict  #: each term's unweighted value, the weighted total, and the factors' counts (n_*)
    solves: tuple[SolveStats, ...]  #: the spline solves (one per ICP round)
    seconds: dict
    fits_computed: int = 0  #: per-frame fits computed for this window (the others came from neighbouring windows)
    reports: dict = field(default_factory=dict)  #: each factor's report (:meth:`Factor.report`), by name
    lines: tuple[str, ...] = ()  #: what the factors say of this window's data (:meth:`Factor.describe`)
    stillness: Silence | None = None  #: the events' stillness evidence, when a factor asked for it
    #: per ICP round after the first: how far its association moved the residuals (px, RMS, the largest over the
    #: factors that associate; the last below ``icp_settle_px`` ended the rounds without a solve)
    association_change_px: tuple[float, ...] = ()
    #: the control points' covariance at the solution (the Laplace approximation, :mod:`eventcap.energy.laplace`)
    covariance: UnitCovariance | None = None


class FitSolver:
    """The per-frame fits' built pieces for a template and camera (the paper's initialisation, and what the capture's
    measures start from): the fitter with the solve's bounds, IPOPT settings and E_2D / E_3D weights. Much cheaper to
    build than a :class:`SplineSolver` (no window problem). terms: the config's ``terms`` decoded (None: decoded
    here)."""

    def __init__(self, template: Template, camera: Camera, config, where: str = "stages.solve",
                 terms: TermSet | None = None):
        self.template, self.camera, self.config = template, camera, config
        self.terms = TermSet.decode(config.terms) if terms is None else terms
        self.lower, self.upper = bounds_with(config.limits, f"{where}.limits")
        self.settings = IpoptSettings.from_config(config.ipopt)
        self.fit_weights = self.terms.detection_weights(camera)
        self.fitter = FrameFitter(template, camera, self.settings, self.lower, self.upper)


class SplineSolver:
    """The spline solve's built pieces for windows of one layout (template, camera, config): the factor problem
    (:class:`FactorProblem` over a spline's control points) and the per-frame fitter. ``config`` is the stage's
    config (plugins/eventcap_spline/spec.py, SplineSolveConfig), the one source of every setting; terms: its
    ``terms`` decoded (None: decoded here); where: its key in the run's config (messages name settings by it)."""

    def __init__(self, template: Template, camera: Camera, layout: Layout, config, where: str = "stages.solve",
                 terms: TermSet | None = None):
        t0 = time.perf_counter()
        self.template, self.camera, self.layout, self.config, self.where = template, camera, layout, config, where
        self.terms = TermSet.decode(config.terms) if terms is None else terms
        lo, hi = bounds_with(config.limits, f"{where}.limits")
        self.settings = IpoptSettings.from_config(config.ipopt)
        self.factors = self.terms.factors(template, camera, dict(layout.sizes))
        self.problem = FactorProblem(SplinePoses(layout.n_seg), self.factors, self.settings, lo, hi,
                                     damp=config.damp, damp_aux=True, name="spline", band=layout.band)
        self.lower, self.upper = self.problem.lower, self.problem.upper
        self.fit_weights = self.terms.detection_weights(camera)
        self.fitter = FrameFitter(template, camera, self.settings, lo, hi)
        self.build_seconds = time.perf_counter() - t0


# --------------------------------------------------------------------------------------------- per-frame fits
def frame_fit(solver: SplineSolver | FitSolver, det: FrameDetections, d: int):
    """The per-frame fit of detection frame d, ((S, t', stats), whether it was computed now). A frame's fit is a
    deterministic function of its detections and the fitter's settings, so neighbouring windows of this process
    share it (keyed by value)."""
    weights = solver.fit_weights
    key = (solver.template.geometry_digest(), repr(sorted(solver.camera.to_dict().items())), solver.lower.tobytes(),
           solver.upper.tobytes(), solver.settings, weights.key(), *(v.tobytes() for v in weights.values(det, d)))
    fit, built = _FITS.get(key, lambda: solver.fitter.fit(det, d, weights, FIT_DAMP))
    return fit, int(built)


def observed_frames(det: FrameDetections) -> np.ndarray:
    """(D,) bool: the detection frames that hold any observation (a landmark or a 3D joint with confidence > 0). The
    others are missing observations: no fit there, and their E_2D / E_3D rows weigh nothing."""
    return (det.confidence_2d.max(axis=1) > 0) | (det.confidence_3d.max(axis=1) > 0)


class NothingObserved(EnergyError):
    """No detection frame of the window holds an observation: nothing to estimate there (a gap, not a failure)."""

    def __init__(self, message: str):
        super().__init__(message, status="gap")


def fit_window(solver: SplineSolver, det: FrameDetections) -> tuple[np.ndarray, np.ndarray, list[SolveStats], int]:
    """Per-frame fits (E_2D + E_3D, the paper's initialisation) at every detection frame of the window that holds an
    observation (:func:`observed_frames`), with the root angles unwrapped along the window: (S (D, 33), t' (D, 3),
    stats, how many were computed here rather than taken from this process's earlier windows). A frame without an
    observation (a missed or rejected detection) has NaN rows: a missing observation, not a failure."""
    S = np.full((det.n, _NP), np.nan)
    T = np.full((det.n, 3), np.nan)
    stats = []
    computed, prev = 0, None
    for d in np.flatnonzero(observed_frames(det)):
        (s, t, st), new = frame_fit(solver, det, int(d))
        computed += new
        S[d], T[d] = (unwrap_root(s, prev) if prev is not None else s), t
        prev = S[d]
        stats.append(st)
    return S, T, stats, computed


def frame_fits(solver: SplineSolver, det: FrameDetections) -> tuple[list[int], list[np.ndarray], int]:
    """The per-frame fits (:func:`frame_fit`) at det's frames that succeed: their frame indices, their poses (33,),
    and how many were computed here (the others came from this process's earlier windows). A frame whose fit fails
    is left out."""
    keep, S, computed = [], [], 0
    for d in range(det.n):
        try:
            (s, _, _), new = frame_fit(solver, det, d)
        except SolveFailed:
            continue
        computed += new
        keep.append(d)
        S.append(s)
    return keep, S, computed


def capture_floor(solver: SplineSolver, det: FrameDetections) -> tuple[float | None, int]:
    """The floor's height (world y, m) over a capture (:func:`eventcap.energy.floor.floor_height`) from the per-frame
    fits at its intensity frames (det: their detections; frames whose fit fails are left out), and how many fits
    were computed here (the others came from this process's earlier windows)."""
    _, S, computed = frame_fits(solver, det)
    if not S:
        return None, computed
    return floor_height(sole_points(np.stack(S), solver.template)[..., 1]), computed


# --------------------------------------------------------------------------------------------- evidence
def window_context(solver: SplineSolver, inputs: WindowInputs, t_ctx_us, det_ctx: FrameDetections, fits, tps,
                   counter: list[int]):
    """The window's context evidence (:func:`eventcap.energy.prior.context_smoothing`) from the per-frame fits at the
    intensity frames around it (t_ctx_us, det_ctx; frames whose fit fails are left out); the fits computed here are
    added to counter[0]."""
    t, S = context_fits(solver, t_ctx_us, det_ctx, counter)
    return context_smoothing(t, S, lambda: detection_curvature(solver.factors, inputs, fits, tps),
                             str(solver.config.smoothing.criterion), inputs.t_det_us, fits, unwrap_root)


def context_fits(solver: SplineSolver, t_ctx_us, det_ctx: FrameDetections, counter: list[int]):
    """The per-frame fits at the detection frames around a window that succeed: their times (K,) and poses (K, 33),
    root angles unwrapped along them; the fits computed here are added to counter[0]."""
    keep, ctx_fits, computed = frame_fits(solver, det_ctx)
    counter[0] += computed
    S = []
    for s in ctx_fits:
        S.append(unwrap_root(s, S[-1]) if S else s)
    return np.asarray(t_ctx_us, dtype=np.int64)[keep], np.stack(S) if S else np.zeros((0, _NP))


def window_stillness(solver: SplineSolver, inputs: WindowInputs) -> Silence:
    """The joints' stillness per knot interval of a window (:func:`eventcap.energy.silence.measure_stillness`)
    around the solve's start; settings: the config's ``stillness``."""
    return measure_stillness(inputs.need("start", "the stillness"), inputs.knots_us, solver.template, solver.camera,
                             inputs.events, solver.config.stillness)


# --------------------------------------------------------------------------------------------- a window
def solve_window(solver: SplineSolver, spline: UniformCubicBSpline, inputs: WindowInputs, what: str = "window",
                 context: tuple[np.ndarray, FrameDetections] | None = None,
                 start: tuple[np.ndarray, dict] | None = None) -> WindowResult:
    """Solve one window (module doc) with the solver's config: fits at its detection frames, every factor's data,
    a penalised spline through the fits as the start, then ``icp_rounds`` alternations of relinearising and IPOPT.
    SolveFailed on a failed solve; NothingObserved when no detection frame holds an observation; EnergyError
    (invalid_config), before anything is measured, when a term that is on reads what the inputs do not provide
    (:meth:`eventcap.energy.terms.TermSet.check`).

    inputs: the window's data (its detections, tracks, events; the evidence is offered here). context: (times,
    detections) of the intensity frames around the window whose fits give the smoothing evidence (None: none).
    start: (control points (n_ctrl, 33), {factor: auxiliary variables}) the solve starts from instead of the
    smoothing spline through the fits (rows with a NaN are taken from it); the stillness is measured around the fits'
    spline either way (benchmarks/speed/bench_warm_start.py starts a window from its neighbour's solution)."""
    solver.terms.check(inputs, solver.where)
    prob = solver.problem
    seconds: dict[str, float] = {}
    t0 = time.perf_counter()
    det = inputs.need("detections", "the spline solve")
    fits, tps, _, n_fits = fit_window(solver, det)
    seen = np.isfinite(fits).all(axis=1)
    if not seen.any():
        raise NothingObserved(f"{what}: none of the window's {det.n} detection frames holds an observation (no "
                              f"person detected there): nothing to estimate")
    counter = [n_fits]
    inputs.offer("fits", lambda: fits)
    inputs.offer("fit_translation", lambda: tps)
    if context is not None:
        inputs.offer("smoothing", lambda: window_context(solver, inputs, context[0], context[1], fits, tps, counter))
        inputs.offer("context_fits", lambda: context_fits(solver, context[0], context[1], counter))
    if inputs.events is not None:
        inputs.offer("stillness", lambda: window_stillness(solver, inputs))
    for f in solver.factors:
        f.collect(inputs)
    # Start: a penalised spline through the fits (the factors' roughness penalty: the motion prior's).
    order, smooth = 2, 1e-12
    for f in solver.factors:
        penalty = f.start_penalty()
        if penalty is not None:
            order, smooth = penalty
    C = np.clip(spline.fit(inputs.t_det_us[seen], fits[seen], smooth=smooth, deriv=order), solver.lower,
                solver.upper)
    inputs.start = _curve(spline, C)
    x = prob.start(C, inputs)
    if start is not None:
        x = _warm(solver, x, start)
    prob.set_window(spline)
    seconds["fit"] = time.perf_counter() - t0
    # a start from a solution (any finite row) restarts as a later ICP round does; an all-NaN start is the cold start
    warm = start is not None and bool(np.isfinite(start[0]).any())
    x, solves, changes = _icp(solver, spline, inputs, x, what, seconds, warm)
    return _result(solver, spline, inputs, x, fits, solves, seconds, counter[0], changes)


def _curve(spline: UniformCubicBSpline, C: np.ndarray):
    C = C.copy()
    return lambda t_us, deriv=0: spline.evaluate(C, t_us, deriv)


def _warm(solver: SplineSolver, x: np.ndarray, start) -> np.ndarray:
    """x with the finite rows of a warm start (control points, {factor: aux}) in place."""
    prob = solver.problem
    C0, aux0 = start
    C0 = np.asarray(C0, dtype=np.float64)
    if C0.shape != (prob.n_units, _NP):
        raise EnergyError(f"start: expected control points {(prob.n_units, _NP)}, got {C0.shape}")
    x = prob.with_aux(x, dict(aux0))
    U = x[:prob.nU].reshape(prob.n_units, _NP)
    rows = np.isfinite(C0).all(axis=1)
    U[rows] = np.clip(C0[rows], solver.lower, solver.upper)
    return x


def _icp(solver: SplineSolver, spline, inputs: WindowInputs, x, what, seconds, warm: bool = False):
    """``icp_rounds`` alternations of relinearising every factor at the current spline and solving (one solve
    without association when icp_rounds is 0). From the second round on, when every factor that associates would
    move its residuals by less than ``icp_settle_px`` (:meth:`Factor.association_change`), the rounds end: the last
    solve stands. Returns (x, solve stats, each later round's change (px))."""
    c, prob = solver.config, solver.problem
    seconds["relinearize"] = seconds["solve"] = 0.0
    rounds = int(c.icp_rounds)
    solves, changes = [], []
    for r in range(max(rounds, 1)):
        t1 = time.perf_counter()
        est = Estimate(_curve(spline, x[:prob.nU].reshape(prob.n_units, _NP)), r, inputs, solver.template,
                       solver.camera, associate=rounds > 0)
        if r > 0 and float(c.icp_settle_px) > 0:  # (0: every round; nothing to measure)
            moved = [v for v in (f.association_change(est) for f in solver.factors) if v is not None]
            if moved:
                changes.append(max(moved))
                if changes[-1] < float(c.icp_settle_px):  # settled: the last solve stands
                    seconds["relinearize"] += time.perf_counter() - t1
                    break
        for f in solver.factors:
            f.relinearize(est)
        prob.set_reference(x)
        t2 = time.perf_counter()
        label = f"ICP round {r + 1}" if rounds > 0 else "no correspondences"
        x, st = prob.solve(x, f"{what}: spline solve ({label})", restart=r > 0 or warm)
        n_cor = sum(int(f.report().get("n_correspondences", 0)) for f in solver.factors)
        solves.append(SolveStats(st.status, st.iterations, st.seconds, n_cor))
        seconds["relinearize"] += t2 - t1
        seconds["solve"] += time.perf_counter() - t2
    return x, solves, tuple(changes)


def _result(solver, spline, inputs, x, fits, solves, seconds, n_fits, changes) -> WindowResult:
    prob = solver.problem
    energies = dict(prob.terms(x))
    energies["total"] = prob.evaluate(x, 0)["value"]
    reports = {f.name: f.report() for f in solver.factors}
    for rep in reports.values():
        energies.update({k: v for k, v in rep.items() if k.startswith("n_")})
    lines = tuple(line for line in (f.describe() for f in solver.factors) if line)
    U, _ = prob.split(x)
    t0 = time.perf_counter()
    covariance = laplace_covariance(prob, x, limits_precision(solver.lower, solver.upper,
                                                              float(solver.config.uncertainty_limits)))
    seconds["laplace"] = time.perf_counter() - t0
    return WindowResult(spline=spline, control=U.copy(), aux=prob.aux(x), fits=fits, energies=energies,
                        solves=tuple(solves), seconds=seconds, fits_computed=n_fits, reports=reports, lines=lines,
                        stillness=inputs.measured().get("stillness"), association_change_px=changes,
                        covariance=covariance)


__all__ = ["FitSolver", "NothingObserved", "SplineSolver", "WindowResult", "capture_floor", "fit_window",
           "frame_fit", "frame_fits", "observed_frames", "solve_window", "window_context", "window_stillness"]
