"""Event-based Double Integral (EDI, Pan et al. 2019; paper Sec. 3.1, Eq. 2): sharp latent log images from a
motion-blurred intensity frame and the events during its exposure.

Model (per pixel, natural-log units). The sensor's latent log intensity is ``L(t) = L(t_ref) + c·E(t)`` with
``E(t)`` the signed event count between ``t_ref`` and ``t``: ``+sum p`` over events in ``(t_ref, t]`` for
``t > t_ref`` and ``-sum p`` over events in ``(t, t_ref]`` for ``t < t_ref``. The frame is the exposure average
of the linear latent image (Eq. 1), ``B = (1/T) ∫ exp(L(t)) dt``, so

    L(t_ref) = log(B) - log((1/T) ∫ exp(c·E(t)) dt)                                   (Eq. 2)

``E`` is piecewise constant (it jumps at the pixel's events), so the integral is an exact finite sum over the
intervals between consecutive events of a pixel. A pixel without events in the exposure gets ``L = log(B)``.

Log convention: ``L = log(I + eps)`` with ``I`` the linear intensity in [0, 1] (``eps`` = 1e-3 as in the event
simulator and v2e/ESIM): events measure changes of ``log(I + eps)``, so the blurry frame enters as
``log(B + eps)`` and the linear latent image is ``exp(L) - eps``. Frames are linear (8-bit DN / 255 for uint8).

Exposure windows follow the project's frame convention: a frame centred at ``t_us`` with exposure ``T`` is
exposed over ``[t_us - T//2, t_us - T//2 + T]`` (:func:`exposure_window`).

The contrast threshold ``c`` is unknown for a real sensor; :func:`estimate_contrast` picks one ``c`` per
recording (several frames jointly, so the result does not flicker from frame to frame) by a 1-D search that
minimises the disagreement of consecutive EDI results: the sharp image of frame k, carried forward by the events
to frame k+1 (``L_k + c·E``), must equal the sharp image of frame k+1. Why not a sharpness prior: on our synthetic scenes the total variation of the EDI image
grows monotonically with c (a blurred ramp has the same TV as a sharp step, while event quantisation adds texture
in proportion to c), and TV with an event-edge agreement term (the EDI authors' energy) put its minimum far from
the true c (docs/results/implementation.md). The consistency energy's minimum
is the contrast that best explains the data; where the sensor lost events (refractory period at fast,
high-contrast edges) that is the *effective* threshold, larger than the nominal one.
"""

from __future__ import annotations

import math
import operator
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numba
import numpy as np

from eventcap.events import EVENT_DTYPE

#: Default offset of the log: L = log(I + eps), as the simulator (SensorConfig.log_eps) and v2e/ESIM.
DEFAULT_LOG_EPS = 1e-3


# --------------------------------------------------------------------------------------------------------------
# input checks


def _as_int(what: str, value: object) -> int:
    try:
        return operator.index(value)  # type: ignore[arg-type]
    except TypeError:
        raise ValueError(f"{what}: expected an integer (µs), got {value!r}") from None


def _check_events(events: np.ndarray, height: int, width: int) -> np.ndarray:
    if not isinstance(events, np.ndarray) or events.dtype != EVENT_DTYPE or events.ndim != 1:
        got = f"{type(events).__name__} {getattr(events, 'dtype', '')} {getattr(events, 'shape', '')}"
        raise ValueError(f"events: expected a 1-D numpy array of eventcap.events.EVENT_DTYPE, got {got}")
    if events.size:
        t = events["t"]
        if t.size > 1 and np.any(t[1:] < t[:-1]):
            i = int(np.argmax(t[1:] < t[:-1])) + 1
            raise ValueError(f"events: expected sorted by time, but row {i} ({t[i]} µs) is before row {i - 1}")
        if int(events["x"].max()) >= width or int(events["y"].max()) >= height:
            raise ValueError(
                f"events: expected pixels inside the {width}x{height} (width x height) image, got x up to "
                f"{int(events['x'].max())}, y up to {int(events['y'].max())}"
            )
    return events


def _check_size(height: int, width: int) -> tuple[int, int]:
    h, w = _as_int("height", height), _as_int("width", width)
    if h < 1 or w < 1:
        raise ValueError(f"image size: expected height, width >= 1, got height={h}, width={w}")
    return h, w


def _contrast_map(C: float | np.ndarray, height: int, width: int) -> np.ndarray:
    """C as a flat (height*width,) float64 array: a scalar or a per-pixel (height, width) map of thresholds."""
    c = np.asarray(C, dtype=np.float64)
    if c.ndim == 0:
        if not (math.isfinite(float(c)) and float(c) > 0):
            raise ValueError(f"C: expected a contrast threshold > 0 (log units), got {float(c)!r}")
        return np.full(height * width, float(c))
    if c.shape != (height, width):
        raise ValueError(f"C: expected a scalar or a (height, width) = ({height}, {width}) map, got shape {c.shape}")
    if not np.all(np.isfinite(c) & (c > 0)):
        raise ValueError("C: expected every per-pixel contrast threshold finite and > 0")
    return c.ravel()


def frame_to_linear(image: np.ndarray) -> np.ndarray:
    """A frame as float64 linear intensity in [0, 1]: uint8 DN / 255, floats checked to lie in [0, 1]. (H, W)."""
    img = np.asarray(image)
    if img.ndim != 2:
        raise ValueError(f"blurry frame: expected a 2-D (height, width) image, got shape {img.shape}")
    if img.dtype == np.uint8:
        return img.astype(np.float64) / 255.0
    if not np.issubdtype(img.dtype, np.floating):
        raise ValueError(f"blurry frame: expected uint8 DN or float linear intensity in [0, 1], got dtype {img.dtype}")
    out = img.astype(np.float64)
    lo, hi = float(np.min(out)), float(np.max(out))
    if not (lo >= 0.0 and hi <= 1.0):  # also catches NaN
        raise ValueError(f"blurry frame: expected float linear intensity in [0, 1], got values in [{lo}, {hi}]")
    return out


def exposure_window(t_us: int, exposure_us: int) -> tuple[int, int]:
    """(start, end) µs of the exposure of a frame centred at ``t_us`` (the frame convention of eventcap.sim)."""
    t, T = _as_int("t_us", t_us), _as_int("exposure_us", exposure_us)
    if T < 1:
        raise ValueError(f"exposure_us: expected >= 1 µs, got {T}")
    start = t - T // 2
    return start, start + T


def to_linear(log_image: np.ndarray, eps: float = DEFAULT_LOG_EPS) -> np.ndarray:
    """Linear intensity ``exp(L) - eps`` of a log image, clipped to [0, 1] (the frame's range). Same shape, float32."""
    return np.clip(np.exp(np.asarray(log_image, np.float64)) - eps, 0.0, 1.0).astype(np.float32)


# --------------------------------------------------------------------------------------------------------------
# event sums


def _signed_sum(events: np.ndarray, a_us: int, b_us: int, n_pix: int, width: int) -> np.ndarray:
    """Per pixel (n_pix,) float64: E between a and b, i.e. +sum p over (a, b] if b >= a, else -sum p over (b, a]."""
    lo, hi, sign = (a_us, b_us, 1.0) if b_us >= a_us else (b_us, a_us, -1.0)
    i0, i1 = np.searchsorted(events["t"], [lo, hi], side="right")
    ev = events[i0:i1]
    pix = ev["y"].astype(np.int64) * width + ev["x"]
    return sign * np.bincount(pix, weights=ev["p"].astype(np.float64), minlength=n_pix)


@numba.njit(cache=True, nogil=True)
def _exposure_integral_kernel(t, pix, pol, c_flat, t_start, t_end):
    """Per pixel ∫_{t_start}^{t_end} exp(c·(S(t) - S(t_start))) dt (µs), S the running event sum.

    t, pix, pol: the events in (t_start, t_end], time-sorted. One pass over the events with per-pixel state.
    """
    n_pix = c_flat.size
    level = np.zeros(n_pix)  # c · (S(t) - S(t_start)) since the last event of the pixel
    last = np.full(n_pix, t_start, np.int64)
    acc = np.zeros(n_pix)
    for k in range(t.size):
        i = pix[k]
        acc[i] += math.exp(level[i]) * (t[k] - last[i])
        level[i] += pol[k] * c_flat[i]
        last[i] = t[k]
    for i in range(n_pix):
        acc[i] += math.exp(level[i]) * (t_end - last[i])
    return acc


# --------------------------------------------------------------------------------------------------------------
# EDI


def latent_log_image(
    blurry: np.ndarray,
    events: np.ndarray,
    t_ref_us: int,
    exposure: tuple[int, int],
    C: float | np.ndarray,
    height: int,
    width: int,
    eps: float = DEFAULT_LOG_EPS,
) -> np.ndarray:
    """The sharp latent log image ``L(t_ref)`` of a blurry frame by EDI (Eq. 2). Returns (height, width) float32.

    blurry: (height, width) linear frame, uint8 DN or float in [0, 1]. events: ``EVENT_DTYPE``, time-sorted; any
    superset of the exposure (only those in ``(t_start, t_end]`` and between the exposure and ``t_ref`` are used).
    exposure: ``(t_start_us, t_end_us)``. C: contrast threshold (log units), scalar or a (height, width) map.
    eps: the log offset, ``L = log(I + eps)``.
    """
    height, width = _check_size(height, width)
    b = frame_to_linear(blurry)
    if b.shape != (height, width):
        raise ValueError(f"blurry frame: expected shape (height, width) = ({height}, {width}), got {b.shape}")
    if len(exposure) != 2:
        raise ValueError(f"exposure: expected (t_start_us, t_end_us), got {exposure!r}")
    t_start, t_end = (_as_int("exposure start", exposure[0]), _as_int("exposure end", exposure[1]))
    if t_end <= t_start:
        raise ValueError(f"exposure: expected (t_start_us, t_end_us) with t_end > t_start, got {exposure!r}")
    t_ref = _as_int("t_ref_us", t_ref_us)
    if not (math.isfinite(eps) and eps > 0):
        raise ValueError(f"eps: expected a log offset > 0, got {eps!r}")
    _check_events(events, height, width)
    n_pix = height * width
    c_flat = _contrast_map(C, height, width)

    i0, i1 = np.searchsorted(events["t"], [t_start, t_end], side="right")
    ev = events[i0:i1]
    pix = ev["y"].astype(np.int64) * width + ev["x"]
    acc = _exposure_integral_kernel(ev["t"], pix, ev["p"].astype(np.float64), c_flat, t_start, t_end)
    # E(t) = (S(t) - S(t_start)) - (S(t_ref) - S(t_start)): shift the integral by the events up to t_ref
    shift = c_flat * _signed_sum(events, t_start, t_ref, n_pix, width)
    log_mean = np.log(acc / (t_end - t_start)) - shift
    return (np.log(b.ravel() + eps) - log_mean).reshape(height, width).astype(np.float32)


def latent_log_sequence(
    L_ref: np.ndarray, t_ref_us: int, times_us: Sequence[int] | np.ndarray, events: np.ndarray, C: float | np.ndarray
) -> np.ndarray:
    """Latent log images at many times from one at ``t_ref_us``: ``L(t) = L(t_ref) + c·E(t)``. (M, H, W) float32.

    L_ref: (height, width) log image at t_ref_us (e.g. from :func:`latent_log_image`); times_us: (M,) int µs in
    any order (e.g. every 1 ms over a batch), before or after t_ref; events: ``EVENT_DTYPE``, time-sorted,
    covering the span between t_ref and the times. All M images are accumulated in one pass over the events;
    working memory is about 3·M·H·W float64 (30 MB for 41 images at 240x180): split very long lists of times.
    """
    L_ref = np.asarray(L_ref)
    if L_ref.ndim != 2:
        raise ValueError(f"L_ref: expected a (height, width) log image, got shape {L_ref.shape}")
    height, width = L_ref.shape
    t_ref = _as_int("t_ref_us", t_ref_us)
    times = np.asarray(times_us)
    if times.ndim != 1 or not (times.size == 0 or np.issubdtype(times.dtype, np.integer)):
        raise ValueError(f"times_us: expected a 1-D array of integer µs, got shape {times.shape} dtype {times.dtype}")
    _check_events(events, height, width)
    c_flat = _contrast_map(C, height, width)
    n_pix = height * width
    if times.size == 0:
        return np.empty((0, height, width), np.float32)

    # running signed sum S at the sorted breakpoints (the query times and t_ref), relative to the first one
    points = np.unique(np.append(times.astype(np.int64), t_ref))
    i0, i1 = np.searchsorted(events["t"], [points[0], points[-1]], side="right")
    ev = events[i0:i1]
    segment = np.searchsorted(points, ev["t"], side="left") - 1  # event in (points[j], points[j+1]] -> j
    pix = ev["y"].astype(np.int64) * width + ev["x"]
    steps = np.bincount(
        segment * n_pix + pix, weights=ev["p"].astype(np.float64), minlength=(points.size - 1) * n_pix
    ).reshape(points.size - 1, n_pix)
    running = np.zeros((points.size, n_pix))
    np.cumsum(steps, axis=0, out=running[1:])
    at = np.searchsorted(points, times)
    e = running[at] - running[np.searchsorted(points, t_ref)]
    out = L_ref.ravel().astype(np.float64) + e * c_flat
    return out.reshape(times.size, height, width).astype(np.float32)


def latent_log_at(L_ref: np.ndarray, t_ref_us: int, t_us: int, events: np.ndarray, C: float | np.ndarray) -> np.ndarray:
    """The latent log image at ``t_us`` from the one at ``t_ref_us``: ``L(t_ref) + c·E(t)``. (H, W) float32."""
    return latent_log_sequence(L_ref, t_ref_us, np.array([_as_int("t_us", t_us)]), events, C)[0]


def sharpen_frames(
    images: np.ndarray,
    t_us: np.ndarray,
    exposure_us: np.ndarray | int,
    events: np.ndarray,
    C: float | np.ndarray,
    eps: float = DEFAULT_LOG_EPS,
) -> np.ndarray:
    """EDI latent log images at the exposure centres of a stack of frames. (K, H, W) float32.

    images: (K, H, W) uint8 or float linear; t_us: (K,) exposure centres; exposure_us: (K,) or one value.
    """
    images, t_us, exposure_us = _check_frames(images, t_us, exposure_us)
    k, height, width = images.shape
    out = np.empty((k, height, width), np.float32)
    for i in range(k):
        window = exposure_window(int(t_us[i]), int(exposure_us[i]))
        out[i] = latent_log_image(images[i], events, int(t_us[i]), window, C, height, width, eps)
    return out


def _check_frames(images, t_us, exposure_us) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    images = np.asarray(images)
    if images.ndim != 3 or images.shape[0] < 1:
        raise ValueError(f"images: expected a (K, height, width) stack with K >= 1, got shape {images.shape}")
    k = images.shape[0]
    t_us = np.asarray(t_us)
    if t_us.shape != (k,) or not np.issubdtype(t_us.dtype, np.integer):
        raise ValueError(f"t_us: expected ({k},) integer exposure centres in µs, got {t_us.shape} {t_us.dtype}")
    exposure_us = (
        np.broadcast_to(np.asarray(exposure_us), (k,)) if np.ndim(exposure_us) == 0 else np.asarray(exposure_us)
    )
    if exposure_us.shape != (k,) or not np.issubdtype(exposure_us.dtype, np.integer) or np.any(exposure_us < 1):
        raise ValueError(f"exposure_us: expected ({k},) integer µs >= 1 (or one value), got {exposure_us!r}")
    return images, t_us, exposure_us


# --------------------------------------------------------------------------------------------------------------
# contrast estimation


@dataclass(frozen=True)
class ContrastEstimate:
    """Result of :func:`estimate_contrast`: the chosen threshold and the energy curve it came from."""

    c: float  # chosen contrast threshold, natural-log units
    energy_at_c: float  # consistency energy at c (mean |log residual| over the used pixels)
    grid: np.ndarray  # (G,) float64 thresholds of the coarse search
    energy: np.ndarray  # (G,) float64 energy at each grid value
    n_pixels: int  # (frame pair, pixel) residuals the energy averages over

    @property
    def at_range_edge(self) -> bool:
        """The grid's best value is its first or last point: the minimum may lie outside the search range."""
        j = int(np.argmin(self.energy))
        return j in (0, self.energy.size - 1)


class _ExposureEvents:
    """The c-independent part of EDI for one frame: its exposure's events as (t, pixel, polarity) arrays and the
    signed event count between exposure start and the reference time, so EDI at a new c is one kernel call."""

    def __init__(self, blurry, events, t_ref, window, height, width, eps):
        t_start, t_end = window
        i0, i1 = np.searchsorted(events["t"], [t_start, t_end], side="right")
        ev = events[i0:i1]
        self.t = ev["t"]
        self.pix = ev["y"].astype(np.int64) * width + ev["x"]
        self.pol = ev["p"].astype(np.float64)
        self.window = (t_start, t_end)
        # per pixel only the signed counts, as int32 (integers: exact); the log image is made again at each c from
        # the frame itself: a recording's frames held 24 bytes a pixel each, 1.5 GB a minute at 240x180, 25 fps
        self.count_to_ref = _signed_sum(events, t_start, t_ref, height * width, width).astype(np.int32)
        self.blurry, self.eps = blurry, eps

    def latent(self, c: float) -> np.ndarray:
        log_b = np.log(frame_to_linear(self.blurry).ravel() + self.eps)
        c_flat = np.full(log_b.size, c)
        acc = _exposure_integral_kernel(self.t, self.pix, self.pol, c_flat, *self.window)
        return log_b - np.log(acc / (self.window[1] - self.window[0])) + c * self.count_to_ref.astype(np.float64)


def estimate_contrast(
    images: np.ndarray,
    t_us: np.ndarray,
    exposure_us: np.ndarray | int,
    events: np.ndarray,
    *,
    c_range: tuple[float, float] = (0.05, 0.5),
    n_grid: int = 19,
    tol: float = 1e-3,
    min_events: int = 2,
    max_opposite_fraction: float = 0.1,
    eps: float = DEFAULT_LOG_EPS,
) -> ContrastEstimate:
    """One contrast threshold for a recording from several of its frames jointly (1-D search).

    Energy(c) = mean of ``|L_{k+1}(c) - L_k(c) - c·E_k|`` (log units) over consecutive frame pairs (k, k+1) and
    their informative pixels, with ``L_k(c)`` the EDI image at frame k's centre and ``E_k`` the signed event count
    from t_k to t_{k+1}. A pixel is informative when ``|E_k| >= min_events`` (single events carry little on c,
    and excluding them keeps background noise from pulling c down) and at most ``max_opposite_fraction`` of its
    events in the pair have the minority polarity: a pixel that went up and down many times has a net count
    dominated by the mismatch of its ON and OFF thresholds, not by c (with them, even the exact log images give too
    small a c: docs/results/implementation.md). The search evaluates an
    ``n_grid`` grid over ``c_range`` and refines the best bracket by golden-section search to ``tol``.

    images: (K, H, W) uint8 or float linear, K >= 2; t_us: (K,) increasing exposure centres; exposure_us: (K,)
    or one value; events: ``EVENT_DTYPE``, time-sorted, covering the exposures and the gaps between them.
    """
    images, t_us, exposure_us = _check_frames(images, t_us, exposure_us)
    k, height, width = images.shape
    if k < 2:
        raise ValueError(f"estimate_contrast: expected at least 2 frames (consecutive pairs are compared), got {k}")
    if np.any(np.diff(t_us) <= 0):
        raise ValueError(f"estimate_contrast: expected increasing frame times t_us, got {t_us.tolist()}")
    c_lo, c_hi = (float(c_range[0]), float(c_range[1]))
    if not (0 < c_lo < c_hi and math.isfinite(c_hi)):
        raise ValueError(f"c_range: expected 0 < low < high, got {c_range!r}")
    if _as_int("n_grid", n_grid) < 3:
        raise ValueError(f"n_grid: expected >= 3 grid points, got {n_grid}")
    if not 0.0 <= max_opposite_fraction <= 0.5:
        raise ValueError(f"max_opposite_fraction: expected a fraction in [0, 0.5], got {max_opposite_fraction!r}")
    if not (tol > 0):
        raise ValueError(f"tol: expected > 0, got {tol!r}")
    _check_events(events, height, width)
    n_pix = height * width

    frames = [
        _ExposureEvents(images[i], events, int(t_us[i]), exposure_window(int(t_us[i]), int(exposure_us[i])),
                        height, width, eps)
        for i in range(k)
    ]  # fmt: skip
    pairs = []
    for i in range(k - 1):
        i0, i1 = np.searchsorted(events["t"], [t_us[i], t_us[i + 1]], side="right")
        pix = events["y"][i0:i1].astype(np.int64) * width + events["x"][i0:i1]
        net = np.bincount(pix, weights=events["p"][i0:i1].astype(np.float64), minlength=n_pix)
        total = np.bincount(pix, minlength=n_pix)
        opposite = (total - np.abs(net)) / 2
        used = np.flatnonzero((np.abs(net) >= min_events) & (opposite <= max_opposite_fraction * total))
        pairs.append((i, used, net[used]))
    n_used = int(sum(p[1].size for p in pairs))
    if n_used == 0:
        raise ValueError(
            f"estimate_contrast: no pixel has >= {min_events} net events of mostly one polarity between "
            "consecutive frames; the contrast cannot be estimated from a static scene"
        )

    def energy(c: float) -> float:
        # two latent images at a time, each made once (all K at once grew with the recording: 0.5 GB a minute)
        total, prev = 0.0, frames[0].latent(c)
        for i, used, count in pairs:
            nxt = frames[i + 1].latent(c)
            total += float(np.abs(nxt[used] - prev[used] - c * count).sum())
            prev = nxt
        return total / n_used

    grid = np.linspace(c_lo, c_hi, int(n_grid))
    values = np.array([energy(c) for c in grid])
    j = int(np.argmin(values))
    c_best, e_best = _golden_section(energy, grid[max(j - 1, 0)], grid[min(j + 1, grid.size - 1)], tol)
    if values[j] < e_best:  # the grid point itself (e.g. at the range's edge) beats the bracket's interior
        c_best, e_best = float(grid[j]), float(values[j])
    return ContrastEstimate(c_best, e_best, grid, values, n_used)


def _golden_section(f: Callable[[float], float], a: float, b: float, tol: float) -> tuple[float, float]:
    """Minimum of a unimodal f on [a, b] to within tol: (argmin, f(argmin))."""
    ratio = (math.sqrt(5.0) - 1.0) / 2.0
    x1, x2 = b - ratio * (b - a), a + ratio * (b - a)
    f1, f2 = f(x1), f(x2)
    while b - a > tol:
        if f1 <= f2:
            b, x2, f2 = x2, x1, f1
            x1 = b - ratio * (b - a)
            f1 = f(x1)
        else:
            a, x1, f1 = x1, x2, f2
            x2 = a + ratio * (b - a)
            f2 = f(x2)
    return (x1, f1) if f1 <= f2 else (x2, f2)
