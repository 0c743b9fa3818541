"""Decoded event columns → ``EVENT_DTYPE``, with the checks and repairs shared by every reader.

Policy, the same for every format (the module docstring of :mod:`eventcap.io` says it to users):

- time: integers are taken in the source's unit (µs unless the format or an attribute says otherwise); floats
  are seconds unless told otherwise, must be finite, and are rounded to the nearest µs. 32-bit integer time
  columns that jump back by more than 2³¹ wrapped around: they are unwrapped (+2³² per wrap) and reported.
- coordinates: must be integers ≥ 0 that fit uint16; outside a declared sensor size → :class:`RecordingError`
  naming the first such event (a declared size that events exceed means the size or the column layout is wrong,
  which dropping would hide; crop with ``roi`` to drop events on purpose).
- polarity: bool (on → +1), {0, 1} (0 → -1) or {-1, +1}; one encoding per file; any other value, or both 0
  and -1 in one file → :class:`RecordingError` naming the event.
- order: events out of time order are sorted (stable) and reported; exact duplicates (same t, x, y, p) are
  dropped (the first kept) and reported.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numba
import numpy as np

from eventcap.events import EVENT_DTYPE
from eventcap.io.recording import RecordingError

#: Multipliers from a time unit to microseconds.
TIME_UNITS_TO_US = {"s": 1e6, "ms": 1e3, "us": 1.0, "ns": 1e-3}
_UNIT_ALIASES = {"s": "s", "sec": "s", "second": "s", "seconds": "s", "ms": "ms", "millisecond": "ms",
                 "milliseconds": "ms", "us": "us", "µs": "us", "μs": "us", "microsecond": "us", "microseconds": "us",
                 "ns": "ns", "nanosecond": "ns", "nanoseconds": "ns"}
# Beyond this a time does not survive the conversion to int64 µs with room for offsets.
_MAX_ABS_US = 2**62


def parse_time_unit(value, default: str | None = None) -> str | None:
    """A time-unit name ("s", "ms", "us", "ns" or a spelled-out alias) → its short form; ``None`` → ``default``."""
    if value is None:
        return default
    if isinstance(value, bytes):
        value = value.decode("utf-8", "replace")
    unit = _UNIT_ALIASES.get(str(value).strip().lower())
    if unit is None:
        raise ValueError(f"unknown time unit {value!r}: expected one of 's', 'ms', 'us', 'ns'")
    return unit


def times_to_us(path, t, unit: str | None, what: str, locate: Callable[[int], str], unwrap32=None) -> np.ndarray:
    """Time stamps (any numeric dtype) → int64 µs, or :class:`RecordingError` naming the first bad one.

    ``unit`` ``None`` means seconds for floats and µs for integers. Floats must be finite and are rounded to
    the nearest µs; every result must lie within ±2^62 µs (room for offsets). ``unwrap32`` (int64 → int64) is
    applied to 32-bit integer columns before scaling. ``locate(i)`` names element ``i`` in messages.
    """
    t = np.asarray(t)
    if t.ndim != 1:
        raise RecordingError(path, f"{what}: expected a 1-D array of times, got shape {t.shape}")
    if t.dtype.kind == "f":
        unit = unit or "s"
        t_us = t.astype(np.float64) * TIME_UNITS_TO_US[unit]
        bad = ~np.isfinite(t_us) | (np.abs(t_us) >= _MAX_ABS_US)
        if bad.any():
            i = int(np.argmax(bad))
            raise RecordingError(path, f"{what} {t[i].item()} {unit} is not a finite number within ±2^62 µs",
                                 locate(i))
        return np.rint(t_us).astype(np.int64)
    if t.dtype.kind not in "iu":
        raise RecordingError(path, f"{what}s must be numbers, got dtype {t.dtype}", locate(0))
    unit = unit or "us"
    if t.dtype == np.uint64:
        # Compared unsigned: a negative time written as unsigned shows up here.
        big = t >= np.uint64(_MAX_ABS_US)
        if big.any():
            i = int(np.argmax(big))
            raise RecordingError(path, f"{what} {int(t[i])} is out of range (must be < 2^62 µs; a negative time "
                                       f"stored unsigned?)", locate(i))
    t64 = t.astype(np.int64)
    if unwrap32 is not None and t.dtype.itemsize == 4:
        t64 = unwrap32(t64)
    scale = TIME_UNITS_TO_US[unit]
    limit = _MAX_ABS_US if scale <= 1 else _MAX_ABS_US // int(scale)
    big = (t64 >= limit) | (t64 <= -limit)
    if big.any():
        i = int(np.argmax(big))
        raise RecordingError(path, f"{what} {int(t64[i])} {unit} is out of range (|t| must be < 2^62 µs)", locate(i))
    if unit == "ns":
        return (t64 + 500) // 1000
    return t64 * int(scale) if scale > 1 else t64


@dataclass(frozen=True)
class RawChunk:
    """Event columns of one stretch of a file as its decoder gives them, before conversion.

    ``t``, ``x``, ``y``, ``p`` are (n,) arrays of any numeric or bool dtype; ``row0`` is the index of the first
    of them among all events of the file (in file order); ``locate(row)`` describes where event ``row`` of the
    file is, for error messages ("line 12", "packet 3, event index 4077", ...).
    """

    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    p: np.ndarray
    row0: int
    locate: Callable[[int], str] = field(default=lambda row: f"event index {row}")

    def __len__(self) -> int:
        return len(self.t)


@dataclass
class ColumnConverter:
    """Converts :class:`RawChunk` s of one file, in order, to ``EVENT_DTYPE`` (file time, µs).

    Keeps what must carry over between chunks: the 32-bit wrap offset and the polarity encoding. ``width`` /
    ``height`` are the declared sensor size (``None``: not declared, only uint16 range is checked);
    ``time_unit`` the unit of the time column (floats default to seconds, integers to µs, when ``None``);
    ``t_add_us`` a file-level time offset added after conversion (e.g. DSEC's ``t_offset``).
    """

    path: object
    width: int | None = None
    height: int | None = None
    time_unit: str | None = None
    t_add_us: int = 0
    wraps: int = 0
    first_wrap_row: int | None = None
    _last_t32: int | None = None
    _polarity: str | None = None  # "01" or "pm1" once seen
    _polarity_row: int = -1

    def convert(self, chunk: RawChunk) -> np.ndarray:
        n = len(chunk)
        for name in ("t", "x", "y", "p"):
            shape = np.shape(getattr(chunk, name))
            if shape != (n,):
                raise RecordingError(self.path, f"event column {name} has shape {shape}, expected ({n},) like t",
                                     chunk.locate(chunk.row0))
        out = np.empty(n, dtype=EVENT_DTYPE)
        if n == 0:
            return out
        out["t"] = self._time(chunk)
        if self.t_add_us:
            out["t"] += self.t_add_us
        out["x"] = self._coordinate(chunk, "x", self.width, "width")
        out["y"] = self._coordinate(chunk, "y", self.height, "height")
        out["p"] = self._polarity_column(chunk)
        return out

    # ------------------------------------------------------------------------------------------------ time
    def _time(self, chunk: RawChunk) -> np.ndarray:
        unwrap = (lambda t64: self._unwrap32(t64, chunk.row0))
        return times_to_us(self.path, chunk.t, self.time_unit, "timestamp", lambda i: chunk.locate(chunk.row0 + i),
                           unwrap)

    def _unwrap32(self, t: np.ndarray, row0: int) -> np.ndarray:
        # A 32-bit µs counter wraps every 71.6 min; a step back by more than half its range is a wrap, not
        # disorder (disorder is repaired by sorting later).
        prev = t[0] if self._last_t32 is None else self._last_t32
        wrapped = np.diff(t, prepend=prev) < -(2**31)
        self._last_t32 = int(t[-1])
        out = t + (self.wraps << 32) if self.wraps else t
        if wrapped.any():
            if self.first_wrap_row is None:
                self.first_wrap_row = row0 + int(np.argmax(wrapped))
            out = out + (np.cumsum(wrapped, dtype=np.int64) << 32)
            self.wraps += int(wrapped.sum())
        return out

    # ----------------------------------------------------------------------------------------- coordinates
    def _coordinate(self, chunk: RawChunk, name: str, limit: int | None, size_name: str) -> np.ndarray:
        v = np.asarray(getattr(chunk, name))
        if v.dtype.kind == "f":
            bad = ~np.isfinite(v) | (v != np.floor(v))
            if bad.any():
                i = int(np.argmax(bad))
                raise RecordingError(self.path, f"{name} = {v[i].item()} is not an integer pixel coordinate",
                                     chunk.locate(chunk.row0 + i))
        elif v.dtype.kind not in "iub":
            raise RecordingError(self.path, f"{name} coordinates must be numbers, got dtype {v.dtype}",
                                 chunk.locate(chunk.row0))
        if v.dtype.kind in "if":
            neg = v < 0
            if neg.any():
                i = int(np.argmax(neg))
                raise RecordingError(self.path, f"{name} = {v[i].item()} is negative (pixel coordinates start at 0, "
                                                f"top-left)", chunk.locate(chunk.row0 + i))
        bound = 65536 if limit is None else limit
        over = v >= bound
        if over.any():
            i = int(np.argmax(over))
            what = (f"{name} = {int(v[i])} is outside the sensor ({size_name} {limit}); {int(over.sum())} of "
                    f"{len(v)} events in this stretch are outside" if limit is not None
                    else f"{name} = {v[i].item()} does not fit a 16-bit pixel coordinate")
            raise RecordingError(self.path, what, chunk.locate(chunk.row0 + i))
        return v.astype(np.uint16)

    # -------------------------------------------------------------------------------------------- polarity
    def _polarity_column(self, chunk: RawChunk) -> np.ndarray:
        p = np.asarray(chunk.p)
        if p.dtype == bool:
            return np.where(p, 1, -1).astype(np.int8)
        if p.dtype.kind not in "iuf":
            raise RecordingError(self.path, f"polarity must be numbers or booleans, got dtype {p.dtype}",
                                 chunk.locate(chunk.row0))
        one = p == 1
        zero = p == 0
        minus = p == -1
        bad = ~(one | zero | minus)
        if bad.any():
            i = int(np.argmax(bad))
            raise RecordingError(self.path, f"polarity {p[i].item()} is not one of the encodings {{0, 1}} or {{-1, +1}}",
                                 chunk.locate(chunk.row0 + i))
        for mask, enc, other in ((zero, "01", "pm1"), (minus, "pm1", "01")):
            if mask.any():
                i = int(np.argmax(mask))
                if self._polarity == other:
                    first = {"01": "0", "pm1": "-1"}[other]
                    raise RecordingError(
                        self.path, f"polarity {p[i].item()} mixes encodings: earlier events ({self._locate_pol(chunk)}) "
                                   f"used {first}, so polarity is neither {{0, 1}} nor {{-1, +1}}",
                        chunk.locate(chunk.row0 + i))
                if self._polarity is None:
                    self._polarity = enc
                    self._polarity_row = chunk.row0 + i
        return np.where(one, 1, -1).astype(np.int8)

    def _locate_pol(self, chunk: RawChunk) -> str:
        return chunk.locate(self._polarity_row)

    def repairs(self) -> list[str]:
        """Sentences for the repairs this converter made so far."""
        if not self.wraps:
            return []
        return [(f"unwrapped {self.wraps} wrap-around(s) of the 32-bit timestamp counter (+2^32 µs each; first at "
                 f"event index {self.first_wrap_row})")]


# ------------------------------------------------------------------------------------------------- ordering
@dataclass
class OrderReport:
    """What :func:`sort_and_dedup` did: counts and the first place of each repair (event indices in input order)."""

    backward_steps: int = 0
    first_backward_row: int = -1
    first_backward_t: tuple[int, int] = (0, 0)
    largest_step_back_us: int = 0
    duplicates: int = 0
    first_duplicate_row: int = -1

    def add(self, other: OrderReport, row0: int) -> None:
        if other.backward_steps:
            if not self.backward_steps:
                self.first_backward_row = row0 + other.first_backward_row
                self.first_backward_t = other.first_backward_t
            self.backward_steps += other.backward_steps
            self.largest_step_back_us = max(self.largest_step_back_us, other.largest_step_back_us)
        if other.duplicates:
            if not self.duplicates:
                self.first_duplicate_row = row0 + other.first_duplicate_row
            self.duplicates += other.duplicates

    def repairs(self) -> list[str]:
        out = []
        if self.backward_steps:
            a, b = self.first_backward_t
            out.append(f"sorted events by time: time went backwards at {self.backward_steps} place(s) (first at event "
                       f"index {self.first_backward_row}: {b} µs after {a} µs; largest step back "
                       f"{self.largest_step_back_us} µs)")
        if self.duplicates:
            out.append(f"dropped {self.duplicates} duplicated event(s) (same t, x, y, p as an earlier one; first at "
                       f"event index {self.first_duplicate_row})")
        return out


def _event_key(ev: np.ndarray) -> np.ndarray:
    # x, y < 2^16 and one polarity bit: a unique 33-bit key per (x, y, p).
    return (ev["x"].astype(np.int64) << 17) | (ev["y"].astype(np.int64) << 1) | (ev["p"] > 0)


@numba.njit(cache=True)
def _later_duplicates(t, key):  # pragma: no cover - compiled
    """Mask of events equal (t and key) to an earlier event; ``t`` sorted. Runs of equal t are short in practice
    (pairwise check) but can be long for vectorised sensors (sort within the run)."""
    n = t.shape[0]
    dup = np.zeros(n, dtype=np.bool_)
    a = 0
    while a < n:
        b = a + 1
        while b < n and t[b] == t[a]:
            b += 1
        if b - a > 32:
            order = np.argsort(key[a:b], kind="mergesort")  # stable: the first occurrence sorts first
            for k in range(1, b - a):
                if key[a + order[k]] == key[a + order[k - 1]]:
                    dup[a + order[k]] = True
        elif b - a > 1:
            for i in range(a + 1, b):
                for j in range(a, i):
                    if key[i] == key[j]:
                        dup[i] = True
                        break
        a = b
    return dup


def sort_and_dedup(ev: np.ndarray) -> tuple[np.ndarray, OrderReport]:
    """Stable-sort events by time and drop exact duplicates (keeping the first); report what changed.

    ``ev`` is ``EVENT_DTYPE``; the returned array is ``ev`` itself when nothing changed. Row numbers in the
    report are indices in the input order.
    """
    report = OrderReport()
    n = len(ev)
    if n < 2:
        return ev, report
    t = ev["t"]
    back = np.flatnonzero(t[1:] < t[:-1])
    order = None
    if back.size:
        i = int(back[0])
        report.backward_steps = int(back.size)
        report.first_backward_row = i + 1
        report.first_backward_t = (int(t[i]), int(t[i + 1]))
        report.largest_step_back_us = int(np.max(t[back] - t[back + 1]))
        order = np.argsort(t, kind="stable")
        ev = ev[order]
        t = ev["t"]
    if np.any(t[1:] == t[:-1]):
        dup = _later_duplicates(t, _event_key(ev))
        if dup.any():
            report.duplicates = int(dup.sum())
            first = int(np.argmax(dup))
            report.first_duplicate_row = int(order[first]) if order is not None else first
            ev = ev[~dup]
    return ev, report
