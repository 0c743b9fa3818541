"""The evaluation's scene: a recording with ground truth on an odd skeleton and per-batch poses made from it, and
running the evaluate stage on them."""

from __future__ import annotations

import functools

import numpy as np

from eventcap.artifacts.pose import PoseSequence
from eventcap.artifacts.recording import EventStream, FrameStack, GroundTruth, Recording
from eventcap.body.kinematics import joint_positions, landmark_positions
from eventcap.body.motions import motion_poses
from eventcap.body.skeleton import DEFAULT_REST_JOINTS, default_landmarks
from eventcap.body.template import Template
from eventcap.camera import davis240c_default
from eventcap.core.config import build_config
from eventcap.core.registry import load_registry
from eventcap.core.stage import StageContext
from eventcap.events import EVENT_DTYPE

STAGES = "eventcap_evaluate.spec:EVALUATE"


FRAME_STEP_US = 40_000  # 25 fps intensity frames


T0_US = 5_000


def odd_rest() -> np.ndarray:
    """A rest skeleton unlike the default one, so the stage must use the recording's template."""
    return DEFAULT_REST_JOINTS * 1.1 + np.random.default_rng(3).normal(0.0, 0.005, (24, 3))


@functools.lru_cache(maxsize=1)
def tiny_template() -> Template:
    """A template with the odd skeleton and a token mesh (a tetrahedron skinned to the pelvis): the evaluation
    needs only its rest joints."""
    rest = odd_rest()
    v = rest[0] + 0.1 * np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float64)
    w = np.zeros((4, 24))
    w[:, 0] = 1.0
    lj, lo = default_landmarks(rest)
    return Template("tiny", rest, v, np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]), w,
                    np.full(4, 0.5, np.float32), lj, lo)


@functools.lru_cache(maxsize=4)
def recording(n_frames: int = 4, ground_truth: bool = True, template: bool = True, n_events: int = 5_000,
              gt_end_us: int | None = None) -> Recording:
    """Intensity frames every 40 ms from 5 ms (blank), uniform random events, ground truth at 1 kHz."""
    cam = davis240c_default()
    tpl = tiny_template()
    frame_t = T0_US + FRAME_STEP_US * np.arange(n_frames, dtype=np.int64)
    gt_t = np.arange(0, (gt_end_us or frame_t[-1] + 5_000) + 1, 1_000, dtype=np.int64)
    S = motion_poses("jumping_jack", gt_t * 1e-6, speed=2.0)
    joints = joint_positions(S, tpl)
    at = np.searchsorted(gt_t, frame_t).clip(max=gt_t.size - 1)
    gt = GroundTruth(t_us=gt_t, poses=S, joints=joints, landmarks=landmark_positions(S, tpl), frame_poses=S[at],
                     frame_joints=joints[at], height=cam.height, width=cam.width)
    frames = FrameStack(images=np.zeros((n_frames, cam.height, cam.width), np.float32), t_us=frame_t,
                        exposure_us=np.full(n_frames, 10_000, np.int64), height=cam.height, width=cam.width)
    rng = np.random.default_rng(0)
    ev = np.zeros(n_events, EVENT_DTYPE)
    ev["t"] = np.sort(rng.integers(0, frame_t[-1] + 10_000, n_events))
    ev["x"] = rng.integers(0, cam.width, n_events)
    ev["y"] = rng.integers(0, cam.height, n_events)
    ev["p"] = rng.choice(np.array([-1, 1], np.int8), n_events)
    return Recording(events=EventStream(events=ev, width=cam.width, height=cam.height), camera=cam, frames=frames,
                     template=tpl if template else None, ground_truth=gt if ground_truth else None,
                     name="tiny-eval")


def batch_sequences(rec: Recording, perturb=None) -> list[PoseSequence]:
    """What the solve stage gives: per batch, poses at every tracking frame t0..t1 (1 ms) — the ground truth, changed
    by ``perturb(t_us, S) -> S`` — so neighbouring batches share their boundary frame."""
    gt, ft = rec.ground_truth, rec.frames.t_us
    out = []
    for t0, t1 in zip(ft[:-1], ft[1:]):
        t = np.arange(t0, t1 + 1, 1_000, dtype=np.int64)
        S = gt.poses[np.searchsorted(gt.t_us, t)].copy()
        if perturb is not None:
            S = perturb(t, S)
        out.append(PoseSequence(t_us=t, poses=S, status="Solve_Succeeded", iterations=5))
    return out


def evaluate(rec: Recording, poses, **config):
    spec = load_registry().get("evaluate")
    cfg = build_config(spec, config, "stages.evaluate")
    out = spec.load_run()({"recording": rec, "poses": poses}, cfg, StageContext(node="evaluate", stage="evaluate"))
    return out["metrics"].values, out["errors"]
