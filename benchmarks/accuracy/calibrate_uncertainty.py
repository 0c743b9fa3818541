"""Calibrate the uncertainty per detector kind (stages.confidence.calibration) on TUNING captures (issues 45, 58).

    eventcap benchmark benchmark=ladder 'seeds=[0,1]' 'only=[a default,d default,e default]' out=runs/bench/tune
    python benchmarks/accuracy/calibrate_uncertainty.py runs/bench/tune [--cues runs/cues] [--write calibration.json]

For every finished run of the rows asked for (``--rows``, the method folders' names; default: every row whose name
ends in ``default``): the uncertainty's cues (the confidence stage's own ``motion_cues``: the solve's σ, the
detections' residuals, the events' gap, the motion between the frames, the joints' image positions) at the evaluated
frames, and the error there (the evaluate stage's, after its per-frame rigid alignment). The runs are split by the
kind of detector that made their detections (simulated, blazepose, file); per kind:

1. the relative weights (per unit of the solve's σ: detection_3d, detection_2d, events, motion, speed, between_mm,
   floor_mm) by coordinate descent over a grid of each, scored by the mean of the kind's pooled Spearman correlation
   and of each row's (the ranking is the same for any common factor); a cue whose leaving out costs less than
   MIN_GAIN is left out (it would only move the uncertainty about, e.g. colour a still torso untrusted);
2. the common factor that puts the kind's pooled 2-sigma coverage at 93.5 % (the middle of the 90-97 % target),
   and, when the runs come at more than one frame rate, each rate's own factor relative to it (``factor_by_fps``:
   the confidence stage interpolates it in log fps at a capture's rate);
3. trusted_mm: the 90th percentile of the uncertainty of the joints in view (so that nine in ten of them are
   trusted), and unseen_mm a fifth above it (a joint out of view is never trusted);
4. each cue's worth: the Spearman correlation and sparsification area with that cue left out (issue 58 item 3).

``--write``: the calibration table (plugins/eventcap_confidence/calibration.json's form) with these kinds' entries
(the entries of kinds not calibrated here kept from the table it replaces). Only tuning captures are accepted:
the ladder's seeds 0-1 (labels ``<motion>-s<seed>``), the open benchmark's tuning seeds (labels ``s<seed>``).
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_uncertainty import capture_groups  # noqa: E402

TARGET = 0.935
#: a cue stays only if leaving it out costs the objective at least this much (Spearman)
MIN_GAIN = 0.005
LADDER_TUNING = (0, 1)
#: the relative weights' grids (per unit of the solve's σ; between_mm and floor_mm in mm per unit)
GRID = {"detection_3d": [0.0, 0.25, 0.5, 1.0, 1.5, 2.5, 4.0], "detection_2d": [0.0, 0.15, 0.3, 0.7, 1.5, 3.0],
        "events": [0.0, 0.5, 1.0, 2.0], "motion": [0.0, 0.1, 0.2, 0.4, 0.8, 1.5],
        "speed": [0.0, 0.05, 0.1, 0.2, 0.4], "between_mm": [0.0, 0.5, 1.0, 2.0, 5.0, 10.0, 20.0],
        "floor_mm": [0.0, 0.5, 1.0, 2.0, 5.0, 10.0]}
CUES = ("detection_3d", "detection_2d", "events", "motion", "speed", "between_mm", "floor_mm")


def is_tuning(label: str) -> bool:
    from eventcap.apps.open_suite import TUNING_SEEDS

    m = re.fullmatch(r".+-s(\d+)", label)
    if m:
        return int(m.group(1)) in LADDER_TUNING
    m = re.fullmatch(r"s(\d+)", label)
    return bool(m) and int(m.group(1)) in TUNING_SEEDS


def run_cues(run_dir: Path) -> dict:
    """The cues and the error at the evaluated frames of a finished run (arrays (F, 24); ``kind`` the detector's)."""
    from eventcap.analysis.confidence import joint_radii
    from eventcap.analysis.uncertainty import detector_kind
    from eventcap.body.kinematics import joint_positions
    from eventcap.core.runner import load_finished_run
    from eventcap.worldframe import upright
    from eventcap_confidence._impl import motion_cues

    runner, result = load_finished_run(run_dir)
    get = lambda key: runner.load_output(result, key)  # noqa: E731
    node = runner.by_name["confidence"]
    det = get("detect.detections")[None]
    rec = upright(get(node.inputs.get("recording", "source.recording"))[None], det)  # the body stage's, if any
    poses = get(node.inputs["poses"] if isinstance(node.inputs, dict) and "poses" in node.inputs else "cut.poses")
    cues = motion_cues(rec, det, [poses[k] for k in sorted(poses)], node.config)
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
    body = cues["body"][k] if cues["body"] is not None else np.zeros((k.size, 24))  # an exact body: none
    return {"E": errors.error_m * 1000.0, "sig": sig[k], "r2": cues["r2"][k], "r3": cues["r3"][k],
            "body": np.nan_to_num(body), "body_weight": np.array(float(node.config.body)),
            "fallback_mm": np.array(float(node.config.fallback_mm)),
            "gap": cues["gap"][k], "between": cues["between"][k], "step": cues["step"][k],
            "edge": np.nan_to_num(edge, nan=-1e9), "f_over_z": f_over_z,
            "radius_px": joint_radii(rec.template)[None] * f_over_z, "est": est,
            "kind": np.array(detector_kind(cues["detector"])), "fps": np.array(cues["fps"] or 0.0),
            "view": np.array(cues["view"])}


def uncertainty(c: dict, w: dict, common: float = 1.0) -> np.ndarray:
    """The uncertainty of one run's cues with relative weights w, the calibrated parts times the common factor
    (before out of view): the confidence stage's own sum (eventcap.analysis.uncertainty.joint_uncertainty) with the
    settings these make, the estimated body's uncertainty at the run's weight (not calibrated) included."""
    from eventcap.analysis.uncertainty import UncertaintyModel, joint_uncertainty

    model = UncertaintyModel(scale=common, detection_2d=common * w["detection_2d"],
                             detection_3d=common * w["detection_3d"], events=common * w["events"], unseen_mm=0.0,
                             floor_mm=common * w["floor_mm"], fallback_mm=float(c["fallback_mm"]),
                             body=float(c["body_weight"]), motion=common * w["motion"], speed=common * w["speed"],
                             between_mm=common * w["between_mm"])
    return joint_uncertainty(model, c["sig"], c["r2"], c["r3"], c["gap"], c["est"], c["body"], c["between"],
                             c["step"])


def in_view(c: dict, u: np.ndarray, margin: float) -> np.ndarray:
    return c["edge"] >= np.maximum(c["radius_px"], margin * u / 1000.0 * c["f_over_z"])


def pooled(runs: list[dict], fn) -> tuple[np.ndarray, np.ndarray]:
    e = np.concatenate([r["E"].ravel() for r in runs])
    u = np.concatenate([fn(r).ravel() for r in runs])
    ok = np.isfinite(e) & np.isfinite(u)
    return u[ok], e[ok]


def score(runs: list[dict], groups: list[str], fn, cover: bool = False) -> dict:
    from eventcap.analysis.uncertainty import coverage, sparsification, spearman

    out = {}
    for g in ["pooled", *sorted(set(groups))]:
        sel = runs if g == "pooled" else [r for r, gg in zip(runs, groups) if gg == g]
        u, e = pooled(sel, fn)
        out[g] = {"runs": len(sel), "spearman": spearman(u, e)}
        if cover:
            out[g].update(ause_ratio=sparsification(u, e)["ratio"], cover2=coverage(u, e, 2.0),
                          u_median=float(np.median(u)), e_median=float(np.median(e)))
    return out


def objective(s: dict) -> float:
    rows = [v["spearman"] for g, v in s.items() if g != "pooled"]
    return 0.5 * s["pooled"]["spearman"] + 0.5 * float(np.mean(rows)) if len(rows) > 1 else s["pooled"]["spearman"]


def fit_weights(runs, groups, fixed: dict | None = None, sweeps: int = 3) -> tuple[dict, float]:
    """Coordinate descent over GRID (the cues in ``fixed`` held at their value)."""
    fixed = fixed or {}
    w = {k: fixed.get(k, 0.0) for k in CUES}
    best = objective(score(runs, groups, lambda r: uncertainty(r, w)))
    for _ in range(sweeps):
        moved = False
        for k in CUES:
            if k in fixed:
                continue
            for v in GRID[k]:
                trial = {**w, k: v}
                o = objective(score(runs, groups, lambda r, t=trial: uncertainty(r, t)))
                if o > best + 1e-4:
                    best, w, moved = o, trial, True
        if not moved:
            break
    return w, best


def common_factor(runs, w, base=lambda r: 1.0) -> float:
    """The factor f (bisected in log) that puts the runs' pooled 2-sigma coverage at TARGET, each run's uncertainty
    being uncertainty(r, w, f * base(r)) (base: the factors it already has, e.g. its rate's)."""
    lo, hi = 1e-3, 1e3
    factor = 1.0
    for _ in range(60):
        factor = np.sqrt(lo * hi)
        u, e = pooled(runs, lambda r, f=factor: uncertainty(r, w, f * base(r)))
        lo, hi = (factor, hi) if float(np.mean(e <= 2 * u)) < TARGET else (lo, factor)
    return float(factor)


def rate_factors(runs, w, factor) -> dict[float, float]:
    """{frames per second: the common factor of that rate's runs / the pooled one}, when the runs were made at more
    than one rate (event-only runs, fps 0, take the pooled factor); {} otherwise."""
    rates = sorted({round(float(r.get("fps", 0.0)), 1) for r in runs} - {0.0})
    if len(rates) < 2:
        return {}
    out = {}
    for fps in rates:
        sel = [r for r in runs if round(float(r.get("fps", 0.0)), 1) == fps]
        out[fps] = common_factor(sel, w) / factor
        print(f"   at {fps:g} fps ({len(sel)} runs): factor {out[fps]:.4f} of the pooled")
    return out


def rate_of(r: dict, by_fps: dict[float, float], by_view: dict[str, float] | None = None) -> float:
    """A run's factor at its frame rate (1: the pooled), times its view's (1: none calibrated)."""
    return by_fps.get(round(float(r.get("fps", 0.0)), 1), 1.0) * (by_view or {}).get(str(r.get("view", "")), 1.0)


def shipped(w, factor, by_fps, by_view, unseen, margin):
    """A run's uncertainty as the confidence stage makes it with these settings (the factors of its rate and view,
    and out of view its own added to unseen_mm as variances: out_of_view's rule)."""
    def full(r):
        u = uncertainty(r, w, factor * rate_of(r, by_fps, by_view))
        return np.where(in_view(r, u, margin), u, np.hypot(u, unseen))
    return full


def view_factors(runs, w, factor, by_fps) -> dict[str, float]:
    """{view: the common factor that puts that view's runs at the target coverage, over the one their kind and
    frame rate already have}, for every view but whole_frames the runs come in (issue 58 item 2)."""
    out = {}
    for view in sorted({str(r.get("view", "whole_frames")) for r in runs} - {"whole_frames"}):
        sel = [r for r in runs if str(r.get("view", "")) == view]
        f = out[view] = common_factor(sel, w, lambda r: factor * rate_of(r, by_fps))
        print(f"   view {view} ({len(sel)} runs): factor {f:.4f} of its kind's at its rate")
    return out


def entry_weights(entry: dict) -> tuple[dict, float, dict]:
    """(relative weights, common factor, {fps: factor}) of a calibration table's entry (what calibrate_kind
    wrote): the views calibrated on top of a kind's shipped calibration (``--views-only``)."""
    scale = float(entry["scale"])
    w = {k: float(entry.get(k, 0.0)) / scale for k in CUES}
    return w, scale, {float(k): float(v) for k, v in entry.get("factor_by_fps", {}).items()}


def calibrate_kind(kind: str, runs, groups, margin: float, unseen_over_trusted: float,
                   base: dict | None = None) -> tuple[dict, dict]:
    """The kind's calibration entry from its tuning runs (module doc, 1-4); with ``base`` (its shipped entry), only
    the views' factors on top of it (the rest of the entry kept)."""
    print(f"\n== detector kind {kind}: {len(runs)} tuning runs ({', '.join(sorted(set(groups)))})")
    if base is not None:
        w, factor, by_fps = entry_weights(base)
        by_view = view_factors(runs, w, factor, by_fps)
        entry = {**base, "factor_by_view": {k: round(v, 4) for k, v in by_view.items()}}
        unseen = float(base["unseen_mm"])
    else:
        w, factor, by_fps, entry = fit_kind(runs, groups)
        by_view = view_factors(runs, w, factor, by_fps)
        us = [uncertainty(r, w, factor * rate_of(r, by_fps, by_view)) for r in runs]
        seen = np.concatenate([(in_view(r, u, margin) & r["est"][:, None]).ravel() for r, u in zip(runs, us)])
        trusted = float(np.nanpercentile(np.concatenate([u.ravel() for u in us])[seen], 90))
        unseen = unseen_over_trusted * trusted
        entry.update(trusted_mm=round(trusted, 1), unseen_mm=round(unseen, 1))
        if by_view:
            entry["factor_by_view"] = {k: round(v, 4) for k, v in by_view.items()}
    print("2-3. settings:", json.dumps(entry))

    final = score(runs, groups, shipped(w, factor, by_fps, by_view, unseen, margin), cover=True)
    for g, v in final.items():
        print(f"   {g:<18} runs {v['runs']:>2}  spearman {v['spearman']:.3f}  ause/random {v['ause_ratio']:.3f}  "
              f"2-sigma {100 * v['cover2']:.1f}%  u median {v['u_median']:.1f}  error median {v['e_median']:.1f} mm")
    if base is None:
        cue_worth(runs, groups, w, final)
    entry["view_margin"] = margin
    return entry, final


def fit_kind(runs, groups) -> tuple[dict, float, dict, dict]:
    """Steps 1-2 of the module doc: (relative weights, common factor, {fps: factor}, the entry's parts)."""
    base = {k: 0.0 for k in CUES}
    s0 = score(runs, groups, lambda r: uncertainty(r, base), cover=True)
    print("   the solve's sigma alone:  " + "  ".join(f"{g} sp {v['spearman']:.3f} ause {v['ause_ratio']:.3f}"
                                                  for g, v in s0.items()))
    w, obj = fit_weights(runs, groups)
    print("1. relative weights (per unit of the solve's sigma):", json.dumps(w), f"objective {obj:.3f}")
    for k in CUES:  # a cue that does not earn its place is left out: it would only move the uncertainty about
        if w[k] != 0:
            o = objective(score(runs, groups, lambda r, t={**w, k: 0.0}: uncertainty(r, t)))
            if o > obj - MIN_GAIN:
                print(f"   {k} left out: it adds {obj - o:+.4f} to the objective (less than {MIN_GAIN})")
                w, obj = {**w, k: 0.0}, o
    factor = common_factor(runs, w)
    by_fps = rate_factors(runs, w, factor)
    entry = {"scale": round(factor, 4), **{k: round(w[k] * factor, 4) for k in ("detection_2d", "detection_3d",
                                                                                 "events", "motion", "speed")},
             "between_mm": round(w["between_mm"] * factor, 2), "floor_mm": round(w["floor_mm"] * factor, 2)}
    if by_fps:
        entry["factor_by_fps"] = {f"{k:g}": round(v, 4) for k, v in sorted(by_fps.items())}
    return w, factor, by_fps, entry


def cue_worth(runs, groups, w, final) -> None:
    """Step 4: each cue left out, and the weights refitted without it."""
    print("4. each cue left out (the others kept; pooled spearman, ause/random; then refitted without it):")
    for k in CUES:
        if w[k] == 0:
            print(f"   {k:<13} not used (weight 0 at the optimum)")
            continue
        wo = {**w, k: 0.0}
        s = score(runs, groups, lambda r, t=wo: uncertainty(r, t), cover=True)["pooled"]
        w2, o2 = fit_weights(runs, groups, fixed={k: 0.0}, sweeps=2)
        s2 = score(runs, groups, lambda r, t=w2: uncertainty(r, t), cover=True)["pooled"]
        print(f"   without {k:<13} spearman {s['spearman']:.3f} ause {s['ause_ratio']:.3f} | refitted "
              f"spearman {s2['spearman']:.3f} ause {s2['ause_ratio']:.3f} (with it: "
              f"{final['pooled']['spearman']:.3f} / {final['pooled']['ause_ratio']:.3f})")


def read_runs(args) -> dict[str, tuple[list, list, list]]:
    """{detector kind: (each run's cues, its group label, its name)} of the finished runs in the folders."""
    by_kind: dict[str, tuple[list, list, list]] = {}
    for folder in map(Path, args.folders):
        gmap = capture_groups(folder)
        for run_dir in sorted((folder / "runs").glob("*/*")):
            label, row = run_dir.parent.name, run_dir.name
            if (args.rows is None and not row.endswith("default")) or (args.rows is not None and row not in args.rows):
                continue
            if not args.evaluate and not is_tuning(label):
                sys.exit(f"{run_dir}: {label} is not a tuning capture: calibrate on tuning seeds only")
            if not (run_dir / "motion.npz").is_file():
                print(f"left out: {label}/{row} (no motion: failed or refused)")
                continue
            cache = Path(args.cues) / f"{folder.name}_{label}_{row}.npz" if args.cues else None
            c = dict(np.load(cache)) if cache is not None and cache.is_file() else None
            if c is None or "fallback_mm" not in c:  # none kept, or kept before the body's uncertainty was
                c = run_cues(run_dir)
                if cache is not None:
                    cache.parent.mkdir(parents=True, exist_ok=True)
                    np.savez_compressed(cache, **c)
            runs, groups, names = by_kind.setdefault(str(c["kind"]), ([], [], []))
            runs.append(c)
            groups.append(f"{folder.name}:{row}:{gmap.get(label, 'whole_frames')}")
            names.append(f"{label}/{row}")
    return by_kind


def evaluate(table: dict, by_kind, margin: float) -> None:
    """``--evaluate``: the table's uncertainty on the runs (check captures too), per kind and per view."""
    from eventcap.analysis.uncertainty import calibration

    for kind, (runs, _, names) in sorted(by_kind.items()):
        name, _ = calibration(table, kind)
        entry = table["detectors"][name]
        w, factor, by_fps = entry_weights(entry)
        by_view, unseen = entry.get("factor_by_view", {}), float(entry["unseen_mm"])
        full = shipped(w, factor, by_fps, by_view, unseen, margin)
        views = [f"{r['view']}@{float(r['fps']):g}fps" for r in runs]
        print(f"\n== {kind} (entry {name!r}): " + ", ".join(f"{n} ({v})" for n, v in zip(names, views)))
        for g, v in score(runs, views, full, cover=True).items():
            print(f"   {g:<22} runs {v['runs']:>2}  spearman {v['spearman']:.3f}  ause/random {v['ause_ratio']:.3f}  "
                  f"2-sigma {100 * v['cover2']:.1f}%  u median {v['u_median']:.1f}  error median "
                  f"{v['e_median']:.1f} mm")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("folders", nargs="+")
    ap.add_argument("--rows", nargs="*", default=None, help="method folders to read (default: *default)")
    ap.add_argument("--cues", default=None, help="keep each run's cues here (npz) and read them back next time")
    ap.add_argument("--unseen-over-trusted", type=float, default=1.2)
    ap.add_argument("--view-margin", type=float, default=1.0)
    ap.add_argument("--write", default=None, help="write the calibration table here (entries of other kinds kept "
                                                  "from --base)")
    ap.add_argument("--base", default=str(Path(__file__).resolve().parents[2] / "plugins" / "eventcap_confidence"
                                          / "calibration.json"))
    ap.add_argument("--source", default="", help="text stored as each written entry's source")
    ap.add_argument("--views-only", action="store_true", help="keep each kind's entry of --base and calibrate only "
                                                              "the views' factors on top of it (factor_by_view)")
    ap.add_argument("--evaluate", action="store_true", help="calibrate nothing: the --base table's uncertainty on "
                                                            "the runs (check captures allowed), per view and rate")
    args = ap.parse_args(argv)
    by_kind = read_runs(args)
    table = json.loads(Path(args.base).read_text())
    if args.evaluate:
        evaluate(table, by_kind, args.view_margin)
        return 0
    for kind, (runs, groups, names) in sorted(by_kind.items()):
        print(f"{kind}: " + ", ".join(names))
        base = table["detectors"].get(kind) if args.views_only else None
        if args.views_only and base is None:
            sys.exit(f"--views-only: {args.base} has no entry for detector kind {kind!r} to calibrate views on")
        entry, _ = calibrate_kind(kind, runs, groups, args.view_margin, args.unseen_over_trusted, base)
        entry.pop("view_margin")
        if args.source or base is None:
            entry["source"] = args.source or f"calibrate_uncertainty.py on {len(runs)} tuning runs"
        table["detectors"][kind] = entry
    if args.write:
        Path(args.write).write_text(json.dumps(table, indent=1) + "\n")
        print(f"wrote {args.write}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
