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
            raise RecordingError(path, f"{what} {t[i].item()} {unit} is not a finite number within ±2^62 µs (the "
                                       f"column is taken as {unit}; if it is in another unit, set source.time_unit)",
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
    #: whether every time value so far was a whole number, and the unit they were taken in (for the rate check)
    time_integral: bool = True
    unit_used: str | None = None
    #: the unit of the time column is a guess (an array or text format without one): checked on the first events
    unit_guessed: bool = False
    _first: list = field(default_factory=list)
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
        out = times_to_us(self.path, chunk.t, self.time_unit, "timestamp", lambda i: chunk.locate(chunk.row0 + i),
                          unwrap)
        t = np.asarray(chunk.t)
        floating = t.dtype.kind == "f"
        self.unit_used = self.time_unit or ("s" if floating else "us")
        if floating and self.time_integral:
            self.time_integral = bool(np.all(t == np.floor(t)))
        if self.unit_guessed and len(out):
            # the unit is checked on the first events, before the time checks: a wrong one makes every gap a jump
            self._first.append(out[:MIN_EVENTS_FOR_RATE * 10])
            first = np.concatenate(self._first)
            if len(first) >= MIN_EVENTS_FOR_RATE:
                if self.time_integral:
                    check_time_unit(self.path, first, self.unit_used)
                self.unit_guessed, self._first = False, []
        return out

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


# ------------------------------------------------------------------------------------------------------ time
#: Neighbouring events (in file order) further apart than this are a jump in time: checked, never taken silently.
#: Event cameras stream continuously (noise alone makes events every second), so a longer silence is a corrupted
#: or spliced file; ``max_gap_s`` (source.max_gap_s, --max-gap-s) accepts longer pauses.
MAX_GAP_US = 60_000_000
#: At most this many events cut off from the rest by jumps in time are dropped as outliers (and named).
TIME_OUTLIER_BUDGET = 100
#: A few events are also cut off from the rest by a jump longer than JUMP_FACTOR times the median gap between the
#: JUMP_WINDOW events before it (and longer than JUMP_MIN_US): a corrupted time word moves a handful of events far
#: from their neighbours. Such a jump with many events after it is a pause, and kept.
JUMP_FACTOR = 10_000
JUMP_WINDOW = 64
JUMP_MIN_US = 1_000_000
#: At most this many of the first events are dropped for lying far from the others (before a pace is known).
HEAD_OUTLIERS = 8
#: The fastest event sensors read out about 1-2 G events/s; more than this many events per µs no sensor makes.
MAX_EVENTS_PER_US = 2_000
#: Below this mean rate no event camera records (background noise alone gives more): with an integer time column
#: whose unit was not given, the unit is wrong (checked over at least MIN_EVENTS_FOR_RATE events).
MIN_EVENT_RATE_HZ = 1.0
MIN_EVENTS_FOR_RATE = 100
#: Time counters whose wrap-around a decoder adds when a corrupted word makes time go backwards: a jump of about
#: one is the decoder's, not the camera's. Each reader declares its own (``ReaderSpec.wraps_us``,
#: :mod:`eventcap.io.registry`); the readers hand them to :class:`TimeGuard`.


def check_event_rate(path, n: int, span_us: int) -> None:
    """Refuse a recording whose events come faster than any sensor makes them (``n`` events in ``span_us`` + 1 µs:
    a broken time column)."""
    if n > MAX_EVENTS_PER_US and n / (span_us + 1) > MAX_EVENTS_PER_US:
        raise RecordingError(path, f"{n:,} events within {_span_words(span_us + 1)}: {n / (span_us + 1):.3g} events per "
                                   f"µs, more than any event sensor makes (at most {MAX_EVENTS_PER_US:,}): the time "
                                   f"column is broken (all one value? the wrong column?)")


def check_time_unit(path, t_us: np.ndarray, unit: str) -> None:
    """Refuse a time column of whole numbers whose unit is a guess when its first events (``t_us``, at least
    MIN_EVENTS_FOR_RATE, as read in ``unit``) come slower than any camera records: the median gap between them,
    robust to a few wild values, gives the rate. The message names ``source.time_unit`` and the units that would
    give a camera's rate."""
    gaps = np.diff(np.sort(np.asarray(t_us, np.int64)))
    gap = float(np.median(gaps)) if len(gaps) else 0.0
    if gap <= 0:
        return
    rate = 1e6 / gap
    if rate >= MIN_EVENT_RATE_HZ:
        return
    scale = TIME_UNITS_TO_US[unit]
    fits = [u for u, k in TIME_UNITS_TO_US.items() if u != unit and MIN_EVENT_RATE_HZ * 100 <= rate * scale / k
            <= MAX_EVENTS_PER_US * 1e6]
    hint = " or ".join(f"source.time_unit={u} ({rate * scale / TIME_UNITS_TO_US[u]:.3g} events/s)" for u in fits)
    raise RecordingError(path, f"the time column holds whole numbers; read as {unit} (the default for "
                               f"{'floating-point' if unit == 's' else 'integer'} columns) its first {len(t_us):,} "
                               f"events come {_span_words(int(gap))} apart (the median), {rate:.2g} events/s, below "
                               f"any event camera's rate (noise alone makes more than {MIN_EVENT_RATE_HZ:g}/s): the "
                               f"unit is wrong. Set it: {hint or 'source.time_unit=s|ms|us|ns'} "
                               f"(read_recording(time_unit=...), eventcap convert/preview --time-unit)")


#: :func:`timing_note`: windows of this length whose events come at least GRID_RATE_PER_MS per ms are judged
GRID_WINDOW_US = 50_000
GRID_RATE_PER_MS = 4.0
#: ... a recording is on a grid when its events share a timestamp with this many others on average (a sensor's
#: readout shares one among a few events) and fill fewer than GRID_MAX_SHARE of those windows' milliseconds
GRID_EVENTS_PER_STAMP = 20.0
GRID_MAX_SHARE = 0.5


def timing_note(t_us: np.ndarray) -> str | None:
    """A sentence when the events' timestamps lie on a grid coarser than a millisecond (a recording made from
    video frames by a converter, or re-timed in bins), else None: the events then carry no timing finer than the
    grid's step, whatever their unit says. Judged where events come fast enough that a sensor's would fill nearly
    every millisecond (at least GRID_RATE_PER_MS per ms over GRID_WINDOW_US): a sensor's timestamps are shared
    by a few events of one readout, a grid's by tens, and fill few of the milliseconds."""
    t = np.asarray(t_us, dtype=np.int64)
    if t.size < 1000:
        return None
    stamps = np.unique(t)
    per_stamp = t.size / stamps.size
    if per_stamp < GRID_EVENTS_PER_STAMP:
        return None
    w_ms = GRID_WINDOW_US // 1000
    first = int(t[0]) // GRID_WINDOW_US
    counts = np.bincount(t // GRID_WINDOW_US - first)
    occupied = np.bincount(np.unique(stamps // 1000) // w_ms - first, minlength=counts.size)
    busy = counts >= GRID_RATE_PER_MS * w_ms
    if busy.sum() < 3:
        return None
    share = float(np.median(occupied[busy] / w_ms))
    if share >= GRID_MAX_SHARE:
        return None
    gaps = np.diff(stamps)
    step_ms = float(np.median(gaps[gaps > 0])) / 1000.0
    return (f"the events' timestamps lie on a grid: {t.size:,} events share {stamps.size:,} timestamps "
            f"({per_stamp:.0f} per timestamp; a sensor's readout shares one among a few) and fill {share:.0%} of "
            f"the milliseconds where events come at {GRID_RATE_PER_MS:g} or more per ms (median step "
            f"{step_ms:.1f} ms): made from video frames by a converter, or re-timed in bins. The events carry no "
            f"timing finer than that step; a motion at 1 ms between is the prior's, not the events'")


def _span_words(us: int) -> str:
    """A duration in words: '104 µs', '2.5 s', '4.8 h', '11.6 days'."""
    us = abs(int(us))
    if us < 1000:
        return f"{us} µs"
    if us < 1_000_000:
        return f"{us / 1e3:.3g} ms"
    s = us / 1e6
    if s < 120:
        return f"{s:.3g} s"
    if s < 7200:
        return f"{s / 60:.3g} min"
    if s < 2 * 86400:
        return f"{s / 3600:.3g} h"
    return f"{s / 86400:.3g} days"


@dataclass
class TimeGuard:
    """Finds jumps in time and wild timestamps in a stream of events in file order (file time, µs) and decides, in
    bounded memory (it holds back at most ``budget`` + 1 events), what to do with each:

    - a few events (at most ``budget``) cut off from their neighbours by jumps (longer than ``max_gap_us``, or than
      JUMP_FACTOR times the recent median gap and JUMP_MIN_US) are dropped as outliers: a single wild timestamp, a
      corrupted time word's events, stray first or last events;
    - a jump within 1/16 of a decoder's counter range (``wraps_us``: a corrupted time word made time go backwards
      and the decoder took it for a wrap-around) is undone: that range is subtracted from every later event;
    - a jump after which time stands still (more than ``budget`` events at one time stamp: a decoder holding time
      when it goes backwards) cuts the recording there: the events after it are dropped;
    - a jump longer than ``max_gap_us`` with more than ``budget`` events on each side is a :class:`RecordingError`
      naming the event index, the two times and the size of the jump (a shorter one is a pause, kept).

    Each decision is a sentence of :meth:`repairs`. The decisions depend on the events only, not on how the stream
    is cut into chunks, so streaming and reading whole agree.
    """

    path: object
    max_gap_us: int = MAX_GAP_US
    budget: int = TIME_OUTLIER_BUDGET
    wraps_us: tuple[int, ...] = ()
    how: str = "pass max_gap_s= (source.max_gap_s, --max-gap-s) to accept pauses that long"
    #: the outlier rule's jumps relative to the pace (off when the caller set max_gap_us: every shorter pause is real)
    relative: bool = True
    row: int = 0  # index in the file of the next event
    ref: int | None = None  # time of the last accepted event (after undone wraps)
    shift: int = 0  # subtracted from every event (undone decoder wraps)
    accepted: int = 0
    cut_at: int | None = None  # index from which every event is dropped
    _recent: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))  # times of the last accepted events
    _head_done: bool = False  # the first budget + 1 events were accepted (and released)
    _head: list = field(default_factory=list)
    _group: list = field(default_factory=list)  # (row, one-event array) held after a jump
    _group_jump: tuple[int, int] = (0, 0)  # (time before, time after) of the jump that opened the group
    _dropped: int = 0
    _dropped_first: list = field(default_factory=list)  # a few (row, t, count, why) for the note
    _cut_dropped: int = 0
    _cut_why: str = ""
    _undone: list = field(default_factory=list)  # (row, wrap, jump)

    def feed(self, ev: np.ndarray) -> np.ndarray:
        """The next events of the file (``EVENT_DTYPE``, file order, file time µs) → those to keep, times corrected
        by undone wraps; events after a jump are held back until later ones decide about them."""
        n = len(ev)
        if n == 0:
            return ev
        if self.cut_at is not None:
            self._cut_dropped += n
            self.row += n
            return ev[:0]
        keep: list[np.ndarray] = []
        start = 0
        while start < n:
            t = ev["t"][start:] - self.shift if self.shift else ev["t"][start:]
            if not self._group and self._head_done:
                # the vectorised stretch up to the next suspicious step (the usual case: all of it)
                stop = self._first_suspicious(t)
                if stop:
                    part = ev[start:start + stop]
                    if self.shift:
                        part = part.copy()
                        part["t"] = t[:stop]
                    keep.append(part)
                    self._accepted_times(t[:stop])
                    self.row += stop
                    start += stop
                    continue
            one = ev[start:start + 1].copy()
            one["t"] = t[0]
            keep.extend(self._step(one, self.row))
            self.row += 1
            start += 1
            if self.cut_at is not None:
                self._cut_dropped += n - start
                self.row += n - start
                break
        keep = [k for k in keep if len(k)]
        return np.concatenate(keep) if len(keep) > 1 else (keep[0] if keep else ev[:0])

    def finish(self) -> np.ndarray:
        """The end of the file: a group still held is outliers (dropped); returns the events still to keep."""
        if self._group:
            self._drop_group("at the end of the file")
        if not self._head:
            return np.empty(0, dtype=EVENT_DTYPE)
        return self._clean_head()

    # ------------------------------------------------------------------------------------------------- logic
    def _jump_limit(self, prev: np.ndarray) -> float:
        """The step beyond which the next event is a jump for the outlier rule, given the accepted times before it
        (``prev``, in order): JUMP_FACTOR times the median gap of the last JUMP_WINDOW of them, at least
        JUMP_MIN_US, at most max_gap_us (and max_gap_us while fewer than 3 came before)."""
        if len(prev) < 3 or not self.relative:
            return float(self.max_gap_us)
        gap = float(np.median(np.abs(np.diff(prev[-JUMP_WINDOW - 1:]))))
        return float(min(max(JUMP_FACTOR * gap, JUMP_MIN_US), self.max_gap_us))

    def _near_wrap(self, d):
        d = np.asarray(d)
        out = np.zeros(d.shape, bool)
        for w in self.wraps_us:
            out |= np.abs(d - w) < w // 16
        return out

    def _first_suspicious(self, t: np.ndarray) -> int:
        """How many of ``t`` (after ``ref``, nothing held) pass as one accepted stretch. Only steps longer than
        JUMP_MIN_US (or of a counter's range) can be jumps: the pace before each of those few is looked at."""
        d = np.diff(t, prepend=self.ref)
        floor = JUMP_MIN_US if self.relative else self.max_gap_us
        cand = np.flatnonzero((np.abs(d) > floor) | self._near_wrap(d))
        for i in cand:
            prev = np.concatenate([self._recent, t[max(0, i - JUMP_WINDOW - 1):i]])
            if abs(d[i]) > self._jump_limit(prev) or self._near_wrap(d[i]):
                return int(i)
        return len(t)

    def _accepted_times(self, t: np.ndarray) -> None:
        self.ref = int(t[-1])
        self.accepted += len(t)
        self._recent = np.concatenate([self._recent, t])[-JUMP_WINDOW - 1:]

    def _is_jump(self, a: int, b: int) -> bool:
        """Whether the step from time ``a`` (the last accepted or held event) to ``b`` is a jump now."""
        return bool(abs(b - a) > self._jump_limit(self._recent) or self._near_wrap(b - a))

    def _accept(self, one: np.ndarray) -> list[np.ndarray]:
        self._accepted_times(one["t"])
        if self._head_done:
            return [one]
        self._head.append(one)  # held: a jump soon after the first events makes them the outliers
        if self.accepted > self.budget:
            self._head_done = True
            return [self._clean_head()]
        return []

    def _clean_head(self) -> np.ndarray:
        """The first events, released: a few (at most HEAD_OUTLIERS) whose time lies far from the others' (beyond
        JUMP_FACTOR times their median gap and JUMP_MIN_US from their median time) are dropped; the jump rule cannot see
        them while it has no pace to compare with."""
        head, self._head = np.concatenate(self._head), []
        if len(head) < 16 or not self.relative:
            return head
        t = head["t"]
        mid = np.median(t)
        gap = float(np.median(np.abs(np.diff(t))))
        far = np.abs(t - mid) > max(JUMP_MIN_US, JUMP_FACTOR * gap)
        k = int(far.sum())
        if 0 < k <= HEAD_OUTLIERS:
            first = int(np.argmax(far))
            self._note_drop(head[far], self.row - len(head) + 1 + first,
                            f"among the first {len(head)} events, {_span_words(abs(int(t[first]) - int(mid)))} "
                            f"from the others")
            head = head[~far]
            self._recent = np.sort(head["t"])[-JUMP_WINDOW - 1:]
            self.ref = int(head["t"][-1])
        return head

    def _step(self, one: np.ndarray, row: int, force: bool = False) -> list[np.ndarray]:
        t = int(one["t"][0])
        if self.ref is None or force:
            return self._accept(one)
        if not self._group:
            if not self._is_jump(self.ref, t):
                return self._accept(one)
            self._group, self._group_jump = [(row, one)], (self.ref, t)
            return []
        last = int(self._group[-1][1]["t"][0])
        jumped = _span_words(self._group_jump[1] - self._group_jump[0])
        if not self._is_jump(self.ref, t):  # back where it was: the held events were a spike
            self._drop_group(f"between a jump of {jumped} and one back")
            return self._accept(one)
        if self._is_jump(last, t):  # off again, elsewhere: the held events were a spike
            self._drop_group(f"between jumps of {jumped} and {_span_words(t - last)}")
            self._group, self._group_jump = [(row, one)], (self.ref, t)
            return []
        self._group.append((row, one))
        return self._level_shift() if len(self._group) > self.budget else []

    def _replay(self, group: list, dt: int = 0, force_first: bool = False) -> list[np.ndarray]:
        out = []
        for k, (r, one) in enumerate(group):
            if dt:
                one = one.copy()
                one["t"] -= dt
            out.extend(self._step(one, r, force=force_first and k == 0))
        return out

    def _level_shift(self) -> list[np.ndarray]:
        """More than ``budget`` events after one jump: a decoder's wrap (undone), a pause (kept), a stray head
        (dropped), time standing still (cut), or a jump longer than max_gap_us (refused)."""
        (before, after), group = self._group_jump, self._group
        jump, row = after - before, group[0][0]
        self._group = []
        for w in self.wraps_us:
            if abs(jump - w) < w // 16:
                self.shift += w
                self._undone.append((row, w, jump))
                return self._replay(group, w)
        times = np.array([int(one["t"][0]) for _, one in group])
        still = bool(np.all(times == times[0]))
        if abs(jump) <= self.max_gap_us and not still:  # a pause (or a step back) and events after it: the camera's
            return self._replay(group, force_first=True)
        if not self._head_done and not still:  # the few events before the jump are the strays
            head, self._head = np.concatenate(self._head), []
            self._note_drop(head, row - len(head), f"the first {len(head)} event(s) of the file, before a jump of "
                                                   f"{_span_words(jump)} at event index {row}")
            self.accepted, self.ref, self._recent = 0, None, self._recent[:0]
            return self._replay(group)
        if still:
            self.cut_at = row
            self._cut_dropped += len(group)
            self._cut_why = (f"time jumps by {_span_words(jump)} there (from {before} to {after} µs, file time) and "
                             f"then stands still (a decoder holds time when a corrupted word makes it go backwards)")
            return []
        raise RecordingError(self.path, f"time jumps by {_span_words(jump)} between neighbouring events (from {before} "
                                        f"to {after} µs, file time), with more than {self.budget} events on each "
                                        f"side: a corrupted or spliced file, or a recording paused that long; "
                                        f"{self.how}", f"event index {row}")

    def _drop_group(self, why: str) -> None:
        rows = [r for r, _ in self._group]
        ev = np.concatenate([one for _, one in self._group])
        self._group = []
        self._note_drop(ev, rows[0], why)

    def _note_drop(self, ev: np.ndarray, row: int, why: str) -> None:
        self._dropped += len(ev)
        if self._dropped > max(self.budget, self.row // 100):
            first = self._dropped_first[0] if self._dropped_first else (row, int(ev["t"][0]) + self.shift, 0, why)
            raise RecordingError(self.path, f"time jumps at many places: {self._dropped} of the first {self.row + 1} "
                                            f"events are cut off from the others by jumps (the first at event index "
                                            f"{first[0]}, {first[3]}): not a few wild timestamps but a broken time "
                                            f"column, a wrong time unit (source.time_unit) or a recording with pauses "
                                            f"({self.how})", f"event index {row}")
        if len(self._dropped_first) < 3:
            self._dropped_first.append((row, int(ev["t"][0]) + self.shift, len(ev), why))

    def repairs(self) -> list[str]:
        """One sentence per kind of decision made so far."""
        out = []
        for row, w, jump in self._undone:
            out.append(f"time jumps by {_span_words(jump)} at event index {row}, about the 2^{w.bit_length() - 1} µs "
                       f"range of the format's time counter, which its decoder adds when a corrupted time word makes "
                       f"time go backwards: subtracted 2^{w.bit_length() - 1} µs from there on")
        if self._dropped:
            first = "; ".join(f"event index {r}" + ("" if k == 1 else f" and {k - 1} after it") +
                              f" at {t} µs (file time), {why}" for r, t, k, why in self._dropped_first)
            more = "" if len(self._dropped_first) < 3 else "; ..."
            out.append(f"dropped {self._dropped} event(s) with wild times, cut off from the others by jumps in "
                       f"time: {first}{more}")
        if self.cut_at is not None:
            out.append(f"cut the recording at event index {self.cut_at}: {self._cut_why}; dropped the "
                       f"{self._cut_dropped} event(s) from there to the end")
        return out
