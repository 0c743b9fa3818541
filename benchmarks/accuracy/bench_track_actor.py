"""Feature tracking on the synthetic actor against ground truth: EKLT (forward, backward, stitched) vs. KLT on
EDI latent images, per 40 ms batch, on features lying on the actor.

    python benchmarks/accuracy/bench_track_actor.py [--motions ...] [--duration 0.5]

The truth of a feature is the surface point under its detection (eventcap.analysis.metrics.feature_ground_truth). Errors are
over all samples of tracks on the actor; survival = fraction of actor tracks that reach the batch end.

The last table is a paired check of stitching: every stitched track against the forward track it starts as
(same corner, same start), over the same batches, split by where the corner lies at its detection: *interior*
(at least ``--contour-px`` from any occluding edge of the true render: silhouette or self-occlusion) or *contour*.
On a contour the "point" a corner follows is where the edge is, not a point of the surface, so neither direction
tracks the surface point the truth is defined by.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "plugins"))

import numpy as np  # noqa: E402

from eventcap.artifacts.recording import EventStream, GroundTruth, Recording  # noqa: E402
from eventcap.body.procedural import procedural_template  # noqa: E402
from eventcap.camera import davis240c_default  # noqa: E402
import cv2  # noqa: E402

from eventcap.body.kinematics import skin  # noqa: E402
from eventcap.analysis.metrics import pose_at, track_errors  # noqa: E402
from eventcap.imaging.render import rasterize, textured_background  # noqa: E402
from eventcap.sim.capture import CaptureConfig, simulate_synthetic  # noqa: E402
from eventcap.imaging import edi  # noqa: E402
from eventcap_track import eklt, klt  # noqa: E402


def contour_distance(rec, t_us: int, jump_m: float = 0.1) -> np.ndarray:
    """(H, W) distance in px to the nearest occluding edge (depth jump > jump_m, or surface/background) at t_us."""
    verts = skin(pose_at(rec.ground_truth, np.array([t_us]))[0], rec.template)
    depth, _, _ = rasterize(rec.camera, verts, rec.template.faces)
    d = np.where(np.isfinite(depth), depth, 100.0)
    edge = np.zeros(d.shape, bool)
    jx = np.abs(np.diff(d, axis=1)) > jump_m
    jy = np.abs(np.diff(d, axis=0)) > jump_m
    edge[:, :-1] |= jx
    edge[:, 1:] |= jx
    edge[:-1] |= jy
    edge[1:] |= jy
    return cv2.distanceTransform((~edge).astype(np.uint8), cv2.DIST_L2, 5)


def per_track_errors(rec, ft):
    """Per-sample errors and per-track (on_actor, start time, start xy) of FeatureTracks, tracks referenced at their
    detection sample (first for forward/stitched, last for backward)."""
    off = ft.offsets
    ref = np.where(np.isin(ft.kind, (1, 3)), off[:-1], off[1:] - 1)
    xy = np.stack([ft.x, ft.y], axis=1)
    err, on = track_errors(rec, ft.track_id, ft.t_us, xy, ft.t_us[ref], xy[ref])
    return err, on, ft.t_us[ref], xy[ref]


def paired_stitch(rec, fwd, sti, contour_px: float) -> dict[str, tuple[list, list]]:
    """Samples of stitched tracks and of the forward tracks they start as, by interior/contour start."""
    out = {"interior": ([], []), "contour": ([], [])}
    if fwd.t_us.size == 0 or sti.t_us.size == 0:
        return out
    ef, onf, tf, xyf = per_track_errors(rec, fwd)
    es, ons, ts, xys = per_track_errors(rec, sti)
    dist = contour_distance(rec, int(ts.min())) if ts.size else None
    for k in np.flatnonzero((sti.kind == 3) & ons):
        same = np.flatnonzero(onf & (tf == ts[k]) & (np.abs(xyf - xys[k]).max(axis=1) < 1e-6))
        if same.size != 1:
            continue
        x, y = np.clip(np.round(xys[k]).astype(int), 0, [dist.shape[1] - 1, dist.shape[0] - 1])
        where = "interior" if dist[y, x] >= contour_px else "contour"
        out[where][0].append(ef[fwd.track_id == same[0]])
        out[where][1].append(es[sti.track_id == k])
    return out


def score(rec, ft):
    """(errors of samples on actor tracks, n actor tracks, survival)."""
    if ft.t_us.size == 0:
        return np.zeros(0), 0, float("nan")
    err, on, _, _ = per_track_errors(rec, ft)
    on_s = on[ft.track_id]
    surv = float(np.mean(np.asarray(ft.survived)[on])) if on.any() else float("nan")
    return err[on_s], int(on.sum()), surv


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--motions", default="karate_kick,boxing_combo,javelin_throw,dance_spin,fast_wave,jumping_jack")
    ap.add_argument("--duration", type=float, default=0.5)
    ap.add_argument("--speed", type=float, default=1.0)
    ap.add_argument("--contour-px", type=float, default=2.0)
    args = ap.parse_args()
    tpl = procedural_template(seed=0)
    cam = davis240c_default(eye=(0.0, 1.0, 3.0), target=(0.0, 1.0, 0.0))
    bg = textured_background(cam.height, cam.width, seed=0)
    methods = ("forward", "backward", "stitched", "klt_latent")
    totals = {m: [] for m in methods}
    pairs = {"interior": ([], []), "contour": ([], [])}
    times = {m: [] for m in methods}
    print(f"{'motion':<14} {'method':<11} {'tracks':>6} {'median px':>9} {'p90 px':>7} {'survival':>8} {'s/batch':>7}")
    for name in args.motions.split(","):
        cap = simulate_synthetic(tpl, cam, bg, CaptureConfig(motions=((name, args.duration),), speed=args.speed,
                                                            n_track_points=10))
        h, w = cam.height, cam.width
        rec = Recording(events=EventStream(events=cap.events, width=w, height=h), camera=cam, template=tpl,
                        ground_truth=GroundTruth(t_us=cap.gt_t_us, poses=cap.gt_poses, joints=cap.gt_joints,
                                                 landmarks=cap.gt_landmarks, frame_poses=cap.frame_poses,
                                                 frame_joints=cap.frame_joints, height=h, width=w))
        imgs = cap.frame_images.astype(np.float32) / 255.0
        C = edi.estimate_contrast(imgs, cap.frame_t_us, cap.frame_exposure_us, cap.events).c
        L = edi.sharpen_frames(imgs, cap.frame_t_us, cap.frame_exposure_us, cap.events, C)
        cfg = eklt.EkltConfig(contrast_threshold=C)
        per = {m: ([], 0, []) for m in methods}
        for k in range(len(imgs) - 1):
            t0, t1 = int(cap.frame_t_us[k]), int(cap.frame_t_us[k + 1])
            ev = cap.events[(cap.events["t"] >= t0) & (cap.events["t"] <= t1)]
            runs = {}
            s = time.perf_counter()
            runs["forward"] = eklt.track(L[k], ev, t0, t1, +1, cfg)
            times["forward"].append(time.perf_counter() - s)
            s = time.perf_counter()
            runs["backward"] = eklt.track(L[k + 1], ev, t0, t1, -1, cfg)
            times["backward"].append(time.perf_counter() - s)
            s = time.perf_counter()
            runs["stitched"] = eklt.track_bidirectional(L[k], L[k + 1], ev, t0, t1, config=cfg)
            times["stitched"].append(time.perf_counter() - s)
            s = time.perf_counter()
            ts = np.arange(t0, t1 + 1, 1000, dtype=np.int64)
            lat = edi.latent_log_sequence(L[k], t0, ts, ev, C)
            runs["klt_latent"] = klt.klt_latent(lat, t0, t1, step_us=1000, features=eklt.detect_features(L[k]))
            times["klt_latent"].append(time.perf_counter() - s)
            for where, (f_err, s_err) in paired_stitch(rec, runs["forward"], runs["stitched"],
                                                       args.contour_px).items():
                pairs[where][0].extend(f_err)
                pairs[where][1].extend(s_err)
            for m, ft in runs.items():
                e, n, sv = score(rec, ft)
                per[m][0].append(e)
                per[m] = (per[m][0], per[m][1] + n, per[m][2] + [sv])
        for m in methods:
            e = np.concatenate(per[m][0]) if per[m][0] else np.zeros(0)
            totals[m].append(e)
            med, p90 = (np.median(e), np.percentile(e, 90)) if e.size else (np.nan, np.nan)
            print(f"{name:<14} {m:<11} {per[m][1]:6d} {med:9.2f} {p90:7.2f} {np.nanmean(per[m][2]):8.2f} "
                  f"{np.mean(times[m][-(len(imgs) - 1):]):7.2f}", flush=True)
    print("all motions:")
    for m in methods:
        e = np.concatenate(totals[m])
        print(f"  {m:<11} median {np.median(e):.2f} px, p90 {np.percentile(e, 90):.2f} px over {e.size} samples; "
              f"{np.mean(times[m]):.2f} s per batch")
    print(f"paired: stitched tracks against the forward tracks they start as (corner >= {args.contour_px:g} px from "
          f"an occluding edge = interior)")
    for where, (f_err, s_err) in pairs.items():
        if not f_err:
            print(f"  {where:<8} no stitched tracks")
            continue
        f, st = np.concatenate(f_err), np.concatenate(s_err)
        print(f"  {where:<8} {len(f_err):4d} tracks: forward median {np.median(f):.2f} / p90 {np.percentile(f, 90):.2f} px,"
              f" stitched median {np.median(st):.2f} / p90 {np.percentile(st, 90):.2f} px")


if __name__ == "__main__":
    main()
