"""Kill a multi-batch run with SIGKILL at random moments, resume it, and check the result: a run killed at any
moment and started again must end with the outputs of an uninterrupted run (eventcap/core/cache.py: atomic commits).

For each trial: start `eventcap run` on the toy pipeline (tests/toy_stages.py) in a fresh cache, SIGKILL its whole
process group (``--kill group``) or the driver alone (``--kill driver``: its pool / Dask workers must then die on their
own) at a random time, note which entries were committed, run the same command again, and check that (1) the final
metrics and every cache entry's files equal an uninterrupted run, (2) the resumed run computed none of the entries
committed before the kill, and (3) with ``--kill driver``, no process of the killed run is left 10 s after the kill.

    python benchmarks/robustness/kill_resume.py --trials 20 [--executor serial|processes|dask|mixed|all] [--kill driver]

The command runs :func:`main` here; tests/test_kill_resume.py runs it with 3 trials (20, and every executor, marked
slow).
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from .paths import TESTS
from .toy import toy_env as env

SLEEP_S = 0.08  # pretend work per batch and stage (--sleep)


def command(run_dir: str, executor: str) -> list[str]:
    return [sys.executable, "-m", "eventcap.apps.cli", "run", f"hydra.searchpath=[file://{TESTS / 'conf'}]",
            "experiment=toy", "stages.signal.n_batches=6", f"stages.smooth.sleep_s={SLEEP_S}",
            f"stages.scale.sleep_s={SLEEP_S}",
            f"executor={executor}", f"hydra.run.dir={run_dir}", "log_level=WARNING"]


def committed(cache: Path) -> dict[str, dict]:
    """key -> {relative file: sha256} of every committed entry."""
    out = {}
    for mf in cache.glob("entries/*/*/manifest.json"):
        m = json.loads(mf.read_text())
        out[m["key"]] = {f: v[1] for f, v in m["files"].items()}
    return out


def survivors(procs, timeout_s: float) -> list:
    """Those of ``procs`` still running (zombies count as gone) after waiting up to ``timeout_s``."""
    import psutil

    deadline = time.monotonic() + timeout_s
    while True:
        alive = []
        for p in procs:
            try:
                if p.status() != psutil.STATUS_ZOMBIE:
                    alive.append(p)
            except psutil.NoSuchProcess:
                pass
        if not alive or time.monotonic() > deadline:
            return alive
        time.sleep(0.1)


def run_trial(workdir: Path, executor: str, kill_after: float, kill: str = "group") -> dict:
    import psutil

    proc = subprocess.Popen(command("runs/killed", executor), cwd=workdir, env=env(), start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    time.sleep(kill_after)
    killed = proc.poll() is None
    orphans, n_children = 0, 0
    if killed and kill == "driver":
        try:
            children = psutil.Process(proc.pid).children(recursive=True)
        except psutil.NoSuchProcess:
            children = []
        n_children = len(children)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        left = survivors(children, 10.0)
        orphans = len(left)
        for p in left:  # counted; removed so that they cannot touch the resumed run
            p.kill()
    elif killed:
        os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    before = committed(workdir / "runs" / "cache")
    res = subprocess.run(command("runs/resumed", executor), cwd=workdir, env=env(), capture_output=True, text=True)
    if res.returncode != 0:
        raise RuntimeError(f"resume failed: {res.stderr[-2000:]}")
    summary = json.loads((workdir / "runs" / "resumed" / "run.json").read_text())
    recomputed = {k for n in summary["nodes"].values() for k in n["computed_keys"]} & set(before)
    metrics = json.loads((workdir / "runs" / "resumed" / "metrics.json").read_text())
    leftovers = list((workdir / "runs" / "cache" / "tmp").iterdir())
    return {"killed": killed, "committed_before": len(before), "recomputed_committed": len(recomputed),
            "metrics": metrics, "entries": committed(workdir / "runs" / "cache"), "tmp_leftovers": len(leftovers),
            "children": n_children, "orphans": orphans}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trials", type=int, default=20)
    ap.add_argument("--executor", default="serial", choices=["serial", "processes", "dask", "mixed", "all"],
                    help="mixed: serial and processes by turns; all: serial, processes and dask by turns")
    ap.add_argument("--kill", default="group", choices=["group", "driver"],
                    help="SIGKILL the run's whole process group, or the driver alone (its workers must follow)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--sleep", type=float, default=0.08, help="pretend work per batch of smooth and scale (s): "
                                                               "longer runs put more kills in the middle of the work")
    args = ap.parse_args(argv)
    global SLEEP_S
    SLEEP_S = args.sleep
    cycle = {"mixed": ("serial", "processes"), "all": ("serial", "processes", "dask")}.get(args.executor,
                                                                                          (args.executor,))
    rng = random.Random(args.seed)
    with tempfile.TemporaryDirectory() as tmp:
        ref_dir = Path(tmp) / "reference"
        ref_dir.mkdir()
        t0 = time.perf_counter()
        subprocess.run(command("runs/ref", "serial"), cwd=ref_dir, env=env(), check=True, capture_output=True)
        full_s = time.perf_counter() - t0
        ref_metrics = json.loads((ref_dir / "runs" / "ref" / "metrics.json").read_text())
        ref_entries = committed(ref_dir / "runs" / "cache")
        print(f"uninterrupted run: {full_s:.2f} s, {len(ref_entries)} entries, metrics {ref_metrics}")
        durations = {"serial": full_s}
        for ex in cycle:  # the kill window of each executor is its own run time (a Dask cluster takes a while)
            if ex not in durations:
                wd = Path(tmp) / f"uninterrupted-{ex}"
                wd.mkdir()
                t0 = time.perf_counter()
                subprocess.run(command("runs/ref", ex), cwd=wd, env=env(), check=True, capture_output=True)
                durations[ex] = time.perf_counter() - t0
                same = committed(wd / "runs" / "cache") == ref_entries
                print(f"uninterrupted run, executor={ex}: {durations[ex]:.2f} s, entries identical to serial={same}")
        bad = killed_n = orphans = 0
        for i in range(args.trials):
            ex = cycle[i % len(cycle)]
            wd = Path(tmp) / f"trial{i}"
            wd.mkdir()
            kill_after = rng.uniform(0.3, durations[ex] * 1.1)
            r = run_trial(wd, ex, kill_after, args.kill)
            same = r["metrics"] == ref_metrics and r["entries"] == ref_entries
            ok = same and r["recomputed_committed"] == 0 and r["orphans"] == 0
            bad += not ok
            killed_n += r["killed"]
            orphans += r["orphans"]
            procs = f", {r['orphans']} of its {r['children']} processes left 10 s after" if args.kill == "driver" else ""
            print(f"trial {i:2d} [{ex:9s}] kill {args.kill} at {kill_after:5.2f} s (killed={r['killed']!s:5}{procs}): "
                  f"{r['committed_before']:2d}/{len(ref_entries)} committed before, "
                  f"{r['recomputed_committed']} of them recomputed, outputs identical={same}, "
                  f"tmp leftovers after resume={r['tmp_leftovers']} -> {'OK' if ok else 'FAIL'}")
        print(f"{args.trials - bad} passed, {bad} failed ({killed_n} killed mid-run, kill={args.kill}, "
              f"orphaned processes: {orphans})")
    return 1 if bad else 0
