"""Convert a recording of any readable format into the project's recording format, streaming the events.

The project's format is the zarr v3 group :meth:`Recording.to_zarr` writes (``eventcap simulate`` writes one,
``source=recording`` reads one). :func:`convert_recording` writes the same group without ever holding the events
in memory: they come from :func:`eventcap.io.iter_event_chunks` and are appended chunk by chunk to the event
columns (:class:`eventcap.artifact.ArrayAppender`, which keeps ``to_zarr``'s chunk layout), checked chunk by
chunk for the :class:`EventStream` invariants (sorted, inside the sensor, polarity ±1). Frames are small and are
written whole. The result reads back with ``Recording.from_zarr`` equal to :func:`recording_from_raw` applied to
:func:`eventcap.io.read_recording` of the same file and options.

The pieces that turn a decoded recording into a :class:`Recording` (camera choice, frames, the ``source``
description, the time window in seconds, the ROI given by its corners) live here and are shared with the
``recording`` source stage, so a converted file and a file read by the stage describe the recording identically.
"""

from __future__ import annotations

import os
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from eventcap.artifact import ArrayAppender, ArtifactError
from eventcap.artifacts.recording import EventStream, FrameStack, Recording
from eventcap.camera import Camera, read_rpg_calibration
from eventcap.events import EVENT_DTYPE
from eventcap.io.detect import project_recording_problem
from eventcap.io.readers import Roi, _finish_frames, iter_event_chunks, open_source
from eventcap.io.sizes import CoordinateStats
from eventcap.io.recording import Frames, RawRecording, RecordingError, logger
from eventcap.io.source import DEFAULT_CHUNK_EVENTS, check_regular
from eventcap.processes import pid_alive

#: End of an open time window ("to the end"), µs; far beyond any recording, with room for offsets.
OPEN_END_US = np.iinfo(np.int64).max // 2


# ------------------------------------------------------------------------------------------- shared with the stage
def is_project_recording(path) -> bool:
    """A directory holding a zarr group written from a Recording artifact (the project's format). A ``zarr.json``
    that is not a regular file is refused (:class:`RecordingError`), never opened."""
    path = Path(path)
    if not (path.is_dir() and os.path.lexists(path / "zarr.json")):
        return False
    return project_recording_problem(path) is None


def read_project_recording(path) -> Recording:
    """A recording in the project's format (a zarr group written from a Recording), read whole; any failure of the
    zarr reader on damaged metadata or chunks is a :class:`RecordingError` naming the folder."""
    import zarr

    path = Path(path)
    try:
        return Recording.from_zarr(zarr.open_group(str(path), mode="r"), where=str(path))
    except (ArtifactError, RecordingError):
        raise
    except (KeyboardInterrupt, SystemExit, MemoryError):
        raise
    except Exception as exc:  # noqa: BLE001 - zarr's and numcodecs' own errors on damaged files
        raise RecordingError(path, f"a damaged recording in the project's format: {type(exc).__name__}: "
                                   f"{str(exc).strip()[:300]}") from exc


def window_from_seconds(t_start_s: float | None, t_end_s: float | None) -> tuple[int, int] | None:
    """A time window in seconds from the first event → ``(start, end)`` µs, half-open; ``None`` when both are 0
    or ``None`` (everything). ``t_end_s`` 0 or ``None`` means to the end."""
    start, end = float(t_start_s or 0.0), float(t_end_s or 0.0)
    if start == 0.0 and end == 0.0:
        return None
    if not (np.isfinite(start) and np.isfinite(end)) or start < 0 or (end and end <= start):
        raise ValueError(f"time window: expected 0 <= t_start_s < t_end_s (t_end_s 0 = to the end), got "
                         f"t_start_s={t_start_s}, t_end_s={t_end_s}")
    return int(round(start * 1e6)), (int(round(end * 1e6)) if end else OPEN_END_US)


def roi_from_corners(corners) -> Roi:
    """A region of interest given by its corners ``[x0, y0, x1, y1]`` (pixels; ``x1``, ``y1`` excluded) → :class:`Roi`."""
    try:
        x0, y0, x1, y1 = (int(v) for v in corners)
    except (TypeError, ValueError):
        raise ValueError(f"roi: expected 4 integers [x0, y0, x1, y1], got {corners!r}") from None
    if x0 < 0 or y0 < 0 or x1 <= x0 or y1 <= y0:
        raise ValueError(f"roi: expected 0 <= x0 < x1 and 0 <= y0 < y1 ([x0, y0, x1, y1], x1 and y1 excluded), "
                         f"got {[x0, y0, x1, y1]}")
    return Roi(x0, y0, x1 - x0, y1 - y0)


def _as_roi(roi) -> Roi | None:
    if roi is None or isinstance(roi, Roi):
        return roi
    try:
        x, y, w, h = (int(v) for v in roi)
    except (TypeError, ValueError):
        raise ValueError(f"roi: expected Roi or (x, y, width, height), got {roi!r}") from None
    return Roi(x, y, w, h)


def nominal_camera(width: int, height: int) -> Camera:
    """A guessed pinhole camera for recordings without a calibration: about 65° horizontal field of view, principal
    point at the image centre, no distortion. Recordings using it say ``UNCALIBRATED`` in their ``source``."""
    f = 0.78 * width
    return Camera(width, height, f, f, (width - 1) / 2, (height - 1) / 2)


def choose_camera(width: int, height: int, *, file_calibration: Camera | None = None, calibration=None,
                  roi: Roi | None = None, hint: str = "pass a calibration file") -> tuple[Camera, str]:
    """The recording's camera and a note saying where it came from.

    ``calibration`` (an rpg ``calib.txt`` of the full sensor) wins over ``file_calibration`` (the file's own, already
    cropped by the reader); with neither, :func:`nominal_camera`. ``width`` × ``height`` is the recording's size
    (the ROI's, when cropped); a ``calibration`` file's principal point is moved by the ROI's corner, as the readers
    do for a file's calibration. ``hint`` ends the note of an uncalibrated recording (how to give a calibration).
    """
    if calibration:
        cam = read_rpg_calibration(calibration, width, height)
        if roi is not None:
            cam = Camera(width, height, cam.fx, cam.fy, cam.cx - roi.x, cam.cy - roi.y, cam.dist, cam.R, cam.t)
        return cam, f"calibration {calibration}"
    if file_calibration is not None:
        return file_calibration, "calibration from the file"
    return nominal_camera(width, height), f"UNCALIBRATED: nominal pinhole intrinsics ({hint})"


def frame_stack(frames: Frames | None) -> FrameStack | None:
    """Decoded frames as the :class:`FrameStack` artifact (exposure 0 = not recorded by the file)."""
    if frames is None:
        return None
    exposure = frames.exposure_us if frames.exposure_us is not None else np.zeros(len(frames), np.int64)
    return FrameStack(images=np.clip(frames.images, 0.0, 1.0).astype(np.float32),
                      t_us=np.asarray(frames.t_us, np.int64), exposure_us=np.asarray(exposure, np.int64),
                      height=frames.height, width=frames.width)


def source_description(format: str, path, t_offset_us: int, camera_note: str, repairs) -> str:
    """The ``source`` attribute of a Recording read from a file: format, path, time offset, camera, repairs."""
    return (f"{format}: {path} (t_offset_us={t_offset_us}; {camera_note}; "
            f"repairs: {'; '.join(repairs) or 'none'})")


def recording_from_raw(raw: RawRecording, *, calibration=None, roi=None, name: str | None = None,
                       hint: str = "pass a calibration file") -> Recording:
    """A decoded recording (:func:`eventcap.io.read_recording`, in memory) as the :class:`Recording` artifact.

    ``calibration``: an rpg ``calib.txt`` overriding the file's calibration; ``roi``: the region ``raw`` was cropped
    to (moves that calibration's principal point); ``name`` defaults to the file's stem. Ground truth of external
    formats is loosely typed and not carried over.
    """
    roi = _as_roi(roi)
    cam, note = choose_camera(raw.width, raw.height, file_calibration=raw.calibration, calibration=calibration,
                              roi=roi, hint=hint)
    return Recording(events=EventStream(events=np.asarray(raw.events).copy(), width=raw.width, height=raw.height),
                     camera=cam, frames=frame_stack(raw.frames), name=raw.path.stem if name is None else name,
                     source=source_description(raw.format, raw.path, raw.t_offset_us, note, raw.repairs))


# ------------------------------------------------------------------------------------------------------ streaming
class _StreamCheck:
    """The :class:`EventStream` invariants, checked chunk by chunk (the whole stream is never in memory)."""

    def __init__(self, width: int | None, height: int | None):
        self.width, self.height = width, height
        self.rows = 0
        self.last_t: int | None = None

    def __call__(self, ev: np.ndarray) -> None:
        if not len(ev):
            return
        t = ev["t"]
        prev = t[0] if self.last_t is None else self.last_t
        back = np.diff(t, prepend=prev) < 0
        if back.any():
            i = int(np.argmax(back))
            before = prev if i == 0 else t[i - 1]
            raise ArtifactError(f"EventStream.events: timestamps not sorted at row {self.rows + i} ({before} > "
                                f"{t[i]} us)")
        for col, limit in (("x", self.width), ("y", self.height)):
            if limit is None:
                continue
            bad = ev[col] >= limit
            if bad.any():
                i = int(np.argmax(bad))
                raise ArtifactError(f"EventStream.events: {col}={ev[col][i]} at row {self.rows + i} outside the "
                                    f"sensor (< {limit})")
        badp = (ev["p"] != 1) & (ev["p"] != -1)
        if badp.any():
            i = int(np.argmax(badp))
            raise ArtifactError(f"EventStream.events: polarity {ev['p'][i]} at row {self.rows + i}, expected -1 or +1")
        self.rows += len(ev)
        self.last_t = int(t[-1])


def _header(cls, attrs: dict) -> dict:
    # The group attributes Artifact.to_zarr writes (attrs in declaration order).
    return {"artifact": cls.type_name(), "schema_version": cls.schema_version,
            "attrs": {n: attrs[n] for n in cls.attr_fields()}}


def _window_frames(frames: Frames | None, start: int, end: int) -> Frames | None:
    # As read_recording: frames whose exposure centre lies in the window.
    if frames is None:
        return None
    keep = (frames.t_us >= start) & (frames.t_us < end)
    if not keep.any():
        return None
    return Frames(frames.images[keep], frames.t_us[keep], None if frames.exposure_us is None else frames.exposure_us[keep])


def _crop_frames(frames: Frames | None, r: Roi) -> Frames | None:
    if frames is None:
        return None
    return Frames(np.ascontiguousarray(frames.images[:, r.y:r.y + r.height, r.x:r.x + r.width]), frames.t_us,
                  frames.exposure_us)


def _judge_size(path, stats: CoordinateStats) -> tuple[int, int]:
    """The inferred size of a streamed file (as read_recording judges it); outliers that read_recording would drop
    are already written here: refused, saying how to crop them."""
    d = stats.judge(path, "pass --width and --height, or crop with --roi")
    if d.dropped:
        what = d.note.partition("outlier event(s): ")[2]
        raise RecordingError(path, f"the file does not declare its sensor size, and {d.dropped} event(s) are outliers "
                                   f"({what}): corrupted events, which would make the inferred sensor larger; crop "
                                   f"them with --roi 0 0 {d.width} {d.height} (read_recording drops them itself)")
    return d.width, d.height


def _check_roi_inside(r: Roi, width: int, height: int) -> None:
    if r.x < 0 or r.y < 0 or r.width <= 0 or r.height <= 0 or r.x + r.width > width or r.y + r.height > height:
        raise ValueError(f"roi {r} does not lie inside the {width} × {height} sensor")


@dataclass
class _Pass:
    """What one streaming pass over the file saw (counts, the window's neighbours, the largest coordinates)."""

    read: int = 0  # events decoded
    in_window: int = 0  # of those, inside the time window
    #: the coordinates seen, for an inferred sensor size (judged as read_recording judges it)
    coords: CoordinateStats = field(default_factory=CoordinateStats)
    last_t_before: int | None = None  # the last event before the window
    first_t_after: int | None = None  # the first event after it
    stopped_early: bool = False  # decoding stopped at the window's end
    first_t: int | None = None  # first and last event written
    last_t: int | None = None


def _stream_into(root, in_path: Path, *, format, chunk_events, calibration, width, height, window, roi, time_unit,
                 progress, columns=None, y_up=False, max_gap_s=None) -> dict:
    """Write the Recording group ``root`` from ``in_path``; returns the statistics of the conversion."""
    t_begin = time.perf_counter()
    declared = open_source(in_path, format, time_unit, columns).width is not None
    infer = not declared and width is None and height is None
    if infer and y_up:
        raise ValueError(f"{in_path}: y_up flips y about the sensor height, which the file does not declare: pass "
                         f"width and height")
    # A file without a sensor size streams against the largest 16-bit sensor; the size is inferred from the
    # largest coordinates at the end, as read_recording does.
    chunks = iter_event_chunks(in_path, chunk_events, format, width=65536 if infer else width,
                               height=65536 if infer else height, time_unit=time_unit, columns=columns, y_up=y_up,
                               max_gap_s=max_gap_s)
    path = chunks.path
    full_w, full_h = (None, None) if infer else (chunks.width, chunks.height)
    if roi is not None and not infer:
        _check_roi_inside(roi, full_w, full_h)

    events_group = root.create_group("events")
    cols = events_group.create_group("events")
    cols.attrs["structured"] = [[n, EVENT_DTYPE.fields[n][0].str] for n in EVENT_DTYPE.names]
    units = EventStream.array_fields()["events"].units
    appenders = {n: ArrayAppender(cols, n, EVENT_DTYPE.fields[n][0], units=units) for n in EVENT_DTYPE.names}
    check = _StreamCheck(roi.width if roi is not None else full_w, roi.height if roi is not None else full_h)
    seen = _copy_events(chunks, appenders, check, window, roi, infer, progress, t_begin)

    if window is not None and seen.in_window == 0:
        start, end = window
        span = (f"the recording's events span 0..{seen.last_t_before} µs" if seen.first_t_after is None else
                f"the last event before it is at {seen.last_t_before} µs and the next at {seen.first_t_after} µs")
        shown = f"[{start}, {end}) µs" if end < OPEN_END_US else f"from {start} µs on"
        raise RecordingError(path, f"no events in the time window {shown}: {span}")
    if infer:
        if roi is None:
            full_w, full_h = _judge_size(path, seen.coords)
        else:
            full_w, full_h = int(np.flatnonzero(seen.coords.hx)[-1]) + 1, int(np.flatnonzero(seen.coords.hy)[-1]) + 1
            _check_roi_inside(roi, full_w, full_h)
    if check.rows == 0:  # only a crop can leave nothing (an empty file or window was refused above)
        raise RecordingError(path, f"no events inside the region of interest {roi}")
    for app in appenders.values():
        app.close()
    w, h, stack, note, repairs = _write_frames_and_camera(root, chunks, seen, window, roi, infer, full_w, full_h,
                                                          calibration)
    events_group.attrs.update(_header(EventStream, {"width": w, "height": h}))
    root.attrs.update(_header(Recording, {"name": path.stem,
                                          "source": source_description(chunks.format, path, chunks.t_offset_us,
                                                                       note, repairs),
                                          "world": ""}))  # set when read (plugins/eventcap_recording)
    seconds = time.perf_counter() - t_begin
    return {"format": chunks.format, "events": check.rows, "events_read": seen.read, "frames": 0 if stack is None
            else len(stack.t_us), "width": w, "height": h, "t_offset_us": chunks.t_offset_us,
            "t_first_us": seen.first_t, "t_last_us": seen.last_t, "camera": note, "repairs": repairs,
            "stopped_at_window_end": seen.stopped_early, "seconds": seconds,
            "events_per_s": seen.read / seconds if seconds > 0 else float("inf")}


def _copy_events(chunks, appenders, check: _StreamCheck, window, roi, infer: bool, progress, t_begin: float) -> _Pass:
    """Append the events of every chunk inside the time window and the ROI (shifted to the ROI's corner) to the
    event columns, checked chunk by chunk; stops after the window's end when the sensor size is declared."""
    seen = _Pass()
    start, end = window if window is not None else (None, None)
    for chunk in chunks:
        seen.read += len(chunk)
        if infer:
            seen.coords.add(chunk["x"], chunk["y"])
        if window is not None:
            t = chunk["t"]
            a, b = np.searchsorted(t, [start, end], side="left")
            if a > 0:
                seen.last_t_before = int(t[a - 1])
            if b < len(t) and seen.first_t_after is None:
                seen.first_t_after = int(t[b])
            chunk = chunk[a:b]
            seen.in_window += len(chunk)
            if b < len(t) and not infer:
                # Past the window's end: the rest of the file cannot contribute (the size is declared).
                seen.stopped_early = True
        if roi is not None and len(chunk):
            keep = ((chunk["x"] >= roi.x) & (chunk["x"] < roi.x + roi.width)
                    & (chunk["y"] >= roi.y) & (chunk["y"] < roi.y + roi.height))
            chunk = chunk[keep]
            chunk["x"] -= roi.x
            chunk["y"] -= roi.y
        if len(chunk):
            check(chunk)
            for n, app in appenders.items():
                app.append(np.ascontiguousarray(chunk[n]))
            seen.first_t = int(chunk["t"][0]) if seen.first_t is None else seen.first_t
            seen.last_t = int(chunk["t"][-1])
        if progress is not None:
            progress(check.rows, seen.read, time.perf_counter() - t_begin)
        if seen.stopped_early:
            break
    return seen


def _write_frames_and_camera(root, chunks, seen: _Pass, window, roi, infer: bool, full_w: int, full_h: int,
                             calibration):
    """The frames (windowed, cropped) and the camera of the converted recording, written into ``root``; logs the
    repairs the pass did not log. Returns (width, height, frame stack or None, camera note, repairs)."""
    path = chunks.path
    source = chunks._source  # the same decoder object read_recording would ask for frames and calibration
    # A completed pass has logged its own repairs; log the rest (frames, inferred size) once here.
    logged = set() if seen.stopped_early else set(chunks.repairs)
    frame_data = source.frames()
    repairs = list(chunks.repairs)  # after frames(): it may add notes, as in read_recording
    if seen.stopped_early:
        logger.info("%s: stopped decoding at the end of the time window (%d µs); repairs and errors after it are "
                    "not looked for", path, window[1])
    if infer:
        repairs.append(f"sensor size not in the file: inferred {full_w} × {full_h} from the largest event "
                       f"coordinates (pass width= and height= to set it)")
    frames = _finish_frames(frame_data, path, chunks.t_offset_us, full_w, full_h, repairs)
    calib = source.calibration(full_w, full_h)
    if window is not None:
        frames = _window_frames(frames, *window)
    if roi is not None:
        frames = _crop_frames(frames, roi)
        if calib is not None:
            c = calib
            calib = Camera(roi.width, roi.height, c.fx, c.fy, c.cx - roi.x, c.cy - roi.y, c.dist, c.R, c.t)
    w, h = (roi.width, roi.height) if roi is not None else (full_w, full_h)
    for repair in repairs:
        if repair not in logged:
            logger.warning("%s: %s", path, repair)
    cam, note = choose_camera(w, h, file_calibration=calib, calibration=calibration, roi=roi)
    cam.write_zarr(root, "camera")
    stack = frame_stack(frames)
    if stack is not None:
        if (stack.width, stack.height) != (w, h):
            raise ArtifactError(f"Recording: frames are {stack.width}x{stack.height}, camera {w}x{h}")
        stack.write_zarr(root, "frames")
    return w, h, stack, note, repairs


# ------------------------------------------------------------------------------------------- atomic output folder
def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    elif path.exists() or path.is_symlink():
        path.unlink()


    return True


def _remove_stale_partials(out: Path) -> None:
    """Remove ``OUT.partial-<pid>`` (and ``OUT.old-<pid>``) folders left by conversions that were killed (their
    process is gone)."""
    if not out.parent.is_dir():
        return
    for p in out.parent.iterdir():
        for prefix in (f"{out.name}.partial-", f"{out.name}.old-"):
            if p.name.startswith(prefix) and p.name[len(prefix):].isdigit():
                pid = int(p.name[len(prefix):])
                if pid != os.getpid() and not pid_alive(pid):
                    logger.info("removing %s, left by a conversion that did not finish (process %d is gone)", p, pid)
                    _remove(p)


def _check_out(in_path: Path, out: Path, overwrite: bool) -> None:
    try:
        src, dst = in_path.resolve(), out.resolve()
    except (RuntimeError, OSError) as exc:  # a loop of symbolic links (RuntimeError before Python 3.13)
        raise ValueError(f"output {out}: cannot resolve the path ({exc}): a loop of symbolic links?") from None
    if dst == src or src.is_relative_to(dst) or (src.is_dir() and dst.is_relative_to(src)):
        raise ValueError(f"output {out} overlaps the input {in_path}: choose another output path")
    if out.exists() or out.is_symlink():
        if not overwrite:
            raise FileExistsError(f"{out} exists: pass overwrite=True (--overwrite) to replace it")
        # Replace only what a conversion could have written: never an arbitrary folder.
        if out.is_dir() and not is_project_recording(out) and any(out.iterdir()):
            raise ValueError(f"{out} exists and is not a recording in the project's format: refusing to replace it")


def _commit(tmp: Path, out: Path) -> None:
    """Move the finished folder into place; an existing ``out`` (checked by _check_out) is replaced."""
    if not (out.exists() or out.is_symlink()):
        os.rename(tmp, out)
        return
    old = out.with_name(f"{out.name}.old-{os.getpid()}")
    _remove(old)
    os.rename(out, old)
    try:
        os.rename(tmp, out)
    except BaseException:
        os.rename(old, out)
        raise
    _remove(old)


def convert_recording(in_path, out_path, *, format: str | None = None, chunk_events: int = DEFAULT_CHUNK_EVENTS,
                      calibration=None, width: int | None = None, height: int | None = None,
                      time_window_us: tuple[int, int] | None = None, roi=None, time_unit: str | None = None,
                      overwrite: bool = False, columns=None, y_up: bool = False, max_gap_s: float | None = None,
                      progress: Callable[[int, int, float], None] | None = None) -> dict:
    """Convert a recording (any format :func:`eventcap.io.read_recording` reads) into the project's format at
    ``out_path`` (a zarr v3 folder, read with ``Recording.from_zarr``), in memory bounded by a few chunks.

    - ``format``, ``width``, ``height``, ``time_unit``, ``columns``, ``y_up``: as for
      :func:`eventcap.io.read_recording` (a file without a sensor size and no ``width``/``height`` gets the size
      inferred from its events, noted as a repair; ``y_up`` then needs ``width``/``height``).
    - ``chunk_events``: events decoded per chunk.
    - ``calibration``: an rpg ``calib.txt`` (of the full sensor) overriding the file's calibration; without either,
      a nominal pinhole camera (the ``source`` attribute then says ``UNCALIBRATED``).
    - ``time_window_us``: ``(start, end)`` µs from the first event, half-open; events and frames (by exposure centre)
      inside it are kept, on the recording's clock. Decoding stops at the window's end when the file declares its
      sensor size, so repairs and errors after the window are not looked for.
    - ``roi``: :class:`eventcap.io.Roi` or ``(x, y, width, height)``; events and frame pixels inside it, shifted to
      (0, 0); the camera's principal point moves with it.
    - ``progress(events_written, events_read, seconds)``: called after each chunk.

    The folder is written as ``OUT.partial-<pid>`` beside ``out_path`` and renamed into place when complete; on
    any error it is removed (a killed conversion's folder is removed by the next conversion to the same path). An
    existing ``out_path`` raises ``FileExistsError`` unless ``overwrite`` (and even then only a recording in the
    project's format, a file, or an empty folder is replaced). Streaming differs from :func:`read_recording` only
    where bounded memory cannot repair: an event earlier than events already written raises
    :class:`RecordingError`.

    Returns statistics: ``events`` (written), ``events_read``, ``frames``, ``width``, ``height``, ``t_offset_us``,
    ``t_first_us``/``t_last_us``, ``format``, ``camera`` (where it came from), ``repairs``, ``seconds``,
    ``events_per_s`` (read), ``out``, ``bytes`` (on disk).
    """
    import zarr

    in_path, out = Path(in_path), Path(out_path)
    if int(chunk_events) < 1:
        raise ValueError(f"chunk_events must be ≥ 1, got {chunk_events}")
    window = None
    if time_window_us is not None:
        try:
            window = tuple(int(v) for v in time_window_us)
            start, end = window
        except (TypeError, ValueError):
            raise ValueError(f"time_window_us: expected (start, end) in µs, got {time_window_us!r}") from None
        if not start < end:
            raise ValueError(f"time_window_us: expected start < end, got ({start}, {end})")
    roi = _as_roi(roi)
    check_regular(in_path)
    if is_project_recording(in_path):
        raise ValueError(f"{in_path} is already a recording in the project's format (read it with "
                         f"source=recording, or copy the folder)")
    _check_out(in_path, out, overwrite)
    out.parent.mkdir(parents=True, exist_ok=True)
    _remove_stale_partials(out)
    tmp = out.with_name(f"{out.name}.partial-{os.getpid()}")
    _remove(tmp)
    try:
        root = zarr.open_group(str(tmp), mode="w-")
        stats = _stream_into(root, in_path, format=format, chunk_events=int(chunk_events), calibration=calibration,
                             width=width, height=height, window=window, roi=roi, time_unit=time_unit,
                             progress=progress, columns=columns, y_up=y_up, max_gap_s=max_gap_s)
        _commit(tmp, out)
    except BaseException:
        _remove(tmp)
        raise
    stats["out"] = str(out)
    stats["bytes"] = sum(f.stat().st_size for f in out.rglob("*") if f.is_file())
    return stats
