"""Scaling of the per-batch work over executors: wall time of the track node of an N-batch run for serial, a process
pool and Dask (LocalCluster) with 1 and 2 workers, the speed-up, and the per-batch overhead of each path
(wall time minus the stage's own compute time recorded in the cache manifests, per batch).

    python benchmarks/bench_executors.py [--duration 1.0]

Runs `eventcap run` in a scratch folder: the recording and sharpening are computed once and cached; each measured run
changes a track parameter that does not matter here (stitch_px by 1e-6) so that every batch is recomputed.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path


def run(cwd: Path, overrides: list[str], tag: str) -> dict:
    cmd = [sys.executable, "-m", "eventcap.cli", "run", f"hydra.run.dir=runs/{tag}", "log_level=WARNING", *overrides]
    subprocess.run(cmd, cwd=cwd, check=True, capture_output=True, text=True)
    return json.loads((cwd / "runs" / tag / "run.json").read_text())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration", type=float, default=1.0)
    args = ap.parse_args()
    base = [f"source.duration_s={args.duration}", "source.motion=jumping_jack", "source.supersample=1"]
    with tempfile.TemporaryDirectory() as tmp:
        cwd = Path(tmp)
        run(cwd, base, "warmup")  # recording, sharpening, and numba's compile caches
        setups = [("serial", ["executor=serial"]), ("processes x1", ["executor=processes", "executor.workers=1"]),
                  ("processes x2", ["executor=processes", "executor.workers=2"]),
                  ("dask x1", ["executor=dask", "executor.workers=1"]), ("dask x2", ["executor=dask", "executor.workers=2"])]
        print(f"{'executor':<14} {'batches':>7} {'wall s':>7} {'compute s':>9} {'overhead ms/batch':>17} {'speed-up':>8}")
        serial_wall = None
        for i, (name, ov) in enumerate(setups):
            summary = run(cwd, base + ov + [f"stages.track.stitch_px={4.0 + 1e-6 * (i + 1)}"], f"m{i}")
            node = summary["nodes"]["track"]
            compute = 0.0
            for key in node["computed_keys"]:
                m = json.loads((cwd / "runs" / "cache" / "entries" / "eklt" / key / "manifest.json").read_text())
                compute += m["elapsed_s"]
            n = node["computed"]
            workers = 2 if name.endswith("x2") else 1
            wall = node["elapsed_s"]
            serial_wall = serial_wall or wall
            overhead = (wall - compute / workers) / n * 1000
            print(f"{name:<14} {n:7d} {wall:7.2f} {compute:9.2f} {overhead:17.1f} {serial_wall / wall:8.2f}", flush=True)


if __name__ == "__main__":
    main()
