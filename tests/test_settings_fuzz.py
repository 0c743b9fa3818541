"""Every setting is checked before any work, naming the key and what it takes (issue 38).

The fuzz: every numeric key of every stage of the default and the main alternative pipelines, found from the stage
specs at test time (keys added later are covered too) x {0, -1, nan, inf, "abc"}, through the pipeline builder
in-process: a refusal (PipelineError naming ``<node config>.<key>``) where the value is outside what the field
declares, acceptance where it is inside, no other exception, and no stage's run function loaded (nothing runs). A
handful go through the real CLI in subprocesses: exit 1, the key in the message, no traceback.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

from eventcap.params import leaves

from eventcap.core.config import ConfigError, log_level_number
from eventcap.core.pipeline import PipelineError, build_pipeline
from eventcap.core.registry import load_registry
from eventcap.core.runner import ExecutorConfig
from eventcap.core.stage import StageSpec, check_value

ROOT = Path(__file__).resolve().parents[1]
PIPELINES = ("default", "paper", "events_only", "frames_smooth")
VALUES = (0, -1, math.nan, math.inf, "abc")
NUMERIC = ("int", "float", "int | None", "float | None", "list[int]", "list[float]")


def composed(pipeline: str) -> dict:
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose(config_name="config", overrides=["experiment=quick", f"pipeline={pipeline}"])
    return OmegaConf.to_container(cfg, resolve=True)


def _type(f: dataclasses.Field) -> str:
    return f.type if isinstance(f.type, str) else f.type.__name__


def numeric_keys(data: dict, registry) -> list[tuple[str, dataclasses.Field]]:
    """(dotted config path, field) of every numeric field of every node of the composed config's pipeline."""
    out = []
    for name, node in data["pipeline"]["nodes"].items():
        path = (node or {}).get("config") or f"stages.{name}"
        values = data
        for part in path.split("."):
            values = values[part]
        spec = registry.get(values["stage"])
        out += [(f"{path}.{key}", f) for key, f in leaves(spec.config) if _type(f) in NUMERIC]
    return out


def legal(f: dataclasses.Field, value) -> bool:
    """Whether the field takes the value, from its type and its declaration (what the builder must agree with)."""
    if isinstance(value, str):
        return False
    t = _type(f)
    if t.startswith("int") and isinstance(value, float) and not (math.isfinite(value) and value == int(value)):
        return False
    return check_value(f, [value] if t.startswith("list") else value) is None


def with_value(data: dict, dotted: str, value, f: dataclasses.Field) -> dict:
    """The config with one key set (the dicts along its path copied, the rest shared)."""
    d = copy.copy(data)
    node = d
    *parents, last = dotted.split(".")
    for part in parents:
        node[part] = copy.copy(node[part])
        node = node[part]
    node[last] = [value] if _type(f).startswith("list") else value
    return d


@pytest.fixture(scope="module")
def registry():
    return load_registry()


def test_every_numeric_stage_key_is_refused_or_taken_before_anything_runs(registry, monkeypatch):
    counts = {"keys": 0, "cases": 0, "refused": 0, "accepted": 0}
    loaded = []  # every run function the builder asks for: it must ask for none (nothing runs, nothing is imported)
    monkeypatch.setattr(StageSpec, "load_run", lambda spec: loaded.append(spec.name))
    seen: set[tuple[str, int]] = set()  # a key of the same stage in another pipeline is checked once
    for pipeline in PIPELINES:
        data = composed(pipeline)
        keys = numeric_keys(data, registry)
        assert len(keys) > 40, pipeline
        keys = [(k, f) for k, f in keys if (k, id(f)) not in seen]
        seen |= {(k, id(f)) for k, f in keys}
        counts["keys"] += len(keys)
        for dotted, f in keys:
            for value in VALUES:
                try:
                    build_pipeline(with_value(data, dotted, value, f), registry)
                    accepted, problems = True, []
                except PipelineError as exc:
                    accepted, problems = False, exc.problems
                counts["cases"] += 1
                counts["accepted" if accepted else "refused"] += 1
                # the synthetic source's roi is [x, y, width, height] inside the sensor: its check hook refuses a
                # one-item list before anything runs
                expected = legal(f, value) and dotted != "source.roi"
                assert accepted == expected, (pipeline, dotted, value, problems)
                if not accepted:
                    assert len(problems) == 1 and f"{dotted}: expected " in problems[0], (dotted, value, problems)
    print(f"settings fuzz: {counts}")
    assert counts["refused"] > counts["accepted"] > 0
    assert loaded == []


def test_what_the_issue_found_is_refused_with_the_key(registry):
    """The cases of issue 38, and values that are legal, through the same builder."""
    data = composed("default")
    cases = {("source.fps", math.nan): "source.fps: expected a finite number > 0, got nan",
             ("source.fps", 0): "source.fps: expected a finite number > 0, got 0",
             ("source.duration_s", -1): "source.duration_s: expected a finite number in (0, 3600], got -1",
             ("source.exposure_us", "abc"): "source.exposure_us: expected an integer >= 1, got 'abc'",
             # issue 48: the bound the stage used to apply itself is the declared one, and a huge value is refused
             ("source.exposure_us", 0): "source.exposure_us: expected an integer >= 1, got 0",
             ("source.camera_height_m", -1): "source.camera_height_m: expected a finite number > 0, got -1",
             ("source.duration_s", 1e308): "source.duration_s: expected a finite number in (0, 3600], got 1e+308",
             ("source.fps", 1e308): "source.fps: expected a finite number > 0, no larger than 1e+09 in size (a bound "
                                    "every setting without its own has), got 1e+308",
             ("stages.track.max_features", 10**30): "stages.track.max_features: expected an integer >= 1, no larger "
                                                    "than 1e+09 in size",
             ("stages.track.patch_px", 24): "stages.track.patch_px: expected an odd integer >= 5, got 24",
             ("stages.solve.knot_ms", math.inf): "stages.solve.knot_ms: expected a finite number > 0, got inf",
             ("stages.detect.outlier_prob", 1.5): "stages.detect.outlier_prob: expected a finite number in [0, 1], "
                                                  "got 1.5"}
    for (key, value), message in cases.items():
        *_, name = key.split(".")
        f = next(f for _, f in numeric_keys(data, registry) if _.endswith("." + name) and _ == key)
        with pytest.raises(PipelineError) as err:
            build_pipeline(with_value(data, key, value, f), registry)
        assert message in err.value.problems[0]
    for key, value in (("stages.solve.terms.sil.gain", 0), ("stages.solve.terms.prior.q_max_ratio", 1e6),
                       ("source.camera_height_m", 2.5), ("source.duration_s", 3600)):
        f = next(f for k, f in numeric_keys(data, registry) if k == key)
        build_pipeline(with_value(data, key, value, f), registry)  # legal: 0 turns a term off


@pytest.mark.parametrize("values, message", [
    ({"kind": "processes", "workers": "abc"}, "executor.workers: expected an integer >= 1, got 'abc'"),
    ({"kind": "processes", "workers": 0}, "executor.workers: expected an integer >= 1, got 0"),
    ({"kind": "dask", "workers": -1}, "executor.workers: expected an integer >= 1, got -1"),
    ({"kind": "dask", "threads_per_worker": 0}, "executor.threads_per_worker: expected an integer >= 1, got 0"),
    ({"kind": "dask", "retries": -1}, "executor.retries: expected an integer >= 0, got -1"),
    ({"kind": "threads"}, "executor.kind: expected one of serial | processes | dask, got 'threads'"),
    ({"kind": "dask", "address": "scheduler"}, "executor.address: expected tcp://host:port"),
    ({"kind": "dask", "wrokers": 2}, "executor.wrokers: no config key named 'wrokers' in executor"),
])
def test_executor_settings(values, message):
    with pytest.raises(ValueError) as err:
        ExecutorConfig.from_mapping(values)
    assert message in str(err.value)


def test_an_unreachable_scheduler_is_refused_after_one_bounded_attempt(monkeypatch):
    """One TCP connection attempt, bounded by 3 s, and the refusal names what happened (refused, not timed out)."""
    import socket

    attempts = []
    connect = socket.create_connection

    def counted(address, timeout=None, *args, **kwargs):
        attempts.append((address, timeout))
        return connect(address, timeout, *args, **kwargs)

    monkeypatch.setattr(socket, "create_connection", counted)
    with socket.socket() as s:  # a port nothing listens on: bound, never listening
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
        with pytest.raises(ValueError, match=rf"executor.address: no Dask scheduler reachable at "
                                             rf"tcp://127.0.0.1:{port} \(Connection refused; waited at most 3 s\)"):
            ExecutorConfig.from_mapping({"kind": "dask", "address": f"tcp://127.0.0.1:{port}"})
    assert attempts == [(("127.0.0.1", port), 3.0)]


def test_log_level():
    assert log_level_number("warning") == 30
    with pytest.raises(ConfigError, match=r"log_level: expected one of DEBUG \| INFO \| WARNING \| ERROR, got "
                                          r"'VERBOSE'"):
        log_level_number("VERBOSE")


@pytest.mark.parametrize("override, message", [
    ("source.fps=nan", "source.fps: expected a finite number > 0, got nan"),
    ("stages.track.max_features=abc", "stages.track.max_features: expected an integer >= 1, got 'abc'"),
    ("log_level=VERBOSE", "log_level: expected one of DEBUG | INFO | WARNING | ERROR, got 'VERBOSE'"),
    ("executor=processes executor.workers=0", "executor.workers: expected an integer >= 1, got 0"),
    ("executor=dask executor.workers=-1", "executor.workers: expected an integer >= 1, got -1"),
])
def test_the_real_cli_refuses_before_anything_runs(tmp_path, override, message):
    env = {**os.environ, "EVENTCAP_CACHE_DIR": str(tmp_path / "cache")}
    proc = subprocess.run([sys.executable, "-m", "eventcap.apps.cli", "run", "experiment=quick", *override.split()],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 1 and message in out and "Traceback" not in out
    assert list(tmp_path.iterdir()) == []  # issue 48: a refused setting leaves nothing on disk (no run folder, cache)


@pytest.mark.parametrize("override, message", [
    ("source.duration_s=1e308", "source.duration_s: expected a finite number in (0, 3600], got 1e+308"),
    ("source.exposure_us=0", "source.exposure_us: expected an integer >= 1, got 0"),
    ("+foo=1", "foo: no config key named 'foo' in the top-level config"),
    ("+stages.bogus.weight=1", "stages.bogus.weight: added with '+', but nothing reads it: no node of the pipeline "
                               "takes its config from stages.bogus"),
    ("+source.foo=1", "source.foo: no config key named 'foo' in the config of stage 'synthetic'"),
    ("source.roi=[0,0,500,500]", "source.roi: expected [x, y, width, height] inside the 240x180 sensor"),
    ("outputs.join=sometimes", "outputs.join: expected one of later | mean, got 'sometimes'"),
])
def test_a_refused_setting_leaves_nothing_on_disk(tmp_path, monkeypatch, capsys, override, message):
    """Issue 48: the settings are checked by a Hydra callback before the run folder is claimed (in-process: the
    same main() the command runs)."""
    from eventcap.apps.cli import main

    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("EVENTCAP_CACHE_DIR", str(tmp_path / "cache"))
    assert main(["run", "experiment=quick", override]) == 1
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []


def test_preflight_names_unknown_keys(registry):
    from eventcap.apps.jobs import preflight
    from eventcap.core.config import ConfigError

    data = composed("default")
    preflight(data, ["+stages.track.max_features=10"])  # added to a node the pipeline runs: read
    with pytest.raises(ConfigError, match="foo: no config key named 'foo' in the top-level config"):
        preflight({**data, "foo": 1}, ["+foo=1"])
    with pytest.raises(ConfigError, match="stages.nope.x: added with '\\+', but nothing reads it"):
        preflight(data, ["+stages.nope.x=1"])
