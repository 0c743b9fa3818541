"""Prophesee event files: RAW (EVT 2.0 / EVT 3.0) and DAT (CD events). Read with our own decoders
(:mod:`eventcap.io.evt`: every event at the time the file gives it, times going backwards kept for the shared time
checks); ``faery`` reads the headers' sensor size and writes the files.

Truncated files: a cut inside a word (EVT2: 4 bytes, EVT3: 2, DAT: 8) is noted. A cut on a word boundary is
noted only where the format shows it: an EVT3 file whose last word opens an event group (ADDR_Y, VECT_BASE_X)
that never comes. EVT2 words and DAT events each stand alone, and none of the three formats stores its length or
an end marker, so a file cut between two of them reads as a shorter recording, with no way to tell.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from eventcap.io.checks import RawChunk
from eventcap.io.evt import (
    DAT_EVENT,
    EVT2_TYPES,
    EVT3_TYPES,
    DatCounter,
    DecoderState,
    dat_columns,
    decode_words,
    decoder_notes,
)
from eventcap.io.recording import RecordingError
from eventcap.io.registry import ReaderSpec
from eventcap.io.source import DEFAULT_CHUNK_EVENTS, RowLocator, Source, file_size, native_call, numbered_chunks

_MAX_HEADER_BYTES = 1 << 20
# Passed to faery when the header has no size: large enough to disable its range check; the size is then
# inferred from the events by the reader (and reported).
_NO_SIZE = (65535, 65535)


def read_header(path: Path) -> tuple[list[str], int]:
    """The ``%`` header lines of a Prophesee file (without the ``%``) and the header length in bytes."""
    lines, length = [], 0
    with open(path, "rb") as f:
        while length < _MAX_HEADER_BYTES:
            line = f.readline(4096)
            if not line.startswith(b"%"):
                break
            length += len(line)
            lines.append(line[1:].decode("utf-8", "replace").strip())
            if not line.endswith(b"\n"):
                break
    return lines, length


def header_kind(lines: list[str]) -> str | None:
    """"evt2" / "evt3" / "evt" (version not named) / "dat" from header lines, or ``None`` if they do not say."""
    for line in lines:
        words = line.replace(";", " ").split()
        if not words:
            continue
        key = words[0].lower()
        value = words[1].lower() if len(words) > 1 else ""
        if key == "evt" or (key == "format" and value.startswith("evt")):
            version = value.removeprefix("evt")
            return {"2": "evt2", "2.0": "evt2", "3": "evt3", "3.0": "evt3"}.get(version, "evt")
    for line in lines:
        if line.lower().startswith(("data file containing", "version")):
            return "dat"
    return None


# Event types (the top 4 bits of a word) each format defines; other codes never occur in a valid stream.
_EVT_TYPES = {"evt3": EVT3_TYPES, "evt2": EVT2_TYPES}
_SAMPLE_BYTES = 1 << 20
#: Words (EVT) or events (DAT) decoded at a time.
_BLOCK = 1 << 20


def header_t0(lines: list[str]) -> int:
    """The file time of t = 0 a Prophesee header states (``% t0 <µs>`` / ``% T0 <µs>``, the last one), or 0."""
    t0 = 0
    for line in lines:
        words = line.replace(";", " ").split()
        if len(words) > 1 and words[0] in ("t0", "T0") and words[1].isdigit():
            t0 = int(words[1])
    return t0


def check_evt_words(path: Path, header_length: int, version: str) -> None:
    """Refuse data that is not an EVT stream: random bytes after a valid header decode into plausible-looking
    events (faery reads any word), but about a third (EVT3) or more (EVT2) of random words carry an event type
    the format does not define. More than 2 % of such words (and more than 16) in the first MiB is refused."""
    word = 2 if version == "evt3" else 4
    with open(path, "rb") as f:
        f.seek(header_length)
        data = f.read(_SAMPLE_BYTES)
    n = len(data) // word
    if n == 0:
        return
    words = np.frombuffer(data[:n * word], "<u2" if word == 2 else "<u4")
    types = (words >> (12 if word == 2 else 28)).astype(np.int64)
    bad = ~np.isin(types, _EVT_TYPES[version])
    k = int(bad.sum())
    if k > 16 and k > 0.02 * n:
        first = int(np.argmax(bad))
        raise RecordingError(path, f"not {version.upper()} data: {k} of the first {n} words ({100 * k / n:.0f} %) "
                                   f"have event types {version.upper()} does not define (first: type "
                                   f"0x{int(types[first]):X} at byte {header_length + word * first})", "data")


def _size_from(decoder_dims, path: Path) -> tuple[int | None, int | None]:
    if tuple(decoder_dims) == _NO_SIZE:
        return None, None
    w, h = (int(v) for v in decoder_dims)
    if w <= 0 or h <= 0:
        raise RecordingError(path, f"header declares an empty sensor ({w} × {h})", "file header")
    return w, h


class EvtSource(Source):
    """A Prophesee RAW file, EVT 2.0 or 3.0 (the version from the header, or ``version`` if it has none)."""

    def __init__(self, path: Path, version: str | None = None, time_unit: str | None = None):
        super().__init__(path, time_unit)
        import faery

        self._faery = faery
        lines, self._header_length = read_header(path)
        self._t0 = header_t0(lines)
        kind = header_kind(lines)
        header_version = kind if kind in ("evt2", "evt3") else None
        if header_version and version and header_version != version:
            raise RecordingError(path, f"the header says {header_version.upper()} but format={version!r} was asked",
                                 "file header")
        self.version = header_version or version
        if self.version is None:
            raise RecordingError(path, "the header names no EVT version (no '% evt 2.0/3.0' or '% format EVT…' "
                                       "line): pass format='evt2' or format='evt3'", "file header")
        self.format = self.version
        with native_call(path, "EVT decoder (faery)", "file header"), \
                faery.evt.Decoder(path, _NO_SIZE, self.version) as decoder:
            dims = decoder.dimensions
        self.width, self.height = _size_from(dims, path)
        self._word = 4 if self.version == "evt2" else 2
        check_evt_words(path, self._header_length, self.version)

    def chunks(self, chunk_events: int = DEFAULT_CHUNK_EVENTS, with_frames: bool = False) -> Iterator[RawChunk]:
        self.notes.clear()
        extra = (file_size(self.path) - self._header_length) % self._word
        if extra:
            self.notes.append(f"the file ends with a partial {self._word}-byte EVT word ({extra} byte(s), truncated "
                              f"file?): ignored")
        dangling = self._dangling_group(extra)
        if dangling:
            self.notes.append(dangling)
        locate = RowLocator()

        def columns():
            state = DecoderState(self.version)
            dtype = "<u4" if self.version == "evt2" else "<u2"
            row, first_word = 0, 0
            with open(self.path, "rb") as f:
                f.seek(self._header_length)
                while True:
                    words = np.fromfile(f, dtype, count=_BLOCK)
                    if not len(words):
                        break
                    t, x, y, p, _ = decode_words(words, state)
                    if len(t):
                        start = self._header_length + self._word * first_word
                        locate.add(row, f"data bytes {start}-{start + self._word * len(words) - 1}")
                        row += len(t)
                        yield t + self._t0, x, y, p
                    first_word += len(words)
            self.notes.extend(decoder_notes(state, self._word, self._header_length))

        yield from numbered_chunks(_guarded(columns(), self.path, f"{self.version.upper()} decoder"), chunk_events,
                                   locate)

    def _dangling_group(self, extra: int) -> str | None:
        """EVT3 only: a note when the file ends inside an event group: after its last event word (ADDR_X, VECT_12,
        VECT_8) comes a word that opens a group (ADDR_Y announces the row of the events that follow it, VECT_BASE_X
        the first column of the vectors that follow it) and no event after it (time words may follow: the encoder
        writes ADDR_Y, TIME_LOW, ADDR_X). A cut right after an event word cannot be told from the end of a
        recording: EVT3 has no length and no end marker (nor have EVT2 words and DAT events, which each stand
        alone)."""
        size = file_size(self.path) - self._header_length - extra
        if self.version != "evt3" or size < 2:
            return None
        tail_words = min(size // 2, 64)
        with open(self.path, "rb") as f:
            f.seek(self._header_length + size - 2 * tail_words)
            words = np.frombuffer(f.read(2 * tail_words), "<u2")
        kinds = (words >> 12).astype(np.int64)
        events = np.flatnonzero(np.isin(kinds, (0x2, 0x4, 0x5)))
        after = kinds[events[-1] + 1:] if len(events) else kinds
        openers = np.flatnonzero(np.isin(after, (0x0, 0x3)))
        if not len(openers):
            return None
        kind = {0x0: "EVT_ADDR_Y (the row of the events that follow it)",
                0x3: "VECT_BASE_X (the first column of the event vectors that follow it)"}[int(after[openers[-1]])]
        return (f"the file ends inside an EVT3 event group: an {kind} is followed by no event (only "
                f"{len(after) - openers[-1] - 1} time word(s)) (truncated file?): the events it announced are "
                f"missing")


class DatSource(Source):
    """A Prophesee DAT file of CD events (version from the header; DAT 2 assumed, and noted, if it has none)."""

    format = "dat"

    def __init__(self, path: Path, time_unit: str | None = None):
        super().__init__(path, time_unit)
        import faery

        self._faery = faery
        _, self._header_length = read_header(path)
        with native_call(path, "DAT decoder (faery)", "file header"):
            try:
                with faery.dat.Decoder(path, _NO_SIZE, None) as decoder:
                    self.version = decoder.version
            except RuntimeError as exc:
                if "version" not in str(exc):
                    raise
                self.version = "dat2"
                self.notes.append("the header names no DAT version: decoded as DAT 2")
            with faery.dat.Decoder(path, _NO_SIZE, self.version) as decoder:
                dims, kind = decoder.dimensions, decoder.event_type
        self._version_note = list(self.notes)
        self.t_add_us = header_t0(read_header(path)[0])
        if kind != "cd":
            raise RecordingError(path, f"DAT event type {kind!r} has no polarity: only CD event files are supported",
                                 "file header")
        self.width, self.height = _size_from(dims, path)

    def chunks(self, chunk_events: int = DEFAULT_CHUNK_EVENTS, with_frames: bool = False) -> Iterator[RawChunk]:
        self.notes[:] = self._version_note
        extra = (file_size(self.path) - self._header_length - 2) % 8
        if extra:
            self.notes.append(f"the file ends with a partial 8-byte DAT event ({extra} byte(s), truncated file?): "
                              f"ignored")

        def columns():  # every event at the time it holds, its 32-bit counter's wraps added (eventcap.io.evt)
            counter = DatCounter()
            with open(self.path, "rb") as f:
                f.seek(self._header_length + 2)
                while True:
                    raw = np.fromfile(f, DAT_EVENT, count=_BLOCK)
                    if not len(raw):
                        break
                    t, x, y, p = dat_columns(raw, self.version)
                    yield counter.unwrap(t), x, y, p

        yield from numbered_chunks(_guarded(columns(), self.path, "DAT decoder"), chunk_events)


def _guarded(columns: Iterator[tuple], path: Path, what: str) -> Iterator[tuple]:
    """Re-raise a decoder failure as a :class:`RecordingError` naming how far decoding got."""
    decoded = 0
    it = iter(columns)
    while True:
        try:
            cols = next(it)
        except StopIteration:
            return
        except RecordingError:
            raise
        except (KeyboardInterrupt, SystemExit, GeneratorExit):
            raise
        except BaseException as exc:
            message = str(exc).strip() or type(exc).__name__
            raise RecordingError(path, f"{what} failed: {type(exc).__name__}: {message}",
                                 f"after event index {decoded}") from exc
        decoded += len(cols[0])
        yield cols


# ------------------------------------------------------------------------------------------------------ writing
def _encoder(path: Path, fmt: str, width: int, height: int):
    import faery

    if fmt == "dat":
        return faery.dat.Encoder(path, "dat2", "cd", True, (int(width), int(height)))
    return faery.evt.Encoder(path, fmt, True, (int(width), int(height)), True)


def _check_decodable(t: np.ndarray, state: dict, fmt: str) -> None:
    """Refuse time gaps the format's short counters cannot carry across (the file would decode to wrong times).

    DAT stores 32 bits of µs and EVT2 34 bits: a gap of half that range is ambiguous (a decoder takes a step back by
    more than half the range for a wrap).
    EVT3 stores 24 bits; faery's decoder recognises a wrap only when the 4096-µs tick goes from 4095 to 0, and
    its encoder writes ticks only where events are, so a recording must have events in the ticks on both sides
    of every 2^24-µs boundary.
    """
    if not len(t):
        return
    t = t.astype(np.int64)
    prev = state.get("prev")
    full = t if prev is None else np.concatenate([[prev], t])
    state.setdefault("t0", int(t[0]))
    state["prev"] = int(t[-1])
    if len(full) < 2:
        return
    if fmt == "evt3":
        tick = (full - state["t0"]) >> 12
        step = np.diff(tick)
        bad = ((tick[1:] >> 12) != (tick[:-1] >> 12)) & (step != 1)
        why = ("no events in the 4.1 ms before or after a wrap of EVT3's 24-bit time counter (every 16.8 s): "
               "faery would write times that decode wrongly; write EVT2, DAT, HDF5 or AEDAT4 instead")
    else:  # a step back of more than half the counter's range is a wrap (eventcap.io.evt)
        limit = 2**31 if fmt == "dat" else 2**33
        bad = np.diff(full) >= limit
        why = (f"a gap of 2^{31 if fmt == 'dat' else 33} µs or more, half the range of {fmt.upper()}'s time counter: "
               f"it could not be told from the counter's wrap-around")
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(f"cannot write {fmt.upper()}: events at {int(full[i])} µs and {int(full[i + 1])} µs (file "
                         f"time): {why}")


def write_prophesee(path: Path, chunks: Iterator[np.ndarray], fmt: str, width: int, height: int) -> None:
    """Write faery-dtype event chunks (absolute µs ≥ 0, sorted) as EVT2 / EVT3 / DAT 2 (t0 in the header).

    Raises ``ValueError`` for time gaps the format cannot represent (see :func:`_check_decodable`).
    """
    dat_dtype = np.dtype([("t", "<u8"), ("x", "<u2"), ("y", "<u2"), ("payload", "u1")])
    state: dict = {}
    with _encoder(path, fmt, width, height) as encoder:
        for chunk in chunks:
            if not len(chunk):
                continue
            _check_decodable(chunk["t"], state, fmt)
            if fmt == "dat":
                encoder.write(chunk.astype(dat_dtype))
            else:
                encoder.write({"events": chunk})


def detect_header(head: bytes, path) -> str | None:
    """The format of a file starting with a Prophesee '%' header: evt2 / evt3 / dat as the header says (a RAW file
    whose header names no EVT version is refused: format=evt2 or evt3); None when it is not such a header."""
    if not head.startswith(b"%"):
        return None
    kind = header_kind(read_header(Path(path))[0])
    if kind == "evt":
        raise RecordingError(path, "the header names no EVT version (no '% evt 2.0/3.0' or '% format EVT…' line): "
                                   "pass format='evt2' or format='evt3'", "file header")
    if kind is None and Path(path).suffix.lower() == ".dat":
        return "dat"
    return kind


def open_evt2(path: Path, time_unit: str | None = None) -> EvtSource:
    return EvtSource(path, "evt2", time_unit)


def open_evt3(path: Path, time_unit: str | None = None) -> EvtSource:
    return EvtSource(path, "evt3", time_unit)


READERS = [
    ReaderSpec(name="evt2", description="Prophesee RAW, EVT 2.0", extensions=(".raw",),
               detect="eventcap.io.prophesee:detect_header", source="eventcap.io.prophesee:open_evt2",
               wraps_us=(2**34,), library="our decoder (eventcap.io.evt)"),
    ReaderSpec(name="evt3", description="Prophesee RAW, EVT 3.0", extensions=(".raw",),
               detect="eventcap.io.prophesee:detect_header", source="eventcap.io.prophesee:open_evt3",
               wraps_us=(2**24,), library="our decoder (eventcap.io.evt)"),
    ReaderSpec(name="dat", description="Prophesee DAT (CD events)", extensions=(".dat",),
               detect="eventcap.io.prophesee:detect_header", source="eventcap.io.prophesee:DatSource",
               wraps_us=(2**32,), library="our decoder; faery reads the header"),
]
