"""A simulated CNN pose detector (stands in for OpenPose + VNect on synthetic captures with ground truth).

Nothing here looks at images: detections are the exact ground truth at each intensity frame, degraded by an
explicit error model whose parameters are the stage's config (see :class:`DetectorErrorModel`):

2D keypoints (the skeleton's BODY_25 landmarks, incl. eyes and ears), in this order:

1. *left/right flips*: per frame and left/right pair (shoulders, elbows, wrists, hips, knees, ankles, eyes, ears,
   toes, heels), with probability ``flip_prob`` the two keypoints trade places (both must be visible);
2. *Gaussian error*: per image axis with std ``sigma_px * b`` where ``b = 1 + blur_gain * streak_px`` and
   ``streak_px`` is the length of the path the (true) point draws on the image during the frame's exposure —
   motion blur is what makes detectors fail on fast motion;
3. *outliers*: with probability ``outlier_prob`` a keypoint is instead placed uniformly within a disc of radius
   ``outlier_radius_px`` around its true position;
4. positions are clipped to the image; keypoints out of the image, behind the camera or hidden behind the body
   (z-buffer of the recording's template, when it has one) are "not detected": position (0, 0), confidence 0;
5. confidence ``confidence / b``, times ``outlier_confidence`` for outliers (flips keep theirs: detectors are
   confidently wrong about sides).

3D joints (SMPL order, relative to the pelvis, world axes — the frame Eq. 7 compares with): truth plus a fixed
random offset per joint drawn once per sequence (std ``bias_m`` per axis, the systematic error of a learned
prior) plus per-frame Gaussian noise (std ``sigma_m`` per axis); the pelvis stays at the origin. Confidence
``confidence_3d / b`` of the joint's own blur, 0 for joints whose projection leaves the image.

Every random draw has a fixed shape from its own child stream of one generator, so changing one error's size
does not reshuffle the others (common random numbers across settings).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

from eventcap.body.skeleton import MIRROR_LANDMARKS, NUM_JOINTS, NUM_LANDMARKS

#: Left/right landmark pairs (i, mirror of i) with i < mirror, (11, 2).
LR_PAIRS: np.ndarray = np.array([(i, int(m)) for i, m in enumerate(MIRROR_LANDMARKS) if m > i], dtype=np.int64)
LR_PAIRS.setflags(write=False)


@dataclass(frozen=True)
class DetectorErrorModel:
    """Error model of the simulated detector; see the module docstring. Pixels, metres, probabilities."""

    sigma_px: float = 2.0
    outlier_prob: float = 0.02
    outlier_radius_px: float = 30.0
    flip_prob: float = 0.02
    blur_gain: float = 0.1
    sigma_m: float = 0.025
    bias_m: float = 0.04
    confidence: float = 0.9
    outlier_confidence: float = 0.3
    confidence_3d: float = 0.9

    def __post_init__(self):
        for f in fields(self):
            v = getattr(self, f.name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"DetectorErrorModel.{f.name}: expected a finite number >= 0, got {v!r}")
            object.__setattr__(self, f.name, float(v))
        for name in ("outlier_prob", "flip_prob", "confidence", "outlier_confidence", "confidence_3d"):
            if getattr(self, name) > 1:
                raise ValueError(f"DetectorErrorModel.{name}: expected a value in [0, 1], got {getattr(self, name)}")

    def describe(self) -> str:
        return ", ".join(f"{f.name}={getattr(self, f.name):g}" for f in fields(self))


@dataclass(frozen=True)
class FrameTruth:
    """What a perfect detector would see at each intensity frame (n frames, L = 25 landmarks, 24 joints).

    keypoints_px (n, L, 2) float64: projections of the landmarks (NaN behind the camera).
    visible (n, L) bool: inside the image, in front of the camera and not hidden by the body.
    streak_px (n, L) float64: length of the landmark's image path during the frame's exposure (0 if unknown).
    joints_rel_m (n, 24, 3) float64: joints minus the pelvis, world axes, metres.
    joint_in_image (n, 24) bool and joint_streak_px (n, 24): the same for the joints' projections.
    occlusion_checked: whether ``visible`` includes the z-buffer test (needs the recording's template).
    """

    t_us: np.ndarray
    keypoints_px: np.ndarray
    visible: np.ndarray
    streak_px: np.ndarray
    joints_rel_m: np.ndarray
    joint_in_image: np.ndarray
    joint_streak_px: np.ndarray
    occlusion_checked: bool


@dataclass(frozen=True)
class SimulatedDetections:
    """Output of :func:`simulate_detector` plus what was done to each keypoint (for tests and diagnostics).

    keypoints_px (n, L, 2), confidence (n, L), joints_3d_m (n, 24, 3), confidence_3d (n, 24),
    outlier (n, L) bool, flipped (n, L) bool, bias_m (24, 3) the sequence's 3D offsets, sigma_px (n, L) the std of
    each keypoint's Gaussian error per axis (sigma_px times its blur factor: the noise it simulates).
    """

    keypoints_px: np.ndarray
    confidence: np.ndarray
    joints_3d_m: np.ndarray
    confidence_3d: np.ndarray
    outlier: np.ndarray
    flipped: np.ndarray
    bias_m: np.ndarray
    sigma_px: np.ndarray


def interpolate_at(t_src_us: np.ndarray, values: np.ndarray, t_us: np.ndarray, what: str = "values") -> np.ndarray:
    """Linear interpolation in time of ``values`` (T, ...) sampled at sorted ``t_src_us`` (T,) at ``t_us`` (n,).

    Exact (bit for bit) at the sample times. Raises ValueError for times outside the sampled range.
    """
    t_src_us = np.asarray(t_src_us, dtype=np.int64)
    t_us = np.asarray(t_us, dtype=np.int64)
    values = np.asarray(values, dtype=np.float64)
    if t_src_us.ndim != 1 or values.shape[:1] != t_src_us.shape or t_src_us.size == 0:
        raise ValueError(f"{what}: expected samples (T, ...) at T times, got {values.shape} at {t_src_us.shape}")
    outside = (t_us < t_src_us[0]) | (t_us > t_src_us[-1])
    if outside.any():
        k = int(np.argmax(outside))
        raise ValueError(f"{what}: time {int(t_us[k])} us (query {k}) lies outside the sampled range "
                         f"[{int(t_src_us[0])}, {int(t_src_us[-1])}] us")
    if t_src_us.size == 1:
        return np.repeat(values, t_us.size, axis=0)
    i = np.clip(np.searchsorted(t_src_us, t_us, side="right") - 1, 0, t_src_us.size - 2)
    w = ((t_us - t_src_us[i]) / (t_src_us[i + 1] - t_src_us[i])).reshape((-1,) + (1,) * (values.ndim - 1))
    return (1.0 - w) * values[i] + w * values[i + 1]


def in_image(px: np.ndarray, height: int, width: int) -> np.ndarray:
    """Pixels (..., 2) inside the image (pixel centres at integers, so [-0.5, width - 0.5)); NaN -> False."""
    x, y = px[..., 0], px[..., 1]
    with np.errstate(invalid="ignore"):
        return np.isfinite(x) & np.isfinite(y) & (x >= -0.5) & (x < width - 0.5) & (y >= -0.5) & (y < height - 0.5)


def exposure_streaks(camera, gt_t_us: np.ndarray, gt_points: np.ndarray, t_us: np.ndarray,
                     exposure_us: np.ndarray) -> np.ndarray:
    """Image path length (n, K) in pixels of K points during each frame's exposure [t - e/2, t + e/2].

    gt_points (T, K, 3) world metres at gt_t_us (T,); the path is the polyline through the points' projections
    at the exposure's ends and every ground-truth sample in between (clipped to the sampled range). Frames with
    unknown exposure (0) get 0; segments with a point behind the camera count 0.
    """
    n, K = len(t_us), gt_points.shape[1]
    out = np.zeros((n, K))
    for f in range(n):
        half = int(exposure_us[f]) // 2
        if half <= 0:
            continue
        a = max(int(t_us[f]) - half, int(gt_t_us[0]))
        b = min(int(t_us[f]) + half, int(gt_t_us[-1]))
        if b <= a:
            continue
        inner = gt_t_us[(gt_t_us > a) & (gt_t_us < b)]
        times = np.concatenate([[a], inner, [b]]).astype(np.int64)
        px = camera.project(interpolate_at(gt_t_us, gt_points, times, "ground truth"))
        out[f] = np.nan_to_num(np.linalg.norm(np.diff(px, axis=0), axis=-1), nan=0.0).sum(axis=0)
    return out


def filmed_body(recording):
    """The body the camera filmed: the actor of a synthetic capture that films one of its own (the ground truth's
    ``actor``), else the recording's template (None when it has none)."""
    gt = recording.ground_truth
    if gt is not None and gt.actor:
        from eventcap.body.anny import anny_from_json

        return anny_from_json(gt.actor)
    return recording.template


def hidden_by_body(camera, template, poses: np.ndarray, points: np.ndarray, margin_m: float) -> np.ndarray:
    """(n, K) bool: points (n, K, 3) lie behind the template's surface posed by poses (n, 33) by more than margin_m.

    The surface depth is read from a z-buffer at the point's (rounded) pixel; pixels without surface hide
    nothing. Joints lie inside the body, a few centimetres behind their own limb's surface, hence the margin.
    """
    from eventcap.body.kinematics import skin
    from eventcap.imaging.render import rasterize

    n, K = points.shape[:2]
    hidden = np.zeros((n, K), dtype=bool)
    px = camera.project(points)
    inside = in_image(px, camera.height, camera.width)
    depth = camera.depth(points)
    for f in range(n):
        zbuf, _, _ = rasterize(camera, skin(poses[f], template), template.faces)
        k = np.flatnonzero(inside[f])
        c = np.clip(np.rint(px[f, k, 0]).astype(np.int64), 0, camera.width - 1)
        r = np.clip(np.rint(px[f, k, 1]).astype(np.int64), 0, camera.height - 1)
        hidden[f, k] = zbuf[r, c] < depth[f, k] - margin_m
    return hidden


def frame_truth(recording, occlusion: bool = True, occlusion_margin_m: float = 0.15,
                stage: str = "simulated", step_us: int = 0) -> FrameTruth:
    """Ground truth of a Recording at its intensity frames, as :class:`FrameTruth`.

    Landmarks (and the blur streaks) come from ``ground_truth.landmarks`` interpolated at ``frames.t_us``
    (exact when frames lie on the ground-truth grid, as in synthetic captures); joints from
    ``ground_truth.frame_joints`` (interpolated ``joints`` if their count differs from the frames'). The
    occlusion test needs the recording's template; without it only image bounds decide visibility.

    step_us > 0: instead of the intensity frames, every ``step_us`` from the first to the last frame (the tracking
    frames of the *_all baseline, detections on EDI latent images), modelled as sharp images (no exposure blur).
    """
    name = recording.name or recording.source or "(unnamed)"
    gt = recording.ground_truth
    if gt is None:
        raise ValueError(f"stage {stage!r} simulates a detector from ground truth, but recording {name!r} has no "
                         f"ground truth (a real recording?): use a real detector instead: stages/detect=blazepose "
                         f"(BlazePose on the images) or detections made elsewhere, stages/detect=file "
                         f"stages.detect.path=<OpenPose JSON folder, .npz or .csv>")
    frames = recording.frames
    if frames is None or frames.t_us.size == 0:
        raise ValueError(f"stage {stage!r}: recording {name!r} has no intensity frames to detect joints in")
    t_us, exposure = frames.t_us, frames.exposure_us
    if step_us > 0:
        t_us = np.arange(int(t_us[0]), int(t_us[-1]) + 1, int(step_us), dtype=np.int64)
        exposure = np.zeros(t_us.size, dtype=np.int64)
    cam = recording.camera
    where = f"recording {name!r}: ground-truth landmarks"
    landmarks = interpolate_at(gt.t_us, gt.landmarks, t_us, where)
    if landmarks.shape[1] != NUM_LANDMARKS:
        raise ValueError(f"{where}: expected {NUM_LANDMARKS} landmarks (BODY_25 order), got {landmarks.shape[1]}")
    # frame_* hold the truth at the recording's frame times, or at gt.frame_t_us when it says so.
    at_frames = gt.frame_joints.shape[0] == t_us.size and (gt.frame_t_us is None
                                                          or np.array_equal(gt.frame_t_us, t_us))
    if at_frames:
        joints = np.asarray(gt.frame_joints, dtype=np.float64)
    else:
        joints = interpolate_at(gt.t_us, gt.joints, t_us, f"recording {name!r}: ground-truth joints")
    keypoints = cam.project(landmarks)
    visible = in_image(keypoints, cam.height, cam.width)
    body = filmed_body(recording) if occlusion else None
    checked = body is not None
    if checked:
        poses = (np.asarray(gt.frame_poses) if at_frames
                 else interpolate_at(gt.t_us, gt.poses, t_us, f"recording {name!r}: ground-truth poses"))
        visible &= ~hidden_by_body(cam, body, poses, landmarks, occlusion_margin_m)
    return FrameTruth(
        t_us=np.asarray(t_us, dtype=np.int64), keypoints_px=keypoints, visible=visible,
        streak_px=exposure_streaks(cam, gt.t_us, gt.landmarks, t_us, exposure),
        joints_rel_m=joints - joints[:, :1], joint_in_image=in_image(cam.project(joints), cam.height, cam.width),
        joint_streak_px=exposure_streaks(cam, gt.t_us, gt.joints, t_us, exposure), occlusion_checked=checked,
    )


def simulate_detector(truth: FrameTruth, model: DetectorErrorModel, rng: np.random.Generator, height: int,
                      width: int) -> SimulatedDetections:
    """Degrade ``truth`` with ``model`` (module docstring), drawing from ``rng``; image ``height`` x ``width`` px."""
    n, L = truth.visible.shape
    g_flip, g_noise, g_out, g_bias, g_noise3 = rng.spawn(5)
    u_flip = g_flip.random((n, len(LR_PAIRS)))
    z2 = g_noise.standard_normal((n, L, 2))
    u_out, u_r, u_a = g_out.random((3, n, L))
    z_bias = g_bias.standard_normal((NUM_JOINTS, 3))
    z3 = g_noise3.standard_normal((n, NUM_JOINTS, 3))

    p = np.array(truth.keypoints_px, dtype=np.float64)
    streak = np.array(truth.streak_px, dtype=np.float64)
    vis = truth.visible
    a, b = LR_PAIRS[:, 0], LR_PAIRS[:, 1]
    flip = (u_flip < model.flip_prob) & vis[:, a] & vis[:, b]
    fr, fc = np.nonzero(flip)
    ia, ib = a[fc], b[fc]
    p[fr, ia], p[fr, ib] = p[fr, ib], p[fr, ia].copy()
    streak[fr, ia], streak[fr, ib] = streak[fr, ib], streak[fr, ia].copy()
    flipped = np.zeros((n, L), dtype=bool)
    flipped[fr, ia] = flipped[fr, ib] = True

    blur = 1.0 + model.blur_gain * streak
    detected = p + (model.sigma_px * blur)[..., None] * z2
    outlier = (u_out < model.outlier_prob) & vis
    radius = model.outlier_radius_px * np.sqrt(u_r)  # uniform over the disc's area
    jump = np.stack([radius * np.cos(2 * np.pi * u_a), radius * np.sin(2 * np.pi * u_a)], axis=-1)
    detected = np.where(outlier[..., None], p + jump, detected)
    detected[..., 0] = np.clip(detected[..., 0], 0.0, width - 1.0)
    detected[..., 1] = np.clip(detected[..., 1], 0.0, height - 1.0)
    confidence = model.confidence / blur * np.where(outlier, model.outlier_confidence, 1.0)
    detected = np.where(vis[..., None], detected, 0.0)
    confidence = np.where(vis, confidence, 0.0)

    bias = model.bias_m * z_bias
    bias[0] = 0.0
    noise3 = model.sigma_m * z3
    noise3[:, 0] = 0.0
    joints = truth.joints_rel_m + bias + noise3
    conf3 = np.where(truth.joint_in_image, model.confidence_3d / (1.0 + model.blur_gain * truth.joint_streak_px), 0.0)
    return SimulatedDetections(keypoints_px=detected, confidence=confidence, joints_3d_m=joints,
                               confidence_3d=conf3, outlier=outlier, flipped=flipped, bias_m=bias,
                               sigma_px=model.sigma_px * blur)
