"""Run functions of the detect stages (imported when a stage runs)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from eventcap.artifacts.pose import Detections


def _frame_times(rec, stage: str) -> np.ndarray:
    if rec.frames is None or rec.frames.t_us.size == 0:
        raise ValueError(f"stage {stage!r} detects joints in intensity frames, but recording "
                         f"{rec.name or rec.source or '(unnamed)'!r} has none (an event-only recording: pipeline=events_only "
                         f"detects in images reconstructed from the events)")
    return rec.frames.t_us


def _detections(t_us, kp, conf, joints, conf3, detector: str) -> Detections:
    return Detections(t_us=np.array(t_us, dtype=np.int64), keypoints_2d=np.asarray(kp, dtype=np.float32),
                      confidence_2d=np.clip(conf, 0.0, 1.0).astype(np.float32),
                      joints_3d=np.asarray(joints, dtype=np.float64),
                      confidence_3d=np.clip(conf3, 0.0, 1.0).astype(np.float32), detector=detector)


def run_simulated(inputs, config, ctx):
    from .simulated import DetectorErrorModel, frame_truth, simulate_detector

    rec = inputs["recording"]
    _frame_times(rec, "simulated")
    model = DetectorErrorModel(
        sigma_px=config.sigma_px, outlier_prob=config.outlier_prob, outlier_radius_px=config.outlier_radius_px,
        flip_prob=config.flip_prob, blur_gain=config.blur_gain, sigma_m=config.sigma_m, bias_m=config.bias_m,
        confidence=config.confidence, outlier_confidence=config.outlier_confidence,
        confidence_3d=config.confidence_3d,
    )
    if config.at not in ("frames", "tracking"):
        raise ValueError(f"stages.detect.at: expected 'frames' or 'tracking', got {config.at!r}")
    if config.at == "tracking" and config.tracking_step_us <= 0:
        raise ValueError(f"stages.detect.tracking_step_us: expected a positive step in us, got {config.tracking_step_us}")
    truth = frame_truth(rec, occlusion=config.occlusion, occlusion_margin_m=config.occlusion_margin_m,
                        step_us=config.tracking_step_us if config.at == "tracking" else 0)
    sim = simulate_detector(truth, model, ctx.rng(config.seed), rec.height, rec.width)
    ctx.log.info("simulated detector: %d frames, %.1f%% of keypoints visible, %d outliers, %d flipped pairs, "
                 "median blur streak %.1f px%s", truth.t_us.size, 100 * truth.visible.mean(), sim.outlier.sum(),
                 sim.flipped.sum() // 2, float(np.median(truth.streak_px)),
                 "" if truth.occlusion_checked else " (no template: occlusion not checked)")
    detector = (f"simulated: ground-truth projections with a CNN-like error model ({model.describe()}, "
                f"seed={config.seed}, occlusion={'z-buffer' if truth.occlusion_checked else 'off'})")
    return {"detections": _detections(truth.t_us, sim.keypoints_px, sim.confidence, sim.joints_3d_m,
                                      sim.confidence_3d, detector)}


def run_file(inputs, config, ctx):
    from . import files

    rec = inputs["recording"]
    t_us = _frame_times(rec, "detections_file")
    if not config.path:
        raise ValueError("stages.detect.path: the detections file or folder is not set (stage 'detections_file')")
    mapping = files.keypoint_mapping(config.layout, config.mapping)
    fmt = files.resolve_format(config.path, config.format)
    table = files.read_detection_table(config.path, fmt, config.layout, config.match)
    rows = files.frame_rows(table, t_us, config.first_frame, config.time_tolerance_us)
    kp, conf = files.keypoints_at_frames(table, rows, mapping, config.layout)
    source_3d = table
    rows_3d = rows
    if config.path_3d:
        source_3d = files.read_detection_table(config.path_3d, files.resolve_format(config.path_3d, "auto"))
        if source_3d.joints_3d is None:
            raise files.DetectionFileError(config.path_3d, "holds no 3D joints (npz joints_3d / csv j<j>_x columns)")
        rows_3d = files.frame_rows(source_3d, t_us, config.first_frame, config.time_tolerance_us)
    joints, conf3 = files.joints_at_frames(source_3d, rows_3d, rec.camera.R, config.frame_3d, config.unit_3d)
    missing = int((rows < 0).sum())
    if missing:
        ctx.log.warning("detections_file: %d of %d intensity frames have no detections in %s (confidence 0)",
                        missing, t_us.size, config.path)
    if source_3d.joints_3d is None:
        ctx.log.info("detections_file: %s has no 3D joints (zeros with confidence 0)", config.path)
    detector = f"file: {Path(config.path).name} ({fmt}, layout {config.layout})"
    if config.path_3d:
        detector += f"; 3D: {Path(config.path_3d).name}"
    return {"detections": _detections(t_us, kp, conf, joints, conf3, detector)}
