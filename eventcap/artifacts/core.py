"""Artifact types the framework itself relies on: the batch plan and metrics."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from eventcap.artifact import Artifact, ArtifactError, array, attr


@dataclass(frozen=True)
class Batch:
    """One batch: the interval between two intensity frames (paper Sec. 3.1), frames ``frame0`` and ``frame0+1``."""

    index: int
    t0_us: int
    t1_us: int
    frame0: int

    def as_key(self) -> dict[str, int]:
        return {"index": self.index, "t0_us": self.t0_us, "t1_us": self.t1_us, "frame0": self.frame0}


@dataclass(frozen=True, eq=False)
class BatchPlan(Artifact):
    """How a recording is cut into batches; per-batch stages run and cache once per row."""

    schema_version: ClassVar[int] = 1
    t0_us: np.ndarray = array("int64", ("n",), units="us", doc="batch start (time of its first intensity frame)")
    t1_us: np.ndarray = array("int64", ("n",), units="us", doc="batch end (time of its second intensity frame)")
    frame0: np.ndarray = array("int64", ("n",), doc="index of the batch's first intensity frame")

    def validate(self) -> None:
        super().validate()
        if np.any(self.t1_us <= self.t0_us):
            i = int(np.argmax(self.t1_us <= self.t0_us))
            raise ArtifactError(f"BatchPlan: batch {i} ends ({self.t1_us[i]} us) before it starts ({self.t0_us[i]} us)")

    def __len__(self) -> int:
        return int(self.t0_us.shape[0])

    def batch(self, i: int) -> Batch:
        return Batch(int(i), int(self.t0_us[i]), int(self.t1_us[i]), int(self.frame0[i]))

    def batches(self) -> list[Batch]:
        return [self.batch(i) for i in range(len(self))]

    @classmethod
    def between_frames(cls, frame_t_us: np.ndarray) -> BatchPlan:
        """One batch between each pair of consecutive frame times."""
        t = np.asarray(frame_t_us, dtype=np.int64)
        return cls(t0_us=t[:-1].copy(), t1_us=t[1:].copy(), frame0=np.arange(max(len(t) - 1, 0), dtype=np.int64))

    @classmethod
    def at_rate(cls, t_first_us: int, t_last_us: int, rate_hz: float) -> BatchPlan:
        """Batches of 1/rate_hz from ``t_first_us`` while they end by ``t_last_us`` (a recording without intensity
        frames: its images are reconstructed at these boundaries, ``frame0`` counts them)."""
        if not rate_hz > 0:
            raise ValueError(f"batch rate: expected a rate > 0 Hz, got {rate_hz!r}")
        period = 1e6 / float(rate_hz)
        n = int(np.floor((int(t_last_us) - int(t_first_us)) / period + 1e-9)) + 1
        return cls.between_frames(int(t_first_us) + np.round(np.arange(max(n, 0)) * period).astype(np.int64))


@dataclass(frozen=True, eq=False)
class Metrics(Artifact):
    """Named scalar results of a stage (JSON-serialisable); the runner collects them into metrics.json."""

    schema_version: ClassVar[int] = 1
    values: dict[str, Any] = attr(doc="metric name -> number, string or nested dict of them")
