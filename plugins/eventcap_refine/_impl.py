"""Run function of the refine stage (imported when the stage runs)."""

from __future__ import annotations

import numpy as np

from eventcap.artifacts.pose import PoseSequence
from eventcap.core.stage import StageFailed
from eventcap.memo import ProcessCache

#: Built problems of this process, keyed by value (template, camera, frames, config): built once per run.
_PROBLEMS = ProcessCache("eventcap_refine.problems", maxsize=16)


def problem_for(template, camera, t_us: np.ndarray, config):
    """The RefineProblem for this template, camera, batch (its tracking times t_us size the terms) and config,
    built once per process for each size. Returns (problem, built_now)."""
    from eventcap.energy.errors import EnergyError
    from eventcap.energy.terms import sample_times

    from .refine import RefineProblem, refine_window

    sizes = tuple((k, t.size) for k, t in sample_times(config.terms, refine_window(t_us, None, None, template)).items())
    key = (template.geometry_digest(), repr(sorted(camera.to_dict().items())), int(t_us.size), sizes, repr(config))

    def build():
        try:
            return RefineProblem(template, camera, t_us.size, config, t_us)
        except EnergyError as exc:  # e.g. min above max: the whole problem is infeasible
            raise StageFailed(f"stages.refine: {exc}", status=exc.status) from exc

    return _PROBLEMS.get(key, build)


def run_refine(inputs, config, ctx):
    from eventcap.energy.errors import EnergyError, SolveFailed

    from .refine import refine_batch

    from eventcap.worldframe import upright

    rec, est, b = inputs["recording"], inputs["poses"], ctx.batch
    rec = upright(rec, inputs.get("detections"))  # the world the poses were solved in
    where = f"batch {b.index}" if b is not None else "batch ?"
    if rec.template is None:
        raise StageFailed(f"stage 'silhouette' needs the actor template, but recording {rec.name or rec.source!r} "
                          "has none", status="missing_template")
    t_us = np.asarray(est.t_us, dtype=np.int64)
    if t_us.size < 1:
        raise StageFailed(f"{where}: the solve gave no poses to refine", status="invalid_input")
    if b is not None and (t_us[0] < b.t0_us or t_us[-1] > b.t1_us):
        raise StageFailed(f"{where}: poses at [{t_us[0]}, {t_us[-1]}] us lie outside the batch [{b.t0_us}, "
                          f"{b.t1_us}] us: are they the solve output of this batch?", status="invalid_input")
    problem, built = problem_for(rec.template, rec.camera, t_us, config)
    if built:
        ctx.log.info("built the refinement NLP for %d tracking frames in %.2f s (once per process)", t_us.size,
                     problem.build_seconds)
        ctx.stats["build_s"] = problem.build_seconds
    # The window of Eq. 12-13 is the batch duration t_N - t_0 (the batch plan's, when the poses cover one frame).
    window = int(t_us[-1] - t_us[0]) if t_us.size > 1 or b is None else int(b.t1_us - b.t0_us)
    try:
        res = refine_batch(problem, t_us, est.poses, rec.events.events, window_us=window)
    except EnergyError as exc:
        raise StageFailed(f"{where}: {exc}", status="invalid_config" if "icp_iterations" in str(exc)
                          else exc.status) from exc
    except SolveFailed as exc:
        raise StageFailed(f"{where}: {exc}", status=exc.status, details=exc.details) from exc
    n_b = [s.boundary for s in res.icp]
    n_m = [s.matched for s in res.icp]
    frac = [m / n if n else 0.0 for m, n in zip(n_m, n_b)]
    secs = sum(res.seconds.values())
    if n_b[-1] and not n_m[-1]:
        ctx.log.warning("%s: none of %d silhouette boundary pixels has an event in its patch and %d us window: the "
                        "poses stay near the solve's", where, n_b[-1], window)
    ctx.log.info("%s: refined %d frames, %d ICP iterations; %d events (%d dropped as noise); %d of %d boundary "
                 "pixels matched (%.0f%%); energy %.3g -> %.3g; %d IPOPT iterations, %.2f s (%s)", where,
                 t_us.size, len(res.icp), res.events, res.events_dropped, n_m[-1], n_b[-1], 100 * frac[-1],
                 res.energies["total_start"], res.energies["total"], res.iterations, secs, res.status)
    ctx.stats.update({"refine_s": secs, "phases_s": res.seconds, "iterations": res.iterations,
                      "events": res.events, "events_dropped": res.events_dropped, "boundary_pixels": n_b,
                      "matched": n_m, "matched_fraction": frac,
                      "solves": [[s.status, s.iterations, s.seconds["solve"]] for s in res.icp]})
    return {"poses": PoseSequence(t_us=t_us.copy(), poses=res.poses, status=res.status, iterations=res.iterations,
                                  energies={k: float(v) for k, v in res.energies.items()})}
