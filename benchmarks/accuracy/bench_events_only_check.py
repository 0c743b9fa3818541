"""Event-only against with-frames on captures nobody tuned on (issue 53, item 4): AE and MPJVE ratios.

    python benchmarks/accuracy/bench_events_only_check.py [--seeds 101,105,109,113,117] [--suite karate_kick]
        [--out runs/bench_events_only_check] [--detector blazepose]

Each capture runs twice through ``eventcap run`` (one shared cache): as the camera it is (``source.frames=false``,
the README's event-only path, ``pipeline=events_only``) and with its intensity frames (``source.frames=true``: the
same simulated events, the default pipeline). The open suite's event-only CHECK seeds (101, 105, ... drawn by
eventcap/apps/open_suite.py, as ``benchmark=open_check`` draws them: report only, never tune on them) and a 25 fps
suite capture (``--suite MOTION``: the davis240c at 25 fps, seed 2, 1 s). Prints, per capture, AE (the evaluate
stage's Procrustes-aligned error, mm), MPJVE (mm/s), the share of joint-frames observed, and the event-only / with-
frames ratios; a run that is refused is reported with its reason. Writes ``<out>/table.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[2]


def capture_overrides(seed: int, detector: str) -> list[str]:
    """The overrides that make check seed ``seed``'s capture and what its user is told (benchmark=open_check)."""
    from eventcap.apps.benchmark import Benchmark, compose_benchmark

    conf = ROOT / "conf"
    cfg = compose_benchmark(conf, "open_check", [f"seeds=[{seed}]", f"detector={detector}"])
    bench = Benchmark(cfg, conf, [])
    cap = bench.captures[0]
    return [*cap.overrides, *cap.body.get("told", ())]


def run(overrides: list[str], run_dir: Path) -> dict:
    from eventcap.apps.benchmark import compose_run
    from eventcap.apps.jobs import run_job

    failures: list[str] = []
    data, yaml_text = compose_run(ROOT / "conf", overrides)
    run_dir.mkdir(parents=True, exist_ok=True)
    got = run_job(data, run_dir, yaml_text, failures)
    if got is None or not got[1].ok:
        return {"ok": False, "reason": "; ".join(failures)[:400] or "refused"}
    m = got[1].metrics.get("evaluate.metrics") or {}
    out = {"ok": True, "AE_mm": m.get("AE_mm"), "MPJVE_mm_s": m.get("MPJVE_mm_s")}
    conf = got[1].metrics.get("confidence.confidence") or {}
    out["observed"] = conf.get("observed_share")
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", default="101,105,109,113,117")
    p.add_argument("--suite", default="karate_kick", help="a 25 fps suite capture's motion ('' = none)")
    p.add_argument("--out", default="runs/bench_events_only_check")
    p.add_argument("--detector", default="blazepose")
    p.add_argument("--cache", default=os.environ.get("EVENTCAP_CACHE_DIR", "runs/cache"))
    a = p.parse_args(argv)
    out = Path(a.out)
    common = [f"cache_dir={a.cache}", "outputs.video=false", "log_level=WARNING"]
    captures = [(f"check{s}", capture_overrides(int(s), a.detector)) for s in a.seeds.split(",") if s]
    if a.suite:
        captures.append((f"suite_{a.suite}_25fps", ["source=synthetic", f"source.motion={a.suite}", "source.seed=2",
                                                   "source.duration_s=1.0", "source.fps=25",
                                                   f"stages/detect={a.detector}"]))
    rows = []
    for name, ov in captures:
        ev = run([*ov, *common, "source.frames=false", "pipeline=events_only", "stages.detect.at=frames"],
                 out / name / "events_only")
        fr = run([*ov, *common, "source.frames=true"], out / name / "with_frames")
        row = {"capture": name, "events_only": ev, "with_frames": fr}
        if ev["ok"] and fr["ok"] and fr["AE_mm"] and fr["MPJVE_mm_s"]:
            row["AE_ratio"] = ev["AE_mm"] / fr["AE_mm"]
            row["MPJVE_ratio"] = ev["MPJVE_mm_s"] / fr["MPJVE_mm_s"]
        rows.append(row)
        print(json.dumps(row), flush=True)
    out.mkdir(parents=True, exist_ok=True)
    (out / "table.json").write_text(json.dumps(rows, indent=1))
    print("| capture | event-only AE / MPJVE | with frames AE / MPJVE | AE ratio | MPJVE ratio |")
    print("|---|---|---|---|---|")
    for r in rows:
        def cell(x):
            return f"{x['AE_mm']:.1f} / {x['MPJVE_mm_s']:.0f}" if x["ok"] else f"refused: {x['reason'][:80]}"
        ratio = (f"{r['AE_ratio']:.2f} | {r['MPJVE_ratio']:.2f}" if "AE_ratio" in r else "- | -")
        print(f"| {r['capture']} | {cell(r['events_only'])} | {cell(r['with_frames'])} | {ratio} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
