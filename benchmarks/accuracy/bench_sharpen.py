"""EDI on the synthetic capture: PSNR of sharpened vs. blurry frames against the true sharp image, estimated C.

    python benchmarks/accuracy/bench_sharpen.py [--duration 0.5] [--motions ...]

PSNR is computed in linear intensity on the whole image and on the moving region (pixels with at least one event
during the frame's exposure: where blur can be), for every frame of the capture. The last columns repeat the
moving-region PSNR on the *fast* frames only: those where some ground-truth surface point of the actor draws an
image path of at least ``--fast-px`` pixels during the exposure (the frames that are blurred at all), with the
moving region taken as pixels with at least two events (isolated background-activity events mark no motion).
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

from eventcap.body.procedural import procedural_template  # noqa: E402
from eventcap.camera import davis240c_default  # noqa: E402
from eventcap.imaging.render import textured_background  # noqa: E402
from eventcap.sim.capture import CaptureConfig, simulate_synthetic  # noqa: E402
from eventcap.sim.events import SensorConfig  # noqa: E402
from eventcap.sim.frames import FrameConfig  # noqa: E402
from eventcap.imaging import edi  # noqa: E402


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    d = (a - b) if mask is None else (a - b)[mask]
    return float(10 * np.log10(1.0 / max(np.mean(d**2), 1e-12)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--motions", default="karate_kick,boxing_combo,javelin_throw,dance_spin,fast_wave,jumping_jack")
    ap.add_argument("--duration", type=float, default=0.5)
    ap.add_argument("--speed", type=float, default=1.0)
    ap.add_argument("--exposure-us", type=int, default=10_000)
    ap.add_argument("--supersample", type=int, default=3)
    ap.add_argument("--fast-px", type=float, default=3.0, help="a frame is fast when the actor's largest blur "
                    "streak during its exposure is at least this long (px)")
    args = ap.parse_args()
    tpl = procedural_template(seed=0)
    cam = davis240c_default(eye=(0.0, 1.0, 3.0), target=(0.0, 1.0, 0.0))
    bg = textured_background(cam.height, cam.width, seed=0)
    c_true = SensorConfig().threshold_pos
    print(f"{'motion':<14} {'frames':>6} {'blurry dB':>9} {'EDI dB':>7} {'gain':>6} {'moving blurry':>13} "
          f"{'moving EDI':>10} {'gain':>6} {'C est':>6} {'C err':>6} {'ms/frame':>8} {'fast':>5} {'fast blurry':>11} "
          f"{'fast EDI':>8} {'gain':>6}")
    gains, actor_gains, c_errs, fast_gains = [], [], [], []
    for name in args.motions.split(","):
        cfg = CaptureConfig(motions=((name, args.duration),), speed=args.speed, supersample=args.supersample,
                            frames=FrameConfig(exposure_us=args.exposure_us))
        cap = simulate_synthetic(tpl, cam, bg, cfg)
        imgs = cap.frame_images.astype(np.float32) / 255.0
        est = edi.estimate_contrast(imgs, cap.frame_t_us, cap.frame_exposure_us, cap.events)
        t = time.perf_counter()
        L = edi.sharpen_frames(imgs, cap.frame_t_us, cap.frame_exposure_us, cap.events, est.c)
        ms = 1000 * (time.perf_counter() - t) / len(imgs)
        sharp = np.clip(edi.to_linear(L), 0, 1)
        rows, fast_rows = [], []
        for k in range(len(imgs)):
            t = cap.frame_t_us[k]
            ev = cap.events[(cap.events["t"] >= t - args.exposure_us // 2) & (cap.events["t"] < t + args.exposure_us // 2)]
            counts = np.zeros(imgs[k].shape, np.int32)
            np.add.at(counts, (ev["y"], ev["x"]), 1)
            actor = counts >= 1
            rows.append((psnr(imgs[k], cap.sharp_images[k]), psnr(sharp[k], cap.sharp_images[k]),
                         psnr(imgs[k], cap.sharp_images[k], actor), psnr(sharp[k], cap.sharp_images[k], actor)))
            if streak_px(cap, t, args.exposure_us) >= args.fast_px:
                moving = counts >= 2
                fast_rows.append((psnr(imgs[k], cap.sharp_images[k], moving),
                                  psnr(sharp[k], cap.sharp_images[k], moving)))
        b, s, ba, sa = np.mean(rows, axis=0)
        fb, fs = np.mean(fast_rows, axis=0) if fast_rows else (np.nan, np.nan)
        if fast_rows:
            fast_gains.append(fs - fb)
        gains.append(s - b)
        actor_gains.append(sa - ba)
        c_errs.append(est.c / c_true - 1)
        print(f"{name:<14} {len(imgs):6d} {b:9.2f} {s:7.2f} {s - b:+6.2f} {ba:13.2f} {sa:10.2f} {sa - ba:+6.2f} "
              f"{est.c:6.3f} {100 * (est.c / c_true - 1):+5.0f}% {ms:8.1f} {len(fast_rows):5d} {fb:11.2f} {fs:8.2f} "
              f"{fs - fb:+6.2f}", flush=True)
    print(f"mean gain: whole image {np.mean(gains):+.2f} dB, moving region {np.mean(actor_gains):+.2f} dB, "
          f"fast frames {np.mean(fast_gains) if fast_gains else np.nan:+.2f} dB over {len(fast_gains)} motion(s); "
          f"C error: mean {100 * np.mean(np.abs(c_errs)):.0f}%, max {100 * np.max(np.abs(c_errs)):.0f}%")


def streak_px(cap, t_us: int, exposure_us: int) -> float:
    """Longest image path (px) any visible ground-truth surface point draws during the exposure centred at t_us."""
    sel = (cap.gt_t_us >= t_us - exposure_us // 2) & (cap.gt_t_us <= t_us + exposure_us // 2)
    px, vis = cap.track_px[sel], cap.track_visible[sel]
    if px.shape[0] < 2:
        return 0.0
    step = np.linalg.norm(np.diff(px, axis=0), axis=-1) * (vis[1:] & vis[:-1])
    return float(step.sum(axis=0).max())


if __name__ == "__main__":
    main()
