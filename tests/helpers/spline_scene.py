"""The spline solve's scene: a window of 3 batches of a fast motion with simulated detections and ground-truth surface
tracks, the stage's inputs, and running the spline, stitch and cut stages on them."""

from __future__ import annotations

import functools

import numpy as np

from eventcap.artifacts import BatchPlan
from eventcap.artifacts.tracking import SlicedTracks
from eventcap.core.stage import StageContext
from eventcap.energy.detections import select_detections
from eventcap.energy.factor import Layout
from eventcap.energy.spline import UniformCubicBSpline
from eventcap.energy.terms import sample_times
from eventcap.energy.window import Tracks, WindowInputs
from eventcap.params import nest
from eventcap.sim.capture import _pick_track_points, _track_points
from eventcap_spline.solve import SplineSolver, solve_window
from eventcap_spline.spec import SplineSolveConfig
from .poses import detect, posed_recording
from .refine_scene import boundary_events

H_US = 10_000  # knot spacing of the test splines


EXACT = dict(sigma_px=0.0, sigma_m=0.0, bias_m=0.0, outlier_prob=0.0, flip_prob=0.0, blur_gain=0.0)


@functools.lru_cache(maxsize=3)
def scene(exact: bool = False, n_frames: int = 4):
    """4 intensity frames (3 batches, 120 ms; or n_frames) of a fast motion, simulated detections (default noise
    unless exact), ground-truth surface tracks in the second batch."""
    rec = posed_recording("high_knees", n_frames=n_frames, speed=1.0, with_template=True)
    det = select_detections(detect("simulated", rec, **(EXACT if exact else {})), rec.frames.t_us)
    t_det = rec.frames.t_us.astype(np.int64)
    t_us = t_det[1] + 1_000 * np.arange(41, dtype=np.int64)
    gt = rec.ground_truth
    S = gt.poses[np.searchsorted(gt.t_us, t_us)]
    tri, bary = _pick_track_points(rec.template, rec.camera, lambda t: S[np.searchsorted(t_us, np.rint(t * 1e6))],
                                   t_us[[0, 20, 40]], 100, seed=0)
    xy, valid = _track_points(rec.template, rec.camera, S, tri, bary)
    return rec, det, t_det, t_us, S, xy, valid


T_SIL = slice(None, None, 5)  # E_sil at every 5th tracking frame of the scene: 9 frames


@functools.lru_cache(maxsize=1)
def silhouette_events() -> np.ndarray:
    """One event on every pixel of the true silhouette's boundary every millisecond of the scene (its 3 batches)."""
    rec, _, t_det = scene()[:3]
    gt = rec.ground_truth
    t = np.arange(t_det[0], t_det[-1] + 1, 1000)
    return boundary_events(rec.template, rec.camera, gt.poses[np.searchsorted(gt.t_us, t)], t)


class BatchSeq(list):
    """Stands in for the runner's lazy BatchSequence (a list with .batches)."""

    def __init__(self, items, batches):
        super().__init__(items)
        self.batches = batches


@functools.lru_cache(maxsize=2)
def stage_data(n_frames: int = 4):
    rec, det_rows, t_det = scene(n_frames=n_frames)[:3]
    det = detect("simulated", rec)
    gt = rec.ground_truth
    plan = BatchPlan.between_frames(t_det)
    sliced = []
    for k in range(len(plan)):  # exact surface tracks of every batch, each batch its own points
        t_us = t_det[k] + 1_000 * np.arange(41, dtype=np.int64)
        S = gt.poses[np.searchsorted(gt.t_us, t_us)]
        tri, bary = _pick_track_points(rec.template, rec.camera,
                                       lambda t, S=S, t_us=t_us: S[np.searchsorted(t_us, np.rint(t * 1e6))],
                                       t_us[[0, 20, 40]], 60, seed=1 + k)
        xy, valid = _track_points(rec.template, rec.camera, S, tri, bary)
        sliced.append(SlicedTracks(t_us=t_us, xy=np.where(valid[..., None], xy, np.nan).astype(np.float32),
                                   valid=valid, track_id=np.arange(xy.shape[1], dtype=np.int32)))
    return rec, det, plan, BatchSeq(sliced, plan.batches())


def stage_inputs(n_frames: int = 4):
    """The stage's inputs on the scene: 3 batches of 40 ms (or n_frames - 1), every batch's tracks (as the runner
    hands them)."""
    rec, det, plan, sliced = stage_data(n_frames)
    return {"recording": rec, "sliced": sliced, "detections": det, "batches": plan}


FAST = {"icp_rounds": 1, "half_window": 1, "knot_ms": 20.0, "tracks.step": 4}  # dotted keys (nest)


def run_stage(inputs, batch, **changes):
    """The spline stage on the stage inputs at a batch, with FAST and these changes (dotted keys:
    run_stage(inputs, b, **{"terms.sil.gain": 0.0}))."""
    from eventcap.core.config import build_config
    from eventcap.core.registry import load_registry

    spec = load_registry().get("spline")
    ctx = StageContext(node="solve", stage="spline", batch=batch)
    return spec.load_run()(inputs, build_config(spec, nest(FAST, changes), "stages.solve"), ctx), ctx


def stitch(poses, plan, **changes):
    from eventcap.core.config import build_config
    from eventcap.core.registry import load_registry

    reg = load_registry()
    spec = reg.get("stitch")
    ctx = StageContext(node="stitch", stage="stitch")
    motion = spec.load_run()({"windows": BatchSeq(poses, plan.batches()[:len(poses)])},
                             build_config(spec, changes, "stages.stitch"), ctx)["motion"]
    cut = reg.get("cut")
    return motion, [cut.load_run()({"motion": motion, "batches": plan}, build_config(cut, {}, "stages.cut"),
                                   StageContext(node="cut", stage="cut", batch=plan.batch(k)))["poses"]
                    for k in range(len(poses))], ctx


def spline_config(changes: dict | None = None) -> SplineSolveConfig:
    """The stage's config with the dotted-key changes (checked as `eventcap run` checks them)."""
    from eventcap.core.config import build_config
    from eventcap.core.registry import load_registry

    return build_config(load_registry().get("spline"), nest(dict(changes or {})), "stages.solve")


def solver(**config) -> SplineSolver:
    """The spline solver of the scene's window (3 batches, E_cor at the middle batch's 41 tracking frames, E_sil at 9
    of them) with the stage's config (defaults but for the changes given, by dotted key: solver(**{"terms.sil.gain":
    0}))."""
    return _solver(tuple(sorted(config.items())))


@functools.lru_cache(maxsize=8)
def _solver(config: tuple) -> SplineSolver:
    rec, det, t_det, t_us = scene()[:4]
    n_seg = int((t_det[-1] - t_det[0]) // H_US)
    cfg = spline_config({"knot_ms": H_US / 1000, **dict(config)})
    spl = UniformCubicBSpline(int(t_det[0]), H_US, n_seg)
    times = sample_times(cfg.terms, scene_inputs(spl, None, None))
    from eventcap.energy.problem import SplinePoses, coupling_band

    band = coupling_band(SplinePoses(n_seg, spl), t_us)
    layout = Layout(n_seg=n_seg, sizes=tuple((k, t.size) for k, t in times.items()), band=band)
    return SplineSolver(rec.template, rec.camera, layout, cfg)


def scene_inputs(spl, xy, valid, events=None) -> WindowInputs:
    """The scene's window as the solve's inputs: its detections, the middle batch's tracks (xy, valid; None: the
    scene's own shapes without any track), the events (None: none)."""
    rec, det, t_det, t_us = scene()[:4]
    if xy is None:
        xy, valid = np.zeros((t_us.size, 0, 2)), np.zeros((t_us.size, 0), dtype=bool)
    return WindowInputs(spl.t0_us, spl.t1_us, knots_us=spl.t0_us + spl.h_us * np.arange(spl.n_seg + 1),
                        t_det_us=t_det, detections=det, tracks=Tracks(t_us, xy, valid), track_times_us=(t_us,),
                        events=events)


def window(sol: SplineSolver, spl, det, xy, valid, events=None, **kw):
    """solve_window on the scene's window with these detections, tracks and events."""
    inputs = scene_inputs(spl, xy, valid, events)
    inputs.detections = det
    return solve_window(sol, spl, inputs, **kw)
