"""The spline solve (not in the paper): one continuous-time pose trajectory over a window of several batches.

    min_C,t'  Σ_f f(S(t_f), t'_f) + λ_damp ‖x - x_start‖²      over the factors f of the config (below)
    s.t.      θ_min <= C_i <= θ_max  for every control point i   (exact joint limits on S(t))

S(t) = Σ_i B_i(t) C_i is a uniform cubic B-spline in the 33 pose parameters (:mod:`eventcap.energy.spline`), so
the unknowns are the n_seg + 3 control points instead of 1,000 poses per second, and the motion is C² at any rate.

The terms are factors of :mod:`eventcap.energy` (one class each; the table in :mod:`eventcap.energy.terms`), each
with its weight ``stages.spline.lambda_<name>``; every registered factor whose weight this stage's config states
and is > 0 takes part: E_2D (Cauchy-robust) and E_3D at every intensity frame of the window, E_cor between the
tracking frames of the batch's (or the window's) tracks, E_sil at the batch's frames every ``sil_step_ms``, the
motion prior, E_still (event silence) and the context pull. Every factor is a function of the poses S = B C, linear
in C, so the chain rule is a product with the basis (:class:`eventcap.energy.problem.FactorProblem`).

Why. The paper's batches are pinned at both ends to per-frame detection fits that are 3-7 cm off, independently
from frame to frame: the 1 kHz motion between them cannot be smooth, and no batch can average that noise. Here
detections enter as soft, robust observations at every intensity frame of the window, the events add the relative
motion within the batch, and the prior keeps velocities smooth; averaging the detector's noise over several frames
is where the accuracy comes from.

A window's solve: per-frame fits at its detection frames (the paper's initialisation, shared between windows of
one process), the prior's gains and the context pull chosen from the fits around the window
(:func:`eventcap.energy.prior.choose_prior_gains`), a penalised spline through the fits as the start, the joints'
stillness measured from the events around that start (E_still), then ``icp_rounds`` alternations of correspondence
search (event tracks and silhouette events at the current spline) and IPOPT, fewer when a round's search finds
the correspondences settled (``icp_settle_px``). Built once per process for a window
layout (:class:`SplineSolver`); every IPOPT status is checked.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass

import numpy as np

from eventcap.body.kinematics import joint_positions
from eventcap.body.skeleton import NUM_POSE_PARAMS
from eventcap.body.template import Template
from eventcap.camera import Camera
from eventcap.energy.correspondences import Correspondences, correspondence_change_px, find_correspondences
from eventcap.energy.detections import FIT_DAMP, FrameDetections, FrameFitter, unwrap_root
from eventcap.energy.errors import EnergyError, SolveFailed
from eventcap.energy.event_search import DENOISE_US, EventIndex
from eventcap.energy.factor import Layout, Window
from eventcap.energy.terms import factors_from_config
from eventcap.energy.ipopt import IpoptSettings, SolveStats, bounds_with
from eventcap.energy.prior import PriorGain, choose_prior_gains, still_gate
from eventcap.energy.problem import FactorProblem, SplinePoses
from eventcap.energy.sil import find_silhouette_correspondences
from eventcap.energy.silence import Silence, measure_silence
from eventcap.energy.spline import PRIOR_ORDERS, UniformCubicBSpline

_NP = NUM_POSE_PARAMS
#: Per-frame fits of this process, by (fitter, detections of the frame): each frame is in several windows.
_FITS: dict = {}
_FITS_MAX = 512


def clear_fits() -> None:
    """Forget this process's per-frame fits."""
    _FITS.clear()


@dataclass(frozen=True)
class WindowResult:
    """The solved spline of one window and how it was obtained."""

    spline: UniformCubicBSpline
    control: np.ndarray  #: (n_ctrl, 33) control points
    t_prime: np.ndarray  #: (D, 3) t' of E_3D per detection frame (zeros without E_3D)
    fits: np.ndarray  #: (D, 33) the per-frame fits (root angles unwrapped along the window) it started from
    energies: dict
    solves: tuple[SolveStats, ...]  #: the spline solves (one per ICP round)
    seconds: dict
    fits_computed: int = 0  #: per-frame fits computed for this window (the others came from neighbouring windows)
    prior_gain: np.ndarray | None = None  #: (33,) the prior's gain per parameter (None: 1)
    silence: Silence | None = None  #: the events' stillness per knot interval and joint (None: term off)
    pull_frames: np.ndarray | None = None  #: (D, 33) the context pull in frames' worth, 1/h - 1 (None: off)
    #: per ICP round after the first: how far its correspondence search moved E_cor (px, RMS; the last below
    #: ``icp_settle_px`` ended the rounds without a solve)
    cor_change_px: tuple[float, ...] = ()


class SplineSolver:
    """The spline solve's built pieces for windows of one layout (template, camera, config): the factor problem
    (:class:`FactorProblem` over a spline's control points) and the per-frame fitter. ``config`` is the stage's
    config (plugins/eventcap_spline/spec.py, SplineSolveConfig), the one source of every setting."""

    def __init__(self, template: Template, camera: Camera, layout: Layout, config):
        t0 = time.perf_counter()
        if config.prior not in PRIOR_ORDERS:
            raise EnergyError(f"stages.spline.prior: expected one of {sorted(PRIOR_ORDERS)}, got {config.prior!r}")
        self.template, self.camera, self.layout, self.config = template, camera, layout, config
        self.order = PRIOR_ORDERS[config.prior]
        lo, hi = bounds_with(config.limits, "stages.spline.limits")
        self.settings = IpoptSettings(max_iter=config.max_iter, tol=config.tol,
                                      mumps_pivot_order=config.mumps_pivot_order)
        self.factors = factors_from_config(config, template, camera, layout)
        self.problem = FactorProblem(SplinePoses(layout.n_seg), self.factors, self.settings, lo, hi,
                                     damp=config.lambda_damp, damp_aux=True, name="spline", band=layout.band)
        self.lower, self.upper = self.problem.lower, self.problem.upper
        self.fitter = FrameFitter(template, camera, self.settings, lo, hi, config.robust_2d_px)
        self.build_seconds = time.perf_counter() - t0

    def factor(self, name: str):
        return self.problem.factor(name)


# --------------------------------------------------------------------------------------------- per-frame fits
def frame_fit(solver: SplineSolver, det: FrameDetections, d: int):
    """The per-frame fit of detection frame d, ((S, t', stats), whether it was computed now). A frame's fit is a
    deterministic function of its detections and the fitter's settings, so neighbouring windows of this process
    share it (keyed by value)."""
    from eventcap.energy.detections import det_values

    c = solver.config
    key = (solver.template.geometry_digest(), repr(sorted(solver.camera.to_dict().items())), solver.lower.tobytes(),
           solver.upper.tobytes(),
           float(c.robust_2d_px), solver.settings, float(c.lambda_2d), float(c.lambda_3d),
           *(v.tobytes() for v in det_values(det, d)))
    if key in _FITS:
        return _FITS[key], 0
    if len(_FITS) > _FITS_MAX:
        _FITS.clear()
    _FITS[key] = solver.fitter.fit(det, d, c.lambda_2d, c.lambda_3d, FIT_DAMP)
    return _FITS[key], 1


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


def detection_curvature(solver: SplineSolver, t_det_us, det: FrameDetections, fits, tps) -> np.ndarray:
    """a_p (33,): the mean diagonal of the detection terms' Hessian (E_2D + E_3D, weighted) at the window's fits, /2:
    what a parameter's detections weigh per rad² in the window's energy (:mod:`eventcap.energy.prior`)."""
    window = Window(int(t_det_us[0]), int(t_det_us[-1]), t_det_us=t_det_us, detections=det)
    seen = np.isfinite(fits).all(axis=1)
    diag = np.zeros((det.n, _NP))
    for name, aux in (("2d", None), ("3d", np.nan_to_num(tps))):
        f = solver.factor(name)
        if f is not None:
            f.prepare(window)
            diag += np.einsum("dpp->dp", f.linearize(np.where(seen[:, None], fits, 0.0), aux, 2).diag)
    return np.maximum(diag[seen].mean(0) / 2.0, 0.0)


def context_gains(solver: SplineSolver, t_ctx_us, det_ctx: FrameDetections, window_fits, window_tp, t_det_us,
                  det: FrameDetections) -> tuple[PriorGain, int]:
    """The prior's gains and the context pull of a window (:func:`eventcap.energy.prior.choose_prior_gains`) from
    the per-frame fits at the intensity frames around it (t_ctx_us, det_ctx); frames whose fit fails are left out.
    Returns (PriorGain, fits computed here)."""
    c = solver.config
    keep, fits, computed = frame_fits(solver, det_ctx)
    S = []
    for s in fits:
        S.append(unwrap_root(s, S[-1]) if S else s)
    pg = choose_prior_gains(
        np.asarray(t_ctx_us, dtype=np.int64)[keep], np.stack(S) if S else np.zeros((0, _NP)),
        lambda: detection_curvature(solver, t_det_us, det, window_fits, window_tp), float(c.lambda_prior),
        float(c.prior_gain_max), str(c.prior_gain_criterion), t_det_us if c.lambda_context > 0 else None,
        window_fits, unwrap_root)
    return pg, computed


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
    from eventcap.energy.floor import floor_height, sole_points

    _, S, computed = frame_fits(solver, det)
    if not S:
        return None, computed
    return floor_height(sole_points(np.stack(S), solver.template)[..., 1]), computed


# --------------------------------------------------------------------------------------------- a window
def solve_window(solver: SplineSolver, spline: UniformCubicBSpline, t_det_us: np.ndarray, det: FrameDetections,
                 t_cor_us: np.ndarray, xy: np.ndarray, valid: np.ndarray, what: str = "window",
                 context: tuple[np.ndarray, FrameDetections] | None = None, events: np.ndarray | None = None,
                 t_sil_us: np.ndarray | None = None, base_gain: np.ndarray | None = None,
                 floor_y: float | None = None, start: tuple[np.ndarray, np.ndarray] | None = None) -> WindowResult:
    """Solve one window (module doc) with the solver's config: fits at its detection frames, a smoothing spline
    through them as the start, then ``icp_rounds`` alternations of correspondence search (at the current spline's
    poses at t_cor_us, with the tracks xy (n_cor, H, 2) / valid (n_cor, H)) and IPOPT. SolveFailed on a failed
    solve.

    context: (times, detections) of the intensity frames around the window from which the prior's gain per
    parameter and the context pull are chosen (:func:`context_gains`); None: the prior is λ_prior for every
    parameter, no pull. events: the recording's events over the window, for E_still (each joint's stillness per
    knot interval, measured around the start spline's projected bones, :func:`window_silence`) and E_sil (the
    silhouette of the current spline at t_sil_us matched to its closest events every round). base_gain: the motion
    prior's fixed gain per pose parameter (33,) (the inertia each turns), times the chosen gains; None: 1. floor_y:
    the floor's height over the capture (:func:`capture_floor`; None: the floor terms hold nothing). start:
    (control points (n_ctrl, 33), t' (D, 3)) the solve starts from instead of the smoothing spline through the fits
    and the fits' t' (rows with a NaN are taken from those); E_still is measured around the fits' spline either
    way (benchmarks/speed/bench_warm_start.py starts a window from its neighbour's solution)."""
    c = solver.config
    if solver.factor("sil") is not None and t_sil_us is None:
        raise EnergyError("E_sil (lambda_sil > 0): the window's silhouette frames t_sil_us are missing")
    if not (math.isfinite(c.robust_cor_px) and c.robust_cor_px >= 0):
        raise EnergyError(f"robust_cor_px: expected a Cauchy scale in pixels >= 0, got {c.robust_cor_px!r}")
    seconds = {}
    t0 = time.perf_counter()
    fits, tps, _, n_fits = fit_window(solver, det)
    seen = np.isfinite(fits).all(axis=1)
    if not seen.any():
        raise NothingObserved(f"{what}: none of the window's {det.n} detection frames holds an observation (no "
                              f"person detected there): nothing to estimate")
    window = Window(spline.t0_us, spline.t1_us, t_det_us=np.asarray(t_det_us, dtype=np.int64), detections=det,
                    t_cor_us=np.asarray(t_cor_us, dtype=np.int64), correspondences=Correspondences.empty(),
                    knots_us=spline.t0_us + spline.h_us * np.arange(spline.n_seg + 1, dtype=np.int64),
                    events=events, floor_y=floor_y)
    pg = None
    if context is not None and (c.prior_gain_max > 1 or c.lambda_context > 0):
        pg, computed = context_gains(solver, context[0], context[1], fits, tps, window.t_det_us, det)
        n_fits += computed
    gain = None if pg is None else pg.gain
    if base_gain is not None:
        gain = np.asarray(base_gain, dtype=np.float64) * (1.0 if gain is None else gain)
    window.prior_gain = gain
    # Start: a penalised spline through the fits (the same prior; fits weighted as ~1 per rad² of error).
    smooth = max(float(c.lambda_prior), 1e-12) * (1.0 if gain is None else gain)
    C = np.clip(spline.fit(np.asarray(t_det_us)[seen], fits[seen], smooth=smooth, deriv=solver.order),
                solver.lower, solver.upper)
    x = start_vector(solver, *_start(solver, C, np.nan_to_num(tps), start))
    seconds["fit"] = time.perf_counter() - t0
    sil, pull_frames = None, (None if pg is None else (None if pg.pull is None else pg.pull[1]))
    if c.lambda_still > 0 and events is not None:
        t1 = time.perf_counter()
        sil = window_silence(solver, spline, C, events)
        window.stillness = sil.stillness
        seconds["silence"] = time.perf_counter() - t1
        if pull_frames is not None:  # a part the events see move is not held to the frames' smoother
            pull_frames = pull_frames * still_gate(sil, t_det_us, float(c.context_gate_floor))
    if pull_frames is not None:  # no pull where the smoother has no value (a frame without an observation)
        target, frames = pg.pull[0], pull_frames
        held = np.isfinite(target).all(axis=1)
        window.pull = (np.where(held[:, None], target, 0.0), pg.curvature * np.where(held[:, None], frames, 0.0))
    x, solves, n_sil_matched, n_boundary, changes = _icp(solver, spline, window, x, xy, valid, t_sil_us, what,
                                                         seconds)
    res = _result(solver, spline, window, x, fits, solves, seconds, n_fits, gain, sil, pull_frames, n_sil_matched,
                  n_boundary)
    return dataclasses.replace(res, cor_change_px=changes)


def _start(solver: SplineSolver, C: np.ndarray, tps: np.ndarray, start) -> tuple[np.ndarray, np.ndarray]:
    """The solve's start: C and tps, with the finite rows of ``start`` (control points, t') in their place."""
    if start is None:
        return C, tps
    C0, T0 = (np.asarray(a, dtype=np.float64) for a in start)
    if C0.shape != C.shape or T0.shape != tps.shape:
        raise EnergyError(f"start: expected control points {C.shape} and t' {tps.shape}, got {C0.shape} and "
                          f"{T0.shape}")
    rows = np.isfinite(C0).all(axis=1)
    C = C.copy()
    C[rows] = np.clip(C0[rows], solver.lower, solver.upper)
    keep = np.isfinite(T0).all(axis=1)
    return C, np.where(keep[:, None], T0, tps)


def start_vector(solver: SplineSolver, C: np.ndarray, tps: np.ndarray) -> np.ndarray:
    """The decision vector of control points C and the detection frames' t' (for E_3D's variables, if any)."""
    x = np.zeros(solver.problem.nx)
    x[:solver.problem.nU] = C.ravel()
    for f, sl in zip(solver.problem.factors, solver.problem.aux_slices):
        if sl is not None and f.name == "3d":
            x[sl] = tps.ravel()
    return x


def _icp(solver: SplineSolver, spline, window: Window, x, xy, valid, t_sil_us, what, seconds):
    """``icp_rounds`` alternations of correspondence search and solve (or one solve without correspondences when
    icp_rounds is 0). From the second round on, a search whose correspondences moved E_cor by less than
    ``icp_settle_px`` (:func:`correspondence_change_px` at the last solution) ends the rounds: the last solve stands.
    Returns (x, solve stats, silhouette pixels matched, silhouette pixels) of the last round and each later
    search's change (px)."""
    c, prob = solver.config, solver.problem
    seconds["correspondences"] = seconds["solve"] = 0.0
    index = None
    if t_sil_us is not None:
        window.t_sil_us = np.asarray(t_sil_us, dtype=np.int64)
    if prob.factor("sil") is not None and window.events is not None:
        t1 = time.perf_counter()
        cam = solver.camera
        index = EventIndex(window.events, cam.width, cam.height, window.t_sil_us, int(round(c.sil_window_ms * 1000)),
                           DENOISE_US)
        seconds["silhouette"] = time.perf_counter() - t1
    cor = prob.factor("cor")
    solves, n_matched, n_boundary, changes = [], 0, 0, []
    for r in range(int(c.icp_rounds)):
        t1 = time.perf_counter()
        Cx = x[:prob.nU].reshape(prob.n_units, _NP)
        Se = spline.evaluate(Cx, window.t_cor_us)
        found = find_correspondences(solver.template, solver.camera, Se, xy, valid, c.edge_margin_px)
        if r > 0 and cor is not None:  # how far this search moved E_cor from what the last solve fitted
            changes.append(correspondence_change_px(
                window.correspondences, cor.residuals_px_of(window.correspondences, Se, window.cor_relative),
                found, cor.residuals_px_of(found, Se, window.cor_relative)))
            if changes[-1] < float(c.icp_settle_px):  # settled: the last solve stands
                seconds["correspondences"] += time.perf_counter() - t1
                break
        window.correspondences = found
        window.cor_weight = None
        if index is not None:
            t3 = time.perf_counter()
            window.silhouette, n_boundary, _ = find_silhouette_correspondences(
                solver.template, solver.camera, spline.evaluate(Cx, window.t_sil_us), index, float(c.sil_dist),
                int(c.sil_patch_px))
            n_matched = window.silhouette.n
            seconds["silhouette"] += time.perf_counter() - t3
        if c.robust_cor_px > 0 and r > 0 and window.correspondences.n and cor is not None:
            cor.set_correspondences(window.correspondences, relative=True)
            e2 = np.sum(cor.residuals_px(Se) ** 2, axis=1)
            window.cor_weight = 1.0 / (1.0 + e2 / float(c.robust_cor_px) ** 2)
        window.estimate = _estimate(spline, Cx.copy())
        t2 = time.perf_counter()
        prob.set_window(spline, window, x)
        x, st = prob.solve(x, f"{what}: spline solve (ICP round {r + 1})")
        solves.append(SolveStats(st.status, st.iterations, st.seconds, window.correspondences.n))
        seconds["correspondences"] += t2 - t1
        seconds["solve"] += time.perf_counter() - t2
    if int(c.icp_rounds) == 0:  # detections and prior only (no events)
        window.estimate = _estimate(spline, x[:prob.nU].reshape(prob.n_units, _NP).copy())
        prob.set_window(spline, window, x)
        x, st = prob.solve(x, f"{what}: spline solve (no correspondences)")
        solves.append(st)
    return x, solves, n_matched, n_boundary, tuple(changes)


def _estimate(spline: UniformCubicBSpline, C: np.ndarray):
    return lambda t_us: spline.evaluate(C, t_us)


def _result(solver, spline, window, x, fits, solves, seconds, n_fits, gain, sil, pull_frames, n_sil_matched,
            n_boundary) -> WindowResult:
    prob = solver.problem
    terms = prob.terms(x)
    energies = {name: terms.get(name, 0.0) for name in ("2d", "3d", "cor", "prior", "still", "sil", "context", "floor",
                                                        "slide", "bones")}
    energies.update({"total": prob.evaluate(x, 0)["value"], "n_correspondences": window.correspondences.n,
                     "n_silhouette": n_sil_matched, "n_boundary": n_boundary})
    U, aux = prob.split(x)
    f3 = next((a for f, a in zip(prob.factors, aux) if f.name == "3d"), None)
    return WindowResult(spline=spline, control=U.copy(), t_prime=np.zeros((fits.shape[0], 3)) if f3 is None
                        else f3.copy(), fits=fits, energies=energies, solves=tuple(solves), seconds=seconds,
                        fits_computed=n_fits, prior_gain=gain, silence=sil, pull_frames=pull_frames)


def window_silence(solver: SplineSolver, spline: UniformCubicBSpline, C: np.ndarray, events: np.ndarray) -> Silence:
    """The joints' stillness per knot interval of one window (:mod:`eventcap.energy.silence`), the bones projected at
    each interval's middle from the spline with control points C; settings ``still_*`` of the config."""
    c = solver.config
    edges = spline.t0_us + spline.h_us * np.arange(spline.n_seg + 1, dtype=np.int64)
    mids = (edges[:-1] + edges[1:]) // 2
    joints = joint_positions(spline.evaluate(C, mids), solver.template.rest_joints)
    cam = solver.camera
    return measure_silence(events, edges, cam.project(joints), cam.height, cam.width,
                           radius_px=int(c.still_radius_px), rate_hz=float(c.still_rate_hz),
                           hold_bins=int(round(c.still_hold_ms / c.knot_ms)),
                           sweep_bins=int(round(c.still_sweep_ms / c.knot_ms)))


__all__ = ["NothingObserved", "SplineSolver", "WindowResult", "capture_floor", "clear_fits", "context_gains", "fit_window",
           "frame_fit", "frame_fits", "observed_frames", "solve_window", "window_silence"]
