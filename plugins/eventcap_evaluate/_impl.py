"""The evaluate stage (paper Sec. 4): join the per-batch pose sequences into one motion and measure it.

Joining (:func:`eventcap.analysis.motion.join_batches`). The solve stage gives one PoseSequence per batch; neighbouring
batches share their boundary tracking frame (the intensity frame between them). Frames are ordered by time and every
time appears once: with ``join=later`` a shared frame keeps the later batch's pose (the batch that starts there),
with ``join=mean`` the average of the batches' poses (root rotation angles averaged modulo 2π). Batches missing from
the sequence (a run on a selection of batches) leave gaps; gaps are not evaluated.

Measures (Table 1), in millimetres:

- the error of a frame is the mean over the 24 joints of the 3D distance between the estimated and the true joint,
  after rigid Procrustes alignment (rotation + translation, no scale) of the estimate to the truth in that frame
  (``align=procrustes``) or without it (``align=none``);
- ``AE_mm`` / ``STD_mm``: mean and (population) standard deviation of the frame errors over every ``every``-th
  tracking frame of the joined motion (indices 0, every, 2·every, ...);
- ``AE_raw_mm``: mean over the tracking frames at the times of intensity frames (the nearest tracking frame within
  half a tracking step of each intensity frame), all of them, whether on the every-n-th grid or not;
  ``AE_nonRaw_mm``: mean over the every-n-th frames that are not at intensity frames;
- ``per_joint_mm``: each joint's mean distance over the every-n-th frames.

Motion detail (beyond the paper; what a 1 kHz capture is for), on root-relative joints (each joint minus the
pelvis; the pelvis itself left out: 23 joints) at every tracking frame:

- ``AE_rootrel_mm``: the mean per-joint error of root-relative joints (no rotation alignment) over the every-n-th
  frames;
- ``depth_mm`` / ``image_plane_mm``: the same errors split along the camera's axes (:func:`eventcap.analysis.metrics.depth_split`):
  the mean of each root-relative error's component along the line of sight (absolute), and of its length in the
  image plane (what one camera knows least, and best);
- ``MPJVE_mm_s``: mean per-joint velocity error, velocities by central differences over ``velocity_window_ms``
  (x(t + h) - x(t - h)) / 2h with h the nearest multiple of the tracking step to half the window
  (``velocity_window_ms`` in the metrics is the window actually used), at every frame with both neighbours;
- ``accel_err_m_s2``: mean per-joint acceleration error, (x(t + h) - 2x(t) + x(t - h)) / h², same frames;
- ``peak_speed_err``: for each batch (the span of one input PoseSequence) and each end effector
  (``end_effectors``: feet, wrists, hands), the relative error of its peak speed in the batch,
  |max pred - max true| / max true; the median over the (batch, end effector) pairs whose true peak exceeds
  ``peak_min_speed_mps`` (0.5 m/s: a joint that hardly moves has no peak to get right) (a fraction: 0.15 = 15%), and
  per end effector in ``peak_speed_err_per_joint``, and every pair in ``peak_speed_errors`` (batches x end
  effectors; null where the true peak is below the threshold);
- ``peak_speed_err_fast``: the same median over the pairs whose true peak reaches ``fast_speed_mps`` (3 m/s): the
  fast moments between two intensity frames, what an event camera is bought for (``n_fast_pairs`` of them);
- ``peak_speed_signed_by_bin``: per bin of the true peak (0.5-1.5, 1.5-3, 3-6, 6+ m/s) the median signed relative
  error (negative: the estimate is too slow there) and the pairs' count; ``peak_speed_true_mps`` and
  ``peak_speed_signed`` (batches x end effectors) keep every pair so that runs can be pooled.

The truth at a tracking frame is the ground truth's joints at that time (exact on its 1 kHz grid, linearly
interpolated between its samples otherwise); frames outside the ground truth's time span are not evaluated.

Data rate: bytes of the events (``EVENT_DTYPE.itemsize`` = 13 per event) and of the intensity frames (8 bit per
pixel) the method read within the evaluated motion's time span, per second of that span, in MB/s (10^6 bytes),
against a high-speed camera giving 8-bit frames of the same resolution at the tracking frame rate (1000 fps).

Gaps: frames without an estimate (NaN poses: windows that saw nothing) are not evaluated; ``coverage`` is the share
of the tracking frames that have one, ``n_gap_frames`` how many do not.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from eventcap.artifacts import Metrics
from eventcap.artifacts.pose import JointErrors
from eventcap.artifacts.recording import GroundTruth, Recording
from eventcap.body.kinematics import joint_positions
from eventcap.body.skeleton import JOINT_INDEX, JOINT_NAMES
from eventcap.events import EVENT_DTYPE
from eventcap.analysis.metrics import (
    END_EFFECTORS,
    SPEED_BINS_MPS,
    depth_split,
    motion_detail,
    procrustes_align,
    root_relative,
    signed_by_speed,
    truth_at,
)
from eventcap.analysis.motion import JOIN_RULES, join_batches  # noqa: F401 (join_batches: part of this module's API)
from eventcap.core.stage import StageContext, StageFailed

ALIGN_MODES = ("procrustes", "none")
_MB = 1e6


def truth_joints(gt: GroundTruth, t_us: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """True joints (n, 24, 3) at the times inside the ground truth's span, and that mask (T,)."""
    return truth_at(gt.t_us, gt.joints, t_us)


def raw_frames(t_us: np.ndarray, frame_t_us: np.ndarray, step_us: float) -> np.ndarray:
    """Mask (T,) of the tracking frames nearest to an intensity frame time, within half a tracking step."""
    raw = np.zeros(t_us.size, dtype=bool)
    ft = np.asarray(frame_t_us, dtype=np.int64)
    ft = ft[(ft >= t_us[0] - step_us / 2) & (ft <= t_us[-1] + step_us / 2)]
    k = np.searchsorted(t_us, ft)  # t_us[k - 1] < ft <= t_us[k]
    lo, hi = np.clip(k - 1, 0, t_us.size - 1), np.clip(k, 0, t_us.size - 1)
    nearest = np.where(np.abs(t_us[lo] - ft) <= np.abs(t_us[hi] - ft), lo, hi)
    ok = np.abs(t_us[nearest] - ft) <= step_us / 2
    raw[nearest[ok]] = True
    return raw


def data_rate(rec: Recording, t0_us: int, t1_us: int, step_us: float | None) -> dict[str, Any]:
    """MB/s of events + 8-bit intensity frames within [t0, t1] against 8-bit frames at the tracking rate."""
    H, W = rec.height, rec.width
    n_events = int(rec.events.window(t0_us, t1_us + 1).shape[0])
    n_frames = 0 if rec.frames is None else int(np.count_nonzero((rec.frames.t_us >= t0_us)
                                                                 & (rec.frames.t_us <= t1_us)))
    duration_s = (t1_us - t0_us) * 1e-6
    out: dict[str, Any] = {"duration_s": duration_s, "n_events": n_events, "n_intensity_frames": n_frames,
                           "bytes_per_event": EVENT_DTYPE.itemsize, "bytes_per_frame": H * W,
                           "events_MBps": None, "frames_MBps": None, "total_MBps": None,
                           "highspeed_fps": None, "highspeed_MBps": None, "reduction": None}
    if duration_s <= 0 or step_us is None:
        return out
    ev = n_events * EVENT_DTYPE.itemsize / _MB / duration_s
    fr = n_frames * H * W / _MB / duration_s
    fps = 1e6 / step_us
    hs = fps * H * W / _MB
    out.update(events_MBps=ev, frames_MBps=fr, total_MBps=ev + fr, highspeed_fps=fps, highspeed_MBps=hs,
               reduction=hs / (ev + fr) if ev + fr > 0 else None)
    return out


def _mean_mm(x: np.ndarray) -> float | None:
    return float(1000.0 * x.mean()) if x.size else None


def _who(rec: Recording) -> str:
    return f"recording {rec.name or rec.source or '(unnamed)'!r}"


def require_truth(rec: Recording) -> tuple[GroundTruth, Any]:
    """The recording's ground truth and template, or StageFailed saying which is missing."""
    if rec.ground_truth is None:
        raise StageFailed(f"{_who(rec)} has no ground truth: evaluate needs a capture with ground-truth joints (a "
                          f"synthetic capture, source=synthetic, or a recording that ships them)",
                          status="no_ground_truth")
    if rec.template is None:
        raise StageFailed(f"{_who(rec)} has no actor template: evaluate needs it to turn the estimated poses into "
                          f"joints", status="no_template")
    return rec.ground_truth, rec.template


def body_errors(gt: GroundTruth, body, stated=None) -> dict[str, Any]:
    """The body's limb lengths and girdle widths (eventcap.body.proportions.SEGMENTS) against the filmed person's,
    which the ground truth's joints and poses give (its rest skeleton): ``body_error_mm`` the median absolute error
    over the segments, ``body_error_by_segment_mm`` each signed (body - truth); ``stated_*`` the same for the
    template as the user gave it, when given."""
    from eventcap.body.proportions import rest_skeleton_from_motion, segment_lengths

    step = max(1, gt.t_us.size // 20)
    truth = segment_lengths(rest_skeleton_from_motion(gt.poses[::step], gt.joints[::step]))
    out: dict[str, Any] = {}
    for key, t in (("body", body), ("stated_body", stated)):
        if t is None:
            continue
        got = segment_lengths(t.rest_joints)
        diff = {n: 1000.0 * (got[n] - truth[n]) for n in truth}
        out[f"{key}_error_mm"] = float(np.median(np.abs(list(diff.values()))))
        out[f"{key}_error_by_segment_mm"] = {n: round(v, 1) for n, v in diff.items()}
    return out


def evaluate_motion(rec: Recording, t_us: np.ndarray, poses: np.ndarray, every: int = 10,
                    align: str = "procrustes", velocity_window_ms: float = 10.0,
                    end_effectors: tuple[str, ...] = END_EFFECTORS, intervals_us: np.ndarray | None = None,
                    peak_min_speed_mps: float = 0.5, fast_speed_mps: float = 3.0) -> tuple[dict[str, Any], JointErrors]:
    """Table 1 measures of a joined motion against the recording's ground truth (see the module docstring)."""
    if isinstance(every, bool) or not isinstance(every, (int, np.integer)) or every < 1:
        raise ValueError(f"stages.evaluate.every: expected an int >= 1, got {every!r}")
    if align not in ALIGN_MODES:
        raise ValueError(f"stages.evaluate.align: expected one of {', '.join(ALIGN_MODES)}, got {align!r}")
    bad = [n for n in end_effectors if n not in JOINT_INDEX or JOINT_INDEX[n] == 0]
    if bad:
        raise ValueError(f"stages.evaluate.end_effectors: {bad[0]!r} is not a joint other than the root; joints: "
                         f"{', '.join(JOINT_NAMES[1:])}")
    if not velocity_window_ms > 0:
        raise ValueError(f"stages.evaluate.velocity_window_ms: expected a positive window, got {velocity_window_ms!r}")
    gt, tpl = require_truth(rec)
    who = _who(rec)
    if gt.t_us.size == 0:
        raise StageFailed(f"{who}: its ground truth is empty", status="no_ground_truth")
    t_us = np.asarray(t_us, dtype=np.int64)
    step = float(np.median(np.diff(t_us))) if t_us.size > 1 else None
    truth, inside = truth_joints(gt, t_us)
    estimated = np.isfinite(poses).all(axis=1)  # a gap (nothing seen: no estimate) is not evaluated
    truth, inside = truth[estimated[inside]], inside & estimated
    if not inside.any() and not estimated.any():
        raise StageFailed(f"{who}: the motion has no estimated frame (every window was a gap: nothing was seen)",
                          status="gap")
    if not inside.any():
        raise StageFailed(f"{who}: no estimated tracking frame ({t_us[0]}..{t_us[-1]} us) lies within its ground "
                          f"truth ({gt.t_us[0]}..{gt.t_us[-1]} us)", status="no_overlap")
    sampled = np.arange(t_us.size) % every == 0
    frame_t = rec.frames.t_us if rec.frames is not None else np.zeros(0, np.int64)
    raw = raw_frames(t_us, frame_t, step if step is not None else 1.0)
    keep = inside & (sampled | raw)  # the frames measured at all
    k_in = keep[inside]
    pred_all = joint_positions(poses[inside], tpl)  # every frame: velocities need the neighbours
    pred = pred_all[k_in]
    true = truth[k_in]
    s_in = sampled[keep]
    rootrel = np.linalg.norm(root_relative(pred[s_in])[:, 1:] - root_relative(true[s_in])[:, 1:], axis=-1)
    depth, image = depth_split(pred[s_in], true[s_in], rec.camera.R)
    if align == "procrustes":
        pred = procrustes_align(pred, true)
    err = np.linalg.norm(pred - true, axis=-1)  # (n, 24) metres
    errors = JointErrors(t_us=t_us[keep], error_m=err, sampled=sampled[keep], raw=raw[keep], align=align)
    frame_err = err.mean(axis=1)
    s, r = errors.sampled, errors.raw
    values: dict[str, Any] = {
        "AE_mm": _mean_mm(frame_err[s]),
        "STD_mm": float(1000.0 * frame_err[s].std()) if s.any() else None,
        "AE_raw_mm": _mean_mm(frame_err[r]),
        "AE_nonRaw_mm": _mean_mm(frame_err[s & ~r]),
        "per_joint_mm": {name: _mean_mm(err[s, j]) for j, name in enumerate(JOINT_NAMES)},
        "n_frames": int(s.sum()),
        "n_raw": int(r.sum()),
        "n_nonRaw": int((s & ~r).sum()),
        "n_tracking_frames": int(t_us.size),
        "n_gap_frames": int((~estimated).sum()),
        "coverage": float(estimated.mean()),
        "n_outside_ground_truth": int((~inside).sum()),
        "AE_rootrel_mm": _mean_mm(rootrel.mean(axis=1)) if rootrel.size else None,
        "depth_mm": _mean_mm(depth.mean(axis=1)) if depth.size else None,
        "image_plane_mm": _mean_mm(image.mean(axis=1)) if image.size else None,
        "every": int(every),
        "align": align,
        "data_rate": data_rate(rec, int(t_us[0]), int(t_us[-1]), step),
    }
    values.update(detail_values(t_us[inside], pred_all, truth, velocity_window_ms, end_effectors, intervals_us,
                                frame_t, peak_min_speed_mps, fast_speed_mps))
    return values, errors


def detail_values(t_us: np.ndarray, pred: np.ndarray, true: np.ndarray, window_ms: float,
                  end_effectors: tuple[str, ...], intervals_us: np.ndarray | None, frame_t_us: np.ndarray,
                  peak_min_speed_mps: float = 0.5, fast_speed_mps: float = 3.0) -> dict[str, Any]:
    """The motion-detail metrics (module docstring) of joints (T, 24, 3) at t_us; batches are ``intervals_us``
    (B, 2), else the spans between consecutive intensity frames."""
    if intervals_us is None:
        ft = np.asarray(frame_t_us, dtype=np.int64)
        intervals_us = np.stack([ft[:-1], ft[1:]], axis=1) if ft.size > 1 else np.zeros((0, 2), np.int64)
    ee = tuple(JOINT_INDEX[n] for n in end_effectors)
    out: dict[str, Any] = {"MPJVE_mm_s": None, "accel_err_m_s2": None, "peak_speed_err": None,
                           "peak_speed_err_fast": None, "peak_speed_err_per_joint": {}, "velocity_window_ms": None,
                           "n_velocity_frames": 0, "end_effectors": list(end_effectors),
                           "peak_min_speed_mps": peak_min_speed_mps, "fast_speed_mps": fast_speed_mps,
                           "n_peak_pairs": 0, "n_fast_pairs": 0}
    if t_us.size < 3:
        return out
    d = motion_detail(t_us, pred, true, window_ms * 1000.0, intervals_us, ee, peak_min_speed_mps)
    out.update({k: d[k] for k in ("MPJVE_mm_s", "accel_err_m_s2", "peak_speed_err", "n_velocity_frames")})
    out["velocity_window_ms"] = d["window_ms"]
    errs = d.get("peak_speed_errors")
    if errs is not None:
        for j, name in enumerate(end_effectors):
            fin = errs[:, j][np.isfinite(errs[:, j])]
            out["peak_speed_err_per_joint"][name] = float(np.median(fin)) if fin.size else None
        out["n_peak_pairs"] = int(np.isfinite(errs).sum())
        pt, pp = d["peak_speed_true"], d["peak_speed_pred"]
        with np.errstate(invalid="ignore", divide="ignore"):
            signed = np.where(np.isfinite(errs), (pp - pt) / pt, np.nan)
        fast = np.isfinite(signed) & (np.nan_to_num(pt) >= fast_speed_mps)
        out["n_fast_pairs"] = int(fast.sum())
        out["peak_speed_err_fast"] = float(np.median(np.abs(signed[fast]))) if fast.any() else None
        out["peak_speed_signed_by_bin"] = signed_by_speed(pt, signed, SPEED_BINS_MPS)
        # every (batch, end effector) pair, so that results of many runs can be pooled (null: no true motion)
        rows = lambda a: [[round(float(v), 5) if np.isfinite(v) else None for v in row] for row in a]  # noqa: E731
        out["peak_speed_errors"] = rows(errs)
        out["peak_speed_signed"] = rows(signed)
        out["peak_speed_true_mps"] = rows(np.where(np.isfinite(errs), pt, np.nan))
    return out


def run(inputs: dict[str, Any], config, ctx: StageContext) -> dict[str, Any]:
    rec: Recording = inputs["recording"]
    if config.join not in JOIN_RULES:
        raise ValueError(f"stages.evaluate.join: expected one of {', '.join(JOIN_RULES)}, got {config.join!r}")
    seq = inputs["poses"]
    if rec.ground_truth is None:
        # A real recording: nothing to measure against. Report what can be (the data rate) and say so, rather than
        # failing every run on real data.
        first, last = seq[0], seq[len(seq) - 1]
        t = np.concatenate([first.t_us, last.t_us])
        step = float(np.median(np.diff(first.t_us))) if first.t_us.size > 1 else None
        reason = f"{_who(rec)} has no ground truth: no joint errors (data rate only)"
        ctx.log.warning("evaluate: %s", reason)
        values = {"evaluated": False, "reason": reason, "n_batches": len(seq),
                  "data_rate": data_rate(rec, int(t.min()), int(t.max()), step)}
        empty = JointErrors(t_us=np.zeros(0, np.int64), error_m=np.zeros((0, 24)), sampled=np.zeros(0, bool),
                            raw=np.zeros(0, bool), align=config.align)
        return {"metrics": Metrics(values=values), "errors": empty}
    require_truth(rec)  # before loading any batch
    parts = [seq[i] for i in range(len(seq))]  # each batch loaded once (a runner BatchSequence reads the cache)
    t_us, poses, shared = join_batches(parts, config.join)
    ctx.report(1, 2)
    spans = np.array([[p.t_us[0], p.t_us[-1]] for p in parts if len(p.t_us) > 1], dtype=np.int64).reshape(-1, 2)
    values, errors = evaluate_motion(rec, t_us, poses, config.every, config.align, config.velocity_window_ms,
                                     tuple(config.end_effectors), spans, config.peak_min_speed_mps,
                                     config.fast_speed_mps)
    statuses: dict[str, int] = {}
    for p in parts:
        if p.status:
            statuses[p.status] = statuses.get(p.status, 0) + 1
    values.update({"join": config.join, "n_batches": len(parts), "n_shared_frames": shared,
                   "solver_status": statuses})
    values.update(body_errors(rec.ground_truth, rec.template, inputs.get("stated")))
    ctx.stats.update({"n_batches": len(parts), "n_frames": values["n_frames"]})
    ctx.report(2, 2)
    return {"metrics": Metrics(values=values), "errors": errors}
