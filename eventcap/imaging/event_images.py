"""Images a detector can look at, made from the events of a short window (for event-only cameras).

A network trained on photographs sees a person in an image made from events only where that image shows the
person's shape. Which image does depends on the recording: a high-pass reconstruction
(:mod:`eventcap.imaging.reconstruct`) keeps the texture of a slow person but smears a fast one; a count of the
events over the last 10-50 ms draws the outline of whatever moved in that window; a time surface weighs each pixel
by how recently it fired. The detect stage tries several and keeps, per image time, the one its network scores best.

Kinds (:func:`parse_kind`): ``reconstruction`` (the image given, unchanged), ``counts:MS`` (events per pixel over
the MS milliseconds before the time, dark on white: the outline drawn as with a pencil), ``surface:MS`` (a time
surface: 1 - exp(-age / (MS/3)) of each pixel's last event within MS ms, dark where it fired last). Every image is
linear intensity in [0, 1], (height, width) float32, as the detectors take them.
"""

from __future__ import annotations

import numpy as np

#: The kinds an image may be (a window in milliseconds follows ``counts`` and ``surface``).
KINDS = ("reconstruction", "counts", "surface")
#: Windows a ``counts`` / ``surface`` image may span, milliseconds.
MIN_WINDOW_MS, MAX_WINDOW_MS = 1, 500


def parse_kind(kind: str) -> tuple[str, int]:
    """``"counts:25"`` -> ``("counts", 25000)`` (window in us); ``"reconstruction"`` -> ``("reconstruction", 0)``."""
    name, _, ms = str(kind).partition(":")
    if name not in KINDS:
        raise ValueError(f"event image {kind!r}: expected one of reconstruction | counts:MS | surface:MS")
    if name == "reconstruction":
        if ms:
            raise ValueError(f"event image {kind!r}: reconstruction takes no window")
        return name, 0
    try:
        window = int(ms)
    except ValueError:
        raise ValueError(f"event image {kind!r}: expected {name}:MS with a window in whole milliseconds "
                         f"({MIN_WINDOW_MS}-{MAX_WINDOW_MS}), e.g. {name}:25") from None
    if not MIN_WINDOW_MS <= window <= MAX_WINDOW_MS:
        raise ValueError(f"event image {kind!r}: the window must lie in [{MIN_WINDOW_MS}, {MAX_WINDOW_MS}] ms")
    return name, window * 1000


def _window(events: np.ndarray, t_us: int, window_us: int) -> np.ndarray:
    a, b = np.searchsorted(events["t"], [int(t_us) - int(window_us), int(t_us)], side="right")
    return events[a:b]


def count_image(events: np.ndarray, t_us: int, window_us: int, height: int, width: int) -> np.ndarray:
    """Events per pixel in (t_us - window_us, t_us], either polarity, dark on white: 1 - counts / (their 95th
    percentile over the pixels that fired), clipped to [0, 1]. A window without events gives a white image."""
    ev = _window(events, t_us, window_us)
    counts = np.bincount(ev["y"].astype(np.int64) * width + ev["x"].astype(np.int64),
                         minlength=height * width).reshape(height, width).astype(np.float32)
    fired = counts[counts > 0]
    scale = max(float(np.percentile(fired, 95)), 1.0) if fired.size else 1.0
    return np.clip(1.0 - counts / scale, 0.0, 1.0).astype(np.float32)


def surface_image(events: np.ndarray, t_us: int, window_us: int, height: int, width: int) -> np.ndarray:
    """A time surface: per pixel, 1 - exp(-age / tau) of its last event within the window (tau a third of it),
    1 (white) where nothing fired: the most recent outline darkest."""
    ev = _window(events, t_us, window_us)
    out = np.ones(height * width, np.float32)
    if ev.size:
        pix = ev["y"].astype(np.int64) * width + ev["x"].astype(np.int64)
        age = (int(t_us) - ev["t"]).astype(np.float64)
        tau = max(window_us / 3.0, 1.0)
        # events are time-ordered: the last write per pixel is its most recent event
        out[pix] = (1.0 - np.exp(-age / tau)).astype(np.float32)
    return out.reshape(height, width)


def event_image(kind: str, events: np.ndarray, t_us: int, height: int, width: int,
                reconstruction: np.ndarray | None = None) -> np.ndarray:
    """The image of one ``kind`` (:func:`parse_kind`) at ``t_us``; ``reconstruction`` is returned for that kind."""
    name, window_us = parse_kind(kind)
    if name == "reconstruction":
        if reconstruction is None:
            raise ValueError("event image 'reconstruction': no reconstructed image given")
        return reconstruction
    if name == "counts":
        return count_image(events, t_us, window_us, height, width)
    return surface_image(events, t_us, window_us, height, width)
