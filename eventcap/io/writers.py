"""Write events (and, where the format holds them, frames and calibration) so that the readers give them back.

Formats: ``aedat4``, ``evt2``, ``evt3``, ``dat`` (events only, via faery; file times must be ≥ 0), ``hdf5``
(h5py), ``npz`` and ``rpg`` (a folder; frames as 8-bit PNG). Files are written under a temporary name beside the
target and renamed into place, so a failed or killed write leaves no half-written file behind.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from eventcap.events import EVENT_DTYPE
from eventcap.io.recording import RawRecording

WRITE_FORMATS = ("aedat4", "evt2", "evt3", "dat", "hdf5", "npz", "rpg")
_EXTENSIONS = {".aedat4": "aedat4", ".raw": "evt3", ".dat": "dat", ".h5": "hdf5", ".hdf5": "hdf5", ".npz": "npz"}
_EXTRAS_FORMATS = ("hdf5", "npz", "rpg")


def _format_for(path: Path, format: str | None) -> str:
    if format is not None:
        fmt = str(format).lower()
        if fmt not in WRITE_FORMATS:
            raise ValueError(f"cannot write format {format!r}: expected one of {', '.join(WRITE_FORMATS)}")
        return fmt
    if path.suffix == "":
        return "rpg"
    fmt = _EXTENSIONS.get(path.suffix.lower())
    if fmt is None:
        raise ValueError(f"{path}: cannot tell the format from the extension {path.suffix!r}: pass format= (one of "
                         f"{', '.join(WRITE_FORMATS)})")
    return fmt


def _checked_chunks(events, width: int, height: int, t_offset_us: int, fmt: str) -> Iterator[np.ndarray]:
    """Validate ``EVENT_DTYPE`` chunks and shift them to file time (``t + t_offset_us``)."""
    chunks = [events] if isinstance(events, np.ndarray) else events
    last_t = None
    for k, chunk in enumerate(chunks):
        chunk = np.asarray(chunk)
        if chunk.dtype != EVENT_DTYPE or chunk.ndim != 1:
            raise ValueError(f"events chunk {k}: expected 1-D EVENT_DTYPE, got {chunk.shape} {chunk.dtype}")
        if not len(chunk):
            continue
        t = chunk["t"] + np.int64(t_offset_us)
        problems = [
            (np.diff(t, prepend=t[0] if last_t is None else last_t) < 0, "time goes backwards (sort the events)"),
            (chunk["x"] >= width, f"x outside the sensor width {width}"),
            (chunk["y"] >= height, f"y outside the sensor height {height}"),
            ((chunk["p"] != 1) & (chunk["p"] != -1), "polarity not ±1"),
        ]
        if fmt not in ("hdf5", "npz"):
            problems.append((t < 0, f"negative file time (format {fmt} stores unsigned times; raise t_offset_us)"))
        for bad, what in problems:
            if bad.any():
                i = int(np.argmax(bad))
                raise ValueError(f"events chunk {k}, event {i}: {what}: {chunk[i]} (t_offset_us={t_offset_us})")
        last_t = int(t[-1])
        out = chunk.copy()
        out["t"] = t
        yield out


def _as_faery(chunks: Iterator[np.ndarray]) -> Iterator[np.ndarray]:
    import faery

    for chunk in chunks:
        out = np.empty(len(chunk), dtype=faery.EVENTS_DTYPE)
        out["t"], out["x"], out["y"], out["on"] = chunk["t"], chunk["x"], chunk["y"], chunk["p"] > 0
        yield out


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    elif path.exists() or path.is_symlink():
        path.unlink()


def _write(path, chunks, width: int, height: int, t_offset_us: int, format: str | None, frames=None,
           calibration=None, ground_truth=None) -> Path:
    path = Path(path)
    fmt = _format_for(path, format)
    if (frames is not None or calibration is not None or ground_truth) and fmt not in _EXTRAS_FORMATS:
        raise ValueError(f"format {fmt} stores events only, but frames, calibration or ground truth were given: "
                         f"write them as {', '.join(_EXTRAS_FORMATS)}, or write the events alone with write_events")
    if fmt == "rpg" and path.exists() and not (path.is_dir() and not any(path.iterdir())):
        raise FileExistsError(f"{path}: the rpg layout is written as a new folder, and this path exists")
    events = _checked_chunks(chunks, int(width), int(height), int(t_offset_us), fmt)
    tmp = path.with_name(path.name + ".partial")
    _remove(tmp)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        if fmt == "aedat4":
            from eventcap.io.aedat4 import write_aedat4

            write_aedat4(tmp, _as_faery(events), width, height)
        elif fmt in ("evt2", "evt3", "dat"):
            from eventcap.io.prophesee import write_prophesee

            write_prophesee(tmp, _as_faery(events), fmt, width, height)
        elif fmt == "hdf5":
            from eventcap.io.hdf5 import write_hdf5

            write_hdf5(tmp, events, width, height, frames, calibration, ground_truth)
        elif fmt == "npz":
            from eventcap.io.arrays import write_npz

            parts = list(events)
            allev = np.concatenate(parts) if parts else np.empty(0, EVENT_DTYPE)
            write_npz(tmp, allev, width, height, frames, calibration, ground_truth)
        else:
            from eventcap.io.rpg import write_rpg

            write_rpg(tmp, events, frames, calibration, ground_truth)
        if fmt == "rpg" and path.exists():
            path.rmdir()
        os.replace(tmp, path)
    except BaseException:
        _remove(tmp)
        raise
    return path


def write_events(path, events: np.ndarray | Iterable[np.ndarray], *, width: int, height: int,
                 format: str | None = None, t_offset_us: int = 0) -> Path:
    """Write events to ``path``; returns the path.

    ``events``: an ``EVENT_DTYPE`` array, or an iterable of such chunks (e.g. :func:`iter_event_chunks`), sorted
    by time across chunks; written with time ``t + t_offset_us`` so a reader gives ``t_offset_us`` back. Chunks
    are written as they come (bounded memory), except for npz. ``format`` defaults from the extension
    (``.aedat4``, ``.raw`` → EVT3, ``.dat``, ``.h5``/``.hdf5``, ``.npz``, no extension → rpg folder). Raises
    ``ValueError`` for events the format cannot hold (unsorted, outside ``width`` × ``height``, bad polarity).
    """
    return _write(path, events, width, height, t_offset_us, format)


def write_recording(path, recording: RawRecording, *, format: str | None = None) -> Path:
    """Write a :class:`RawRecording` (events; frames, calibration and ground truth where the format holds them).

    Frames, calibration and ground truth need ``hdf5``, ``npz`` or ``rpg`` (rpg keeps no exposure times, frames
    as 8-bit PNG, ground truth only as rpg's ``t_us`` + ``pose``); other formats raise ``ValueError`` if the
    recording has any.
    """
    r = recording
    frames = None
    if r.frames is not None:
        exposure = r.frames.exposure_us
        frames = (r.frames.images, r.frames.t_us + r.t_offset_us, exposure)
    gt = None
    if r.ground_truth:
        gt = dict(r.ground_truth)
        if "t_us" in gt:
            gt["t_us"] = np.asarray(gt["t_us"], dtype=np.int64) + r.t_offset_us
    return _write(path, r.events, r.width, r.height, r.t_offset_us, format, frames, r.calibration, gt)
