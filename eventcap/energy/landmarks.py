"""Where the detector puts the hips and shoulders on this person (not in the paper): their widths, from the data.

A 2D detector's points are its own definition, not the template's joints: BlazePose puts the hips and the
shoulders nearer together in the image than the ANNY actor's hip and shoulder joints (docs/results/
implementation.md). Fitted to the template's joints, narrower hips can only be a pelvis turned away from the camera:
depth error at the hips, and through them at the legs and the torso.

Each pair's (left, right) scale is measured per capture, without ground truth: for every intensity frame whose two
points have confident 2D and 3D detections, the length the 2D points show along the direction the 3D detection
gives them (:func:`eventcap.camera.seen_length`: the segment along that direction whose ends lie on the two points'
rays, its middle at the depth of the frame's per-frame fit; the 3D detector's direction, not its metric length),
against the template's width. The scale is the median over the frames where the pair lies mostly
across the line of sight (that share of the direction >= 0.7, where the ratio is well conditioned), clipped to
[0.6, 1.2]; too few frames (fewer than 5) keep the template's. The solve's template then has the pair's landmarks
moved towards the pair's middle by its scale, attached to the pair's parent joint (the pelvis, the collars), so
that they move with the body, not with the limbs.

The limbs' lengths cannot be measured so: BlazePose's shins are shorter in 2D than the actor's, but its 3D shins
tilt along the line of sight by as much, so their direction explains the short 2D points.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from eventcap.body.kinematics import joint_positions
from eventcap.body.skeleton import JOINT_INDEX, LANDMARK_INDEX, PARENTS
from eventcap.camera import seen_length

#: The left-right pairs whose width a detector defines its own way.
PAIRS = (("l_hip", "r_hip"), ("l_shoulder", "r_shoulder"))
MIN_FRAMES = 5
MIN_ACROSS = 0.7
SCALE_RANGE = (0.6, 1.2)


@dataclass(frozen=True)
class LandmarkWidths:
    """The detector's width of each pair against the template's (1: as the template), and the frames behind it."""

    scale: dict  #: pair name ("l_hip-r_hip") -> scale
    frames: dict  #: pair name -> frames used (0: the template's width kept)


def measure_widths(template, camera, fits: np.ndarray, det) -> LandmarkWidths:
    """The width scale of each pair of :data:`PAIRS` (module doc) from the per-frame fits (K, 33) at K detection
    frames and their detections (FrameDetections of those K frames)."""
    Jc = camera.to_camera(joint_positions(np.atleast_2d(fits), template.rest_joints))  # (K, 24, 3)
    scale, frames = {}, {}
    for a, b in PAIRS:
        ja, jb, la, lb = JOINT_INDEX[a], JOINT_INDEX[b], LANDMARK_INDEX[a], LANDMARK_INDEX[b]
        ok = ((det.confidence_2d[:, la] > 0) & (det.confidence_2d[:, lb] > 0) & (det.confidence_3d[:, ja] > 0)
              & (det.confidence_3d[:, jb] > 0))
        name = f"{a}-{b}"
        scale[name], frames[name] = 1.0, 0
        if ok.sum() < MIN_FRAMES:
            continue
        n = camera.undistort_points(det.keypoints_2d[ok][:, [la, lb]])
        z = 0.5 * (Jc[ok, ja, 2] + Jc[ok, jb, 2])
        v = (det.joints_3d[ok, ja] - det.joints_3d[ok, jb]) @ camera.R.T
        across = np.linalg.norm(v[:, :2], axis=1) / np.maximum(np.linalg.norm(v, axis=1), 1e-9)
        length = seen_length(n[:, 0], n[:, 1], v, z)
        ratio = length / np.linalg.norm(template.rest_joints[ja] - template.rest_joints[jb])
        use = (across >= MIN_ACROSS) & np.isfinite(ratio) & (z > 0) & (ratio > 0)
        if use.sum() < MIN_FRAMES:
            continue
        scale[name] = float(np.clip(np.median(ratio[use]), *SCALE_RANGE))
        frames[name] = int(use.sum())
    return LandmarkWidths(scale, frames)


def with_widths(template, widths: LandmarkWidths):
    """The template with each pair's landmarks moved towards the pair's middle by its scale (module doc)."""
    lj = np.array(template.landmark_joint, dtype=np.int64)
    lo = np.array(template.landmark_offset, dtype=np.float64)
    rest = template.rest_joints
    for a, b in PAIRS:
        s = widths.scale.get(f"{a}-{b}", 1.0)
        if s == 1.0:
            continue
        mid = 0.5 * (rest[JOINT_INDEX[a]] + rest[JOINT_INDEX[b]])
        for name in (a, b):
            j, lm = JOINT_INDEX[name], LANDMARK_INDEX[name]
            p = int(PARENTS[j])
            point = rest[lj[lm]] + lo[lm]  # the landmark where the template has it
            lj[lm], lo[lm] = p, mid + s * (point - mid) - rest[p]
    tag = ",".join(f"{k}={v:.3f}" for k, v in widths.scale.items())
    return replace(template, name=f"{template.name}[widths {tag}]", landmark_joint=lj, landmark_offset=lo)


__all__ = ["PAIRS", "LandmarkWidths", "measure_widths", "with_widths"]
