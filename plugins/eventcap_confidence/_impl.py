"""Run function of the confidence stage (imported when it runs)."""

from __future__ import annotations

import numpy as np

from eventcap.artifacts.pose import JointConfidence
from eventcap.analysis.confidence import OBSERVED, motion_confidence
from eventcap.analysis.motion import join_batches
from eventcap.core.stage import StageFailed


def event_support(rec, template, t_us: np.ndarray, poses: np.ndarray, config) -> np.ndarray:
    """(T, 24) in [0, 1]: how much the events show each joint's bones where the estimate puts them, per time bin
    (1 - stillness of :func:`eventcap.energy.silence.measure_silence`), at every frame of the motion."""
    from eventcap.body.kinematics import joint_positions
    from eventcap.energy.silence import measure_silence

    bin_us = max(1, int(round(config.bin_ms * 1000)))
    edges = np.arange(int(t_us[0]), int(t_us[-1]) + bin_us, bin_us, dtype=np.int64)
    if edges.size < 2:
        edges = np.array([int(t_us[0]), int(t_us[0]) + bin_us], dtype=np.int64)
    mids = (edges[:-1] + edges[1:]) // 2
    k = np.clip(np.searchsorted(t_us, mids), 0, t_us.size - 1)
    P = poses[k]
    est = np.isfinite(P).all(axis=1)
    J = joint_positions(np.where(est[:, None], P, 0.0), template)
    cam = rec.camera
    px = np.full((mids.size, 24, 2), np.nan)
    front = cam.depth(J.reshape(-1, 3)).reshape(mids.size, 24) > 0.05
    px[front & est[:, None]] = cam.project(J[front & est[:, None]])
    sil = measure_silence(rec.events.window(int(edges[0]), int(edges[-1])), edges, px, cam.height, cam.width,
                          radius_px=int(config.event_radius_px), rate_hz=float(config.event_rate_hz),
                          hold_bins=0, sweep_bins=0)
    seen = 1.0 - sil.stillness
    b = np.clip(np.searchsorted(edges, t_us, side="right") - 1, 0, mids.size - 1)
    return np.where(np.isfinite(seen[b]), seen[b], 0.0)


def run_confidence(inputs, config, ctx):
    from eventcap.worldframe import upright

    rec, det, seq = inputs["recording"], inputs["detections"], inputs["poses"]
    rec = upright(rec, det)  # the world the motion was solved in
    if rec.template is None:
        raise StageFailed(f"stage 'confidence' needs the actor template, but recording {rec.name or rec.source!r} "
                          "has none", status="missing_template")
    parts = [seq[i] for i in range(len(seq))]
    t_us, poses, _ = join_batches(parts, "later")
    est = np.isfinite(poses).all(axis=1)
    ev = event_support(rec, rec.template, t_us, poses, config) if est.any() else np.zeros((t_us.size, 24))
    c = motion_confidence(rec.template, rec.camera, t_us, poses, np.asarray(det.t_us, dtype=np.int64),
                          np.asarray(det.keypoints_2d, dtype=np.float64), det.observed(),
                          np.asarray(det.confidence_2d, dtype=np.float64), ev, float(config.detection_frac),
                          float(config.still_frac))
    observed = (c >= OBSERVED).mean(axis=0)
    ctx.log.info("confidence: %d frames (%d without an estimate); joints observed (confidence >= %.1f) on average "
                 "%.0f%% of the estimated frames, the least seen: %s", t_us.size, int((~est).sum()), OBSERVED,
                 100.0 * float((c[est] >= OBSERVED).mean()) if est.any() else 0.0,
                 ", ".join(f"{n} {100 * observed[j]:.0f}%" for j, n in _least_seen(observed)))
    ctx.stats.update({"observed_share": [round(float(v), 4) for v in observed], "gap_frames": int((~est).sum())})
    return {"confidence": JointConfidence(t_us=t_us, confidence=c.astype(np.float32), estimated=est)}


def _least_seen(observed: np.ndarray, n: int = 3):
    from eventcap.body.skeleton import JOINT_NAMES

    order = np.argsort(observed, kind="stable")[:n]
    return [(int(j), JOINT_NAMES[j]) for j in order]
