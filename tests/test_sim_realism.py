"""Sensor realism of the simulated DVS: the photoreceptor's low-pass (time constant, falling with the light, event
timing of a step) and leak events (rate, polarity, period), and the step bound that keeps the sampling exact."""

from __future__ import annotations

import math

import numpy as np
import pytest

from eventcap.sim.events import EventSimulator, SensorConfig, simulate_all

H, W = 4, 5
EPS = 1e-3


def quiet(**kw) -> SensorConfig:
    return SensorConfig(threshold_sigma=0.0, noise_rate_hz=0.0, refractory_us=0, seed=0, **kw)


def tau_s(cutoff_white_hz: float, intensity: float) -> float:
    """The stated time constant: cutoff proportional to the photocurrent, v2e's dark floor."""
    return 1.0 / (2 * math.pi * cutoff_white_hz * (intensity + 20 / 255) / (275 / 255))


def step_response(cutoff_hz: float, i0: float, i1: float, t_end_us: int, dt_us: int = 5):
    """Photoreceptor output (log) of one pixel after an intensity step i0 -> i1 at t = 0, sampled every dt_us."""
    sim = EventSimulator(quiet(photoreceptor_cutoff_hz=cutoff_hz), H, W)
    sim.reset(np.full((H, W), math.log(i0 + EPS), np.float32), 0)
    times, out, events = [], [], []
    for t in range(1, t_end_us + 1, dt_us):
        events.append(sim.step(np.full((H, W), math.log(i1 + EPS), np.float32), t))
        times.append(t)
        out.append(sim.photoreceptor_output[0, 0])
    return np.array(times), np.array(out), np.concatenate(events)


@pytest.mark.parametrize("i0, i1", [(0.1, 0.8), (0.8, 0.1)])
def test_step_response_has_the_stated_time_constant(i0, i1):
    tau = tau_s(1500.0, i1)  # after the step the pixel's photocurrent is i1's
    t, y, _ = step_response(1500.0, i0, i1, int(5 * tau * 1e6))
    l0, l1 = math.log(i0 + EPS), math.log(i1 + EPS)
    frac = (y - l0) / (l1 - l0)
    t63 = np.interp(1 - math.exp(-1), frac, t)  # frac rises monotonically
    assert t63 == pytest.approx(tau * 1e6, rel=0.01), (t63, tau * 1e6)
    # From the first sample on (the step itself is a 1 µs ramp), the remaining gap decays exactly as exp(-t / tau).
    np.testing.assert_allclose(1 - frac, (1 - frac[0]) * np.exp(-(t - 1) * 1e-6 / tau), atol=1e-6)
    assert frac[0] < 0.01


def test_time_constant_falls_with_illumination():
    # White-pixel cutoffs of a 3 kHz-at-1-klux photoreceptor at 500 lux and at 10 lux: 50 x slower in the dim room.
    taus = []
    for cutoff in (1500.0, 30.0):
        tau = tau_s(cutoff, 0.5)
        t, y, _ = step_response(cutoff, 0.2, 0.5, int(3 * tau * 1e6), dt_us=max(1, int(tau * 1e6 / 400)))
        frac = (y - math.log(0.2 + EPS)) / (math.log(0.5 + EPS) - math.log(0.2 + EPS))
        taus.append(np.interp(1 - math.exp(-1), frac, t))
    assert taus[1] / taus[0] == pytest.approx(50.0, rel=0.02)
    assert taus[0] == pytest.approx(tau_s(1500.0, 0.5) * 1e6, rel=0.01)


def test_step_events_come_when_the_filtered_signal_crosses_each_level():
    cutoff, i0, i1 = 300.0, 0.1, 0.8
    tau = tau_s(cutoff, i1)
    _, _, ev = step_response(cutoff, i0, i1, int(6 * tau * 1e6), dt_us=10)
    px = ev[(ev["x"] == 0) & (ev["y"] == 0)]
    dl = math.log(i1 + EPS) - math.log(i0 + EPS)
    k = np.arange(1, int(dl / 0.2) + 1)
    expected = 1 - tau * 1e6 * np.log(1 - k * 0.2 / dl)  # the filter reaches k C at t_k
    assert np.all(px["p"] == 1) and px.size == k.size == 10
    np.testing.assert_allclose(px["t"], expected, atol=3.0)
    # An ideal pixel fires all ten at the step; this one spreads them over ~3 tau (the smear of dim light).
    assert px["t"][-1] - px["t"][0] > 2.5 * tau * 1e6


def test_step_bound_keeps_the_relaxation_within_the_sampling_bound():
    cfg = quiet(photoreceptor_cutoff_hz=30.0)
    sim = EventSimulator(cfg, H, W)
    sim.reset(np.full((H, W), math.log(0.1 + EPS), np.float32), 0)
    bright = np.full((H, W), math.log(0.9 + EPS), np.float32)
    sim.step(bright, cfg.min_step_us)  # a big jump: the photoreceptor lags by ~2 log units
    t = cfg.min_step_us
    assert sim.max_step_us() < cfg.max_step_us
    for _ in range(20):
        before = sim.photoreceptor_output.copy()
        step = sim.max_step_us()
        t += min(step, cfg.max_step_us)
        sim.step(bright, t)
        moved = float(np.abs(sim.photoreceptor_output - before).max())
        assert moved <= cfg.max_log_change * 1.0001 or step == cfg.min_step_us, (moved, step)
    ideal = EventSimulator(quiet(), H, W)
    assert ideal.max_step_us() == np.iinfo(np.int64).max


def test_leak_events_appear_at_the_stated_rate_on_a_static_scene():
    img = np.full((20, 20), 0.4, np.float32)
    # Without per-pixel spread every pixel fires exactly rate x duration ON events (its phase is below one period).
    ev = simulate_all(lambda t: img, 0, 2_000_000, quiet(leak_rate_hz=5.0, leak_rate_spread_decades=0.0))
    counts = np.bincount(ev["y"].astype(int) * 20 + ev["x"], minlength=400)
    assert np.all(ev["p"] == 1) and np.all(counts == 10)
    gaps = np.diff(ev[(ev["x"] == 3) & (ev["y"] == 7)]["t"])
    np.testing.assert_allclose(gaps, 200_000, atol=2)  # one event per 1 / 5 Hz
    # With the default spread (0.1 decades, log-normal) the mean rate is 5 Hz x exp((0.1 ln 10)^2 / 2).
    ev = simulate_all(lambda t: img, 0, 2_000_000, quiet(leak_rate_hz=5.0))
    expected = 5.0 * math.exp((0.1 * math.log(10)) ** 2 / 2) * 400 * 2.0
    assert ev.size == pytest.approx(expected, rel=0.03) and np.all(ev["p"] == 1)


def test_leak_and_bandwidth_off_leave_the_ideal_pixel_unchanged():
    rng = np.random.default_rng(0)
    frames = [rng.uniform(0.05, 0.9, (H, W)).astype(np.float32) for _ in range(6)]

    def render(t):
        return frames[min(t // 10_000, 5)]

    base = simulate_all(render, 0, 55_000, SensorConfig(seed=1))
    again = simulate_all(render, 0, 55_000, SensorConfig(seed=1, leak_rate_hz=0.0, photoreceptor_cutoff_hz=None))
    np.testing.assert_array_equal(base, again)
    assert base.size > 20


def test_bad_realism_config_is_rejected():
    with pytest.raises(ValueError, match="SensorConfig.photoreceptor_cutoff_hz: expected None"):
        SensorConfig(photoreceptor_cutoff_hz=0.0)
    with pytest.raises(ValueError, match="SensorConfig.leak_rate_hz: expected a finite number >= 0"):
        SensorConfig(leak_rate_hz=float("nan"))
