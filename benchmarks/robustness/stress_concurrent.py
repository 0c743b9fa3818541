"""Many runs and sweeps at once on one cache, drivers and workers killed with SIGKILL, then resumed (issue 19).

What it does, in a temporary folder:

1. reference: every distinct configuration once, one after the other, serial executor, in a cache of its own;
2. stress: ``--runs`` single runs (executors serial / processes / dask by turns, configurations by turns) and
   ``--sweeps`` overlapping sweeps, all started at once on ONE shared cache; while they run, ``--kills`` drivers
   (random live ones) and ``--worker-kills`` pool/Dask workers get SIGKILL at random moments;
3. resume: every command that did not exit 0 is run again (all at once), until it does (at most 3 rounds);
4. counts: processes started, exits, run folders and mixed folders (a folder whose ``config.yaml`` and
   ``.hydra/config.yaml`` disagree, or whose log has more than one run), entries in the cache, entry computations
   finished twice (the cache's "computed twice" warning; the entry locks should make it 0), processes of a killed
   driver still alive 10 s after the kill (orphans), and whether every result equals the serial reference: each
   run's metrics.json (and motion.npz with ``--pipeline tiny``), and every cache entry's files, checksum by checksum.

    python benchmarks/robustness/stress_concurrent.py --runs 6 --sweeps 2 --kills 3 --worker-kills 2 [--pipeline toy|tiny]

``--pipeline toy``: the framework's toy stages (tests/toy_stages.py, seconds per run); ``tiny``: the real pipeline on a
0.09 s synthetic capture (a minute of CPU per process: use few runs).
"""

from __future__ import annotations

import argparse
import json
import os
import random
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
TESTS = ROOT / "tests"
sys.path.insert(0, str(ROOT))  # the kill/resume harness: tests/helpers
from tests.helpers.kill_resume import committed  # noqa: E402
from tests.helpers.toy import toy_env  # noqa: E402


def env() -> dict[str, str]:
    """The toy stages' environment (tests/helpers/toy.py), BLAS/OpenMP pinned to one thread."""
    e = toy_env()
    e.setdefault("OMP_NUM_THREADS", "1")
    return e


PIPELINES = {
    # variants: one override that changes a late stage (shared upstream entries, distinct downstream ones)
    "toy": {"base": [f"hydra.searchpath=[file://{TESTS / 'conf'}]", "experiment=toy", "outputs.poses=null",
                     "stages.signal.n_batches=8", "stages.signal.sleep_s=0.5", "stages.smooth.sleep_s=0.3",
                     "stages.scale.sleep_s=0.3"],
            "key": "stages.scale.factor", "values": ["1", "2", "3"], "name": "toy"},
    "tiny": {"base": ["experiment=quick", "source.duration_s=0.09", "template=procedural", "template.target_faces=2000",
                      "source.n_track_points=20", "outputs.video=false"],
             "key": "stages.evaluate.every", "values": ["10", "5"], "name": "quick"},
}


class Job:
    """One `eventcap run` command (a single run or a sweep) and its processes over the rounds."""

    def __init__(self, i: int, args: list[str], kind: str, executor: str, workdir: Path):
        self.i, self.args, self.kind, self.executor, self.workdir = i, args, kind, executor, workdir
        self.proc: subprocess.Popen | None = None
        self.rounds: list[int | None] = []  # exit code per round (negative: killed by that signal)
        self.seen: dict[int, object] = {}  # pid -> psutil.Process of every descendant seen

    def start(self, round_: int) -> None:
        log = open(self.workdir / f"job{self.i}.round{round_}.log", "w")
        self.proc = subprocess.Popen([sys.executable, "-m", "eventcap.apps.cli", "run", *self.args], cwd=self.workdir,
                                     env=env(), stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        log.close()

    def descendants(self) -> list:
        import psutil

        try:
            kids = psutil.Process(self.proc.pid).children(recursive=True)
        except psutil.NoSuchProcess:
            return []
        for k in kids:
            self.seen.setdefault(k.pid, k)
        return kids


def alive(procs) -> list:
    import psutil

    out = []
    for p in procs:
        try:
            if p.is_running() and p.status() != psutil.STATUS_ZOMBIE:
                out.append(p)
        except psutil.NoSuchProcess:
            pass
    return out


def make_jobs(args, workdir: Path) -> tuple[list[Job], list[tuple[str, str]]]:
    spec = PIPELINES[args.pipeline]
    cache = ["cache_dir=" + str(workdir / "cache"), "log_level=INFO"]
    jobs, configs = [], set()
    executors = ("serial", "processes", "dask")
    for i in range(args.runs):
        value = spec["values"][i % len(spec["values"])]
        ex = executors[i % len(executors)]
        jobs.append(Job(i, [*spec["base"], *cache, f"{spec['key']}={value}", f"executor={ex}",
                            f"name=run{value}"], "run", ex, workdir))
        configs.add(value)
    vals = spec["values"]
    for s in range(args.sweeps):
        pick = [vals[(s + k) % len(vals)] for k in range(2)]  # overlapping pairs: 1,2 / 2,3 / 3,1 ...
        ex = ("processes", "serial")[s % 2]
        jobs.append(Job(args.runs + s, ["-m", *spec["base"], *cache, f"{spec['key']}={','.join(pick)}",
                                        f"executor={ex}", f"name=sweep{s}"], "sweep", ex, workdir))
        configs.update(pick)
    return jobs, sorted((spec["key"], v) for v in configs)


def reference(args, tmp: Path, configs) -> dict[str, dict]:
    """Metrics (and motion.npz) of each configuration, run serially in a cache of its own."""
    import numpy as np

    spec = PIPELINES[args.pipeline]
    ref = tmp / "reference"
    ref.mkdir()
    out = {}
    t0 = time.perf_counter()
    for key, value in configs:
        p = subprocess.run([sys.executable, "-m", "eventcap.apps.cli", "run", *spec["base"], f"{key}={value}",
                            f"cache_dir={ref / 'cache'}", f"hydra.run.dir=runs/{value}", "log_level=WARNING"],
                           cwd=ref, env=env(), capture_output=True, text=True)
        if p.returncode != 0:
            raise RuntimeError(f"reference run {key}={value} failed: {p.stderr[-3000:]}")
        d = ref / "runs" / value
        out[value] = {"metrics": json.loads((d / "metrics.json").read_text())}
        if (d / "motion.npz").exists():
            with np.load(d / "motion.npz") as z:
                out[value]["motion"] = {k: z[k] for k in z.files}
    print(f"reference: {len(configs)} configurations run serially in {time.perf_counter() - t0:.1f} s, "
          f"{len(committed(ref / 'cache'))} entries")
    return out, committed(ref / "cache")


def stress(args, jobs: list[Job], rng: random.Random) -> dict:
    """Start every job at once; kill drivers and workers at random; return the kill records."""
    import psutil

    for j in jobs:
        j.start(0)
    t0 = time.monotonic()
    kill_at = sorted(rng.uniform(args.kill_from, args.kill_until) for _ in range(args.kills))
    wkill_at = sorted(rng.uniform(args.kill_from, args.kill_until) for _ in range(args.worker_kills))
    driver_kills, worker_kills, orphans = [], [], []
    while any(j.proc.poll() is None for j in jobs):
        now = time.monotonic() - t0
        for j in jobs:
            if j.proc.poll() is None:
                j.descendants()
        if kill_at and now >= kill_at[0]:
            kill_at.pop(0)
            live = [j for j in jobs if j.proc.poll() is None]
            if live:
                j = rng.choice(live)
                kids = j.descendants()
                os.kill(j.proc.pid, signal.SIGKILL)
                driver_kills.append({"job": j.i, "executor": j.executor, "at_s": round(now, 2),
                                     "children": kids})
        if wkill_at and now >= wkill_at[0]:
            cands = [(j, k) for j in jobs if j.proc.poll() is None for k in j.descendants()
                     if "spawn_main" in " ".join(_cmdline(k))]
            if cands:
                wkill_at.pop(0)
                j, k = rng.choice(cands)
                try:
                    k.kill()
                    worker_kills.append({"job": j.i, "executor": j.executor, "at_s": round(now, 2), "pid": k.pid})
                except psutil.NoSuchProcess:
                    pass
            elif now > args.kill_until + 30:
                wkill_at.clear()  # no worker left to kill
        time.sleep(0.05)
    for j in jobs:
        j.rounds.append(j.proc.returncode)
    for k in driver_kills:
        k["mid_run"] = jobs[k["job"]].rounds[0] == -signal.SIGKILL  # the killed drivers' processes must be gone 10 s after the kill
        deadline = time.monotonic() + 10
        while alive(k["children"]) and time.monotonic() < deadline:
            time.sleep(0.1)
        left = alive(k["children"])
        orphans += left
        k["left"] = len(left)
        k["children"] = len(k["children"])
    for p in orphans:  # counted; removed so that they cannot touch the resumed runs
        try:
            p.kill()
        except psutil.NoSuchProcess:
            pass
    return {"driver_kills": driver_kills, "worker_kills": worker_kills, "orphans": len(orphans),
            "elapsed_s": time.monotonic() - t0}


def _cmdline(p) -> list[str]:
    try:
        return p.cmdline()
    except Exception:  # noqa: BLE001 - gone or a zombie
        return []


def resume(jobs: list[Job]) -> int:
    rounds = 0
    for r in range(1, 4):
        todo = [j for j in jobs if j.rounds[-1] != 0]
        if not todo:
            break
        rounds = r
        for j in todo:
            j.start(r)
        for j in todo:
            j.proc.wait()
            j.rounds.append(j.proc.returncode)
    return rounds


def check_folders(workdir: Path) -> dict:
    folders = [p.parent for p in (workdir / "runs").rglob(".hydra") if p.is_dir()]
    jobs = [f for f in folders if (f / ".hydra" / "overrides.yaml").exists()]
    mixed = []
    for f in jobs:
        ours, theirs = f / "config.yaml", f / ".hydra" / "config.yaml"
        log = f / "eventcap.log"
        n_runs = log.read_text().count("run folder: ") if log.exists() else 0
        same = True
        if ours.exists() and theirs.exists():
            import yaml

            a, b = yaml.safe_load(ours.read_text()), yaml.safe_load(theirs.read_text())
            same = a.get("stages") == b.get("stages") and a.get("name") == b.get("name")
        if n_runs > 1 or not same:
            mixed.append(str(f))
    return {"folders": len(jobs), "mixed": mixed, "with_run_json": sum((f / "run.json").exists() for f in jobs)}


def compare(workdir: Path, ref: dict, key: str) -> dict:
    """Every finished run's results against the serial reference of its configuration."""
    import numpy as np
    import yaml

    n = same = 0
    bad = []
    for rj in (workdir / "runs").rglob("run.json"):
        d = rj.parent
        if not json.loads(rj.read_text()).get("ok"):
            continue
        cfg = yaml.safe_load((d / "config.yaml").read_text())
        node, _, field = key.removeprefix("stages.").partition(".")
        value = str(cfg["stages"][node][field])
        value = value.removesuffix(".0") if value.endswith(".0") else value
        r = ref[value]
        n += 1
        ok = json.loads((d / "metrics.json").read_text()) == r["metrics"]
        if "motion" in r:
            with np.load(d / "motion.npz") as z:
                ok = ok and set(z.files) == set(r["motion"]) and all(np.array_equal(z[k], r["motion"][k])
                                                                    for k in z.files)
        same += ok
        if not ok:
            bad.append(str(d))
    return {"finished_runs": n, "equal_to_serial": same, "different": bad}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pipeline", default="toy", choices=sorted(PIPELINES))
    ap.add_argument("--runs", type=int, default=6, help="single runs started at once")
    ap.add_argument("--sweeps", type=int, default=2, help="sweeps (2 jobs each) started with them")
    ap.add_argument("--kills", type=int, default=3, help="SIGKILLs of random live drivers")
    ap.add_argument("--worker-kills", type=int, default=2, help="SIGKILLs of random pool / Dask workers")
    ap.add_argument("--kill-from", type=float, default=2.0, help="kills happen between these seconds")
    ap.add_argument("--kill-until", type=float, default=12.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--keep", help="work in this folder (kept) instead of a temporary one")
    args = ap.parse_args(argv)
    rng = random.Random(args.seed)
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = (Path(args.keep) if args.keep else Path(tmp_name)).resolve()
        tmp.mkdir(parents=True, exist_ok=True)
        work = tmp / "stress"
        work.mkdir()
        jobs, configs = make_jobs(args, work)
        ref, ref_entries = reference(args, tmp, configs)
        s = stress(args, jobs, rng)
        print(f"stress: {len(jobs)} commands at once ({args.runs} runs, {args.sweeps} sweeps) on one cache, "
              f"{s['elapsed_s']:.1f} s; {len(s['driver_kills'])} drivers and {len(s['worker_kills'])} workers "
              f"killed with SIGKILL")
        for k in s["driver_kills"]:
            print(f"  driver of job {k['job']} [{k['executor']}] killed at {k['at_s']} s"
                  f"{'' if k['mid_run'] else ' (it had just finished)'}: {k['left']} of its "
                  f"{k['children']} processes left 10 s later")
        for k in s["worker_kills"]:
            print(f"  a worker of job {k['job']} [{k['executor']}] killed at {k['at_s']} s")
        first = {j.i: j.rounds[0] for j in jobs}
        rounds = resume(jobs)
        ok_final = sum(j.rounds[-1] == 0 for j in jobs)
        print(f"exits of the first round: {sorted(first.values(), key=str)}; resumed in {rounds} round(s); "
              f"{ok_final}/{len(jobs)} commands finished with exit 0")
        logs = "".join(p.read_text(errors="replace") for p in work.glob("job*.log"))
        twice = len(re.findall(r"was computed twice", logs))
        waited = len(re.findall(r"committed by another run meanwhile", logs))
        logged = len(re.findall(r"\): computed in \d|: batch \d+/\d+ computed in \d", logs))
        entries = committed(work / "cache")
        same_entries = {k: v for k, v in entries.items() if k in ref_entries}
        entries_equal = all(ref_entries[k] == v for k, v in same_entries.items())
        folders = check_folders(work)
        cmp = compare(work, ref, PIPELINES[args.pipeline]["key"])
        processes = sum(len(j.rounds) for j in jobs)
        leftovers = list((work / "cache" / "tmp").iterdir()) + list((work / "cache" / "locks").glob("*"))
        print(f"processes started: {processes} ({len(jobs)} commands x rounds); run folders: {folders['folders']} "
              f"({folders['with_run_json']} with run.json), mixed folders: {len(folders['mixed'])}")
        print(f"cache: {len(entries)} entries (reference: {len(ref_entries)}; the same keys: "
              f"{len(same_entries) == len(ref_entries) == len(entries)}, files identical: {entries_equal}); "
              f"computations logged by the drivers: {logged}; entries computed twice: {twice}; loads of an entry "
              f"another run computed meanwhile: {waited}; "
              f"tmp/lock leftovers: {len(leftovers)}")
        print(f"orphaned processes 10 s after a driver kill: {s['orphans']}")
        print(f"results: {cmp['equal_to_serial']} of {cmp['finished_runs']} finished runs equal to the serial run "
              f"(metrics{' and motion.npz' if args.pipeline == 'tiny' else ''})")
        good = (ok_final == len(jobs) and not folders["mixed"] and twice == 0 and s["orphans"] == 0
                and entries_equal and len(entries) == len(ref_entries) and not cmp["different"]
                and cmp["finished_runs"] > 0)
        print("OK" if good else "FAIL")
        for d in folders["mixed"] + cmp["different"]:
            print("  problem:", d)
        return 0 if good else 1


if __name__ == "__main__":
    sys.exit(main())
