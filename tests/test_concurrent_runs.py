"""Runs at the same time, through the CLI (issue 19): each run gets its own folder and a live run's folder is refused;
pool workers die with a driver killed by kill -9; concurrent runs and sweeps compute each cache entry once."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from eventcap.core.cache import Cache, EntryLock, clean_stale_locks
from eventcap.core.rundir import LOCK_NAME, claim, release

from helpers.paths import TESTS
from helpers.toy import run_concurrently, toy_env
from helpers.kill_resume import survivors

TOY = [sys.executable, "-m", "eventcap.apps.cli", "run", f"hydra.searchpath=[file://{TESTS / 'conf'}]", "experiment=toy",
       "outputs.poses=null"]


def _factor(text: str) -> float:
    return float(text.split("factor: ")[1].split()[0])


def _wait_for(pred, timeout_s: float, what: str):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        got = pred()
        if got:
            return got
        time.sleep(0.05)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")


def _computed(run_json: Path) -> list[str]:
    return [k for n in json.loads(run_json.read_text())["nodes"].values() for k in n["computed_keys"]]


# ---------------------------------------------------------------------------------------------------------------------
# 1. run folders
# ---------------------------------------------------------------------------------------------------------------------
def test_two_runs_started_together_get_their_own_consistent_folders(tmp_path):
    procs = {f: subprocess.Popen(TOY + [f"stages.scale.factor={f}", f"cache_dir={tmp_path / 'cache'}"], cwd=tmp_path,
                                 env=toy_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for f in (1, 3)}
    outs = {f: p.communicate(timeout=120) for f, p in procs.items()}
    assert all(p.returncode == 0 for p in procs.values()), outs
    folders = sorted(d for d in (tmp_path / "runs" / "toy").iterdir())
    assert len(folders) == 2, folders
    sums = {}
    for d in folders:
        assert re.fullmatch(r"\d{4}-\d\d-\d\d_\d\d-\d\d-\d\d\.\d{6}(-\d+)?", d.name), d.name
        factor = _factor((d / "config.yaml").read_text())
        assert _factor((d / ".hydra" / "config.yaml").read_text()) == factor  # Hydra's copy and ours agree
        assert f"stages.scale.factor={factor:g}" in (d / ".hydra" / "overrides.yaml").read_text().replace("- ", "")
        assert json.loads((d / "run.json").read_text())["ok"]
        log = (d / "eventcap.log").read_text()
        assert f"run folder: {d}" in log and all(f"run folder: {o}" not in log for o in folders if o != d)
        sums[factor] = json.loads((d / "metrics.json").read_text())["total.metrics"]["sum"]
    assert set(sums) == {1.0, 3.0} and sums[3.0] == pytest.approx(3 * sums[1.0])
    # the shared entries (signal, 4 smooth) were computed by one of the two runs only
    computed = [k for d in folders for k in _computed(d / "run.json")]
    assert len(computed) == len(set(computed)) == len(Cache(tmp_path / "cache").entries()) == 1 + 4 + 2 * (4 + 1)


def test_a_default_folder_is_always_fresh(tmp_path):
    first = claim(tmp_path / "runs" / "2026-01-01_00-00-00.000000", fresh=True)
    second = claim(tmp_path / "runs" / "2026-01-01_00-00-00.000000", fresh=True)  # the same microsecond
    try:
        assert first.name == "2026-01-01_00-00-00.000000" and second.name == "2026-01-01_00-00-00.000000-1"
        assert f"pid {os.getpid()}" in (second / LOCK_NAME).read_text()
    finally:
        release(first)
        release(second)


def test_a_live_runs_folder_is_refused_and_left_alone(tmp_path):
    same = ["hydra.run.dir=runs/same", f"cache_dir={tmp_path / 'cache'}"]
    a = subprocess.Popen(TOY + same + ["stages.scale.factor=5", "stages.smooth.sleep_s=2.0"], cwd=tmp_path,
                         env=toy_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        _wait_for(lambda: f"pid {a.pid} " in (tmp_path / "runs" / "same" / LOCK_NAME).read_text()
                  if (tmp_path / "runs" / "same" / LOCK_NAME).exists() else False, 60, "the first run's claim")
        b = subprocess.run(TOY + same + ["stages.scale.factor=7"], cwd=tmp_path, env=toy_env(), capture_output=True,
                           text=True, timeout=120)
        assert a.poll() is None, "the first run ended before the second was started; the test proves nothing"
    finally:
        out_a = a.communicate(timeout=120)
    assert b.returncode == 2
    assert "the run folder runs/same is in use by another eventcap process (pid " + str(a.pid) in b.stderr
    assert "hydra.run.dir" in b.stderr
    assert a.returncode == 0, out_a
    d = tmp_path / "runs" / "same"
    assert _factor((d / "config.yaml").read_text()) == _factor((d / ".hydra" / "config.yaml").read_text()) == 5.0
    assert "factor=7" not in (d / ".hydra" / "overrides.yaml").read_text()
    # a finished run's folder can be run into again (as before): nobody holds it any more
    c = subprocess.run(TOY + same + ["stages.scale.factor=7"], cwd=tmp_path, env=toy_env(), capture_output=True,
                       text=True, timeout=120)
    assert c.returncode == 0, c.stderr[-2000:]
    assert _factor((d / ".hydra" / "config.yaml").read_text()) == _factor((d / "config.yaml").read_text()) == 7.0


# ---------------------------------------------------------------------------------------------------------------------
# 2. workers die with their driver
# ---------------------------------------------------------------------------------------------------------------------
def _kill_driver_and_check_workers(tmp_path, executor: str, n_workers: int) -> None:
    import psutil

    p = subprocess.Popen(TOY + [f"executor={executor}", f"cache_dir={tmp_path / 'cache'}", "stages.signal.n_batches=12",
                                "stages.smooth.sleep_s=2", "hydra.run.dir=runs/killed", "log_level=WARNING"],
                         cwd=tmp_path, env=toy_env(), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                         start_new_session=True)
    driver = psutil.Process(p.pid)
    children: list = []
    locks = tmp_path / "cache" / "locks"
    try:
        # the workers are busy once two batches are being computed (two entry locks held at once)
        _wait_for(lambda: len(list(locks.glob("*.lock"))) >= 2 if locks.is_dir() else False, 90,
                  "the workers to start on batches")
        children = driver.children(recursive=True)
        workers = [c for c in children if "spawn_main" in " ".join(c.cmdline())]
        assert len(workers) >= n_workers, [c.cmdline() for c in children]
        os.kill(p.pid, signal.SIGKILL)
        p.wait(timeout=10)

        left = survivors(children, 10.0)
        assert not left, f"the workers and resource tracker of the killed driver did not exit: {left}"
    finally:
        for c in [driver, *children]:  # nothing of this test may outlive it, whatever happened above
            try:
                c.kill()
            except psutil.NoSuchProcess:
                pass
        p.wait(timeout=10)
    # the resumed run finishes the job
    r = subprocess.run(TOY + [f"executor={executor}", f"cache_dir={tmp_path / 'cache'}", "stages.signal.n_batches=12",
                              "hydra.run.dir=runs/resumed", "log_level=WARNING"], cwd=tmp_path, env=toy_env(),
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert list((tmp_path / "cache" / "tmp").iterdir()) == []


def test_pool_workers_die_with_a_killed_driver(tmp_path):
    _kill_driver_and_check_workers(tmp_path, "processes", 2)


@pytest.mark.slow
def test_dask_workers_die_with_a_killed_driver(tmp_path):
    _kill_driver_and_check_workers(tmp_path, "dask", 2)


# ---------------------------------------------------------------------------------------------------------------------
# 3. each entry computed once
# ---------------------------------------------------------------------------------------------------------------------
def test_entry_lock_is_exclusive_and_a_killed_holder_leaves_nothing_stuck(tmp_path):
    holder = subprocess.Popen([sys.executable, "-c", (
        "import sys, time; from eventcap.core.cache import EntryLock; lock = EntryLock(sys.argv[1], 'abc123');"
        "assert lock.acquire(owner='node x'); print('held', flush=True); time.sleep(60)"), str(tmp_path)],
        stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        lock = EntryLock(tmp_path, "abc123")
        assert not lock.acquire(blocking=False)
        waits = []
        assert not lock.held
        holder.send_signal(signal.SIGKILL)  # no clean-up at all: the kernel drops the flock
        holder.wait(timeout=10)
        assert lock.acquire(on_wait=lambda who, s: waits.append(who))
        assert lock.held and f"pid {os.getpid()}" in lock.path.read_text()
        lock.release()
        assert not lock.path.exists()
    finally:
        holder.kill()
        holder.wait()
    # a killed holder's file (unlocked) is removed by the cache's orphan clean-up; a file whose name is no lock the
    # cache makes (<key>.lock, a 40-hex key) is not the cache's to remove
    stale = EntryLock(tmp_path, "def456" * 6 + "abcd")
    stale.path.parent.mkdir(parents=True, exist_ok=True)
    stale.path.write_text("pid 1 on host gone")
    foreign = stale.path.with_name("notes.lock")
    foreign.write_text("someone else's")
    assert clean_stale_locks(tmp_path) == 1 and not stale.path.exists() and foreign.read_text() == "someone else's"


@pytest.mark.parametrize("executor", ["processes", pytest.param("dask", marks=pytest.mark.slow)])
def test_two_identical_runs_compute_each_entry_once(tmp_path, executor):
    args = [f"cache_dir={tmp_path / 'cache'}", "stages.signal.n_batches=6", "stages.signal.sleep_s=0.5",
            "stages.smooth.sleep_s=0.1", "log_level=INFO"]
    procs = [subprocess.Popen(TOY + args + [f"hydra.run.dir=runs/{n}", f"executor={ex}"], cwd=tmp_path, env=toy_env(),
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for n, ex in (("a", "serial"), ("b", executor))]
    outs = [p.communicate(timeout=300) for p in procs]
    assert all(p.returncode == 0 for p in procs), outs
    computed = _computed(tmp_path / "runs" / "a" / "run.json") + _computed(tmp_path / "runs" / "b" / "run.json")
    entries = Cache(tmp_path / "cache").entries()
    assert len(entries) == 1 + 6 + 6 + 1
    assert sorted(computed) == sorted(e.key for e in entries)  # every entry computed, and by one run only
    ma, mb = (json.loads((tmp_path / "runs" / n / "metrics.json").read_text()) for n in ("a", "b"))
    assert ma == mb
    # whoever lost the race for the signal entry waited for it and said so in its log
    logs = "".join((tmp_path / "runs" / n / "eventcap.log").read_text() for n in ("a", "b"))
    assert "committed by another run meanwhile" in logs
    assert list((tmp_path / "cache" / "locks").iterdir()) == []


@pytest.mark.slow
def test_two_overlapping_sweeps_compute_each_entry_once(tmp_path):
    base = TOY[:4] + ["-m"] + TOY[4:] + [f"cache_dir={tmp_path / 'cache'}", "stages.smooth.sleep_s=0.05",
                                         "stages.signal.sleep_s=0.3", "log_level=WARNING"]
    # the same name: both sweeps would have had runs/s/multirun_<second> before
    run_concurrently([base + ["stages.scale.factor=1,2,3", "name=s"], base + ["stages.scale.factor=3,2,1", "name=s"]],
                     tmp_path)
    sweeps = sorted((tmp_path / "runs" / "s").glob("multirun_*"))
    assert len(sweeps) == 2 and all(len(list(s.glob("[0-9]"))) == 3 for s in sweeps), sweeps
    jobs = sorted((tmp_path / "runs").glob("*/multirun_*/[0-9]"))
    for j in jobs:
        assert _factor((j / "config.yaml").read_text()) == _factor((j / ".hydra" / "config.yaml").read_text())
    computed = [k for j in jobs for k in _computed(j / "run.json")]
    entries = Cache(tmp_path / "cache").entries()
    assert len(entries) == 1 + 4 + 3 * (4 + 1)
    assert sorted(computed) == sorted(e.key for e in entries)


def test_a_benchmark_refuses_a_folder_another_benchmark_is_writing(tmp_path):
    out = tmp_path / "bench"
    holder = subprocess.Popen([sys.executable, "-c", (
        "import sys, time; from eventcap.core.rundir import claim; claim(sys.argv[1], what='benchmark');"
        "print('held', flush=True); time.sleep(60)"), str(out)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        p = subprocess.run([sys.executable, "-m", "eventcap.apps.cli", "benchmark", "benchmark=quick", f"out={out}"],
                           cwd=tmp_path, capture_output=True, text=True, timeout=120)
    finally:
        holder.kill()
        holder.wait()
    assert p.returncode == 2, p.stdout[-2000:] + p.stderr[-2000:]
    assert f"the benchmark folder {out} is in use by another eventcap process (pid {holder.pid} " in p.stderr
    assert not (out / "runs").exists()


def test_a_pool_worker_killed_mid_run_is_replaced_and_the_result_unchanged(toy_cfg, tmp_path):
    import threading

    import psutil

    from eventcap.core.runner import Runner

    def run(name, executor):
        cfg = toy_cfg(signal={"n_batches": 6}, smooth={"sleep_s": 0.3})
        cfg["cache_dir"], cfg["executor"] = str(tmp_path / name), executor
        return Runner(cfg).run(), Cache(cfg["cache_dir"])

    reference, ref_cache = run("ref", {"kind": "serial"})
    killed = []

    def kill_one_worker():
        me = psutil.Process()
        locks = tmp_path / "pool" / "locks"
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not killed:
            time.sleep(0.05)
            if not (locks.is_dir() and list(locks.glob("*.lock"))):
                continue  # a worker is computing a batch once its entry lock exists
            workers = [p for p in me.children(recursive=True) if "spawn_main" in " ".join(p.cmdline())
                       and "resource_tracker" not in " ".join(p.cmdline())]
            if workers:
                workers[0].kill()
                killed.append(workers[0].pid)

    t = threading.Thread(target=kill_one_worker)
    t.start()
    result, cache = run("pool", {"kind": "processes", "workers": 2})
    t.join()
    assert killed, "no worker was killed"
    assert result.ok and result.metrics == reference.metrics
    assert {e.key: e.manifest["files"] for e in cache.entries()} == {e.key: e.manifest["files"]
                                                                     for e in ref_cache.entries()}
    assert list((tmp_path / "pool" / "tmp").iterdir()) == []


@pytest.mark.parametrize("kind", ["serial", pytest.param("processes", marks=pytest.mark.slow),
                                  pytest.param("dask", marks=pytest.mark.slow)])
def test_an_entry_another_process_holds_is_put_off_then_waited_for(toy_cfg, tmp_path, kind, caplog):
    import threading

    from eventcap.core.runner import Runner

    def run(name, executor):
        cfg = toy_cfg(signal={"n_batches": 4})
        cfg["cache_dir"], cfg["executor"] = str(tmp_path / name), executor
        return Runner(cfg).run()

    reference = run("ref", {"kind": "serial"})
    held_key = reference.batch_keys["smooth"][0]
    lock = EntryLock(tmp_path / "held", held_key)  # as another run computing smooth batch 0 would
    assert lock.acquire(owner="node smooth batch 0")

    def release_when_the_others_are_done():  # ... and then dying without committing it
        deadline = time.monotonic() + 120
        while len(list((tmp_path / "held" / "entries").glob("toy_smooth/*"))) < 3 and time.monotonic() < deadline:
            time.sleep(0.05)
        lock.release()

    timer = threading.Thread(target=release_when_the_others_are_done)
    timer.start()
    with caplog.at_level("INFO", logger="eventcap.core.runner"):
        result = run("held", {"kind": kind, "workers": 2})
    timer.join()
    assert result.ok and result.metrics == reference.metrics
    assert sorted(k for r in result.nodes.values() for k in r.computed_keys) == sorted(
        k for r in reference.nodes.values() for k in r.computed_keys)  # batch 0 too, once the holder was gone
    assert "smooth: 1 batch(es) being computed by another run: waiting for them" in caplog.text


@pytest.mark.slow
def test_the_issues_two_real_runs_at_once_keep_their_own_folders(tmp_path):
    # issue 19's report: a default run and a stages.solve.terms.sil.weight=2 run started in the same second shared one
    # folder, ending with .hydra/config.yaml from one and config.yaml / metrics.json from the other
    tiny = ["pipeline=paper", "experiment=quick", "source.duration_s=0.09", "template=procedural",
            "template.target_faces=2000", "source.n_track_points=20", "outputs.video=false",
            f"cache_dir={tmp_path / 'cache'}"]  # the issue's runs: the paper's pipeline, whose refine node it varies
    procs = [subprocess.Popen([sys.executable, "-m", "eventcap.apps.cli", "run", *tiny, *extra], cwd=tmp_path,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for extra in ([], ["stages.solve.terms.sil.weight=2"])]
    outs = [p.communicate(timeout=900) for p in procs]
    assert all(p.returncode == 0 for p in procs), [o[1][-2000:] for o in outs]
    folders = sorted((tmp_path / "runs" / "quick").iterdir())
    assert len(folders) == 2
    import yaml

    seen = set()
    for d in folders:
        ours = yaml.safe_load((d / "config.yaml").read_text())["stages"]["solve"]["terms"]["sil"]["weight"]
        hydras = yaml.safe_load((d / ".hydra" / "config.yaml").read_text())["stages"]["solve"]["terms"]["sil"]["weight"]
        assert ours == hydras
        seen.add(float(ours))
        assert (d / "motion.npz").exists() and "evaluate.metrics" in json.loads((d / "metrics.json").read_text())
        assert (d / "eventcap.log").read_text().count("run folder: ") == 1
    assert seen == {1.0, 2.0}
    computed = [k for d in folders for k in _computed(d / "run.json")]
    assert len(computed) == len(set(computed)) == len(Cache(tmp_path / "cache").entries())
