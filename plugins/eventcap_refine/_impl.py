"""Run function of the refine stage (imported when the stage runs)."""

from __future__ import annotations

import hashlib

import numpy as np

from eventcap.artifacts.pose import PoseSequence
from eventcap.stage import StageFailed

#: Built problems of this process, by (template, camera, frames, solver settings, bounds): built once per run.
_PROBLEMS: dict = {}
#: Skinning kernels by (rest joints, frames): shared by problems that differ only in solver settings or bounds.
_KERNELS: dict = {}


def bounds_with(limits) -> tuple[np.ndarray, np.ndarray]:
    """skeleton.pose_bounds() with the config's overrides {name: [min, max]} applied (as the solve's)."""
    from eventcap.energy.ipopt import bounds_with as solve_bounds

    return solve_bounds(limits, "stages.refine.limits")


def problem_for(template, camera, frames: int, settings, limits=None):
    """The RefineProblem for this template, camera, batch length, solver settings and bounds, built once per
    process. Returns (problem, built_now)."""
    from eventcap.energy.kernels import SkinningKernels

    from .refine import RefineProblem

    lo, hi = bounds_with(limits)
    digest = template.geometry_digest()
    key = (digest, repr(sorted(camera.to_dict().items())), int(frames), settings, lo.tobytes(), hi.tobytes())
    prob = _PROBLEMS.get(key)
    if prob is not None:
        return prob, False
    kkey = (hashlib.sha1(np.ascontiguousarray(template.rest_joints).tobytes()).hexdigest(), int(frames))
    if kkey not in _KERNELS:
        _KERNELS[kkey] = SkinningKernels(template.rest_joints, int(frames))
    try:
        prob = RefineProblem(template, camera, frames, settings, lower=lo, upper=hi, kernels=_KERNELS[kkey])
    except ValueError as exc:  # e.g. min above max: the whole problem is infeasible
        raise StageFailed(f"stages.refine.limits: {exc}", status="invalid_bounds") from exc
    _PROBLEMS[key] = prob
    return prob, True


def run_refine(inputs, config, ctx):
    from eventcap.energy.ipopt import IpoptSettings

    from eventcap.energy.sil import SilhouetteWeights

    from .refine import refine_batch

    rec, est, b = inputs["recording"], inputs["poses"], ctx.batch
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
    try:
        weights = SilhouetteWeights(sil=config.lambda_sil, stab=config.lambda_stab, dist=config.lambda_dist,
                                loss=config.loss, huber_px=config.huber_px)
        settings = IpoptSettings(max_iter=config.max_iter, tol=config.tol,
                                 mumps_pivot_order=config.mumps_pivot_order)
    except ValueError as exc:
        raise StageFailed(f"stages.refine: {exc}", status="invalid_config") from exc
    if isinstance(config.icp_iterations, bool) or config.icp_iterations < 1:
        raise StageFailed(f"stages.refine.icp_iterations: expected an integer >= 1, got {config.icp_iterations!r}",
                          status="invalid_config")
    for name in ("patch_px", "denoise_us"):
        if getattr(config, name) < 0:
            raise StageFailed(f"stages.refine.{name}: expected an integer >= 0, got {getattr(config, name)!r}",
                              status="invalid_config")
    problem, built = problem_for(rec.template, rec.camera, t_us.size, settings, config.limits)
    if built:
        ctx.log.info("built the refinement NLP for %d tracking frames in %.2f s (once per process)", t_us.size,
                     problem.build_seconds)
        ctx.stats["build_s"] = problem.build_seconds
    # The window of Eq. 12-13 is the batch duration t_N - t_0 (the batch plan's, when the poses cover one frame).
    window = int(t_us[-1] - t_us[0]) if t_us.size > 1 or b is None else int(b.t1_us - b.t0_us)
    res = refine_batch(problem, t_us, est.poses, rec.events.events, weights, icp_iterations=config.icp_iterations,
                       patch_px=config.patch_px, window_us=window, denoise_us=config.denoise_us)
    n_b = [s.boundary for s in res.icp]
    n_m = [s.matched for s in res.icp]
    frac = [m / n if n else 0.0 for m, n in zip(n_m, n_b)]
    secs = sum(res.seconds.values())
    if n_b[-1] and not n_m[-1]:
        ctx.log.warning("%s: none of %d silhouette boundary pixels has an event in its %d px patch and %d us "
                        "window: the poses stay at the solve's (E_stab only)", where, n_b[-1], config.patch_px,
                        window)
    ctx.log.info("%s: refined %d frames, %d ICP iterations; %d events (%d dropped as noise); %d of %d boundary "
                 "pixels matched (%.0f%%); E_sil %.3g -> %.3g; %d IPOPT iterations, %.2f s (%s)", where, t_us.size,
                 len(res.icp), res.events, res.events_dropped, n_m[-1], n_b[-1], 100 * frac[-1],
                 res.energies["sil_start"], res.energies["sil"], res.iterations, secs, res.status)
    ctx.stats.update({"refine_s": secs, "phases_s": res.seconds, "iterations": res.iterations,
                      "events": res.events, "events_dropped": res.events_dropped, "boundary_pixels": n_b,
                      "matched": n_m, "matched_fraction": frac,
                      "solves": [[s.status, s.iterations, s.seconds["solve"]] for s in res.icp]})
    return {"poses": PoseSequence(t_us=t_us.copy(), poses=res.poses, status=res.status, iterations=res.iterations,
                                  energies={k: float(v) for k, v in res.energies.items()})}
