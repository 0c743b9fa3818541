"""Run function of the batch-solve stage (imported when the stage runs)."""

from __future__ import annotations

import numpy as np

from eventcap.artifacts.pose import PoseSequence
from eventcap.core.stage import StageFailed
from eventcap.memo import ProcessCache

#: Built problems of this process, keyed by value (template, camera, frames, config): built once per run.
_PROBLEMS = ProcessCache("eventcap_solve.problems", maxsize=16)


def problem_for(template, camera, frames: int, config):
    """The BatchProblem for this template, camera, batch length and config, built once per process. Returns
    (problem, built_now)."""
    from eventcap.energy.errors import EnergyError

    from .batch import BatchProblem

    def build():
        try:
            return BatchProblem(template, camera, frames, config)
        except EnergyError as exc:  # e.g. min above max: the whole problem is infeasible
            raise StageFailed(f"stages.solve: {exc}", status=exc.status) from exc

    key = (template.geometry_digest(), repr(sorted(camera.to_dict().items())), int(frames), repr(config))
    return _PROBLEMS.get(key, build)


def run_batch(inputs, config, ctx):
    from eventcap.energy.errors import EnergyError, SolveFailed

    from .batch import select_detections, solve_batch

    from eventcap.worldframe import upright

    rec, sliced, detections, b = inputs["recording"], inputs["sliced"], inputs["detections"], ctx.batch
    rec = upright(rec, detections)  # the detections' world
    where = f"batch {b.index if b else '?'}"
    if rec.template is None:
        raise StageFailed(f"stage 'batch' needs the actor template, but recording {rec.name or rec.source!r} has "
                          "none", status="missing_template")
    t_us = np.asarray(sliced.t_us, dtype=np.int64)
    if t_us.size < 2:
        raise StageFailed(f"{where}: {t_us.size} tracking frame(s); need at least 2", status="invalid_input")
    times = t_us if config.mode == "all" else t_us[[0, -1]]
    try:
        det = select_detections(detections, times)
    except ValueError as exc:
        hint = (" — mode 'all' fits detections at every tracking frame: with the simulated detector set "
                "stages.detect.at=tracking") if config.mode == "all" else ""
        raise StageFailed(f"{where}: {exc}{hint}", status="missing_detections") from exc
    problem, built = problem_for(rec.template, rec.camera, t_us.size, config)
    if built:
        ctx.log.info("built the batch NLP for %d tracking frames in %.2f s (once per process)", t_us.size,
                     problem.build_seconds)
        ctx.stats["build_s"] = problem.build_seconds
    try:
        res = solve_batch(problem, t_us, sliced.xy, sliced.valid, det)
    except (EnergyError, SolveFailed) as exc:
        raise StageFailed(f"{where}: {exc}", status=exc.status, details=getattr(exc, "details", {})) from exc
    n_cor = res.energies.get("n_correspondences")  # present when a term uses the tracks' correspondences
    ctx.log.info("%s: %s, %s correspondences, %d IPOPT iterations, %.2f s solving (%s)", where, config.mode,
                 "no" if n_cor is None else n_cor, res.iterations, sum(res.seconds.values()), res.status)
    ctx.stats.update({"solve_s": sum(res.seconds.values()), "phases_s": res.seconds, "iterations": res.iterations,
                      "solves": [[st.status, st.iterations, st.seconds] for st in res.solves],
                      **{k: int(v) for k, v in res.energies.items() if k.startswith("n_")}})
    if n_cor == 0 and config.mode not in ("linear", "all"):
        ctx.log.warning("%s: 0 track-to-mesh correspondences: the poses between the frames come from the "
                        "detections and the other terms alone", where)
    energies = {k: (int(v) if k.startswith("n_") else float(v)) for k, v in res.energies.items()}
    return {"poses": PoseSequence(t_us=t_us.copy(), poses=res.poses, status=res.status, iterations=res.iterations,
                                  energies=energies)}
