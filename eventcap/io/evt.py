"""Our own decoders of Prophesee EVT 2.0 / EVT 3.0 words and DAT events: every event at the time the file gives it.

Why not the library's decoder: faery (like most) clamps a time that goes backwards to the previous one and, in EVT3,
ignores a time word that goes back. A flipped bit or a block of words out of place then moves events silently, stacks
thousands of them on one microsecond, and the readers' duplicate check deletes real events as "duplicates" (issue
57). Here a time going backwards stays as the file holds it; the shared time checks (:mod:`eventcap.io.checks`:
sorting with a note naming the index and the size of the step back, a wild event dropped, a jump refused or a
decoder's wrap undone) then treat it as they treat any other format's.

The formats (Prophesee's documentation, "EVT 2.0 / EVT 3.0 format"):

- EVT 2.0, 32-bit words, type in the top 4 bits: CD_OFF (0x0) / CD_ON (0x1) carry x (bits 11-21), y (0-10) and the
  6 low bits of the time (22-27); EVT_TIME_HIGH (0x8) the upper 28 bits of a 34-bit µs counter; EXT_TRIGGER (0xA),
  OTHERS (0xE) and CONTINUED (0xF) carry no CD event.
- EVT 3.0, 16-bit words, type in the top 4 bits: EVT_ADDR_Y (0x0) sets y; EVT_ADDR_X (0x2) is one event at x with
  polarity bit 11; VECT_BASE_X (0x3) sets the x and polarity of the vectors after it; VECT_12 (0x4) / VECT_8 (0x5)
  are up to 12 / 8 events at the next x (a bit per pixel), advancing x; EVT_TIME_LOW (0x6) / EVT_TIME_HIGH (0x8) the
  lower / upper 12 bits of a 24-bit µs counter (a TIME_HIGH resets the lower bits); CONTINUED_4 (0x7), EXT_TRIGGER
  (0xA), OTHERS (0xE), CONTINUED_12 (0xF) carry no CD event.
- DAT: after the header, a type and a size byte, then 8-byte events: a 32-bit µs time and a 32-bit word (DAT 2: x
  bits 0-13, y 14-27, polarity 28-31; DAT 1: x 0-8, y 9-16, polarity 17-20).

Counter wraps: the time-high counter steps back by more than half its range (EVT2 2^27 of 2^28 words of 64 µs,
EVT3 2^11 of 2^12 words of 4096 µs, DAT 2^31 of its 32-bit µs) only at a wrap, which is added (as Prophesee's and
faery's decoders do; a forward step is taken as it is, whatever its size, so files with long pauses decode as
before); a smaller step back is time going backwards, kept. A word of a type the format does not define, events before
the first time word, and EVT3 events before their row or column is given carry no position in time or space: they
are counted and dropped, and the reader's notes say so.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numba
import numpy as np

#: Event types (the top 4 bits of a word) each format defines.
EVT3_TYPES = (0x0, 0x2, 0x3, 0x4, 0x5, 0x6, 0x7, 0x8, 0xA, 0xE, 0xF)
EVT2_TYPES = (0x0, 0x1, 0x8, 0xA, 0xE, 0xF)
#: The time counters: EVT2 34 bits of µs (time-high words of 64 µs), EVT3 24 bits (time-high words of 4096 µs).
EVT2_RANGE_US = 1 << 34
EVT3_RANGE_US = 1 << 24

# state slots (one int64 array carried from block to block)
_T_HIGH, _T, _LOOPS, _HAVE_T, _Y, _HAVE_Y, _X, _HAVE_X, _POL = range(9)
_UNDEFINED, _FIRST_UNDEFINED, _UNPLACED, _FIRST_UNPLACED, _WORDS = range(9, 14)
_STATE_SIZE = 14


@dataclass
class DecoderState:
    """What carries over between blocks of one file, and what the decoder counted (for the reader's notes)."""

    version: str
    slots: np.ndarray = field(default_factory=lambda: _fresh_slots())

    @property
    def undefined(self) -> int:
        return int(self.slots[_UNDEFINED])

    @property
    def first_undefined_word(self) -> int:
        return int(self.slots[_FIRST_UNDEFINED])

    @property
    def unplaced(self) -> int:
        return int(self.slots[_UNPLACED])

    @property
    def first_unplaced_word(self) -> int:
        return int(self.slots[_FIRST_UNPLACED])


def _fresh_slots() -> np.ndarray:
    s = np.zeros(_STATE_SIZE, np.int64)
    s[_FIRST_UNDEFINED] = s[_FIRST_UNPLACED] = -1
    return s


@numba.njit(cache=True)
def _note_unplaced(s, k, n):  # pragma: no cover - compiled
    if s[_UNPLACED] == 0:
        s[_FIRST_UNPLACED] = s[_WORDS] + k
    s[_UNPLACED] += n


@numba.njit(cache=True)
def _note_undefined(s, k):  # pragma: no cover - compiled
    if s[_UNDEFINED] == 0:
        s[_FIRST_UNDEFINED] = s[_WORDS] + k
    s[_UNDEFINED] += 1


@numba.njit(cache=True)
def _popcount(v):  # pragma: no cover - compiled
    n = 0
    while v:
        v &= v - 1
        n += 1
    return n


@numba.njit(cache=True)
def _decode_evt3(words, s):  # pragma: no cover - compiled
    """(t, x, y, p, word) of the EVT3 words, state ``s`` updated; t without the header's t0."""
    n_max = 0
    for w in words:
        kind = w >> 12
        if kind == 0x2:
            n_max += 1
        elif kind == 0x4:
            n_max += _popcount(w & 0xFFF)
        elif kind == 0x5:
            n_max += _popcount(w & 0xFF)
    t_out = np.empty(n_max, np.int64)
    x_out = np.empty(n_max, np.int64)
    y_out = np.empty(n_max, np.int64)
    p_out = np.empty(n_max, np.uint8)
    w_out = np.empty(n_max, np.int64)
    n = 0
    for k in range(words.shape[0]):
        w = np.int64(words[k])
        kind = w >> 12
        if kind == 0x0:  # EVT_ADDR_Y
            s[_Y] = w & 0x7FF
            s[_HAVE_Y] = 1
        elif kind == 0x2 or kind == 0x4 or kind == 0x5:
            if kind == 0x2:  # EVT_ADDR_X: one event
                count = 1
            elif kind == 0x4:
                count = _popcount(w & 0xFFF)
            else:
                count = _popcount(w & 0xFF)
            if kind != 0x2 and s[_HAVE_X] == 0:
                _note_unplaced(s, k, count)
                continue
            if s[_HAVE_T] == 0 or s[_HAVE_Y] == 0:
                _note_unplaced(s, k, count)
                if kind == 0x4:
                    s[_X] += 12
                elif kind == 0x5:
                    s[_X] += 8
                continue
            if kind == 0x2:
                t_out[n] = s[_T]
                x_out[n] = w & 0x7FF
                y_out[n] = s[_Y]
                p_out[n] = (w >> 11) & 1
                w_out[n] = s[_WORDS] + k
                n += 1
            else:
                width = 12 if kind == 0x4 else 8
                for bit in range(width):
                    if (w >> bit) & 1:
                        t_out[n] = s[_T]
                        x_out[n] = s[_X] + bit
                        y_out[n] = s[_Y]
                        p_out[n] = s[_POL]
                        w_out[n] = s[_WORDS] + k
                        n += 1
                s[_X] += width
        elif kind == 0x3:  # VECT_BASE_X
            s[_X] = w & 0x7FF
            s[_POL] = (w >> 11) & 1
            s[_HAVE_X] = 1
        elif kind == 0x6:  # EVT_TIME_LOW
            if s[_HAVE_T]:
                s[_T] = (s[_LOOPS] << 24) + (s[_T_HIGH] << 12) + (w & 0xFFF)
        elif kind == 0x8:  # EVT_TIME_HIGH
            high = w & 0xFFF
            if s[_HAVE_T]:
                if high - s[_T_HIGH] < -2048:
                    s[_LOOPS] += 1
            s[_T_HIGH] = high
            s[_HAVE_T] = 1
            s[_T] = (s[_LOOPS] << 24) + (high << 12)
        elif kind == 0x7 or kind == 0xA or kind == 0xE or kind == 0xF:
            pass
        else:
            _note_undefined(s, k)
    s[_WORDS] += words.shape[0]
    return t_out[:n], x_out[:n], y_out[:n], p_out[:n], w_out[:n]


@numba.njit(cache=True)
def _decode_evt2(words, s):  # pragma: no cover - compiled
    """(t, x, y, p, word) of the EVT2 words, state ``s`` updated; t without the header's t0."""
    n_max = 0
    for w in words:
        if (w >> 28) <= 1:
            n_max += 1
    t_out = np.empty(n_max, np.int64)
    x_out = np.empty(n_max, np.int64)
    y_out = np.empty(n_max, np.int64)
    p_out = np.empty(n_max, np.uint8)
    w_out = np.empty(n_max, np.int64)
    n = 0
    for k in range(words.shape[0]):
        w = np.int64(words[k])
        kind = w >> 28
        if kind <= 1:  # CD_OFF, CD_ON
            if s[_HAVE_T] == 0:
                _note_unplaced(s, k, 1)
                continue
            t_out[n] = (((s[_LOOPS] << 28) + s[_T_HIGH]) << 6) + ((w >> 22) & 0x3F)
            x_out[n] = (w >> 11) & 0x7FF
            y_out[n] = w & 0x7FF
            p_out[n] = kind
            w_out[n] = s[_WORDS] + k
            n += 1
        elif kind == 0x8:  # EVT_TIME_HIGH
            high = w & 0xFFFFFFF
            if s[_HAVE_T]:
                if high - s[_T_HIGH] < -(1 << 27):
                    s[_LOOPS] += 1
            s[_T_HIGH] = high
            s[_HAVE_T] = 1
        elif kind == 0xA or kind == 0xE or kind == 0xF:
            pass
        else:
            _note_undefined(s, k)
    s[_WORDS] += words.shape[0]
    return t_out[:n], x_out[:n], y_out[:n], p_out[:n], w_out[:n]


def decode_words(words: np.ndarray, state: DecoderState) -> tuple[np.ndarray, ...]:
    """Decode one block of a file's words (``<u4`` for EVT2, ``<u2`` for EVT3), in file order, continuing ``state``:
    ``(t, x, y, p, word_index)`` with t in µs on the file's clock before its header's t0, p in {0, 1} and the index
    of the word each event came from (for messages)."""
    if state.version == "evt3":
        return _decode_evt3(np.ascontiguousarray(words, np.uint16), state.slots)
    if state.version == "evt2":
        return _decode_evt2(np.ascontiguousarray(words, np.uint32), state.slots)
    raise ValueError(f"decode_words: EVT version {state.version!r} (evt2 or evt3)")


def decoder_notes(state: DecoderState, word_bytes: int, header_bytes: int) -> list[str]:
    """The sentences of what the decoder could not place (for the reader's repairs)."""
    notes = []
    name = state.version.upper()
    if state.undefined:
        at = header_bytes + word_bytes * state.first_undefined_word
        notes.append(f"skipped {state.undefined} word(s) of a type {name} does not define (first at byte {at}): "
                     f"damaged words, which carry no event")
    if state.unplaced:
        at = header_bytes + word_bytes * state.first_unplaced_word
        what = "before the first time word" if state.version == "evt2" else \
            "before the words that give their time, row or column"
        notes.append(f"dropped {state.unplaced} event(s) {what} (first at byte {at}): the file gives them no "
                     f"{'time' if state.version == 'evt2' else 'time or position'}")
    return notes


class DatCounter:
    """DAT's 32-bit µs times -> int64, its wraps added by the half-range rule (see the module docstring), carried
    from block to block."""

    def __init__(self) -> None:
        self.prev: int | None = None
        self.loops = 0

    def unwrap(self, t: np.ndarray) -> np.ndarray:
        t = t.astype(np.int64)
        if not len(t):
            return t
        d = np.diff(t, prepend=t[0] if self.prev is None else self.prev)
        loops = self.loops + np.cumsum(d < -(1 << 31), dtype=np.int64)
        self.prev, self.loops = int(t[-1]), int(loops[-1])
        return t + (loops << 32)


#: DAT events: a 32-bit time and a 32-bit word.
DAT_EVENT = np.dtype([("t", "<u4"), ("w", "<u4")])


def dat_columns(raw: np.ndarray, version: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(t as uint32, x, y, polarity payload) of DAT events (``DAT_EVENT`` records) of ``version`` dat1 / dat2."""
    w = raw["w"]
    if version == "dat1":
        return raw["t"], (w & 0x1FF).astype(np.uint16), ((w >> 9) & 0xFF).astype(np.uint16), \
            ((w >> 17) & 0xF).astype(np.uint8)
    return raw["t"], (w & 0x3FFF).astype(np.uint16), ((w >> 14) & 0x3FFF).astype(np.uint16), \
        (w >> 28).astype(np.uint8)
