"""Calibrate the uncertainty's settings (stages.confidence.*) on the open benchmark's TUNING seeds (issue 45).

    eventcap benchmark benchmark=open only=[default] cache_dir=/work/cache out=runs/bench/tune
    python benchmarks/accuracy/calibrate_uncertainty.py runs/bench/tune [--cues runs/cues]

For every finished run of the ``default`` row: the uncertainty's cues (the confidence stage's own
``motion_cues``: the solve's σ, the detections' residuals, the events' gap, the joints' image positions) at the
evaluated frames, and the error there (the evaluate stage's, after its per-frame rigid alignment). Then:

1. the relative weights (detection_3d / scale, detection_2d / scale, events / scale, floor_mm / scale) on a grid,
   each scored by the mean of the pooled Spearman correlation and of each group's (the ranking is the same for any
   common factor);
2. the common factor that puts the pooled 2-sigma coverage at 93.5 % (the middle of the 90-97 % target);
3. trusted_mm: the 90th percentile of the uncertainty of the joints in view on whole-body captures with frames (so
   that nine in ten of them are trusted), and unseen_mm a fifth above it (a joint out of view is never trusted).

It prints each step's figures and the settings to state in plugins/eventcap_confidence/spec.py. Never run it on the
check seeds: the suite refuses them for tuning (benchmark=open holds only seeds 0-19).
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_uncertainty import capture_groups  # noqa: E402

TARGET = 0.935


def run_cues(run_dir: Path) -> dict:
    """The cues and the error at the evaluated frames of a finished run (arrays (F, 24))."""
    from eventcap.analysis.uncertainty import joint_uncertainty  # noqa: F401 (the model the cues feed)
    from eventcap.body.kinematics import joint_positions
    from eventcap.analysis.confidence import joint_radii
    from eventcap.core.runner import load_finished_run
    from eventcap.worldframe import upright
    from eventcap_confidence._impl import motion_cues

    runner, result = load_finished_run(run_dir)
    get = lambda key: runner.load_output(result, key)  # noqa: E731
    det = get("detect.detections")[None]
    rec = upright(get("source.recording")[None], det)
    cut = get("cut.poses")
    cues = motion_cues(rec, det, [cut[k] for k in sorted(cut)], runner.by_name["confidence"].config)
    errors = get("evaluate.errors")[None]
    t = cues["t_us"]
    k = np.searchsorted(t, errors.t_us)
    est = cues["estimated"][k]
    P = cues["poses"][k]
    J = np.zeros((k.size, 24, 3))
    J[est] = joint_positions(P[est], rec.template)
    cam = rec.camera
    z = cam.depth(J.reshape(-1, 3)).reshape(k.size, 24)
    px = np.full((k.size, 24, 2), np.nan)
    front = (z > 0.05) & est[:, None]
    px[front] = cam.project(J[front])
    edge = np.minimum.reduce([px[..., 0] + 0.5, cam.width - 0.5 - px[..., 0], px[..., 1] + 0.5,
                              cam.height - 0.5 - px[..., 1]])  # px inside the nearest edge (in_image's measure)
    f_over_z = max(cam.fx, cam.fy) / np.maximum(z, 0.05)
    sig = cues["sigma"] if cues["sigma"] is not None else np.full((t.size, 24), np.nan)
    return {"E": errors.error_m * 1000.0, "sig": sig[k], "r2": cues["r2"][k], "r3": cues["r3"][k],
            "gap": cues["gap"][k], "edge": np.nan_to_num(edge, nan=-1e9), "f_over_z": f_over_z,
            "radius_px": joint_radii(rec.template)[None] * f_over_z, "est": est}


def uncertainty(c: dict, w: dict, common: float = 1.0) -> np.ndarray:
    """The uncertainty of one run's cues with relative weights w, times the common factor (before out of view)."""
    var = (c["sig"] ** 2 + (w["detection_3d"] * np.nan_to_num(c["r3"])) ** 2
           + (w["detection_2d"] * np.nan_to_num(c["r2"])) ** 2 + (w["events"] * np.nan_to_num(c["gap"])) ** 2
           + w["floor_mm"] ** 2)
    return common * np.sqrt(var)


def in_view(c: dict, u: np.ndarray, margin: float) -> np.ndarray:
    return c["edge"] >= np.maximum(c["radius_px"], margin * u / 1000.0 * c["f_over_z"])


def pooled(runs: list[dict], fn) -> tuple[np.ndarray, np.ndarray]:
    e = np.concatenate([r["E"].ravel() for r in runs])
    u = np.concatenate([fn(r).ravel() for r in runs])
    ok = np.isfinite(e) & np.isfinite(u)
    return u[ok], e[ok]


def score(runs: list[dict], groups: list[str], fn) -> dict:
    from eventcap.analysis.uncertainty import coverage, sparsification, spearman

    out = {}
    for g in ["pooled", *sorted(set(groups))]:
        sel = runs if g == "pooled" else [r for r, gg in zip(runs, groups) if gg == g]
        u, e = pooled(sel, fn)
        out[g] = {"runs": len(sel), "spearman": spearman(u, e), "ause_ratio": sparsification(u, e)["ratio"],
                  "cover2": coverage(u, e, 2.0)}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("folders", nargs="+")
    ap.add_argument("--cues", default=None, help="keep each run's cues here (npz) and read them back next time")
    ap.add_argument("--unseen-over-trusted", type=float, default=1.2)
    ap.add_argument("--view-margin", type=float, default=1.0)
    args = ap.parse_args(argv)
    from eventcap.apps.open_suite import TUNING_SEEDS

    runs, groups, names = [], [], []
    for folder in map(Path, args.folders):
        gmap = capture_groups(folder)
        for run_dir in sorted((folder / "runs").glob("*/default")):
            label = run_dir.parent.name
            if int(label.lstrip("s")) not in TUNING_SEEDS:
                sys.exit(f"{run_dir}: seed {label} is not a tuning seed: calibrate on benchmark=open only")
            if not (run_dir / "motion.npz").is_file():
                print(f"left out: {label} (no motion: failed or refused)")
                continue
            cache = Path(args.cues) / f"{label}.npz" if args.cues else None
            if cache is not None and cache.is_file():
                c = dict(np.load(cache))
            else:
                c = run_cues(run_dir)
                if cache is not None:
                    cache.parent.mkdir(parents=True, exist_ok=True)
                    np.savez_compressed(cache, **c)
            runs.append(c)
            groups.append(gmap.get(label, "other"))
            names.append(label)
    print(f"{len(runs)} tuning runs: " + ", ".join(f"{n} ({g})" for n, g in zip(names, groups)))
    # 1. relative weights, by ranking
    grid = {"detection_3d": [0.0, 0.4, 1.0, 1.5, 2.5, 4.0, 6.0], "detection_2d": [0.0, 0.3, 0.7, 1.5, 3.0],
            "events": [0.0, 0.5, 1.0, 2.0, 4.0], "floor_mm": [0.0, 20.0, 50.0]}
    best = None
    for vals in itertools.product(*grid.values()):
        w = dict(zip(grid, vals))
        s = score(runs, groups, lambda r, w=w: uncertainty(r, w))
        obj = 0.5 * s["pooled"]["spearman"] + 0.5 * np.mean([v["spearman"] for g, v in s.items() if g != "pooled"])
        if best is None or obj > best[0]:
            best = (obj, w, s)
    obj, w, s = best
    print("1. relative weights (per unit of the solve's sigma):", json.dumps(w))
    for g, v in s.items():
        print(f"   {g:<13} runs {v['runs']:>2}  spearman {v['spearman']:.3f}  ause/random {v['ause_ratio']:.3f}")
    # 2. the common factor for 93.5 % coverage within 2 uncertainties (pooled), out of view included
    margin, factor = args.view_margin, 1.0
    lo, hi = 1e-3, 1e3
    for _ in range(60):
        factor = np.sqrt(lo * hi)
        u, e = pooled(runs, lambda r, f=factor: uncertainty(r, w, f))
        cov = float(np.mean(e <= 2 * u))
        lo, hi = (factor, hi) if cov < TARGET else (lo, factor)
    # 3. trusted_mm and unseen_mm from the joints in view of whole-body captures with frames
    us = [uncertainty(r, w, factor) for r in runs]
    seen = np.concatenate([(in_view(r, u, margin) & r["est"][:, None]).ravel()
                           for r, u, g in zip(runs, us, groups) if g == "whole_frames"])
    uw = np.concatenate([u.ravel() for u, g in zip(us, groups) if g == "whole_frames"])
    trusted = float(np.nanpercentile(uw[seen], 90))
    unseen = args.unseen_over_trusted * trusted
    final = {"scale": round(factor, 4), **{k: round(v * factor, 4) for k, v in w.items() if k != "floor_mm"},
             "floor_mm": round(w["floor_mm"] * factor, 1), "trusted_mm": round(trusted, 0),
             "unseen_mm": round(unseen, 0), "view_margin": margin}
    print("2-3. settings:", json.dumps(final))

    def full(r):
        u = uncertainty(r, w, factor)
        return np.where(in_view(r, u, margin), u, np.maximum(u, unseen))

    for g, v in score(runs, groups, full).items():
        print(f"   {g:<13} runs {v['runs']:>2}  spearman {v['spearman']:.3f}  ause/random {v['ause_ratio']:.3f}  "
              f"2-sigma coverage {100 * v['cover2']:.1f}%")
    return 0


if __name__ == "__main__":
    sys.exit(main())
