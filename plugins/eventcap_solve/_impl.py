"""Run function of the batch-solve stage (imported when the stage runs)."""

from __future__ import annotations

import numpy as np

from eventcap.artifacts.pose import PoseSequence
from eventcap.energy.ipopt import bounds_with  # noqa: F401  (shared with the other solves; imported from here by bench_fusion)
from eventcap.stage import StageFailed

#: Built problems of this process, by (template digest, camera, frames, solver settings): built once per run.
_PROBLEMS: dict = {}


def problem_for(template, camera, frames: int, settings, limits=None, robust_px: float = 0.0):
    """The BatchProblem for this template, camera, batch length and joint limits, built once per process."""
    from .batch import BatchProblem

    lo, hi = bounds_with(limits)
    key = (template.geometry_digest(), repr(sorted(camera.to_dict().items())), int(frames), settings,
           lo.tobytes(), hi.tobytes(), float(robust_px))
    prob = _PROBLEMS.get(key)
    if prob is None:
        try:
            prob = BatchProblem(template, camera, frames, settings, lower=lo, upper=hi, robust_px=robust_px)
        except ValueError as exc:  # e.g. min above max: the whole problem is infeasible
            raise StageFailed(f"stages.solve.limits: {exc}", status="invalid_bounds") from exc
        _PROBLEMS[key] = prob
    return prob


def run_batch(inputs, config, ctx):
    from .batch import EnergyWeights, IpoptSettings, select_detections, solve_batch

    rec, sliced, detections, b = inputs["recording"], inputs["sliced"], inputs["detections"], ctx.batch
    if rec.template is None:
        raise StageFailed(f"stage 'batch' needs the actor template, but recording {rec.name or rec.source!r} has "
                          "none", status="missing_template")
    t_us = np.asarray(sliced.t_us, dtype=np.int64)
    if t_us.size < 2:
        raise StageFailed(f"batch {b.index if b else '?'}: {t_us.size} tracking frame(s); need at least 2",
                          status="invalid_input")
    times = t_us if config.mode == "all" else t_us[[0, -1]]
    try:
        det = select_detections(detections, times)
    except ValueError as exc:
        hint = (" — mode 'all' fits detections at every tracking frame: with the simulated detector set "
                "stages.detect.at=tracking") if config.mode == "all" else ""
        raise StageFailed(f"batch {b.index if b else '?'}: {exc}{hint}", status="missing_detections") from exc
    settings = IpoptSettings(max_iter=config.max_iter, tol=config.tol, mumps_pivot_order=config.mumps_pivot_order)
    weights = EnergyWeights(cor=config.lambda_cor, d2=config.lambda_2d, d3=config.lambda_3d, temp=config.lambda_temp,
                            damp=config.lambda_damp)
    n_built = len(_PROBLEMS)
    problem = problem_for(rec.template, rec.camera, t_us.size, settings, config.limits, config.robust_2d_px)
    if len(_PROBLEMS) > n_built:
        ctx.log.info("built the batch NLP for %d tracking frames in %.2f s (once per process)", t_us.size,
                     problem.build_seconds)
        ctx.stats["build_s"] = problem.build_seconds
    res = solve_batch(problem, t_us, sliced.xy, sliced.valid, det, mode=config.mode, icp_rounds=config.icp_rounds,
                      weights=weights, phi_scope=config.phi_scope, max_tracks=config.max_tracks,
                      edge_margin_px=config.edge_margin_px, still_m=config.still_m,
                      boundary=config.boundary)
    ctx.log.info("batch %s: %s, %d correspondences, %d IPOPT iterations, %.2f s solving (%s)",
                 b.index if b else "?", config.mode, res.energies["n_correspondences"], res.iterations,
                 sum(res.seconds.values()), res.status)
    ctx.stats.update({"solve_s": sum(res.seconds.values()), "phases_s": res.seconds, "iterations": res.iterations,
                      "solves": [[st.status, st.iterations, st.seconds] for st in res.solves],
                      "n_correspondences": int(res.energies["n_correspondences"])})
    if int(res.energies["n_correspondences"]) == 0 and config.lambda_cor > 0:
        ctx.log.warning("batch %s: 0 track-to-mesh correspondences: E_cor is empty, the poses between the frames come "
                        "from the detections and the temporal prior alone", b.index if b else "?")
    energies = {k: (int(v) if k == "n_correspondences" else float(v)) for k, v in res.energies.items()}
    return {"poses": PoseSequence(t_us=t_us.copy(), poses=res.poses, status=res.status, iterations=res.iterations,
                                  energies=energies)}
