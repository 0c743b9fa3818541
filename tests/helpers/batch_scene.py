"""The batch solve's scene: a fast motion's first batch with exact detections and ground-truth surface tracks (no event
simulation), its problem and its stage inputs."""

from __future__ import annotations

import functools

import numpy as np
from eventcap_solve.batch import BatchProblem

from eventcap.analysis.metrics import mean_joint_error
from eventcap.artifacts import BatchPlan
from eventcap.artifacts.tracking import SlicedTracks
from eventcap.body.kinematics import joint_positions
from eventcap.params import nest
from eventcap.sim.capture import _pick_track_points, _track_points
from .poses import detect, posed_recording

T0, N = 5_000, 40  # first batch of posed_recording: frames at 5 ms and 45 ms, tracking frames every 1 ms


EXACT = dict(sigma_px=0.0, sigma_m=0.0, bias_m=0.0, outlier_prob=0.0, flip_prob=0.0, blur_gain=0.0)


@functools.lru_cache(maxsize=2)
def scene(motion: str = "high_knees", speed: float = 2.0, n_points: int = 200):
    """A fast motion's first batch with exact detections and ground-truth surface tracks (no event simulation)."""
    rec = posed_recording(motion, n_frames=3, speed=speed, with_template=True)
    det = detect("simulated", rec, **EXACT)
    t_us = T0 + 1_000 * np.arange(N + 1, dtype=np.int64)
    gt = rec.ground_truth
    S = gt.poses[np.searchsorted(gt.t_us, t_us)]
    tri, bary = _pick_track_points(rec.template, rec.camera, lambda t: S[np.searchsorted(t_us, np.rint(t * 1e6))],
                                   t_us[[0, N // 2, N]], n_points, seed=0)
    xy, valid = _track_points(rec.template, rec.camera, S, tri, bary)
    return rec, det, t_us, S, xy, valid


def problem(**config) -> BatchProblem:
    """The batch problem of the scene with the stage's config (defaults but for the changes given, by dotted key:
    problem(**{"tracks.edge_margin_px": 0.0}))."""
    return _problem(tuple(sorted(config.items())))


@functools.lru_cache(maxsize=8)
def _problem(config: tuple) -> BatchProblem:
    rec = scene()[0]
    from eventcap.core.config import build_config
    from eventcap.core.registry import load_registry

    cfg = build_config(load_registry().get("batch"), nest(dict(config)), "stages.solve")
    return BatchProblem(rec.template, rec.camera, N + 1, cfg)


def joint_error_mm(rec, poses, truth) -> np.ndarray:
    rest = rec.template.rest_joints
    return 1000 * mean_joint_error(joint_positions(poses, rest), joint_positions(truth, rest))


def stage_inputs():
    rec, det, t_us, S, xy, valid = scene()
    sliced = SlicedTracks(t_us=t_us, xy=np.where(valid[..., None], xy, np.nan).astype(np.float32), valid=valid,
                          track_id=np.arange(xy.shape[1], dtype=np.int32))
    plan = BatchPlan(t0_us=np.array([T0]), t1_us=np.array([T0 + 1000 * N]), frame0=np.array([0]))
    return {"recording": rec, "sliced": sliced, "detections": det, "batches": plan}
