"""Typed artifacts exchanged between stages (the public types a plugin declares its ports with)."""

from .base import Artifact, ArtifactError, ArraySpec, AttrSpec, array, attr
from .core import Batch, BatchPlan, Metrics

__all__ = ["Artifact", "ArtifactError", "ArraySpec", "AttrSpec", "array", "attr", "Batch", "BatchPlan", "Metrics"]
