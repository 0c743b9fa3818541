"""Specs of the frames-only smoothing stages (pipeline=frames_smooth). Declarations only: scipy loads when they run."""

from __future__ import annotations

from dataclasses import dataclass

from eventcap.artifacts.pose import PoseSequence
from eventcap.core.stage import Port, StageSpec, param


@dataclass
class SmoothConfig:
    pool: str = param("group", help="one smoothing parameter per group of pose parameters (group: all angles, "
                                    "root translation) | per parameter (parameter)", choices=("group", "parameter"))
    lam: float = param(0.0, ge=0, help="smoothing parameter in s³ for every group (0 = chosen from the fits alone by "
                                 "the criterion)")
    criterion: str = param("gcv", help="how lam is chosen from the fits alone: gcv (generalised cross-validation) | "
                                       "reml (restricted likelihood)",
                           choices=("reml", "gcv"))


SMOOTH = StageSpec(
    name="smooth", kind="fuse", version=3,
    description="frames only: cubic smoothing splines through the per-frame fits at the intensity frames, smoothing "
                "chosen from the fits (REML or GCV), sampled at every tracking frame (frames_smooth; not in the paper)",
    config=SmoothConfig,
    inputs={"fits": Port(PoseSequence, "every batch's poses; their first and last rows are the per-frame fits at "
                                       "the batch's two intensity frames (solve mode linear)", all_batches=True)},
    outputs={"motion": Port(PoseSequence, doc="the smoothed motion at every tracking frame of every batch")},
    run="eventcap_smooth._impl:run_smooth",
)


@dataclass
class SplitConfig:
    pass


SPLIT = StageSpec(
    name="split", kind="fuse", version=1,
    description="one batch's frames of a whole-recording motion (at the times of the batch's own poses)",
    config=SplitConfig,
    inputs={"frames": Port(PoseSequence, "this batch's poses: only their times are used"),
            "motion": Port(PoseSequence, "the whole motion, holding every one of those times")},
    outputs={"poses": Port(PoseSequence)}, per_batch=True,
    run="eventcap_smooth._impl:run_split",
)
