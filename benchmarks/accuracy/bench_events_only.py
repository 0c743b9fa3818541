"""Event-only cameras: images from events against the truth, and the event-only pipeline against the one with frames.

    python benchmarks/accuracy/bench_events_only.py images    [--motions a,b] [--duration 1] [--seed 0]
    python benchmarks/accuracy/bench_events_only.py pipelines [--motions a,b] [--duration 1] [--seed 0] [--paths frames,events]
    python benchmarks/accuracy/bench_events_only.py picture   [--motion karate_kick] [--frame 12] [--png out.png]
    python benchmarks/accuracy/bench_events_only.py withheld  [--motions a,b] [--duration 1]

``images``: on synthetic captures (the ``source`` node through the normal runner and cache), reconstructions from
the events alone (:mod:`eventcap.imaging.reconstruct`: direct integration, the per-pixel high-pass filter at several
cutoffs, with and without a spatial Gaussian) at every intensity-frame time, compared with the true sharp image's
log, log(I + 1e-3), up to scale and offset (:func:`eventcap.imaging.reconstruct.agreement`): Pearson correlation, the RMS
after the affine fit, and the correlation of the image gradients (what the tracker uses). Over two regions: the
actor (pixels where the true image differs from the static background, grown by 3 px: what detector and tracker
need) and the whole image (the static background cannot be recovered from events; it reads as mid-grey).
For reference the same numbers for the blurry intensity frame (what the path with frames starts from).

``pipelines``: the same motions, seed and length through ``eventcap run`` twice: the path with frames (the default
pipeline) and the event-only path (``pipeline=events_only source.frames=false``: the same simulated events, the
frames left out, images reconstructed from events for the tracker and the detector). Reported per motion: AE (the
evaluate stage's metrics.json: Procrustes-aligned mean per-joint error on every 10th frame, mm) and MPJVE: root-
relative joints (pelvis subtracted), velocity by central differences over +-10 ms (v(t) = (J(t+10ms) - J(t-10ms)) /
20 ms) of the estimate (motion.npz) and of the ground truth (the recording's 1 kHz joints), mean over joints and
frames of |v_est - v_true| in mm/s (frames whose +-10 ms neighbours exist in both). ``events_same_source``: the
event-only pipeline on the capture with frames (see ``withheld``); ``events_blur10``: the same with the reconstructions
declared as 10 ms exposures, so the simulated detector errs as much as on the blurry frames (the tracker's share).

``withheld``: checks that ``source.frames=false`` changes nothing but the frames (same events, ground truth,
reconstructions), so the ``events_same_source`` path (pipeline=events_only on the capture with frames, which no
stage of that pipeline reads) gives the poses of ``events`` at half the simulation cost.

``picture``: one PNG — the blurry frame, the reconstruction from events alone, the true sharp image, the events of
the last 10 ms — at one frame time of a synthetic capture.
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

import numpy as np  # noqa: E402

from eventcap.imaging.reconstruct import agreement, high_pass, median_baseline, smooth_image  # noqa: E402

MOTIONS = "karate_kick,boxing_combo,javelin_throw,dance_spin,fast_wave,jumping_jack"
#: (name, cutoff rad/s, smooth px, median baseline) compared by `images`
OPTIONS = [("integrate", 0.0, 0.0, False), ("high_pass 3", 3.0, 0.0, False), ("high_pass 10", 10.0, 0.0, False),
           ("high_pass 30", 30.0, 0.0, False), ("high_pass 100", 100.0, 0.0, False),
           ("high_pass 30 +g0.7", 30.0, 0.7, False),
           ("integrate -median", 0.0, 0.0, True), ("high_pass 3 -median", 3.0, 0.0, True),
           ("high_pass 10 -median", 10.0, 0.0, True), ("high_pass 30 -median", 30.0, 0.0, True),
           ("high_pass 3 -median +g0.7", 3.0, 0.7, True)]
EPS = 1e-3


def run_one(overrides: list[str], run_dir: Path):
    """``eventcap run <overrides>`` into run_dir (pipeline + run outputs); returns (runner, result) or None."""
    from eventcap.apps.benchmark import compose_run
    from eventcap.apps.cli import run_job

    data, text = compose_run(ROOT / "conf", overrides)
    run_dir.mkdir(parents=True, exist_ok=True)
    failures: list[str] = []
    got = run_job(data, run_dir, text, failures)
    if failures:
        print(f"  problems: {'; '.join(failures)}", file=sys.stderr)
    return got


def source_recording(motion: str, args, frames: bool = True):
    """The synthetic capture (through the runner and its cache: only template + source run)."""
    from eventcap.artifacts.recording import Recording

    rd = Path(args.out) / "sources" / f"{motion}-s{args.seed}-{'frames' if frames else 'events'}"
    got = run_one([*sequence(motion, args), "pipeline=simulate", f"source.frames={str(frames).lower()}",
                   "outputs.poses=null"], rd)
    runner, result = got
    rec = runner.load_output(result, "source.recording")[None]
    assert isinstance(rec, Recording)
    return rec


def sequence(motion: str, args) -> list[str]:
    return ["source=synthetic", f"source.motion={motion}", f"source.seed={args.seed}",
            f"source.duration_s={args.duration}", f"stages.detect.seed={args.seed}", f"cache_dir={args.cache}",
            "log_level=WARNING"]


def actor_mask(rec, k: int, grow_px: int = 3) -> np.ndarray:
    import cv2

    from eventcap.imaging.render import textured_background

    bg = textured_background(rec.height, rec.width, seed=0)
    m = (np.abs(rec.ground_truth.sharp_images[k] - bg) > 1e-3).astype(np.uint8)
    return cv2.dilate(m, np.ones((2 * grow_px + 1, 2 * grow_px + 1), np.uint8)) > 0


# ----------------------------------------------------------------------------------------------------------- images
def cmd_images(args) -> dict:
    rows = {name: {"actor": [], "image": []} for name, *_ in OPTIONS + [("blurry frame",)]}
    for motion in args.motions.split(","):
        rec = source_recording(motion, args)
        fr, gt = rec.frames, rec.ground_truth
        truth = np.log(gt.sharp_images.astype(np.float64) + EPS)
        masks = [actor_mask(rec, k) for k in range(fr.t_us.size)]
        for name, cutoff, smooth, baseline in OPTIONS:
            t0 = time.perf_counter()
            R = high_pass(rec.events.events, rec.height, rec.width, fr.t_us, cutoff_rad_s=cutoff)
            if baseline:
                R = R - median_baseline(rec.events.events, rec.height, rec.width, cutoff_rad_s=cutoff)
            if smooth:
                R = np.stack([smooth_image(r, smooth) for r in R])
            dt = time.perf_counter() - t0
            for k in range(1, fr.t_us.size):  # frame 0: too few events before it to judge any method
                rows[name]["actor"].append(agreement(R[k], truth[k], masks[k]))
                rows[name]["image"].append(agreement(R[k], truth[k]))
            print(f"  {motion:<14} {name:<20} {fr.t_us.size} images from {rec.events.events.size} events in "
                  f"{dt:.2f} s")
        blurry = np.log(fr.images.astype(np.float64) + EPS)
        for k in range(1, fr.t_us.size):
            rows["blurry frame"]["actor"].append(agreement(blurry[k], truth[k], masks[k]))
            rows["blurry frame"]["image"].append(agreement(blurry[k], truth[k]))
    table = {}
    print(f"\n{'option':<22} {'actor: corr':>11} {'rmse':>6} {'grad corr':>9}   {'image: corr':>11} {'rmse':>6} "
          f"{'grad corr':>9}  (mean over {len(rows['integrate']['actor'])} images)")
    for name, r in rows.items():
        vals = {reg: {"correlation": float(np.mean([a.correlation for a in r[reg]])),
                      "rmse": float(np.mean([a.rmse for a in r[reg]])),
                      "gradient_correlation": float(np.mean([a.gradient_correlation for a in r[reg]]))}
                for reg in ("actor", "image")}
        table[name] = vals
        a, i = vals["actor"], vals["image"]
        print(f"{name:<22} {a['correlation']:>11.3f} {a['rmse']:>6.3f} {a['gradient_correlation']:>9.3f}   "
              f"{i['correlation']:>11.3f} {i['rmse']:>6.3f} {i['gradient_correlation']:>9.3f}")
    return table


# -------------------------------------------------------------------------------------------------------- pipelines
def velocities(t_us: np.ndarray, joints: np.ndarray, h_us: int = 10_000) -> tuple[np.ndarray, np.ndarray]:
    """Root-relative joint velocities (m/s) by central differences over +-h_us at the times that have both
    neighbours on the (regular) sample grid; returns (times, velocities (n, J, 3))."""
    rel = joints - joints[:, :1]
    index = {int(t): i for i, t in enumerate(t_us)}
    ts, vs = [], []
    for t in t_us:
        a, b = index.get(int(t) - h_us), index.get(int(t) + h_us)
        if a is not None and b is not None:
            ts.append(int(t))
            vs.append((rel[b] - rel[a]) / (2 * h_us * 1e-6))
    return np.asarray(ts, np.int64), np.asarray(vs)


def mpjve_mm_s(t_est, joints_est, gt) -> float:
    te, ve = velocities(np.asarray(t_est, np.int64), np.asarray(joints_est))
    tt, vt = velocities(np.asarray(gt.t_us, np.int64), np.asarray(gt.joints))
    common, ie, it = np.intersect1d(te, tt, return_indices=True)
    if common.size == 0:
        raise ValueError("no common times between the estimate and the ground truth")
    return float(1000.0 * np.linalg.norm(ve[ie] - vt[it], axis=-1).mean())


def cmd_pipelines(args) -> dict:
    from eventcap.body.kinematics import joint_positions

    # events_same_source: the source keeps its frames but no stage of pipeline=events_only reads them (the detector
    # reads reconstruct.recording): the same poses as `events`, with one simulation per sequence instead of two.
    paths = {"frames": [], "events": ["pipeline=events_only", "source.frames=false"],
             "events_same_source": ["pipeline=events_only"],
             # the detector's blur model as for the 10 ms frames (instead of sharp): isolates the tracker's share
             "events_blur10": ["pipeline=events_only", "stages.reconstruct.exposure_us=10000"]}
    out: dict = {}
    motions = args.motions.split(",")
    for motion in reversed(motions) if args.reverse else motions:
        for path in args.paths.split(","):
            rd = Path(args.out) / "runs" / f"{motion}-s{args.seed}" / path
            t0 = time.perf_counter()
            got = run_one([*sequence(motion, args), *paths[path], "outputs.video=false", *args.extra.split()], rd)
            wall = time.perf_counter() - t0
            rec = {"wall_s": wall, "AE_mm": None, "MPJVE_mm_s": None}
            if got is not None:
                runner, result = got
                m = result.metrics.get("evaluate.metrics") or {}
                rec["AE_mm"] = m.get("AE_mm")
                rec["ok"] = result.ok
                npz = rd / "motion.npz"
                if npz.exists():
                    src = runner.load_output(result, "source.recording")[None]
                    mo = np.load(npz)
                    joints = joint_positions(mo["poses"], src.template)
                    rec["MPJVE_mm_s"] = mpjve_mm_s(mo["t_us"], joints, src.ground_truth)
            out.setdefault(motion, {})[path] = rec
            print(f"  {motion:<14} {path:<7} AE {rec['AE_mm'] if rec['AE_mm'] is None else round(rec['AE_mm'], 1)}"
                  f" mm, MPJVE {rec['MPJVE_mm_s'] if rec['MPJVE_mm_s'] is None else round(rec['MPJVE_mm_s'])} mm/s"
                  f" ({wall:.0f} s)", flush=True)
    print(f"\n{'motion':<14} " + " ".join(f"{p + ' AE':>10} {p + ' MPJVE':>12}" for p in args.paths.split(",")))
    for motion, r in out.items():
        print(f"{motion:<14} " + " ".join(
            f"{_f(r.get(p, {}).get('AE_mm'), 1):>10} {_f(r.get(p, {}).get('MPJVE_mm_s'), 0):>12}"
            for p in args.paths.split(",")))
    for p in args.paths.split(","):
        ae = [r[p]["AE_mm"] for r in out.values() if r.get(p, {}).get("AE_mm") is not None]
        ve = [r[p]["MPJVE_mm_s"] for r in out.values() if r.get(p, {}).get("MPJVE_mm_s") is not None]
        if ae:
            print(f"mean {p}: AE {np.mean(ae):.1f} mm, MPJVE {np.mean(ve):.0f} mm/s over {len(ae)} motions")
    return out


def _f(x, digits):
    return "-" if x is None else f"{x:.{digits}f}"


# ---------------------------------------------------------------------------------------------------------- picture
def cmd_picture(args) -> dict:
    import cv2

    from eventcap.imaging.reconstruct import DEFAULT_CUTOFF_RAD_S, to_intensity, to_log_images
    from eventcap.imaging.viz import event_image, label, to_bgr

    rec = source_recording(args.motion, args)
    fr, gt = rec.frames, rec.ground_truth
    k = int(np.clip(args.frame, 0, fr.t_us.size - 1))
    t = int(fr.t_us[k])
    R = high_pass(rec.events.events, rec.height, rec.width, fr.t_us[k:k + 1], cutoff_rad_s=DEFAULT_CUTOFF_RAD_S)
    recon = to_intensity(to_log_images(R))[0]
    a = agreement(R[0], np.log(gt.sharp_images[k] + EPS), actor_mask(rec, k))
    panels = [(f"blurry frame {k} ({fr.exposure_us[k] / 1e3:.0f} ms)", to_bgr(fr.images[k])),
              (f"from events only (corr {a.correlation:.2f})", to_bgr(recon)),
              ("true sharp image", to_bgr(gt.sharp_images[k])),
              ("events, last 10 ms", event_image(rec.events.window(t - 10_000, t + 1), rec.height, rec.width))]
    tiles = []
    for title, img in panels:
        img = cv2.resize(img, (rec.width * 3, rec.height * 3), interpolation=cv2.INTER_NEAREST)
        label(img, title, (6, 18), 0.5)
        tiles.append(img)
    png = Path(args.png)
    png.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(png), np.concatenate(tiles, axis=1))
    print(f"wrote {png}: {args.motion} seed {args.seed}, frame {k} at t = {t / 1e3:.1f} ms; actor region: "
          f"correlation {a.correlation:.3f}, gradient correlation {a.gradient_correlation:.3f}")
    return {"png": str(png), "frame": k, "t_us": t, "correlation": a.correlation}


# --------------------------------------------------------------------------------------------------------- withheld
def cmd_withheld(args) -> dict:
    """source.frames=false withholds the frames and changes nothing else: the same events, ground truth, batches and
    images from events as the capture with frames (so `events_same_source` runs give the poses `events` would)."""
    from eventcap.imaging.reconstruct import reconstruct

    out = {}
    for motion in args.motions.split(","):
        a, b = source_recording(motion, args, frames=True), source_recording(motion, args, frames=False)
        same_events = bool(np.array_equal(a.events.events, b.events.events))
        same_truth = bool(np.array_equal(a.ground_truth.joints, b.ground_truth.joints)
                          and np.array_equal(a.ground_truth.sharp_images, b.ground_truth.sharp_images)
                          and np.array_equal(b.ground_truth.frame_t_us, a.frames.t_us))
        times = a.frames.t_us
        same_images = bool(np.array_equal(reconstruct(a.events.events, a.height, a.width, times),
                                          reconstruct(b.events.events, b.height, b.width, times)))
        out[motion] = {"events": int(a.events.events.size), "same_events": same_events, "same_truth": same_truth,
                       "same_images": same_images, "frames": (a.frames.t_us.size, b.frames)}
        print(f"  {motion}: {a.events.events.size} events; identical events {same_events}, ground truth and its "
              f"image times {same_truth}, reconstructions {same_images}; frames {a.frames.t_us.size} vs "
              f"{'none' if b.frames is None else b.frames.t_us.size}")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", choices=["images", "pipelines", "picture", "withheld"])
    ap.add_argument("--motions", default=MOTIONS)
    ap.add_argument("--motion", default="karate_kick")
    ap.add_argument("--frame", type=int, default=12)
    ap.add_argument("--duration", type=float, default=1.0, help="seconds of capture per motion")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--paths", default="frames,events",
                    help="frames | events | events_same_source | events_blur10, comma-separated")
    ap.add_argument("--reverse", action="store_true", help="motions in reverse order (two processes sharing a cache)")
    ap.add_argument("--cache", default=str(ROOT / "runs" / "cache"))
    ap.add_argument("--out", default=str(ROOT / "runs" / "bench_events_only"))
    ap.add_argument("--png", default=str(ROOT / "runs" / "bench_events_only" / "reconstruction.png"))
    ap.add_argument("--extra", default="", help="more hydra overrides for `pipelines`, space separated")
    args = ap.parse_args()
    res = {"images": cmd_images, "pipelines": cmd_pipelines, "picture": cmd_picture,
           "withheld": cmd_withheld}[args.what](args)
    dest = Path(args.out) / (f"pipelines-{args.paths.replace(',', '+')}.json" if args.what == "pipelines"
                             else f"{args.what}.json")
    dest.parent.mkdir(parents=True, exist_ok=True)
    dest.write_text(json.dumps(res, indent=1, default=str))
    print(f"wrote {dest}")


if __name__ == "__main__":
    main()
