"""How well does the real detector (stage `blazepose`) see our synthetic actors? Detection rate, 2D and 3D error.

    python benchmarks/accuracy/bench_detector.py [--motions a,b] [--duration 1] [--templates procedural,anny]
                                        [--images frames,latent,sharp] [--models full,lite] [--static]

For every motion the synthetic capture and its EDI latent images come from the normal runner and cache (a
pipeline of template -> source -> sharpen), then BlazePose runs on three kinds of images at the intensity
frames: the raw blurred frames (what *_linear sees), the EDI latent images (what the method sees) and, as a
reference no real capture has, the renderer's true sharp images. Against the ground truth:

- rate: images in which the person was found;
- 2D: pixel error of the mapped BODY_25 landmarks that are visible in the truth (in the image, not hidden by the
  body) and detected (confidence > 0), median and 90th percentile; `seen` = the fraction of visible landmarks
  detected;
- 3D: the mapped root-relative joints (17 of the 24: those with a BlazePose counterpart) after a rigid
  alignment per frame (rotation + translation), mean per joint, mm;
- ms/image: wall time of the networks per image (the machine may be busy: use farm-bench for a clean figure).
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
sys.path.insert(0, str(ROOT / "benchmarks" / "accuracy"))

import numpy as np  # noqa: E402
import zarr  # noqa: E402
from bench_solve import run  # noqa: E402
from eventcap.imaging import edi  # noqa: E402
from eventcap.artifacts.recording import Recording  # noqa: E402
from eventcap.artifacts.tracking import LatentFrames  # noqa: E402
from eventcap.body.skeleton import JOINT_NAMES, LANDMARK_NAMES  # noqa: E402
from eventcap.analysis.metrics import procrustes_align  # noqa: E402
from eventcap_detect import blazepose as bp  # noqa: E402
from eventcap_detect.simulated import frame_truth  # noqa: E402

MOTIONS = "karate_kick,boxing_combo,javelin_throw,dance_spin,fast_wave,jumping_jack"


def capture(motion: str, template: str, args) -> tuple[Recording, LatentFrames]:
    """The recording and its EDI latent images, through the runner and cache."""
    rd = Path(args.out) / f"{motion}-s{args.seed}-{template}"
    run([f"template={template}", f"source.motion={motion}", f"source.duration_s={args.duration}",
         f"source.seed={args.seed}", "pipeline=simulate", "+pipeline.nodes.sharpen={inputs:{recording:source.recording}}",
         f"cache_dir={args.cache}", "export=[source.recording,sharpen.latent]", "log_level=WARNING",
         *args.extra.split()], rd)
    rec = Recording.from_zarr(zarr.open_group(str(rd / "source.recording.zarr"), mode="r"))
    latent = LatentFrames.from_zarr(zarr.open_group(str(rd / "sharpen.latent.zarr"), mode="r"))
    return rec, latent


def score(seq: bp.SequenceResult, truth, camera_R: np.ndarray) -> dict:
    """Rate, 2D errors (px) of visible detected landmarks, 3D error (mm) of the mapped joints."""
    w2 = bp.mapping_matrix(bp.LANDMARK_FROM_BLAZEPOSE, LANDMARK_NAMES)
    w3 = bp.mapping_matrix(bp.JOINT_FROM_BLAZEPOSE, JOINT_NAMES)
    mapped_lm = w2.any(axis=1)
    mapped_j = w3.any(axis=1)
    err2, seen, visible, err3 = [], 0, 0, []
    for i, pose in enumerate(seq.poses):
        vis = truth.visible[i] & mapped_lm
        visible += int(vis.sum())
        if pose is None:
            continue
        xy, conf = bp.mapped(w2, pose.xy, pose.visibility * pose.presence * pose.flag)
        ok = vis & (conf > 0)
        seen += int(ok.sum())
        err2.append(np.linalg.norm(xy[ok] - truth.keypoints_px[i, ok], axis=1))
        j, _ = bp.mapped(w3, pose.world, pose.presence)
        j = (j - j[0]) @ camera_R
        a = procrustes_align(j[mapped_j], truth.joints_rel_m[i, mapped_j])
        err3.append(1000 * np.linalg.norm(a - truth.joints_rel_m[i, mapped_j], axis=1).mean())
    e2 = np.concatenate(err2) if err2 else np.zeros(0)
    n = len(seq.poses)
    found = sum(p is not None for p in seq.poses)
    return {"n_images": n, "found": found, "rate": found / max(n, 1),
            "seen": seen / max(visible, 1), "px_median": float(np.median(e2)) if e2.size else None,
            "px_p90": float(np.percentile(e2, 90)) if e2.size else None,
            "mm_3d": float(np.mean(err3)) if err3 else None, "ms_per_image": 1000 * seq.seconds / max(n, 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--motions", default=MOTIONS)
    ap.add_argument("--duration", type=float, default=1.0, help="seconds of capture per motion")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--templates", default="procedural")
    ap.add_argument("--images", default="frames,latent,sharp")
    ap.add_argument("--models", default="full")
    ap.add_argument("--static", action="store_true", help="also without tracking (the detector on every image)")
    ap.add_argument("--cache", default=str(ROOT / "runs" / "bench-cache"))
    ap.add_argument("--out", default=str(ROOT / "runs" / "bench_detector"))
    ap.add_argument("--extra", default="", help="more hydra overrides, space separated")
    args = ap.parse_args()
    rows = []
    header = (f"{'template':<11} {'motion':<14} {'images':<7} {'model':<5} {'track':<6} {'found':>7} {'seen':>6} "
              f"{'px med':>7} {'px p90':>7} {'3D mm':>6} {'ms/img':>7}")
    print(header)
    nets = {m: bp.BlazePose(m) for m in args.models.split(",")}
    for template in args.templates.split(","):
        for motion in args.motions.split(","):
            t0 = time.perf_counter()
            rec, latent = capture(motion, template, args)
            truth = frame_truth(rec)
            sources = {"frames": rec.frames.images,
                       "latent": [edi.to_linear(L, latent.eps) for L in latent.log_images],
                       "sharp": rec.ground_truth.sharp_images}
            for kind in args.images.split(","):
                for model, net in nets.items():
                    for track in ([True, False] if args.static else [True]):
                        seq = bp.detect_sequence(net, sources[kind], rec.frames.t_us, track=track,
                                                 events=rec.events.events)
                        r = {"template": template, "motion": motion, "images": kind, "model": model,
                             "track": track, **score(seq, truth, rec.camera.R)}
                        rows.append(r)
                        print(f"{template:<11} {motion:<14} {kind:<7} {model:<5} {str(track):<6} "
                              f"{r['found']:>3}/{r['n_images']:<3} {r['seen']:>6.2f} {r['px_median'] or 0:>7.2f} "
                              f"{r['px_p90'] or 0:>7.2f} {r['mm_3d'] or 0:>6.1f} {r['ms_per_image']:>7.1f}",
                              flush=True)
            print(f"  ({motion}: {time.perf_counter() - t0:.0f} s with the capture)", file=sys.stderr)
    print("\nmeans over motions")
    keys = sorted({(r["template"], r["images"], r["model"], r["track"]) for r in rows},
                  key=lambda k: (k[0], k[1], k[2], not k[3]))
    for k in keys:
        sel = [r for r in rows if (r["template"], r["images"], r["model"], r["track"]) == k]
        found = sum(r["found"] for r in sel)
        n = sum(r["n_images"] for r in sel)

        def mean(f, sel=sel):
            v = [r[f] for r in sel if r[f] is not None]
            return float(np.mean(v)) if v else float("nan")

        print(f"{k[0]:<11} {'(all)':<14} {k[1]:<7} {k[2]:<5} {str(k[3]):<6} {found:>3}/{n:<3} {mean('seen'):>6.2f} "
              f"{mean('px_median'):>7.2f} {mean('px_p90'):>7.2f} {mean('mm_3d'):>6.1f} {mean('ms_per_image'):>7.1f}")
    Path(args.out).mkdir(parents=True, exist_ok=True)
    (Path(args.out) / "detector.json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
