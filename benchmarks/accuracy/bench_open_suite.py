"""The open benchmark's captures and what simulating them costs (``eventcap benchmark benchmark=open``).

Part ``draws``: the captures a preset draws (seed, group, and every drawn value), as a Markdown table.

Part ``cost``: CPU seconds of the synthetic source per second of capture, for the first capture of each camera
among the drawn ones, simulated for ``--duration`` s with exactly the suite's overrides (its ``camera_overrides``
included) and, with ``--compare``, without the camera's cost options (the full sensor, 3x3 samples per pixel). The
source runs in this process (the ANNY actor), so its CPU time is this process's: on a shared machine a fairer figure
than wall time, and still indicative only.

    python benchmarks/accuracy/bench_open_suite.py --part draws [--preset open_check]
    python benchmarks/accuracy/bench_open_suite.py --part cost [--duration 0.2] [--compare]
    python benchmarks/accuracy/bench_open_suite.py --part markdown --results runs/benchmark/open_check/benchmark.json

Part ``markdown``: a finished suite's ``benchmark.json`` as the Markdown of docs/open-benchmark.md: Table 1 per
group, the captures where the first row (default) is not lower than ``--against`` rows, and every failed run.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

from eventcap.apps.benchmark import Benchmark, compose_benchmark, compose_run
from eventcap.core.stage import StageContext

CONF = Path(__file__).resolve().parents[2] / "conf"


def suite(preset: str, extra: list[str]) -> Benchmark:
    return Benchmark(compose_benchmark(CONF, preset, extra), CONF, [])


def part_draws(args) -> None:
    bench = suite(args.preset, [])
    keys = ["group", "motion", "motion_start_s", "camera", "distance_m", "height_m", "tilt_deg", "illuminance_lux",
            "contrast_threshold", "background", "background_seed", "source_seed"]
    print(f"## Captures of benchmark={args.preset} (purpose {bench.purpose})\n")
    print("| seed | " + " | ".join(keys) + " |")
    print("|---" * (len(keys) + 1) + "|")
    for c in bench.captures:
        print(f"| {c.seed} | " + " | ".join(str(c.drawn[k]) for k in keys) + " |")


def source_config(overrides: list[str]):
    """The synthetic source's typed config as a run with these overrides composes it."""
    from eventcap_synthetic.spec import SyntheticConfig

    data, _ = compose_run(CONF, overrides)
    src = {k: v for k, v in data["source"].items() if k != "stage"}
    return SyntheticConfig(**src)


def simulate(tpl, cfg) -> tuple[float, float, int]:
    """(CPU s, wall s, events) of the synthetic source with this config, in this process."""
    from eventcap_synthetic._impl import run_synthetic

    log = logging.getLogger("bench_open_suite.source")
    log.propagate = False
    t0, c0 = time.perf_counter(), time.process_time()
    rec = run_synthetic({"template": tpl}, cfg, StageContext(node="source", stage="synthetic", log=log))["recording"]
    return time.process_time() - c0, time.perf_counter() - t0, int(rec.events.events.size)


def part_cost(args) -> None:
    from eventcap.body.anny import anny_template

    bench = suite(args.preset, [f"duration_s={args.duration}"])
    per_camera = bench.cfg.get("camera_overrides") or {}
    tpl = anny_template()
    first = {}
    for c in bench.captures:
        first.setdefault(c.drawn["camera"], c)
    simulate(tpl, source_config(["source.duration_s=0.02", "source.n_track_points=10"]))  # numba compiles: untimed
    print(f"## Simulation cost, benchmark={args.preset}: the first capture of each camera, {args.duration} s "
          "(CPU s of this process; a shared 2-core machine: indicative)\n")
    print("| capture | camera | cost options | events | wall s | CPU s | CPU s per s of capture |")
    print("|---|---|---|---|---|---|---|")
    for camera, c in sorted(first.items()):
        own = [str(o) for o in per_camera.get(camera) or ()]
        variants = [own] + ([[]] if args.compare and own else [])
        for opts in variants:
            seq = [o for o in c.overrides if o not in own and not o.startswith("stages/")]
            cfg = source_config([*seq, *opts])
            cpu, wall, n = simulate(tpl, cfg)
            print(f"| {c.label} ({c.group}) | {camera} | {' '.join(opts) or 'none (full sensor, 3x3 samples)'} | "
                  f"{n} | {wall:.1f} | {cpu:.1f} | {cpu / args.duration:.0f} |", flush=True)


def _f(x, digits=1, pct=False):
    if x is None:
        return "-"
    return f"{100 * x:.0f}%" if pct else f"{x:.{digits}f}"


def part_markdown(args) -> None:
    from eventcap.apps.benchmark import failed_runs, group_tables

    res = json.loads(Path(args.results).read_text())
    # recomputed from the runs' records, so a suite finished by an older version reads the same
    res["groups"] = group_tables(res["runs"], res["methods"], {n: g["label"] for n, g in res["groups"].items()})
    res["failures"] = failed_runs(res["runs"])
    print(f"Purpose: {res.get('note')}\n")
    for name, g in res["groups"].items():
        print(f"#### {g['label']} ({name}, {g['captures']} captures)\n")
        print("| row | AE (mm) | AE.rootrel (mm) | MPJVE (mm/s) | peak-speed error | evaluated / runs |")
        print("|---|---|---|---|---|---|")
        for r in g["table"]:
            ae = "-" if r["AE_mm"] is None else f"{r['AE_mm']:.1f} ± {r['AE_STD_mm']:.1f}"
            print(f"| {r['method']} | {ae} | {_f(r.get('AE_rootrel_mm'))} | {_f(r.get('MPJVE_mm_s'), 0)} | "
                  f"{_f(r.get('peak_speed_err'), pct=True)} | {r['evaluated']} / {r['runs']} |")
        print()
    ref = res["methods"][0]
    labels = {"AE_mm": "AE", "AE_rootrel_mm": "AE.rootrel", "MPJVE_mm_s": "MPJVE", "peak_speed_err": "peak"}
    desc = {c["seed"]: c for c in res["captures"]}
    print(f"#### Captures where {ref} is not lower than {', '.join(args.against)}\n")
    print(f"| capture | group | what was drawn | against | measure | {ref} | other |")
    print("|---|---|---|---|---|---|---|")
    for name, g in res["groups"].items():
        for other in args.against:
            for key, res_k in g["per_capture"]["against"].get(other, {}).items():
                for c in res_k["not_lower"]:
                    fmt = (lambda v: _f(v, pct=True)) if key == "peak_speed_err" else (
                        (lambda v: _f(v, 0)) if key == "MPJVE_mm_s" else _f)
                    print(f"| s{c['seed']} | {name} | {desc[c['seed']]['description']} | {other} | {labels[key]} | "
                          f"{fmt(c[ref])} | {fmt(c[other])} |")
            for c in (g["per_capture"].get("unmeasured") or {}).get(other, []):
                print(f"| s{c['seed']} | {name} | {desc[c['seed']]['description']} | {other} | AE | no result | "
                      f"{_f(c[other])} |")
    print("\n#### Runs that failed, were refused or are incomplete\n")
    print("| capture | group | row | state | reason |")
    print("|---|---|---|---|---|")
    for f in res["failures"]:
        state = f["state"] + (", evaluated" if f["evaluated"] else "")
        print(f"| {f['capture']} | {f['group']} | {f['method']} | {state} | {f['reason']} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--part", default="draws", choices=("draws", "cost", "markdown"))
    ap.add_argument("--preset", default="open", help="open (the tuning seeds) | open_check (the check seeds)")
    ap.add_argument("--duration", type=float, default=0.2, help="cost: seconds simulated per capture")
    ap.add_argument("--compare", action="store_true", help="cost: also without the camera's cost options")
    ap.add_argument("--results", default="runs/benchmark/open_check/benchmark.json", help="markdown: benchmark.json")
    ap.add_argument("--against", nargs="+", default=["frames_smooth", "linear"], help="markdown: rows to list losses to")
    args = ap.parse_args()
    {"draws": part_draws, "cost": part_cost, "markdown": part_markdown}[args.part](args)


if __name__ == "__main__":
    main()
