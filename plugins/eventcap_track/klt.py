"""Frame-based baseline for the event tracker: pyramidal Lucas-Kanade on latent images every 1 ms (``klt_latent``).

This is the naive alternative EventCap argues against (paper Sec. 1): turn the events back into dense images at the
tracking rate -- latent log images ``L(t) = L(t_k) + E(t)`` at every millisecond, as EDI gives them -- and run a
classical frame tracker on them. It tracks the same corners as EKLT (``eklt.detect_features``) and returns the same
:class:`~eventcap_track.eklt.FeatureTracks` layout (one sample per latent frame), so the two can be scored alike
and stitched alike (``eklt.stitch``).

Latent images are log intensities; OpenCV's LK needs 8-bit images, so every frame of a run is mapped to 0..255
with one linear map (fixed from the start image's 0.5-99.5 % range, widened by a quarter on each side so that
brightening and darkening stay representable) -- brightness constancy between frames is preserved.
"""

from __future__ import annotations

import math
import operator
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from .eklt import (
    KIND_BACKWARD,
    KIND_FORWARD,
    EkltConfig,
    FeatureTracks,
    _check_features,
    _check_log_image,
    _check_mask,
    _from_samples,
    detect_features,
    log_to_uint8,
)


@dataclass(frozen=True)
class KltConfig:
    """Parameters of pyramidal Lucas-Kanade (``cv2.calcOpticalFlowPyrLK``) on latent frames."""

    # Side of the square LK window, px (OpenCV's default is 21).
    window_px: int = 21
    # Pyramid levels above the full resolution; 3 handles ~8x the window's reach, far more than 1 ms of motion.
    max_level: int = 3
    # Iterations and step size at which LK stops refining a level.
    max_iterations: int = 30
    epsilon: float = 0.01
    # Drop a feature whose window's minimum eigenvalue (normalised by the window area) falls below this
    # (OpenCV's default 1e-4): a textureless window cannot be tracked.
    min_eig_threshold: float = 1e-4
    # Drop a feature whose LK residual (mean absolute 8-bit difference over the window) exceeds this.
    max_error: float = 30.0

    def __post_init__(self) -> None:
        if not (isinstance(self.window_px, int) and self.window_px >= 3):
            raise ValueError(f"KltConfig.window_px: expected an integer >= 3, got {self.window_px!r}")
        for name in ("max_level", "max_iterations"):
            v = getattr(self, name)
            if not (isinstance(v, int) and v >= (0 if name == "max_level" else 1)):
                raise ValueError(f"KltConfig.{name}: expected a non-negative integer, got {v!r}")
        for name in ("epsilon", "min_eig_threshold", "max_error"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"KltConfig.{name}: expected a finite number > 0, got {v!r}")


def _frame_getter(latent_log, n_frames: int) -> Callable[[int, int], np.ndarray]:
    """A function (index, t_us) -> (H, W) log image over either a callable or an (n, H, W) stack."""
    if callable(latent_log):
        return lambda i, t: _check_log_image(f"latent_log({t})", latent_log(t))
    stack = np.asarray(latent_log)
    if stack.ndim != 3:
        raise ValueError(f"latent_log: expected a callable t_us -> (height, width) or an (n, height, width) array, "
                         f"got an array of shape {stack.shape}")
    if stack.shape[0] < n_frames:
        raise ValueError(f"latent_log: expected at least {n_frames} frames (one per step over the interval), got "
                         f"{stack.shape[0]}")
    return lambda i, t: _check_log_image(f"latent_log[{i}]", stack[i])


def klt_latent(
    latent_log,
    t_start_us: int,
    t_end_us: int,
    step_us: int = 1000,
    direction: int = +1,
    config: KltConfig = KltConfig(),
    *,
    features=None,
    mask=None,
    detector: EkltConfig = EkltConfig(),
) -> FeatureTracks:
    """Track features with pyramidal LK through latent log images at ``t_start_us + i * step_us``.

    latent_log: a callable ``t_us -> (height, width)`` log image, or an (n, height, width) array whose frame i is
    at ``t_start_us + i * step_us`` (n >= (t_end_us - t_start_us) // step_us + 1). Frames are read at every step
    up to ``t_end_us`` (and at ``t_end_us`` itself when the interval is not a multiple of the step, callables
    only). direction=+1 starts on the first frame, -1 on the last and runs back in time. features: (K, 2) (x, y)
    px on the start frame; default ``eklt.detect_features(start frame, mask, detector)``.
    Returns FeatureTracks (one sample per frame while a feature is tracked; cost = LK residual / 255).
    """
    try:
        t0, t1, step = operator.index(t_start_us), operator.index(t_end_us), operator.index(step_us)
    except TypeError:
        raise ValueError(f"t_start_us, t_end_us, step_us: expected integers (µs), got {t_start_us!r}, "
                         f"{t_end_us!r}, {step_us!r}") from None
    if t1 <= t0 or step < 1:
        raise ValueError(f"expected t_end_us > t_start_us and step_us >= 1, got {t0}, {t1}, {step}")
    if direction not in (1, -1):
        raise ValueError(f"direction: expected +1 (forward) or -1 (backward), got {direction!r}")
    times = list(range(t0, t1 + 1, step))
    if times[-1] != t1 and callable(latent_log):
        times.append(t1)
    get = _frame_getter(latent_log, len(times))
    order = list(range(len(times))) if direction == 1 else list(range(len(times) - 1, -1, -1))
    first = get(order[0], times[order[0]])
    height, width = first.shape
    if features is None:
        feats = detect_features(first, _check_mask(mask, height, width), detector)
    else:
        feats = _check_features(features, height, width)
    n = feats.shape[0]
    lo, hi = np.percentile(first, [0.5, 99.5])
    pad = 0.25 * max(hi - lo, 1e-6)
    lo, hi = lo - pad, hi + pad
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, config.max_iterations, config.epsilon)
    ks = [np.arange(n, dtype=np.int32)]
    ts = [np.full(n, times[order[0]], np.int64)]
    xs, ys, cs = [feats[:, 0].copy()], [feats[:, 1].copy()], [np.zeros(n)]
    alive = np.ones(n, bool)
    pos = feats.astype(np.float32).reshape(-1, 1, 2)
    prev = log_to_uint8(first, lo, hi)
    for i in order[1:]:
        if not alive.any():
            break
        img = get(i, times[i])
        if img.shape != (height, width):
            raise ValueError(f"latent frame at t={times[i]} µs: expected shape ({height}, {width}), got {img.shape}")
        cur = log_to_uint8(img, lo, hi)
        idx = np.flatnonzero(alive)
        nxt, status, err = cv2.calcOpticalFlowPyrLK(
            prev, cur, pos[idx], None, winSize=(config.window_px, config.window_px), maxLevel=config.max_level,
            criteria=criteria, minEigThreshold=config.min_eig_threshold,
        )
        nxt = nxt.reshape(-1, 2)
        err = err.ravel()
        ok = (status.ravel() == 1) & np.all(np.isfinite(nxt), axis=1) & (err <= config.max_error)
        ok &= (nxt[:, 0] >= 0) & (nxt[:, 0] <= width - 1) & (nxt[:, 1] >= 0) & (nxt[:, 1] <= height - 1)
        alive[idx[~ok]] = False
        good = idx[ok]
        pos[good, 0] = nxt[ok]
        ks.append(good.astype(np.int32))
        ts.append(np.full(good.size, times[i], np.int64))
        xs.append(nxt[ok, 0].astype(np.float64))
        ys.append(nxt[ok, 1].astype(np.float64))
        cs.append(err[ok] / 255.0)
        prev = cur
    kind = np.full(n, KIND_FORWARD if direction == 1 else KIND_BACKWARD, np.int8)
    cat = np.concatenate
    return _from_samples(cat(ks), cat(ts), cat(xs), cat(ys), cat(cs).astype(np.float32), kind, alive, height, width)
