"""What a reader returns: a decoded recording (events, optional frames and calibration) and its error type."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from eventcap.camera import Camera
from eventcap.events import EVENT_DTYPE

logger = logging.getLogger("eventcap.io")


class RecordingError(ValueError):
    """A recording that cannot be read as it is: names the file, where in it, and what is wrong.

    ``str(error)`` reads ``"<path>: <where>: <what>"``; the parts are also attributes.
    """

    def __init__(self, path, what: str, where: str | None = None):
        self.path = Path(path)
        self.where = where
        self.what = what
        super().__init__(f"{self.path}: {where}: {what}" if where else f"{self.path}: {what}")


def _readonly(arr: np.ndarray) -> np.ndarray:
    """A read-only view (the caller's array keeps its own flags; nothing is copied)."""
    view = arr.view()
    view.setflags(write=False)
    return view


@dataclass(frozen=True, eq=False)
class Frames:
    """The sensor's intensity frames (e.g. DAVIS APS images), on the events' clock.

    - ``images``: (N, height, width) float32 linear intensity in [0, 1] (8-bit sources divided by 255, 16-bit by
      65535; colour converted to grey). One dtype for every source, exact for 8- and 16-bit data, and what the
      sharpening stage (EDI) computes in.
    - ``t_us``: (N,) int64, centre of each frame's exposure, microseconds on the recording's clock (the same clock
      as the events, so it can be negative if a frame was exposed before the first event).
    - ``exposure_us``: (N,) int64 exposure durations in microseconds, or ``None`` when the file does not record
      them (rpg text layout, HDF5 files without an exposure dataset).

    Frames are sorted by ``t_us`` with distinct times. Arrays are stored as read-only views; equality is identity.
    """

    images: np.ndarray
    t_us: np.ndarray
    exposure_us: np.ndarray | None = None

    def __post_init__(self):
        images = np.asarray(self.images)
        if images.ndim != 3 or images.dtype != np.float32:
            raise ValueError(f"Frames.images: expected (N, height, width) float32, got {images.shape} {images.dtype}")
        n = images.shape[0]
        t = np.asarray(self.t_us)
        if t.shape != (n,) or t.dtype != np.int64:
            raise ValueError(f"Frames.t_us: expected ({n},) int64 microseconds, got {t.shape} {t.dtype}")
        if n > 1 and np.any(np.diff(t) <= 0):
            raise ValueError("Frames.t_us: expected strictly increasing frame times")
        object.__setattr__(self, "images", _readonly(images))
        object.__setattr__(self, "t_us", _readonly(t))
        if self.exposure_us is not None:
            e = np.asarray(self.exposure_us)
            if e.shape != (n,) or e.dtype != np.int64 or np.any(e < 0):
                raise ValueError(f"Frames.exposure_us: expected ({n},) int64 microseconds ≥ 0, got {e.shape} {e.dtype}")
            object.__setattr__(self, "exposure_us", _readonly(e))

    @property
    def height(self) -> int:
        return int(self.images.shape[1])

    @property
    def width(self) -> int:
        return int(self.images.shape[2])

    def __len__(self) -> int:
        return int(self.images.shape[0])


@dataclass(frozen=True, eq=False)
class RawRecording:
    """One decoded event-camera recording, in the project's conventions (``EVENT_DTYPE``, eventcap/events.py).

    - ``events``: (N,) ``EVENT_DTYPE``, sorted by time, no exact duplicates, inside the sensor, polarity ±1.
      Time is in microseconds since the recording's first event: ``t + t_offset_us`` is the file's own time.
    - ``width``, ``height``: sensor size in pixels (after a region-of-interest crop, the crop's size).
    - ``t_offset_us``: the file's time of the first event (µs); added back by the writers.
    - ``path``, ``format``: where it came from and which reader decoded it (``"aedat4"``, ``"hdf5"``, ...).
    - ``frames``: intensity frames on the same clock, or ``None``.
    - ``calibration``: a :class:`eventcap.camera.Camera` (intrinsics + distortion, identity extrinsics) when the
      file has one, else ``None``.
    - ``ground_truth``: loosely typed for now: a mapping of names to arrays as the source stores them (rpg
      ``groundtruth.txt`` gives ``t_us`` on the events' clock and ``pose`` (N, 7) ``px py pz qx qy qz qw``), or
      ``None``.
    - ``repairs``: one sentence per repair or guess the reader made (sorting, dropped duplicates, a truncated
      tail, an inferred sensor size, ...). Empty when the file was read exactly as stored.

    Arrays are stored as read-only views (not copies); equality is identity.
    """

    events: np.ndarray
    width: int
    height: int
    t_offset_us: int
    path: Path
    format: str
    frames: Frames | None = None
    calibration: Camera | None = None
    ground_truth: Mapping[str, np.ndarray] | None = None
    repairs: tuple[str, ...] = ()

    def __post_init__(self):
        ev = np.asarray(self.events)
        if ev.dtype != EVENT_DTYPE or ev.ndim != 1:
            raise ValueError(f"RawRecording.events: expected 1-D EVENT_DTYPE {EVENT_DTYPE}, got {ev.shape} {ev.dtype}")
        object.__setattr__(self, "events", _readonly(ev))
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or int(value) != value or not 0 < value <= 65536:
                raise ValueError(f"RawRecording.{name}: expected a positive number of pixels, got {value!r}")
            object.__setattr__(self, name, int(value))
        object.__setattr__(self, "t_offset_us", int(self.t_offset_us))
        object.__setattr__(self, "path", Path(self.path))
        object.__setattr__(self, "repairs", tuple(self.repairs))
        f = self.frames
        if f is not None and (f.height, f.width) != (self.height, self.width):
            raise ValueError(f"RawRecording.frames: expected frames of height {self.height} and width {self.width}, "
                             f"got height {f.height} and width {f.width}")
        c = self.calibration
        if c is not None and (c.height, c.width) != (self.height, self.width):
            raise ValueError(f"RawRecording.calibration: expected a camera of height {self.height} and width "
                             f"{self.width}, got height {c.height} and width {c.width}")
