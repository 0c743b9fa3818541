"""The refinement's scene: an actor's first batch with exact ground truth and one event on every pixel of its true
silhouette boundary, and running the silhouette stage on it."""

from __future__ import annotations

import functools

import numpy as np

from eventcap.artifacts import BatchPlan
from eventcap.artifacts.pose import PoseSequence
from eventcap.artifacts.recording import EventStream, Recording
from eventcap.body.skeleton import pose_bounds
from eventcap.core.config import build_config
from eventcap.params import nest
from eventcap.core.registry import load_registry
from eventcap.core.stage import StageContext
from eventcap.energy.boundary import (
    boundary_pixels,
    silhouettes,
)
from eventcap.events import EVENT_DTYPE
from .poses import posed_recording

T0, N = 5_000, 40  # first batch of posed_recording: frames at 5 ms and 45 ms, tracking frames every 1 ms


def boundary_events(template, camera, poses, t_us) -> np.ndarray:
    """One event (+1) on every silhouette boundary pixel of the template posed with poses[f], at t_us[f]."""
    frame, px, _ = boundary_pixels(silhouettes(template, camera, poses))
    ev = np.zeros(frame.size, EVENT_DTYPE)
    ev["t"], ev["x"], ev["y"], ev["p"] = t_us[frame], px[:, 0], px[:, 1], 1
    return ev[np.argsort(ev["t"], kind="stable")]


@functools.lru_cache(maxsize=2)
def scene(motion: str = "high_knees", speed: float = 1.0):
    """A moving actor's first batch with exact ground truth and events on the true silhouette boundary (module
    doc): (recording, t_us (41,), ground-truth poses (41, 33), ground-truth masks (41, H, W))."""
    rec = posed_recording(motion, n_frames=3, speed=speed, with_template=True)
    t_us = T0 + 1_000 * np.arange(N + 1, dtype=np.int64)
    gt = rec.ground_truth
    S = gt.poses[np.searchsorted(gt.t_us, t_us)]
    ev = boundary_events(rec.template, rec.camera, S, t_us)
    rec = Recording(events=EventStream(events=ev, width=rec.camera.width, height=rec.camera.height),
                    camera=rec.camera, frames=rec.frames, template=rec.template, ground_truth=rec.ground_truth,
                    name=f"{rec.name}-boundary-events")
    return rec, t_us, S, silhouettes(rec.template, rec.camera, S)


def perturbed(S: np.ndarray, seed: int = 0, angles_rad: float = 0.05, root_rad: float = 0.05,
              root_m: float = 0.02) -> np.ndarray:
    """Ground truth with a known error, the same at every frame: N(0, angles_rad) on the 27 joint angles,
    N(0, root_rad) on the root rotation and N(0, root_m) on the root translation; clipped into the joint bounds."""
    rng = np.random.default_rng(seed)
    out = S.copy()
    out[:, :27] += rng.normal(0, angles_rad, 27)
    out[:, 27:30] += rng.normal(0, root_rad, 3)
    out[:, 30:] += rng.normal(0, root_m, 3)
    lo, hi = pose_bounds()
    return np.clip(out, lo, hi)


def stage_inputs(frames: int = N + 1, start: np.ndarray | None = None):
    rec, t_us, S, _ = scene()
    poses = perturbed(S) if start is None else start
    est = PoseSequence(t_us=t_us[:frames].copy(), poses=poses[:frames].copy(), status="Solve_Succeeded")
    plan = BatchPlan(t0_us=np.array([T0]), t1_us=np.array([T0 + 1000 * (frames - 1)]), frame0=np.array([0]))
    return {"recording": rec, "poses": est, "batches": plan}


def run_stage(inputs=None, **config):
    spec = load_registry().get("silhouette")
    inputs = inputs or stage_inputs()
    plan = inputs["batches"]
    ctx = StageContext(node="refine", stage="silhouette", batch=plan.batch(0))
    return spec.load_run()(inputs, build_config(spec, nest(config), "stages.refine"), ctx), ctx
