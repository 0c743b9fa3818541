"""Test stages for the run outputs: per-batch poses from a known motion, with failures on request."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from eventcap.artifacts import BatchPlan
from eventcap.artifacts.pose import PoseSequence
from eventcap.artifacts.recording import Recording
from eventcap.core.stage import Port, StageFailed, StageSpec, param


@dataclass
class KnownPosesConfig:
    motion: str = param("jumping_jack", help="the motion whose poses every batch returns")
    step_us: int = param(1000, help="tracking frame step")
    fail_batches: list = param(default_factory=list, help="these batches fail (all: [-1])")


def run(inputs, config, ctx):
    from eventcap.body.motions import motion_poses

    b = ctx.batch
    if b.index in config.fail_batches or -1 in config.fail_batches:
        raise StageFailed(f"batch {b.index} fails on request", status="test_failure")
    t = np.arange(b.t0_us, b.t1_us + 1, config.step_us, dtype=np.int64)
    return {"poses": PoseSequence(t_us=t, poses=motion_poses(config.motion, t * 1e-6), status="known")}


KNOWN_POSES = StageSpec(
    name="known_poses", kind="solve", version=1, description="per-batch poses of a known motion (tests)",
    config=KnownPosesConfig, inputs={"recording": Port(Recording), "batches": Port(BatchPlan)},
    outputs={"poses": Port(PoseSequence)}, run="output_stages:run", per_batch=True)
SPECS = [KNOWN_POSES]
