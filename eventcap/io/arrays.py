"""NumPy event files: ``.npy`` (structured or (N, 4)) and ``.npz`` (columns, plus optional size, frames, calibration).

Read (never with pickles):

- ``.npy``: a structured array with fields t, x, y, p (or aliases, see ``source.COLUMN_NAMES``), or an (N, 4)
  or (4, N) array (C or Fortran order) whose column order is given (``columns=("x", "y", "t", "p")``) or whose
  time column is recognised as in HDF5 files. Memory-mapped, so it streams. A file shorter than its header
  declares (truncated) keeps its complete events and says so (an array stored column by column cannot: refused);
  trailing bytes are reported and ignored.
- ``.npz``: column arrays ``t, x, y, p`` (or aliases) or one array ``events`` (structured or (N, 4));
  optional ``width``, ``height``, ``time_unit``; frames ``frames`` (N, H, W) with ``frames_t_us`` and optional
  ``frames_exposure_us``; ``calibration`` (9,) ``fx fy cx cy k1 k2 p1 p2 k3`` or (4,); ground-truth arrays
  under ``ground_truth/<name>``. Members are loaded whole (zip members do not stream).

Integer times are µs, float times seconds, unless ``time_unit`` says otherwise.
Written (:func:`write_npz`): that npz layout with ``t`` int64 (file time, µs), ``x``, ``y`` uint16, ``p`` int8.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from eventcap.camera import Camera
from eventcap.io.checks import RawChunk, parse_time_unit, times_to_us
from eventcap.io.recording import RecordingError
from eventcap.io.registry import ReaderSpec
from eventcap.io.source import (
    DEFAULT_CHUNK_EVENTS,
    FrameData,
    Source,
    check_fits_in_memory,
    columns_of_2d,
    match_columns,
    native_call,
)

NPY_MAGIC = b"\x93NUMPY"
ZIP_MAGICS = (b"PK\x03\x04", b"PK\x05\x06")


def _event_major(path, arr: np.ndarray, notes: list[str], where: str) -> np.ndarray:
    """An unnamed 2-D event array as (N, 4) (a (4, N) array is transposed, a view; noted)."""
    if arr.ndim == 2 and arr.shape[0] == 4 and arr.shape[1] != 4:
        notes.append(f"{where} has shape {arr.shape}: read as 4 rows of {arr.shape[1]} events, i.e. (4, N)")
        return arr.T
    return arr


def _event_columns(path, arr: np.ndarray, notes: list[str], where: str, declared=None):
    """(t, x, y, p) views or a column-index tuple for a structured or (N, 4) array."""
    if arr.dtype.names:
        roles = match_columns(arr.dtype.names)
        if roles is None:
            raise RecordingError(path, f"structured array has fields {list(arr.dtype.names)}: expected t, x, y, p "
                                       f"(or aliases)", where)
        if arr.ndim != 1:
            raise RecordingError(path, f"structured event array must be 1-D, got shape {arr.shape}", where)
        return ("fields", tuple(roles[r] for r in "txyp"))
    if arr.ndim == 2 and arr.shape[1] == 4:
        cols, note = columns_of_2d(path, np.asarray(arr[:100_000]), declared)
        if note:
            notes.append(note)
        return ("2d", cols)
    raise RecordingError(path, f"event array has shape {arr.shape} and dtype {arr.dtype}: expected a structured "
                               f"array with t, x, y, p, or shape (N, 4) or (4, N)", where)


def _split(arr: np.ndarray, layout, a: int, b: int):
    kind, keys = layout
    block = arr[a:b]
    if kind == "fields":
        return tuple(np.asarray(block[k]) for k in keys)
    return tuple(np.asarray(block[:, c]) for c in keys)


class NpySource(Source):
    """A ``.npy`` file of events (memory-mapped)."""

    format = "npy"

    def __init__(self, path: Path, time_unit: str | None = None, columns: tuple[str, ...] | None = None):
        super().__init__(path, time_unit)
        self.columns = columns
        self._array = _event_major(path, self._map(), self.notes, "the array")
        self._layout = _event_columns(path, self._array, self.notes, "array", columns)

    def _map(self) -> np.ndarray:
        path = self.path
        with native_call(path, "npy header reader (numpy)", "header"), open(path, "rb") as f:
            version = np.lib.format.read_magic(f)
            if version == (1, 0):
                shape, fortran, dtype = np.lib.format.read_array_header_1_0(f)
            else:
                shape, fortran, dtype = np.lib.format.read_array_header_2_0(f)
            offset = f.tell()
        if dtype.hasobject:
            raise RecordingError(path, "the array holds Python objects: refusing to unpickle", "header")
        if len(shape) not in (1, 2) or any(s < 0 for s in shape):
            raise RecordingError(path, f"event array has shape {shape}: expected (N,) structured, (N, 4) or (4, N)",
                                 "header")
        order = "F" if fortran and len(shape) == 2 else "C"
        # The axis that counts events, and whether each event's values lie together on disk (then a truncated
        # file keeps its complete events) or column by column (then it cannot).
        events_axis = 1 if len(shape) == 2 and shape[0] == 4 and shape[1] != 4 else 0
        event_major = len(shape) == 1 or (events_axis == 0) == (order == "C")
        per_event = dtype.itemsize * (shape[1 - events_axis] if len(shape) == 2 else 1)
        if per_event == 0:
            raise RecordingError(path, f"event array rows have no bytes (dtype {dtype}, shape {shape})", "header")
        data_bytes = path.stat().st_size - offset
        declared = int(shape[events_axis])
        available = data_bytes // per_event
        rows = min(declared, available)
        if available < declared:
            if not event_major:
                raise RecordingError(path, f"file truncated: {data_bytes} of {declared * per_event} data bytes, and "
                                           f"the {shape} array is stored column by column ({order} order), so no "
                                           f"event is complete", "data")
            self.notes.append(f"file truncated: the header declares {declared} events but only {available} complete "
                              f"ones are stored: kept those")
        elif data_bytes > declared * per_event:
            self.notes.append(f"{data_bytes - declared * per_event} byte(s) after the declared {declared} events: "
                              f"ignored")
        kept = tuple(shape) if len(shape) == 1 else ((rows, shape[1]) if events_axis == 0 else (shape[0], rows))
        if len(shape) == 1:
            kept = (rows,)
        if rows == 0:
            return np.empty(kept, dtype=dtype, order=order)
        with native_call(path, "npy reader (numpy)", "data"):
            return np.memmap(path, dtype=dtype, mode="r", offset=offset, shape=kept, order=order)

    def chunks(self, chunk_events: int = DEFAULT_CHUNK_EVENTS, with_frames: bool = False) -> Iterator[RawChunk]:
        n = len(self._array)
        for a in range(0, n, chunk_events):
            b = min(n, a + chunk_events)
            yield RawChunk(*_split(self._array, self._layout, a, b), a)


class NpzSource(Source):
    """A ``.npz`` archive of event columns and optional extras."""

    format = "npz"

    def __init__(self, path: Path, time_unit: str | None = None, columns: tuple[str, ...] | None = None):
        super().__init__(path, time_unit)
        self.columns = columns
        with native_call(path, "npz reader (numpy)", "archive"), np.load(path, allow_pickle=False) as npz:
            self._keys = list(npz.files)
            total = sum(i.file_size for i in npz.zip.infolist())
        check_fits_in_memory(path, total, "the archive's arrays")
        roles = match_columns(k for k in self._keys if "/" not in k)
        if roles is not None:
            self._cols = tuple(self._load(roles[r]) for r in "txyp")
            n = {len(c) if c.ndim == 1 else -1 for c in self._cols}
            if len(n) != 1 or -1 in n:
                raise RecordingError(path, f"event columns {[roles[r] for r in 'txyp']} must be 1-D and of one "
                                           f"length, got shapes {[c.shape for c in self._cols]}")
        elif "events" in self._keys:
            arr = _event_major(path, self._load("events"), self.notes, "array 'events'")
            layout = _event_columns(path, arr, self.notes, "array 'events'", columns)
            self._cols = _split(arr, layout, 0, len(arr))
        else:
            raise RecordingError(path, f"no event data: expected arrays t, x, y, p (or aliases) or 'events'; found "
                                       f"{self._keys}")
        if "width" in self._keys and "height" in self._keys:
            try:
                self.width, self.height = int(self._load("width").item()), int(self._load("height").item())
            except (TypeError, ValueError) as exc:
                raise RecordingError(path, f"width/height are not integers: {exc}") from exc
            if not (0 < self.width <= 65536 and 0 < self.height <= 65536):
                raise RecordingError(path, f"sensor size {self.width} × {self.height} is not a positive 16-bit size")
        if "time_unit" in self._keys and self.time_unit is None:
            try:
                self.time_unit = parse_time_unit(str(self._load("time_unit").item()))
            except ValueError as exc:
                raise RecordingError(path, str(exc), "array 'time_unit'") from exc

    def _load(self, key: str) -> np.ndarray:
        with native_call(self.path, "npz reader (numpy)", f"array {key!r}"), \
                np.load(self.path, allow_pickle=False) as npz:
            return npz[key]

    def chunks(self, chunk_events: int = DEFAULT_CHUNK_EVENTS, with_frames: bool = False) -> Iterator[RawChunk]:
        n = len(self._cols[0])
        for a in range(0, n, chunk_events):
            b = min(n, a + chunk_events)
            yield RawChunk(*(c[a:b] for c in self._cols), a)

    def frames(self) -> FrameData | None:
        if "frames" not in self._keys:
            return None
        if "frames_t_us" not in self._keys:
            self.notes.append("array 'frames' has no 'frames_t_us' beside it: frames ignored")
            return None
        images = self._load("frames")
        t = times_to_us(self.path, self._load("frames_t_us"), "us", "frames_t_us", lambda i: f"frame {i}")
        exposure = None
        if "frames_exposure_us" in self._keys:
            exposure = times_to_us(self.path, self._load("frames_exposure_us"), "us", "frames_exposure_us",
                                      lambda i: f"frame {i}")
        return FrameData(images, t, exposure)

    def calibration(self, width: int, height: int) -> Camera | None:
        if "calibration" not in self._keys:
            return None
        c = np.asarray(self._load("calibration"), dtype=np.float64).reshape(-1)
        if c.shape not in ((4,), (9,)):
            raise RecordingError(self.path, f"expected 4 values (fx fy cx cy) or 9 (… k1 k2 p1 p2 k3), got {c.shape}",
                                 "array 'calibration'")
        try:
            return Camera(width, height, *c[:4], c[4:] if len(c) == 9 else np.zeros(5))
        except ValueError as exc:
            raise RecordingError(self.path, str(exc), "array 'calibration'") from exc

    def ground_truth(self) -> dict[str, np.ndarray] | None:
        out = {k.removeprefix("ground_truth/"): self._load(k) for k in self._keys if k.startswith("ground_truth/")}
        return out or None


def write_npz(path: Path, events: np.ndarray, width: int, height: int, frames=None, calibration=None,
              ground_truth=None) -> None:
    """Write events (``EVENT_DTYPE``, file time µs) and optional extras as a compressed npz (layout above)."""
    arrays = {"t": events["t"].astype(np.int64), "x": events["x"], "y": events["y"], "p": events["p"],
              "width": np.int64(width), "height": np.int64(height)}
    if frames is not None:
        images, t_us, exposure_us = frames
        arrays["frames"] = images
        arrays["frames_t_us"] = np.asarray(t_us, dtype=np.int64)
        if exposure_us is not None:
            arrays["frames_exposure_us"] = np.asarray(exposure_us, dtype=np.int64)
    if calibration is not None:
        arrays["calibration"] = np.array([calibration.fx, calibration.fy, calibration.cx, calibration.cy,
                                          *calibration.dist])
    for k, v in (ground_truth or {}).items():
        arrays[f"ground_truth/{k}"] = np.asarray(v)
    with open(path, "wb") as f:
        np.savez_compressed(f, **arrays)


READERS = [
    ReaderSpec(name="npy", description="NumPy .npy: a structured array, or (N, 4) / (4, N) columns",
               extensions=(".npy",), magic=(NPY_MAGIC,), magic_name="a NumPy .npy", source="eventcap.io.arrays:NpySource",
               columns=True, declares_size=False, library="numpy"),
    ReaderSpec(name="npz", description="NumPy .npz: event columns, frames, calibration", extensions=(".npz",),
               magic=ZIP_MAGICS, magic_name="a NumPy .npz (zip)", source="eventcap.io.arrays:NpzSource", columns=True,
               declares_size=False, extras="frames, calibration", library="numpy"),
]
