"""Executors give identical results (serial, process pool, Dask); a Dask worker killed mid-run does not change them;
sweeps run on Hydra's joblib and submitit launchers sharing one cache; stores that cannot rename are refused."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time

import pytest

from eventcap.core.cache import Cache, CacheError
from eventcap.core.runner import Runner

from helpers.paths import TESTS
from helpers.toy import toy_env


def entries(cache_dir) -> dict[str, dict]:
    return {e.key: {f: v[1] for f, v in e.manifest["files"].items()} for e in Cache(cache_dir).entries()}


def run_with(toy_cfg, tmp_path, name, executor, **stage_changes):
    cfg = toy_cfg(**stage_changes)
    cfg["cache_dir"] = str(tmp_path / name)
    cfg["executor"] = executor
    return Runner(cfg).run(), cfg["cache_dir"]


def test_serial_processes_dask_identical(toy_cfg, tmp_path):
    changes = {"signal": {"n_batches": 6, "seed": 5}}
    serial, c1 = run_with(toy_cfg, tmp_path, "serial", {"kind": "serial"}, **changes)
    pool, c2 = run_with(toy_cfg, tmp_path, "pool", {"kind": "processes", "workers": 2}, **changes)
    dask, c3 = run_with(toy_cfg, tmp_path, "dask", {"kind": "dask", "workers": 2}, **changes)
    assert serial.ok and pool.ok and dask.ok
    assert serial.metrics == pool.metrics == dask.metrics
    assert entries(c1) == entries(c2) == entries(c3) and len(entries(c1)) == 1 + 6 + 6 + 1


def test_dask_worker_killed_mid_run_still_identical(toy_cfg, tmp_path):
    import psutil

    changes = {"signal": {"n_batches": 8}, "smooth": {"sleep_s": 0.4}, "scale": {"sleep_s": 0.4}}
    reference, c_ref = run_with(toy_cfg, tmp_path, "ref", {"kind": "serial"}, **changes)
    killed = []

    def kill_one_worker():
        me = psutil.Process()
        deadline = time.time() + 60
        while time.time() < deadline and not killed:
            time.sleep(0.2)
            if not list((tmp_path / "dask" / "entries").glob("toy_smooth/*")):
                continue  # wait until workers are busy with batches
            workers = [p for p in me.children(recursive=True) if "spawn" in " ".join(p.cmdline())]
            if workers:
                os.kill(workers[0].pid, signal.SIGKILL)
                killed.append(workers[0].pid)

    t = threading.Thread(target=kill_one_worker)
    t.start()
    result, c_dask = run_with(toy_cfg, tmp_path, "dask", {"kind": "dask", "workers": 2}, **changes)
    t.join()
    assert killed, "no worker was killed"
    assert result.ok and result.metrics == reference.metrics
    assert entries(c_dask) == entries(c_ref)
    assert list((tmp_path / "dask" / "tmp").iterdir()) == []


def test_unknown_executor_key_is_named(toy_cfg):
    cfg = toy_cfg()
    cfg["executor"] = {"kind": "dask", "adress": "tcp://x:1"}
    with pytest.raises(ValueError, match="executor.adress: no config key named 'adress' in executor; did you mean 'address'"):
        Runner(cfg)


def test_object_store_cache_is_refused(tmp_path):
    with pytest.raises(CacheError, match=r"s3:// stores cannot rename a directory atomically"):
        Cache("s3://bucket/eventcap-cache")
    assert Cache(f"file://{tmp_path / 'c'}").root == (tmp_path / "c").resolve()


@pytest.mark.parametrize("launcher", ["joblib", "submitit_local"])
def test_sweep_on_hydra_launchers_shares_the_cache(tmp_path, launcher):
    cmd = [sys.executable, "-m", "eventcap.apps.cli", "run", "-m", f"hydra.searchpath=[file://{TESTS / 'conf'}]",
           "experiment=toy", f"hydra/launcher={launcher}", "stages.scale.factor=1,2", f"cache_dir={tmp_path / 'cache'}"]
    if launcher == "submitit_local":
        cmd += ["hydra.launcher.timeout_min=5"]
    p = subprocess.run(cmd, cwd=tmp_path, env=toy_env(), capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-3000:]
    sweep = next((tmp_path / "runs" / "toy").glob("multirun_*"))
    sums = sorted(json.loads((sweep / str(i) / "metrics.json").read_text())["total.metrics"]["sum"] for i in (0, 1))
    assert sums[1] == pytest.approx(2 * sums[0])
    # 1 signal + 4 smooth shared by both jobs, 2 x (4 scale + 1 total)
    assert len(Cache(tmp_path / "cache").entries()) == 1 + 4 + 2 * 5


def test_a_worker_with_another_stage_refuses_the_task(toy, tmp_path):
    """A Dask worker from another install (another stage version, other defaults) refuses to compute under the
    driver's key: the task fails with status worker_mismatch naming what differs, and nothing is committed."""
    import dataclasses

    from eventcap.core.config import build_config, config_to_dict
    from eventcap.core.registry import load_registry
    from eventcap.core.runner import Task, base_doc, execute_task

    spec = load_registry().get("toy_scale")
    config = build_config(spec, {"factor": 3.0}, "stages.scale")
    doc = base_doc(spec, config, "stages.scale")
    Cache(tmp_path / "cache")  # made (and marked) as the driver makes it
    task = Task(str(tmp_path / "cache"), "scale", "toy_scale", config_to_dict(config), "stages.scale", {}, "a" * 64,
                doc, check_install=True)

    older = execute_task(dataclasses.replace(task, doc={**doc, "version": spec.version + 1}))
    assert older.status == "failed" and older.failure_status == "worker_mismatch"
    assert f"version: here {spec.version}, the driver's {spec.version + 1}" in older.error
    assert "install the same eventcap and plugins" in older.error
    other_default = {**doc, "config": {**doc["config"], "factor": 2.5}}
    res = execute_task(dataclasses.replace(task, doc=other_default))
    assert res.failure_status == "worker_mismatch" and "config: here differs at factor" in res.error
    assert Cache(tmp_path / "cache").lookup("toy_scale", "a" * 64) is None
    # the same install passes the check (and then fails only for want of its input)
    same = execute_task(task)
    assert same.status == "failed" and same.failure_status != "worker_mismatch"


def _start(cmd, env):
    return subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


@pytest.fixture
def dask_scheduler(tmp_path):
    """A Dask scheduler on this machine, as `dask scheduler` starts one for a cluster; its address, and a function
    that starts a worker process with a given environment (as on another machine)."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    dask = [sys.executable, "-m", "distributed.cli.dask_scheduler"]
    procs = [_start([*dask, "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"], dict(os.environ))]
    address = f"tcp://127.0.0.1:{port}"

    def worker(env):
        procs.append(_start([sys.executable, "-m", "distributed.cli.dask_worker", address, "--nworkers", "1",
                             "--nthreads", "1", "--no-dashboard"], env))

    deadline = time.time() + 60
    while time.time() < deadline:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                break
        time.sleep(0.2)
    try:
        yield address, worker
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()


def _wait_for_workers(address, n):
    from distributed import Client

    with Client(address, timeout="30s") as client:
        client.wait_for_workers(n, timeout=60)


def test_a_cluster_at_an_address_gives_the_serial_result_and_refuses_another_install(toy_cfg, tmp_path,
                                                                                      dask_scheduler):
    """executor.address: the run's batches go to workers started apart (`dask worker`, their own environment, as on
    other machines sharing the cache) and give what serial gives; a worker whose toy_scale is another version
    refuses its batches (worker_mismatch), the run says so, and nothing of it is committed."""
    address, worker = dask_scheduler
    changes = {"signal": {"n_batches": 4, "seed": 2}}
    serial, c_serial = run_with(toy_cfg, tmp_path, "serial", {"kind": "serial"}, **changes)
    worker(toy_env())
    _wait_for_workers(address, 1)
    same, c_same = run_with(toy_cfg, tmp_path, "cluster", {"kind": "dask", "address": address, "retries": 0},
                            **changes)
    assert same.ok and same.metrics == serial.metrics and entries(c_same) == entries(c_serial)

    from distributed import Client

    with Client(address, timeout="30s") as client:  # its one worker replaced by another install's
        client.retire_workers(close_workers=True)
    env = toy_env()
    env["EVENTCAP_STAGES"] = "toy_stages:SPECS,toy_stages:NEWER_SCALE"
    worker(env)
    _wait_for_workers(address, 1)
    res, c_other = run_with(toy_cfg, tmp_path / "other", "cluster", {"kind": "dask", "address": address,
                                                                     "retries": 0}, **changes)
    assert not res.ok
    failed = res.nodes["scale"].failed
    assert len(failed) == 4 and {f["status"] for f in failed} == {"worker_mismatch"}
    assert "version: here 2, the driver's 1" in failed[0]["error"]
    stages = [e.stage for e in Cache(c_other).entries()]
    assert res.nodes["total"].skipped and "toy_smooth" in stages and "toy_scale" not in stages
