"""The error a computation of the domain library ends with when it did not succeed, with a status the run records.

The library (body, camera, sim, io, energy, motion, ...) imports nothing from the orchestration (stage, runner,
cache, registry, cli, pipeline, jobs, benchmark): its modules raise errors of their own, subclasses of
:class:`ComputationFailed` when a run should record a short machine-readable status (e.g. ``bad_poses``, a solver's
status), and the runner translates them into the failed unit's record (``run.json``: ``failed[].status``), as it
does for a stage's :class:`eventcap.core.stage.StageFailed`. Plain input mistakes stay ``ValueError``.
"""

from __future__ import annotations

from typing import Any


class ComputationFailed(RuntimeError):
    """A computation that did not succeed: the message says why, ``status`` names the outcome in a word (recorded by
    the runner as the failed unit's status), ``details`` holds JSON-serialisable diagnostics."""

    def __init__(self, message: str, status: str = "failed", details: dict[str, Any] | None = None):
        super().__init__(message)
        self.status = status
        self.details = details or {}
