"""Chunks (issue 46): a per-batch node cut by a plan of chunks runs one task per chunk, reads every batch it needs,
and `batches=` selects the chunks that overlap the selected batches; the spline solve keeps a chunk's batches and
solves them in one window with margins."""

from __future__ import annotations

import numpy as np
import pytest

from eventcap.artifacts import BatchPlan
from eventcap.artifacts.core import Batch
from eventcap.core.pipeline import build_pipeline
from eventcap.core.registry import load_registry
from eventcap.core.runner import Runner
from eventcap.core.stage import StageFailed
from eventcap.core.testing import StageConformance


def _grouped(cfg, size=2):
    cfg["pipeline"]["nodes"]["group"] = {"inputs": {"batches": "signal.batches"}}
    cfg["pipeline"]["nodes"]["per_group"] = {"inputs": {"chunks": "scale.chunk", "batches": "signal.batches",
                                                        "groups": "group.groups"}}
    cfg["stages"]["group"] = {"stage": "toy_group", "size": size}
    cfg["stages"]["per_group"] = {"stage": "toy_per_group"}
    return cfg


def test_a_node_is_cut_by_the_plan_its_stage_names(toy_cfg):
    nodes = {n.name: n for n in build_pipeline(_grouped(toy_cfg()), load_registry())}
    assert (nodes["per_group"].plan_node, nodes["per_group"].plan_port) == ("group", "groups")
    assert (nodes["scale"].plan_node, nodes["scale"].plan_port) == ("signal", "batches")


def test_one_task_per_chunk_reading_its_batches(toy_cfg):
    runner = Runner(_grouped(toy_cfg()))
    r = runner.run()
    assert r.ok and r.nodes["per_group"].computed == 2 and r.nodes["scale"].computed == 4
    groups, scaled = runner.load_output(r, "per_group.chunk"), runner.load_output(r, "scale.chunk")
    assert [groups[g].label for g in (0, 1)] == ["0+1", "2+3"]
    np.testing.assert_array_equal(groups[1].values, np.concatenate([scaled[2].values, scaled[3].values]))
    again = Runner(_grouped(toy_cfg())).run()
    assert again.nodes["per_group"].cached == 2 and again.computed_keys() == 0


@pytest.mark.parametrize("selection, labels", [("1:3", {0: "1", 1: "2"}), ("2", {0: "0+1"}), ("3:4", {1: "3"})])
def test_a_batch_selection_runs_the_chunks_it_overlaps(toy_cfg, selection, labels):
    cfg = _grouped(toy_cfg())
    cfg["batches"] = selection
    runner = Runner(cfg)
    r = runner.run()
    assert r.ok
    assert {g: s.label for g, s in runner.load_output(r, "per_group.chunk").items()} == labels


def test_chunk_rows_group_batches_and_fold_a_short_tail():
    from eventcap_spline.chunks import chunk_rows

    t = np.arange(0, 1_000_001, 40_000)  # 25 batches of 40 ms
    assert chunk_rows(t[:-1], t[1:], 0.4) == [(0, 9), (10, 19), (20, 24)]  # 5 batches = 0.2 s: a chunk of its own
    assert chunk_rows(t[:-1], t[1:], 0.44) == [(0, 10), (11, 24)]  # the tail of 3 (< 0.22 s) joins the one before
    assert chunk_rows(t[:-1], t[1:], 10.0) == [(0, 24)]
    assert chunk_rows(t[:-1], t[1:], 0.01) == [(k, k) for k in range(25)]  # a batch each


def test_a_chunk_window_is_its_batches_with_margins_shifted_inwards():
    from eventcap_spline._impl import unit_role

    t = np.arange(0, 1_000_001, 40_000)
    plan = BatchPlan(t0_us=t[:-1], t1_us=t[1:], frame0=np.arange(25))
    chunk = lambda i, a, z: Batch(i, int(t[a]), int(t[z + 1]), a)  # noqa: E731
    assert unit_role(plan, chunk(1, 10, 19), 2, 1) == (10, (8, 21, 10, 19))
    assert unit_role(plan, chunk(0, 0, 9), 2, 1) == (0, (0, 13, 0, 9))  # shifted inwards: the same length
    assert unit_role(plan, chunk(2, 20, 24), 2, 1) == (20, (16, 24, 20, 24))
    assert unit_role(plan, chunk(0, 0, 24), 2, 1) == (0, (0, 24, 0, 24))  # fewer batches than the window: all
    assert unit_role(plan, chunk(3, 7, 7), 2, 1) == (7, (5, 9, 7, 7))  # one batch: the window of that batch
    with pytest.raises(StageFailed, match="stages.solve.window_step: 2 applies to a solve per batch"):
        unit_role(plan, chunk(1, 10, 19), 2, 2)


def test_a_plan_a_stage_names_must_be_one_of_its_batch_plan_inputs():
    from eventcap.core.stage import Port, StageSpec, StageSpecError
    from eventcap_spline.spec import ChunksConfig

    with pytest.raises(StageSpecError, match="plan 'groups' must name a BatchPlan input of a per-batch stage"):
        StageSpec(name="x", kind="k", version=1, description="", config=ChunksConfig,
                  inputs={"batches": Port(BatchPlan)}, outputs={"out": Port(BatchPlan)}, run="m:f", per_batch=True,
                  plan="groups")


def test_the_spline_pipeline_solves_a_chunk_per_task_and_resumes(tmp_path):
    """0.25 s (6 batches) in chunks of 0.12 s: two windows, each keeping its 3 batches with a batch of margin on each side (shifted inwards at the ends); one
    motion without a gap; a second run computes nothing."""
    import json

    from eventcap.apps.cli import main
    from helpers.runs import TINY_SPLINE_RUN

    args = [*TINY_SPLINE_RUN, "source.duration_s=0.25", "stages.chunk.seconds=0.12", f"cache_dir={tmp_path / 'c'}"]
    assert main(["run", *args, f"hydra.run.dir={tmp_path / 'a'}"]) == 0
    nodes = json.loads((tmp_path / "a" / "run.json").read_text())["nodes"]
    assert nodes["solve"]["computed"] == 2 and nodes["track"]["computed"] == 6 and nodes["cut"]["computed"] == 6
    log = (tmp_path / "a" / "eventcap.log").read_text()
    assert "chunk 0 (batches 0..2): window of batches 0..4" in log  # a margin of 1, shifted inwards
    assert "chunk 1 (batches 3..5): window of batches 1..5" in log
    with np.load(tmp_path / "a" / "motion.npz") as z:
        t, poses = z["t_us"], z["poses"]
    assert np.all(np.diff(t) == 1000) and np.isfinite(poses).all()
    metrics = json.loads((tmp_path / "a" / "metrics.json").read_text())["evaluate.metrics"]
    assert 5 < metrics["AE_mm"] < 60
    assert main(["run", *args, f"hydra.run.dir={tmp_path / 'b'}"]) == 0
    again = json.loads((tmp_path / "b" / "run.json").read_text())["nodes"]
    assert sum(n["computed"] for n in again.values()) == 0


class TestChunksConformance(StageConformance):
    stage_name = "chunks"
    sensitive = ("seconds", 0.5)

    def make_inputs(self):
        t = np.arange(0, 400_001, 40_000)
        return {"batches": BatchPlan(t0_us=t[:-1], t1_us=t[1:], frame0=np.arange(10))}

    def test_the_chunks_cover_the_batches_once(self):
        out = self.run_once(seconds=0.12)["chunks"]
        assert out.t0_us.tolist() == [0, 120_000, 240_000] and out.t1_us.tolist() == [120_000, 240_000, 400_000]
        assert out.frame0.tolist() == [0, 3, 6]  # the last chunk took the tail of one batch
