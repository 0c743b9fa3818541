"""Images from events alone (eventcap.imaging.reconstruct), the `reconstruct` stage, rate-based batch plans and the
event-only sources: exactness of the filter, accuracy against a known scene, the stage's outputs, clear errors."""

from __future__ import annotations

import functools

import numpy as np
import pytest

from eventcap.artifacts import BatchPlan
from eventcap.artifacts.recording import EventStream, FrameStack, GroundTruth, Recording
from eventcap.camera import Camera
from eventcap.events import make_events
from eventcap.imaging.reconstruct import agreement, high_pass, median_baseline, reconstruct, to_intensity, to_log_images
from eventcap.sim.events import SensorConfig, simulate_all
from eventcap.core.testing import StageConformance

H, W = 24, 32


def random_events(n=3000, seed=0, t_max=200_000):
    rng = np.random.default_rng(seed)
    return make_events(np.sort(rng.integers(0, t_max, n)), rng.integers(0, W, n), rng.integers(0, H, n),
                       rng.choice([-1, 1], n))


def test_high_pass_equals_the_event_by_event_filter():
    """The closed form (one histogram per sample interval) against the per-event recursion of Scheerlinck et al.:
    decay the pixel's state to the event's time, add p * C."""
    ev = random_events()
    times = np.array([10_000, 50_000, 50_000, 120_000, 199_999, 250_000])
    cutoff, C = 20.0, 0.17
    got = high_pass(ev, H, W, times, cutoff_rad_s=cutoff, contrast=C)
    state = np.zeros((H, W))
    last = np.zeros((H, W))
    want = []
    i = 0
    for T in times:
        while i < ev.size and ev["t"][i] <= T:
            y, x = ev["y"][i], ev["x"][i]
            state[y, x] = state[y, x] * np.exp(-cutoff * 1e-6 * (ev["t"][i] - last[y, x])) + C * ev["p"][i]
            last[y, x] = ev["t"][i]
            i += 1
        want.append(state * np.exp(-cutoff * 1e-6 * (T - last)))
    assert got.shape == (6, H, W) and got.dtype == np.float32
    np.testing.assert_allclose(got, np.array(want), atol=1e-5)
    assert np.abs(got).max() > 0.3  # the check is not vacuous


def test_cutoff_zero_is_direct_integration():
    ev = random_events(seed=1)
    got = high_pass(ev, H, W, [100_000, 300_000], cutoff_rad_s=0.0, contrast=0.2)
    sel = ev[ev["t"] <= 100_000]
    acc = np.zeros((H, W))
    np.add.at(acc, (sel["y"].astype(int), sel["x"].astype(int)), sel["p"])
    np.testing.assert_allclose(got[0], 0.2 * acc, atol=1e-6)
    acc_all = np.zeros((H, W))
    np.add.at(acc_all, (ev["y"].astype(int), ev["x"].astype(int)), ev["p"])
    np.testing.assert_allclose(got[1], 0.2 * acc_all, atol=1e-6)


@functools.lru_cache(maxsize=1)
def moving_square():
    """Events of a bright square sliding across a dark-grey wall with a vertical stripe (the project's DVS
    simulator), and a render function for the true image at any time."""
    yy, xx = np.mgrid[0:H, 0:W]

    def render(t_us):
        img = np.full((H, W), 0.2, np.float32)
        img[:, 26:28] = 0.5  # a static stripe: no events, unrecoverable
        x0 = 2.0 + 16.0 * t_us / 200_000  # 80 px/s
        img[(xx >= x0) & (xx < x0 + 6) & (yy >= 8) & (yy < 16)] = 0.8
        return img

    ev = simulate_all(render, 0, 200_000, SensorConfig(threshold_sigma=0.0, noise_rate_hz=0.0, refractory_us=0, seed=0))
    return ev, render


def test_reconstruction_matches_the_true_image_where_it_moved():
    ev, render = moving_square()
    times = np.array([100_000, 150_000, 190_000])
    truth = [np.log(render(int(t)) + 1e-3) for t in times]
    region = np.zeros((H, W), bool)
    region[4:20, :24] = True  # where the square is or was (the stripe never changes)
    plain = high_pass(ev, H, W, times, cutoff_rad_s=3.0)
    median = reconstruct(ev, H, W, times, cutoff_rad_s=3.0, baseline="median")
    r_plain = [agreement(plain[k], truth[k], region).correlation for k in range(3)]
    r_median = [agreement(median[k], truth[k], region).correlation for k in range(3)]
    # The square's own pixels are reconstructed; the wall it uncovered keeps a trace (events: -1.4 log units)
    # that the median baseline removes.
    assert min(r_median) > 0.93
    assert min(r_median) > max(r_plain) + 0.05
    # Without decay (direct integration) the square reads log(0.8 / 0.2) = 1.39 above the wall, within one threshold
    k = 2
    x0 = int(np.ceil(2.0 + 16.0 * times[k] / 200_000))
    integrated = reconstruct(ev, H, W, times, cutoff_rad_s=0.0, baseline="median")
    inside = integrated[k, 10:14, x0 + 1:x0 + 5].mean()
    assert abs(inside - np.log(0.801 / 0.201)) < 0.2
    # the whole image, static stripe included: worse (the stripe is not in the events)
    assert agreement(median[k], truth[k]).correlation < r_median[k] - 0.05


def test_median_baseline_is_the_per_pixel_median():
    ev, _ = moving_square()
    base = median_baseline(ev, H, W, cutoff_rad_s=3.0, samples=5, step_us=1000)
    times = np.unique(np.round(np.linspace(ev["t"][0], ev["t"][-1], 5)).astype(np.int64))
    np.testing.assert_allclose(base, np.median(high_pass(ev, H, W, times, 3.0), axis=0), atol=1e-6)


def test_log_and_intensity_conversions():
    rel = np.array([[[0.0, 1.0, -10.0]]], np.float32)
    logs = to_log_images(rel, eps=1e-3, base_intensity=0.5)
    assert logs[0, 0, 0] == pytest.approx(np.log(0.501))
    np.testing.assert_allclose(to_intensity(logs, 1e-3)[0, 0], [0.5, 1.0, 0.0],
                               atol=1e-6)


@pytest.mark.parametrize("kwargs, message", [
    ({"times_us": [20, 10]}, "expected sorted times; time 1 (10 us)"),
    ({"cutoff_rad_s": -1.0}, "cutoff_rad_s: expected a decay rate >= 0"),
    ({"contrast": 0.0}, "contrast: expected a log-intensity step > 0"),
])
def test_bad_arguments_are_named(kwargs, message):
    args = {"times_us": [10, 20], **kwargs}
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        high_pass(random_events(10), H, W, **args)


def test_bad_baseline_and_events_outside_the_sensor():
    with pytest.raises(ValueError, match="baseline: expected none | median"):
        reconstruct(random_events(10), H, W, [10], baseline="mean")
    with pytest.raises(ValueError, match="outside the 8 x 24 sensor"):
        high_pass(random_events(50), 24, 8, [10])


def test_agreement_is_invariant_to_scale_and_offset():
    rng = np.random.default_rng(0)
    truth = rng.normal(size=(20, 30))
    a = agreement(3.0 * truth - 1.0, truth)
    assert a.correlation == pytest.approx(1.0) and a.rmse < 1e-9 and a.gradient_correlation == pytest.approx(1.0)
    b = agreement(truth + rng.normal(size=truth.shape), truth)
    assert 0.6 < b.correlation < 0.8 and b.n_pixels == 600
    with pytest.raises(ValueError, match="mask holds 0 pixels"):
        agreement(truth, truth, np.zeros(truth.shape, bool))


# ----------------------------------------------------------------------------------------------- batch plan at rate
def test_batch_plan_at_rate():
    plan = BatchPlan.at_rate(1_000, 101_000, 25.0)
    assert list(plan.t0_us) == [1_000, 41_000] and list(plan.t1_us) == [41_000, 81_000]
    assert list(plan.frame0) == [0, 1]
    assert len(BatchPlan.at_rate(0, 30_000, 25.0)) == 0
    odd = BatchPlan.at_rate(0, 1_000_000, 30.0)  # 33,333.3 us: rounded per boundary, no drift
    assert len(odd) == 30 and odd.t1_us[-1] == 1_000_000
    with pytest.raises(ValueError, match="expected a rate > 0 Hz"):
        BatchPlan.at_rate(0, 10, 0.0)


# ------------------------------------------------------------------------------------------------------ the stage
def small_recording(with_frames: bool) -> Recording:
    ev, render = moving_square()
    cam = Camera(width=W, height=H, fx=30.0, fy=30.0, cx=W / 2, cy=H / 2)
    frames = None
    if with_frames:
        t = np.array([50_000, 100_000, 150_000])
        frames = FrameStack(images=np.stack([render(int(x)) for x in t]), t_us=t,
                            exposure_us=np.full(3, 10_000, np.int64), height=H, width=W)
    gt_t = np.array([50_000, 100_000, 150_000])
    joints = np.tile(np.c_[np.linspace(-0.3, 0.3, 24), np.zeros(24), np.full(24, 2.0)], (3, 1, 1))  # 2 m away
    gt = GroundTruth(t_us=gt_t, poses=np.zeros((3, 33)), joints=joints, landmarks=joints[:, :25 - 1].repeat(2, 1)[:, :25],
                     frame_poses=np.zeros((3, 33)), frame_joints=joints, height=H, width=W,
                     sharp_images=np.stack([render(int(x)) for x in gt_t]))
    return Recording(events=EventStream(events=ev, width=W, height=H), camera=cam, frames=frames, ground_truth=gt,
                     name="square")


class TestReconstructStage(StageConformance):
    stage_name = "reconstruct"
    sensitive = ("cutoff_rad_s", 10.0)
    insensitive = None

    def make_inputs(self):
        return {"recording": small_recording(False), "batches": BatchPlan.at_rate(20_000, 200_000, 25.0)}

    def test_images_at_every_batch_boundary(self):
        out = self.run_once()
        lat, rec = out["latent"], out["recording"]
        want_t = [20_000, 60_000, 100_000, 140_000, 180_000]
        assert list(lat.t_us) == want_t and lat.log_images.shape == (5, H, W) and lat.contrast == 0.2
        assert rec.frames is not None and list(rec.frames.t_us) == want_t
        assert rec.frames.images.min() >= 0 and rec.frames.images.max() <= 1
        assert set(rec.frames.exposure_us) == {0}  # declared sharp (config exposure_us)
        assert rec.events.events.size == small_recording(False).events.events.size  # the events stay
        np.testing.assert_allclose(rec.frames.images, to_intensity(lat.log_images, lat.eps), atol=1e-6)

    def test_replacing_frames_keeps_the_truths_frame_times(self):
        inputs = {"recording": small_recording(True), "batches": BatchPlan.between_frames(np.array([50_000, 100_000,
                                                                                                    150_000]))}
        from eventcap.core.stage import StageContext

        out = self.spec().load_run()(inputs, self.config(exposure_us=10_000), StageContext(node="r", stage="reconstruct"))
        rec = out["recording"]
        assert list(rec.ground_truth.frame_t_us) == [50_000, 100_000, 150_000]
        assert set(rec.frames.exposure_us) == {10_000} and rec.frames.images.shape == (3, H, W)
        # not the recorded frames: images from the events (the static stripe is mid-grey)
        assert abs(float(rec.frames.images[1][:, 26:28].mean()) - 0.5) < 0.05

    def test_empty_plan_fails_clearly(self):
        from eventcap.core.stage import StageContext, StageFailed

        inputs = {"recording": small_recording(False), "batches": BatchPlan.at_rate(0, 1000, 25.0)}
        with pytest.raises(StageFailed, match="the batch plan is empty"):
            self.spec().load_run()(inputs, self.config(), StageContext(node="r", stage="reconstruct"))


# ---------------------------------------------------------------------------------------------------------- preview
def test_preview_shows_event_only_recordings(tmp_path):
    """`eventcap preview` on a recording without frames: reconstruction | true sharp image | events | skeleton."""
    import dataclasses
    import subprocess
    import sys

    import cv2
    import zarr

    rec = small_recording(False)
    gt = dataclasses.replace(rec.ground_truth, frame_t_us=np.array([50_000, 100_000, 150_000]))
    rec = dataclasses.replace(rec, ground_truth=gt)
    path = tmp_path / "eo.zarr"
    rec.to_zarr(zarr.open_group(str(path), mode="w"))
    out = tmp_path / "p.png"
    p = subprocess.run([sys.executable, "-m", "eventcap.apps.cli", "preview", str(path), "--frame", "2", "--scale", "2",
                        "--out", str(out)], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    img = cv2.imread(str(out))
    assert img.shape == (2 * H, 4 * 2 * W, 3)  # four panels
    recon = img[:, :2 * W].astype(int)
    # the square (t = 150 ms: x0 = 14) is bright in the reconstruction, the wall it left mid-grey
    assert recon[2 * 12, 2 * 17].mean() > recon[2 * 12, 2 * 4].mean() + 60
    # the same recording with frames: no reconstruction unless asked (--reconstruct adds it)
    rec_f = small_recording(True)
    path_f = tmp_path / "f.zarr"
    rec_f.to_zarr(zarr.open_group(str(path_f), mode="w"))
    for extra, panels in (([], 4), (["--reconstruct"], 5)):
        q = subprocess.run([sys.executable, "-m", "eventcap.apps.cli", "preview", str(path_f), "--out", str(out), *extra],
                           capture_output=True, text=True, timeout=120)
        assert q.returncode == 0, q.stderr
        assert cv2.imread(str(out)).shape[1] == panels * 2 * W


# ------------------------------------------------------------------------------------------------------- pipeline
@pytest.mark.parametrize("track", ["eklt", "klt_latent", "oracle"])
def test_events_only_pipeline_builds_and_no_image_stage_reads_the_source_frames(track):
    from pathlib import Path

    from eventcap.apps.benchmark import compose_run
    from eventcap.core.pipeline import build_pipeline
    from eventcap.core.registry import load_registry

    root = Path(__file__).resolve().parents[1]
    cfg, _ = compose_run(root / "conf", ["pipeline=events_only", f"stages/track={track}"])
    nodes = {n.name: n for n in build_pipeline(cfg, load_registry())}
    assert nodes["reconstruct"].spec.name == "reconstruct" and nodes["track"].spec.name == track
    assert str(nodes["detect"].inputs["recording"]) == "reconstruct.recording"
    assert str(nodes["track"].inputs["latent"]) == "reconstruct.latent"
    assert "sharpen" not in nodes  # no EDI: it needs frames
    # the default pipeline is untouched by the reconstruct stage's config group
    cfg_d, _ = compose_run(root / "conf", [])
    assert "reconstruct" not in cfg_d["pipeline"]["nodes"] and cfg_d["stages"]["sharpen"]["stage"] == "edi"


def test_recording_source_cuts_event_only_files_at_the_batch_rate(tmp_path):
    from eventcap.io import write_events
    from eventcap.core.stage import StageContext

    spec = load_registry_spec("recording")
    rng = np.random.default_rng(0)
    n = 4000
    ev = make_events(np.sort(rng.integers(10_000, 230_000, n)), rng.integers(0, 64, n), rng.integers(0, 48, n),
                     rng.choice([-1, 1], n))
    path = write_events(tmp_path / "eo.npz", ev, width=64, height=48)
    from eventcap.core.config import build_config

    run = spec.load_run()
    out = run({}, build_config(spec, {"path": str(path), "batch_rate_hz": 20.0}, "source"),
              StageContext(node="source", stage="recording"))
    plan, rec = out["batches"], out["recording"]
    assert rec.frames is None
    t0 = int(rec.events.events["t"][0])
    assert list(plan.t0_us - t0) == [0, 50_000, 100_000, 150_000] and list(plan.t1_us - plan.t0_us) == [50_000] * 4
    with pytest.raises(ValueError, match=r"source.batch_rate_hz: expected a finite number > 0, got 0"):
        run({}, build_config(spec, {"path": str(path), "batch_rate_hz": 0.0}, "source"),
            StageContext(node="source", stage="recording"))


def load_registry_spec(name):
    from eventcap.core.registry import load_registry

    return load_registry().get(name)


def test_synthetic_source_without_frames_keeps_events_truth_and_batches():
    from eventcap.body.procedural import procedural_template
    from eventcap.core.config import build_config
    from eventcap.core.stage import StageContext

    spec = load_registry_spec("synthetic")
    tpl = procedural_template(target_faces=3000)
    base = {"duration_s": 0.09, "supersample": 1, "n_track_points": 10, "motion": "jumping_jack", "speed": 2.0}
    outs = [spec.load_run()({"template": tpl}, build_config(spec, {**base, "frames": f}, "source"),
                            StageContext(node="source", stage="synthetic")) for f in (True, False)]
    (rec_f, plan_f), (rec_e, plan_e) = [(o["recording"], o["batches"]) for o in outs]
    assert rec_f.frames is not None and rec_e.frames is None
    assert np.array_equal(rec_f.events.events, rec_e.events.events) and rec_e.events.events.size > 1000
    assert np.array_equal(plan_f.t0_us, plan_e.t0_us) and np.array_equal(plan_f.t1_us, plan_e.t1_us)
    assert rec_f.ground_truth.frame_t_us is None  # with frames the recording stays as it was
    assert np.array_equal(rec_e.ground_truth.frame_t_us, rec_f.frames.t_us)
    assert np.array_equal(rec_e.ground_truth.sharp_images, rec_f.ground_truth.sharp_images)
    # the simulated detector finds its truth at the reconstructed images' times
    from eventcap_detect.simulated import frame_truth

    rspec = load_registry_spec("reconstruct")
    rec_r = rspec.load_run()({"recording": rec_e, "batches": plan_e}, build_config(rspec, {}, "stages.reconstruct"),
                             StageContext(node="reconstruct", stage="reconstruct"))["recording"]
    truth = frame_truth(rec_r, occlusion=False)
    assert np.array_equal(truth.t_us, rec_f.frames.t_us)
    np.testing.assert_array_equal(truth.joints_rel_m,
                                  rec_f.ground_truth.frame_joints - rec_f.ground_truth.frame_joints[:, :1])
    assert truth.streak_px.max() == 0.0  # declared sharp (exposure 0)
