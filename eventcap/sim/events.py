"""Simulated event camera: turns a rendered linear-intensity video into a DVS event stream (ESIM / v2e style).

This is a *simulator*: everything it emits is synthetic. It is independent of what is rendered; its only input is
a render function ``render(t_us) -> (height, width) float32`` of linear intensity in [0, 1].

Pixel model (per pixel u, natural-log units)
--------------------------------------------
- Log intensity ``L(u, t) = log(I(u, t) + log_eps)``; ``log_eps`` keeps black pixels finite.
- Every pixel holds a reference level ``ref(u)`` (the log intensity memorised at its last reset) and fires an
  event of polarity ``p`` whenever ``L`` reaches ``ref + C_on(u)`` (p = +1) or ``ref - C_off(u)`` (p = -1),
  after which the reference moves by exactly ``+C_on`` / ``-C_off`` (paper, "Event Camera Model":
  ``L(t_i) - L(t_p) = p_i C``). ``C_on(u)``, ``C_off(u)`` are drawn once per pixel from
  ``N(C, threshold_sigma^2)`` (fixed-pattern mismatch) and clipped below at ``threshold_min``.
- Between two render samples ``(t_a, L_a)`` and ``(t_b, L_b)`` the log intensity is interpolated *linearly in
  time*; a pixel emits one event at each threshold level crossed, at the interpolated crossing time
  ``t = t_a + (level - L_a) / (L_b - L_a) * (t_b - t_a)``, rounded to the nearest integer microsecond. Within one
  interval a pixel's signal is monotonic, so all its crossings there have one polarity. The reference is
  initialised to ``L(t0)`` at the first sample (all pixels freshly reset).
- Refractory period: after an emitted event, a pixel emits nothing for ``refractory_us``. Crossings that fall
  in the refractory window are *dropped from the output but still move the reference by ±C*, as if the pixel had
  fired and been reset. This keeps ``|L - ref| < C`` at every sample, so no error accumulates and the pixel does
  not emit a burst of stale events when the window ends; the information lost is exactly the dropped events'
  ``sum(p * C)`` (counted in ``EventChunk.n_refractory_dropped``). Background-activity events are pixel events
  too: they obey the refractory period and start a new one.
- Background activity (leak / shot noise): every pixel fires independent Poisson events at ``noise_rate_hz``
  with random polarity; a fraction ``hot_pixel_fraction`` of pixels (chosen once) fire additionally at
  ``hot_pixel_rate_hz``. Noise events do not move the reference (they model spurious firings of the readout,
  not a change of the memorised level), so a static scene produces noise at exactly the configured rate.
  Noise times are drawn uniformly in integer microseconds, i.e. an exact Poisson process on the µs grid.

Sensor realism (both off by default, so the default capture is the ideal pixel above)
--------------------------------------------------------------------------------------
- Photoreceptor bandwidth (``photoreceptor_cutoff_hz``): the change detector sees a first-order low-pass of ``L``
  whose cutoff is proportional to the pixel's photocurrent, ``f_c = f_white (I + 20/255) / (275/255)`` (v2e's
  model, Delbruck et al. 2021; the caller scales ``f_white`` with the scene illuminance: the DVS128's 3 kHz at
  1 klux falls to 30 Hz at 10 lux). Dim pixels lag: a fast limb's events come late and smeared in time, and small
  fast changes are lost. The filter is integrated exactly for ``L`` linear between samples (no stability limit on
  the step); the crossings inside a step are interpolated linearly, and :meth:`EventSimulator.max_step_us` bounds
  the next step so the filter's own relaxation moves at most ``max_log_change`` per step (see there).
- Leak events (``leak_rate_hz``): each pixel's reference drifts down by ``leak_rate_hz * C_on`` per second, as the
  reset switch's junction leakage does, so a static pixel fires ON events at its leak rate (per-pixel rates
  log-normal with ``leak_rate_spread_decades``, random phases). Unlike background activity these events do move
  the reference, and they come only ON and periodically.

Time sampling
-------------
Renders are the expensive part, so the driver (:func:`render_samples`) picks each next sample time adaptively:
no pixel's log intensity may change by more than ``max_log_change_fraction * min(C_on, C_off)`` (nominal C)
between consecutive samples. The next step is predicted from the last one (scaled by target/observed change,
growing at most 2x); a candidate that changes too much is kept as a future sample and the interval is subdivided
(a render at an earlier time), so every render becomes a sample and none is wasted. Steps are bounded by
``[min_step_us, max_step_us]``; at the minimum step a larger change is accepted and counted as a forced step.

Not modelled: the photoreceptor's second pole and its noise (v2e's ``photoreceptor_noise``), shot-noise rates
that grow in the dark (background activity here has one rate for every pixel and light level), the dark current's
growing share of the log signal in dim light (``log_eps`` is fixed), slow threshold drift, readout bus saturation
and event-rate controllers, and timestamp jitter.
"""

from __future__ import annotations

import math
import operator
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass

import numba
import numpy as np

from eventcap.events import EVENT_DTYPE, empty_events, make_events

_NEVER_US = np.iinfo(np.int64).min // 4  # "last event time" of a pixel that has not fired yet
#: Dark-current floor of the photoreceptor's cutoff, in intensity units: v2e's (255 I + 20) / 275 scaling.
_DARK_FLOOR = 20.0 / 255.0


@dataclass(frozen=True)
class SensorConfig:
    """Parameters of the simulated DVS pixel array (defaults: a DAVIS240C-like sensor in indoor light)."""

    # Nominal contrast threshold of ON events, natural-log units (v2e and ESIM default 0.2).
    threshold_pos: float = 0.2
    # Nominal contrast threshold of OFF events, natural-log units.
    threshold_neg: float = 0.2
    # Std of each pixel's thresholds around the nominal ones (absolute, log units), drawn once per pixel.
    threshold_sigma: float = 0.03
    # Floor of the drawn thresholds: a near-zero threshold would fire on rounding noise. 0.05 is 5 sigma below
    # the default nominal value, so it only bites for unusually wide spreads.
    threshold_min: float = 0.05
    # Refractory period in µs. Real DVS pixels are held in reset for tens of µs to ~1 ms depending on the bias;
    # 100 µs caps a pixel at 10 kHz. Events are lost only where L changes by more than C per 100 µs (the log
    # change of a moving edge bunches at its dark end; docs/results/implementation.md). 0 gives the ideal stream.
    refractory_us: int = 100
    # Background-activity noise per pixel, Hz (Poisson, random polarity); DAVIS sensors indoors: ~0.1-1 Hz.
    noise_rate_hz: float = 0.2
    # Fraction of pixels that are hot (chosen once per sensor); 0 disables hot pixels.
    hot_pixel_fraction: float = 0.0
    # Extra Poisson event rate of a hot pixel, Hz (on top of noise_rate_hz).
    hot_pixel_rate_hz: float = 100.0
    # L = log(I + log_eps) for I in [0, 1]; 1e-3 as in v2e/ESIM (black maps to -6.9 instead of -inf).
    log_eps: float = 1e-3
    # Adaptive sampling: largest per-pixel |delta L| allowed between consecutive render samples, as a fraction of
    # the nominal threshold min(threshold_pos, threshold_neg). Smaller = more renders, more exact timestamps.
    max_log_change_fraction: float = 0.5
    # Smallest step between render samples, µs. Caps the render rate of fast scenes at 1e6/min_step_us per second
    # of capture (5000/s: ~50 s per second of capture at ~10 ms per render, inside the generator's 60 s budget);
    # in forced steps timestamps are only as exact as this step (0.2 of a 1 ms tracking frame).
    min_step_us: int = 200
    # Largest step between render samples, µs: a static scene is still re-rendered this often, so a change that
    # starts there is noticed at most this late.
    max_step_us: int = 5_000
    # Leak events per pixel per second (Hz), ON polarity: the memorised reference drifts down by
    # leak_rate_hz * C_on per second, as the reset switch's junction leakage does (v2e's model; v2e's "noisy" preset
    # uses 0.1 Hz). Each pixel's rate is drawn once, log-normal with leak_rate_spread_decades (v2e:
    # noise_rate_cov_decades 0.1), and its phase at random. 0 disables leak (the default: the ideal pixel).
    leak_rate_hz: float = 0.0
    leak_rate_spread_decades: float = 0.1
    # Photoreceptor bandwidth: 3 dB cutoff (Hz) of a white pixel (I = 1) in the scene's light, or None for an ideal,
    # infinitely fast photoreceptor (the default). A pixel of intensity I low-passes its log intensity with a first-
    # order filter of cutoff photoreceptor_cutoff_hz * (I + 20/255) / (275/255): proportional to its photocurrent,
    # with v2e's floor for dark pixels (v2ecore/emulator_utils.py rescale_intensity_frame). The caller scales the
    # white cutoff with the scene illuminance (the bandwidth is proportional to the light).
    photoreceptor_cutoff_hz: float | None = None
    # Seed of the per-pixel thresholds, the hot-pixel choice and the noise.
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("threshold_pos", "threshold_neg", "threshold_min", "log_eps"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"SensorConfig.{name}: expected a finite number > 0, got {value!r}")
        if self.photoreceptor_cutoff_hz is not None and not (
            math.isfinite(self.photoreceptor_cutoff_hz) and self.photoreceptor_cutoff_hz > 0
        ):
            raise ValueError(
                "SensorConfig.photoreceptor_cutoff_hz: expected None (ideal photoreceptor) or a finite number > 0, "
                f"got {self.photoreceptor_cutoff_hz!r}"
            )
        for name in ("threshold_sigma", "noise_rate_hz", "hot_pixel_rate_hz", "leak_rate_hz",
                     "leak_rate_spread_decades"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"SensorConfig.{name}: expected a finite number >= 0, got {value!r}")
        if not 0.0 <= self.hot_pixel_fraction <= 1.0:
            raise ValueError(
                f"SensorConfig.hot_pixel_fraction: expected a value in [0, 1], got {self.hot_pixel_fraction!r}"
            )
        if not 0.0 < self.max_log_change_fraction <= 1.0:
            raise ValueError(
                f"SensorConfig.max_log_change_fraction: expected a value in (0, 1], got {self.max_log_change_fraction!r}"
            )
        for name in ("refractory_us", "min_step_us", "max_step_us", "seed"):
            _require_int(f"SensorConfig.{name}", getattr(self, name))
        if self.refractory_us < 0:
            raise ValueError(f"SensorConfig.refractory_us: expected >= 0 µs, got {self.refractory_us}")
        if not 1 <= self.min_step_us <= self.max_step_us:
            raise ValueError(
                "SensorConfig: expected 1 <= min_step_us <= max_step_us, "
                f"got min_step_us={self.min_step_us}, max_step_us={self.max_step_us}"
            )

    @property
    def max_log_change(self) -> float:
        """The adaptive-sampling bound on per-pixel |delta L| between samples (log units)."""
        return self.max_log_change_fraction * min(self.threshold_pos, self.threshold_neg)


def _require_int(what: str, value: object) -> int:
    """``value`` as a Python int (numpy integers too), or a ValueError naming ``what``."""
    try:
        return operator.index(value)  # type: ignore[arg-type]
    except TypeError:
        raise ValueError(f"{what}: expected an integer, got {value!r}") from None


def _rngs(config: SensorConfig) -> tuple[np.random.Generator, ...]:
    """Independent generators for thresholds, hot-pixel choice, noise and leak, so changing one leaves the others
    (spawned children depend only on their index: adding the fourth left the first three unchanged)."""
    seeds = np.random.SeedSequence(config.seed).spawn(4)
    return tuple(np.random.default_rng(s) for s in seeds)


def pixel_thresholds(config: SensorConfig, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """The per-pixel ON and OFF contrast thresholds of the simulated sensor, each (height, width) float64 log units."""
    _check_size(height, width)
    rng = _rngs(config)[0]
    c_on = rng.normal(config.threshold_pos, config.threshold_sigma, size=(height, width))
    c_off = rng.normal(config.threshold_neg, config.threshold_sigma, size=(height, width))
    return np.maximum(c_on, config.threshold_min), np.maximum(c_off, config.threshold_min)


def hot_pixels(config: SensorConfig, height: int, width: int) -> np.ndarray:
    """Flat indices (y * width + x, sorted int64) of the simulated sensor's hot pixels."""
    _check_size(height, width)
    n_hot = round(config.hot_pixel_fraction * height * width)
    rng = _rngs(config)[1]
    return np.sort(rng.choice(height * width, size=n_hot, replace=False)).astype(np.int64)


def _check_size(height: int, width: int) -> None:
    for name, value in (("height", height), ("width", width)):
        if not 0 < _require_int(f"sensor {name}", value) < 65536:
            raise ValueError(f"sensor {name}: expected an integer in [1, 65535], got {value!r}")


@numba.njit(cache=True, nogil=True)
def _emit_kernel(l_prev, l_new, ref, c_on, c_off, last_t, t_prev, t_new, refractory_us, noise_pix, noise_t, noise_p):
    """Crossings of every pixel between two samples, merged with its noise events, refractory applied.

    l_prev, l_new: (N,) float32 log intensity at t_prev, t_new; ref, last_t: (N,) per-pixel state, updated in place;
    noise_*: noise candidates sorted by (pixel, time). Returns (t, pixel, p, n_dropped) in pixel-major order.
    """
    n_pix = l_new.size
    n_noise = noise_pix.size
    total = n_noise
    for i in range(n_pix):
        d = l_new[i] - ref[i]
        if d >= c_on[i]:
            total += int(d / c_on[i])
        elif -d >= c_off[i]:
            total += int(-d / c_off[i])
    out_t = np.empty(total, np.int64)
    out_pix = np.empty(total, np.int64)
    out_p = np.empty(total, np.int8)
    k = 0
    j = 0  # next noise candidate; pixels are visited in increasing order, like the noise sort order
    dropped = 0
    span = float(t_new - t_prev)
    for i in range(n_pix):
        d = l_new[i] - ref[i]
        n = 0
        step = 0.0
        pol = 0
        if d >= c_on[i]:
            n = int(d / c_on[i])
            step = c_on[i]
            pol = 1
        elif -d >= c_off[i]:
            n = int(-d / c_off[i])
            step = -c_off[i]
            pol = -1
        if n == 0 and (j >= n_noise or noise_pix[j] != i):
            continue
        l0 = float(l_prev[i])
        slope = float(l_new[i]) - l0  # != 0 whenever n > 0: l_prev lies strictly inside (ref - C_off, ref + C_on)
        r = ref[i]
        lt = last_t[i]
        q = 1
        while q <= n or (j < n_noise and noise_pix[j] == i):
            ts = t_new + 1
            if q <= n:
                frac = (r + q * step - l0) / slope
                ts = t_prev + math.floor(frac * span + 0.5)
                if ts < t_prev:
                    ts = t_prev
                elif ts > t_new:
                    ts = t_new
            if j < n_noise and noise_pix[j] == i and noise_t[j] < ts:
                te = noise_t[j]
                pe = noise_p[j]
                j += 1
            else:
                te = ts
                pe = pol
                q += 1
            if te - lt >= refractory_us:
                out_t[k] = te
                out_pix[k] = i
                out_p[k] = pe
                k += 1
                lt = te
            else:
                dropped += 1
        ref[i] = r + n * step
        last_t[i] = lt
    return out_t[:k], out_pix[:k], out_p[:k], dropped


class EventSimulator:
    """Stateful simulated DVS pixel array: feed log-intensity samples in time order, get the events between them.

    State per pixel: reference log level, previous sample, time of the last emitted event. Use
    :func:`simulate` for the adaptive render loop; use this class directly to drive it with your own samples.
    """

    def __init__(self, config: SensorConfig, height: int, width: int) -> None:
        _check_size(height, width)
        self.config = config
        self.height = int(height)
        self.width = int(width)
        c_on, c_off = pixel_thresholds(config, height, width)
        self._c_on = c_on.ravel()
        self._c_off = c_off.ravel()
        self._hot = hot_pixels(config, height, width)
        rngs = _rngs(config)
        self._noise_rng = rngs[2]
        # Sensor realism (off by default): the photoreceptor's low-pass and the reference's leak act on the signal
        # the change detector sees; the kernel then treats it exactly like the ideal pixel's log intensity.
        self._lowpass = config.photoreceptor_cutoff_hz is not None
        self._realistic = self._lowpass or config.leak_rate_hz > 0
        self._leak_per_us = np.zeros(height * width)  # log units per µs added to the signal (= reference drift)
        self._leak_phase = np.zeros(height * width)
        if config.leak_rate_hz > 0:
            leak_rng = rngs[3]
            rate = config.leak_rate_hz * 10.0 ** (config.leak_rate_spread_decades * leak_rng.standard_normal(
                height * width))
            self._leak_per_us = rate * self._c_on * 1e-6
            # Pixels were last reset at random times: each starts a random fraction of C_on towards its leak event.
            self._leak_phase = leak_rng.uniform(0.0, 1.0, height * width) * self._c_on
        self._raw_prev: np.ndarray | None = None  # float64 log intensity of the last sample
        self._filtered: np.ndarray | None = None  # float64 photoreceptor output (low-passed log intensity)
        self._leak = np.zeros(0)
        self._ref: np.ndarray | None = None
        self._last_t = np.full(height * width, _NEVER_US, np.int64)
        self._l_prev: np.ndarray | None = None
        self._t_prev = 0
        #: Crossings and noise firings suppressed by the refractory period since the last reset.
        self.n_refractory_dropped = 0

    @property
    def t_us(self) -> int:
        """Time of the last sample fed in, µs."""
        return self._t_prev

    def reset(self, log_intensity: np.ndarray, t_us: int) -> None:
        """Start at time ``t_us`` with every pixel's reference at ``log_intensity`` ((height, width), log units)."""
        flat = self._check_log(log_intensity)
        self._ref = flat.astype(np.float64)
        self._l_prev = flat.astype(np.float32, copy=True)
        if self._realistic:
            self._raw_prev = flat.astype(np.float64)
            self._filtered = self._raw_prev.copy()  # steady state: the photoreceptor has settled
            self._leak = self._leak_phase.copy()
            self._l_prev = (self._filtered + self._leak).astype(np.float32)
        self._last_t.fill(_NEVER_US)
        self._t_prev = int(t_us)
        self.n_refractory_dropped = 0

    def step(self, log_intensity: np.ndarray, t_us: int) -> np.ndarray:
        """Advance to a new sample ((height, width) log intensity at ``t_us``); return the events in
        (previous sample, t_us], sorted by time (ties by pixel, row-major), as ``EVENT_DTYPE``."""
        if self._ref is None or self._l_prev is None:
            raise ValueError("EventSimulator.step: call reset() with the first sample before step()")
        t_us = int(t_us)
        if t_us <= self._t_prev:
            raise ValueError(f"EventSimulator.step: expected t_us > {self._t_prev} (the previous sample), got {t_us}")
        flat = self._check_log(log_intensity).astype(np.float32, copy=False)
        if self._realistic:
            flat = self._pixel_signal(flat, t_us - self._t_prev)
        noise_pix, noise_t, noise_p = self._draw_noise(self._t_prev, t_us)
        t, pix, p, dropped = _emit_kernel(
            self._l_prev, flat, self._ref, self._c_on, self._c_off, self._last_t, self._t_prev, t_us,
            self.config.refractory_us, noise_pix, noise_t, noise_p,
        )  # fmt: skip
        self.n_refractory_dropped += int(dropped)
        self._l_prev = flat.copy()
        self._t_prev = t_us
        if t.size == 0:
            return empty_events()
        order = np.argsort(t, kind="stable")
        pix = pix[order]
        return make_events(t[order], pix % self.width, pix // self.width, p[order])

    def _cutoff_hz(self, intensity_plus_eps: np.ndarray) -> np.ndarray:
        """Per-pixel photoreceptor cutoff (Hz) at linear intensity (+ log_eps): proportional to the photocurrent."""
        intensity = intensity_plus_eps - self.config.log_eps
        return self.config.photoreceptor_cutoff_hz * (intensity + _DARK_FLOOR) / (1.0 + _DARK_FLOOR)

    def _pixel_signal(self, flat: np.ndarray, dt_us: int) -> np.ndarray:
        """What the change detector compares with its reference: the photoreceptor's low-pass of the log intensity
        plus the accumulated leak (a reference drifting down is a signal drifting up). Float32 like the input.

        The low-pass is integrated exactly for a log intensity linear between the samples (the simulator's own
        assumption), with the cutoff of the step's mean photocurrent: y_b = x_b - s tau + (y_a - x_a + s tau) e^(-dt/tau)
        with s the slope. Exact at every sample whatever the step, so no step is too long for stability; the crossing
        times inside a step are interpolated linearly like the input's, which :meth:`max_step_us` keeps accurate.
        """
        raw = flat.astype(np.float64)
        if self._lowpass:
            assert self._raw_prev is not None and self._filtered is not None
            dt = float(dt_us) * 1e-6
            tau = 1.0 / (2.0 * np.pi * self._cutoff_hz(0.5 * (np.exp(self._raw_prev) + np.exp(raw))))
            slope_tau = (raw - self._raw_prev) / dt * tau
            self._filtered = raw - slope_tau + (self._filtered - self._raw_prev + slope_tau) * np.exp(-dt / tau)
        else:
            self._filtered = raw
        self._raw_prev = raw
        if self._leak_per_us.any():
            self._leak = self._leak + self._leak_per_us * dt_us
        return (self._filtered + self._leak).astype(np.float32)

    def max_step_us(self) -> int:
        """Longest next render step that keeps the photoreceptor's own relaxation below the sampling bound.

        Between samples the filtered signal moves by (its input's change, at most the sampler's bound) plus its
        relaxation towards the input, at most |x - y| / tau per unit time at the step's start (the gap only shrinks
        while the input holds). Bounding the relaxation by ``config.max_log_change`` keeps each step's change of the
        detector's signal within twice the bound (one threshold by default), so crossings stay as exactly timed as
        the ideal pixel's. Never below ``min_step_us`` (the sampler's floor); unbounded without the low-pass.
        """
        if not self._lowpass or self._raw_prev is None or self._filtered is None:
            return np.iinfo(np.int64).max
        rate = np.abs(self._raw_prev - self._filtered) * (2.0 * np.pi * 1e-6) * self._cutoff_hz(np.exp(self._raw_prev))
        worst = float(rate.max()) if rate.size else 0.0
        if worst <= 0.0:
            return np.iinfo(np.int64).max
        return max(self.config.min_step_us, int(self.config.max_log_change / worst))

    @property
    def photoreceptor_output(self) -> np.ndarray | None:
        """(height, width) float64 low-passed log intensity at the last sample (None for the ideal pixel)."""
        if not self._lowpass or self._filtered is None:
            return None
        return self._filtered.reshape(self.height, self.width).copy()

    def _check_log(self, log_intensity: np.ndarray) -> np.ndarray:
        arr = np.asarray(log_intensity)
        if arr.shape != (self.height, self.width):
            raise ValueError(
                f"log intensity: expected shape (height, width) = ({self.height}, {self.width}), got {arr.shape}"
            )
        return arr.ravel()

    def _draw_noise(self, t_prev: int, t_new: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Background and hot-pixel Poisson events in (t_prev, t_new], sorted by (pixel, time)."""
        cfg = self.config
        rng = self._noise_rng
        span_s = (t_new - t_prev) * 1e-6
        pix = []
        if cfg.noise_rate_hz > 0:
            n = rng.poisson(cfg.noise_rate_hz * self._c_on.size * span_s)
            pix.append(rng.integers(0, self._c_on.size, n))
        if cfg.hot_pixel_rate_hz > 0 and self._hot.size:
            n = rng.poisson(cfg.hot_pixel_rate_hz * self._hot.size * span_s)
            pix.append(self._hot[rng.integers(0, self._hot.size, n)])
        if not pix:
            return np.empty(0, np.int64), np.empty(0, np.int64), np.empty(0, np.int8)
        pix_all = np.concatenate(pix).astype(np.int64)
        t = rng.integers(t_prev + 1, t_new + 1, pix_all.size, dtype=np.int64)
        p = (rng.integers(0, 2, pix_all.size, dtype=np.int8) * 2 - 1).astype(np.int8)
        order = np.lexsort((t, pix_all))
        return pix_all[order], t[order], p[order]


@dataclass(frozen=True)
class RenderSample:
    """One accepted render sample of the adaptive time sampling."""

    t_us: int
    intensity: np.ndarray  # (height, width) float32 linear intensity in [0, 1], as rendered
    log_intensity: np.ndarray  # (height, width) float32, log(intensity + log_eps)
    max_log_change: float  # max over pixels of |delta L| since the previous sample (0 for the first)
    n_renders: int  # renders made so far, including this sample's (cumulative)
    forced: bool  # accepted at a step <= min_step_us although max_log_change exceeded the bound


def _checked_render(render: Callable[[int], np.ndarray], t_us: int, shape: tuple[int, int] | None) -> np.ndarray:
    img = np.asarray(render(t_us))
    if img.ndim != 2 or (shape is not None and img.shape != shape):
        want = "(height, width)" if shape is None else f"(height, width) = {shape}"
        raise ValueError(f"render({t_us}): expected an image of shape {want}, got shape {img.shape}")
    img = img.astype(np.float32, copy=True)  # own copy: a renderer may reuse its output buffer between calls
    lo, hi = float(img.min()), float(img.max())
    if not (lo >= 0.0 and hi <= 1.0):  # also catches NaN
        raise ValueError(f"render({t_us}): expected linear intensity in [0, 1], got values in [{lo}, {hi}]")
    return img


def render_samples(
    render: Callable[[int], np.ndarray],
    t0_us: int,
    t1_us: int,
    config: SensorConfig,
    *,
    required_t_us: Iterable[int] = (),
    max_step_us_at: Callable[[int], int] | None = None,
) -> Iterator[RenderSample]:
    """Render the scene at adaptively chosen times in [t0_us, t1_us] (both included), one render per sample.

    Consecutive samples differ by at most ``config.max_log_change`` in any pixel's log intensity, unless the step
    is already ``config.min_step_us`` (then ``forced``). ``required_t_us``: times that must be samples (e.g.
    exposure boundaries); ``max_step_us_at(t)``: an extra upper bound on the step starting at sample time t.
    """
    t0_us, t1_us = _check_interval(t0_us, t1_us)
    required = sorted({int(t) for t in required_t_us if t0_us < int(t) < t1_us} | {t1_us})
    target = config.max_log_change
    eps = np.float32(config.log_eps)

    img = _checked_render(render, t0_us, None)
    shape = img.shape
    n_renders = 1
    log_prev = np.log(img + eps)
    yield RenderSample(t0_us, img, log_prev, 0.0, n_renders, False)

    t_prev = t0_us
    step = config.min_step_us  # start cautiously; accepted steps grow it quickly (x2 per step)
    pending: list[tuple[int, np.ndarray, np.ndarray]] = []  # rendered future samples, nearest last
    i_req = 0
    while t_prev < t1_us:
        while required[i_req] <= t_prev:
            i_req += 1
        limit = config.max_step_us if max_step_us_at is None else min(config.max_step_us, max_step_us_at(t_prev))
        t_try = min(t_prev + max(1, min(step, limit)), required[i_req])
        if pending and pending[-1][0] <= t_try:
            t_c, img_c, log_c = pending.pop()
        else:
            t_c = t_try
            img_c = _checked_render(render, t_c, shape)
            n_renders += 1
            log_c = np.log(img_c + eps)
        change = float(np.max(np.abs(log_c - log_prev)))
        dt = t_c - t_prev
        if change > target and dt > config.min_step_us:
            pending.append((t_c, img_c, log_c))
            # Linear prediction of the step that would meet the bound; at most 0.8x the rejected one.
            step = max(config.min_step_us, min(int(dt * 0.8), int(dt * 0.8 * target / change)))
            continue
        forced = change > target
        yield RenderSample(t_c, img_c, log_c, change, n_renders, forced)
        growth = 2.0 if change <= 0 else min(2.0, 0.8 * target / change)
        step = max(config.min_step_us, int(dt * growth))
        t_prev, log_prev = t_c, log_c


def _check_interval(t0_us: int, t1_us: int) -> tuple[int, int]:
    t0_us = _require_int("t0_us (µs)", t0_us)
    t1_us = _require_int("t1_us (µs)", t1_us)
    if t1_us <= t0_us:
        raise ValueError(f"capture interval: expected t1_us > t0_us, got t0_us={t0_us}, t1_us={t1_us}")
    return t0_us, t1_us


@dataclass(frozen=True)
class EventChunk:
    """Simulated events of one stretch of a capture, with the render samples that produced them.

    Concatenating the chunks of a capture in order gives a time-sorted stream (chunk k's times are >= chunk k-1's).
    """

    events: np.ndarray  # EVENT_DTYPE, sorted by t, all in [t_start_us, t_end_us]
    t_start_us: int  # previous chunk's last sample (t0_us for the first chunk)
    t_end_us: int  # this chunk's last sample
    sample_t_us: np.ndarray  # (S,) int64 sample times of this chunk (the first chunk includes t0_us)
    sample_max_log_change: np.ndarray  # (S,) float32 max |delta L| since the previous sample
    n_renders: int  # renders made while producing this chunk (sums to the capture's total)
    n_forced_steps: int  # samples accepted at a step <= min_step_us above the log-change bound
    n_refractory_dropped: int  # crossings / noise firings suppressed by the refractory period


def simulate(
    render: Callable[[int], np.ndarray],
    t0_us: int,
    t1_us: int,
    config: SensorConfig = SensorConfig(),
    *,
    chunk_us: int = 10_000,
    required_t_us: Iterable[int] = (),
    max_step_us_at: Callable[[int], int] | None = None,
    on_sample: Callable[[RenderSample], None] | None = None,
) -> Iterator[EventChunk]:
    """Simulate the event camera over [t0_us, t1_us], yielding :class:`EventChunk` s of about ``chunk_us`` each.

    ``render(t_us)`` returns the (height, width) float32 linear intensity in [0, 1] at integer time t_us; it is
    called once per sample time. Memory stays bounded by one chunk. ``required_t_us``, ``max_step_us_at`` and
    ``on_sample`` let another consumer share the same renders (see ``eventcap.sim.frames.simulate_capture``):
    ``on_sample`` is called with every accepted sample, in time order, before the chunk containing it is yielded.
    """
    if _require_int("chunk_us", chunk_us) < 1:
        raise ValueError(f"chunk_us: expected an integer >= 1, got {chunk_us!r}")
    sim: EventSimulator | None = None
    parts: list[np.ndarray] = []
    times: list[int] = []
    changes: list[float] = []
    renders_before = 0
    forced = 0
    dropped_before = 0
    chunk_start = int(t0_us)
    def step_bound(t_us: int) -> int:
        own = sim.max_step_us() if sim is not None else np.iinfo(np.int64).max
        return own if max_step_us_at is None else min(own, max_step_us_at(t_us))

    bound = max_step_us_at if config.photoreceptor_cutoff_hz is None else step_bound
    for sample in render_samples(render, t0_us, t1_us, config, required_t_us=required_t_us, max_step_us_at=bound):
        if sim is None:
            sim = EventSimulator(config, *sample.intensity.shape)
            sim.reset(sample.log_intensity, sample.t_us)
        else:
            ev = sim.step(sample.log_intensity, sample.t_us)
            if ev.size:
                parts.append(ev)
        if on_sample is not None:
            on_sample(sample)
        times.append(sample.t_us)
        changes.append(sample.max_log_change)
        forced += sample.forced
        if sample.t_us - chunk_start >= chunk_us or sample.t_us == t1_us:
            yield EventChunk(
                events=np.concatenate(parts) if parts else empty_events(),
                t_start_us=chunk_start,
                t_end_us=sample.t_us,
                sample_t_us=np.asarray(times, np.int64),
                sample_max_log_change=np.asarray(changes, np.float32),
                n_renders=sample.n_renders - renders_before,
                n_forced_steps=forced,
                n_refractory_dropped=sim.n_refractory_dropped - dropped_before,
            )
            parts, times, changes, forced = [], [], [], 0
            renders_before = sample.n_renders
            dropped_before = sim.n_refractory_dropped
            chunk_start = sample.t_us


def simulate_all(
    render: Callable[[int], np.ndarray], t0_us: int, t1_us: int, config: SensorConfig = SensorConfig()
) -> np.ndarray:
    """All simulated events over [t0_us, t1_us] as one sorted ``EVENT_DTYPE`` array (short captures, tests)."""
    chunks = [c.events for c in simulate(render, t0_us, t1_us, config)]
    return np.concatenate(chunks) if chunks else np.empty(0, EVENT_DTYPE)
