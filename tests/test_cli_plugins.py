"""The CLI end to end on the toy pipeline, and a third-party stage package installed and run from outside."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from helpers.paths import TESTS
from helpers.toy import toy_env

TOY = [f"hydra.searchpath=[file://{TESTS / 'conf'}]", "experiment=toy"]


def run_cli(args, cwd, env=None, check=True):
    proc = subprocess.run([sys.executable, "-m", "eventcap.apps.cli", *args], cwd=cwd, env=env or toy_env(),
                          capture_output=True, text=True, timeout=300)
    if check and proc.returncode != 0:
        raise AssertionError(f"exit {proc.returncode}\n{proc.stdout}\n{proc.stderr}")
    return proc


def test_run_writes_run_folder_and_resumes(tmp_path):
    p = run_cli(["run", *TOY], tmp_path)
    runs = sorted((tmp_path / "runs" / "toy").iterdir())
    assert len(runs) == 1
    folder = runs[0]
    for name in ("config.yaml", "eventcap.log", "metrics.json", "run.json"):
        assert (folder / name).is_file(), name
    metrics = json.loads((folder / "metrics.json").read_text())
    assert metrics["total.metrics"]["n_batches"] == 4
    assert "computing" in (folder / "eventcap.log").read_text()
    p2 = run_cli(["run", *TOY, "hydra.run.dir=runs/again"], tmp_path)
    log2 = (tmp_path / "runs" / "again" / "eventcap.log").read_text()
    assert "0 computed, 10 cached" in log2 and "4 batches: 4 cached, 0 to compute" in log2
    assert p.returncode == p2.returncode == 0


def test_run_reports_failures_and_exits_nonzero(tmp_path):
    p = run_cli(["run", *TOY, "stages.smooth.fail_batches=[1]"], tmp_path, check=False)
    assert p.returncode == 1
    assert "batch 1 FAILED (Injected_Failure)" in p.stderr + p.stdout
    assert "run incomplete: smooth failed in 1 of 4 batches: 1 Injected_Failure (batch 1)" in p.stderr + p.stdout


def test_bad_override_and_bad_stage_are_clear(tmp_path):
    p = run_cli(["run", *TOY, "stages.smooth.windw=3"], tmp_path, check=False)
    # Hydra's "Key 'windw' is not in struct" becomes the project's message, without asking for a '+'
    assert p.returncode == 1 and "stages.smooth.windw: no config key named 'windw' in stages.smooth" in p.stderr
    assert "did you mean 'window'?" in p.stderr and "+stages" not in p.stderr
    p = run_cli(["run", *TOY, "stages.scale.stage=toy_scal"], tmp_path, check=False)
    assert p.returncode == 1 and "did you mean 'toy_scale'" in p.stdout + p.stderr


def test_cfg_job_shows_composed_config(tmp_path):
    p = run_cli(["run", "--cfg", "job", *TOY], tmp_path)
    assert "stage: toy_smooth" in p.stdout and "nodes:" in p.stdout
    assert not (tmp_path / "runs").exists()


def test_multirun_shares_cache_and_cache_commands(tmp_path):
    run_cli(["run", "-m", *TOY, "stages.scale.factor=1,2"], tmp_path)
    sweep = next((tmp_path / "runs" / "toy").glob("multirun_*"))
    m = [json.loads((sweep / str(i) / "metrics.json").read_text())["total.metrics"]["sum"] for i in (0, 1)]
    assert m[1] == pytest.approx(2 * m[0])
    log1 = (sweep / "1" / "eventcap.log").read_text()
    assert "smooth (toy_smooth v1): 4 batches: 4 cached" in log1  # shared with job 0
    ls = run_cli(["cache", "ls"], tmp_path).stdout
    assert "toy_scale" in ls and "15 entries" in ls  # 1 signal + 4 smooth + 2x4 scale + 2 total
    key = json.loads((sweep / "0" / "run.json").read_text())["nodes"]["total"]["keys"][0]
    ex = run_cli(["cache", "explain", key[:8]], tmp_path).stdout
    assert "stage    toy_sum v1" in ex and "chunks <- " in ex and "power = 1" in ex
    bad = run_cli(["cache", "explain", "ffffffff"], tmp_path, check=False)
    assert bad.returncode == 2 and "no cache entry with key 'ffffffff'" in bad.stderr
    gc = run_cli(["cache", "gc", "--all"], tmp_path).stdout
    assert "15 cache entries" in gc


def test_third_party_plugin_installed_and_run(tmp_path):
    site = tmp_path / "site"
    pip = subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "--no-build-isolation", "--quiet",
                          "--target", str(site), str(TESTS / "fixtures" / "eventcap_hello")],
                         capture_output=True, text=True, timeout=300)
    assert pip.returncode == 0, pip.stderr[-3000:]
    env = toy_env()
    env["PYTHONPATH"] = f"{site}:{env['PYTHONPATH']}"
    listing = run_cli(["stages", "-v"], tmp_path, env=env).stdout
    assert "hello_count" in listing and "[eventcap-hello]" in listing
    (tmp_path / "conf" / "pipeline").mkdir(parents=True)
    (tmp_path / "conf" / "pipeline" / "hello.yaml").write_text(
        "nodes:\n  signal: {}\n  hello:\n    inputs: {batches: signal.batches}\n")
    run_cli(["run", f"hydra.searchpath=[file://{TESTS / 'conf'},file://{tmp_path / 'conf'}]", "pipeline=hello",
             "+stages/signal=toy", "+stages.hello.stage=hello_count", "+stages.hello.scale=2.0",
             "hydra.run.dir=runs/hello"], tmp_path, env=env)
    m = json.loads((tmp_path / "runs" / "hello" / "metrics.json").read_text())
    assert m["hello.metrics"] == {"batches": 4, "duration_s": 2 * 0.2}
