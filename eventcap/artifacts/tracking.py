"""Artifacts of Sec. 3.1: sharpened latent images, asynchronous feature tracks, and tracks sliced at 1 ms."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from eventcap.artifact import Artifact, ArtifactError, array, attr


@dataclass(frozen=True, eq=False)
class LatentFrames(Artifact):
    """EDI latent log images L(t_k) = log(I + eps) at every intensity frame's exposure centre (Eq. 2)."""

    schema_version: ClassVar[int] = 1
    time_dims: ClassVar[dict[str, str]] = {"n": "t_us"}
    log_images: np.ndarray = array("float32", ("n", "height", "width"), units="log(linear intensity + eps)")
    t_us: np.ndarray = array("int64", ("n",), units="us")
    contrast: float = attr(units="log intensity", doc="contrast threshold C used for the event integrals")
    eps: float = attr(doc="offset of the log")
    contrast_estimated: bool = attr(default=False, doc="C came from the automatic search")
    height: int = attr(default=0, units="px")
    width: int = attr(default=0, units="px")


@dataclass(frozen=True, eq=False)
class Tracks(Artifact):
    """Asynchronous 2D feature tracks of one batch: samples (track, time, position), time-sorted per track."""

    schema_version: ClassVar[int] = 1
    track_id: np.ndarray = array("int32", ("s",), doc="track of each sample, 0..n_tracks-1")
    t_us: np.ndarray = array("int64", ("s",), units="us")
    xy: np.ndarray = array("float32", ("s", 2), units="px")
    cost: np.ndarray = array("float32", ("s",), doc="match cost of the sample (method-specific, smaller is better)")
    kind: np.ndarray = array("int8", ("h",), doc="1 forward only, 2 backward only, 3 stitched (Sec. 3.1)")
    survived: np.ndarray = array("bool", ("h",), doc="tracked to the batch end in its direction(s)")

    @property
    def n_tracks(self) -> int:
        return int(self.kind.shape[0])

    def validate(self) -> None:
        super().validate()
        if self.track_id.size and (self.track_id.min() < 0 or self.track_id.max() >= self.n_tracks):
            raise ArtifactError(f"Tracks.track_id: expected ids in [0, {self.n_tracks}), "
                                f"got [{self.track_id.min()}, {self.track_id.max()}]")


@dataclass(frozen=True, eq=False)
class SlicedTracks(Artifact):
    """Tracks sampled at every tracking frame of a batch (1 ms by default): the solver's correspondences."""

    schema_version: ClassVar[int] = 1
    t_us: np.ndarray = array("int64", ("f",), units="us", doc="tracking frame times t_0..t_N")
    xy: np.ndarray = array("float32", ("f", "h", 2), units="px (nan where not valid)")
    valid: np.ndarray = array("bool", ("f", "h"), doc="inside the track's observed time span")
    track_id: np.ndarray = array("int32", ("h",))

    def validate(self) -> None:
        super().validate()
        if np.isnan(self.xy[self.valid]).any():
            raise ArtifactError("SlicedTracks.xy: NaN at a valid position")
