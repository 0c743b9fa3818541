"""Does the uncertainty mean something? Its figures on finished open-benchmark runs (issue 45), with the truth.

    eventcap benchmark benchmark=open_check only=[default] cache_dir=/work/cache out=runs/bench/check \\
        "overrides=[outputs.video=false,outputs.c3d=true]"
    python benchmarks/accuracy/bench_uncertainty.py runs/bench/check [more benchmark or run folders] [--plot out.png]
    python benchmarks/accuracy/bench_uncertainty.py runs/bench/ladder_check --method edefault   # a ladder row

For every run of the ``default`` row in each benchmark folder (``<folder>/runs/<capture>/default``), pooled over the
runs and per group of the open suite (whole body with frames, whole body event-only, partial view):

- the error: each joint's 3D distance to the truth after the evaluation's per-frame rigid alignment (the evaluate
  stage's ``errors``: its every-n-th tracking frames), against ``uncertainty_mm`` of the run's motion.npz there;
- ``spearman``: the rank correlation of uncertainty and error over the (frame, joint) pairs (target >= 0.5);
- ``ause/random``: the area between the sparsification curve (drop the most uncertain first) and the oracle's, over
  a random ranking's (target <= 0.4);
- ``cover2``: the share of errors within 2 uncertainties (target 0.90-0.97); ``cover1`` within one;
- ``out/obs``: of the (frame, joint) pairs whose true joint is out of the image, the share marked observed
  (confidence >= 0.5; the issue's measure, target <= 2 %); ``obs/out``: of those marked observed, the share truly out;
- ``c3d -1``: points with residual -1 in motion.c3d at frames that are not a gap (target 0), when the run wrote one.

``--plot``: the mean error against the uncertainty, binned (quantile bins of the uncertainty), per group, with the
line error = uncertainty; ``--json``: every figure. Runs that failed or have no uncertainty are listed and left out.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
GROUPS = ("whole_frames", "whole_events", "partial")


def capture_groups(folder: Path) -> dict[str, str]:
    """{capture label: group} from a benchmark folder's benchmark.json (empty when it has none)."""
    p = folder / "benchmark.json"
    if not p.is_file():
        return {}
    doc = json.loads(p.read_text())
    return {c["label"]: c.get("group", "") for c in doc.get("captures") or []}


def measure_run(run_dir: Path) -> dict:
    """The (frame, joint) pairs of one run: error and uncertainty at the evaluated frames, and over every frame the
    truth in view against the confidence; the C3D residuals outside gaps."""
    from eventcap.analysis.confidence import OBSERVED, in_image
    from eventcap.analysis.metrics import truth_at
    from eventcap.core.runner import load_finished_run
    from eventcap.worldframe import upright

    m = np.load(run_dir / "motion.npz")
    if "uncertainty_mm" not in m.files:
        return {"error": "motion.npz has no uncertainty_mm"}
    runner, result = load_finished_run(run_dir)
    errors = runner.load_output(result, "evaluate.errors")[None]
    rec = runner.load_output(result, "source.recording")[None]
    det = runner.load_output(result, "detect.detections")[None]
    rec = upright(rec, det)
    t, u, c, est = m["t_us"], m["uncertainty_mm"].astype(np.float64), m["confidence"], m["estimated"]
    k = np.searchsorted(t, errors.t_us)
    if not np.array_equal(t[np.minimum(k, t.size - 1)], errors.t_us):
        return {"error": "the evaluated frames are not among motion.npz's frames"}
    out = {"error_mm": errors.error_m * 1000.0, "uncertainty_mm": u[k]}
    truth, inside = truth_at(rec.ground_truth.t_us, rec.ground_truth.joints, t[est])
    true_in = in_image(rec.camera, truth)
    seen = (c[est] >= OBSERVED)[inside]
    out["out_of_view"] = int((~true_in).sum())
    out["out_of_view_observed"] = int((seen & ~true_in).sum())
    out["observed"] = int(seen.sum())
    c3d_path = run_dir / "motion.c3d"
    if c3d_path.is_file():
        out["c3d_minus_one_outside_gaps"], out["c3d_points"] = c3d_invalid_outside_gaps(c3d_path, t, est)
    return out


def c3d_invalid_outside_gaps(path: Path, t_us: np.ndarray, est: np.ndarray) -> tuple[int, int]:
    """(points with residual -1 at frames the motion estimated, points there) of a motion.c3d (read with the c3d
    package: frame n at t0 + (n - first) · step)."""
    import warnings

    import c3d

    with open(path, "rb") as fh, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = c3d.Reader(fh)
        step_us = int(round(1e6 / float(r.point_rate)))
        frames = [(i, p[:, 3].copy()) for i, p, _ in r.read_frames()]
    first = frames[0][0]
    t0 = int(t_us[est][0])
    estimated = set(int(v) for v in t_us[est])
    bad = total = 0
    for i, res in frames:
        if t0 + (i - first) * step_us in estimated:
            bad += int((res == -1).sum())
            total += res.size
    return bad, total


def figures(rows: list[dict]) -> dict:
    from eventcap.analysis.uncertainty import coverage, sparsification, spearman

    if not rows:
        return {"runs": 0}
    e = np.concatenate([r["error_mm"].ravel() for r in rows])
    u = np.concatenate([r["uncertainty_mm"].ravel() for r in rows])
    ok = np.isfinite(e) & np.isfinite(u)
    sp = sparsification(u[ok], e[ok])
    out = {"runs": len(rows), "pairs": int(ok.sum()), "error_mean_mm": float(e[ok].mean()),
           "error_median_mm": float(np.median(e[ok])),
           "uncertainty_median_mm": float(np.median(u[ok])), "spearman": spearman(u, e),
           "ause_ratio": sp["ratio"], "cover1": coverage(u, e, 1.0), "cover2": coverage(u, e, 2.0)}
    oov = sum(r["out_of_view"] for r in rows)
    out["out_of_view"] = oov
    out["out_of_view_observed"] = sum(r["out_of_view_observed"] for r in rows) / oov if oov else None
    obs = sum(r["observed"] for r in rows)
    out["observed_out_of_view"] = sum(r["out_of_view_observed"] for r in rows) / obs if obs else None
    c3d = [r for r in rows if "c3d_points" in r]
    if c3d:
        out["c3d_minus_one_outside_gaps"] = sum(r["c3d_minus_one_outside_gaps"] for r in c3d)
        out["c3d_points"] = sum(r["c3d_points"] for r in c3d)
    return out


def plot(path: Path, by_group: dict[str, list[dict]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = [g for g in by_group if by_group[g]]
    fig, axes = plt.subplots(1, len(groups), figsize=(4.2 * len(groups), 4.0), squeeze=False)
    for ax, g in zip(axes[0], groups):
        e = np.concatenate([r["error_mm"].ravel() for r in by_group[g]])
        u = np.concatenate([r["uncertainty_mm"].ravel() for r in by_group[g]])
        ok = np.isfinite(e) & np.isfinite(u)
        e, u = e[ok], u[ok]
        edges = np.unique(np.quantile(u, np.linspace(0, 1, 11)))
        b = np.clip(np.searchsorted(edges, u, side="right") - 1, 0, edges.size - 2)
        mu = np.array([u[b == i].mean() for i in range(edges.size - 1)])
        me = np.array([e[b == i].mean() for i in range(edges.size - 1)])
        q90 = np.array([np.quantile(e[b == i], 0.9) for i in range(edges.size - 1)])
        ax.scatter(u[:: max(1, u.size // 3000)], e[:: max(1, u.size // 3000)], s=2, alpha=0.15, color="grey",
                   label="(frame, joint) pairs")
        ax.plot(mu, me, "o-", color="C0", label="mean error per bin")
        ax.plot(mu, q90, "s--", color="C1", label="90th percentile")
        top = float(max(mu.max(), me.max()) * 2.2)
        ax.plot([0, top], [0, top], "k:", lw=1, label="error = uncertainty")
        ax.plot([0, top], [0, 2 * top], color="0.6", lw=1, ls="-.", label="error = 2 x uncertainty")
        ax.set_xlim(0, top)
        ax.set_ylim(0, top * 1.5)
        ax.set_xlabel("uncertainty (mm)")
        ax.set_ylabel("error after rigid alignment (mm)")
        ax.set_title(f"{g} ({len(by_group[g])} runs)")
        ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _fmt(v, pct: bool = False) -> str:
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "-"
    return f"{100 * v:.1f}%" if pct else f"{v:.2f}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("folders", nargs="+", help="benchmark output folders (their runs/<capture>/default are read) or "
                                               "run folders")
    ap.add_argument("--method", default="default", help="the row whose runs are measured")
    ap.add_argument("--plot", default=None, help="write the binned error-against-uncertainty plot here (PNG)")
    ap.add_argument("--json", default=None, help="write every figure here")
    args = ap.parse_args(argv)
    by_group: dict[str, list[dict]] = {g: [] for g in GROUPS}
    skipped = []
    for folder in map(Path, args.folders):
        groups = capture_groups(folder)
        dirs = [folder] if (folder / "run.json").is_file() else sorted((folder / "runs").glob(f"*/{args.method}"))
        for run_dir in dirs:
            label = run_dir.parent.name if run_dir != folder else folder.name
            if not (run_dir / "motion.npz").is_file():
                skipped.append(f"{folder.name}/{label}: no motion.npz (failed or refused)")
                continue
            try:
                r = measure_run(run_dir)
            except Exception as exc:  # noqa: BLE001 - listed, the others still count
                skipped.append(f"{folder.name}/{label}: {type(exc).__name__}: {exc}")
                continue
            if "error" in r:
                skipped.append(f"{folder.name}/{label}: {r['error']}")
                continue
            r["label"] = f"{folder.name}/{label}"
            by_group.setdefault(groups.get(label, "other"), []).append(r)
    table = {"pooled": figures([r for rows in by_group.values() for r in rows])}
    table.update({g: figures(rows) for g, rows in by_group.items() if rows})
    head = (f"{'':<14}{'runs':>5}{'pairs':>7}{'err mm':>8}{'err med':>8}{'u med':>7}{'spearman':>9}{'ause/rnd':>9}"
            f"{'cover1':>8}"
            f"{'cover2':>8}{'out/obs':>8}{'obs/out':>8}{'c3d -1':>8}")
    print(head)
    for name, f in table.items():
        if not f.get("runs"):
            continue
        c3d = "-" if "c3d_points" not in f else f"{f['c3d_minus_one_outside_gaps']}/{f['c3d_points']}"
        print(f"{name:<14}{f['runs']:>5}{f['pairs']:>7}{f['error_mean_mm']:>8.1f}{f['error_median_mm']:>8.1f}"
              f"{f['uncertainty_median_mm']:>7.1f}"
              f"{_fmt(f['spearman']):>9}{_fmt(f['ause_ratio']):>9}{_fmt(f['cover1'], True):>8}"
              f"{_fmt(f['cover2'], True):>8}{_fmt(f['out_of_view_observed'], True):>8}"
              f"{_fmt(f['observed_out_of_view'], True):>8}{c3d:>8}")
    for s in skipped:
        print(f"left out: {s}")
    if args.plot:
        plot(Path(args.plot), {g: rows for g, rows in by_group.items() if rows})
        print(f"wrote {args.plot}")
    if args.json:
        Path(args.json).write_text(json.dumps(table, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
