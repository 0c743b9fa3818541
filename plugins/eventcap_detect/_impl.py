"""Run functions of the detect stages (imported when a stage runs)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from eventcap.artifacts.pose import Detections
from eventcap.core.stage import StageFailed

from .spec import SHIPPED_NOISE, noise_files


def _frame_times(rec, stage: str) -> np.ndarray:
    if rec.frames is None or rec.frames.t_us.size == 0:
        raise ValueError(f"stage {stage!r} detects joints in intensity frames, but recording "
                         f"{rec.name or rec.source or '(unnamed)'!r} has none (an event-only recording: pipeline=events_only "
                         f"detects in images reconstructed from the events)")
    return rec.frames.t_us


def _detections(t_us, kp, conf, joints, conf3, detector: str, view=None, noise=None) -> Detections:
    """The Detections artifact; noise: the detector's noise model, :class:`NoiseModel`."""
    in_view, status, up, world_R, turn = view if view is not None else (None, (), (), None, None)
    joints = np.asarray(joints, dtype=np.float64)
    if turn is not None:
        joints = joints @ turn  # the root-relative joints' axes: the assumed level world's -> the upright world's
    n = noise if noise is not None else NoiseModel(None, None, 0.0, "")
    return Detections(t_us=np.array(t_us, dtype=np.int64), keypoints_2d=np.asarray(kp, dtype=np.float32),
                      confidence_2d=np.clip(conf, 0.0, 1.0).astype(np.float32), joints_3d=joints,
                      confidence_3d=np.clip(conf3, 0.0, 1.0).astype(np.float32), detector=detector,
                      in_view=None if in_view is None else np.asarray(in_view, bool), image_status=tuple(status),
                      person_up=tuple(up), world_R=world_R,
                      sigma_2d_px=None if n.sigma_2d_px is None else np.asarray(n.sigma_2d_px, np.float32),
                      sigma_3d_m=None if n.sigma_3d_m is None else np.asarray(n.sigma_3d_m, np.float32),
                      bias_2d_px=None if n.bias_2d_px is None else np.asarray(n.bias_2d_px, np.float32),
                      bias_3d_m=None if n.bias_3d_m is None else np.asarray(n.bias_3d_m, np.float32),
                      outlier_share=float(n.outlier_share), noise_model=n.source)


@dataclass(frozen=True)
class NoiseModel:
    """A detector's noise model for its images: sigma_2d_px (n, 25) each landmark's white noise per image axis (px),
    sigma_3d_m (n, 24, 3) each root-relative joint's along each camera axis (m), bias_2d_px (25,) and bias_3d_m
    (24, 3) the spread of the offsets that stay over a capture, the share of outliers, and where it comes from (the
    Detections artifact's doc)."""

    sigma_2d_px: np.ndarray | None
    sigma_3d_m: np.ndarray | None
    outlier_share: float
    source: str
    bias_2d_px: np.ndarray | None = None
    bias_3d_m: np.ndarray | None = None


def view_settings(config):
    """The view checks' settings from a detect stage's config (ViewChecksConfig fields; the simulated detector has
    only min_found: it sees the ground truth, nothing to reject)."""
    from .checks import ViewSettings

    if not hasattr(config, "checks"):
        return ViewSettings.without_checks(config.min_found)
    return ViewSettings(checks=tuple(config.checks), border_px=config.border_px, min_in_view=config.min_in_view,
                        region_ratio=config.region_ratio, edge_ratio=config.edge_ratio, head_ratio=config.head_ratio,
                        shoulder_ratio=config.shoulder_ratio, window_us=config.check_window_us,
                        min_found=config.min_found, min_agree=getattr(config, "min_agree", 2),
                        agree_ratio=getattr(config, "agree_ratio", 0.2))


def person_up(joints: np.ndarray, conf3: np.ndarray, ok: np.ndarray, R: np.ndarray) -> tuple[tuple, int, float]:
    """The person's mean vertical in camera axes: the pelvis-to-shoulders direction of the accepted detections' 3D
    joints (world axes, turned back by the camera's rotation R); () when no accepted detection has both. Also the
    number of images it comes from and the median angle (degrees) of their verticals from the mean (how upright the
    person stayed: a person lying down for a while, bending or turning upside down spreads it)."""
    from eventcap.body.skeleton import JOINT_INDEX

    sh = [JOINT_INDEX["l_shoulder"], JOINT_INDEX["r_shoulder"]]
    use = ok & (conf3[:, sh] > 0).all(axis=1) & (conf3[:, 0] > 0)
    if not use.any():
        return (), 0, float("nan")
    v = joints[use][:, sh].mean(axis=1) - joints[use][:, 0]
    v = v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-9)
    up = R @ v.mean(axis=0)
    n = float(np.linalg.norm(up))
    if not n > 0.5:
        return (), int(use.sum()), float("nan")
    up = up / n
    spread = float(np.degrees(np.median(np.arccos(np.clip((v @ R.T) @ up, -1.0, 1.0)))))
    return tuple(float(x) for x in up), int(use.sum()), spread


#: The person's vertical turns an assumed level world (Recording.world 'assumed_level') upright only when measured in
#: at least this many accepted images, with the per-image verticals this close to their mean (median, degrees) and a
#: camera tilt (pitch or roll) within this bound: otherwise the person did not stand upright enough to say where up is.
UP_MIN_IMAGES = 5
UP_MAX_SPREAD_DEG = 20.0
UP_MAX_TILT_DEG = 60.0
#: A vertical within this angle of the assumed level world's y keeps it: that close, the measurement's own error
#: (docs/results/implementation.md) is as large as the tilt.
UP_MIN_TILT_DEG = 5.0


def upright_world(rec, up: tuple, n: int, spread: float, log) -> np.ndarray | None:
    """The world->camera rotation that makes the person's vertical the world's y, for a recording whose world was
    only assumed level (``Recording.world == 'assumed_level'``, no ground truth); None to keep the recording's camera.
    The log says which, and why."""
    from eventcap.camera import level_rotation, tilt_from_up

    if rec.world != "assumed_level":
        return None
    keep = "world frame: kept the camera assumed level (pitch 0, roll 0): "
    if rec.ground_truth is not None:
        log.info(keep + "the recording holds ground truth in that world")
        return None
    if not up or n < UP_MIN_IMAGES:
        log.warning(keep + "the person's vertical was measured in %d accepted images, fewer than %d (give "
                    "source.camera_pitch_deg / camera_roll_deg if the camera was tilted)", n, UP_MIN_IMAGES)
        return None
    pitch, roll = tilt_from_up(up)
    if spread > UP_MAX_SPREAD_DEG or max(abs(pitch), abs(roll)) > UP_MAX_TILT_DEG:
        log.warning(keep + "the person did not stay upright enough to say where up is (their vertical spreads "
                    "%.0f deg over %d images, at most %.0f; it would tilt the camera pitch %.0f deg, roll %.0f deg, "
                    "at most %.0f): give source.camera_pitch_deg / camera_roll_deg", spread, n, UP_MAX_SPREAD_DEG,
                    pitch, roll, UP_MAX_TILT_DEG)
        return None
    off = float(np.degrees(np.arccos(np.clip(np.dot(rec.camera.R @ np.array([0.0, 1.0, 0.0]), up), -1.0, 1.0))))
    if off < UP_MIN_TILT_DEG:
        log.info(keep + "the person's vertical (mean over %d images) is %.1f deg from it, within the measurement's "
                 "own error (%.0f deg)", n, off, UP_MIN_TILT_DEG)
        return None
    log.info("world frame: y up along the person's vertical (pelvis to shoulders, mean over %d images, spread %.0f "
             "deg): the camera is pitched %.0f deg, rolled %.0f deg (source.up=level keeps it level)", n, spread,
             pitch, roll)
    return level_rotation(pitch, roll)


def _log_world_up(rec, up: tuple, n: int, log) -> None:
    """Compare the world's y with the person's vertical; advise the tilt that makes them agree when they do not."""
    from eventcap.camera import tilt_from_up

    if not up:
        log.info("world up: not checked (no accepted detection with the shoulders and the pelvis in 3D)")
        return
    world_up = rec.camera.R @ np.array([0.0, 1.0, 0.0])
    angle = float(np.degrees(np.arccos(np.clip(np.dot(world_up, up), -1.0, 1.0))))
    pitch, roll = tilt_from_up(up)
    msg = (f"world up: the person's mean vertical (pelvis to shoulders, {n} images) is {angle:.0f} deg from the "
           f"world's y; a camera tilted pitch {pitch:.0f} deg, roll {roll:.0f} deg would make them agree")
    if angle > 20:
        log.warning(msg + f" (for a recording without extrinsics: source.camera_pitch_deg={pitch:.0f} "
                          f"source.camera_roll_deg={roll:.0f}; or the person does not stand upright)")
    else:
        log.info(msg)


def finish(rec, t_us, kp, conf, joints, conf3, in_view, found, config, ctx, what: str, joint_views=None,
           agreeing=None):
    """In view, checks, enough detections to solve: zero what is not observed, log per rejected image, stop the
    stage when too few images hold a detection (StageFailed naming the counts); the person's vertical, and the upright
    world it gives (:func:`upright_world`). Returns (in_view, status, up, world_R, turn): world_R None keeps the
    recording's camera; turn takes the joints' rows from the recording's world axes into world_R's."""
    from . import checks

    settings = view_settings(config)
    n = int(t_us.size)
    in_view = np.asarray(in_view, bool) & (conf > 0) & found[:, None]
    status, why_rejected = checks.check_images(kp, in_view, found, t_us, rec.events.events, rec.width, rec.height,
                                               settings, agreeing)
    for i, (st, w) in enumerate(zip(status, why_rejected)):
        if st == checks.CLOSE_UP:
            ctx.log.info("%s: image %d (t = %.3f s) a close-up: %s; its lower body marked unobserved", what, i,
                         t_us[i] / 1e6, w)
        elif st not in ("ok", "no_person"):
            ctx.log.info("%s: image %d (t = %.3f s) rejected by check %s: %s", what, i, t_us[i] / 1e6, st, w)
    ok = np.array([st in checks.ACCEPTED for st in status], bool)
    close = np.array([st == checks.CLOSE_UP for st in status], bool)
    rejected = np.array([st not in (*checks.ACCEPTED, "no_person") for st in status], bool)
    in_view &= ok[:, None]
    lower = np.setdiff1d(np.arange(in_view.shape[1]), checks.UPPER_BODY)
    in_view[np.ix_(close, lower)] = False  # a close-up: the body it drew under the head and shoulders is not seen
    conf[~in_view] = 0.0
    kp[~in_view & ~rejected[:, None]] = 0.0  # a rejected image keeps the detector's positions, to look at
    conf3[~ok] = 0.0
    conf3[np.ix_(close, checks.LOWER_JOINTS)] = 0.0
    if joint_views is not None:
        conf3[~joint_views] = 0.0
    summary = checks.found_message(status, what)
    gap = checks.longest_gap(status)
    ctx.stats.update({"images": n, "accepted": int(ok.sum()), "status": {k: status.count(k) for k in set(status)},
                      "longest_gap_images": gap})
    if n and ok.sum() < settings.min_found * n:
        why = (f": {100 * ok.sum() / n:.0f}% of the images, fewer than {100 * settings.min_found:.0f}% "
               f"(stages.detect.min_found={settings.min_found:g}): too few to solve anything") if ok.any() else ""
        a, b = checks.longest_stretch(status)
        if b - a + 1 >= 10:  # a stretch worth solving on its own: say how to cut it out
            why += (f"; the longest stretch with a person is images {a}-{b}: source.t_start_s={t_us[a] / 1e6:.2f} "
                    f"source.t_end_s={t_us[b] / 1e6:.2f} keeps it")
        hint = checks.refusal_hint(status, why_rejected, rec.images_from_events)
        raise StageFailed(f"{checks.found_message(status, what, enough=False)}{why}; {hint}",
                          status="too_few_detections" if ok.any() else "no_person")
    level = ctx.log.warning if ok.sum() < n else ctx.log.info
    level("%s; the longest run without one: %d images; %.1f%% of the accepted landmarks in view", summary, gap,
          100.0 * in_view[ok].mean() if ok.any() else 0.0)
    up, n_up, spread = person_up(joints, conf3, ok, rec.camera.R)
    world_R = upright_world(rec, up, n_up, spread, ctx.log)
    if world_R is None:
        _log_world_up(rec, up, n_up, ctx.log)
        return in_view, status, up, None, None
    return in_view, status, up, world_R, rec.camera.R.T @ world_R


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
    kp, conf, conf3 = sim.keypoints_px.copy(), sim.confidence.copy(), sim.confidence_3d.copy()
    view = finish(rec, truth.t_us, kp, conf, sim.joints_3d_m, conf3, conf > 0, np.ones(truth.t_us.size, bool),
                  config, ctx, "simulated detector")
    return {"detections": _detections(truth.t_us, kp, conf, sim.joints_3d_m, conf3, detector, view,
                                      simulated_noise(sim, model))}


def simulated_noise(sim, model) -> NoiseModel:
    """The noise model the simulated detector simulates, stated as it is (plugins/eventcap_detect/simulated.py): each
    landmark's white Gaussian error sigma_px times its blur factor (no 2D offset); each joint's per-frame noise
    sigma_m (white) and its fixed offset bias_m drawn once per capture (the pelvis is exact: the joints are relative
    to it); outliers and flips their probabilities."""
    n, J = sim.joints_3d_m.shape[:2]
    s3 = np.full((n, J, 3), float(model.sigma_m))  # isotropic: the same along every camera axis
    s3[:, 0] = 0.0
    b3 = np.full((J, 3), float(model.bias_m))
    b3[0] = 0.0
    return NoiseModel(sim.sigma_px, s3, float(min(1.0, model.outlier_prob + 2 * model.flip_prob)),
                      f"simulated: the error model it simulates (2D: sigma_px={model.sigma_px:g} x each landmark's blur "
                      f"factor, outliers {model.outlier_prob:g}, flips {model.flip_prob:g}; 3D: sigma_m="
                      f"{1000 * model.sigma_m:g} mm per image, bias_m={1000 * model.bias_m:g} mm per capture)",
                      np.zeros(sim.sigma_px.shape[1]), b3)


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
    from .checks import inside_image

    kp, conf, conf3 = np.array(kp, np.float64), np.array(conf, np.float64), np.array(conf3, np.float64)
    in_view = inside_image(kp, rec.width, rec.height, config.border_px)
    view = finish(rec, t_us, kp, conf, joints, conf3, in_view, (conf > 0).any(axis=1), config, ctx,
                  f"detections_file {Path(config.path).name}")
    not_root = (np.arange(joints.shape[1]) != 0)[:, None]
    white = np.where(not_root, 1e-3 * float(config.noise_3d_mm), 0.0).repeat(3, axis=1)
    noise = NoiseModel(np.full(kp.shape[:2], float(config.noise_px)), np.repeat(white[None], t_us.size, axis=0), 0.0,
                       f"file: stated by stages.detect.noise_px={config.noise_px:g} px, offset_px={config.offset_px:g} px, "
                       f"noise_3d_mm={config.noise_3d_mm:g} mm, offset_3d_mm={config.offset_3d_mm:g} mm (every axis)",
                       np.full(kp.shape[1], float(config.offset_px)),
                       np.where(not_root, 1e-3 * float(config.offset_3d_mm), 0.0).repeat(3, axis=1))
    return {"detections": _detections(t_us, kp, conf, joints, conf3, detector, view, noise)}


def _blazepose_images(rec, latent, config):
    """(times, images) the detector looks at, images as a lazy sequence of linear-intensity (H, W) arrays."""
    from eventcap.imaging import edi

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


def _event_alternatives(rec, times, config, log):
    """For images reconstructed from the events (``FrameStack.origin == 'events'``) detected at them (at=frames, or
    at=latent where the latent images are those reconstructions): the images of
    each moment the detector tries (config.event_images, :mod:`eventcap.imaging.event_images`); None otherwise."""
    from eventcap.imaging.event_images import event_image, parse_kind

    kinds = list(config.event_images or ())
    for k in kinds:
        try:
            parse_kind(k)
        except ValueError as exc:
            raise ValueError(f"stages.detect.event_images: {exc}") from None
    # at=latent on an event-only pipeline: its latent images are the same reconstructions
    if not kinds or config.at not in ("frames", "latent") or not rec.images_from_events:
        return None
    if kinds == ["reconstruction"]:
        return None
    events, h, w = rec.events.events, rec.height, rec.width
    log.info("blazepose: the images were reconstructed from the events: trying %s at each, keeping the one the "
             "network scores best (stages.detect.event_images)", " | ".join(kinds))

    def alternatives(i, image):
        return [(k, event_image(k, events, int(times[i]), h, w, reconstruction=image)) for k in kinds]

    return alternatives


def run_blazepose(inputs, config, ctx):
    from eventcap.body.skeleton import JOINT_NAMES, LANDMARK_NAMES

    from . import blazepose as bp
    from .checks import inside_image

    rec, latent = inputs["recording"], inputs.get("latent")
    if config.at not in ("frames", "latent", "tracking"):
        raise ValueError(f"stages.detect.at: expected frames | latent | tracking, got {config.at!r}")
    times, images = _blazepose_images(rec, latent, config)
    alternatives = _event_alternatives(rec, times, config, ctx.log)
    net = bp.BlazePose(config.model, config.detector_threshold, config.presence_threshold)
    seq = bp.detect_sequence(net, images, times, track=config.track, find=config.find, events=rec.events.events,
                             events_window_us=config.events_window_us, gamma=config.gamma,
                             log=ctx.log.warning, alternatives=alternatives, agree_ratio=config.agree_ratio)
    n = times.size
    w2 = bp.mapping_matrix(bp.LANDMARK_FROM_BLAZEPOSE, LANDMARK_NAMES)
    w3 = bp.mapping_matrix(bp.JOINT_FROM_BLAZEPOSE, JOINT_NAMES)
    kp = np.zeros((n, len(LANDMARK_NAMES), 2))
    conf = np.zeros((n, len(LANDMARK_NAMES)))
    joints = np.zeros((n, len(JOINT_NAMES), 3))
    conf3 = np.zeros((n, len(JOINT_NAMES)))
    in_view = np.zeros((n, len(LANDMARK_NAMES)), bool)
    joint_views = np.zeros((n, len(JOINT_NAMES)), bool)
    for i, pose in enumerate(seq.poses):
        if pose is None:
            continue
        kp[i], conf[i] = bp.mapped(w2, pose.xy, pose.visibility * pose.presence * pose.flag)
        j, conf3[i] = bp.mapped(w3, pose.world, pose.presence * pose.flag)
        joints[i] = (j - j[0]) @ rec.camera.R  # camera -> world axes (rows: v_world = R^T v_cam), root-relative
        # in view: present (the network's own output) and inside the image, for every point a landmark is made of
        seen = (pose.presence >= config.landmark_presence) & inside_image(pose.xy, rec.width, rec.height,
                                                                          config.border_px)
        in_view[i] = bp.mapped(w2, pose.xy, seen.astype(float))[1] > 0
        joint_views[i] = bp.mapped(w3, pose.world, seen.astype(float))[1] > 0
    in_view &= inside_image(kp, rec.width, rec.height, config.border_px)
    found = np.array([p is not None for p in seq.poses], bool)
    origins = [h.partition("@")[0] for h in seq.found_by]
    how = {k: origins.count(k) for k in ("tracked", "detector", "events", "last box", "image")}
    if alternatives is not None and found.any():
        kinds = [h.partition("@")[2] for h, f in zip(seq.found_by, found) if f]
        ctx.stats["best_image"] = {k: kinds.count(k) for k in sorted(set(kinds))}
        ctx.log.info("blazepose: the image it scored best, per image with a person: %s",
                     ", ".join(f"{k} {c}" for k, c in sorted(ctx.stats["best_image"].items(), key=lambda x: -x[1])))
    ms = 1000 * seq.seconds / max(n, 1)
    ctx.stats.update({"found": int(found.sum()), "found_by": how, "tracking_losses": len(seq.losses),
                      "ms_per_image": ms})
    ctx.log.info("blazepose (%s, at %s): person found in %d of %d images (tracked %d, detector %d, events %d, "
                 "last box %d, whole image %d), %d tracking losses, %.1f ms per image", config.model, config.at,
                 found.sum(), n, how["tracked"], how["detector"], how["events"], how["last box"], how["image"],
                 len(seq.losses), ms)
    agreeing = None if alternatives is None else (np.array(seq.agreeing), np.array(seq.tried))
    if agreeing is not None and found.any():
        ctx.stats["agreeing_images"] = {int(k): int((agreeing[0][found] == k).sum()) for k in
                                        np.unique(agreeing[0][found])}
    view = finish(rec, times, kp, conf, joints, conf3, in_view, found, config, ctx,
                  f"blazepose ({config.model}, at {config.at})", joint_views=joint_views, agreeing=agreeing)
    detector = (f"blazepose: BlazePose GHUM 3D {config.model} (MediaPipe Pose, TFLite) on {config.at} images, "
                f"track={config.track}, find={config.find}")
    frames = rec.frames.t_us if rec.frames is not None else np.zeros(0, np.int64)
    return {"detections": _detections(times, kp, conf, joints, conf3, detector, view,
                                      blazepose_noise(config.at, times, frames, noise_files(config.noise)[0],
                                                      event_images=rec.images_from_events))}


def blazepose_noise(at: str, times: np.ndarray, frame_t_us: np.ndarray, path: Path = SHIPPED_NOISE,
                    event_images: bool = False) -> NoiseModel:
    """BlazePose's noise model for images at ``times``: the measured noise of each kind of image (the raw frames,
    the EDI latent images at the frames, latent images between the frames, and images made from the events alone:
    ``event_images``, an event-only camera's; the raw frames' where the table measures none), per landmark and joint or one
    figure for all, from ``models/blazepose_noise.json`` (benchmarks/accuracy/detector_noise.py): white noise per
    image and a capture's offset (none where the table states none: BlazePose's 3D is an effective figure, the
    table's ``source`` says why), the 2D ones times √ of the table's ``inflation_2d`` (the landmarks of an image err
    together: d coordinates tell what d / inflation independent ones would). An image between the frames (at=tracking) that falls on
    an intensity frame counts as a latent image at the frame."""
    import json

    from eventcap.body.skeleton import NUM_JOINTS, NUM_LANDMARKS

    path = Path(path)
    table = json.loads(path.read_text())
    t = np.asarray(times, dtype=np.int64)
    kind = np.full(t.size, "frames" if at == "frames" else "latent", dtype=object)
    if event_images:
        kind[:] = "events" if "events" in table["landmarks_2d_px"] else "frames"
    elif at == "tracking":
        kind[~np.isin(t, np.asarray(frame_t_us, dtype=np.int64))] = "between"

    def per(name: str, k: str, shape: tuple, unit: float) -> np.ndarray:
        """A figure of the table for one kind of image: one for all, per point, per axis, or per point and axis. A
        latent image between the frames that the table does not measure counts as one at the frames (they are made
        alike, and measured alike where both were: docs/results/events-add.md)."""
        row = table[name].get(k, table[name]["latent"] if k == "between" else None)
        if row is None:
            raise ValueError(f"{path}: {name}: no figure for the {k!r} images (expected one of "
                             f"{sorted(table[name])})")
        return np.broadcast_to(np.asarray(row, dtype=np.float64) * unit, shape).copy()

    s2 = np.stack([per("landmarks_2d_px", k, (NUM_LANDMARKS,), 1.0) for k in kind]) if t.size else \
        np.zeros((0, NUM_LANDMARKS))
    s3 = (np.stack([per("joints_3d_mm", k, (NUM_JOINTS, 3), 1e-3) for k in kind]) if t.size
          else np.zeros((0, NUM_JOINTS, 3)))
    s3[:, 0] = 0.0  # the joints are relative to the pelvis
    # a capture's offset: that of the images it mostly holds
    most = str(kind[0]) if event_images and t.size else ("frames" if at == "frames" else "latent")
    # an image's landmarks err together: each counts as its spread times √(d / n_eff), the table's inflation
    inflate = table.get("inflation_2d", {})
    s2 = s2 * np.sqrt(np.array([float(inflate.get(k if k in inflate else "latent", 1.0)) for k in kind]))[:, None]
    b2 = per("bias_2d_px", most, (NUM_LANDMARKS,), 1.0) * np.sqrt(float(inflate.get(most, 1.0)))
    b3 = per("bias_3d_mm", most, (NUM_JOINTS, 3), 1e-3) if "bias_3d_mm" in table else np.zeros((NUM_JOINTS, 3))
    b3[0] = 0.0
    return NoiseModel(s2, s3, float(table.get("outlier_share", 0.0)), f"blazepose: {table['source']}", b2, b3)
