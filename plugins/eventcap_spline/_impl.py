"""Run function of the spline stage (imported when the stage runs).

One way through a unit of the solve (:func:`run_spline`): the stage's ``terms`` decoded once (a
:class:`eventcap.energy.terms.TermSet`); the unit's part in the plan of windows (:func:`unit_role`); its window
planned once (:class:`eventcap_spline.plan.WindowPlan`); every term that is on checked against what the window
provides (a term that reads something the solve does not offer fails here, naming the setting that turns it off);
the capture's template and the built solver (once per process); the window solved
(:func:`eventcap_spline.solve.solve_window`); its curve output at the tracking rate.
"""

from __future__ import annotations

import functools

import numpy as np

from eventcap.artifacts.pose import PoseSequence
from eventcap.core.stage import StageFailed
from eventcap.energy.detections import select_detections
from eventcap.energy.errors import EnergyError, SolveFailed
from eventcap.energy.landmarks import measure_widths, with_widths
from eventcap.energy.terms import TermSet
from eventcap.memo import ProcessCache
from eventcap.worldframe import upright

from . import solve  # solve.solve_window through its module: benchmarks and tests wrap it there
from .plan import WindowPlan, plan_window
from .solve import FitSolver, NothingObserved, SplineSolver, WindowResult, capture_floor, frame_fit, observed_frames

#: Built solvers of this process, keyed by value (template, camera, window layout, config): built once per run.
_SOLVERS = ProcessCache("eventcap_spline.solvers", maxsize=16)
#: What a process measured over a capture, by capture and settings: the solve's template, the floor.
_TEMPLATES = ProcessCache("eventcap_spline.capture_templates", maxsize=8)
_FLOORS = ProcessCache("eventcap_spline.capture_floors", maxsize=8)


def window_of(n_batches: int, k: int, half: int) -> tuple[int, int]:
    """First and last batch (inclusive) of batch k's window: 2·half + 1 batches centred on k, shifted inwards at
    the ends of the recording (all batches when there are fewer)."""
    if n_batches <= 2 * half + 1:
        return 0, n_batches - 1
    a = min(max(k - half, 0), n_batches - 2 * half - 1)
    return a, a + 2 * half


@functools.lru_cache(maxsize=64)
def window_schedule(n_batches: int, half: int, step: int) -> tuple[tuple[int, int, int, int, int], ...]:
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
    """Batch k's part in the :func:`window_schedule`: (a, z, ka, kz) when batch k solves the window of batches a..z that
    keeps batches ka..kz; None when it solves none (another batch's window keeps it: :func:`kept_by`)."""
    if not 0 <= k < n_batches:
        raise ValueError(f"batch {k}: expected 0 .. {n_batches - 1}")
    for c, a, z, ka, kz in window_schedule(n_batches, half, step):
        if c == k:
            return a, z, ka, kz
    return None


def unit_role(batches, unit, half: int, step: int) -> tuple[int, tuple[int, int, int, int] | None]:
    """The batches a unit of the solve (a batch, or a chunk of batches: the node's plan) keeps, and its window:
    (its first batch, (a, z, ka, kz) or None). A unit of one batch takes its part in the :func:`window_schedule` (None:
    another batch's window keeps it). A chunk keeps its batches ka..kz, and its window is them with ``half``
    batches on each side, shifted inwards at the ends of the recording (all batches when there are fewer); then
    windows advance by whole chunks, and ``step`` must be 1."""
    t0, t1 = np.asarray(batches.t0_us), np.asarray(batches.t1_us)
    kept = np.flatnonzero((t0 >= unit.t0_us) & (t1 <= unit.t1_us))
    if kept.size == 0:
        raise StageFailed(f"{unit_name(unit)}: none of the recording's {len(batches)} batches lies in it "
                          f"({unit.t0_us}..{unit.t1_us} us)", status="invalid_input")
    ka, kz, n = int(kept[0]), int(kept[-1]), len(batches)
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
    """The batch whose window keeps batch k (:func:`window_schedule`)."""
    return next(c for c, _, _, ka, kz in window_schedule(n_batches, half, step) if ka <= k <= kz)


def capture_template(rec, config, terms: TermSet, plan: WindowPlan, detections, ctx):
    """The template of the solve: the recording's, with the detector's hip and shoulder widths measured over the
    capture (eventcap.energy.landmarks) unless ``landmarks`` is template (the same in every
    window, kept per process); the log says which."""
    if config.landmarks == "template":
        return rec.template
    frames, where = plan.capture_frames_us, plan.where
    try:
        det = select_detections(detections, frames)
    except ValueError as exc:
        raise StageFailed(f"{where}: the landmark widths: {exc}", status="missing_detections") from exc
    key = ("widths", rec.template.geometry_digest(), repr(config), frames.tobytes(),
           *(np.ascontiguousarray(a).tobytes() for a in (det.keypoints_2d, det.confidence_2d, det.joints_3d,
                                                          det.confidence_3d)))

    def measure():
        plain = fit_solver_for(rec.template, rec.camera, config, terms)
        fits, keep = [], []
        for d in range(det.n):
            try:
                fits.append(frame_fit(plain, det, d)[0][0])
                keep.append(d)
            except SolveFailed:
                continue
        widths = measure_widths(rec.template, rec.camera, np.asarray(fits), det.rows(keep)) if keep else None
        if widths is None:
            return rec.template
        ctx.log.info("%s: where the detector puts the joints, over the capture (stages.solve.landmarks=%s): %s",
                     where, config.landmarks,
                     "; ".join(f"{k} {v:.3f} of the template's ({widths.frames[k]} frames)"
                               for k, v in widths.scale.items()))
        ctx.stats["landmark_widths"] = dict(widths.scale)
        return with_widths(rec.template, widths)

    return _TEMPLATES.get(key, measure)[0]


def capture_floor_of(solver: SplineSolver, plan: WindowPlan, detections, log) -> float | None:
    """The floor's height over the capture (the floor evidence of every window; asked for by the factors that need
    it), from the per-frame fits at every intensity frame of the capture (eventcap_spline.solve.capture_floor; the
    same in every window, kept per process)."""
    frames, where = plan.capture_frames_us, plan.where
    try:
        det = select_detections(detections, frames)
    except ValueError as exc:
        raise StageFailed(f"{where}: the floor: {exc}", status="missing_detections") from exc
    # the floor depends on the per-frame fits: the solver's template, camera and config, not its window layout
    key = (solver.template.geometry_digest(), repr(sorted(solver.camera.to_dict().items())), repr(solver.config),
           frames.tobytes(), *(np.ascontiguousarray(a).tobytes() for a in (
               det.keypoints_2d, det.confidence_2d, det.joints_3d, det.confidence_3d)))

    def measure():
        h = capture_floor(solver, det)[0]
        log.info("%s: the floor over the capture: y = %s (median lowest sole point of the fits at %d intensity "
                 "frames)", where, "unknown" if h is None else f"{h:.3f} m", frames.size)
        return h

    return _FLOORS.get(key, measure)[0]


def solver_for(template, camera, layout, config, terms: TermSet):
    """The built solver for this window layout and config (built once per process, keyed by value; terms: the
    config's, decoded)."""
    def build():
        try:
            return SplineSolver(template, camera, layout, config, terms=terms)
        except EnergyError as exc:
            raise StageFailed(f"stages.solve: {exc}", status=exc.status) from exc

    return _SOLVERS.get((template.geometry_digest(), repr(sorted(camera.to_dict().items())), layout, repr(config)),
                        build)


def fit_solver_for(template, camera, config, terms: TermSet):
    """The per-frame fits' solver for this template, camera and config (built once per process, keyed by value)."""
    def build():
        try:
            return FitSolver(template, camera, config, terms=terms)
        except EnergyError as exc:
            raise StageFailed(f"stages.solve: {exc}", status=exc.status) from exc

    return _SOLVERS.get(("fits", template.geometry_digest(), repr(sorted(camera.to_dict().items())), repr(config)),
                        build)[0]


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


def decode_terms(config) -> TermSet:
    """The stage's ``terms`` group decoded once (StageFailed naming the key of a group it cannot use)."""
    try:
        return TermSet.decode(config.terms)
    except EnergyError as exc:
        raise StageFailed(f"stages.solve: {exc}", status=exc.status) from exc


def check_terms(terms: TermSet, plan: WindowPlan) -> None:
    """StageFailed naming the first term that is on but reads what the window's solve does not provide (its
    inputs, a kind of detection the detector does not give, a noise model nobody states) and the setting that turns
    it off: before anything is measured or built (:meth:`eventcap.energy.terms.TermSet.check`)."""
    try:
        terms.check(plan.inputs(), "stages.solve")
    except EnergyError as exc:
        raise StageFailed(f"{plan.what}: {exc}", status=exc.status) from exc


def run_spline(inputs, config, ctx):
    inputs = {**inputs, "recording": upright(inputs["recording"], inputs["detections"])}  # the detections' world
    rec, batches, unit = inputs["recording"], inputs["batches"], ctx.batch
    if rec.template is None:
        raise StageFailed(f"stage 'spline' needs the actor template, but recording {rec.name or rec.source!r} has "
                          "none", status="missing_template")
    if unit is None:
        raise StageFailed("stage 'spline' runs per batch (no batch given)", status="invalid_input")
    check_config(config)
    terms = decode_terms(config)
    half, step = int(config.half_window), int(config.window_step)
    b, role = unit_role(batches, unit, half, step)
    if role is None:  # another batch's window keeps this batch (windows advance by window_step batches)
        ctx.stats["kept_by"] = kept_by(len(batches), b, half, step)
        return {"poses": PoseSequence(t_us=np.zeros(0, dtype=np.int64), poses=np.zeros((0, 33)), status="in_window",
                                      iterations=0, energies={})}
    where = f"batch {unit.index}" if role[2] == role[3] else f"chunk {unit.index} (batches {role[2]}..{role[3]})"
    plan = plan_window(inputs, config, terms, where, role, ctx.log)
    check_terms(terms, plan)
    template = capture_template(rec, config, terms, plan, inputs["detections"], ctx)
    solver, built = solver_for(template, rec.camera, plan.layout, config, terms)
    if built:
        ctx.log.info("built the spline NLP (%d control points; terms %s) in %.2f s (once per process)",
                     plan.spline.n_ctrl, ", ".join(f"{f.name} ({f.n})" for f in solver.factors), solver.build_seconds)
        ctx.stats["build_s"] = solver.build_seconds
    data = plan.inputs()
    data.offer("floor_y", lambda: capture_floor_of(solver, plan, inputs["detections"], ctx.log))
    try:
        res = solve.solve_window(solver, plan.spline, data, what=plan.what, context=plan.context)
    except NothingObserved as exc:  # a gap: nothing was seen, so nothing is estimated (stitch leaves it out)
        ctx.log.warning("%s: a gap: %s", where, str(exc).removeprefix(f"{plan.what}: "))
        ctx.stats["gap"] = True
        t_out = plan.t_out_us
        return {"poses": PoseSequence(t_us=t_out, poses=np.full((t_out.size, 33), np.nan), status="gap",
                                      iterations=0, energies={})}
    except (StageFailed, SolveFailed, EnergyError) as exc:  # name the window in every failure (the fits' too)
        msg = str(exc) if plan.what in str(exc) else f"{plan.what}: {exc}"
        raise StageFailed(msg, status=getattr(exc, "status", "failed"), details=getattr(exc, "details", {})) from exc
    poses, sigma = window_poses(plan, res, template)
    log_window(ctx, config, res, plan)
    energies = {k: (int(v) if k.startswith("n_") else float(v)) for k, v in res.energies.items()}
    iters = int(sum(s.iterations for s in res.solves))
    return {"poses": PoseSequence(t_us=plan.t_out_us, poses=poses, sigma_mm=sigma, status=res.solves[-1].status,
                                  iterations=iters, energies=energies)}


def window_poses(plan: WindowPlan, res: WindowResult, template) -> tuple[np.ndarray, np.ndarray]:
    """The window's curve at its output times (poses (T, 33)) and each joint's σ there (the Laplace approximation,
    mm (T, 24)): between its first and last detection frame that holds an observation (NaN beyond: never
    extrapolated); stitch blends the overlapping windows."""
    t_out, spline = plan.t_out_us, plan.spline
    poses = spline.evaluate(res.control, t_out)
    seen = plan.t_det_us[observed_frames(plan.detections)]
    poses[(t_out < seen[0]) | (t_out > seen[-1])] = np.nan
    # The window unwrapped its root angles from its own first fit: one branch per window (its first pose's root
    # angles in (-π, π]); stitch aligns neighbouring windows' branches before blending.
    first = int(np.flatnonzero(np.isfinite(poses[:, 0]))[0])
    poses[:, 27:30] -= 2.0 * np.pi * np.round(poses[first, 27:30] / (2.0 * np.pi))
    sigma = res.covariance.joint_sigma_mm(spline.basis(t_out), poses, template).astype(np.float32)
    return poses, sigma


def log_window(ctx, config, res: WindowResult, plan: WindowPlan) -> None:
    """The window's log lines and run statistics: the solve's, and what each factor says of its data."""
    (a, z), where, scope = plan.window, plan.where, plan.scope
    iters = int(sum(s.iterations for s in res.solves))
    secs = sum(res.seconds.values())
    ctx.log.info("%s: window of batches %d..%d (%d frames of detections, %d fitted here, %d control points, tracks "
                 "of %s), %d IPOPT iterations, %.2f s (%s)", where, a, z, plan.t_det_us.size, res.fits_computed,
                 plan.spline.n_ctrl, f"batch {scope[0]}" if len(scope) == 1 else f"{len(scope)} batches", iters, secs,
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
