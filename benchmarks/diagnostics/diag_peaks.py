"""Which fast moments a motion loses: the peak-speed error of each (batch, end effector) against how fast the truth
was, signed (negative: the estimate is slower than the truth).

    python benchmarks/diagnostics/diag_peaks.py BENCH_DIR [BENCH_DIR ...] [--method default] [--cache runs/cache]

The metric `peak_speed_err` of `metrics.json` is the median of |max pred - max true| / max true over the pairs of a
40 ms batch and an end effector (wrists, ankles, head) whose true peak exceeds 0.5 m/s. Most such pairs are slow (on
karate_kick, 58 of 91 peak below 1.5 m/s), so the median says little about the fastest moments. This splits the
pairs by their true peak speed (0.5-1.5, 1.5-3, 3-6, 6+ m/s) and gives the median error, absolute and signed, of
each bin.

Each BENCH_DIR is an `eventcap benchmark` output folder; the run's `motion.npz` comes from its run folder and the
ground truth from the source entry of the cache its run.json names (nothing is recomputed). A diagnosis with the
ground truth: nothing here is used by a run.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
BINS = ((0.5, 1.5), (1.5, 3.0), (3.0, 6.0), (6.0, np.inf))


def load(run_dir: Path, cache: Path):
    import zarr

    from eventcap.artifacts.recording import Recording
    from eventcap.analysis.metrics import truth_at

    key = json.loads((run_dir / "run.json").read_text())["nodes"]["source"]["keys"][0]
    data = next(cache.glob(f"entries/*/{key}/data"), None)
    if data is None:
        raise SystemExit(f"{run_dir}: the source entry {key} is not in {cache}")
    rec = Recording.from_zarr(zarr.open_group(str(data), mode="r")["recording"])
    m = np.load(run_dir / "motion.npz")
    est = m["estimated"] if "estimated" in m.files else np.isfinite(m["joints"]).all(axis=(1, 2))
    t, J = m["t_us"][est], m["joints"][est]
    G, inside = truth_at(rec.ground_truth.t_us, rec.ground_truth.joints, t)
    return t[inside], J[inside], G


def peak_pairs(t, J, G, window_us: float = 10_000.0, batch_us: int = 40_000) -> np.ndarray:
    """(n, 2): the true peak speed (m/s) and the signed relative error of the estimate's peak, per (batch, end
    effector) with a true peak above 0.5 m/s."""
    from eventcap.body.skeleton import JOINT_INDEX
    from eventcap.analysis.metrics import central_derivative, root_relative

    ee = [JOINT_INDEX[n] for n in ("l_wrist", "r_wrist", "l_ankle", "r_ankle", "head")]
    vp, valid = central_derivative(root_relative(J), t, window_us, 1)
    vt, _ = central_derivative(root_relative(G), t, window_us, 1)
    sp, st = np.linalg.norm(vp[:, ee], axis=-1), np.linalg.norm(vt[:, ee], axis=-1)
    rows = []
    for t0 in range(int(t[0]), int(t[-1]), batch_us):
        w = valid & (t >= t0) & (t < t0 + batch_us)
        if w.any():
            pt, pp = st[w].max(axis=0), sp[w].max(axis=0)
            rows += [(a, (b - a) / a) for a, b in zip(pt, pp) if a > 0.5]
    return np.array(rows).reshape(-1, 2)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("bench", nargs="+")
    ap.add_argument("--method", default="default")
    ap.add_argument("--cache", default=str(ROOT / "runs" / "cache"))
    args = ap.parse_args()
    print(f"{'run':<40} {'pairs':>5} {'median |err|':>12}  " + "  ".join(f"{lo:g}-{hi:g} m/s" for lo, hi in BINS))
    for bench in args.bench:
        for run_dir in sorted(Path(bench).glob(f"runs/*/{args.method}")):
            r = peak_pairs(*load(run_dir, Path(args.cache)))
            cells = []
            for lo, hi in BINS:
                s = r[(r[:, 0] >= lo) & (r[:, 0] < hi)]
                cells.append(f"{len(s):>2}: {np.median(s[:, 1]):+.2f}" if len(s) else "  -")
            name = f"{Path(bench).name}/{run_dir.parent.name}"
            print(f"{name:<40} {len(r):>5} {np.median(np.abs(r[:, 1])):12.3f}  " + "  ".join(f"{c:>10}" for c in cells))


if __name__ == "__main__":
    main()
