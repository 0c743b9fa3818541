"""The body stage against the truth: the stature and the segments it estimates, their standard errors, and what a
detector shares within a capture (issue 54). Runs only the nodes the body needs (template, source, detect, and
reconstruct for an event-only camera), through the normal runner and cache; the body stage's own run function.

    python benchmarks/accuracy/bench_body.py default detector=simulated duration_s=1.0 "seeds=[0,1]"
    python benchmarks/accuracy/bench_body.py open "seeds=[0,2,4]" [--body told|exact|nothing] [--json out.json]

The first argument is a benchmark preset (conf/benchmark/<preset>.yaml), the rest its overrides (as
``eventcap benchmark``). Each capture is told what the ``default`` row is told (``--body``; ``nothing``: not even
a height). Per capture:

- ``stature``: the truth (the drawn person's, else the template's), the template's, the posterior +- its SD (an
  unstated stature kept: the template's +- the prior's SD), and what the floor alone says +- its SE (the same fit
  without the stature's prior); ``z``: (posterior - truth) / SD;
- ``segments cm``: the median over the 10 limbs and girdles of |length - truth|, the template's -> the body's
  (evaluate's ``stated_body_error_mm`` and ``body_error_mm``, in cm);
- ``in 2 SD``: the share of the 10 segments whose posterior lies within 2 SD of the truth; ``seen in 2 SE``: the same
  for what each segment's images alone say (its seen length +- its SE).

Then, pooled: the shares within 2 SD, and the spread over captures of what each capture's images share (``--spread``:
each measured segment's weighted mean log error of its seen length at the true depths, the floor's median log error
of the pelvis depth: the means and SDs per kind that ``DETECTOR_DEFINITIONS`` and ``DETECTOR_SPREAD`` state).
``--draws N``: for the simulated detector, whose fixed 3D offsets are drawn from its seed alone (every capture of a
seed shares them), the same spread over N more seeds of the detector on each capture (its errors drawn again, the
capture as it is). Never run on the check seeds to choose anything.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
NODES = ("template", "source", "sharpen", "detect", "reconstruct")


def captures(preset: str, overrides: list[str]):
    from eventcap.apps.benchmark import Benchmark, compose_benchmark

    cfg = compose_benchmark(ROOT / "conf", preset, overrides)
    return Benchmark(cfg, ROOT / "conf")


def prepare(bench, cap, body: str = "told"):
    """The capture's recording, detections and template (told as the ``default`` row is), computed or read from
    the cache; None when the detector refused it."""
    from eventcap.core.runner import Runner

    row = next(m for m in bench.methods if m.name == "default")
    row = dataclasses.replace(row, body=body)
    data, _ = bench._compose_row(bench.row_overrides(cap, row), tuple(row.overrides_for(cap.frames) or ()))
    data["pipeline"]["nodes"] = {k: v for k, v in data["pipeline"]["nodes"].items() if k in NODES}
    runner = Runner(data)
    result = runner.run(None)
    det = runner.load_output(result, "detect.detections")
    if not det:
        return None
    rec = runner.load_output(result, "source.recording")[None]
    return rec, det[None], runner.load_output(result, "template.template")[None], data["stages"]


def body_config(stages_body: dict):
    from eventcap.core.config import build_config
    from eventcap.core.registry import load_registry

    keys = {k: v for k, v in stages_body.items() if k != "stage"}
    return build_config(load_registry().get("proportions"), keys, "stages.body")


def estimate(rec, det, template, config):
    """The body stage's output template and its stats (run through its own run function)."""
    from eventcap.core.stage import StageContext
    from eventcap_body._impl import run_proportions

    ctx = StageContext("body", "proportions")
    out = run_proportions({"recording": rec, "detections": det, "template": template}, config, ctx)
    return out["template"], ctx.stats.get("body", {})


def truth_segments(gt) -> dict:
    from eventcap.body.proportions import rest_skeleton_from_motion, segment_lengths

    step = max(1, gt.t_us.size // 20)
    return segment_lengths(rest_skeleton_from_motion(gt.poses[::step], gt.joints[::step]))


def redetect(rec, stages_detect: dict, seed: int):
    """The capture's simulated detections with the detector's errors drawn from another seed."""
    from eventcap.core.config import build_config
    from eventcap.core.registry import load_registry
    from eventcap.core.stage import StageContext

    spec = load_registry().get(stages_detect["stage"])
    keys = {k: v for k, v in stages_detect.items() if k != "stage"}
    cfg = build_config(spec, {**keys, "seed": seed}, "stages.detect")
    return spec.load_run()({"recording": rec}, cfg, StageContext(node="detect", stage=spec.name))["detections"]


def spread_sample(rec, det, template, stats=None) -> dict:
    """What this capture's images share, against the truth: per measured segment the mean log error of its seen
    length at the true pelvis depths (the detector's definitions removed), and the floor's median log error of
    the pelvis depth."""
    from eventcap.body.proportions import SEGMENTS, floor_depths, foot_geometry, image_noise, seen_segments
    from eventcap.worldframe import upright
    from eventcap_body._impl import detector_definitions

    gt = rec.ground_truth
    cam = upright(rec, det).camera
    k = np.clip(np.searchsorted(gt.t_us, det.t_us), 0, gt.t_us.size - 1)
    z_true = cam.to_camera(gt.joints[k, 0])[:, 2]
    truth = truth_segments(gt)
    args = (det.keypoints_2d, det.confidence_2d, det.joints_3d, det.confidence_3d)
    seen = seen_segments(cam, *args)
    defs, _ = detector_definitions(det.detector)
    out = {"segments": {}, "noise": {}, "floor": None, "floor_noise": None}
    for n in SEGMENTS:
        if len(seen.image[n]) >= 3:
            L = seen.unit[n] * (z_true[seen.image[n]] + seen.offset[n]) / defs.get(n, 1.0)
            g = image_noise(seen.pixels[n], seen.across[n])
            w = 1.0 / g ** 2
            r = np.log(L / truth[n])
            mean = float(np.sum(w * r) / w.sum())
            scale = 1.4826 * float(np.median(np.abs((r - mean) / g)))  # the images' noise, as the fit reads it
            out["segments"][n] = mean
            out["noise"][n] = scale ** 2 / float(w.sum())  # what of the mean's error the images' noise explains
    if rec.world == "":
        fz = floor_depths(cam, *args, foot_geometry(template.rest_joints, template.rest_landmarks))
        ok = np.isfinite(fz) & (fz > 0)
        if ok.sum() >= 3:
            r = np.log(fz[ok] / z_true[ok])
            out["floor"] = float(np.median(r))
            out["floor_noise"] = (1.4826 * float(np.median(np.abs(r - np.median(r))))) ** 2 / int(ok.sum())
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("preset")
    ap.add_argument("overrides", nargs="*")
    ap.add_argument("--body", default="told", choices=("told", "exact", "nothing"),
                    help="what each capture is told: as its default row (told), its exact body, or nothing")
    ap.add_argument("--json", default="")
    ap.add_argument("--plot", default="", help="a PNG: per capture the true stature, the template's, the posterior "
                                               "+- 2 SD and the floor alone +- 2 SE")
    ap.add_argument("--spread", action="store_true", help="print what each capture's images share (calibration)")
    ap.add_argument("--draws", type=int, default=0, help="with --spread: draw the simulated detector's errors again "
                                                         "from this many more seeds per capture")
    a = ap.parse_args(argv)
    logging.getLogger("eventcap").setLevel(logging.WARNING)
    from eventcap.body.proportions import SEGMENTS, segment_lengths

    bench = captures(a.preset, a.overrides)
    if bench.purpose == "check":
        print("CHECK SEEDS: for reporting only; never choose anything on these figures")
    rows = []
    for cap in bench.captures:
        got = prepare(bench, cap, a.body)
        if got is None:
            print(f"{cap.label}: refused at detect")
            continue
        rec, det, tpl, stages = got
        body, stats = estimate(rec, det, tpl, body_config(stages["body"]))
        truth = truth_segments(rec.ground_truth)
        H_true = float((cap.drawn or {}).get("actor_height_m") or np.ptp(tpl.vertices[:, 1]))
        before, after = segment_lengths(tpl.rest_joints), segment_lengths(body.rest_joints)
        err0 = 100 * float(np.median([abs(before[n] - truth[n]) for n in SEGMENTS]))
        err1 = 100 * float(np.median([abs(after[n] - truth[n]) for n in SEGMENTS]))
        segs = stats.get("segments_cm") or {}
        z_post = [(segs[n]["posterior"] - 100 * truth[n]) / segs[n]["sd"] for n in segs if segs[n]["sd"] > 0]
        z_seen = [(segs[n]["seen"] - 100 * truth[n]) / segs[n]["seen_se"] for n in segs if segs[n]["seen"] is not None]
        st = stats.get("stature")
        row = {"capture": cap.label, "detector": det.detector.split(":")[0], "group": cap.group,
               "told": "height" if "height_m" in tpl.stated else "nothing", "H_true": H_true,
               "H_template": float(np.ptp(tpl.vertices[:, 1])), "H": float(np.ptp(body.vertices[:, 1])),
               "H_sd": (st or {}).get("sd") or (stats.get("sd") or {}).get("height_m"), "H_floor": (st or {}).get("floor"), "H_floor_se": (st or {}).get("floor_se"),
               "share": (st or {}).get("share"), "err_template_cm": err0, "err_cm": err1, "z_post": z_post,
               "z_seen": z_seen, "sex": stats.get("sex"), "sex_sd": (stats.get("sd") or {}).get("sex"),
               "noise": stats.get("noise"), "scale_from": stats.get("scale_from") or stats.get("why")}
        if a.spread:
            row["spread"] = [spread_sample(rec, det, tpl)]
            for k in range(a.draws):
                row["spread"].append(spread_sample(rec, redetect(rec, stages["detect"], 1000 + k), tpl))
        rows.append(row)
        zH = (row["H"] - H_true) / row["H_sd"] if row["H_sd"] else float("nan")
        print(f"{cap.label:28s} {row['detector']:9s} told {row['told']:7s} stature {H_true:.3f}: "
              f"{row['H_template']:.3f} -> {row['H']:.3f} +- {row['H_sd'] or 0:.3f} (z {zH:+.2f}; floor alone "
              f"{row['H_floor'] or float('nan'):.3f} +- {row['H_floor_se'] or float('nan'):.3f}); segments "
              f"{err0:.2f} -> {err1:.2f} cm; in 2 SD {np.mean(np.abs(z_post) < 2) if z_post else float('nan'):.2f}, "
              f"seen in 2 SE {np.mean(np.abs(z_seen) < 2) if z_seen else float('nan'):.2f}", flush=True)
    if not rows:
        return 1
    zp = np.concatenate([r["z_post"] for r in rows if r["z_post"]] or [np.zeros(0)])
    zs = np.concatenate([r["z_seen"] for r in rows if r["z_seen"]] or [np.zeros(0)])
    zh = np.array([(r["H"] - r["H_true"]) / r["H_sd"] for r in rows if r["H_sd"]])
    print(f"\n{len(rows)} captures: segments within 2 SD {np.mean(np.abs(zp) < 2):.3f} (n {zp.size}); seen within 2 SE "
          f"{np.mean(np.abs(zs) < 2):.3f} (n {zs.size}); stature within 2 SD {np.mean(np.abs(zh) < 2) if zh.size else float('nan'):.3f} "
          f"(n {zh.size})")
    for told in ("height", "nothing"):
        sub = [r for r in rows if r["told"] == told]
        if sub:
            print(f"told {told}: segments median over captures {np.median([r['err_template_cm'] for r in sub]):.2f} -> "
                  f"{np.median([r['err_cm'] for r in sub]):.2f} cm, mean {np.mean([r['err_template_cm'] for r in sub]):.2f}"
                  f" -> {np.mean([r['err_cm'] for r in sub]):.2f} ({len(sub)} captures)")
    if a.spread:
        from eventcap.body.proportions import KIND_OF, KINDS

        per, noise = {}, {}
        for r in rows:
            for sample in r["spread"]:
                for n, v in sample["segments"].items():
                    per.setdefault(KIND_OF[n], []).append(v)
                    noise.setdefault(KIND_OF[n], []).append(sample["noise"][n])
        allv = np.concatenate([np.array(v) for v in per.values()])
        print("spread: per kind, the mean and SD over captures (and draws) of a capture's mean log error of the seen "
              "length at the true depths, and the SD left when the images' own noise is taken out (what DETECTOR_SPREAD "
              "states): " + ", ".join(
                  f"{k} {np.mean(per[k]):+.3f} +- {np.std(per[k]):.3f} -> "
                  f"{np.sqrt(max(np.var(per[k]) - np.mean(noise[k]), 0.0)):.3f} (n {len(per[k])})"
                  for k in KINDS if k in per))
        print(f"spread: all segments RMS {np.sqrt(np.mean(allv ** 2)):.3f}, SD {np.std(allv):.3f}, mean {np.mean(allv):+.3f}")
        fl = np.array([s_["floor"] for r in rows for s_ in r["spread"] if s_["floor"] is not None])
        fn = np.array([s_["floor_noise"] for r in rows for s_ in r["spread"] if s_["floor"] is not None])
        if fl.size:
            print(f"spread: floor's pelvis depth, log error {fl.mean():+.3f} +- {fl.std():.3f} -> "
                  f"{np.sqrt(max(np.var(fl) - np.mean(fn), 0.0)):.3f} without the images' noise (n {fl.size})")
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1, default=float))
    if a.plot:
        plot_statures(Path(a.plot), rows, f"{a.preset} {' '.join(a.overrides)} (told: {a.body})")
    return 0


def plot_statures(path: Path, rows: list, title: str) -> None:
    """Per capture: the truth (black), the template's (grey), the posterior +- 2 SD (blue) and what the floor alone
    says +- 2 SE (orange), in cm against the truth."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(max(6.0, 0.45 * len(rows) + 2), 4.2))
    x = np.arange(len(rows))
    ax.axhline(0.0, color="k", lw=1, label="truth")
    ax.scatter(x, [100 * (r["H_template"] - r["H_true"]) for r in rows], color="0.5", marker="_", s=200,
               label="template (as told)")
    for i, r in enumerate(rows):
        if r["H_sd"]:
            ax.errorbar(i - 0.12, 100 * (r["H"] - r["H_true"]), yerr=200 * r["H_sd"], color="tab:blue", fmt="o",
                        capsize=3)
        else:  # not estimated: the body's stature as told or the template's
            ax.plot(i - 0.12, 100 * (r["H"] - r["H_true"]), "o", color="tab:blue", mfc="none")
        if r["H_floor"]:
            ax.errorbar(i + 0.12, 100 * (r["H_floor"] - r["H_true"]), yerr=200 * r["H_floor_se"], color="tab:orange",
                        fmt="s", capsize=3, ms=4)
    ax.errorbar([], [], yerr=[], color="tab:blue", fmt="o", capsize=3, label="posterior +- 2 SD (open: kept)")
    ax.errorbar([], [], yerr=[], color="tab:orange", fmt="s", capsize=3, ms=4, label="floor alone +- 2 SE")
    ax.set_xticks(x, [r["capture"] for r in rows], rotation=60, ha="right", fontsize=7)
    ax.set_ylabel("stature - truth (cm)")
    import textwrap

    ax.set_title("\n".join(textwrap.wrap(title, 90)), fontsize=8)
    ax.legend(fontsize=7, loc="best")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
