"""The small contract every format reader implements, and helpers they share (native-call guard, memory guard)."""

from __future__ import annotations

import bisect
import contextlib
import errno
import os
import stat
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from eventcap.camera import Camera
from eventcap.processes import available_memory_bytes  # noqa: F401 - part of this module's API
from eventcap.io.checks import RawChunk
from eventcap.io.recording import RecordingError

DEFAULT_CHUNK_EVENTS = 1 << 20


@dataclass
class FrameData:
    """Frames as a source stores them, before conversion to :class:`eventcap.io.Frames`.

    ``images`` (N, H, W) or (N, H, W, C) of uint8/uint16/float; ``t_us`` (N,) int64 file time of each
    exposure's centre; ``exposure_us`` (N,) int64 or ``None``; ``locate(i)`` names frame ``i`` in messages.
    """

    images: np.ndarray
    t_us: np.ndarray
    exposure_us: np.ndarray | None = None
    locate: Callable[[int], str] = field(default=lambda i: f"frame {i}")


class Source:
    """One open recording of one format: declared sensor size, event chunks, and optional extras.

    Subclasses set ``format``, ``width`` / ``height`` (``None`` when the file does not declare them) and
    ``time_unit`` (``None``: floats are seconds, integers µs), optionally ``t_add_us`` (a file-level time
    offset), and implement :meth:`chunks`. ``notes`` collects repairs found while decoding (a truncated tail,
    an assumed version, ...).
    """

    format: str = ""

    def __init__(self, path: Path, time_unit: str | None = None):
        self.path = Path(path)
        self.events_path = self.path  # the file event-level errors name (rpg: events.txt inside the folder)
        self.width: int | None = None
        self.height: int | None = None
        self.time_unit = time_unit
        self.t_add_us = 0
        self.notes: list[str] = []
        #: column order of unnamed 2-D arrays / text columns given by the caller (names like ("x", "y", "t", "p"))
        self.columns: tuple[str, ...] | None = None

    def chunks(self, chunk_events: int = DEFAULT_CHUNK_EVENTS, with_frames: bool = False) -> Iterator[RawChunk]:
        """Event columns in file order, about ``chunk_events`` at a time (memory bounded by the chunk)."""
        raise NotImplementedError

    def frames(self) -> FrameData | None:
        """The intensity frames, if the file has any (formats that interleave them with events, AEDAT4, collect
        them during a :meth:`chunks` pass with ``with_frames=True`` and decode again otherwise)."""
        return None

    def calibration(self, width: int, height: int) -> Camera | None:
        """The camera calibration, if the file has one, for a sensor of ``width`` × ``height``."""
        return None

    def ground_truth(self) -> dict[str, np.ndarray] | None:
        """Ground truth as stored (loosely typed); a ``t_us`` entry is in file time, µs."""
        return None


class RowLocator:
    """Maps an event index to "packet k, event index i" for formats decoded packet by packet."""

    def __init__(self):
        self._starts: list[int] = []
        self._labels: list[str] = []

    def add(self, first_row: int, label: str) -> None:
        self._starts.append(first_row)
        self._labels.append(label)

    def __call__(self, row: int) -> str:
        k = bisect.bisect_right(self._starts, row) - 1
        return f"{self._labels[k]}, event index {row}" if k >= 0 else f"event index {row}"


def numbered_chunks(arrays: Iterator[tuple], chunk_events: int, locate=None) -> Iterator[RawChunk]:
    """:func:`rechunk` a decoder's (t, x, y, p) column tuples into RawChunks that carry their first row's index in
    the file (and ``locate``, the row -> place-in-file describer for error messages, when the format has one)."""
    row = 0
    for t, x, y, p in rechunk(arrays, chunk_events):
        yield RawChunk(t, x, y, p, row) if locate is None else RawChunk(t, x, y, p, row, locate)
        row += len(t)


def rechunk(arrays: Iterator[tuple], chunk_events: int) -> Iterator[tuple]:
    """Regroup a stream of column tuples into tuples of about ``chunk_events`` rows (the last may be shorter)."""
    pending: list[tuple] = []
    count = 0
    for cols in arrays:
        n = len(cols[0])
        if n == 0:
            continue
        pending.append(cols)
        count += n
        while count >= chunk_events:
            merged = tuple(np.concatenate(c) for c in zip(*pending)) if len(pending) > 1 else pending[0]
            yield tuple(c[:chunk_events] for c in merged)
            rest = tuple(c[chunk_events:] for c in merged)
            count = len(rest[0])
            pending = [rest] if count else []
    if count:
        yield tuple(np.concatenate(c) for c in zip(*pending)) if len(pending) > 1 else pending[0]


@contextlib.contextmanager
def native_call(path, what: str, where: str | None = None):
    """Turn any failure of a decoding library into a :class:`RecordingError` naming the file.

    Rust extensions raise ``PanicException`` (a ``BaseException``) on malformed data, so everything but
    interpreter exits is caught here.
    """
    try:
        yield
    except RecordingError:
        raise
    except (KeyboardInterrupt, SystemExit, GeneratorExit):
        raise
    except BaseException as exc:
        message = str(exc).strip() or type(exc).__name__
        raise RecordingError(path, f"{what} failed: {type(exc).__name__}: {message}", where) from exc


#: Seconds a decoding library may spend on a file's structure in a probe before the file is refused.
PROBE_TIMEOUT_S = 10.0


def probe_in_child(path, what: str, fn: Callable[[], object], timeout_s: float = PROBE_TIMEOUT_S) -> None:
    """Run ``fn`` in a forked child first, and refuse the file if it does not finish within ``timeout_s``.

    A C library can loop forever on damaged metadata (HDF5 reading a corrupted attribute does), and a call into
    it cannot be interrupted in-process. The child's own errors are ignored: the caller then runs ``fn``'s work
    itself and reports them. Where ``fork`` is missing, nothing is probed."""
    import signal
    import time

    if not hasattr(os, "fork"):
        return
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the child
        try:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, 1)
            os.dup2(devnull, 2)
            fn()
        except BaseException:  # noqa: BLE001 - reported by the caller's own run
            pass
        os._exit(0)
    deadline = time.monotonic() + timeout_s
    delay = 0.001
    while True:
        done, _ = os.waitpid(pid, os.WNOHANG)
        if done:
            return
        if time.monotonic() > deadline:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            raise RecordingError(path, f"{what} did not finish reading the file's structure within {timeout_s:g} s "
                                       f"(damaged metadata that the library loops on): refused")
        time.sleep(delay)
        delay = min(delay * 2, 0.05)


def check_fits_in_memory(path, nbytes: int, what: str) -> None:
    """Refuse to load ``nbytes`` when that would take more than half the available memory.

    A corrupted header can declare terabytes; allocating them would get the process killed instead of
    raising an error.
    """
    avail = available_memory_bytes()
    if avail is not None and nbytes > avail // 2:
        raise RecordingError(path, f"{what} would need {nbytes / 1e9:.1f} GB, more than half the available "
                                   f"memory ({avail / 1e9:.1f} GB): a corrupted size, or a file to stream with "
                                   f"iter_event_chunks")


_KINDS = ((stat.S_ISFIFO, "a named pipe (FIFO)"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))


def check_regular(path, folder: bool = True) -> None:
    """Refuse at once, in one line, a path that is not a regular file (or, when ``folder``, a folder): a named pipe
    (opening one waits for a writer, possibly forever), a device (/dev/zero never ends), a socket, a symbolic link
    loop or a dangling link. Only ``stat`` is called: nothing is opened."""
    path = Path(path)
    try:
        st = os.stat(path)  # follows links; never blocks, whatever the file is
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise RecordingError(path, "a loop of symbolic links (the link leads back to itself): not a file") \
                from None
        if exc.errno == errno.ENOENT:
            if os.path.islink(path):
                raise RecordingError(path, f"a symbolic link to {os.readlink(path)}, which does not exist") from None
            raise RecordingError(path, "no such file or folder") from None
        raise RecordingError(path, f"cannot read it: {exc.strerror or exc}") from None
    if stat.S_ISREG(st.st_mode) or (folder and stat.S_ISDIR(st.st_mode)):
        return
    if stat.S_ISDIR(st.st_mode):
        raise RecordingError(path, "a folder, expected a file")
    kind = next((name for test, name in _KINDS if test(st.st_mode)), "not a regular file")
    link = f" (a link to {os.path.realpath(path)})" if os.path.islink(path) else ""
    raise RecordingError(path, f"{kind}{link}, not a recording file: refused without opening it (reading it could "
                               f"wait forever or never end)")


def regular_sibling(path) -> bool:
    """Whether an optional file beside a recording (images.txt, calib.txt, ...) is there: ``False`` when absent,
    ``True`` when a regular file; anything else (a pipe, a device, a link loop) is refused by :func:`check_regular`."""
    if not os.path.lexists(path):
        return False
    check_regular(path, folder=False)
    return True


def file_size(path: Path) -> int:
    try:
        return path.stat().st_size
    except OSError as exc:
        raise RecordingError(path, f"cannot read the file: {exc}") from exc


# ------------------------------------------------------------------------------------ column layouts of arrays
#: Names accepted for each event column (compared case-insensitively) in HDF5 groups, compound and npz files.
COLUMN_NAMES = {
    "t": ("t", "ts", "t_us", "timestamp", "timestamps", "time", "times"),
    "x": ("x", "xs"),
    "y": ("y", "ys"),
    "p": ("p", "ps", "pol", "polarity", "polarities", "on"),
}


def match_columns(names) -> dict[str, str] | None:
    """Map roles t, x, y, p to the names in ``names`` that hold them, or ``None`` if one is missing."""
    lower = {str(n).lower(): n for n in names}
    found = {}
    for role, aliases in COLUMN_NAMES.items():
        hit = next((lower[a] for a in aliases if a in lower), None)
        if hit is None:
            return None
        found[role] = hit
    return found


def parse_columns(value) -> tuple[str, ...] | None:
    """A column order given by a user: ``"x,y,t,p"``, ``"x y t p"`` or a sequence of names → a tuple of 4 names
    that name t, x, y and p once each (aliases of ``COLUMN_NAMES`` allowed), or ``None`` for an empty value."""
    if value is None or (not isinstance(value, str) and len(value) == 0) or value == "":
        return None
    if isinstance(value, bytes):
        value = value.decode("utf-8", "replace")
    names = [s.strip() for s in value.replace(";", ",").replace(" ", ",").split(",") if s.strip()] \
        if isinstance(value, str) else [n.decode() if isinstance(n, bytes) else str(n) for n in value]
    roles = match_columns(names)
    if roles is None or len(names) != 4 or len({n.lower() for n in names}) != 4:
        raise ValueError(f"columns={value!r}: expected 4 names that name t, x, y, p once each, e.g. "
                         f"'x,y,t,p' (aliases: {', '.join(a for v in COLUMN_NAMES.values() for a in v[:3])}, ...)")
    return tuple(names)


def columns_of_2d(path, sample: np.ndarray, declared=None) -> tuple[tuple[int, int, int, int], str | None]:
    """Column indices (t, x, y, p) of an (N, 4) event array, and a note saying how they were guessed (if they were).

    ``declared`` (a string like ``"t,x,y,p"`` or a sequence of names) wins. Otherwise the time column is the
    one that is (nearly) non-decreasing: column 0 → (t, x, y, p) as in rpg / tonic exports, column 2 →
    (x, y, t, p) as in MVSEC. Anything else is refused rather than guessed.
    """
    if declared is not None:
        if isinstance(declared, bytes):
            declared = declared.decode("utf-8", "replace")
        names = [s.strip() for s in declared.replace(";", ",").replace(" ", ",").split(",") if s.strip()] \
            if isinstance(declared, str) else [n.decode() if isinstance(n, bytes) else str(n) for n in declared]
        roles = match_columns(names)
        if roles is None or len(names) != 4:
            raise RecordingError(path, f"column names {names!r} do not name t, x, y, p once each")
        return tuple(names.index(roles[r]) for r in "txyp"), None
    if len(sample) < 3:
        return (0, 1, 2, 3), "2-D event array without column names, too short to check: read as (t, x, y, p)"
    frac = [float(np.mean(np.diff(sample[:, c].astype(np.float64)) >= 0)) for c in (0, 2)]
    if frac[0] >= 0.9 and frac[0] >= frac[1]:
        return (0, 1, 2, 3), "2-D event array without column names: read as (t, x, y, p) (column 0 is time-ordered)"
    if frac[1] >= 0.9:
        return (2, 0, 1, 3), "2-D event array without column names: read as (x, y, t, p) (column 2 is time-ordered)"
    raise RecordingError(path, "2-D event array without column names and no time-ordered column 0 or 2: "
                               "cannot tell which column is time; store a structured array or name the columns")
