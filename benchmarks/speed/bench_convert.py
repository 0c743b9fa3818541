"""Benchmark of `eventcap convert`: wall time, events/s and peak memory of converting a large simulated file.

    python benchmarks/speed/bench_convert.py --events 100000000 [--format evt3|npy] [--dir /tmp] [--keep]

Writes a simulated recording (random events on a 1280 × 720 sensor at about 5 M events/s, written chunk by chunk so
the generator's memory stays bounded; not real sensor data), then runs ``eventcap convert`` on it in a child
process and reports the child's wall time, events/s and peak resident memory (``ru_maxrss`` of the child, i.e. its
VmHWM). The files are deleted afterwards unless ``--keep``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from eventcap.events import EVENT_DTYPE  # noqa: E402

WIDTH, HEIGHT = 1280, 720


def simulated_chunks(n_events: int, rate_per_s: float = 5e6, chunk: int = 1 << 21, seed: int = 0):
    """``n_events`` simulated events (uniform pixels and polarities, Poisson-like times at ``rate_per_s``), sorted,
    without exact duplicates, as ``EVENT_DTYPE`` chunks; times in µs from 0."""
    rng = np.random.default_rng(seed)
    written, t0 = 0, 0
    while written < n_events:
        n = min(chunk, n_events - written)
        span_us = max(1, int(n / rate_per_s * 1e6))
        ev = np.empty(n, EVENT_DTYPE)
        ev["t"] = t0 + np.sort(rng.integers(0, span_us, n))
        ev["x"], ev["y"] = rng.integers(0, WIDTH, n), rng.integers(0, HEIGHT, n)
        ev["p"] = rng.choice(np.array([-1, 1], np.int8), n)
        key = (ev["t"] << 22) ^ (ev["x"].astype(np.int64) << 11) ^ (ev["y"].astype(np.int64) << 1) ^ (ev["p"] > 0)
        _, first = np.unique(key, return_index=True)
        if len(first) < n:  # the rare exact duplicate (same µs, pixel and polarity) is dropped, as a sensor would not
            ev = ev[np.sort(first)]
        t0 += span_us  # the next chunk starts after this one: sorted across chunks, no duplicates across them
        written += len(ev)
        yield ev


def write_input(path: Path, n_events: int, fmt: str) -> float:
    from eventcap.io import write_events

    t = time.perf_counter()
    if fmt == "npy":
        # A plain structured array file, filled chunk by chunk through a memory map.
        arr = np.lib.format.open_memmap(path, mode="w+", dtype=EVENT_DTYPE, shape=(n_events,))
        k = 0
        for ev in simulated_chunks(n_events):
            arr[k:k + len(ev)] = ev
            k += len(ev)
        arr.flush()
        del arr
        if k < n_events:
            raise SystemExit(f"generated {k} events, fewer than {n_events}")
    else:
        write_events(path, simulated_chunks(n_events), width=WIDTH, height=HEIGHT, format=fmt)
    return time.perf_counter() - t


def du(path: Path) -> int:
    if path.is_file():
        return path.stat().st_size
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--events", type=float, default=1e7, help="number of events (default 1e7)")
    ap.add_argument("--format", default="evt3", choices=["evt3", "evt2", "dat", "npy"])
    ap.add_argument("--chunk-events", type=int, default=1 << 20)
    ap.add_argument("--dir", default="/tmp", help="where to write the files (needs ~15 bytes per event)")
    ap.add_argument("--keep", action="store_true", help="keep the input and output files")
    args = ap.parse_args()
    n = int(args.events)
    folder = Path(args.dir) / f"bench_convert_{os.getpid()}"
    folder.mkdir(parents=True)
    src = folder / ("in.npy" if args.format == "npy" else f"in.{'dat' if args.format == 'dat' else 'raw'}")
    out = folder / "out.zarr"
    try:
        free = shutil.disk_usage(folder).free
        if free < 16 * n:
            raise SystemExit(f"{folder}: {free / 1e9:.1f} GB free, about {16 * n / 1e9:.1f} GB needed")
        gen_s = write_input(src, n, args.format)
        print(f"input: {n:,} simulated events as {args.format}, {du(src) / 1e6:.0f} MB, written in {gen_s:.1f} s",
              flush=True)
        cmd = [sys.executable, "-m", "eventcap.apps.cli", "convert", str(src), str(out), "--chunk-events",
               str(args.chunk_events)]
        if args.format == "npy":
            cmd += ["--width", str(WIDTH), "--height", str(HEIGHT)]
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
        t = time.perf_counter()
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
        wall = time.perf_counter() - t
        peak_kb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss  # the only child run: the converter
        if proc.returncode != 0:
            print(proc.stdout, proc.stderr, sep="\n")
            raise SystemExit(f"convert failed with exit code {proc.returncode}")
        import zarr

        stored = zarr.open_group(str(out), mode="r")["events/events/t"].shape[0]
        result = {"events": n, "stored": int(stored), "format": args.format, "wall_s": round(wall, 2),
                  "events_per_s": round(n / wall), "peak_rss_mb": round(peak_kb / 1024, 1),
                  "input_mb": round(du(src) / 1e6), "output_mb": round(du(out) / 1e6)}
        print(proc.stdout.strip())
        print(f"convert: {n:,} events in {wall:.1f} s wall ({n / wall / 1e6:.2f} M events/s, including start-up), "
              f"peak RSS {peak_kb / 1024:.0f} MB, output {result['output_mb']} MB")
        print(json.dumps(result))
        if stored != n:
            raise SystemExit(f"stored {stored} events, expected {n}")
    finally:
        if not args.keep:
            shutil.rmtree(folder, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
