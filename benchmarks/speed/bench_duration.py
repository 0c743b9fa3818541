"""Time and peak memory of the default pipeline against the capture's length (issue 37: cost linear in duration,
memory flat, a 60 s capture under 2 GB).

    python benchmarks/speed/bench_duration.py [--durations 5 20 60] [--motion karate_kick] [--detector blazepose]
                                        [--base-dir runs/bench_duration] [--json out.json] [-- run overrides ...]

For each duration, two things are measured, each in a child process of its own:

1. **the source**: ``eventcap run pipeline=simulate`` makes the synthetic recording (template + source) into a cache
   kept under ``--base-dir`` (one per capture, reused by later calls; its figures are kept beside it in
   ``source.json`` and printed again). Simulating is not what a user pays after recording, so it is reported apart.
2. **the pipeline**: the default pipeline from a fresh copy of that cache (only the recording in it) to the outputs
   without video (``outputs.video=false``), serially, with the detector named by ``--detector``. The child runs
   ``eventcap run`` in-process with the stage timers of ``profile_pipeline.py`` (CPU and wall seconds per stage,
   inclusive) and records the process's high-water mark of resident memory after each stage's call.

Whole-process figures come from ``os.wait4`` on the child: wall time, CPU seconds (user + system) and the peak resident
set size (``ru_maxrss``, the child and anything it waited for). "per 40 ms" divides by the capture's length in 40 ms
units. The machine may be shared: CPU seconds are disturbed less by other load than wall seconds; the load average at
the end of each run is printed. Nothing is asserted.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
EVENTCAP = [sys.executable, "-m", "eventcap.apps.cli"]
STAGES = ("template", "source", "sharpen", "detect", "track", "slice", "solve", "stitch", "cut", "evaluate",
          "confidence")


def measured(cmd: list[str], **kw) -> dict:
    """Run cmd; its wall seconds, CPU seconds (user + sys) and peak RSS in MB (itself and what it waited for)."""
    w0 = time.perf_counter()
    proc = subprocess.Popen(cmd, **kw)
    _, status, ru = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    return {"code": proc.returncode, "wall_s": time.perf_counter() - w0, "cpu_s": ru.ru_utime + ru.ru_stime,
            "peak_mb": ru.ru_maxrss / 1024, "load": os.getloadavg()[0]}


# --------------------------------------------------------------------------------------------- child side
def child(args) -> None:
    """profile_pipeline's timed in-process run, plus the memory high-water mark after each stage's call."""
    sys.path.insert(0, str(HERE))
    import profile_pipeline

    import eventcap.core.stage as stage

    load_run = stage.StageSpec.load_run
    peak_mb: dict[str, float] = {}
    rss_mb: dict[str, float] = {}

    def load_run_rss(self):
        fn = load_run(self)

        def run(inputs, config, ctx):
            try:
                return fn(inputs, config, ctx)
            finally:
                peak_mb[ctx.node] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
                rss_mb[ctx.node] = max(rss_mb.get(ctx.node, 0.0), _rss_mb())

        return run

    stage.StageSpec.load_run = load_run_rss
    # profile_pipeline's "cache I/O" is loads and commits together: time them apart too (inside its timer)
    cache_cpu: dict[str, float] = {"cache: load": 0.0, "cache: commit": 0.0}
    from eventcap.core.cache import Cache

    for name in ("load", "commit"):
        def timed(*a, _fn=getattr(Cache, name), _label=f"cache: {name}", **kw):
            c0 = time.process_time()
            try:
                return _fn(*a, **kw)
            finally:
                cache_cpu[_label] += time.process_time() - c0

        setattr(Cache, name, timed)
    vars(args).setdefault("warm_start", False)  # profile_pipeline's own options that this script does not offer
    profile_pipeline.child(args)
    out = Path(args.child)
    res = json.loads(out.read_text())
    res["cpu"].update(cache_cpu)
    res.update(peak_after_mb=peak_mb, rss_after_mb=rss_mb)
    out.write_text(json.dumps(res))


def _rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


# --------------------------------------------------------------------------------------------- parent side
def source_overrides(args, duration: float) -> list[str]:
    return [f"source.motion={args.motion}", f"source.duration_s={duration:g}", f"source.seed={args.seed}",
            *args.source.split()]


def base_cache(args, duration: float) -> tuple[Path, dict | None]:
    """The cache holding only the template and the recording (made and measured once), and its figures."""
    tag = hashlib.sha256(f"{args.motion}|{duration:g}|{args.seed}|{args.source}".encode()).hexdigest()[:10]
    base = Path(args.base_dir).resolve() / f"base-{args.motion}-{duration:g}s-{tag}"  # the child runs elsewhere
    if (base / "entries").is_dir():
        info = base / "source.json"
        return base, json.loads(info.read_text()) if info.is_file() else None
    tmp = base.with_name(base.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    env = dict(os.environ, EVENTCAP_CACHE_DIR=str(tmp))
    with tempfile.TemporaryDirectory() as scratch:
        res = measured([*EVENTCAP, "run", "pipeline=simulate", "outputs.poses=null", "log_level=WARNING",
                        f"hydra.run.dir={scratch}/run", *source_overrides(args, duration)], env=env, cwd=scratch)
    if res["code"] != 0:
        raise SystemExit(f"simulating {duration:g} s failed (exit {res['code']})")
    res["disk_mb"] = sum(f.stat().st_size for f in tmp.rglob("*") if f.is_file()) / 2**20
    (tmp / "source.json").write_text(json.dumps(res))
    tmp.rename(base)
    return base, res


def run_pipeline(args, base: Path, duration: float) -> dict:
    with tempfile.TemporaryDirectory(prefix="bench_duration_") as tmp:
        cache = Path(tmp) / "cache"
        shutil.copytree(base, cache)
        out = Path(tmp) / "timers.json"
        overrides = [f"stages/detect={args.detector}", "outputs.video=false", "log_level=WARNING",
                     f"hydra.run.dir={tmp}/run", *source_overrides(args, duration), *args.overrides]
        env = dict(os.environ, EVENTCAP_CACHE_DIR=str(cache), OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1",
                   MKL_NUM_THREADS="1")
        res = measured([sys.executable, __file__, "--child", str(out), "--", *overrides], env=env, cwd=tmp,
                       stdout=subprocess.DEVNULL)
        timers = json.loads(out.read_text()) if out.is_file() else {}
        if res["code"] != 0 or timers.get("code") != 0:
            raise SystemExit(f"the {duration:g} s run failed (exit {res['code']}); run `eventcap run` with "
                             f"{' '.join(overrides)} to see its log")
        record = json.loads((Path(tmp) / "run" / "run.json").read_text())
    nodes = record["nodes"]
    res.update(batches=len(nodes["solve"]["keys"]), partial=any(o.startswith("batches=") for o in overrides),
               per_batch=[k for k, v in nodes.items() if v["per_batch"]],
               node_wall_s={k: v["elapsed_s"] for k, v in nodes.items()},
               stage_cpu_s={k.removeprefix("stage "): v for k, v in timers["cpu"].items() if k.startswith("stage ")},
               parts_cpu_s={k: v for k, v in timers["cpu"].items() if not k.startswith("stage ")},
               peak_after_mb=timers["peak_after_mb"], rss_after_mb=timers["rss_after_mb"],
               failed={k: len(v["failed"]) for k, v in nodes.items() if v["failed"]},
               computed=[k for k, v in nodes.items() if v["computed"]])
    if "source" in res["computed"]:
        print(f"warning: the {duration:g} s run simulated its recording again (not found in {base}): its figures "
              "include the source", flush=True)
    return res


def report(rows: list[dict]) -> None:
    print("\nsource (simulating the recording; measured once, when its cache was made)")
    print(f"{'duration s':>10} {'wall s':>8} {'CPU s':>8} {'CPU s per s':>11} {'peak RSS MB':>11} {'disk MB':>8} "
          f"{'load':>5}")
    for r in rows:
        s = r["source"]
        if s is None:
            print(f"{r['duration']:10g}   (cache made elsewhere: no figures)")
        else:
            print(f"{r['duration']:10g} {s['wall_s']:8.1f} {s['cpu_s']:8.1f} {s['cpu_s'] / r['duration']:11.1f} "
                  f"{s['peak_mb']:11.0f} {s.get('disk_mb', float('nan')):8.0f} {s.get('load', float('nan')):5.1f}"
                  + (f"  ({s['note']})" if s.get("note") else ""))
    print("\npipeline (from the cached recording to the outputs without video, serial)")
    print(f"{'duration s':>10} {'batches':>7} {'wall s':>8} {'CPU s':>8} {'CPU s/40ms':>10} {'wall s/40ms':>11} "
          f"{'peak RSS MB':>11} {'load':>5} failed")
    for r in rows:
        p, n40 = r["pipeline"], r["duration"] / 0.04
        part = p.get("partial", False)
        cpu40, wall40 = ("(part)", "(part)") if part else (f"{p['cpu_s'] / n40:.3f}", f"{p['wall_s'] / n40:.3f}")
        print(f"{r['duration']:10g} {p['batches']:7d} {p['wall_s']:8.1f} {p['cpu_s']:8.1f} {cpu40:>10} {wall40:>11} "
              f"{p['peak_mb']:11.0f} {p['load']:5.1f} {p['failed'] or ''}")
    if any(r["pipeline"].get("partial") for r in rows):
        print("(part): only some batches ran (batches=...); per-batch stages below are per batch run, whole-recording "
              "stages per 40 ms of the whole capture")
    print("\nper stage: CPU s per 40 ms (wall s per 40 ms from run.json) | peak RSS MB after the stage's calls")
    print(f"{'stage':<22}" + "".join(f"{str(r['duration']) + ' s':>30}" for r in rows))
    for st in STAGES:
        cells = []
        for r in rows:
            p = r["pipeline"]
            n40 = p["batches"] if p.get("partial") and st in p["per_batch"] else r["duration"] / 0.04
            cpu, wall = p["stage_cpu_s"].get(st), p["node_wall_s"].get(st)
            if cpu is None and wall is None:
                cells.append(f"{'-':>30}")
                continue
            cells.append(f"{(cpu or 0) / n40:9.4f} ({(wall or 0) / n40:7.4f}) | {p['peak_after_mb'].get(st, 0):6.0f}")
        print(f"{st:<22}" + "".join(cells))
    for part in ("cache I/O", "cache: load", "cache: commit", "outputs (motion files)"):
        cells = [r["pipeline"]["parts_cpu_s"].get(part) for r in rows]
        print(f"{part:<22}" + "".join(f"{'-':>9}{'':>21}" if v is None else
                                      f"{v / (r['duration'] / 0.04):9.4f}{'':>21}" for v, r in zip(cells, rows)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--durations", type=float, nargs="+", default=[5.0, 20.0, 60.0], help="capture lengths, s")
    ap.add_argument("--motion", default="karate_kick")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--detector", default="blazepose", help="stages/detect option (blazepose | simulated)")
    ap.add_argument("--source", default="", help="more source overrides, e.g. 'source.fps=10'")
    ap.add_argument("--base-dir", default=str(ROOT / "runs" / "bench_duration"),
                    help="where the simulated recordings are kept (one cache per capture, reused)")
    ap.add_argument("--json", help="also write the figures here")
    ap.add_argument("--from-json", nargs="+", metavar="JSON", help="only print the tables of earlier --json files")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("overrides", nargs="*", help="more `eventcap run` overrides (after --)")
    args = ap.parse_args()
    if args.child:
        return child(args)
    if args.from_json:
        rows = [r for f in args.from_json for r in json.loads(Path(f).read_text())]
        return report(sorted(rows, key=lambda r: r["duration"]))
    rows = []
    for d in args.durations:
        base, src = base_cache(args, d)
        print(f"{d:g} s: recording ready ({base}); running the pipeline", flush=True)
        rows.append({"duration": d, "source": src, "pipeline": run_pipeline(args, base, d)})
        if args.json:
            Path(args.json).write_text(json.dumps(rows, indent=1))
    report(rows)


if __name__ == "__main__":
    main()
