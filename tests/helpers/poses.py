"""Recordings of exact ground truth without rendering, and running a detect stage on them."""

from __future__ import annotations

import functools

import numpy as np

from eventcap.artifacts.recording import EventStream, FrameStack, GroundTruth, Recording
from eventcap.body.kinematics import joint_positions, landmark_positions
from eventcap.body.motions import sequence_poses
from eventcap.body.skeleton import DEFAULT_REST_JOINTS
from eventcap.camera import davis240c_default
from eventcap.core.config import build_config
from eventcap.core.registry import load_registry
from eventcap.core.stage import StageContext
from eventcap.events import EVENT_DTYPE


@functools.lru_cache(maxsize=1)
def small_template():
    from eventcap.body.procedural import procedural_template

    return procedural_template(target_faces=3000)


@functools.lru_cache(maxsize=8)
def posed_recording(motion: str = "stand", n_frames: int = 100, speed: float = 1.0, yaw: float | None = None,
                    with_template: bool = False, ground_truth: bool = True) -> Recording:
    """A recording of exact ground truth without rendering (blank frames, no events): 25 fps, 10 ms exposure,
    ground truth at 1 kHz; the actor is the default skeleton (no template: no occlusion test) unless asked."""
    cam = davis240c_default()
    tpl = small_template() if with_template else None
    frame_t = 5_000 + 40_000 * np.arange(n_frames, dtype=np.int64)
    gt_t = np.arange(0, frame_t[-1] + 5_001, 1_000, dtype=np.int64)
    S = sequence_poses([(motion, gt_t[-1] * 1e-6)], gt_t * 1e-6, speed=speed, template=tpl)
    if yaw is not None:
        S[:, 27] = yaw
    body = tpl if tpl is not None else DEFAULT_REST_JOINTS
    joints, landmarks = joint_positions(S, body), landmark_positions(S, body)
    at = np.searchsorted(gt_t, frame_t)
    gt = GroundTruth(t_us=gt_t, poses=S, joints=joints, landmarks=landmarks, frame_poses=S[at],
                     frame_joints=joints[at], height=cam.height, width=cam.width)
    frames = FrameStack(images=np.zeros((n_frames, cam.height, cam.width), np.float32), t_us=frame_t,
                        exposure_us=np.full(n_frames, 10_000, np.int64), height=cam.height, width=cam.width)
    return Recording(events=EventStream(events=np.zeros(0, EVENT_DTYPE), width=cam.width, height=cam.height),
                     camera=cam, frames=frames, template=tpl, ground_truth=gt if ground_truth else None,
                     name=f"posed-{motion}")


def detect(stage: str, rec: Recording, **config):
    spec = load_registry().get(stage)
    cfg = build_config(spec, config, "stages.detect")
    return spec.load_run()({"recording": rec}, cfg, StageContext(node="detect", stage=stage))["detections"]


def truth_2d(rec: Recording) -> np.ndarray:
    """Ground-truth projections (n, 25, 2) of the landmarks at the frames (frames lie on the 1 kHz grid)."""
    gt = rec.ground_truth
    return rec.camera.project(gt.landmarks[np.searchsorted(gt.t_us, rec.frames.t_us)])


def truth_3d(rec: Recording) -> np.ndarray:
    j = rec.ground_truth.frame_joints
    return j - j[:, :1]
