"""Errors of the energy library (:class:`eventcap.errors.ComputationFailed`: the runner records their ``status``
and ``details``)."""

from __future__ import annotations

from eventcap.errors import ComputationFailed


class EnergyError(ComputationFailed, ValueError):
    """Data a factor or solve cannot use; ``status`` names the cause for the run's records."""

    def __init__(self, message: str, status: str = "invalid_input", details: dict | None = None):
        super().__init__(message, status, details)


class SolveFailed(ComputationFailed):
    """A solve that did not succeed (IPOPT's status, or nothing to fit); recorded as the batch's failure with its
    ``status`` and ``details``, never cached as a success."""


__all__ = ["EnergyError", "SolveFailed"]
