"""Tests of EDI sharpening (eventcap.imaging.edi): exactness of Eq. 2, propagation, sharpening of simulated fast
motions against the true sharp image, automatic contrast, bad input."""

from __future__ import annotations


import numpy as np
import pytest

from eventcap.events import EVENT_DTYPE, make_events
from eventcap.imaging import edi
from eventcap.sim.events import SensorConfig
from helpers import edi_scenes as scenes


EPS = edi.DEFAULT_LOG_EPS


def random_events(rng, n, t0, t1, height, width):
    t = np.sort(rng.integers(t0, t1 + 1, n))
    return make_events(t, rng.integers(0, width, n), rng.integers(0, height, n), rng.choice([-1, 1], n))


def exact_blurry(L_ref, t_ref, window, events, c, steps=20_000):
    """Eq. 1 for a latent that follows the events exactly: (1/T) ∫ exp(L_ref + c E(t)) dt by a fine midpoint rule
    on the µs grid (E is constant between integer µs), minus eps. (H, W) float64 linear."""
    height, width = L_ref.shape
    t0, t1 = window
    ts = np.arange(t0, t1)  # E on [t, t+1) equals E at t (events at integer times, right-continuous sums)
    acc = np.zeros(height * width)
    for t in ts:
        acc += np.exp(L_ref.ravel() + c * edi._signed_sum(events, t_ref, int(t), height * width, width))
    return acc.reshape(height, width) / ts.size - EPS


def test_smoke_shapes_and_static_pixels():
    height, width = 7, 9
    rng = np.random.default_rng(0)
    blurry = rng.uniform(0.05, 0.95, (height, width))
    no_events = np.empty(0, EVENT_DTYPE)
    L = edi.latent_log_image(blurry, no_events, 500, (0, 1000), 0.2, height, width)
    assert L.shape == (height, width) and L.dtype == np.float32
    np.testing.assert_allclose(L, np.log(blurry + EPS), rtol=1e-6)  # no events: the frame is the latent image
    np.testing.assert_allclose(edi.to_linear(L), blurry, atol=1e-6)
    # uint8 frames are DN / 255
    dn = np.rint(blurry * 255).astype(np.uint8)
    np.testing.assert_allclose(edi.latent_log_image(dn, no_events, 500, (0, 1000), 0.2, height, width),
                               np.log(dn / 255.0 + EPS), rtol=1e-6)  # fmt: skip


def test_eq2_inverts_eq1_exactly():
    """A blurry frame made by Eq. 1 from a latent that changes exactly by c per event is sharpened back to it."""
    height, width, c = 6, 8, 0.23
    rng = np.random.default_rng(1)
    window, t_ref = (1000, 3000), 2000
    events = random_events(rng, 150, 900, 3100, height, width)  # some fall outside the exposure
    L_ref = np.log(rng.uniform(0.05, 0.5, (height, width)) + EPS)
    blurry = exact_blurry(L_ref, t_ref, window, events, c)
    L = edi.latent_log_image(blurry, events, t_ref, window, c, height, width)
    np.testing.assert_allclose(L, L_ref, atol=2e-5)

    # reference time at the exposure's start, end, or outside it: the same latent seen at another time
    for other in (1000, 3000, 500, 3500):
        expected = L_ref + c * edi._signed_sum(events, t_ref, other, height * width, width).reshape(height, width)
        got = edi.latent_log_image(blurry, events, other, window, c, height, width)
        np.testing.assert_allclose(got, expected, atol=2e-5)

    # a per-pixel threshold map is used per pixel
    c_map = rng.uniform(0.15, 0.3, (height, width))
    acc = np.zeros(height * width)
    for t in range(*window):
        acc += np.exp(L_ref.ravel() + c_map.ravel() * edi._signed_sum(events, t_ref, t, height * width, width))
    blurry_map = acc.reshape(height, width) / (window[1] - window[0]) - EPS
    np.testing.assert_allclose(edi.latent_log_image(blurry_map, events, t_ref, window, c_map, height, width),
                               L_ref, atol=2e-5)  # fmt: skip


def test_propagation_matches_edi_at_other_times():
    height, width, c = 5, 6, 0.2
    rng = np.random.default_rng(2)
    events = random_events(rng, 400, 0, 50_000, height, width)
    blurry = rng.uniform(0.1, 0.9, (height, width))
    window = (20_000, 30_000)
    L_a = edi.latent_log_image(blurry, events, 25_000, window, c, height, width)
    times = np.array([40_000, 25_000, 0, 21_234, 50_000, 30_000])  # unsorted, before and after t_ref
    seq = edi.latent_log_sequence(L_a, 25_000, times, events, c)
    assert seq.shape == (times.size, height, width) and seq.dtype == np.float32
    for t, img in zip(times, seq):
        # EDI with any reference time describes the same latent signal (Eq. 2 is consistent with L(t) = L + cE)
        np.testing.assert_allclose(img, edi.latent_log_image(blurry, events, int(t), window, c, height, width),
                                   atol=1e-5)  # fmt: skip
        np.testing.assert_allclose(img, edi.latent_log_at(L_a, 25_000, int(t), events, c), atol=1e-6)
    np.testing.assert_allclose(seq[1], L_a, atol=1e-6)
    assert edi.latent_log_sequence(L_a, 25_000, np.array([], np.int64), events, c).shape == (0, height, width)


@pytest.mark.parametrize("name", ["bars 400 px/s", "checkerboard 360 px/s", "siemens star 680 px/s rim",
                                  "discs 800 px/s"])  # fmt: skip
def test_sharpening_beats_the_blurry_frame_by_3_db(name):
    """Simulated fast motion, 240x180, default sensor noise, 10 ms exposure: PSNR vs the true sharp image."""
    render = scenes.scenes()[name]
    events, frames = scenes.capture(render, 12_000)
    frame = frames[0]
    truth = render(frame.t_us)
    p_blurry = scenes.psnr(frame.image / 255.0, truth)
    p_edi = scenes.psnr(scenes.sharpen(frame, events, 0.2), truth)
    assert p_edi >= p_blurry + 3.0, (p_blurry, p_edi)


def test_contrast_estimate_within_20_percent():
    """One C per recording from 3 frames jointly; the simulator's nominal C is 0.2 (per-pixel sigma 0.03).

    The texture at 1000 px/s is the case where pixels flicker up and down between frames (ON/OFF threshold
    mismatch), the checkerboard one with clean monotonic edges."""
    for name in ("checkerboard 360 px/s", "texture 1000 px/s"):
        render = scenes.scenes()[name]
        events, frames = scenes.capture(render, 90_000)
        images = np.stack([f.image for f in frames])
        t_us = np.array([f.t_us for f in frames])
        est = edi.estimate_contrast(images, t_us, frames[0].exposure_us, events)
        assert abs(est.c / 0.2 - 1.0) <= 0.2, (name, est.c)
        assert est.grid.shape == est.energy.shape == (19,)
        assert est.energy_at_c <= est.energy.min() + 1e-12
        assert est.n_pixels > 1000
        # and the estimated C sharpens as well as the true one
        truth = render(frames[1].t_us)
        p_blurry = scenes.psnr(frames[1].image / 255.0, truth)
        assert scenes.psnr(scenes.sharpen(frames[1], events, est.c), truth) >= p_blurry + 3.0


def bar_capture(height: int, width: int, x0_px: float, speed_px_s: float, t_end_us: int):
    """A 12 px bright bar crossing a height x width sensor from x0_px at speed_px_s, simulated for t_end_us at 40 fps
    with 5 ms exposures: (render, events, frames)."""
    xx = np.arange(width, dtype=np.float64)

    def render(t_us: int) -> np.ndarray:
        x0 = x0_px + speed_px_s * t_us * 1e-6
        cover = np.clip(np.minimum(xx + 1, x0 + 12) - np.maximum(xx, x0), 0, 1)
        return np.broadcast_to((0.2 + 0.6 * cover)[None, :], (height, width)).astype(np.float32)

    from eventcap.sim.frames import FrameConfig, simulate_capture

    chunks = list(simulate_capture(render, 0, t_end_us, SensorConfig(), FrameConfig(fps=40.0, exposure_us=5_000)))
    return render, np.concatenate([c.events.events for c in chunks]), [f for c in chunks for f in c.frames]


def test_other_sensor_size_davis346():
    """Nothing assumes 240x180: a moving bar on a 346x260 (DAVIS346) sensor, with per-frame exposures."""
    height, width = 260, 346
    render, events, frames = bar_capture(height, width, 100.0, 300.0, 60_000)
    images = np.stack([f.image for f in frames])
    t_us = np.array([f.t_us for f in frames])
    latents = edi.sharpen_frames(images, t_us, np.full(len(frames), 5_000), events, 0.2)
    assert latents.shape == (len(frames), height, width) and np.isfinite(latents).all()
    swept = slice(95, 135)  # columns the bar crosses in the first exposure; elsewhere both are the static frame
    truth = render(frames[0].t_us)[:, swept]
    p_blurry = scenes.psnr(images[0][:, swept] / 255.0, truth)
    assert scenes.psnr(edi.to_linear(latents[0])[:, swept], truth) > p_blurry + 3.0
    est = edi.estimate_contrast(images, t_us, 5_000, events)
    assert abs(est.c / 0.2 - 1.0) <= 0.2



def test_contrast_estimate_memory_per_frame_is_its_counts_only():
    """The estimate reads every frame of a recording: per frame it may keep its signed counts (int32), not images in
    float64 (every frame's log image and latent image at once: ~1.6 GB a minute of capture at 240x180, 25 fps)."""
    import tracemalloc

    height, width = 60, 240
    _, events, frames = bar_capture(height, width, 20.0, 400.0, 500_000)
    images = np.stack([f.image for f in frames])
    t_us = np.array([f.t_us for f in frames])
    edi.estimate_contrast(images[:3], t_us[:3], 5_000, events)  # numba's compilation outside the measurement
    peaks, ests = {}, {}
    for k in (5, images.shape[0]):
        tracemalloc.start()
        ests[k] = edi.estimate_contrast(images[:k], t_us[:k], 5_000, events)
        peaks[k] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    k = images.shape[0]
    assert k >= 19
    per_frame = (peaks[k] - peaks[5]) / (k - 5)
    # measured 7 bytes a pixel (the int32 counts, the pair's informative pixels); with every frame's log image and
    # latent image held at once and the counts in float64 it was 26
    assert 0 < per_frame < 12 * height * width, per_frame
    assert abs(ests[k].c / 0.2 - 1.0) <= 0.2

def test_exception():
    height, width = 4, 5
    ok = make_events([10, 20], [1, 2], [0, 3], [1, -1])
    blurry = np.full((height, width), 0.5)
    with pytest.raises(ValueError, match="EVENT_DTYPE"):
        edi.latent_log_image(blurry, np.zeros(3), 15, (0, 30), 0.2, height, width)
    with pytest.raises(ValueError, match="sorted by time"):
        edi.latent_log_image(blurry, ok[::-1].copy(), 15, (0, 30), 0.2, height, width)
    with pytest.raises(ValueError, match="inside the 5x4"):
        edi.latent_log_image(blurry, make_events([1], [5], [0], [1]), 15, (0, 30), 0.2, height, width)
    with pytest.raises(ValueError, match=r"shape \(height, width\) = \(4, 5\), got \(5, 4\)"):
        edi.latent_log_image(blurry.T, ok, 15, (0, 30), 0.2, height, width)
    with pytest.raises(ValueError, match=r"linear intensity in \[0, 1\]"):
        edi.latent_log_image(blurry * 255, ok, 15, (0, 30), 0.2, height, width)
    with pytest.raises(ValueError, match="t_end > t_start"):
        edi.latent_log_image(blurry, ok, 15, (30, 0), 0.2, height, width)
    with pytest.raises(ValueError, match="C: expected a contrast threshold > 0"):
        edi.latent_log_image(blurry, ok, 15, (0, 30), 0.0, height, width)
    with pytest.raises(ValueError, match=r"C: expected a scalar or a \(height, width\)"):
        edi.latent_log_image(blurry, ok, 15, (0, 30), np.full((2, 2), 0.2), height, width)
    with pytest.raises(ValueError, match="t_ref_us: expected an integer"):
        edi.latent_log_image(blurry, ok, 15.5, (0, 30), 0.2, height, width)
    with pytest.raises(ValueError, match="times_us: expected a 1-D array of integer"):
        edi.latent_log_sequence(np.zeros((height, width)), 0, np.array([0.5]), ok, 0.2)
    images = np.full((1, height, width), 128, np.uint8)
    with pytest.raises(ValueError, match="at least 2 frames"):
        edi.estimate_contrast(images, np.array([15]), 10, ok)
    images = np.full((2, height, width), 128, np.uint8)
    with pytest.raises(ValueError, match="static scene"):
        edi.estimate_contrast(images, np.array([15, 40]), 10, ok)
    with pytest.raises(ValueError, match="increasing frame times"):
        edi.estimate_contrast(images, np.array([40, 15]), 10, ok)
    with pytest.raises(ValueError, match=r"exposure_us: expected \(2,\) integer"):
        edi.estimate_contrast(images, np.array([15, 40]), np.array([10, 0]), ok)
