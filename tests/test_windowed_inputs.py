"""Windowed reads (issue 55, item 3): a per-batch task reads only its time range of the recording and the latent
images from the cache (``Port.window``), with the margins its stage declares, and the runner's memo drops the
capture-long artifacts a task does not read whole."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

import eventcap.artifact as artifact_mod
from eventcap.artifacts import Batch, BatchPlan, EventStream, FrameStack, GroundTruth, LatentFrames, Recording
from eventcap.camera import Camera
from eventcap.core import runner as runner_mod
from eventcap.core.cache import Cache
from eventcap.core.stage import Port, StageSpecError
from eventcap.events import EVENT_DTYPE

W, H = 16, 12


@dataclass
class Cfg:
    """A stage config without settings."""


@pytest.fixture(scope="module")
def stored(tmp_path_factory):
    """A recording and its cache entry, written once in chunks of 4 KiB (a read accepts them, smaller than its
    own)."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(artifact_mod, "_CHUNK_BYTES", 4096)
        rec = recording()
        cache, entry = committed(tmp_path_factory.mktemp("windowed"), recording=rec)
    return rec, cache, entry


def recording(n_events: int = 20_000, n_frames: int = 26, seed: int = 0) -> Recording:
    """1 s of events (runs of equal timestamps included) and 25 fps frames with ground truth at the frames and
    at 200 Hz."""
    rng = np.random.default_rng(seed)
    ev = np.zeros(n_events, EVENT_DTYPE)
    ev["t"] = np.sort(rng.integers(0, 1_000_000, n_events) // 7 * 7)  # many equal times
    ev["x"], ev["y"] = rng.integers(0, W, n_events), rng.integers(0, H, n_events)
    ev["p"] = rng.choice([-1, 1], n_events)
    cam = Camera(width=W, height=H, fx=20.0, fy=20.0, cx=W / 2, cy=H / 2)
    t_f = np.arange(n_frames, dtype=np.int64) * 40_000
    frames = FrameStack(images=rng.random((n_frames, H, W)).astype(np.float32), t_us=t_f,
                        exposure_us=np.full(n_frames, 5000, np.int64), height=H, width=W)
    t_gt = np.arange(0, 1_000_001, 5000, dtype=np.int64)
    gt = GroundTruth(t_us=t_gt, poses=rng.random((t_gt.size, 33)), joints=rng.random((t_gt.size, 24, 3)),
                     landmarks=rng.random((t_gt.size, 5, 3)), frame_poses=rng.random((n_frames, 33)),
                     frame_joints=rng.random((n_frames, 24, 3)), height=H, width=W,
                     sharp_images=rng.random((n_frames, H, W)).astype(np.float32))
    return Recording(events=EventStream(events=ev, width=W, height=H), camera=cam, frames=frames, ground_truth=gt,
                     name="windowed")


def committed(tmp_path, **outputs):
    cache = Cache(tmp_path / "cache")
    cache.commit("test", "k" * 64, {"stage": "test"}, outputs)
    return cache, cache.lookup("test", "k" * 64)


@pytest.mark.parametrize("window", [(0, 1_000_000), (123_456, 345_678), (40_000, 80_000), (999_999, 2_000_000),
                                    (-50, -1), (2_000_000, 3_000_000), (7 * 1000, 7 * 1000)])
def test_a_window_holds_exactly_the_rows_of_its_time_range(stored, window):
    rec, cache, entry = stored
    artifact_mod._CHUNK_STARTS.clear()
    assert cache.load(entry, "recording", Recording).events.events.shape == (20_000,)
    part = cache.load(entry, "recording", Recording, window)
    t0, t1 = window
    ev = rec.events.events
    want = ev[(ev["t"] >= t0) & (ev["t"] <= t1)]  # both ends included
    assert part.events.events.dtype == EVENT_DTYPE and part.events.events.shape == want.shape
    assert np.array_equal(part.events.events, want)
    f = (rec.frames.t_us >= t0) & (rec.frames.t_us <= t1)
    assert np.array_equal(part.frames.t_us, rec.frames.t_us[f])
    assert part.frames.images.shape == (int(f.sum()), H, W) and np.array_equal(part.frames.images, rec.frames.images[f])
    gt = rec.ground_truth
    g = (gt.t_us >= t0) & (gt.t_us <= t1)
    assert np.array_equal(part.ground_truth.t_us, gt.t_us[g])
    assert part.ground_truth.track_px is None and part.ground_truth.joints.shape == (int(g.sum()), 24, 3)
    # the ground truth's frames have no times of their own: they follow the frames kept
    assert np.array_equal(part.ground_truth.frame_poses, gt.frame_poses[f])
    assert np.array_equal(part.ground_truth.sharp_images, gt.sharp_images[f])
    assert part.camera.to_dict() == rec.camera.to_dict() and part.name == rec.name


def test_a_window_reads_the_chunks_at_its_ends_not_the_whole_time_column(stored, monkeypatch):
    rec, cache, entry = stored
    cache.load(entry, "recording", Recording, (0, 10))  # the chunks' first values, once per process
    reads = []
    real = artifact_mod.read_array
    monkeypatch.setattr(artifact_mod, "read_array", lambda arr, where, rows=None: reads.append((where, rows))
                        or real(arr, where, rows))
    part = cache.load(entry, "recording", Recording, (500_000, 520_000))
    t_reads = [rows for where, rows in reads if where.endswith("events/t")]
    chunk = 4096 // 8
    assert all(r is not None for r in t_reads)
    assert sum(r.stop - r.start for r in t_reads) <= 3 * chunk  # the two ends' chunks and the rows kept
    assert len(part.events.events) < 0.05 * len(rec.events.events)


def test_latent_frames_are_windowed_by_their_times(tmp_path):
    t = np.arange(10, dtype=np.int64) * 40_000
    lat = LatentFrames(log_images=np.arange(10 * H * W, dtype=np.float32).reshape(10, H, W), t_us=t, contrast=0.2,
                       eps=1e-3, height=H, width=W)
    cache, entry = committed(tmp_path, latent=lat)
    part = cache.load(entry, "latent", LatentFrames, (80_000, 160_000))
    assert np.array_equal(part.t_us, [80_000, 120_000, 160_000])
    assert np.array_equal(part.log_images, lat.log_images[2:5]) and part.contrast == 0.2


def plan(n: int = 10) -> BatchPlan:
    return BatchPlan.between_frames(np.arange(n + 1, dtype=np.int64) * 40_000)


def test_a_units_window_has_its_margins_in_batches_clipped_at_the_ends():
    p = plan(10)
    chunk = Batch(0, 120_000, 240_000, 3)  # batches 3..5
    assert runner_mod.unit_window(p, chunk, 0) == (120_000, 240_000)
    assert runner_mod.unit_window(p, chunk, 2) == (40_000, 320_000)  # batches 1..7
    assert runner_mod.unit_window(p, chunk, 5) == (0, 400_000)  # clipped to the plan
    assert runner_mod.unit_window(p, Batch(9, 360_000, 400_000, 9), 1) == (320_000, 400_000)
    assert runner_mod.unit_window(p, Batch(0, 500_000, 600_000, 0), 3) == (500_000, 600_000)  # beyond the plan


@pytest.mark.parametrize("n, half, chunk", [(25, 2, 5), (25, 3, 7), (7, 2, 3), (12, 1, 12), (30, 4, 1)])
def test_the_spline_solves_windows_lie_inside_what_its_chunks_read(n, half, chunk):
    """The solve's window of batches a..z (shifted inwards at the ends of the recording) and its events lie inside
    the range the runner reads for the chunk (the spline's recording port: 2·half_window batches on each side)."""
    from eventcap_spline._impl import unit_role
    from eventcap_spline.spec import SPLINE, SplineSolveConfig

    p = plan(n)
    margin = SPLINE.inputs["recording"].margin(SplineSolveConfig(half_window=half))
    assert margin == 2 * half
    for ka in range(0, n, chunk):
        kz = min(ka + chunk, n) - 1
        unit = Batch(ka // chunk, int(p.t0_us[ka]), int(p.t1_us[kz]), ka)
        _, (a, z, _, _) = unit_role(p, unit, half, 1)
        t0, t1 = runner_mod.unit_window(p, unit, margin)
        assert t0 <= p.t0_us[a] and p.t1_us[z] <= t1, (ka, kz, a, z)


def test_a_window_on_a_port_that_cannot_have_one_is_refused():
    from eventcap.core.stage import StageSpec

    ok = StageSpec("w", "test", 1, "", Cfg, {"recording": Port(Recording, window=1)}, {"plan": Port(BatchPlan)},
                   "m:f", per_batch=True)
    assert ok.inputs["recording"].margin(Cfg()) == 1
    with pytest.raises(StageSpecError, match=r"input .plan.: window applies .* \(BatchPlan has none\)"):
        StageSpec("w", "test", 1, "", Cfg, {"plan": Port(BatchPlan, window=1)}, {"out": Port(BatchPlan)}, "m:f",
                  per_batch=True)
    with pytest.raises(StageSpecError, match="input 'recording': window applies"):
        StageSpec("w", "test", 1, "", Cfg, {"recording": Port(Recording, window=1)}, {"out": Port(BatchPlan)}, "m:f")
    with pytest.raises(StageSpecError, match="expected a number of batches >= 0, got -1"):
        Port(Recording, window=lambda c: -1).margin(Cfg())


def test_a_task_drops_the_capture_long_artifacts_it_does_not_read_whole():
    rec, p = recording(n_events=100), plan(3)
    memo = runner_mod._ARTIFACTS
    memo.clear()
    try:
        memo.put(("root", "source", "a", "recording"), rec)
        memo.put(("root", "body", "b", "recording"), rec)
        memo.put(("root", "source", "a", "batches"), p)
        assert runner_mod._drop_capture_artifacts({("root", "body", "b", "recording")}) == 1
        assert ("root", "source", "a", "recording") not in memo
        assert ("root", "body", "b", "recording") in memo and ("root", "source", "a", "batches") in memo
        assert runner_mod._drop_capture_artifacts(set()) == 1 and len(memo) == 1  # the plan grows with nothing
    finally:
        memo.clear()


def test_a_windowed_input_leaves_out_the_optional_fields_its_stage_never_reads(stored):
    rec, cache, entry = stored
    part = cache.load(entry, "recording", Recording, (200_000, 300_000), ("frames", "ground_truth"))
    assert part.frames is None and part.ground_truth is None
    ev = rec.events.events
    assert np.array_equal(part.events.events, ev[(ev["t"] >= 200_000) & (ev["t"] <= 300_000)])
    with pytest.raises(ValueError, match="applies to a windowed read only"):
        cache.load(entry, "recording", Recording, None, ("ground_truth",))
    from eventcap.core.stage import StageSpec

    with pytest.raises(StageSpecError, match=r"without=\('events',\) applies to a windowed input and names optional "
                                             r"fields of Recording \(frames, ground_truth, template\)"):
        StageSpec("w", "test", 1, "", Cfg, {"recording": Port(Recording, window=0, without=("events",))},
                  {"out": Port(BatchPlan)}, "m:f", per_batch=True)
    with pytest.raises(StageSpecError, match="applies to a windowed input"):
        StageSpec("w", "test", 1, "", Cfg, {"recording": Port(Recording, without=("frames",))},
                  {"out": Port(BatchPlan)}, "m:f", per_batch=True)


def test_the_track_and_spline_stages_read_their_unit_of_the_recording_without_its_ground_truth():
    from eventcap_spline.spec import SPLINE
    from eventcap_track.spec import EKLT, KLT_LATENT, ORACLE

    for spec in (EKLT, KLT_LATENT):
        assert spec.inputs["recording"].window == 0 and spec.inputs["latent"].window == 0
        assert set(spec.inputs["recording"].without) == {"frames", "ground_truth"}
    assert SPLINE.inputs["recording"].without == ("frames", "ground_truth")
    assert ORACLE.inputs["recording"].window is None  # the oracle reads the ground truth's tracks


def test_a_stage_packages_memos_are_emptied_once_its_last_node_has_run(toy_cfg):
    """The toy pipeline's stages all run from module toy_stages: its memos (``toy_stages.*``) live through the run
    and are emptied after its last node; another package's are kept."""
    from eventcap.core.runner import Runner
    from eventcap.memo import ProcessCache

    mine, other = ProcessCache("toy_stages.solvers", maxsize=2), ProcessCache("toy_stages_other.solvers", maxsize=2)
    mine.put("built", 1)
    other.put("built", 2)
    runner = Runner(toy_cfg())
    seen = []
    real = runner._release_memos
    runner._release_memos = lambda done: (seen.append(("built" in mine, done)), real(done))
    assert runner.run().ok
    assert seen[:-1] == [(True, d) for d in range(1, len(runner.nodes))] and seen[-1] == (True, len(runner.nodes))
    assert "built" not in mine and "built" in other
