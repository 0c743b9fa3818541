"""Tests of the simulated intensity frames (eventcap.sim.frames): Eq. 1 exposure averages, blur, readout noise."""

from __future__ import annotations

import numpy as np
import pytest

from eventcap.sim.events import SensorConfig, simulate
from eventcap.sim.frames import FrameConfig, frame_times_us, sensor_readout, simulate_capture

NOISELESS_FRAMES = FrameConfig(full_well_electrons=None, read_noise_dn=0.0)
QUIET_SENSOR = SensorConfig(noise_rate_hz=0.0)


def moving_bar(height: int, width: int, speed_px_s: float, x_start: float, bar_px: float = 6.0, lo=0.1, hi=0.9):
    """A bright vertical bar [x0, x0 + bar_px) moving right at speed_px_s, exactly box-filtered over each pixel."""
    xx = np.arange(width, dtype=np.float64)[None, :].repeat(height, 0)

    def coverage(x0: float) -> np.ndarray:
        return np.clip(np.minimum(xx + 1.0, x0 + bar_px) - np.maximum(xx, x0), 0.0, 1.0)

    def render(t_us: int) -> np.ndarray:
        return (lo + (hi - lo) * coverage(x_start + speed_px_s * t_us * 1e-6)).astype(np.float32)

    render.coverage = coverage  # type: ignore[attr-defined]
    return render


def gradient_energy(img: np.ndarray) -> float:
    img = img.astype(np.float64)
    return float(np.sum(np.diff(img, axis=1) ** 2) + np.sum(np.diff(img, axis=0) ** 2))


def capture(render, t0_us, t1_us, frame_config, sensor_config=QUIET_SENSOR):
    chunks = list(simulate_capture(render, t0_us, t1_us, sensor_config, frame_config))
    return chunks, [f for c in chunks for f in c.frames]


def test_frame_times_fill_the_interval():
    cfg = FrameConfig(fps=25.0, exposure_us=10_000)
    np.testing.assert_array_equal(frame_times_us(0, 200_000, cfg), [5_000, 45_000, 85_000, 125_000, 165_000])
    seven = frame_times_us(1_000, 1_001_000, FrameConfig(fps=7.0, exposure_us=20_000))
    assert seven.tolist() == [11_000 + round(k * 1e6 / 7) for k in range(7)]  # rounded per frame, no drift
    assert frame_times_us(0, 9_999, cfg).size == 0


def test_static_scene_frame_equals_the_image():
    height, width = 30, 40
    img = np.random.default_rng(0).uniform(0.0, 1.0, (height, width)).astype(np.float32)
    _, frames = capture(lambda t: img, 0, 100_000, NOISELESS_FRAMES)
    assert len(frames) == 3
    for f in frames:
        assert f.image.dtype == np.uint8 and f.image.shape == (height, width)
        assert f.exposure_us == 10_000
        np.testing.assert_allclose(f.mean_intensity, img, atol=1e-6)
        np.testing.assert_array_equal(f.image, np.rint(img.astype(np.float64) * 255))

    # with the default readout noise: unbiased, and as noisy as the model says (shot at 5000 e-, 1 DN read)
    _, noisy = capture(lambda t: img, 0, 100_000, FrameConfig())
    residual = noisy[0].image.astype(np.float64) - img * 255.0
    interior = (img > 0.05) & (img < 0.95)  # away from the clipping at 0 and 255
    predicted = np.sqrt(255.0**2 * img / 5000.0 + 1.0 + 1.0 / 12.0)  # shot, read, quantisation
    z = residual[interior] / predicted[interior]
    assert abs(z.mean()) < 0.1
    assert 0.9 < z.std() < 1.1
    assert not np.array_equal(noisy[0].image, noisy[1].image)  # fresh noise per frame


def test_fast_motion_blurs_the_frame_and_static_stays_sharp():
    height, width, speed = 16, 80, 2_000.0  # 20 px of motion within the 10 ms exposure
    render = moving_bar(height, width, speed, x_start=20.0)
    _, frames = capture(render, 0, 40_000, NOISELESS_FRAMES)
    f = frames[0]
    sharp = render(f.t_us)
    ratio = gradient_energy(f.image) / gradient_energy(np.rint(sharp * 255.0))
    assert ratio < 0.2

    # the blur is the exact exposure average of the moving bar (Eq. 1), not a few ghost copies
    x0s = 20.0 + speed * 1e-6 * np.linspace(f.t_us - 5_000, f.t_us + 5_000, 4001)
    exact = 0.1 + 0.8 * np.mean([render.coverage(x0)[0] for x0 in x0s], axis=0)
    assert np.max(np.abs(f.mean_intensity[0] - exact)) < 2e-3

    static = moving_bar(height, width, 0.0, x_start=20.0)
    _, frames = capture(static, 0, 40_000, NOISELESS_FRAMES)
    np.testing.assert_array_equal(frames[0].image, np.rint(static(0).astype(np.float64) * 255.0))


def test_exposure_average_of_a_linear_ramp_is_the_mid_exposure_value():
    height, width = 8, 9
    base = np.linspace(0.1, 0.5, height * width, dtype=np.float64).reshape(height, width)

    def ramp(t_us):  # linear in time, 0.3 per 100 ms of brightening
        return (base + 3e-6 * t_us).astype(np.float32)

    cfg = FrameConfig(fps=20.0, exposure_us=30_000, full_well_electrons=None, read_noise_dn=0.0)
    _, frames = capture(ramp, 0, 100_000, cfg)
    assert [f.t_us for f in frames] == [15_000, 65_000]
    for f in frames:
        np.testing.assert_allclose(f.mean_intensity, ramp(f.t_us), atol=2e-6)
        np.testing.assert_array_equal(f.image, np.rint(ramp(f.t_us).astype(np.float64) * 255.0))


def test_one_render_per_sample_shared_by_events_and_frames():
    height, width = 12, 30
    render_calls = []
    scene = moving_bar(height, width, 500.0, x_start=2.0)

    def render(t_us):
        render_calls.append(t_us)
        return scene(t_us)

    cfg = FrameConfig(fps=25.0, exposure_us=8_000, min_samples_per_exposure=20)
    chunks, frames = capture(render, 0, 100_000, cfg)
    samples = np.concatenate([c.events.sample_t_us for c in chunks])
    assert len(render_calls) == samples.size == sum(c.events.n_renders for c in chunks)
    assert len(set(render_calls)) == len(render_calls)
    assert len(frames) == 3 and sum(c.events.events.size for c in chunks) > 1_000
    for f in frames:
        start, end = f.t_us - 4_000, f.t_us + 4_000
        inside = samples[(samples >= start) & (samples <= end)]
        assert inside[0] == start and inside[-1] == end  # exposure boundaries are samples
        assert np.diff(inside).max() <= 8_000 // 20
    # each frame is delivered in the chunk during which its exposure ended
    for c in chunks:
        for f in c.frames:
            assert c.events.t_start_us < f.t_us + 4_000 <= c.events.t_end_us


def test_event_stream_unchanged_in_kind_when_frames_share_the_samples():
    # The forced exposure samples only refine the time sampling: the event count stays within a few percent.
    render = moving_bar(10, 40, 800.0, x_start=2.0)
    alone = sum(c.events.size for c in simulate(render, 0, 30_000, QUIET_SENSOR))
    chunks, _ = capture(render, 0, 30_000, FrameConfig(exposure_us=8_000))
    shared = sum(c.events.events.size for c in chunks)
    assert alone > 1_000 and abs(shared - alone) < 0.05 * alone


def test_readout_noise_statistics_and_determinism():
    mean = np.full((200, 200), 0.5, np.float32)
    cfg = FrameConfig()
    a = sensor_readout(mean, cfg, np.random.default_rng(5)).astype(np.float64)
    assert abs(a.mean() - 127.5) < 0.1
    assert abs(a.std() - np.sqrt(255.0**2 * 0.5 / 5000.0 + 1.0)) < 0.1  # 2.74 DN
    b = sensor_readout(mean, cfg, np.random.default_rng(5)).astype(np.float64)
    np.testing.assert_array_equal(a, b)
    saturated = sensor_readout(np.ones((4, 4)), FrameConfig(read_noise_dn=0.0, full_well_electrons=None), None)
    assert saturated.dtype == np.uint8 and np.all(saturated == 255)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"fps": 0.0}, r"fps: expected a finite number > 0, got 0.0"),
        ({"fps": 200.0}, r"exposure_us: expected at most the frame period 5000 µs \(fps=200.0\), got 10000"),
        ({"exposure_us": 0}, r"exposure_us: expected >= 1 µs, got 0"),
        ({"exposure_us": 4.8e3}, r"exposure_us: expected an integer, got 4800.0"),
        ({"min_samples_per_exposure": 0}, r"min_samples_per_exposure: expected >= 1, got 0"),
        ({"full_well_electrons": -1.0}, r"full_well_electrons: expected None or a finite number > 0, got -1.0"),
        ({"read_noise_dn": -0.5}, r"read_noise_dn: expected a finite number >= 0, got -0.5"),
    ],
)
def test_bad_frame_config_is_rejected(kwargs, message):
    with pytest.raises(ValueError, match=message):
        FrameConfig(**kwargs)
