"""Read any supported recording into a :class:`RawRecording`, or stream its events chunk by chunk."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from eventcap.camera import Camera
from eventcap.events import EVENT_DTYPE
from eventcap.io.checks import (
    MAX_GAP_US,
    ColumnConverter,
    OrderReport,
    TimeGuard,
    check_event_rate,
    parse_time_unit,
    sort_and_dedup,
)
from eventcap.io.detect import detect_format
from eventcap.io.registry import readers
from eventcap.io.recording import Frames, RawRecording, RecordingError, logger
from eventcap.io.sizes import (  # noqa: F401 - part of this module's API
    KNOWN_SENSORS,
    MAX_OUTSIDE_SHARE,
    MIN_INFERRED_SIDE,
    OUTLIER_BUDGET_MAX,
    PLAUSIBLE_HEIGHT,
    PLAUSIBLE_WIDTH,
    CoordinateStats,
    size_note,
)
from eventcap.io.source import DEFAULT_CHUNK_EVENTS, FrameData, Source, check_regular, parse_columns



@dataclass(frozen=True)
class Roi:
    """A sensor region: top-left pixel ``(x, y)`` and its ``width`` × ``height`` in pixels."""

    x: int
    y: int
    width: int
    height: int


def open_source(path, format: str | None = None, time_unit: str | None = None, columns=None) -> Source:
    """The format reader for ``path`` (format detected from the content when ``format`` is ``None``), from the
    registered readers (:mod:`eventcap.io.registry`)."""
    path = Path(path)
    check_regular(path)
    registry = readers()
    fmt = detect_format(path) if format is None else str(format).lower()
    spec = registry.find(fmt)
    if spec is None:
        raise ValueError(f"unknown format {format!r}: expected one of {', '.join(registry.names())}")
    unit = parse_time_unit(time_unit)
    cols = parse_columns(columns)
    if cols is not None and not spec.columns:
        raise ValueError(f"columns={columns!r} applies to array and text files ({', '.join(registry.column_formats())}); "
                         f"{path} is {fmt}, whose fields are named by the format")
    return spec.load("source")(path, unit, **({"columns": cols} if cols is not None else {}))


def __getattr__(name: str):
    if name == "COLUMN_FORMATS":  # the formats whose columns can be unnamed, from the registry
        return readers().column_formats()
    raise AttributeError(name)


def _sensor_size(source: Source, width: int | None, height: int | None) -> tuple[int | None, int | None]:
    """The declared sensor size: the file's, else the caller's; a conflict between the two is an error."""
    if (width is None) != (height is None):
        raise ValueError(f"give both width and height or neither, got width={width}, height={height}")
    if width is not None and (int(width) <= 0 or int(height) <= 0 or width > 65536 or height > 65536):
        raise ValueError(f"width and height must be positive 16-bit sizes, got {width} × {height}")
    if source.width is not None:
        if width is not None and (int(width), int(height)) != (source.width, source.height):
            raise ValueError(f"{source.path}: the file declares a {source.width} × {source.height} sensor but "
                             f"width={width}, height={height} were given")
        return source.width, source.height
    return (int(width), int(height)) if width is not None else (None, None)


def _converter(source: Source, width, height) -> ColumnConverter:
    conv = ColumnConverter(source.events_path, width, height, source.time_unit, source.t_add_us)
    conv.unit_guessed = source.time_unit is None and source.format in readers().column_formats()
    return conv


def _max_gap_us(max_gap_s) -> int | None:
    """max_gap_s in µs; None when not given (the default, with the outlier rule relative to the events' pace)."""
    if max_gap_s is None:
        return None
    try:
        v = float(max_gap_s)
    except (TypeError, ValueError):
        v = float("nan")
    if not (np.isfinite(v) and 0 < v <= 1e9):
        raise ValueError(f"max_gap_s: expected seconds > 0 (at most 1e9), got {max_gap_s!r}")
    return int(round(v * 1e6))


def _time_guard(source: Source, max_gap_us: int | None) -> TimeGuard:
    return TimeGuard(source.events_path, MAX_GAP_US if max_gap_us is None else max_gap_us,
                     wraps_us=readers().wraps_us(source.format), relative=max_gap_us is None)


def _check_rate(source: Source, n: int, span_us: int) -> None:
    """The whole recording's event rate against what sensors make (:func:`eventcap.io.checks.check_event_rate`)."""
    check_event_rate(source.events_path, n, span_us)


def recording_has_frames(path, format: str | None = None) -> bool:
    """Whether a recording (any format of :mod:`eventcap.io`, or the project's zarr) holds intensity frames; cheap for
    the project's zarr and AEDAT4 (a declared frame stream), a decode of the frames otherwise."""
    p = Path(path)
    check_regular(p)
    if (p / "zarr.json").is_file() or (p / ".zgroup").is_file():
        return (p / "frames").is_dir()
    source = open_source(p, format or None)
    if source.format == "aedat4":
        return getattr(source, "_frame_id", None) is not None
    return source.frames() is not None


def recording_has_ground_truth(path, format: str | None = None) -> bool:
    """Whether a recording carries a body's ground truth (what the simulated detector and the evaluation need).
    Only the project's zarr format can: a synthetic capture keeps it in its ``ground_truth`` group. The other formats
    never give one (what some store, such as the rpg dataset's camera poses, is not a body's motion). Cheap: reads
    no data."""
    p = Path(path)
    if format not in (None, "", "eventcap"):
        return False
    if (p / "zarr.json").is_file() or (p / ".zgroup").is_file():
        return (p / "ground_truth").is_dir()
    return False


def read_recording(path, format: str | None = None, time_window_us: tuple[int, int] | None = None,
                   roi: Roi | tuple[int, int, int, int] | None = None, *, width: int | None = None,
                   height: int | None = None, time_unit: str | None = None, columns=None,
                   y_up: bool = False, max_gap_s: float | None = None) -> RawRecording:
    """Decode a recording (any format of :mod:`eventcap.io`) into a checked :class:`RawRecording`.

    - ``format``: a registered reader's format (``eventcap.io.registry.readers().names()``); ``None`` detects it
      from the content (then the extension).
    - ``time_window_us``: ``(start, end)`` in µs on the recording's clock (0 = first event), half-open; keeps
      the events and the frames (by exposure centre) inside it. Times stay on the recording's clock.
    - ``roi``: :class:`Roi` or ``(x, y, width, height)``; keeps events and frame pixels inside it, shifted so
      the ROI's corner is (0, 0); the calibration's principal point moves with it.
    - ``width`` / ``height``: sensor size for files that do not declare one (otherwise inferred from the
      events and noted); conflicting with a declared size is an error.
    - ``time_unit``: unit of the time column of array/text formats ("s", "ms", "us", "ns") when the file's
      default (integers µs, floats s) is wrong.
    - ``columns``: the column order of unnamed (N, 4) / (4, N) arrays and text files, e.g. ``"x,y,t,p"`` or
      ``("x", "y", "t", "p")`` (npy, npz, hdf5, text); without it, names in the file or the time-ordered column
      decide (noted).
    - ``y_up``: the file's y axis points up (origin bottom-left): events are flipped to the project's top-left
      origin (``y → height - 1 - y``). Frames are taken as stored (images are stored top row first).
    - ``max_gap_s``: the longest pause between neighbouring events taken as real (default 60 s); longer jumps in
      time are outliers (dropped), a decoder's artefact (undone or cut) or refused
      (:class:`eventcap.io.checks.TimeGuard`).

    Raises :class:`RecordingError` (a ``ValueError``) naming the file, the position and the problem; every
    repair made is in ``repairs`` and logged as a warning on the ``eventcap.io`` logger.
    """
    source = open_source(path, format, time_unit, columns)
    path = source.path
    width, height = _sensor_size(source, width, height)
    conv = _converter(source, width, height)
    guard = _time_guard(source, _max_gap_us(max_gap_s))
    parts = [guard.feed(conv.convert(raw)) for raw in source.chunks(DEFAULT_CHUNK_EVENTS, with_frames=True)]
    parts = [p for p in (*parts, guard.finish()) if len(p)]
    events = np.concatenate(parts) if len(parts) > 1 else (parts[0] if parts else np.empty(0, EVENT_DTYPE))
    if len(events) == 0:
        raise RecordingError(path, "the recording contains no events" + "".join(f"; {n}" for n in source.notes))
    events, order = sort_and_dedup(events)
    _check_rate(source, len(events), int(events["t"][-1]) - int(events["t"][0]))
    frame_data = source.frames()
    repairs = [*source.notes, *conv.repairs(), *guard.repairs(), *order.repairs()]
    if width is None:
        events, width, height, note = infer_sensor_size(events, path)
        repairs.append(note)
        if len(events) == 0:
            raise RecordingError(path, "the recording contains no events inside the inferred sensor")
    if y_up:
        events["y"] = height - 1 - events["y"]
    t_offset = int(events["t"][0])
    events["t"] -= t_offset
    frames = _finish_frames(frame_data, path, t_offset, width, height, repairs)
    calibration = source.calibration(width, height)
    ground_truth = source.ground_truth()
    if ground_truth is not None and "t_us" in ground_truth:
        ground_truth = {**ground_truth, "t_us": np.asarray(ground_truth["t_us"], dtype=np.int64) - t_offset}
    if time_window_us is not None:
        events, frames, ground_truth = _time_window(path, time_window_us, events, frames, ground_truth)
    if roi is not None:
        events, frames, calibration, width, height = _crop(path, roi, events, frames, calibration, width, height)
    for repair in repairs:
        logger.warning("%s: %s", path, repair)
    return RawRecording(events, width, height, t_offset, path, source.format, frames, calibration, ground_truth,
                        tuple(repairs))


def infer_sensor_size(events: np.ndarray, path=None, how: str = "pass width= and height= (source.width, "
                      "source.height)") -> tuple[np.ndarray, int, int, str]:
    """The sensor size of events whose file does not declare one (:mod:`eventcap.io.sizes` says how it is judged):
    the events without the outliers, the width and height, and the note saying what was inferred and dropped.
    Raises :class:`RecordingError` when the events do not show a plausible sensor."""
    stats = CoordinateStats()
    stats.add(events["x"], events["y"])
    d = stats.judge(path, how)
    note = d.note
    if d.dropped:
        kept = events[(events["x"] < d.keep_x) & (events["y"] < d.keep_y)]
        # the exact count (the streaming statistics bound it from below when both axes are cut)
        note = size_note(d.width, d.height, len(events) - len(kept), d.reasons)
        events = kept
    return events, d.width, d.height, note


# ------------------------------------------------------------------------------------------------------- frames
def _to_unit_float(path, images: np.ndarray, locate) -> np.ndarray:
    if images.dtype == np.uint8:
        return images.astype(np.float32) / np.float32(255.0)
    if images.dtype == np.uint16:
        return images.astype(np.float32) / np.float32(65535.0)
    if images.dtype == bool:
        return images.astype(np.float32)
    if images.dtype.kind == "f":
        per_frame_ok = np.all(np.isfinite(images) & (images >= 0) & (images <= 1), axis=(1, 2))
        if not per_frame_ok.all():
            i = int(np.argmin(per_frame_ok))
            raise RecordingError(path, f"float pixel values must be finite and in [0, 1], got min "
                                       f"{np.nanmin(images[i])}, max {np.nanmax(images[i])}", locate(i))
        return images.astype(np.float32)
    raise RecordingError(path, f"unsupported pixel type {images.dtype}: expected uint8, uint16 or float in [0, 1]")


def _finish_frames(data: FrameData | None, path: Path, t_offset: int, width: int, height: int,
                   repairs: list[str]) -> Frames | None:
    """Check and convert a source's frames: grey float32 in [0, 1], sorted distinct times on the events' clock."""
    if data is None:
        return None
    images = np.asarray(data.images)
    if images.ndim == 4 and images.shape[3] in (3, 4):
        # Rec. 601 luma; alpha dropped.
        rgb = images[..., :3].astype(np.float32)
        images = rgb @ np.array([0.299, 0.587, 0.114], dtype=np.float32)
        if data.images.dtype == np.uint8:
            images /= 255.0
        elif data.images.dtype == np.uint16:
            images /= 65535.0
        repairs.append("colour frames converted to grey (Rec. 601 luma)")
    if images.ndim != 3:
        raise RecordingError(path, f"frames: expected (N, height, width) images, got shape {images.shape}")
    n = images.shape[0]
    if images.shape[1:] != (height, width):
        raise RecordingError(path, f"frames are {images.shape[2]} wide and {images.shape[1]} high but the sensor is "
                                   f"{width} × {height}", data.locate(0))
    t = np.asarray(data.t_us, dtype=np.int64)
    exposure = None if data.exposure_us is None else np.asarray(data.exposure_us, dtype=np.int64)
    if t.shape != (n,) or (exposure is not None and exposure.shape != (n,)):
        raise RecordingError(path, f"frames: {n} images but {t.shape[0]} time stamps"
                                   + ("" if exposure is None else f" and {exposure.shape[0]} exposure times"))
    if exposure is not None and np.any(exposure < 0):
        i = int(np.argmax(exposure < 0))
        raise RecordingError(path, f"negative exposure time {exposure[i]} µs", data.locate(i))
    pixels = _to_unit_float(path, images, data.locate)
    if n > 1 and np.any(np.diff(t) < 0):
        order = np.argsort(t, kind="stable")
        repairs.append(f"sorted {n} frames by time (frame time went backwards at "
                       f"{int(np.sum(np.diff(t) < 0))} place(s))")
        pixels, t = pixels[order], t[order]
        exposure = None if exposure is None else exposure[order]
    if n > 1 and np.any(np.diff(t) == 0):
        keep = np.concatenate([[True], np.diff(t) != 0])
        repairs.append(f"dropped {int(n - keep.sum())} frame(s) with the same time stamp as the frame before")
        pixels, t = pixels[keep], t[keep]
        exposure = None if exposure is None else exposure[keep]
    try:
        return Frames(np.ascontiguousarray(pixels), t - t_offset, exposure)
    except ValueError as exc:  # a check above missed a case: still name the file
        raise RecordingError(path, f"frames: {exc}") from exc


# ---------------------------------------------------------------------------------------------- window and ROI
def _time_window(path, window, events, frames, ground_truth):
    try:
        start, end = (int(v) for v in window)
    except (TypeError, ValueError):
        raise ValueError(f"time_window_us: expected (start, end) in µs, got {window!r}") from None
    if not start < end:
        raise ValueError(f"time_window_us: expected start < end, got ({start}, {end})")
    t = events["t"]
    a, b = np.searchsorted(t, start, "left"), np.searchsorted(t, end, "left")
    if a == b:
        raise RecordingError(path, f"no events in the time window [{start}, {end}) µs: the recording's events span "
                                   f"0..{int(t[-1])} µs")
    events = events[a:b]
    if frames is not None:
        keep = (frames.t_us >= start) & (frames.t_us < end)
        frames = Frames(frames.images[keep], frames.t_us[keep],
                        None if frames.exposure_us is None else frames.exposure_us[keep]) if keep.any() else None
    if ground_truth is not None and "t_us" in ground_truth:
        gt_t = np.asarray(ground_truth["t_us"])
        keep = (gt_t >= start) & (gt_t < end)
        ground_truth = {k: (np.asarray(v)[keep] if np.ndim(v) and len(v) == len(gt_t) else v)
                        for k, v in ground_truth.items()}
    return events, frames, ground_truth


def _crop(path, roi, events, frames, calibration: Camera | None, width: int, height: int):
    r = roi if isinstance(roi, Roi) else Roi(*(int(v) for v in roi))
    if r.x < 0 or r.y < 0 or r.width <= 0 or r.height <= 0 or r.x + r.width > width or r.y + r.height > height:
        raise ValueError(f"roi {r} does not lie inside the {width} × {height} sensor")
    x, y = events["x"], events["y"]
    keep = (x >= r.x) & (x < r.x + r.width) & (y >= r.y) & (y < r.y + r.height)
    if not keep.any():
        raise RecordingError(path, f"no events inside the region of interest {r}")
    events = events[keep]
    events["x"] -= r.x
    events["y"] -= r.y
    if frames is not None:
        frames = Frames(np.ascontiguousarray(frames.images[:, r.y:r.y + r.height, r.x:r.x + r.width]), frames.t_us,
                        frames.exposure_us)
    if calibration is not None:
        c = calibration
        calibration = Camera(r.width, r.height, c.fx, c.fy, c.cx - r.x, c.cy - r.y, c.dist, c.R, c.t)
    return events, frames, calibration, r.width, r.height


# ---------------------------------------------------------------------------------------------------- streaming
class EventChunks:
    """A recording's events as a stream of ``EVENT_DTYPE`` chunks, in bounded memory (for conversions).

    Opening reads the header and the first chunk (to fix ``t_offset_us``); each iteration decodes the file again
    from the start. Chunks hold about ``chunk_events`` events on the same clock as :func:`read_recording`
    (µs since the first event); the checks are the same, and sorting / duplicate removal happen within a window
    of one chunk (events of one time stamp are never split between chunks). An event earlier than events already
    streamed cannot be repaired in bounded memory: that raises :class:`RecordingError` (use
    :func:`read_recording`). ``repairs`` lists the repairs of the iteration so far.
    """

    def __init__(self, path, format: str | None = None, chunk_events: int = DEFAULT_CHUNK_EVENTS,
                 width: int | None = None, height: int | None = None, time_unit: str | None = None,
                 columns=None, y_up: bool = False, max_gap_s: float | None = None):
        if int(chunk_events) < 1:
            raise ValueError(f"chunk_events must be ≥ 1, got {chunk_events}")
        self.chunk_events = int(chunk_events)
        self.y_up = bool(y_up)
        self._max_gap_us = _max_gap_us(max_gap_s)
        self._guard: TimeGuard | None = None
        self._source = open_source(path, format, time_unit, columns)
        self.path, self.format = self._source.path, self._source.format
        w, h = _sensor_size(self._source, width, height)
        if w is None:
            raise RecordingError(self.path, "the file does not declare its sensor size: pass width= and height= to "
                                            "stream it (read_recording infers it)")
        self.width, self.height = w, h
        self._conv: ColumnConverter | None = None
        self._order = OrderReport()
        chunks = self._absolute_chunks()
        first = next(chunks, None)
        chunks.close()  # releases the decoder's file now, not at garbage collection
        if first is None:
            raise RecordingError(self.path, "the recording contains no events"
                                 + "".join(f"; {n}" for n in self._source.notes))
        self.t_offset_us = int(first["t"][0])

    @property
    def repairs(self) -> tuple[str, ...]:
        conv = [] if self._conv is None else self._conv.repairs()
        guard = [] if self._guard is None else self._guard.repairs()
        return (*self._source.notes, *conv, *guard, *self._order.repairs())

    def __iter__(self) -> Iterator[np.ndarray]:
        n, last = 0, None
        for chunk in self._absolute_chunks():
            n += len(chunk)
            last = int(chunk["t"][-1])
            chunk["t"] -= self.t_offset_us
            if self.y_up:
                chunk["y"] = self.height - 1 - chunk["y"]
            yield chunk
        if n:
            _check_rate(self._source, n, last - self.t_offset_us)
        for repair in self.repairs:
            logger.warning("%s: %s", self.path, repair)

    def _decoded(self) -> Iterator[tuple[np.ndarray, int, object]]:
        """(events kept by the time guard, the file index of the first decoded event of the stretch, its locator)."""
        self._guard = guard = _time_guard(self._source, self._max_gap_us)
        locate, row = None, 0
        for raw in self._source.chunks(self.chunk_events):
            locate, row = raw.locate, raw.row0
            yield guard.feed(self._conv.convert(raw)), row, locate
        yield guard.finish(), row, locate or (lambda r: f"event index {r}")

    def _absolute_chunks(self) -> Iterator[np.ndarray]:
        self._conv = _converter(self._source, self.width, self.height)
        self._order = OrderReport()
        carry = np.empty(0, EVENT_DTYPE)
        streamed_t: int | None = None
        locate = None
        for ev, row0, locate in self._decoded():
            if len(carry):
                ev = np.concatenate([carry, ev])
            if streamed_t is not None and len(ev) and ev["t"].min() < streamed_t:
                i = int(np.argmax(ev["t"] < streamed_t)) - len(carry)
                raise RecordingError(self.path, f"time goes back to {int(ev['t'].min())} µs, before events already "
                                                f"streamed (up to {streamed_t} µs): cannot sort in bounded memory; "
                                                f"read_recording sorts it in memory", locate(row0 + max(i, 0)))
            ev, report = sort_and_dedup(ev)
            self._order.add(report, row0 - len(carry))
            # Hold back the last time stamp's events: its run may continue in the next chunk.
            cut = int(np.searchsorted(ev["t"], ev["t"][-1], "left")) if len(ev) else 0
            out, carry = ev[:cut], ev[cut:]
            if len(out):
                streamed_t = int(out["t"][-1])
                yield out
        if len(carry):
            yield carry


def iter_event_chunks(path, chunk_events: int = DEFAULT_CHUNK_EVENTS, format: str | None = None, *,
                      width: int | None = None, height: int | None = None,
                      time_unit: str | None = None, columns=None, y_up: bool = False,
                      max_gap_s: float | None = None) -> EventChunks:
    """Stream a recording's events in chunks of about ``chunk_events`` (see :class:`EventChunks`).

    The returned object is iterable (each pass re-reads the file) and tells ``width``, ``height``,
    ``t_offset_us`` and, as iteration proceeds, ``repairs``. Every format streams except npz (its members are
    loaded whole); memory is bounded by a few chunks.
    """
    return EventChunks(path, format, chunk_events, width, height, time_unit, columns, y_up, max_gap_s)
