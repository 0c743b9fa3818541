"""Small, honest test stages for the framework (not part of the method): a seeded signal cut into batches,
a per-batch moving average, a per-batch scale, and a whole-recording sum. Registered in tests through
EVENTCAP_STAGES=toy_stages:SPECS with tests/ on PYTHONPATH."""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from eventcap.artifacts import Artifact, BatchPlan, Metrics, array, attr
from eventcap.core.stage import Port, StageFailed, StageSpec, param


@dataclass(frozen=True, eq=False)
class Series(Artifact):
    """A sampled scalar signal."""

    schema_version: ClassVar[int] = 1
    t_us: np.ndarray = array("int64", ("n",), units="us")
    values: np.ndarray = array("float64", ("n",), units="1")
    label: str = attr(default="")


@dataclass
class SignalConfig:
    n_batches: int = param(4, help="number of batches")
    samples_per_batch: int = param(50, help="samples per batch")
    seed: int = param(0, help="random seed")
    sleep_s: float = param(0.0, help="pretend work (s)", affects_result=False)


@dataclass
class SmoothConfig:
    window: int = param(5, help="moving-average window (samples)")
    sleep_s: float = param(0.0, help="pretend work per batch (s)", affects_result=False)
    fail_batches: list[int] = param(default_factory=list, help="batches that raise (failure injection)",
                                    affects_result=False)


@dataclass
class ScaleConfig:
    factor: float = param(2.0, help="multiplier")
    sleep_s: float = param(0.0, help="pretend work per batch (s)", affects_result=False)


@dataclass
class SumConfig:
    power: int = param(1, help="sum of values**power")


def run_signal(inputs, config: SignalConfig, ctx):
    time.sleep(config.sleep_s)
    n = config.n_batches * config.samples_per_batch
    rng = ctx.rng(config.seed)
    t = np.arange(n + 1, dtype=np.int64) * 1000
    values = np.cumsum(rng.normal(size=n + 1))
    frames = t[:: config.samples_per_batch]
    return {"series": Series(t_us=t, values=values, label="signal"), "batches": BatchPlan.between_frames(frames)}


def run_smooth(inputs, config: SmoothConfig, ctx):
    b = ctx.batch
    if b.index in config.fail_batches:
        raise StageFailed(f"injected failure in batch {b.index}", status="Injected_Failure")
    time.sleep(config.sleep_s)
    s = inputs["series"]
    m = (s.t_us >= b.t0_us) & (s.t_us <= b.t1_us)
    v = s.values[m]
    k = np.ones(config.window) / config.window
    sm = np.convolve(np.pad(v, config.window // 2, mode="edge"), k, mode="valid")[: v.size]
    return {"chunk": Series(t_us=s.t_us[m].copy(), values=sm, label=f"batch{b.index}")}


def run_scale(inputs, config: ScaleConfig, ctx):
    time.sleep(config.sleep_s)
    c = inputs["chunk"]
    return {"chunk": Series(t_us=c.t_us.copy(), values=c.values * config.factor, label=c.label)}


@dataclass
class NeighboursConfig:
    reach: int = param(1, help="batches on each side whose chunks are averaged in")


def run_neighbours(inputs, config: NeighboursConfig, ctx):
    """Per batch: the batch's chunk plus the mean value of the chunks of the batches within ``reach`` (those of
    the plan given: a batch selection leaves the others out)."""
    chunks, k = inputs["chunks"], ctx.batch.index
    where = {b.index: i for i, b in enumerate(chunks.batches)}
    near = [chunks[where[j]].values.mean() for j in range(k - config.reach, k + config.reach + 1) if j in where]
    own = chunks[where[k]]
    return {"chunk": Series(t_us=own.t_us.copy(), values=own.values + float(np.mean(near)),
                            label=f"{own.label}+{len(near)}")}


@dataclass
class GroupConfig:
    size: int = param(2, help="batches per group")


def run_group(inputs, config: GroupConfig, ctx):
    """Groups of ``size`` consecutive batches (the last may be shorter), as a plan."""
    plan = inputs["batches"]
    first = np.arange(0, len(plan), config.size)
    last = np.minimum(first + config.size, len(plan)) - 1
    return {"groups": BatchPlan(t0_us=plan.t0_us[first].copy(), t1_us=plan.t1_us[last].copy(),
                                frame0=plan.frame0[first].copy())}


@dataclass
class PerGroupConfig:
    pass


def run_per_group(inputs, config: PerGroupConfig, ctx):
    """Per group: the values of its batches' chunks (those given), one after another."""
    chunks, g = inputs["chunks"], ctx.batch
    mine = [i for i, b in enumerate(chunks.batches) if b.t0_us >= g.t0_us and b.t1_us <= g.t1_us]
    parts = [chunks[i] for i in mine]
    return {"chunk": Series(t_us=np.concatenate([c.t_us for c in parts]),
                            values=np.concatenate([c.values for c in parts]),
                            label="+".join(str(chunks.batches[i].index) for i in mine))}


def run_sum(inputs, config: SumConfig, ctx):
    chunks = inputs["chunks"]
    total = float(sum(np.sum(chunks[i].values ** config.power) for i in range(len(chunks))))
    return {"metrics": Metrics(values={"sum": total, "n_batches": len(chunks)})}


SPECS = [
    StageSpec(name="toy_signal", kind="toy_source", version=1, description="seeded random walk cut into batches",
              config=SignalConfig, inputs={}, outputs={"series": Port(Series), "batches": Port(BatchPlan)},
              run="toy_stages:run_signal"),
    StageSpec(name="toy_smooth", kind="toy_filter", version=1, description="per-batch moving average",
              config=SmoothConfig, inputs={"series": Port(Series), "batches": Port(BatchPlan)},
              outputs={"chunk": Port(Series)}, run="toy_stages:run_smooth", per_batch=True),
    StageSpec(name="toy_scale", kind="toy_filter", version=1, description="per-batch scaling",
              config=ScaleConfig, inputs={"chunk": Port(Series)}, outputs={"chunk": Port(Series)},
              run="toy_stages:run_scale", per_batch=True),
    StageSpec(name="toy_neighbours", kind="toy_filter", version=1,
              description="per batch, plus the mean of its neighbouring batches' chunks",
              config=NeighboursConfig, inputs={"chunks": Port(Series, all_batches=True)},
              outputs={"chunk": Port(Series)}, run="toy_stages:run_neighbours", per_batch=True),
    StageSpec(name="toy_group", kind="toy_plan", version=1, description="consecutive batches in groups",
              config=GroupConfig, inputs={"batches": Port(BatchPlan)}, outputs={"groups": Port(BatchPlan)},
              run="toy_stages:run_group"),
    StageSpec(name="toy_per_group", kind="toy_filter", version=1,
              description="per group of batches: its batches' chunks one after another",
              config=PerGroupConfig, inputs={"chunks": Port(Series, all_batches=True), "batches": Port(BatchPlan),
                                             "groups": Port(BatchPlan)},
              outputs={"chunk": Port(Series)}, run="toy_stages:run_per_group", per_batch=True, plan="groups"),
    StageSpec(name="toy_sum", kind="toy_reduce", version=1, description="sum over all batches",
              config=SumConfig, inputs={"chunks": Port(Series, all_batches=True)},
              outputs={"metrics": Port(Metrics)}, run="toy_stages:run_sum"),
]

#: toy_scale as another install has it (a newer version): a worker whose EVENTCAP_STAGES adds this is not the
#: driver's (tests/test_executors.py)
NEWER_SCALE = [dataclasses.replace(next(s for s in SPECS if s.name == "toy_scale"), version=2)]
