"""The windows' disagreement at the spline solve's seams, judged on finished runs (stitch v5, docs/results/real.md).

    python benchmarks/accuracy/bench_seams.py RUN_DIR [RUN_DIR ...]

For each run with ground truth (a finished `eventcap run` of the spline pipeline, its cache still holding the
solve's windows): the windows, how many evaluated frames lie where two or more overlap, the σ there blended alone
against with the windows' spread added (what the stitch now ships), and the uncertainty the confidence stage makes
from either σ (the shipped calibration, as benchmarks/accuracy/calibrate_uncertainty.py computes it) against the
error (evaluate.errors), over every evaluated frame and over the overlaps: Spearman, sparsification area over
random, 2-sigma coverage. Nothing is asserted.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(ROOT / "plugins"))
import calibrate_uncertainty as cu  # noqa: E402


def run_pairs(run_dir: Path, table: dict) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """{"old" | "new": (uncertainty, error, in an overlap)} at the run's evaluated (frame, joint) pairs."""
    from eventcap.analysis.uncertainty import calibration
    from eventcap.core.runner import load_finished_run
    from eventcap_spline.stitch import blend_sigma, window_weights

    runner, res = load_finished_run(run_dir)
    windows, sigmas = [], []
    for p in (p for _, p in sorted(runner.load_output(res, "solve.poses").items()) if p.t_us.size):
        ok = np.isfinite(p.poses).all(axis=1)
        windows.append((np.asarray(p.t_us)[ok], np.asarray(p.poses)[ok]))
        sigmas.append(None if p.sigma_mm is None else np.asarray(p.sigma_mm)[ok])
    taper = float(runner.by_name["stitch"].config.taper)
    t = np.asarray(runner.load_output(res, "stitch.motion")[None].t_us)
    alone = blend_sigma(windows, sigmas, taper, t)
    count = np.zeros(t.size, dtype=int)
    for idx, _ in window_weights(windows, taper, t):
        count[idx] += 1
    c = cu.run_cues(run_dir)
    k = np.searchsorted(t, runner.load_output(res, "evaluate.errors")[None].t_us)
    overlap = np.broadcast_to((count[k] > 1)[:, None], c["E"].shape)
    entry = table["detectors"][calibration(table, str(c["kind"]))[0]]
    w, factor, by_fps = cu.entry_weights(entry)
    full = cu.shipped(w, factor, by_fps, entry.get("factor_by_view", {}), float(entry["unseen_mm"]), 1.0)
    print(f"{run_dir}: {len(windows)} windows, {int((count[k] > 1).sum())} of {k.size} evaluated frames in overlaps; "
          f"σ median there {np.nanmedian(alone[k][count[k] > 1]):.1f} (blended alone) -> "
          f"{np.nanmedian(c['sig'][count[k] > 1]):.1f} mm (with the spread)")
    return {"new": (full(c), c["E"], overlap), "old": (full({**c, "sig": alone[k]}), c["E"], overlap)}


def main(argv=None) -> int:
    from eventcap.analysis.uncertainty import coverage, sparsification, spearman

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+")
    args = ap.parse_args(argv)
    table = json.loads((ROOT / "plugins" / "eventcap_confidence" / "calibration.json").read_text())
    got = [run_pairs(Path(r), table) for r in args.runs]
    for where in ("every frame", "overlaps"):
        for name, label in (("old", "σ blended alone"), ("new", "with the spread")):
            u = np.concatenate([g[name][0].ravel() for g in got])
            e = np.concatenate([g[name][1].ravel() for g in got])
            sel = np.concatenate([g[name][2].ravel() for g in got]) if where == "overlaps" else np.ones(u.size, bool)
            ok = sel & np.isfinite(u) & np.isfinite(e)
            if ok.sum() < 2:
                print(f"{where:<12} {label}: no pairs")
                continue
            u, e = u[ok], e[ok]
            print(f"{where:<12} {label:<16} pairs {u.size:>6}  spearman {spearman(u, e):.3f}  ause/random "
                  f"{sparsification(u, e)['ratio']:.3f}  2-sigma {100 * coverage(u, e):.1f}%  u median "
                  f"{np.median(u):.1f}  error median {np.median(e):.1f} mm")
    return 0


if __name__ == "__main__":
    sys.exit(main())
