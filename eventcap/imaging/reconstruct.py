"""Intensity images from events alone, without learned weights (for event-only cameras and previews).

Method: the per-pixel high-pass filter of Scheerlinck, Barnes and Mahony (ACCV 2018, "Continuous-time intensity
estimation using event cameras"), events only. Each pixel's log intensity estimate jumps by ``±contrast`` at each
of its events and decays towards 0 with rate ``cutoff_rad_s`` in between:

    dL/dt = contrast * sum_i p_i delta(t - t_i) - cutoff_rad_s * L,

so ``L(T) = contrast * sum_{t_i <= T} p_i exp(-cutoff_rad_s (T - t_i))``. ``cutoff_rad_s = 0`` is direct
integration (every event kept forever). The filter is linear and time-invariant, so the event-by-event update and
this closed form agree exactly; we evaluate it at the requested times only, one weighted histogram
(``np.bincount``) per interval between two sample times, carrying the state forward by one decay factor —
vectorised over events and pixels, no Python loop over events.

What it cannot do: recover anything that did not change. A static background produces no events and reads 0
(mid-grey); a moving actor appears against it, with a fading negative trace where it was during the last
``1/cutoff_rad_s`` seconds. The estimate is a *relative* log image (unknown offset per pixel); compare it with a true
image only up to scale and offset (:func:`agreement`), on the pixels that moved.

``benchmarks/accuracy/bench_events_only.py`` compares the options against the true sharp images of the synthetic capture.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Defaults of the reconstruction, chosen by ``benchmarks/accuracy/bench_events_only.py`` (docs/results/events-only.md, docs/results/settings.md).
DEFAULT_CUTOFF_RAD_S = 3.0
DEFAULT_CONTRAST = 0.2
DEFAULT_BASE_INTENSITY = 0.5
DEFAULT_BASELINE = "median"


def high_pass(events: np.ndarray, height: int, width: int, times_us, cutoff_rad_s: float = DEFAULT_CUTOFF_RAD_S,
              contrast: float = DEFAULT_CONTRAST) -> np.ndarray:
    """Relative log images (n, height, width) float32 at ``times_us`` (n,) from ``events`` (EVENT_DTYPE, sorted).

    Events with ``t <= times_us[k]`` contribute to image k. ``cutoff_rad_s`` >= 0 is the decay rate (0 = direct
    integration), ``contrast`` the log-intensity step of one event.
    """
    t = np.asarray(times_us, dtype=np.int64)
    if t.ndim != 1:
        raise ValueError(f"times_us: expected a 1-D array of times (us), got shape {t.shape}")
    if t.size > 1 and np.any(np.diff(t) < 0):
        k = int(np.argmax(np.diff(t) < 0)) + 1
        raise ValueError(f"times_us: expected sorted times; time {k} ({t[k]} us) is before time {k - 1} "
                         f"({t[k - 1]} us)")
    if not (np.isfinite(cutoff_rad_s) and cutoff_rad_s >= 0):
        raise ValueError(f"cutoff_rad_s: expected a decay rate >= 0 rad/s, got {cutoff_rad_s!r}")
    if not (np.isfinite(contrast) and contrast > 0):
        raise ValueError(f"contrast: expected a log-intensity step > 0, got {contrast!r}")
    if height <= 0 or width <= 0:
        raise ValueError(f"image size: expected height, width > 0, got {height} x {width}")
    ev_t = events["t"]
    if ev_t.size > 1 and np.any(np.diff(ev_t) < 0):
        raise ValueError("events: expected events sorted by time")
    npix = int(height) * int(width)
    pix = events["y"].astype(np.int64) * int(width) + events["x"].astype(np.int64)
    if pix.size and (pix.min() < 0 or pix.max() >= npix or events["x"].max() >= width):
        raise ValueError(f"events: coordinates outside the {width} x {height} sensor")
    pol = events["p"].astype(np.float64)
    ends = np.searchsorted(ev_t, t, side="right")  # events [ends[k-1], ends[k]) arrive in (t[k-1], t[k]]
    rate = float(cutoff_rad_s) * 1e-6  # per microsecond
    state = np.zeros(npix, np.float64)
    out = np.empty((t.size, height, width), np.float32)
    start, t_prev = 0, (int(ev_t[0]) if ev_t.size else (int(t[0]) if t.size else 0))
    for k in range(t.size):
        stop = int(ends[k])
        tk = int(t[k])
        if rate > 0:
            state *= np.exp(-rate * max(tk - t_prev, 0))
        if stop > start:
            w = pol[start:stop]
            if rate > 0:
                w = w * np.exp(-rate * (tk - ev_t[start:stop]).astype(np.float64))
            state += np.bincount(pix[start:stop], weights=w, minlength=npix)
        start, t_prev = max(start, stop), tk
        out[k] = (contrast * state).reshape(height, width)
    return out


def median_baseline(events: np.ndarray, height: int, width: int, cutoff_rad_s: float = DEFAULT_CUTOFF_RAD_S,
                    contrast: float = DEFAULT_CONTRAST, samples: int = 200, step_us: int = 5000) -> np.ndarray:
    """Per-pixel median (height, width) float32 of the filter's output over the whole recording: every ``step_us``,
    or ``samples`` times evenly spread when the recording is longer. Most pixels show the static background most
    of the time, so subtracting it leaves ~0 where the background shows now, removing the fading traces of where
    the actor was (non-causal: it uses the whole recording; an offline pipeline can)."""
    if samples < 1 or step_us < 1:
        raise ValueError(f"median baseline: expected samples >= 1 and step_us >= 1, got {samples}, {step_us}")
    ev_t = events["t"]
    if ev_t.size == 0:
        return np.zeros((height, width), np.float32)
    t0, t1 = int(ev_t[0]), int(ev_t[-1])
    # At most ~256 MB of float32 images (a 1280 x 720 sensor gets ~70 samples).
    n = int(min(samples, (t1 - t0) // step_us + 1, max(16, (256 << 20) // (4 * height * width))))
    times = np.unique(np.round(np.linspace(t0, t1, max(n, 1))).astype(np.int64))
    return np.median(high_pass(events, height, width, times, cutoff_rad_s, contrast), axis=0).astype(np.float32)


def smooth_image(image: np.ndarray, sigma_px: float) -> np.ndarray:
    """A Gaussian of std ``sigma_px`` over one (H, W) image (spatial denoising), float32."""
    import cv2

    return cv2.GaussianBlur(np.asarray(image, np.float32), (0, 0), float(sigma_px), borderType=cv2.BORDER_REPLICATE)


def reconstruct(events: np.ndarray, height: int, width: int, times_us, cutoff_rad_s: float = DEFAULT_CUTOFF_RAD_S,
                contrast: float = DEFAULT_CONTRAST, baseline: str = DEFAULT_BASELINE, smooth_px: float = 0.0
                ) -> np.ndarray:
    """The recipe the `reconstruct` stage and previews use: :func:`high_pass` at ``times_us``, minus the
    :func:`median_baseline` when ``baseline="median"`` (``"none"``: nothing subtracted), then a Gaussian of
    ``smooth_px`` (0 = none). Relative log images (n, height, width) float32."""
    if baseline not in ("none", "median"):
        raise ValueError(f"baseline: expected none | median, got {baseline!r}")
    if not (np.isfinite(smooth_px) and smooth_px >= 0):
        raise ValueError(f"smooth_px: expected a std >= 0 px, got {smooth_px!r}")
    out = high_pass(events, height, width, times_us, cutoff_rad_s, contrast)
    if baseline == "median":
        out -= median_baseline(events, height, width, cutoff_rad_s, contrast)
    if smooth_px > 0:
        for k in range(out.shape[0]):
            out[k] = smooth_image(out[k], smooth_px)
    return out


def to_log_images(relative: np.ndarray, eps: float = 1e-3, base_intensity: float = DEFAULT_BASE_INTENSITY
                  ) -> np.ndarray:
    """Relative log images -> log(I + eps) as LatentFrames store them, with "no change" at ``base_intensity``."""
    return (np.float32(np.log(base_intensity + eps)) + relative).astype(np.float32)


def to_intensity(log_images: np.ndarray, eps: float = 1e-3) -> np.ndarray:
    """log(I + eps) -> linear intensity in [0, 1] (clipped), float32: what a detector or a preview is shown."""
    return np.clip(np.exp(log_images.astype(np.float64)) - eps, 0.0, 1.0).astype(np.float32)


@dataclass(frozen=True)
class Agreement:
    """How well an estimated log image matches the true one up to scale and offset, over ``n_pixels``.

    ``correlation``: Pearson correlation; ``rmse``: RMS of the residual after the least-squares affine fit of the
    estimate to the truth (log units; = std(truth) * sqrt(1 - correlation^2)); ``gradient_correlation``: the
    correlation of their image gradients (what a feature tracker sees), both axes pooled.
    """

    correlation: float
    rmse: float
    gradient_correlation: float
    n_pixels: int


def _corr(a: np.ndarray, b: np.ndarray) -> float:
    a = a - a.mean()
    b = b - b.mean()
    d = float(np.sqrt((a * a).sum() * (b * b).sum()))
    return float((a * b).sum() / d) if d > 0 else 0.0


def agreement(estimate: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None) -> Agreement:
    """Compare one estimated log image with the true log image (both (H, W)) on ``mask`` (default: all pixels)."""
    est = np.asarray(estimate, np.float64)
    tru = np.asarray(truth, np.float64)
    if est.shape != tru.shape or est.ndim != 2:
        raise ValueError(f"agreement: expected two (H, W) images of one shape, got {est.shape} and {tru.shape}")
    m = np.ones(est.shape, bool) if mask is None else np.asarray(mask, bool)
    if m.shape != est.shape:
        raise ValueError(f"agreement: mask shape {m.shape} differs from the images' {est.shape}")
    if m.sum() < 3:
        raise ValueError(f"agreement: the mask holds {int(m.sum())} pixels, need at least 3")
    e, t = est[m], tru[m]
    r = _corr(e, t)
    A = np.stack([e, np.ones_like(e)], axis=1)
    coef, *_ = np.linalg.lstsq(A, t, rcond=None)
    rmse = float(np.sqrt(np.mean((A @ coef - t) ** 2)))
    gx_e, gy_e = np.diff(est, axis=1), np.diff(est, axis=0)
    gx_t, gy_t = np.diff(tru, axis=1), np.diff(tru, axis=0)
    mx, my = m[:, 1:] & m[:, :-1], m[1:] & m[:-1]
    g = _corr(np.concatenate([gx_e[mx], gy_e[my]]), np.concatenate([gx_t[mx], gy_t[my]]))
    return Agreement(correlation=r, rmse=rmse, gradient_correlation=g, n_pixels=int(m.sum()))
