"""Run function of the confidence stage (imported when it runs)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from eventcap.artifacts.pose import JointConfidence
from eventcap.analysis.confidence import OBSERVED, joints_in_view
from eventcap.analysis.motion import join_batches
from eventcap.analysis.uncertainty import (
    CALIBRATED,
    RATE_SCALED,
    UncertaintyModel,
    at_times,
    body_mm,
    calibration,
    confidence_of,
    detection_residuals,
    detector_kind,
    event_gap_mm,
    frame_rate,
    joined_sigma,
    joint_uncertainty,
    motion_mm,
    out_of_view,
    rate_factor,
    view_of,
)
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


def read_calibration(config) -> dict:
    """The calibration table ``stages.confidence.calibration`` names (``shipped``: the stage's own); StageFailed
    naming the key and the file when it cannot be read as one."""
    import json

    from .spec import calibration_files

    path = Path(calibration_files(str(config.calibration))[0])
    try:
        table = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise StageFailed(f"stages.confidence.calibration: cannot read {path} as a JSON calibration table: {exc}",
                          status="invalid_config") from None
    if not isinstance(table, dict) or not isinstance(table.get("detectors"), dict):
        raise StageFailed(f"stages.confidence.calibration: {path}: expected an object with a 'detectors' object "
                          "{kind: {setting: value}}", status="invalid_config")
    return table


def settings_of(config, detector: str, fps: float | None = None, view: str = "whole_frames") -> tuple[str, dict]:
    """(the calibration entry used, the uncertainty's settings) for detections made by ``detector`` (the Detections'
    text) on a capture of ``fps`` intensity frames per second (None: none) seen as ``view`` (:func:`view_of`): the
    detector kind's calibration from the table, its parts times the entry's factor at that frame rate
    (:func:`rate_factor`) and its factor for that view (``factor_by_view``, 1 where it states none), each setting
    given in the config taking its place (a trusted_mm given without unseen_mm keeps the table's unseen / trusted
    ratio)."""
    kind = detector_kind(detector)
    try:
        name, cal = calibration(read_calibration(config), kind)
    except ValueError as exc:
        raise StageFailed(f"stages.confidence.calibration: {exc}", status="invalid_config") from None
    cal["rate_factor"] = rate_factor(cal.pop("factor_by_fps"), fps)
    cal["view"], cal["view_factor"] = view, cal.pop("factor_by_view").get(view, 1.0)
    for key in RATE_SCALED:
        cal[key] *= cal["rate_factor"] * cal["view_factor"]
    ratio = cal["unseen_mm"] / cal["trusted_mm"]
    for key in CALIBRATED:
        v = getattr(config, key, None)
        if v is not None:
            cal[key] = float(v)
    if config.trusted_mm is not None and config.unseen_mm is None:  # the table's unseen / trusted kept
        cal["unseen_mm"] = ratio * cal["trusted_mm"]
    return name, cal


def model_of(config, detector: str = "", fps: float | None = None,
             view: str = "whole_frames") -> tuple[UncertaintyModel, dict]:
    """The uncertainty's model and its settings (trusted_mm, unseen_mm, the entry used) for the detector at the
    capture's frame rate and view, from the stage's config (StageFailed naming a key whose value cannot work)."""
    name, cal = settings_of(config, detector, fps, view)
    if cal["unseen_mm"] < cal["trusted_mm"]:
        raise StageFailed(f"stages.confidence.unseen_mm: expected at least trusted_mm ({cal['trusted_mm']:g} mm: a "
                          f"joint out of view must never be marked observed), got {cal['unseen_mm']:g}",
                          status="invalid_config")
    model = UncertaintyModel(scale=cal["scale"], detection_2d=cal["detection_2d"], detection_3d=cal["detection_3d"],
                             events=cal["events"], unseen_mm=cal["unseen_mm"], floor_mm=cal["floor_mm"],
                             fallback_mm=float(config.fallback_mm), body=float(config.body), motion=cal["motion"],
                             speed=cal["speed"], between_mm=cal["between_mm"])
    return model, {**cal, "entry": name}


def motion_cues(rec, det, parts, config) -> dict:
    """What the uncertainty is made of at every frame of the joined per-batch poses (eventcap.analysis.uncertainty):
    ``t_us`` (T,), ``estimated`` (T,), ``sigma`` (T, 24) the solve's σ (None: the poses carry none), the detections'
    residuals ``r2``, ``r3`` (T, 24) mm interpolated between the frames, the events' ``gap`` (T, 24) mm, the body's
    own uncertainty ``body`` (T, 24) mm (None: an exact body), the motion between the frames ``between`` (T,) and
    ``step`` (T, 24) mm (:func:`eventcap.analysis.uncertainty.motion_mm`), the ``detector`` that made the
    detections."""
    tpl, cam = rec.template, rec.camera
    t_us, poses, _ = join_batches(parts, "later")
    est = np.isfinite(poses).all(axis=1)
    t_det = np.asarray(det.t_us, dtype=np.int64)
    idx = np.searchsorted(t_us, t_det)
    hit = (idx < t_us.size) & (t_us[np.minimum(idx, t_us.size - 1)] == t_det)
    P_det = np.full((t_det.size, 33), np.nan)
    P_det[hit] = poses[idx[hit]]
    r2, r3 = detection_residuals(tpl, cam, P_det, det.keypoints_2d, det.observed(), det.joints_3d, det.confidence_3d)
    ev = event_support(rec, tpl, t_us, poses, config) if est.any() else np.zeros((t_us.size, 24))
    between, step = motion_mm(tpl, t_us, poses, t_det[hit])
    fps = capture_fps(rec)
    return {"t_us": t_us, "estimated": est, "sigma": joined_sigma(parts, t_us), "r2": at_times(t_us, t_det, r2),
            "r3": at_times(t_us, t_det, r3), "gap": event_gap_mm(tpl, cam, t_us, poses, t_det[hit], ev),
            "events": ev, "poses": poses, "body": body_mm(tpl, poses), "between": between, "step": step,
            "detector": str(det.detector), "fps": fps, "view": capture_view(rec, poses, fps, det)}


def capture_view(rec, poses: np.ndarray, fps: float | None, det=None) -> str:
    """The view the uncertainty is calibrated for (:func:`eventcap.analysis.uncertainty.view_of`): the capture's
    frames, and the share of the body in the image: the smaller of the estimate's joints inside the image over its
    estimated frames and the detections' landmarks observed over the images where the detector saw a person (a
    close-up the solve draws as a small whole body is still one the detector saw only the top of)."""
    est = np.isfinite(poses).all(axis=1)
    share = float(joints_in_view(rec.template, rec.camera, poses)[est].mean()) if est.any() else 1.0
    if det is not None:
        seen = det.observed()
        found = seen.any(axis=1)
        share = min(share, float(seen[found].mean())) if found.any() else share
    return view_of(fps, share)


def capture_fps(rec) -> float | None:
    """The capture's intensity frames per second (None: an event-only capture, whose images come from the events)."""
    return None if rec.frames is None or rec.images_from_events else frame_rate(rec.frames.t_us)


def motion_uncertainty(rec, cues: dict, config, model: UncertaintyModel) -> tuple[np.ndarray, np.ndarray]:
    """(uncertainty (T, 24) mm, in view (T, 24)) from the cues (:func:`motion_cues`) with the stage's settings and
    the model (:func:`model_of`) for the cues' detector, frame rate and view: a joint is in view with
    ``view_margin`` times its uncertainty around it, and one out of view is raised to ``unseen_mm``."""
    u = joint_uncertainty(model, cues["sigma"], cues["r2"], cues["r3"], cues["gap"], cues["estimated"],
                          cues.get("body"), cues.get("between"), cues.get("step"))
    seen = joints_in_view(rec.template, rec.camera, cues["poses"],
                          float(config.view_margin) * np.nan_to_num(u) / 1000.0)
    return out_of_view(u, seen, model.unseen_mm), seen


def run_confidence(inputs, config, ctx):
    from eventcap.worldframe import upright

    rec, det, seq = inputs["recording"], inputs["detections"], inputs["poses"]
    rec = upright(rec, det)  # the world the motion was solved in
    if rec.template is None:
        raise StageFailed(f"stage 'confidence' needs the actor template, but recording {rec.name or rec.source!r} "
                          "has none", status="missing_template")
    parts = [seq[i] for i in range(len(seq))]
    cues = motion_cues(rec, det, parts, config)
    t_us, est = cues["t_us"], cues["estimated"]
    model, cal = model_of(config, cues["detector"], cues["fps"], cues["view"])
    u, seen = motion_uncertainty(rec, cues, config, model)
    c = confidence_of(u, cal["trusted_mm"])
    rate = ("no intensity frames" if cues["fps"] is None else f"{cues['fps']:.3g} fps")
    ctx.log.info("confidence: the uncertainty calibrated for detector kind %r (entry %r of %s) at %s: factor %.3g; "
                 "view %s: factor %.3g; scale %.3g, trusted %g mm", detector_kind(cues["detector"]), cal["entry"],
                 config.calibration, rate, cal["rate_factor"], cal["view"], cal["view_factor"], cal["scale"],
                 cal["trusted_mm"])
    if cues["sigma"] is None:
        ctx.log.warning("confidence: the poses carry no σ of their solve (a solve without a Laplace approximation): "
                        "stages.confidence.fallback_mm (%g mm) stands for it, so the uncertainty is only that of "
                        "where the cues disagree, not calibrated for this solve", float(config.fallback_mm))
    observed = (c >= OBSERVED).mean(axis=0)
    ctx.log.info("confidence: %d frames (%d without an estimate); uncertainty median %.0f mm (joints in view), %.0f "
                 "mm (out of view); joints observed (confidence >= %.1f) on average %.0f%% of the estimated frames, "
                 "the least seen: %s", t_us.size, int((~est).sum()), _median(u[est][seen[est]]),
                 _median(u[est][~seen[est]]), OBSERVED,
                 100.0 * float((c[est] >= OBSERVED).mean()) if est.any() else 0.0,
                 ", ".join(f"{n} {100 * observed[j]:.0f}%" for j, n in _least_seen(observed)))
    ctx.stats.update({"observed_share": [round(float(v), 4) for v in observed], "gap_frames": int((~est).sum()),
                      "uncertainty_median_mm": [round(float(v), 1) for v in _column_medians(u[est])],
                      "solve_sigma": cues["sigma"] is not None, "calibration": cal["entry"],
                      "rate_factor": round(float(cal["rate_factor"]), 4), "view": cal["view"],
                      "view_factor": round(float(cal["view_factor"]), 4)})
    return {"confidence": JointConfidence(t_us=t_us, confidence=c.astype(np.float32),
                                          uncertainty_mm=u.astype(np.float32), estimated=est)}


def _median(x: np.ndarray) -> float:
    return float(np.median(x)) if x.size else float("nan")


def _column_medians(u: np.ndarray) -> np.ndarray:
    return np.median(u, axis=0) if u.size else np.full(24, np.nan)


def _least_seen(observed: np.ndarray, n: int = 3):
    from eventcap.body.skeleton import JOINT_NAMES

    order = np.argsort(observed, kind="stable")[:n]
    return [(int(j), JOINT_NAMES[j]) for j in order]
