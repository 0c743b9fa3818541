"""Artifacts of a recording: events, intensity frames, ground truth, and the recording that bundles them.

A :class:`Recording` stored as a zarr group is the project's own recording format: ``eventcap simulate`` writes
one, ``source=recording`` reads it (and the other formats' readers convert into it).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from eventcap.body.template import Template
from eventcap.camera import Camera
from eventcap.events import EVENT_DTYPE

from eventcap.artifact import Artifact, ArtifactError, array, attr


@dataclass(frozen=True, eq=False)
class EventStream(Artifact):
    """Events of one sensor, sorted by time, inside the sensor, polarity ±1 (``EVENT_DTYPE``, eventcap/events.py)."""

    schema_version: ClassVar[int] = 1
    time_dims: ClassVar[dict[str, str]] = {"n": "events.t"}
    events: np.ndarray = array(EVENT_DTYPE, ("n",), units="t: us, x/y: px, p: ±1")
    width: int = attr(units="px")
    height: int = attr(units="px")

    def validate(self) -> None:
        super().validate()
        ev = self.events
        if ev.size == 0:
            return
        dt = np.diff(ev["t"])
        if dt.size and dt.min() < 0:
            i = int(np.argmax(dt < 0)) + 1
            raise ArtifactError(f"EventStream.events: timestamps not sorted at row {i} ({ev['t'][i - 1]} > {ev['t'][i]} us)")
        for col, limit in (("x", self.width), ("y", self.height)):
            bad = ev[col] >= limit
            if bad.any():
                i = int(np.argmax(bad))
                raise ArtifactError(f"EventStream.events: {col}={ev[col][i]} at row {i} outside the sensor (< {limit})")
        badp = (ev["p"] != 1) & (ev["p"] != -1)
        if badp.any():
            i = int(np.argmax(badp))
            raise ArtifactError(f"EventStream.events: polarity {ev['p'][i]} at row {i}, expected -1 or +1")

    def window(self, t0_us: int, t1_us: int) -> np.ndarray:
        """Events with t0_us <= t < t1_us (a view)."""
        a, b = np.searchsorted(self.events["t"], [t0_us, t1_us], side="left")
        return self.events[a:b]


@dataclass(frozen=True, eq=False)
class FrameStack(Artifact):
    """Intensity frames (APS) as linear intensity in [0, 1] (8-bit sources / 255, 16-bit / 65535), with
    exposure-centre times and exposure durations (0 = unknown: the file did not record it)."""

    schema_version: ClassVar[int] = 2
    time_dims: ClassVar[dict[str, str]] = {"n": "t_us"}
    images: np.ndarray = array("float32", ("n", "height", "width"), units="linear intensity [0,1]")
    t_us: np.ndarray = array("int64", ("n",), units="us", doc="exposure centre")
    exposure_us: np.ndarray = array("int64", ("n",), units="us")
    height: int = attr(units="px")
    width: int = attr(units="px")
    origin: str = attr(default="", doc="'' the camera's own frames | 'events': images reconstructed from the events "
                                       "(an event-only camera; a detector may then make other images from them)")

    def validate(self) -> None:
        super().validate()
        if self.origin not in ("", "events"):
            raise ArtifactError(f"FrameStack.origin: expected '' or 'events', got {self.origin!r}")
        if self.t_us.size > 1 and np.any(np.diff(self.t_us) <= 0):
            i = int(np.argmax(np.diff(self.t_us) <= 0)) + 1
            raise ArtifactError(f"FrameStack.t_us: frame times must increase; frame {i} is at {self.t_us[i]} us")
        if np.any(self.exposure_us < 0):
            raise ArtifactError("FrameStack.exposure_us: exposures must be >= 0")
        if self.images.size and (self.images.min() < 0 or self.images.max() > 1):
            raise ArtifactError(
                f"FrameStack.images: expected linear intensity in [0, 1], got [{self.images.min()}, {self.images.max()}]"
            )


@dataclass(frozen=True, eq=False)
class GroundTruth(Artifact):
    """Exact motion of a synthetic capture (or a reference capture of a real one)."""

    schema_version: ClassVar[int] = 1
    time_dims: ClassVar[dict[str, str]] = {"t": "t_us", "n": "frame_t_us"}
    t_us: np.ndarray = array("int64", ("t",), units="us")
    poses: np.ndarray = array("float64", ("t", 33), units="rad, m (S = [theta, R, t])")
    joints: np.ndarray = array("float64", ("t", 24, 3), units="m")
    landmarks: np.ndarray = array("float64", ("t", "l", 3), units="m")
    frame_poses: np.ndarray = array("float64", ("n", 33), units="rad, m")
    frame_joints: np.ndarray = array("float64", ("n", 24, 3), units="m")
    height: int = attr(units="px")
    width: int = attr(units="px")
    sharp_images: np.ndarray = array("float32", ("n", "height", "width"), units="linear intensity [0,1]",
                                     optional=True)
    track_tri: np.ndarray = array("int32", ("p",), doc="triangle of each tracked surface point", optional=True)
    track_bary: np.ndarray = array("float32", ("p", 3), optional=True)
    track_px: np.ndarray = array("float32", ("t", "p", 2), units="px", optional=True)
    track_visible: np.ndarray = array("bool", ("t", "p"), optional=True)
    frame_t_us: np.ndarray = array("int64", ("n",), units="us", optional=True,
                                   doc="times of frame_poses, frame_joints and sharp_images; None = the recording's "
                                       "intensity frame times (set when they differ, e.g. an event-only capture)")
    actor: str = attr(default="", doc="the filmed body when it is not the recording's template: JSON of its model "
                                      "and parameters (a synthetic capture's source.actor); '' = the recording's "
                                      "template is the filmed body")


#: Recording.world's values (see its doc).
WORLDS = ("", "assumed_level", "level", "camera")


@dataclass(frozen=True, eq=False)
class Recording(Artifact):
    """One event-camera recording: events, frames, camera, optionally the actor template and ground truth."""

    schema_version: ClassVar[int] = 1
    #: a windowed read keeps the ground truth's frames (without times of their own) at the frames it keeps
    window_links: ClassVar[dict[str, dict[str, tuple[str, str]]]] = {"ground_truth": {"n": ("frames", "n")}}
    events: EventStream
    camera: Camera
    frames: FrameStack | None = None
    template: Template | None = None
    ground_truth: GroundTruth | None = None
    name: str = attr(default="")
    source: str = attr(default="", doc="where it came from (file, or the simulation's settings)")
    world: str = attr(default="", doc="how its world frame was set: '' from the camera's extrinsics (a synthetic "
                                      "capture's, a calibration's); 'assumed_level': no extrinsics, the camera "
                                      "assumed level at the origin until the detect stage measures the person's "
                                      "vertical; 'level': no extrinsics, level or tilted as the user said; "
                                      "'camera': the camera's own axes (y down)")

    def validate(self) -> None:
        super().validate()
        if self.world not in WORLDS:
            raise ArtifactError(f"Recording.world: expected one of {' | '.join(map(repr, WORLDS))}, got "
                                f"{self.world!r}")
        e, c = self.events, self.camera
        if (e.width, e.height) != (c.width, c.height):
            raise ArtifactError(
                f"Recording: events are {e.width}x{e.height} but the camera is {c.width}x{c.height} (width x height)"
            )
        if self.frames is not None and (self.frames.width, self.frames.height) != (c.width, c.height):
            raise ArtifactError(
                f"Recording: frames are {self.frames.width}x{self.frames.height}, camera {c.width}x{c.height}"
            )

    @property
    def width(self) -> int:
        return self.camera.width

    @property
    def images_from_events(self) -> bool:
        """Whether the recording's images were made from its events (an event-only camera's reconstructions,
        ``FrameStack.origin`` 'events'), not taken by the camera."""
        return self.frames is not None and self.frames.origin == "events"

    @property
    def height(self) -> int:
        return self.camera.height

    def require_frames(self, stage: str) -> FrameStack:
        if self.frames is None or self.frames.images.shape[0] < 2:
            n = 0 if self.frames is None else self.frames.images.shape[0]
            raise ArtifactError(
                f"stage {stage!r} needs intensity frames (at least 2), but recording {self.name or self.source!r} "
                f"has {n} (an event-only recording: run pipeline=events_only, images reconstructed from the events)"
            )
        return self.frames
