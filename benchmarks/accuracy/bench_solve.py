"""Batch pose optimisation (issue 5) against ground truth: `batch` vs the `linear` and `per_frame` baselines.

    python benchmarks/accuracy/bench_solve.py [--motions a,b] [--duration 0.5] [--seed 0] [--cache runs/bench-cache]

For every motion, the default pipeline up to the solve (synthetic capture -> EDI -> EKLT -> slicing -> simulated
detector -> solve; `pipeline=no_refine`, as only the solve's poses are measured) runs once per solve mode through
the normal runner, so the upstream stages are computed once and cached (rerunning the script recomputes nothing). The error is the paper's AE: mean per-joint position error after rigid
Procrustes alignment per frame, in mm, over every tracking frame (1 kHz) of every batch. Also printed: solve
wall time per batch (median, from the stage's own timing: correspondence search + IPOPT, build excluded), IPOPT
iterations per batch, and the NLP build time once per process.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "plugins"))

import numpy as np  # noqa: E402
from hydra import compose, initialize_config_dir  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402

import zarr  # noqa: E402
from eventcap.artifacts.pose import PoseSequence  # noqa: E402
from eventcap.artifacts.recording import Recording  # noqa: E402
from eventcap.core.cache import Cache  # noqa: E402
from eventcap.body.kinematics import joint_positions  # noqa: E402
from eventcap.analysis.metrics import mean_joint_error, pose_at  # noqa: E402
from eventcap.core.runner import Runner  # noqa: E402

MODES = ("linear", "per_frame", "batch")


def run(overrides: list[str], run_dir: Path) -> Path:
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose(config_name="config", overrides=overrides)
    result = Runner(OmegaConf.to_container(cfg, resolve=True)).run(run_dir)
    if not result.ok:
        failed = {n: r.failed for n, r in result.nodes.items() if r.failed}
        print(f"  run incomplete ({' '.join(overrides)}): {failed}", file=sys.stderr)
    return run_dir


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--motions", default="karate_kick,boxing_combo,javelin_throw,dance_spin,fast_wave,jumping_jack")
    ap.add_argument("--duration", type=float, default=0.5, help="seconds of capture per motion")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--modes", default=",".join(MODES))
    ap.add_argument("--cache", default=str(ROOT / "runs" / "bench-cache"))
    ap.add_argument("--out", default=str(ROOT / "runs" / "bench_solve"))
    ap.add_argument("--extra", default="", help="more hydra overrides, space separated")
    args = ap.parse_args()
    modes = args.modes.split(",")
    out = Path(args.out)
    rows, builds = [], []
    cache = Cache(args.cache)
    print(f"{'motion':<14} {'mode':<10} {'AE mm':>7} {'AE std':>7} {'batches':>7} {'s/batch':>8} {'iters':>6} "
          f"{'fit it':>6} {'ICP it':>6} {'ICP s':>6}")
    for motion in args.motions.split(","):
        for mode in modes:
            rd = out / f"{motion}-s{args.seed}-{mode}"
            t0 = time.perf_counter()
            ov = [f"source.motion={motion}", f"source.duration_s={args.duration}", f"source.seed={args.seed}",
                  f"stages/solve={mode}", f"cache_dir={args.cache}", "export=[source.recording,solve.poses]",
                  "pipeline=no_refine",  # only the solve's poses are measured here; bench_refine_pipeline does refine
                  "log_level=WARNING", *args.extra.split()]
            run(ov, rd)
            wall = time.perf_counter() - t0
            rec = Recording.from_zarr(zarr.open_group(str(rd / "source.recording.zarr"), mode="r"))
            keys = json.loads((rd / "run.json").read_text())["nodes"]["solve"]["keys"]
            entries = [cache.lookup("batch", k) for k in keys]  # None: the batch failed (recorded, not cached)
            failed = sum(e is None for e in entries)
            if failed:
                print(f"  {motion} {mode}: {failed} of {len(keys)} batches failed; AE is over the others",
                      file=sys.stderr)
            stats = [e.manifest.get("stats", {}) for e in entries if e is not None]
            secs = [s["solve_s"] for s in stats if "solve_s" in s]
            # solves of a batch: the two end fits first, then one per ICP round (modes batch / per_frame)
            fit_its = [it for s in stats for _, it, _ in s.get("solves", [])[:2]]
            icp_its = [it for s in stats for _, it, _ in s.get("solves", [])[2:]]
            icp_s = [sec for s in stats for _, _, sec in s.get("solves", [])[2:]]
            builds += [s["build_s"] for s in stats if "build_s" in s]
            errs, iters = [], []
            for f in sorted((rd / "solve.poses").glob("batch*.zarr")):
                ps = PoseSequence.from_zarr(zarr.open_group(str(f), mode="r"))
                pred = joint_positions(ps.poses, rec.template.rest_joints)
                true = joint_positions(pose_at(rec.ground_truth, ps.t_us), rec.template.rest_joints)
                errs.append(mean_joint_error(pred, true))
                iters.append(ps.iterations)
            e = np.concatenate(errs) * 1000 if errs else np.array([np.nan])
            row = {"motion": motion, "mode": mode, "seed": args.seed, "ae_mm": float(e.mean()), "failed": failed,
                   "ae_std_mm": float(e.std()), "batches": len(errs), "solve_s_median": float(np.median(secs)) if secs else float("nan"),
                   "iterations_median": float(np.median(iters)) if iters else float("nan"), "wall_s": wall,
                   "fit_iterations_median": float(np.median(fit_its)) if fit_its else None,
                   "icp_solve_iterations_median": float(np.median(icp_its)) if icp_its else None,
                   "icp_solve_s_median": float(np.median(icp_s)) if icp_s else None}
            rows.append(row)
            print(f"{motion:<14} {mode:<10} {row['ae_mm']:7.1f} {row['ae_std_mm']:7.1f} {row['batches']:7d} "
                  f"{row['solve_s_median']:8.2f} {row['iterations_median']:6.0f} {row['fit_iterations_median'] or 0:6.0f} "
                  f"{row['icp_solve_iterations_median'] or 0:6.0f} {row['icp_solve_s_median'] or 0:6.2f}", flush=True)
    print("\nmean over motions:")
    for mode in modes:
        r = [x for x in rows if x["mode"] == mode]
        print(f"  {mode:<10} AE {np.mean([x['ae_mm'] for x in r]):6.1f} mm   solve {np.median([x['solve_s_median'] for x in r]):.2f} s/batch")
    if builds:
        print(f"  NLP build: {np.median(builds):.2f} s median over {len(builds)} builds (once per process)")
    if "batch" in modes and "linear" in modes:
        for motion in args.motions.split(","):
            b = next(x["ae_mm"] for x in rows if x["motion"] == motion and x["mode"] == "batch")
            lin = next(x["ae_mm"] for x in rows if x["motion"] == motion and x["mode"] == "linear")
            print(f"  {motion:<14} batch error {100 * (b / lin - 1):+.0f}% relative to linear")
    out.mkdir(parents=True, exist_ok=True)
    (out / f"results-s{args.seed}.json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
