"""Peak memory of the default pipeline against the capture's length (issue 55, item 3: memory flat as the capture
grows), optionally against another checkout's code on the same captures, with their motions compared exactly.

    python benchmarks/speed/bench_memory.py [--durations 2 8 | --durations 2 --repeat 1 4] [--batches 0:25]
                                            [--against DIR] [--parallel] [--detector blazepose]
                                            [--base-dir runs/bench_duration] [--json out.json] [-- overrides ...]

Captures: each of ``--durations`` simulated once into a cache under ``--base-dir`` (as ``bench_duration.py`` does,
and shared with it); or, with ``--repeat K ...``, the first duration's recording repeated K times end to end (times
shifted by its length; the motion restarts at each copy), written as a recording in the project's format and read
with ``source=recording``: a long capture without simulating one (simulating costs about a minute per second of
capture on a quiet machine).

Each run is ``eventcap run`` of the default pipeline from a fresh copy of that cache (only the template and, when
simulated, the recording in it) to the outputs without video, serially, in a child process: its peak resident set
size (``ru_maxrss`` from ``os.wait4``), CPU seconds (user + system) and wall seconds are printed per capture, with
the peak's ratio to the shortest capture's. ``--batches 0:25`` solves the same first chunk of every capture (the
whole-recording stages still read all of it): the growth of the peak is then what the length of the capture
costs, at fixed work.

``--against DIR``: the same runs with the code of DIR (an export of another commit, e.g. ``git archive main | tar -x
-C DIR``; run with ``PYTHONPATH=DIR:DIR/plugins`` and this checkout's virtualenv), and each capture's ``motion.npz``
of both compared array by array, exactly (``np.array_equal``, NaNs equal). ``--parallel`` starts all runs at once
(peak memory is per process and not disturbed; CPU and wall seconds are). The machine may be shared: the load
average at the end of each run is printed. Nothing is asserted.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
sys.path.insert(0, str(HERE))
import bench_duration  # noqa: E402  (the simulated captures and the wait4 measurement)


def repeated(base: Path, k: int) -> Path:
    """The recording of the cache ``base`` repeated ``k`` times end to end, as a recording in the project's zarr
    format beside it (made once)."""
    out = base.parent / f"{base.name}-x{k}.zarr"
    if out.is_dir():
        return out
    import zarr

    from eventcap.artifacts import EventStream, FrameStack, GroundTruth, Recording
    from eventcap.core.cache import Cache

    cache = Cache(base, create=False)
    [entry] = [e for e in cache.entries() if "recording" in e.manifest["outputs"]]
    rec = cache.load(entry, "recording", Recording)
    f, g, ev = rec.frames, rec.ground_truth, rec.events.events
    period = int(np.median(np.diff(f.t_us)))
    span = int(f.t_us[-1]) + period  # the next copy's first frame continues the frame clock
    if ev["t"].max() >= span or (g is not None and g.frame_t_us is not None):
        raise SystemExit(f"{base}: cannot repeat this recording (events after its last frame period, or ground "
                         "truth at times of its own)")
    events = np.concatenate([ev] * k)
    events["t"] += np.repeat(np.arange(k, dtype=np.int64) * span, ev.size)
    frames = FrameStack(images=np.concatenate([f.images] * k), t_us=np.concatenate([f.t_us + i * span for i in range(k)]),
                        exposure_us=np.concatenate([f.exposure_us] * k), height=f.height, width=f.width,
                        origin=f.origin)
    if g is not None:
        keep = g.t_us < span  # a row at the end of one copy is the next copy's first
        parts = {}
        for name, spec in GroundTruth.array_fields().items():
            a = getattr(g, name)
            if a is not None and spec.dims[0] == "t":
                parts[name] = np.concatenate([a[keep] + i * span if name == "t_us" else a[keep] for i in range(k)])
            elif a is not None and spec.dims[0] == "n":
                parts[name] = np.concatenate([a] * k)
        g = dataclasses.replace(g, **parts)
    long = dataclasses.replace(rec, events=EventStream(events=events, width=rec.events.width, height=rec.events.height),
                               frames=frames, ground_truth=g, name=f"{rec.name} x{k}")
    tmp = out.with_name(out.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    long.to_zarr(zarr.open_group(str(tmp), mode="w"))
    tmp.rename(out)
    return out


def run_once(args, base: Path, source: list[str], code: Path | None, keep: Path) -> dict:
    """The default pipeline from a copy of ``base`` with this checkout's code (``code`` None) or DIR's; the run
    folder's motion.npz is kept as ``keep``."""
    with tempfile.TemporaryDirectory(prefix="bench_memory_") as tmp:
        cache = Path(tmp) / "cache"
        shutil.copytree(base, cache)
        overrides = [f"stages/detect={args.detector}", "outputs.video=false", "log_level=WARNING",
                     f"hydra.run.dir={tmp}/run", *source, *([f"batches={args.batches}"] if args.batches else []),
                     *args.overrides]
        env = dict(os.environ, EVENTCAP_CACHE_DIR=str(cache), OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1",
                   MKL_NUM_THREADS="1")
        if code is not None:
            env["PYTHONPATH"] = os.pathsep.join([str(code), str(code / "plugins"), env.get("PYTHONPATH", "")])
        res = bench_duration.measured(["nice", "-n", "10", *bench_duration.EVENTCAP, "run", *overrides], env=env,
                                      cwd=tmp, stdout=subprocess.DEVNULL)
        if res["code"] != 0:
            raise SystemExit(f"the run ({code or 'this checkout'}; {' '.join(source)}) failed (exit {res['code']}); "
                             f"run `eventcap run` with {' '.join(overrides)} to see its log")
        keep.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(Path(tmp) / "run" / "motion.npz", keep)
    return res


def same_motion(a: Path, b: Path) -> str:
    """'equal' when every array of the two motion.npz files is equal (NaNs equal), else what differs."""
    with np.load(a) as x, np.load(b) as y:
        if set(x.files) != set(y.files):
            return f"different arrays: {sorted(set(x.files) ^ set(y.files))}"
        diff = [k for k in x.files if x[k].shape != y[k].shape or not np.array_equal(
            x[k], y[k], equal_nan=x[k].dtype.kind in "fc")]
    return f"equal ({len(x.files)} arrays)" if not diff else "differ: " + ", ".join(diff)


def report(rows: list[dict], against: str | None, batches: str | None) -> None:
    print(f"\nthe default pipeline, serial, no video{f', batches={batches}' if batches else ''}")
    print(f"{'code':<8} {'capture s':>9} {'peak RSS MB':>11} {'x shortest':>10} {'CPU s':>8} {'wall s':>8} "
          f"{'load':>5}")
    for who in ("this", "against") if against else ("this",):
        first = rows[0][who]["peak_mb"]
        for r in rows:
            m = r[who]
            print(f"{who:<8} {r['seconds']:9g} {m['peak_mb']:11.0f} {m['peak_mb'] / first:10.2f} {m['cpu_s']:8.1f} "
                  f"{m['wall_s']:8.1f} {m['load']:5.1f}")
    if against:
        print(f"\nmotion.npz, this checkout against {against}:")
        for r in rows:
            print(f"  {r['seconds']:g} s: {r['motion']}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--durations", type=float, nargs="+", default=[2.0, 8.0], help="capture lengths, s")
    ap.add_argument("--repeat", type=int, nargs="+", help="captures of the first duration's recording repeated K "
                                                          "times instead of simulated ones")
    ap.add_argument("--batches", help="batches= of every run (e.g. 0:25, the first chunk)")
    ap.add_argument("--against", type=Path, help="a checkout (export) of other code to run on the same captures")
    ap.add_argument("--parallel", action="store_true", help="start every run at once")
    ap.add_argument("--motion", default="karate_kick")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--detector", default="blazepose", help="stages/detect option (blazepose | simulated)")
    ap.add_argument("--source", default="", help="more source overrides, e.g. 'source.fps=10'")
    ap.add_argument("--base-dir", default=str(ROOT / "runs" / "bench_duration"),
                    help="where the simulated recordings are kept (one cache per capture, reused)")
    ap.add_argument("--out", default=str(ROOT / "runs" / "bench_memory"), help="where the motions are kept")
    ap.add_argument("--json", help="also write the figures here")
    ap.add_argument("overrides", nargs="*", help="more `eventcap run` overrides (after --)")
    args = ap.parse_args()
    captures = []  # (seconds, base cache, source overrides)
    if args.repeat:
        base, _ = bench_duration.base_cache(args, args.durations[0])
        for k in args.repeat:
            captures.append((k * args.durations[0], base, ["source=recording", f"source.path={repeated(base, k)}"]))
    else:
        for d in args.durations:
            captures.append((d, bench_duration.base_cache(args, d)[0], bench_duration.source_overrides(args, d)))
    jobs = [(i, who, code) for i in range(len(captures))
            for who, code in (("this", None), ("against", args.against)) if who == "this" or code is not None]
    out = Path(args.out)

    def job(j):
        i, who, code = j
        seconds, base, source = captures[i]
        print(f"{seconds:g} s, {code or 'this checkout'}: running the pipeline", flush=True)
        return j, run_once(args, base, source, code, out / f"{seconds:g}s-{who}.npz")

    with ThreadPoolExecutor(max_workers=len(jobs) if args.parallel else 1) as pool:
        results = list(pool.map(job, jobs))
    rows = [{"seconds": s} for s, _, _ in captures]
    for (i, who, _), res in results:
        rows[i][who] = res
    if args.against:
        for r in rows:
            r["motion"] = same_motion(out / f"{r['seconds']:g}s-this.npz", out / f"{r['seconds']:g}s-against.npz")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    report(rows, str(args.against) if args.against else None, args.batches)


if __name__ == "__main__":
    main()
