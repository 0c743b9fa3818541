"""Scaling of the per-batch work over executors: serial, a process pool and Dask (LocalCluster) with N workers.

    python benchmarks/speed/bench_executors.py [--duration 1.0]                      # the track node (--scope track)
    python benchmarks/speed/bench_executors.py --scope pipeline --duration 3 \\
        [--setups serial dask:1 dask:2 dask:4] [--detector blazepose] \
        [--recording-cache runs/bench_duration/base-...]                      # the whole default pipeline

``--scope track`` (the default): wall time of the track node of an N-batch run, the speed-up, and the per-batch
overhead of each path (wall time minus the stage's own compute time recorded in the cache manifests, per batch).
The recording and sharpening are computed once and cached; each measured run changes a track parameter that does not
matter here (stitch_px by 1e-6) so that every batch is recomputed. Capture: jumping_jack, supersample 1.

``--scope pipeline``: the whole default pipeline (the default capture, karate_kick at 25 fps) from a cache holding
only the recording to the outputs without video, once per setup, each from a fresh copy of that cache. The
recording is simulated once, and a 2-batch warm-up run fills numba's compile caches. Per setup: the whole process's
wall time and speed-up over serial, the CPU seconds of every process (``os.wait4`` on the driver: the Dask workers
and nannies are its descendants and are waited for when the cluster closes), the wall time of each node (run.json),
and for the solve node (per-batch spline windows, most of the time) the sum of its batches' own compute time
(cache manifests) and the parallel efficiency ``compute / (workers x wall)``; and whether the setup's motion
(``motion.npz``) equals the first setup's array by array, exactly (``np.array_equal``, NaNs equal).

Setups are ``serial``, ``processes:N`` or ``dask:N`` (N workers, one thread each). The machine may be shared with
other work: the load average after each run is printed. Nothing is asserted.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

EVENTCAP = [sys.executable, "-m", "eventcap.apps.cli", "run"]


def run(cwd: Path, overrides: list[str], tag: str, env: dict | None = None) -> dict:
    cmd = [*EVENTCAP, f"hydra.run.dir=runs/{tag}", "log_level=WARNING", *overrides]
    subprocess.run(cmd, cwd=cwd, check=True, capture_output=True, text=True, env=env)
    return json.loads((cwd / "runs" / tag / "run.json").read_text())


def setup_overrides(setup: str) -> tuple[list[str], int]:
    """The executor overrides of 'serial' | 'processes:N' | 'dask:N', and the number of workers."""
    kind, _, n = setup.partition(":")
    if kind == "serial" and not n:
        return ["executor=serial"], 1
    if kind in ("processes", "dask") and n.isdigit() and int(n) >= 1:
        return [f"executor={kind}", f"executor.workers={n}"], int(n)
    raise SystemExit(f"--setups: expected serial, processes:N or dask:N, got {setup!r}")


def motion_arrays(path: Path) -> dict:
    """Every array of a run's motion.npz, by name."""
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def equal_arrays(a: dict, b: dict) -> bool:
    """The same names and every array equal exactly (NaNs equal where both are NaN)."""
    return a.keys() == b.keys() and all(
        np.array_equal(a[k], b[k], equal_nan=a[k].dtype.kind in "fc") for k in a)


def compute_s(cache: Path, stage: str, keys: list[str]) -> float:
    """Sum of the entries' own compute seconds (the runner's elapsed_s in each manifest)."""
    return sum(json.loads((cache / "entries" / stage / k / "manifest.json").read_text())["elapsed_s"] for k in keys)


def bench_track(args) -> None:
    base = [f"source.duration_s={args.duration}", "source.motion=jumping_jack", "source.supersample=1"]
    setups = args.setups or ["serial", "processes:1", "processes:2", "dask:1", "dask:2"]
    with tempfile.TemporaryDirectory() as tmp:
        cwd = Path(tmp)
        run(cwd, base, "warmup")  # recording, sharpening, and numba's compile caches
        print(f"{'executor':<14} {'batches':>7} {'wall s':>7} {'compute s':>9} {'overhead ms/batch':>17} {'speed-up':>8}")
        serial_wall = None
        for i, setup in enumerate(setups):
            ov, workers = setup_overrides(setup)
            summary = run(cwd, base + ov + [f"stages.track.stitch_px={4.0 + 1e-6 * (i + 1)}"], f"m{i}")
            node = summary["nodes"]["track"]
            compute = compute_s(cwd / "runs" / "cache", "eklt", node["computed_keys"])
            n = node["computed"]
            wall = node["elapsed_s"]
            serial_wall = serial_wall or wall
            overhead = (wall - compute / workers) / n * 1000
            print(f"{setup:<14} {n:7d} {wall:7.2f} {compute:9.2f} {overhead:17.1f} {serial_wall / wall:8.2f}", flush=True)


def measured(cmd: list[str], cwd: Path, env: dict) -> dict:
    """Run cmd; wall seconds, CPU seconds of it and its waited-for descendants, their largest peak RSS (MB)."""
    w0 = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=cwd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    err = proc.stderr.read()
    _, status, ru = os.wait4(proc.pid, 0)
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{err[-3000:]}")
    return {"wall_s": time.perf_counter() - w0, "cpu_s": ru.ru_utime + ru.ru_stime, "peak_mb": ru.ru_maxrss / 1024,
            "load": os.getloadavg()[0]}


PIPELINE_NODES = ("sharpen", "detect", "track", "slice", "solve", "stitch", "cut", "evaluate", "confidence")


def bench_pipeline(args) -> None:
    source = [f"source.duration_s={args.duration}", f"source.motion={args.motion}"]
    common = [*source, f"stages/detect={args.detector}", "outputs.video=false", "log_level=WARNING"]
    setups = args.setups or ["serial", "dask:1", "dask:2", "dask:4"]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        cwd = Path(tmp)
        if args.recording_cache:  # made elsewhere (e.g. by bench_duration.py) for the same capture
            shutil.copytree(args.recording_cache, cwd / "base")
        env = dict(os.environ, EVENTCAP_CACHE_DIR=str(cwd / "base"))
        rec = run(cwd, ["pipeline=simulate", "outputs.poses=null", *source], "simulate", env)
        if args.recording_cache and rec["nodes"]["source"]["computed"]:
            print(f"note: {args.recording_cache} did not hold this capture's recording; simulated it here")
        shutil.copytree(cwd / "base", cwd / "warm")
        run(cwd, [*common, "batches=2"], "warmup", dict(os.environ, EVENTCAP_CACHE_DIR=str(cwd / "warm")))
        shutil.rmtree(cwd / "warm")
        print(f"{args.duration:g} s of {args.motion}, detector {args.detector}; wall and CPU s of the whole process "
              f"(CPU: all processes), per-node wall s (run.json)")
        head = "".join(f"{n[:8]:>9}" for n in PIPELINE_NODES)
        print(f"{'setup':<12} {'wall s':>7} {'speed-up':>8} {'CPU s':>7} {'peak MB':>7} {'load':>5}{head}"
              f" {'solve compute s':>15} {'solve eff.':>10} {'motion':>9}")
        serial_wall, first_motion = None, None
        for i, setup in enumerate(setups):
            ov, workers = setup_overrides(setup)
            cache = cwd / f"cache{i}"
            shutil.copytree(cwd / "base", cache)
            env = dict(os.environ, EVENTCAP_CACHE_DIR=str(cache))
            res = measured([*EVENTCAP, f"hydra.run.dir=runs/m{i}", *common, *ov], cwd, env)
            nodes = json.loads((cwd / "runs" / f"m{i}" / "run.json").read_text())["nodes"]
            solve = nodes["solve"]
            compute = compute_s(cache, solve["stage"], solve["computed_keys"])
            shutil.rmtree(cache)
            serial_wall = serial_wall or res["wall_s"]
            cells = "".join(f"{nodes[n]['elapsed_s']:9.1f}" if n in nodes else f"{'-':>9}" for n in PIPELINE_NODES)
            eff = compute / (workers * solve["elapsed_s"]) if solve["elapsed_s"] else float("nan")
            motion = motion_arrays(cwd / "runs" / f"m{i}" / "motion.npz")
            first_motion = first_motion or motion
            same = equal_arrays(first_motion, motion)
            print(f"{setup:<12} {res['wall_s']:7.1f} {serial_wall / res['wall_s']:8.2f} {res['cpu_s']:7.1f} "
                  f"{res['peak_mb']:7.0f} {res['load']:5.1f}{cells} {compute:15.1f} {eff:10.2f} "
                  f"{'equal' if same else 'DIFFERENT':>9}", flush=True)
            rows.append({"setup": setup, **res, "nodes": {n: v["elapsed_s"] for n, v in nodes.items()},
                         "solve_batches": solve["computed"], "solve_compute_s": compute, "motion_equal": same})
            if args.json:
                Path(args.json).write_text(json.dumps(rows, indent=1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scope", choices=("track", "pipeline"), default="track",
                    help="track: the track node only; pipeline: the whole default pipeline")
    ap.add_argument("--duration", type=float, default=1.0, help="capture length, s")
    ap.add_argument("--setups", nargs="+", help="serial | processes:N | dask:N (default: per scope, see above)")
    ap.add_argument("--motion", default="karate_kick", help="--scope pipeline: the capture's motion")
    ap.add_argument("--detector", default="blazepose", help="--scope pipeline: stages/detect option")
    ap.add_argument("--recording-cache", help="--scope pipeline: a cache folder that already holds the capture's "
                    "recording (copied, not changed), e.g. one of bench_duration.py's")
    ap.add_argument("--json", help="--scope pipeline: also write the figures here")
    args = ap.parse_args()
    (bench_track if args.scope == "track" else bench_pipeline)(args)


if __name__ == "__main__":
    main()
