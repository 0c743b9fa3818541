"""Typed artifacts exchanged between stages: every type a plugin declares its ports with, importable from here.

``docs/artifacts.md`` lists each with its fields (made by :func:`eventcap.artifacts.reference.markdown`; a test keeps
the page and the dataclasses in step). The contract every type follows (declared arrays, validation, zarr I/O) is
:mod:`eventcap.artifact`.
"""

from eventcap.artifact import Artifact, ArtifactError, ArraySpec, AttrSpec, array, attr
from eventcap.body.template import Template
from eventcap.camera import Camera

from .core import Batch, BatchPlan, Metrics
from .pose import Detections, JointConfidence, JointErrors, PoseSequence
from .recording import EventStream, FrameStack, GroundTruth, Recording
from .tracking import LatentFrames, SlicedTracks, Tracks

#: every artifact type, in the order docs/artifacts.md lists them (the recording first, then the data flow)
TYPES: tuple[type[Artifact], ...] = (
    Recording, EventStream, FrameStack, Camera, Template, GroundTruth, BatchPlan, LatentFrames, Tracks, SlicedTracks,
    Detections, PoseSequence, JointErrors, JointConfidence, Metrics)

__all__ = ["Artifact", "ArtifactError", "ArraySpec", "AttrSpec", "array", "attr", "Batch", "TYPES",
           *(t.__name__ for t in TYPES)]
