"""Joining the windows of the spline solve into one motion without seams (not in the paper).

Each batch keeps its own interval of its window's spline (:mod:`.solve`); neighbouring batches are solved in
different windows (they see different events and detections at the window's far ends), so where two batches
meet their curves disagree by a few millimetres to centimetres: a seam, visible as a spike in the 1 kHz velocity.

``stitch`` (whole recording) fits one cubic B-spline over the whole recording, on the same knot grid as the
windows (knots every ``knot_ms`` from the first intensity frame), to every batch's poses by least squares with a
small acceleration prior. Inside a batch the window's curve already lies in that spline space and is kept
(up to the prior); at a seam the two sides' disagreement is spread over the neighbouring knots, so the joined
motion is C² everywhere. Root angles are first moved by multiples of 2π so each batch continues the one before.
``cut`` (per batch) gives each batch its frames of the stitched motion, so the batch boundaries of everything
downstream (evaluate, outputs) stay as they are.
"""

from __future__ import annotations

import math

import numpy as np

from eventcap.artifacts.pose import PoseSequence
from eventcap.stage import StageFailed


def stitch(t_list: list[np.ndarray], pose_list: list[np.ndarray], h_us: int, smooth: float):
    """One spline through the batches' poses: returns (t_us (unique, sorted), poses, spline, control points)."""
    from eventcap.energy.spline import UniformCubicBSpline

    P = [np.asarray(p, dtype=np.float64).copy() for p in pose_list]
    for k in range(1, len(P)):  # each batch on the branch of the one before (root angles)
        d = P[k][0, 27:30] - P[k - 1][-1, 27:30]
        P[k][:, 27:30] -= 2.0 * np.pi * np.round(d / (2.0 * np.pi))
    t_all = np.concatenate([np.asarray(t, dtype=np.int64) for t in t_list])
    p_all = np.concatenate(P)
    t0, t1 = int(t_all.min()), int(t_all.max())
    n_seg = max(1, int(math.ceil((t1 - t0) / h_us)))
    spl = UniformCubicBSpline(t0, int(h_us), n_seg)
    C = spl.fit(t_all, p_all, smooth=smooth, deriv=2)
    t_out = np.unique(t_all)
    return t_out, spl.evaluate(C, t_out), spl, C


def run_stitch(inputs, config, ctx):
    seq = inputs["windows"]
    K = len(seq)
    if K < 1:
        raise StageFailed("stitch: no batches of the spline solve", status="invalid_input")
    if not (math.isfinite(config.knot_ms) and config.knot_ms > 0):
        raise StageFailed(f"stages.stitch.knot_ms: expected a positive number of ms, got {config.knot_ms!r}",
                          status="invalid_config")
    if not (math.isfinite(config.smooth) and config.smooth >= 0):
        raise StageFailed(f"stages.stitch.smooth: expected a number >= 0, got {config.smooth!r}",
                          status="invalid_config")
    ts, ps = [], []
    for k in range(K):
        p = seq[k]
        t = np.asarray(p.t_us, dtype=np.int64)
        if ts and t[0] != ts[-1][-1]:
            raise StageFailed(f"stitch: batch {seq.batches[k].index} starts at t = {int(t[0])} us, but the batch "
                              f"before it ends at {int(ts[-1][-1])} us: the batches must be contiguous",
                              status="invalid_input")
        ts.append(t)
        ps.append(np.asarray(p.poses))
        ctx.report(k + 1, K)
    seams = [float(np.abs(ps[k][0, :27] - ps[k - 1][-1, :27]).max()) for k in range(1, K)]
    t_out, poses, spl, _ = stitch(ts, ps, int(round(config.knot_ms * 1000)), float(config.smooth))
    ctx.log.info("stitch: %d batches into one spline of %d control points; largest joint-angle seam before "
                 "stitching %.3f rad", K, spl.n_ctrl, max(seams, default=0.0))
    ctx.stats.update({"seam_rad_max": max(seams, default=0.0), "seam_rad_median": float(np.median(seams or [0]))})
    return {"motion": PoseSequence(t_us=t_out, poses=poses, status="stitched", iterations=0,
                                   energies={"n_ctrl": float(spl.n_ctrl)})}


def run_cut(inputs, config, ctx):
    motion, b = inputs["motion"], ctx.batch
    if b is None:
        raise StageFailed("cut runs per batch (no batch given)", status="invalid_input")
    t = np.asarray(motion.t_us, dtype=np.int64)
    sel = (t >= b.t0_us) & (t <= b.t1_us)
    if sel.sum() < 2 or t[sel][0] != b.t0_us or t[sel][-1] != b.t1_us:
        raise StageFailed(f"cut: the stitched motion has no frames spanning batch {b.index} [{b.t0_us}, {b.t1_us}] "
                          "us", status="invalid_input")
    return {"poses": PoseSequence(t_us=t[sel].copy(), poses=np.asarray(motion.poses)[sel].copy(), status="stitched",
                                  iterations=0, energies={})}
