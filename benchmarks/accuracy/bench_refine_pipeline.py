"""Silhouette refinement (issue 6) in the full pipeline: refine vs the batch solve alone, against ground truth.

    python benchmarks/accuracy/bench_refine_pipeline.py [--motions a,b] [--duration 0.5] [--extra "source.speed=2"]

Runs the default pipeline (synthetic capture -> EDI -> EKLT -> slicing -> simulated detector -> batch solve ->
refine) per motion through the normal runner (cached: a rerun recomputes nothing) and compares, over every 10th
tracking frame: AE (mean per-joint error after per-frame Procrustes alignment, mm), the unaligned mean joint error
(mm), and the IoU of the projected template silhouette with the ground-truth silhouette. Refinement time per
batch comes from the cache manifests (elapsed_s of each committed batch, inputs loading included). For the first
motion, a before/after picture of one frame is written: the silhouette outline of the solve (yellow) and of the
refinement (green) over the latent image with the events of +-2 ms (red/blue), ground truth in white.
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

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import zarr  # noqa: E402
from bench_solve import run  # noqa: E402

from eventcap.artifacts.pose import PoseSequence  # noqa: E402
from eventcap.artifacts.recording import Recording  # noqa: E402
from eventcap.artifacts.tracking import LatentFrames  # noqa: E402
from eventcap.body.kinematics import joint_positions, skin  # noqa: E402
from eventcap.core.cache import Cache  # noqa: E402
from eventcap.analysis.metrics import mean_joint_error, pose_at  # noqa: E402
from eventcap.imaging.render import rasterize  # noqa: E402
from eventcap.imaging.viz import event_image, to_bgr  # noqa: E402


def masks(rec: Recording, poses: np.ndarray) -> np.ndarray:
    verts = skin(poses, rec.template)
    return np.stack([rasterize(rec.camera, v, rec.template.faces)[1] >= 0 for v in verts])


def iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    inter = (a & b).sum(axis=(1, 2))
    union = (a | b).sum(axis=(1, 2))
    return inter / np.maximum(union, 1)


def load_batches(folder: Path) -> list[PoseSequence]:
    return [PoseSequence.from_zarr(zarr.open_group(str(f), mode="r")) for f in sorted(folder.glob("batch*.zarr"))]


def picture(rec, latent, solve, refine, k: int, path: Path, scale: int = 5) -> None:
    """Before/after overlay at tracking frame k of a batch (see module doc), cropped around the actor."""
    t = int(solve.t_us[k])
    i = int(np.argmin(np.abs(latent.t_us - t)))
    img = np.exp(latent.log_images[i]) - latent.eps
    ev = rec.events.window(t - 2000, t + 2000)
    base = event_image(ev, rec.height, rec.width, background=to_bgr(np.clip(img, 0, 1)))
    truth = pose_at(rec.ground_truth, np.array([t]))
    sets = ((truth, (255, 255, 255)), (solve.poses[k:k + 1], (0, 220, 255)), (refine.poses[k:k + 1], (0, 200, 0)))
    ms = [masks(rec, poses)[0] for poses, _ in sets]
    ys, xs = np.nonzero(np.logical_or.reduce(ms))
    y0, y1 = max(ys.min() - 8, 0), min(ys.max() + 9, rec.height)
    x0, x1 = max(xs.min() - 8, 0), min(xs.max() + 9, rec.width)
    base = cv2.resize(base[y0:y1, x0:x1], None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    for m, (_, colour) in zip(ms, sets):
        m = cv2.resize(m[y0:y1, x0:x1].astype(np.uint8), None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
        contours, _ = cv2.findContours(m, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(base, contours, -1, colour, 1)
    for j, (text, colour) in enumerate(((f"t={t / 1000:.0f} ms", (255, 255, 255)), ("truth", (255, 255, 255)),
                                        ("solve", (0, 220, 255)), ("refine", (0, 200, 0)))):
        cv2.putText(base, text, (4, 14 + 14 * j), cv2.FONT_HERSHEY_SIMPLEX, 0.45, colour, 1)
    cv2.imwrite(str(path), base)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--motions", default="karate_kick,boxing_combo,javelin_throw,dance_spin,fast_wave,jumping_jack")
    ap.add_argument("--duration", type=float, default=0.5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cache", default=str(ROOT / "runs" / "bench-cache"))
    ap.add_argument("--out", default=str(ROOT / "runs" / "bench_refine_pipeline"))
    ap.add_argument("--extra", default="", help="more hydra overrides, space separated")
    args = ap.parse_args()
    out = Path(args.out)
    cache = Cache(args.cache)
    rows = []
    print(f"{'motion':<14} {'AE solve':>8} {'AE refine':>9} {'raw solve':>9} {'raw refine':>10} {'IoU solve':>9} "
          f"{'IoU refine':>10} {'refine s/batch':>14}")
    for n, motion in enumerate(args.motions.split(",")):
        rd = out / f"{motion}-s{args.seed}"
        t0 = time.perf_counter()
        run([f"source.motion={motion}", f"source.duration_s={args.duration}", f"source.seed={args.seed}",
             f"cache_dir={args.cache}", "export=[source.recording,sharpen.latent,solve.poses,refine.poses]",
             "log_level=WARNING", *args.extra.split()], rd)
        rec = Recording.from_zarr(zarr.open_group(str(rd / "source.recording.zarr"), mode="r"))
        solve, refine = load_batches(rd / "solve.poses"), load_batches(rd / "refine.poses")
        keys = json.loads((rd / "run.json").read_text())["nodes"]["refine"]["keys"]
        secs = [cache.lookup("silhouette", k).manifest.get("elapsed_s", np.nan) for k in keys]
        res = {"solve": ([], [], []), "refine": ([], [], [])}
        for s, r in zip(solve, refine):
            idx = np.arange(0, s.t_us.size, 10)
            truth_p = pose_at(rec.ground_truth, s.t_us[idx])
            tj = joint_positions(truth_p, rec.template.rest_joints)
            tm = masks(rec, truth_p)
            for name, ps in (("solve", s), ("refine", r)):
                pj = joint_positions(ps.poses[idx], rec.template.rest_joints)
                res[name][0].append(mean_joint_error(pj, tj))
                res[name][1].append(mean_joint_error(pj, tj, align=False))
                res[name][2].append(iou(masks(rec, ps.poses[idx]), tm))
        m = {f"{k}_{q}": float(np.concatenate(v[j]).mean() * (1000 if j < 2 else 1))
             for k, v in res.items() for j, q in enumerate(("ae_mm", "raw_mm", "iou"))}
        row = {"motion": motion, **m, "refine_s_median": float(np.median(secs)), "wall_s": time.perf_counter() - t0}
        rows.append(row)
        print(f"{motion:<14} {m['solve_ae_mm']:8.1f} {m['refine_ae_mm']:9.1f} {m['solve_raw_mm']:9.1f} "
              f"{m['refine_raw_mm']:10.1f} {m['solve_iou']:9.3f} {m['refine_iou']:10.3f} "
              f"{row['refine_s_median']:14.2f}", flush=True)
        if n == 0:
            latent = LatentFrames.from_zarr(zarr.open_group(str(rd / "sharpen.latent.zarr"), mode="r"))
            b = len(solve) // 2
            picture(rec, latent, solve[b], refine[b], 20, out / f"refine_{motion}.png")
            print(f"  picture: {out / f'refine_{motion}.png'}")
    print("\nmean: AE %.1f -> %.1f mm, unaligned %.1f -> %.1f mm, IoU %.3f -> %.3f, refine %.2f s/batch (median)" % (
        np.mean([r["solve_ae_mm"] for r in rows]), np.mean([r["refine_ae_mm"] for r in rows]),
        np.mean([r["solve_raw_mm"] for r in rows]), np.mean([r["refine_raw_mm"] for r in rows]),
        np.mean([r["solve_iou"] for r in rows]), np.mean([r["refine_iou"] for r in rows]),
        np.median([r["refine_s_median"] for r in rows])))
    out.mkdir(parents=True, exist_ok=True)
    (out / f"results-s{args.seed}.json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
