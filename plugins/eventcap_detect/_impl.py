"""Run functions of the detect stages (imported when a stage runs)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from eventcap.artifacts.pose import Detections
from eventcap.stage import StageFailed


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


def _blazepose_images(rec, latent, config):
    """(times, images) the detector looks at, images as a lazy sequence of linear-intensity (H, W) arrays."""
    from eventcap import edi

    if config.at == "frames":
        frames = rec.require_frames("blazepose")
        return frames.t_us.copy(), frames.images
    if latent is None:
        raise ValueError(f"stages.detect.at={config.at}: the blazepose node needs the EDI latent images as its "
                         f"'latent' input (wire latent: sharpen.latent; conf/stages/detect/blazepose.yaml does)")
    if config.at == "latent":
        return latent.t_us.copy(), [edi.to_linear(L, latent.eps) for L in latent.log_images]
    if config.tracking_step_us <= 0:
        raise ValueError(f"stages.detect.tracking_step_us: expected a positive step in us, got "
                         f"{config.tracking_step_us}")
    tf = latent.t_us
    times = np.arange(int(tf[0]), int(tf[-1]) + 1, int(config.tracking_step_us), dtype=np.int64)
    nearest = np.clip(np.searchsorted(tf, times), 1, tf.size - 1)
    nearest -= (times - tf[nearest - 1]) < (tf[nearest] - times)  # the nearer of the two frames

    def images():
        events = rec.events.events
        for k in np.unique(nearest):
            logs = edi.latent_log_sequence(latent.log_images[k], int(tf[k]), times[nearest == k], events,
                                           latent.contrast)
            yield from (edi.to_linear(L, latent.eps) for L in logs)

    return times, images()


def run_blazepose(inputs, config, ctx):
    from eventcap.body.skeleton import JOINT_NAMES, LANDMARK_NAMES

    from . import blazepose as bp

    rec, latent = inputs["recording"], inputs.get("latent")
    if config.at not in ("frames", "latent", "tracking"):
        raise ValueError(f"stages.detect.at: expected frames | latent | tracking, got {config.at!r}")
    times, images = _blazepose_images(rec, latent, config)
    net = bp.BlazePose(config.model, config.detector_threshold, config.presence_threshold)
    seq = bp.detect_sequence(net, images, times, track=config.track, find=config.find, events=rec.events.events,
                             events_window_us=config.events_window_us, gamma=config.gamma,
                             log=ctx.log.warning)
    n = times.size
    w2 = bp.mapping_matrix(bp.LANDMARK_FROM_BLAZEPOSE, LANDMARK_NAMES)
    w3 = bp.mapping_matrix(bp.JOINT_FROM_BLAZEPOSE, JOINT_NAMES)
    kp = np.zeros((n, len(LANDMARK_NAMES), 2))
    conf = np.zeros((n, len(LANDMARK_NAMES)))
    joints = np.zeros((n, len(JOINT_NAMES), 3))
    conf3 = np.zeros((n, len(JOINT_NAMES)))
    for i, pose in enumerate(seq.poses):
        if pose is None:
            continue
        kp[i], conf[i] = bp.mapped(w2, pose.xy, pose.visibility * pose.presence * pose.flag)
        j, conf3[i] = bp.mapped(w3, pose.world, pose.presence * pose.flag)
        joints[i] = (j - j[0]) @ rec.camera.R  # camera -> world axes (rows: v_world = R^T v_cam), root-relative
    outside = (kp[..., 0] < 0) | (kp[..., 1] < 0) | (kp[..., 0] > rec.width - 1) | (kp[..., 1] > rec.height - 1)
    conf[outside] = 0.0
    kp[conf == 0] = 0.0
    found = sum(p is not None for p in seq.poses)
    if n and not found:
        raise StageFailed(f"blazepose ({config.model}, at {config.at}): no person found in any of the {n} images "
                          f"(detector, events and the whole image tried; is there a person in view?)",
                          status="no_person")
    how = {k: seq.found_by.count(k) for k in ("tracked", "detector", "events", "image")}
    ms = 1000 * seq.seconds / max(n, 1)
    ctx.stats.update({"images": n, "found": found, "found_by": how, "tracking_losses": len(seq.losses),
                      "ms_per_image": ms})
    level = ctx.log.warning if found < n else ctx.log.info
    level("blazepose (%s, at %s): person found in %d of %d images (tracked %d, detector %d, events %d, whole "
          "image %d), %d tracking losses, %.1f ms per image", config.model, config.at, found, n, how["tracked"],
          how["detector"], how["events"], how["image"], len(seq.losses), ms)
    detector = (f"blazepose: BlazePose GHUM 3D {config.model} (MediaPipe Pose, TFLite) on {config.at} images, "
                f"track={config.track}, find={config.find}")
    return {"detections": _detections(times, kp, conf, joints, conf3, detector)}
