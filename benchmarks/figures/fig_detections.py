"""A picture of the real detector at work: BlazePose's detections over a raw (blurred) intensity frame and over
its EDI latent image, against the ground-truth projections.

    python benchmarks/figures/fig_detections.py [--template anny] [--motion karate_kick] [--duration 1] [--frame auto]

The capture and its latent images come from the runner and cache (as in bench_detector.py). The frame shown is,
with ``--frame auto``, the one whose landmarks streak the most during the exposure (the blurriest). Panels, at
``--scale`` image pixels per sensor pixel:

- left: the raw frame; middle: its EDI latent image; right (`--sharp`, default on): the renderer's true sharp
  image, which no real capture has;
- green rings: ground-truth BODY_25 landmarks visible in the image; red: the detector's mapped BODY_25 landmarks
  and skeleton (confidence > 0.5 solid, lower thin); the title of each panel gives the median pixel error.

Writes runs/figures/detections_<template>_<motion>[_<tag>].png and prints each panel's errors.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "plugins"))
sys.path.insert(0, str(ROOT / "benchmarks" / "accuracy"))

import cv2  # noqa: E402
import numpy as np  # noqa: E402
from bench_detector import capture  # noqa: E402
from eventcap.imaging import edi  # noqa: E402
from eventcap.body.skeleton import LANDMARK_INDEX, LANDMARK_NAMES  # noqa: E402
from eventcap_detect import blazepose as bp  # noqa: E402
from eventcap_detect.simulated import frame_truth  # noqa: E402

# BODY_25 limbs drawn between landmarks
LIMBS = [("nose", "neck"), ("neck", "r_shoulder"), ("r_shoulder", "r_elbow"), ("r_elbow", "r_wrist"),
         ("neck", "l_shoulder"), ("l_shoulder", "l_elbow"), ("l_elbow", "l_wrist"), ("neck", "mid_hip"),
         ("mid_hip", "r_hip"), ("r_hip", "r_knee"), ("r_knee", "r_ankle"), ("mid_hip", "l_hip"),
         ("l_hip", "l_knee"), ("l_knee", "l_ankle"), ("r_ankle", "r_heel"), ("r_ankle", "r_big_toe"),
         ("l_ankle", "l_heel"), ("l_ankle", "l_big_toe"), ("nose", "r_eye"), ("nose", "l_eye"),
         ("r_eye", "r_ear"), ("l_eye", "l_ear")]


def panel(image: np.ndarray, xy: np.ndarray, conf: np.ndarray, truth_xy: np.ndarray, visible: np.ndarray,
          scale: int, title: str, box: tuple[int, int, int, int]) -> np.ndarray:
    """One panel: the grey image cropped to ``box`` (x0, y0, x1, y1) and enlarged, truth rings (green),
    detections and limbs (red)."""
    x0, y0, x1, y1 = box
    g = np.round(np.clip(image[y0:y1, x0:x1], 0, 1) * 255).astype(np.uint8)
    xy, truth_xy = xy - (x0, y0), truth_xy - (x0, y0)
    im = cv2.cvtColor(cv2.resize(g, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST), cv2.COLOR_GRAY2BGR)

    def p(v):
        return int(round((v[0] + 0.5) * scale - 0.5)), int(round((v[1] + 0.5) * scale - 0.5))

    for i in np.flatnonzero(visible):
        cv2.circle(im, p(truth_xy[i]), 2 * scale, (0, 200, 0), 1, cv2.LINE_AA)
    for a, b in LIMBS:
        ia, ib = LANDMARK_INDEX[a], LANDMARK_INDEX[b]
        if conf[ia] > 0 and conf[ib] > 0:
            strong = min(conf[ia], conf[ib]) > 0.5
            cv2.line(im, p(xy[ia]), p(xy[ib]), (40, 40, 230), 2 if strong else 1, cv2.LINE_AA)
    for i in np.flatnonzero(conf > 0):
        cv2.circle(im, p(xy[i]), max(2, scale // 2), (0, 0, 255), -1, cv2.LINE_AA)
    bar = np.full((28, im.shape[1], 3), 255, np.uint8)
    cv2.putText(bar, title, (6, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    return np.vstack([bar, im])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--template", default="anny")
    ap.add_argument("--motion", default="karate_kick")
    ap.add_argument("--duration", type=float, default=1.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--frame", default="auto", help="index of the intensity frame, or 'auto' (the blurriest)")
    ap.add_argument("--scale", type=int, default=5)
    ap.add_argument("--margin", type=int, default=20, help="pixels around the actor's landmarks (crop)")
    ap.add_argument("--no-sharp", dest="sharp", action="store_false")
    ap.add_argument("--cache", default=str(ROOT / "runs" / "bench-cache"))
    ap.add_argument("--out", default=str(ROOT / "runs" / "bench_detector"))
    ap.add_argument("--extra", default="", help="more hydra overrides of the capture, e.g. source.exposure_us=30000")
    ap.add_argument("--tag", default="", help="appended to the picture's name")
    args = ap.parse_args()

    rec, latent = capture(args.motion, args.template, args)
    truth = frame_truth(rec)
    streak = np.where(truth.visible, truth.streak_px, 0.0).max(axis=1)
    i = int(np.argmax(streak)) if args.frame == "auto" else int(args.frame)
    images = {"raw frame": rec.frames.images,
              "EDI latent": [edi.to_linear(L, latent.eps) for L in latent.log_images]}
    if args.sharp:
        images["true sharp (ref.)"] = rec.ground_truth.sharp_images
    net = bp.BlazePose("full")
    h, w = rec.frames.images[0].shape
    pts = truth.keypoints_px[i][np.isfinite(truth.keypoints_px[i]).all(axis=1)]
    lo, hi = np.floor(pts.min(axis=0)) - args.margin, np.ceil(pts.max(axis=0)) + args.margin
    box = (max(0, int(lo[0])), max(0, int(lo[1])), min(w, int(hi[0])), min(h, int(hi[1])))
    w2 = bp.mapping_matrix(bp.LANDMARK_FROM_BLAZEPOSE, LANDMARK_NAMES)
    panels = []
    t_ms = (int(rec.frames.t_us[i]) - int(rec.frames.t_us[0])) / 1000
    print(f"{args.template} {args.motion} frame {i} (t = {t_ms:.0f} ms), exposure {rec.frames.exposure_us[i]} us, "
          f"longest landmark streak {streak[i]:.1f} px")
    for name, seq_images in images.items():
        # the same tracking as the stage: the sequence up to this frame, so the ROI comes from the frames before
        seq = bp.detect_sequence(net, seq_images[: i + 1], rec.frames.t_us[: i + 1], events=rec.events.events)
        pose = seq.poses[i]
        vis = truth.visible[i] & w2.any(axis=1)
        if pose is None:
            xy, conf, title = np.zeros((len(LANDMARK_NAMES), 2)), np.zeros(len(LANDMARK_NAMES)), f"{name}: no person"
        else:
            xy, conf = bp.mapped(w2, pose.xy, pose.visibility * pose.presence * pose.flag)
            ok = vis & (conf > 0)
            err = np.linalg.norm(xy[ok] - truth.keypoints_px[i, ok], axis=1)
            title = f"{name}: med {np.median(err):.1f}, max {err.max():.1f} px"
            worst = LANDMARK_NAMES[int(np.flatnonzero(ok)[np.argmax(err)])]
            print(f"  {name}: {ok.sum()} landmarks, median {np.median(err):.2f} px, p90 "
                  f"{np.percentile(err, 90):.2f} px, worst {worst} {err.max():.1f} px")
        panels.append(panel(np.asarray(seq_images[i]), xy, conf, truth.keypoints_px[i], vis, args.scale, title, box))
    tag = f"_{args.tag}" if args.tag else ""
    out = ROOT / "runs" / "figures" / f"detections_{args.template}_{args.motion}{tag}.png"
    out.parent.mkdir(parents=True, exist_ok=True)
    gap = np.full((panels[0].shape[0], 6, 3), 255, np.uint8)
    row = [panels[0]]
    for p in panels[1:]:
        row += [gap, p]
    cv2.imwrite(str(out), np.hstack(row))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
