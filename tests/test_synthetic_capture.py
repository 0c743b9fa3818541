"""The synthetic event-camera capture: noise-only static scenes, event rates growing with speed, blur, ground truth.

Captures here render one sample per pixel (supersample=1) to keep the suite fast; the default is 3.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest

from eventcap.body.kinematics import skin
from eventcap.body.procedural import procedural_template
from eventcap.camera import davis240c_default
from eventcap.imaging.render import textured_background
from eventcap.sim.capture import CaptureConfig, simulate_synthetic
from eventcap.sim.events import SensorConfig
from eventcap.sim.frames import FrameConfig

H, W = 180, 240


@functools.lru_cache(maxsize=1)
def scene():
    tpl = procedural_template(seed=0)
    cam = davis240c_default(eye=(0.0, 1.0, 3.0), target=(0.0, 1.0, 0.0))
    return tpl, cam, textured_background(H, W, seed=0)


@functools.lru_cache(maxsize=8)
def capture(motion: str, duration_s: float = 0.1, speed: float = 1.0, noise_hz: float = 0.2, seed: int = 0,
            supersample: int = 1):
    tpl, cam, bg = scene()
    cfg = CaptureConfig(motions=((motion, duration_s),), seed=seed, speed=speed,
                        sensor=SensorConfig(noise_rate_hz=noise_hz, seed=seed), frames=FrameConfig(seed=seed),
                        n_track_points=120, supersample=supersample)
    return simulate_synthetic(tpl, cam, bg, cfg)


def gradient_energy(img: np.ndarray, mask: np.ndarray) -> float:
    gy, gx = np.gradient(img.astype(np.float64))
    return float(np.mean((gx**2 + gy**2)[mask]))


def test_static_scene_gives_only_noise_at_the_configured_rate():
    quiet = capture("stand", noise_hz=0.0)
    assert quiet.events.size == 0  # nothing moves and no noise: not a single event
    noisy = capture("stand", noise_hz=2.0)
    expected = 2.0 * H * W * 0.1
    assert abs(noisy.events.size - expected) < 5 * np.sqrt(expected), (noisy.events.size, expected)
    assert set(np.unique(noisy.events["p"])) == {-1, 1}


def test_event_rate_grows_with_motion_speed():
    counts = [capture("jumping_jack", speed=s, noise_hz=0.0).events.size for s in (0.5, 1.0, 2.0)]
    assert counts[0] < counts[1] < counts[2], counts
    assert counts[1] > 1000


def test_events_sorted_inside_sensor_and_integer_microseconds():
    ev = capture("jumping_jack").events
    assert ev.dtype.names == ("t", "x", "y", "p") and ev["t"].dtype == np.int64
    assert np.all(np.diff(ev["t"]) >= 0) and ev["t"].min() >= 0 and ev["t"].max() <= 100_000
    assert ev["x"].max() < W and ev["y"].max() < H


def test_fast_motion_blurs_frames_static_is_sharp():
    tpl, cam, bg = scene()
    fast, still = capture("jumping_jack", speed=2.0), capture("stand")
    k = 2
    t = fast.frame_t_us[k]
    ev = fast.events[(fast.events["t"] >= t - 5000) & (fast.events["t"] < t + 5000)]
    moving = np.zeros((H, W), bool)
    moving[ev["y"], ev["x"]] = True  # where the scene changed during the exposure
    blurred = gradient_energy(fast.frame_images[k] / 255.0, moving) / gradient_energy(fast.sharp_images[k], moving)
    assert moving.sum() > 1000 and blurred < 0.8, (moving.sum(), blurred)
    actor = np.abs(still.sharp_images[k] - bg) > 1e-3
    sharp = gradient_energy(still.frame_images[k] / 255.0, actor) / gradient_energy(still.sharp_images[k], actor)
    assert 0.9 < sharp < 1.1, sharp


def test_frames_and_ground_truth_shapes_and_units():
    cap = capture("jumping_jack")
    n = cap.frame_images.shape[0]
    assert n == 3 and cap.frame_images.dtype == np.uint8
    assert np.array_equal(cap.frame_t_us, [5_000, 45_000, 85_000]) and np.all(cap.frame_exposure_us == 10_000)
    T = cap.gt_t_us.size
    assert T == 101 and np.all(np.diff(cap.gt_t_us) == 1000)
    assert cap.gt_poses.shape == (T, 33) and cap.gt_joints.shape == (T, 24, 3) and cap.gt_landmarks.shape == (T, 25, 3)
    assert 1.2 < cap.gt_joints[:, 15, 1].max() < 1.9  # the head is at a human height (m)
    assert cap.frame_joints.shape == (n, 24, 3)


def test_ground_truth_tracks_follow_the_surface():
    tpl, cam, bg = scene()
    cap = capture("jumping_jack")
    P = cap.track_tri.size
    assert 60 <= P <= 120
    assert cap.track_visible[[5, 45, 85]].mean() > 0.6
    i = 50  # recompute one time step independently
    verts = skin(cap.gt_poses[i], tpl)
    world = np.einsum("pk,pkd->pd", cap.track_bary.astype(np.float64), verts[tpl.faces[cap.track_tri]])
    assert np.allclose(cam.project(world), cap.track_px[i], atol=1e-3)
    # visible points move with the limbs: some move more than 1 px over the 100 ms
    moved = np.linalg.norm(cap.track_px[-1] - cap.track_px[0], axis=1)
    assert moved.max() > 5.0


def test_deterministic_for_a_seed():
    a = capture("jumping_jack")
    b = simulate_synthetic(*scene(), CaptureConfig(motions=(("jumping_jack", 0.1),), n_track_points=120,
                                                   sensor=SensorConfig(noise_rate_hz=0.2), frames=FrameConfig(),
                                                   supersample=1))
    assert np.array_equal(a.events, b.events) and np.array_equal(a.frame_images, b.frame_images)


@pytest.mark.parametrize("bad", [(("karate_kik", 0.1),), (("stand", -1.0),)])
def test_bad_motion_config_is_a_clear_error(bad):
    with pytest.raises(ValueError, match="unknown motion 'karate_kik'|duration"):
        simulate_synthetic(*scene(), CaptureConfig(motions=bad))


def test_poses_in_chunks_are_the_poses_of_one_call_and_bound_the_memory():
    """The capture tabulates its poses in chunks (a 60 s grid in one call peaked at ~4 GB): the values must be the
    very same as one call's, across a cross-fade between two motions and the feet placed on the floor."""
    import tracemalloc

    from eventcap.sim.capture import motion_function, poses_in_chunks

    tpl, _, _ = scene()
    poses_at = motion_function(CaptureConfig(motions=(("karate_kick", 1.5), ("boxing_combo", 1.5)), seed=1), tpl)
    t = np.arange(0, 3_000_000, 50) * 1e-6  # the render grid of 3 s (POSE_GRID_US)
    tracemalloc.start()
    whole = poses_at(t)
    _, peak_whole = tracemalloc.get_traced_memory()
    tracemalloc.reset_peak()
    chunked = poses_in_chunks(poses_at, t, chunk=997)  # chunks that do not divide the grid
    _, peak_chunked = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert chunked.shape == whole.shape == (60_000, 33)
    assert np.array_equal(chunked, whole)
    assert peak_chunked - whole.nbytes < 0.25 * (peak_whole - whole.nbytes), (peak_chunked, peak_whole)
