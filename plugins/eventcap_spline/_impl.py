"""Run function of the spline stage (imported when the stage runs)."""

from __future__ import annotations

import functools
import math

import numpy as np

from eventcap.artifacts.pose import PoseSequence
from eventcap.analysis.motion import tracking_times_us
from eventcap.core.stage import StageFailed

#: Built solvers of this process, keyed by value (template, camera, window layout, config): built once per run.
_SOLVERS: dict = {}
_SOLVERS_MAX = 16


def window_of(n_batches: int, k: int, half: int) -> tuple[int, int]:
    """First and last batch (inclusive) of batch k's window: 2·half + 1 batches centred on k, shifted inwards at
    the ends of the recording (all batches when there are fewer)."""
    if n_batches <= 2 * half + 1:
        return 0, n_batches - 1
    a = min(max(k - half, 0), n_batches - 2 * half - 1)
    return a, a + 2 * half


@functools.lru_cache(maxsize=64)
def window_plan(n_batches: int, half: int, step: int) -> tuple[tuple[int, int, int, int, int], ...]:
    """The windows solved when windows advance by ``step`` batches: (solving batch, a, z, ka, kz) each, the window of
    batches a..z (:func:`window_of` of the solving batch) keeping batches ka..kz.

    The batches are cut into consecutive runs of ``step`` (the last may be shorter); each run is kept by one window,
    solved by the run's middle batch (the earlier of two middles). Near the ends of the recording windows shift
    inwards, so two runs' windows can be the same batches: such runs are one run, kept by that window solved once.
    step 1: every batch solves its own window and keeps itself (no runs are joined). Windows must overlap to be
    blended: ValueError unless 1 <= step <= max(1, 2·half)."""
    if not 1 <= step <= max(1, 2 * half):
        raise ValueError(f"window step {step}: expected 1 .. max(1, 2·half_window) = {max(1, 2 * half)} "
                         "(neighbouring windows must overlap to be blended)")
    plan: list[list[int]] = []
    for ka in range(0, n_batches, step):
        kz = min(ka + step, n_batches) - 1
        c = ka + (kz - ka) // 2
        a, z = window_of(n_batches, c, half)
        if step > 1 and plan and (plan[-1][1], plan[-1][2]) == (a, z):
            plan[-1][4] = kz
        else:
            plan.append([c, a, z, ka, kz])
    return tuple(tuple(w) for w in plan)


def window_role(n_batches: int, k: int, half: int, step: int) -> tuple[int, int, int, int] | None:
    """Batch k's part in the :func:`window_plan`: (a, z, ka, kz) when batch k solves the window of batches a..z that
    keeps batches ka..kz; None when it solves none (another batch's window keeps it: :func:`kept_by`)."""
    if not 0 <= k < n_batches:
        raise ValueError(f"batch {k}: expected 0 .. {n_batches - 1}")
    for c, a, z, ka, kz in window_plan(n_batches, half, step):
        if c == k:
            return a, z, ka, kz
    return None


def unit_role(plan, unit, half: int, step: int) -> tuple[int, tuple[int, int, int, int] | None]:
    """The batches a unit of the solve (a batch, or a chunk of batches: the node's plan) keeps, and its window:
    (its first batch, (a, z, ka, kz) or None). A unit of one batch takes its part in the :func:`window_plan` (None:
    another batch's window keeps it). A chunk keeps its batches ka..kz, and its window is them with ``half``
    batches on each side, shifted inwards at the ends of the recording (all batches when there are fewer); then
    windows advance by whole chunks, and ``step`` must be 1."""
    t0, t1 = np.asarray(plan.t0_us), np.asarray(plan.t1_us)
    kept = np.flatnonzero((t0 >= unit.t0_us) & (t1 <= unit.t1_us))
    if kept.size == 0:
        raise StageFailed(f"{unit_name(unit)}: none of the recording's {len(plan)} batches lies in it "
                          f"({unit.t0_us}..{unit.t1_us} us)", status="invalid_input")
    ka, kz, n = int(kept[0]), int(kept[-1]), len(plan)
    if ka == kz:
        return ka, window_role(n, ka, half, step)
    if step != 1:
        raise StageFailed(f"stages.solve.window_step: {step} applies to a solve per batch; a solve per chunk keeps "
                          f"its chunk's batches (window_step must be 1)", status="invalid_config")
    length = kz - ka + 1 + 2 * half
    if length >= n:
        return ka, (0, n - 1, ka, kz)
    a = min(max(ka - half, 0), n - length)
    return ka, (a, a + length - 1, ka, kz)


def unit_name(unit) -> str:
    """How messages name a unit of the solve: its index in the node's plan."""
    return f"unit {unit.index}"


def kept_by(n_batches: int, k: int, half: int, step: int) -> int:
    """The batch whose window keeps batch k (:func:`window_plan`)."""
    return next(c for c, _, _, ka, kz in window_plan(n_batches, half, step) if ka <= k <= kz)


def cor_frames(n_frames: int, step: int) -> np.ndarray:
    """Indices of the tracking frames whose poses E_cor compares: every ``step``-th, always with the last."""
    idx = np.arange(0, n_frames, step)
    return idx if idx[-1] == n_frames - 1 else np.append(idx, n_frames - 1)


def window_tracks(parts, step: int, where: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The tracks of several consecutive batches as one set for E_cor: (t_us (n_cor,), xy (n_cor, H, 2), valid
    (n_cor, H)). Each batch contributes its correspondence frames (every ``step``-th tracking frame and its last,
    :func:`cor_frames`) and its own columns of tracks, valid only within its own frames; neighbouring batches share
    their boundary frame."""
    times, cols = [], []
    for part in parts:
        t = np.asarray(part.t_us, dtype=np.int64)
        if t.size < 2:
            raise StageFailed(f"{where}: {t.size} tracking frame(s) in a batch of the window; need at least 2",
                              status="invalid_input")
        idx = cor_frames(t.size, step)
        times.append(t[idx])
        cols.append((idx, np.asarray(part.xy, dtype=np.float64), np.asarray(part.valid)))
    t_cor = np.unique(np.concatenate(times))
    H = sum(xy.shape[1] for _, xy, _ in cols)
    xy_all = np.full((t_cor.size, H, 2), np.nan)
    valid_all = np.zeros((t_cor.size, H), dtype=bool)
    o = 0
    for t_p, (idx, xy, valid) in zip(times, cols):
        rows = np.searchsorted(t_cor, t_p)
        h = xy.shape[1]
        xy_all[rows, o:o + h] = xy[idx]
        valid_all[rows, o:o + h] = valid[idx]
        o += h
    bad = valid_all & ~np.all(np.isfinite(xy_all), axis=-1)
    if bad.any():
        raise StageFailed(f"{where}: a track has a non-finite position where it is marked valid", status="invalid_input")
    return t_cor, xy_all, valid_all


def prior_context(config, plan, t_det, detections, where: str, log):
    """(times, detections) of the detections within ``smoothing.seconds`` of the window's detection frames t_det
    (at the intensity frames, and between them where the detector looked), whose fits give the window's evidence
    of the motion (the prior's process power, the context pull); None (and a log line) when the intensity frames come
    less often than ``smoothing.min_fps``. StageFailed when their detections are missing."""
    from eventcap.energy.detections import detection_times, select_detections

    frames = np.unique(np.concatenate([plan.t0_us, plan.t1_us]))
    fps = 1e6 / float(np.median(np.diff(frames))) if frames.size > 1 else 0.0
    if fps < float(config.smoothing.min_fps):
        log.info("%s: no smoothing evidence from the fits around the window (no prior gains, no context pull): "
                 "intensity frames at %.1f fps, below stages.solve.smoothing.min_fps (%g)", where, fps,
                 float(config.smoothing.min_fps))
        return None
    reach = int(round(float(config.smoothing.seconds) * 1e6))
    t_ctx = detection_times(detections, int(t_det[0]) - reach, int(t_det[-1]) + reach)
    try:
        return t_ctx, select_detections(detections, t_ctx)
    except ValueError as exc:
        raise StageFailed(f"{where}: the prior's context: {exc}", status="missing_detections") from exc


def capture_template(rec, config, layout, plan, detections, where: str, ctx):
    """The template of the solve: the recording's, with the detector's hip and shoulder widths measured over the
    capture (eventcap.energy.landmarks) unless ``landmarks`` is template (the same in every
    window, kept per process); the log says which."""
    from eventcap.energy.detections import select_detections
    from eventcap.energy.errors import SolveFailed
    from eventcap.energy.landmarks import measure_widths, with_widths

    from .solve import frame_fit

    if config.landmarks == "template":
        return rec.template
    frames = np.unique(np.concatenate([plan.t0_us, plan.t1_us]))
    try:
        det = select_detections(detections, frames)
    except ValueError as exc:
        raise StageFailed(f"{where}: the landmark widths: {exc}", status="missing_detections") from exc
    key = ("widths", rec.template.geometry_digest(), repr(config), frames.tobytes(),
           *(np.ascontiguousarray(a).tobytes() for a in (det.keypoints_2d, det.confidence_2d, det.joints_3d,
                                                          det.confidence_3d)))
    if key not in _FLOORS:
        _bound_captures()
        plain = fit_solver_for(rec.template, rec.camera, config)
        fits, keep = [], []
        for d in range(det.n):
            try:
                fits.append(frame_fit(plain, det, d)[0][0])
                keep.append(d)
            except SolveFailed:
                continue
        widths = measure_widths(rec.template, rec.camera, np.asarray(fits), det.rows(keep)) if keep else None
        if widths is None:
            _FLOORS[key] = rec.template
        else:
            _FLOORS[key] = with_widths(rec.template, widths)
            ctx.log.info("%s: where the detector puts the joints, over the capture (stages.solve.landmarks=%s): %s",
                         where, config.landmarks,
                         "; ".join(f"{k} {v:.3f} of the template's ({widths.frames[k]} frames)"
                                   for k, v in widths.scale.items()))
            ctx.stats["landmark_widths"] = dict(widths.scale)
    return _FLOORS[key]


def capture_floor_of(solver, plan, detections, where: str, log) -> float | None:
    """The floor's height over the capture (the floor evidence of every window; asked for by the factors that need
    it), from the per-frame fits at every intensity frame of the plan (eventcap_spline.solve.capture_floor; the
    same in every window, kept per process)."""
    from eventcap.energy.detections import select_detections

    from .solve import capture_floor

    frames = np.unique(np.concatenate([plan.t0_us, plan.t1_us]))
    try:
        det = select_detections(detections, frames)
    except ValueError as exc:
        raise StageFailed(f"{where}: the floor: {exc}", status="missing_detections") from exc
    key = (id(solver), frames.tobytes(), *(np.ascontiguousarray(a).tobytes() for a in (
        det.keypoints_2d, det.confidence_2d, det.joints_3d, det.confidence_3d)))
    if key not in _FLOORS:
        _bound_captures()
        _FLOORS[key] = capture_floor(solver, det)[0]
        h = _FLOORS[key]
        log.info("%s: the floor over the capture: y = %s (median lowest sole point of the fits at %d intensity "
                 "frames)", where, "unknown" if h is None else f"{h:.3f} m", frames.size)
    return _FLOORS[key]


#: What a process measured over a capture (the solve's template, the floor), by capture and settings.
_FLOORS: dict = {}


def _bound_captures() -> None:
    if len(_FLOORS) >= 8:
        _FLOORS.clear()


def solver_for(template, camera, layout, config):
    """The built solver for this window layout and config (built once per process, keyed by value)."""
    from eventcap.energy.errors import EnergyError

    from .solve import SplineSolver

    key = (template.geometry_digest(), repr(sorted(camera.to_dict().items())), layout, repr(config))
    solver = _SOLVERS.get(key)
    built = solver is None
    if built:
        try:
            solver = SplineSolver(template, camera, layout, config)
        except EnergyError as exc:
            raise StageFailed(f"stages.solve: {exc}", status=exc.status) from exc
        if len(_SOLVERS) >= _SOLVERS_MAX:
            _SOLVERS.clear()
        _SOLVERS[key] = solver
    return solver, built


def fit_solver_for(template, camera, config):
    """The per-frame fits' solver for this template, camera and config (built once per process, keyed by value)."""
    from eventcap.energy.errors import EnergyError

    from .solve import FitSolver

    key = ("fits", template.geometry_digest(), repr(sorted(camera.to_dict().items())), repr(config))
    if key not in _SOLVERS:
        try:
            solver = FitSolver(template, camera, config)
        except EnergyError as exc:
            raise StageFailed(f"stages.solve: {exc}", status=exc.status) from exc
        if len(_SOLVERS) >= _SOLVERS_MAX:
            _SOLVERS.clear()
        _SOLVERS[key] = solver
    return _SOLVERS[key]


def clear_solvers() -> None:
    """Forget this process's built solvers and per-frame fits."""
    from .solve import clear_fits

    _SOLVERS.clear()
    _FLOORS.clear()
    clear_fits()


def check_config(config) -> None:
    """StageFailed naming the key of a value that its declaration allows but the solve cannot use (the bounds of
    each setting are its declaration's, checked before anything runs)."""
    most = max(1, 2 * int(config.half_window))
    if int(config.window_step) > most:
        raise StageFailed(f"stages.solve.window_step: expected at most max(1, 2·half_window) = {most} (neighbouring "
                          f"windows must overlap to be blended), got {config.window_step}", status="invalid_config")
    if round(float(config.knot_ms) * 1000) < 1:
        raise StageFailed(f"stages.solve.knot_ms: expected at least 0.001 ms (1 µs), got {config.knot_ms!r}",
                          status="invalid_config")


def window_inputs(inputs, config, where: str, role: tuple[int, int, int, int]):
    """The data of a unit's window (role: :func:`unit_role`, the window a..z keeping batches ka..kz): (the first
    kept batch that has tracks, its tracks, window (a, z), the batches whose tracks E_cor uses, their index among
    the tracks, detection times, their detections, the tracks at the correspondence frames
    (:class:`eventcap.energy.window.Tracks`), the tracking times of each batch the window keeps)."""
    from eventcap.energy.detections import detection_times, select_detections
    from eventcap.energy.window import Tracks

    sliced, detections, plan = inputs["sliced"], inputs["detections"], inputs["batches"]
    a, z, ka, kz = role
    # every batch's tracks, as the runner hands them (runner.BatchSequence: .batches names them, loaded on access)
    index = {bb.index: i for i, bb in enumerate(sliced.batches)}
    present = [k for k in range(ka, kz + 1) if k in index]  # batches= may select part of a chunk
    if not present:
        raise StageFailed(f"{where}: no tracks of {'batch' if ka == kz else 'batches'} {ka}"
                          f"{'' if ka == kz else f'..{kz}'} among the {len(sliced)} given", status="invalid_input")
    b = present[0]
    own = sliced[index[b]]
    t_us = np.asarray(own.t_us, dtype=np.int64)
    if t_us.size < 2:
        raise StageFailed(f"{where}: {t_us.size} tracking frame(s); need at least 2", status="invalid_input")
    # own: the tracks of the batches the window keeps (this batch alone at window_step 1); window: all of its batches
    kept = [k for k in range(ka, kz + 1) if k in index]
    scope = kept if config.tracks.scope == "own" else [k for k in range(a, z + 1) if k in index]
    # every detection within the window's span: at its intensity frames, and between them where the detector looked
    t_det = detection_times(detections, int(plan.t0_us[a]), int(plan.t1_us[z]))
    if t_det.size < 2:
        t_det = np.unique(np.concatenate([plan.t0_us[a:z + 1], plan.t1_us[a:z + 1]]))
    try:
        det = select_detections(detections, t_det)
    except ValueError as exc:
        raise StageFailed(f"{where}: {exc}", status="missing_detections") from exc
    problems = det.problems()
    if problems:
        raise StageFailed(f"{where}: detections unusable: " + "; ".join(problems), status="invalid_input")
    part = (lambda k: own if k == b else sliced[index[k]])
    t_cor, xy, valid = window_tracks([part(k) for k in scope], int(config.tracks.step), where)
    tracks = Tracks(t_cor, xy, valid, float(config.tracks.edge_margin_px))
    kept_times = tuple(np.asarray(part(k).t_us, dtype=np.int64) for k in kept)
    return b, own, (a, z), scope, index, t_det, det, tracks, kept_times


def window_times(sliced, index, plan, b: int, a: int, z: int, t_us: np.ndarray) -> np.ndarray:
    """The window's batches' tracking times (one grid for the whole recording, eventcap.analysis.motion.tracking_times_us), so
    overlapping windows give the same times. They follow from the plan at the step of batch b (the unit's first)
    when that step reproduces its own times (a whole number of µs: 1 kHz); else they are read from the batches' tracks."""
    rate = 1e6 / int(np.median(np.diff(t_us)))
    whole_us = np.array_equal(tracking_times_us(int(plan.t0_us[b]), int(plan.t1_us[b]), rate), t_us)
    return np.unique(np.concatenate([
        np.asarray(sliced[index[k]].t_us, dtype=np.int64) if k in index and not whole_us
        else tracking_times_us(int(plan.t0_us[k]), int(plan.t1_us[k]), rate) for k in range(a, z + 1)]))


def run_spline(inputs, config, ctx):
    from eventcap.energy.errors import EnergyError, SolveFailed
    from eventcap.energy.factor import Layout
    from eventcap.energy.problem import SplinePoses, coupling_band
    from eventcap.energy.spline import UniformCubicBSpline
    from eventcap.energy.terms import FACTORS, sample_times
    from eventcap.energy.window import WindowInputs
    from eventcap.worldframe import upright

    from .solve import NothingObserved, observed_frames, solve_window

    inputs = {**inputs, "recording": upright(inputs["recording"], inputs["detections"])}  # the detections' world
    rec, plan, unit = inputs["recording"], inputs["batches"], ctx.batch
    where = f"batch {unit.index}" if unit is not None else "batch ?"
    if rec.template is None:
        raise StageFailed(f"stage 'spline' needs the actor template, but recording {rec.name or rec.source!r} has "
                          "none", status="missing_template")
    if unit is None:
        raise StageFailed("stage 'spline' runs per batch (no batch given)", status="invalid_input")
    check_config(config)
    step = int(config.window_step)
    b, role = unit_role(plan, unit, int(config.half_window), step)
    if role is not None and role[2] < role[3]:  # a chunk of batches
        where = f"chunk {unit.index} (batches {role[2]}..{role[3]})"
    if role is None:  # another batch's window keeps this batch (windows advance by window_step batches)
        ctx.stats["kept_by"] = kept_by(len(plan), b, int(config.half_window), step)
        return {"poses": PoseSequence(t_us=np.zeros(0, dtype=np.int64), poses=np.zeros((0, 33)), status="in_window",
                                      iterations=0, energies={})}
    b, own, (a, z), scope, index, t_det, det, tracks, kept_times = window_inputs(inputs, config, where, role)
    h_us = int(round(config.knot_ms * 1000))
    n_seg = int(math.ceil((t_det[-1] - t_det[0]) / h_us))
    spline = UniformCubicBSpline(int(t_det[0]), h_us, n_seg)
    data = WindowInputs(spline.t0_us, spline.t1_us,
                        knots_us=spline.t0_us + spline.h_us * np.arange(n_seg + 1, dtype=np.int64),
                        t_det_us=t_det, detections=det, tracks=tracks, track_times_us=kept_times,
                        events=rec.events.window(int(t_det[0]), int(t_det[-1]) + 1), contact=config.contact)
    times = sample_times(config.terms, data)
    band = max([coupling_band(SplinePoses(n_seg, spline), tracks.t_us)]  # how far coupled samples reach
               + [coupling_band(SplinePoses(n_seg, spline), t) for k, t in times.items()
                  if FACTORS[k].couples_neighbours and t.size > 1])
    layout = Layout(n_seg=n_seg, sizes=tuple((k, int(t.size)) for k, t in times.items()), band=band)
    template = capture_template(rec, config, layout, plan, inputs["detections"], where, ctx)
    solver, built = solver_for(template, rec.camera, layout, config)
    if built:
        ctx.log.info("built the spline NLP (%d control points; terms %s) in %.2f s (once per process)",
                     spline.n_ctrl, ", ".join(f"{f.name} ({f.n})" for f in solver.factors), solver.build_seconds)
        ctx.stats["build_s"] = solver.build_seconds
    what = f"{where} (window of batches {a}..{z})"
    context = prior_context(config, plan, t_det, inputs["detections"], where, ctx.log)
    t_win = window_times(inputs["sliced"], index, plan, b, a, z, np.asarray(own.t_us, dtype=np.int64))
    data.offer("floor_y", lambda: capture_floor_of(solver, plan, inputs["detections"], where, ctx.log))
    try:
        res = solve_window(solver, spline, data, what=what, context=context)
    except NothingObserved as exc:  # a gap: nothing was seen, so nothing is estimated (stitch leaves it out)
        ctx.log.warning("%s: a gap: %s", where, str(exc).removeprefix(f"{what}: "))
        ctx.stats["gap"] = True
        return {"poses": PoseSequence(t_us=t_win, poses=np.full((t_win.size, 33), np.nan), status="gap",
                                      iterations=0, energies={})}
    except (StageFailed, SolveFailed, EnergyError) as exc:  # name the window in every failure (the fits' too)
        msg = str(exc) if what in str(exc) else f"{what}: {exc}"
        raise StageFailed(msg, status=getattr(exc, "status", "failed"), details=getattr(exc, "details", {})) from exc
    # The output is the window's curve at the tracking rate, between its first and last detection frame that holds
    # an observation (NaN beyond: never extrapolated); stitch blends the overlapping windows.
    poses = spline.evaluate(res.control, t_win)
    seen = t_det[observed_frames(det)]
    poses[(t_win < seen[0]) | (t_win > seen[-1])] = np.nan
    # The window unwrapped its root angles from its own first fit: one branch per window (its first pose's root
    # angles in (-π, π]); stitch aligns neighbouring windows' branches before blending.
    first = int(np.flatnonzero(np.isfinite(poses[:, 0]))[0])
    poses[:, 27:30] -= 2.0 * np.pi * np.round(poses[first, 27:30] / (2.0 * np.pi))
    sigma = res.covariance.joint_sigma_mm(spline.basis(t_win), poses, template).astype(np.float32)  # the Laplace σ
    log_window(ctx, config, res, where, (a, z), t_det, scope, spline)
    energies = {k: (int(v) if k.startswith("n_") else float(v)) for k, v in res.energies.items()}
    iters = int(sum(s.iterations for s in res.solves))
    return {"poses": PoseSequence(t_us=t_win, poses=poses, sigma_mm=sigma, status=res.solves[-1].status,
                                  iterations=iters, energies=energies)}


def log_window(ctx, config, res, where, window, t_det, scope, spline) -> None:
    """The window's log lines and run statistics: the solve's, and what each factor says of its data."""
    a, z = window
    iters = int(sum(s.iterations for s in res.solves))
    secs = sum(res.seconds.values())
    ctx.log.info("%s: window of batches %d..%d (%d frames of detections, %d fitted here, %d control points, tracks "
                 "of %s), %d IPOPT iterations, %.2f s (%s)", where, a, z, t_det.size, res.fits_computed,
                 spline.n_ctrl, f"batch {scope[0]}" if len(scope) == 1 else f"{len(scope)} batches", iters, secs,
                 res.solves[-1].status)
    for line in res.lines:
        ctx.log.info("%s: %s", where, line)
    if res.association_change_px and len(res.solves) < int(config.icp_rounds):
        ctx.log.info("%s: the association settled after ICP round %d (it moved the residuals by %.3g px, below "
                     "stages.solve.icp_settle_px = %g): %d of %d rounds", where, len(res.solves),
                     res.association_change_px[-1], float(config.icp_settle_px), len(res.solves),
                     int(config.icp_rounds))
    if config.tracks.scope == "window" and len(scope) < z - a + 1:
        ctx.log.warning("%s: only %d of the window's %d batches have tracks (batches= selects part of the plan)",
                        where, len(scope), z - a + 1)
    if res.stillness is not None:
        st = res.stillness.stillness
        ctx.log.info("%s: event silence: background %.2f events/px/s; %.0f%% of (knot interval, joint) pairs still "
                     "(stillness > 0.5)", where, res.stillness.background_hz, 100.0 * float(np.mean(st > 0.5)))
        ctx.stats["stillness_mean"] = [float(v) for v in st.mean(0)]
        ctx.stats["background_hz"] = res.stillness.background_hz
    for rep in res.reports.values():
        ctx.stats.update({k: v for k, v in rep.items() if not k.startswith("n_")})
    ctx.stats.update({"solve_s": secs, "phases_s": res.seconds, "iterations": iters, "window": [a, z],
                      "fits_computed": res.fits_computed,
                      "solves": [[s.status, s.iterations, s.seconds] for s in res.solves],
                      "association_change_px": [float(v) for v in res.association_change_px],
                      **{k: v for k, v in res.energies.items() if k.startswith("n_")}})
