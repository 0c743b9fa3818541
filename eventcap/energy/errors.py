"""Errors of the energy library (a leaf: no imports). The runner records a failure's ``status`` and ``details``."""

from __future__ import annotations


class EnergyError(ValueError):
    """Data a factor or solve cannot use. ``status`` names the cause for the run's records (the runner reads it)."""

    status = "invalid_input"


class SolveFailed(RuntimeError):
    """A solve that did not succeed (IPOPT's status, or nothing to fit); recorded as the batch's failure with its
    ``status`` and ``details``, never cached as a success."""

    def __init__(self, message: str, status: str = "failed", details: dict | None = None):
        super().__init__(message)
        self.status = status
        self.details = details or {}


__all__ = ["EnergyError", "SolveFailed"]
