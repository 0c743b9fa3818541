"""Two sweeps on one cache at once; the toy stages pass the conformance suite every stage inherits."""

from __future__ import annotations

import json
import sys

import numpy as np

from eventcap.artifacts import BatchPlan
from eventcap.core.cache import Cache
from eventcap.core.testing import StageConformance

from helpers.paths import TESTS
from helpers.toy import run_concurrently


def test_two_sweeps_concurrently_on_one_cache(tmp_path):
    base = [sys.executable, "-m", "eventcap.apps.cli", "run", "-m", f"hydra.searchpath=[file://{TESTS / 'conf'}]",
            "experiment=toy", "stages.smooth.sleep_s=0.02", f"cache_dir={tmp_path / 'cache'}", "log_level=WARNING"]
    run_concurrently([base + ["stages.scale.factor=1,2,3", "name=a"], base + ["stages.scale.factor=3,2,1", "name=b"]],
                     tmp_path)
    cache = Cache(tmp_path / "cache")
    entries = cache.entries()
    assert len(entries) == 1 + 4 + 3 * 4 + 3
    for e in entries:
        cache.verify(e)  # every file present and matching its checksum
    assert list((cache.root / "tmp").iterdir()) == []
    sums = {}
    for exp in ("a", "b"):
        jobs = [j for j in (tmp_path / "runs" / exp).glob("multirun_*/*") if j.is_dir()]
        assert len(jobs) == 3
        for job in jobs:
            assert json.loads((job / "run.json").read_text())["ok"]
            factor = float((job / "config.yaml").read_text().split("factor: ")[1].split()[0])
            sums.setdefault(factor, set()).add(json.loads((job / "metrics.json").read_text())["total.metrics"]["sum"])
    assert all(len(v) == 1 for v in sums.values()) and sums[2.0].pop() == 2 * sums[1.0].pop()


class _ToyConformance(StageConformance):
    def make_inputs(self):
        spec = self.spec()
        out = {}
        series_cls = __import__("toy_stages").Series
        t = np.arange(0, 80_001, 1000, dtype=np.int64)
        s = series_cls(t_us=t, values=np.sin(t / 1e4), label="x")
        for port, p in spec.inputs.items():
            if p.type is BatchPlan:
                out[port] = BatchPlan.between_frames(np.array([0, 40_000, 80_000]))
            elif p.all_batches:
                out[port] = [s, s]
            else:
                out[port] = s
        return out


class TestToySignal(_ToyConformance):
    stage_name = "toy_signal"
    sensitive = ("seed", 1)
    insensitive = ("sleep_s", 0.001)


class TestToySmooth(_ToyConformance):
    stage_name = "toy_smooth"
    sensitive = ("window", 3)
    insensitive = ("fail_batches", [5])


class TestToySum(_ToyConformance):
    stage_name = "toy_sum"
    sensitive = ("power", 2)


import pytest  # noqa: E402


@pytest.fixture(autouse=True)
def _toy_registered(toy):
    yield


def test_the_suite_asks_for_a_sensitive_setting_while_the_stage_has_one():
    class NoSensitive(_ToyConformance):
        stage_name = "toy_sum"

    with pytest.raises(AssertionError, match=r"set sensitive = \(setting, another value\) on NoSensitive: stage "
                                             r"'toy_sum' has settings that change its result: power"):
        NoSensitive().test_cache_key_sensitive()
