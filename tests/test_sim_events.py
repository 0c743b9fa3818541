"""Tests of the simulated DVS pixel array (eventcap.sim.events) on analytic scenes with known answers."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from eventcap.events import EVENT_DTYPE
from eventcap.sim.events import (
    EventSimulator,
    SensorConfig,
    hot_pixels,
    pixel_thresholds,
    render_samples,
    simulate,
    simulate_all,
)

NOISELESS = SensorConfig(noise_rate_hz=0.0, refractory_us=0)


# ---------------------------------------------------------------- analytic scenes (linear intensity in [0, 1])
def static_scene(height: int, width: int, seed: int = 1):
    img = np.random.default_rng(seed).uniform(0.05, 0.95, (height, width)).astype(np.float32)
    return lambda t_us: img


def moving_edge(height: int, width: int, speed_px_s: float, x_start: float = 5.0, lo=0.1, hi=0.9):
    """A vertical dark|bright edge at x_start + v t (bright on the right), exactly box-filtered over each pixel."""
    xx = np.arange(width, dtype=np.float64)[None, :].repeat(height, 0)

    def render(t_us: int) -> np.ndarray:
        x0 = x_start + speed_px_s * t_us * 1e-6
        coverage = np.clip(xx + 1.0 - x0, 0.0, 1.0)  # fraction of pixel [x, x+1] right of the edge
        return (lo + (hi - lo) * coverage).astype(np.float32)

    return render


def moving_texture(height: int, width: int, speed_px_s: float, seed: int = 3):
    """A smooth random texture (squashed sum of sinusoids) translating diagonally at speed_px_s."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
    waves = [(rng.uniform(0.05, 0.4), rng.uniform(0, 2 * np.pi), rng.uniform(0, 2 * np.pi)) for _ in range(6)]

    def render(t_us: int) -> np.ndarray:
        s = speed_px_s * t_us * 1e-6 / np.sqrt(2)
        acc = np.zeros((height, width))
        for k, ang, ph in waves:
            acc += np.sin(k * ((xx - s) * np.cos(ang) + (yy - s) * np.sin(ang)) + ph)
        return (0.5 + 0.4 * np.tanh(0.7 * acc)).astype(np.float32)  # in (0.1, 0.9): no flat clipped regions

    return render


def log_ramp(height: int, width: int, l0: float, rate_per_us: float, eps: float = 1e-3):
    """Uniform brightness with log(I + eps) = l0 + rate * t exactly (so linear interpolation is exact)."""

    def render(t_us: int) -> np.ndarray:
        return np.full((height, width), np.exp(l0 + rate_per_us * t_us) - eps, np.float32)

    return render


def per_pixel_counts(ev: np.ndarray, height: int, width: int, polarity: int | None = None) -> np.ndarray:
    sel = ev if polarity is None else ev[ev["p"] == polarity]
    return np.bincount(sel["y"].astype(np.int64) * width + sel["x"], minlength=height * width).reshape(height, width)


# ---------------------------------------------------------------- single step against hand-computed crossings
def test_step_places_crossings_by_linear_interpolation():
    cfg = SensorConfig(threshold_sigma=0.0, noise_rate_hz=0.0, refractory_us=0)
    sim = EventSimulator(cfg, 1, 2)
    sim.reset(np.zeros((1, 2), np.float32), 0)
    ev = sim.step(np.array([[0.5, -0.45]], np.float32), 1000)
    # pixel 0: +0.2 at 0.4 of the step, +0.4 at 0.8; pixel 1: -0.2 at 444.4 µs, -0.4 at 888.9 µs
    assert ev.dtype == EVENT_DTYPE
    assert ev["t"].tolist() == [400, 444, 800, 889]
    assert ev["x"].tolist() == [0, 1, 0, 1]
    assert ev["y"].tolist() == [0, 0, 0, 0]
    assert ev["p"].tolist() == [1, -1, 1, -1]
    # the references moved by exactly the emitted crossings: 0.1 more up and 0.05 more down give nothing yet
    assert sim.step(np.array([[0.5 + 0.099, -0.45 - 0.049]], np.float32), 2000).size == 0
    ev = sim.step(np.array([[0.61, -0.61]], np.float32), 3000)
    assert ev["p"].tolist() == [1, -1]


def test_step_rejects_bad_input():
    sim = EventSimulator(NOISELESS, 4, 6)
    with pytest.raises(ValueError, match="call reset"):
        sim.step(np.zeros((4, 6)), 10)
    with pytest.raises(ValueError, match=r"expected shape \(height, width\) = \(4, 6\), got \(6, 4\)"):
        sim.reset(np.zeros((6, 4)), 0)
    sim.reset(np.zeros((4, 6)), 100)
    with pytest.raises(ValueError, match="expected t_us > 100"):
        sim.step(np.zeros((4, 6)), 100)


# ---------------------------------------------------------------- noise
def test_static_scene_gives_noise_at_the_configured_rate():
    height, width, rate_hz, duration_s = 40, 50, 5.0, 2.0
    cfg = SensorConfig(noise_rate_hz=rate_hz, refractory_us=100, seed=7)
    ev = simulate_all(static_scene(height, width), 0, int(duration_s * 1e6), cfg)
    expected = rate_hz * height * width * duration_s  # 20,000; Poisson std 141
    assert abs(ev.size - expected) < 4 * np.sqrt(expected)
    n_on = int(np.sum(ev["p"] == 1))
    assert abs(n_on / ev.size - 0.5) < 4 * 0.5 / np.sqrt(ev.size)  # random polarity
    counts = per_pixel_counts(ev, height, width)
    dispersion = counts.var() / counts.mean()  # 1 for independent Poisson pixels
    assert 0.9 < dispersion < 1.1


def test_static_scene_without_noise_gives_no_events():
    ev = simulate_all(static_scene(30, 40), 0, 500_000, SensorConfig(noise_rate_hz=0.0))
    assert ev.size == 0


def test_hot_pixels_fire_at_their_rate():
    height, width = 40, 50
    cfg = SensorConfig(noise_rate_hz=0.5, hot_pixel_fraction=0.01, hot_pixel_rate_hz=200.0, seed=3)
    hot = hot_pixels(cfg, height, width)
    assert hot.size == 20
    ev = simulate_all(static_scene(height, width), 0, 1_000_000, cfg)
    counts = per_pixel_counts(ev, height, width).ravel()
    expected_hot = 200.5 * (1 - 200.5 * cfg.refractory_us * 1e-6)  # refractory loses ~2 %
    assert abs(counts[hot].mean() - expected_hot) < 4 * np.sqrt(200.5 / hot.size)
    cold = np.delete(counts, hot)
    assert abs(cold.mean() - 0.5) < 4 * np.sqrt(0.5 / cold.size)


# ---------------------------------------------------------------- signal events
def test_event_count_grows_with_edge_speed():
    height, width = 20, 80
    counts = []
    for speed in (50.0, 100.0, 200.0):
        ev = simulate_all(moving_edge(height, width, speed), 0, 200_000, NOISELESS)
        counts.append(ev.size)
    # the edge sweeps 10, 20, 40 px; each swept pixel fires ~log(0.901/0.101)/0.2 ~ 11 OFF events
    assert 0.8 * 10 * height * 11 < counts[0] < 1.2 * 10 * height * 11
    assert 1.9 < counts[1] / counts[0] < 2.1
    assert 1.9 < counts[2] / counts[1] < 2.1


def test_brightening_gives_on_events_and_darkening_off_events():
    height, width = 10, 12
    c_on, c_off = pixel_thresholds(NOISELESS, height, width)
    # log intensity rises by 1.5 over 100 ms: each pixel fires exactly floor(1.5 / C_on(u)) ON events
    up = simulate_all(log_ramp(height, width, -2.0, 1.5e-5), 0, 100_000, NOISELESS)
    assert up.size > 0 and np.all(up["p"] == 1)
    np.testing.assert_array_equal(per_pixel_counts(up, height, width), np.floor(1.5 / c_on + 1e-9))
    down = simulate_all(log_ramp(height, width, -0.5, -1.5e-5), 0, 100_000, NOISELESS)
    assert down.size > 0 and np.all(down["p"] == -1)
    np.testing.assert_array_equal(per_pixel_counts(down, height, width), np.floor(1.5 / c_off + 1e-9))


def test_timestamps_of_a_log_linear_ramp_are_exact():
    height, width, rate = 6, 7, 1e-4  # 0.1 log units per ms
    c_on, _ = pixel_thresholds(NOISELESS, height, width)
    ev = simulate_all(log_ramp(height, width, -6.0, rate), 0, 50_000, NOISELESS)  # L: -6 -> -1
    ev = ev[np.lexsort((ev["t"], ev["x"], ev["y"]))]
    counts = per_pixel_counts(ev, height, width)
    k = np.concatenate([np.arange(1, n + 1) for n in counts.ravel()])  # index of the crossing within its pixel
    exact_t = k * c_on[ev["y"], ev["x"]] / rate
    assert np.max(np.abs(ev["t"] - exact_t)) <= 1.0  # µs: rounding to integer µs plus float32 log precision


def test_polarity_sum_reproduces_log_change_within_one_threshold():
    height, width = 30, 40
    render = moving_texture(height, width, speed_px_s=300.0)
    t1 = 150_000
    ev = simulate_all(render, 0, t1, NOISELESS)
    c_on, c_off = pixel_thresholds(NOISELESS, height, width)
    on = per_pixel_counts(ev, height, width, 1)
    off = per_pixel_counts(ev, height, width, -1)
    reconstructed = on * c_on - off * c_off
    true_change = np.log(render(t1) + 1e-3).astype(np.float64) - np.log(render(0) + 1e-3)
    residual = true_change - reconstructed  # must lie in (-C_off, C_on) per pixel
    assert ev.size > 10_000
    assert np.all(residual < c_on + 1e-5) and np.all(residual > -c_off - 1e-5)


def test_timestamps_sorted_and_within_interval():
    height, width, t0, t1 = 20, 30, 1_000, 121_000
    cfg = SensorConfig(noise_rate_hz=20.0, seed=2)
    chunks = list(simulate(moving_edge(height, width, 150.0), t0, t1, cfg, chunk_us=20_000))
    ev = np.concatenate([c.events for c in chunks])
    assert ev.size > 1000
    assert np.all(np.diff(ev["t"]) >= 0)
    assert ev["t"].min() >= t0 and ev["t"].max() <= t1
    assert ev["x"].max() < width and ev["y"].max() < height
    assert set(np.unique(ev["p"]).tolist()) == {-1, 1}
    assert chunks[0].t_start_us == t0 and chunks[-1].t_end_us == t1
    for a, b in itertools.pairwise(chunks):
        assert a.t_end_us == b.t_start_us
    for c in chunks:
        assert c.events.size == 0 or (c.events["t"].min() >= c.t_start_us and c.events["t"].max() <= c.t_end_us)
        assert c.t_end_us - c.t_start_us <= 20_000 + cfg.max_step_us
    samples = np.concatenate([c.sample_t_us for c in chunks])
    assert samples[0] == t0 and samples[-1] == t1 and np.all(np.diff(samples) > 0)


def test_refractory_period_enforces_minimum_interval_and_keeps_reference():
    height, width, refractory = 20, 40, 500
    render = moving_edge(height, width, 1000.0, lo=0.02, hi=1.0)  # ~19 events per pixel within 1 ms
    cfg = SensorConfig(noise_rate_hz=50.0, hot_pixel_fraction=0.02, hot_pixel_rate_hz=2000.0, refractory_us=refractory)
    ev = simulate_all(render, 0, 30_000, cfg)
    ev = ev[np.lexsort((ev["t"], ev["x"], ev["y"]))]
    same_pixel = (np.diff(ev["x"].astype(int)) == 0) & (np.diff(ev["y"].astype(int)) == 0)
    assert same_pixel.sum() > 500
    assert np.diff(ev["t"])[same_pixel].min() >= refractory

    # Noise off: dropped crossings still move the reference, so emitted + dropped = the refractory-free count,
    # and the pixels fire again once the window is over (no stale burst, no lost track).
    free = list(simulate(render, 0, 30_000, SensorConfig(noise_rate_hz=0.0, refractory_us=0)))
    limited = list(simulate(render, 0, 30_000, SensorConfig(noise_rate_hz=0.0, refractory_us=refractory)))
    n_free = sum(c.events.size for c in free)
    n_limited = sum(c.events.size for c in limited)
    n_dropped = sum(c.n_refractory_dropped for c in limited)
    assert n_dropped > 0.5 * n_free
    assert n_limited + n_dropped == n_free


def test_adaptive_sampling_bounds_log_change_per_sample():
    height, width = 24, 32
    calls = []
    scene = moving_texture(height, width, speed_px_s=800.0)

    def render(t_us):
        calls.append(t_us)
        return scene(t_us)

    cfg = SensorConfig(noise_rate_hz=0.0, min_step_us=1, max_log_change_fraction=0.25)
    chunks = list(simulate(render, 0, 50_000, cfg))
    samples = np.concatenate([c.sample_t_us for c in chunks])
    assert sum(c.n_forced_steps for c in chunks) == 0
    assert sum(c.n_renders for c in chunks) == len(calls) == samples.size  # every render is a sample
    assert sorted(calls) == samples.tolist()
    logs = np.stack([np.log(scene(int(t)) + np.float32(1e-3)) for t in samples])
    per_sample = np.abs(np.diff(logs, axis=0)).max(axis=(1, 2))
    assert per_sample.max() <= 0.25 * 0.2 + 1e-6
    np.testing.assert_allclose(np.concatenate([c.sample_max_log_change for c in chunks])[1:], per_sample, rtol=1e-5)
    assert per_sample.mean() > 0.5 * 0.25 * 0.2  # and it does not oversample either


def test_adaptive_sampling_respects_step_bounds_and_required_times():
    cfg = SensorConfig(noise_rate_hz=0.0, min_step_us=200, max_step_us=3_000)
    fast = list(render_samples(moving_edge(8, 40, 3000.0), 0, 10_000, cfg))
    steps = np.diff([s.t_us for s in fast])
    assert steps.min() >= 200 or steps[-1] < 200  # only the last step may be cut short by t1
    assert any(s.forced for s in fast)  # a sharp edge at 3000 px/s changes L by > 0.1 per 200 µs
    assert all(s.max_log_change <= cfg.max_log_change for s in fast if not s.forced)
    static = [s.t_us for s in render_samples(static_scene(8, 8), 0, 20_000, cfg, required_t_us=[7_777, 25_000])]
    assert 7_777 in static and static[-1] == 20_000
    assert np.diff(static).max() <= 3_000


def test_same_seed_same_events_other_seed_other_events():
    render = moving_edge(16, 24, 300.0)
    cfg = SensorConfig(noise_rate_hz=30.0, threshold_sigma=0.05, seed=11)
    a = simulate_all(render, 0, 60_000, cfg)
    b = simulate_all(render, 0, 60_000, cfg)
    c = simulate_all(render, 0, 60_000, SensorConfig(noise_rate_hz=30.0, threshold_sigma=0.05, seed=12))
    assert a.size > 0
    np.testing.assert_array_equal(a, b)
    assert a.size != c.size or not np.array_equal(a, c)


# ---------------------------------------------------------------- errors
@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"threshold_pos": 0.0}, r"threshold_pos: expected a finite number > 0, got 0.0"),
        ({"threshold_neg": -0.2}, r"threshold_neg: expected a finite number > 0"),
        ({"threshold_sigma": -0.01}, r"threshold_sigma: expected a finite number >= 0"),
        ({"noise_rate_hz": float("nan")}, r"noise_rate_hz: expected a finite number >= 0, got nan"),
        ({"hot_pixel_fraction": 1.5}, r"hot_pixel_fraction: expected a value in \[0, 1\], got 1.5"),
        ({"log_eps": 0.0}, r"log_eps: expected a finite number > 0"),
        ({"max_log_change_fraction": 0.0}, r"max_log_change_fraction: expected a value in \(0, 1\]"),
        ({"refractory_us": -1}, r"refractory_us: expected >= 0 µs, got -1"),
        ({"refractory_us": 1e-4}, r"refractory_us: expected an integer, got 0.0001"),
        ({"min_step_us": 500, "max_step_us": 100}, r"min_step_us <= max_step_us, got min_step_us=500"),
        ({"min_step_us": 0}, r"expected 1 <= min_step_us"),
    ],
)
def test_bad_config_is_rejected(kwargs, message):
    with pytest.raises(ValueError, match=message):
        SensorConfig(**kwargs)


def test_bad_capture_input_is_rejected():
    scene = static_scene(4, 5)
    with pytest.raises(ValueError, match=r"expected t1_us > t0_us, got t0_us=10, t1_us=10"):
        next(simulate(scene, 10, 10))
    with pytest.raises(ValueError, match=r"t1_us \(µs\): expected an integer, got 0.5"):
        next(simulate(scene, 0, 0.5))
    with pytest.raises(
        ValueError, match=r"render\(0\): expected an image of shape \(height, width\), got shape \(5,\)"
    ):
        next(simulate(lambda t: np.zeros(5, np.float32), 0, 100))
    with pytest.raises(
        ValueError, match=r"render\(0\): expected linear intensity in \[0, 1\], got values in \[0.0, 2.0\]"
    ):
        next(simulate(lambda t: np.array([[0.0, 2.0]]), 0, 100))
    with pytest.raises(
        ValueError, match=r"expected an image of shape \(height, width\) = \(4, 5\), got shape \(5, 4\)"
    ):
        list(simulate(lambda t: np.zeros((4, 5) if t == 0 else (5, 4), np.float32), 0, 100))
    with pytest.raises(ValueError, match=r"sensor width: expected an integer in \[1, 65535\], got 0"):
        EventSimulator(SensorConfig(), 4, 0)
    with pytest.raises(ValueError, match=r"chunk_us: expected an integer >= 1, got 0"):
        next(simulate(scene, 0, 100, chunk_us=0))
