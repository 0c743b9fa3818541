"""The project's one event representation (every reader converts to it) and small helpers around it."""

from __future__ import annotations

import numpy as np

#: Every event in the project: time in integer microseconds, pixel (origin top-left), polarity in {-1, +1}.
EVENT_DTYPE = np.dtype([("t", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "i1")])


def make_events(t, x, y, p) -> np.ndarray:
    """Pack column arrays into an array of ``EVENT_DTYPE`` (copying, with range checks on the casts)."""
    t = np.asarray(t)
    n = t.shape[0]
    out = np.empty(n, dtype=EVENT_DTYPE)
    for name, col in (("t", t), ("x", x), ("y", y), ("p", p)):
        col = np.asarray(col)
        if col.shape != (n,):
            raise ValueError(f"event column {name!r}: expected shape ({n},), got {col.shape}")
        out[name] = col
    return out


def empty_events() -> np.ndarray:
    """A zero-length event array."""
    return np.empty(0, dtype=EVENT_DTYPE)
