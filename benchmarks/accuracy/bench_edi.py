"""Benchmark of EDI sharpening and trajectory slicing (eventcap.imaging.edi, eventcap_track.bspline).

Prints (1) a PSNR table over synthetic fast motions at 240x180 (simulated DAVIS240C-like sensor with default
noise, 10 ms exposures at 25 fps, 3 frames per motion): the blurry frame, EDI at the simulator's nominal C = 0.2,
and EDI at the C estimated per recording, all against the true sharp image ``render(t_centre)`` in linear
intensity; (2) the estimated C per motion, and where the TV-based sharpness energies would have put it;
(3) time per frame of EDI, of latent images every 1 ms over a batch, of the C search; (4) accuracy and time of
slicing 100 tracks over 40 ms at 1 kHz; (5) EDI on the real DAVIS346 file when the project's reader is there.

    python3 benchmarks/accuracy/bench_edi.py

The scenes (analytic, exactly box-filtered where practical) are tests/helpers/edi_scenes.py, shared with
tests/test_edi.py.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "plugins"))
sys.path.insert(0, str(ROOT))  # the scenes: tests/helpers

from eventcap.imaging import edi
from eventcap.sim.frames import IntensityFrame
from eventcap_track import bspline
from tests.helpers.edi_scenes import HEIGHT, NOMINAL_C, WIDTH, bars, capture, psnr, scenes, sharpen


# ---------------------------------------------------------------------------------------------- reference energies


def _sobel_magnitude(img: np.ndarray) -> np.ndarray:
    return np.hypot(cv2.Sobel(img, cv2.CV_64F, 1, 0, ksize=3), cv2.Sobel(img, cv2.CV_64F, 0, 1, ksize=3))


def _binary_edges(g: np.ndarray) -> np.ndarray:
    gn = (g - g.min()) / (g.max() - g.min() + 1e-12)
    th = gn.mean()
    return gn > th + (1.0 - th) / 3.0


def tv_energies(frames: list[IntensityFrame], events: np.ndarray, grid: np.ndarray) -> tuple[float, float]:
    """argmin over grid of (TV of the EDI image, TV - event-edge agreement as the EDI authors' energy)."""
    tv, tv_edge = np.zeros(grid.size), np.zeros(grid.size)
    for f in frames:
        near = events[np.abs(events["t"] - f.t_us) <= 500]  # event edge map: events within ±0.5 ms of t_ref
        m = np.bincount(near["y"].astype(np.int64) * WIDTH + near["x"], minlength=HEIGHT * WIDTH)
        m_edges = _binary_edges(_sobel_magnitude(m.reshape(HEIGHT, WIDTH).astype(np.float64)))
        for i, c in enumerate(grid):
            g = _sobel_magnitude(sharpen(f, events, float(c)).astype(np.float64))
            tv[i] += g.sum()
            tv_edge[i] += 0.15 * g.sum() / 8.0 - np.sum(_binary_edges(g) & m_edges)
    return float(grid[np.argmin(tv)]), float(grid[np.argmin(tv_edge)])


# ---------------------------------------------------------------------------------------------- benchmark parts


def bench_psnr() -> None:
    print("EDI on simulated fast motions, 240x180, 10 ms exposure, 3 frames each, PSNR (dB) vs render(t_centre)")
    print(f"{'motion':30s} {'events':>8s} {'blurry':>7s} {'EDI@0.2':>8s} {'gain':>6s} {'C est':>6s} {'err':>5s} "
          f"{'EDI@est':>8s} {'gain':>6s}  {'TV argmin':>9s} {'TV+edge argmin':>14s}")  # fmt: skip
    gains, gains_est, c_errors = [], [], []
    grid = np.round(np.arange(0.05, 0.501, 0.025), 3)
    for name, render in scenes().items():
        events, frames = capture(render, 90_000)
        est = edi.estimate_contrast(
            np.stack([f.image for f in frames]), np.array([f.t_us for f in frames]), frames[0].exposure_us, events
        )
        p_blur = np.mean([psnr(f.image / 255.0, render(f.t_us)) for f in frames])
        p_edi = np.mean([psnr(sharpen(f, events, NOMINAL_C), render(f.t_us)) for f in frames])
        p_est = np.mean([psnr(sharpen(f, events, est.c), render(f.t_us)) for f in frames])
        c_err = est.c / NOMINAL_C - 1.0
        tv_arg, tv_edge_arg = tv_energies(frames, events, grid)
        gains.append(p_edi - p_blur)
        gains_est.append(p_est - p_blur)
        c_errors.append(c_err)
        print(f"{name:30s} {events.size:8d} {p_blur:7.2f} {p_edi:8.2f} {p_edi - p_blur:+6.2f} {est.c:6.3f} "
              f"{c_err:+5.0%} {p_est:8.2f} {p_est - p_blur:+6.2f}  {tv_arg:9.3f} {tv_edge_arg:14.3f}")  # fmt: skip
    print(
        f"mean gain at C=0.2: {np.mean(gains):+.2f} dB ({sum(g >= 3 for g in gains)}/{len(gains)} cases >= 3 dB); "
        f"at estimated C: {np.mean(gains_est):+.2f} dB ({sum(g >= 3 for g in gains_est)}/{len(gains)} >= 3 dB)"
    )
    print(f"C estimate: {sum(abs(e) <= 0.2 for e in c_errors)}/{len(c_errors)} within 20% of {NOMINAL_C}; "
          f"mean |error| {np.mean(np.abs(c_errors)):.0%}")  # fmt: skip


def bench_speed() -> None:
    render = bars(400.0)
    events, frames = capture(render, 90_000)
    f = frames[0]
    window = edi.exposure_window(f.t_us, f.exposure_us)
    n_in = int(np.count_nonzero((events["t"] > window[0]) & (events["t"] <= window[1])))
    edi.latent_log_image(f.image, events, f.t_us, window, 0.2, HEIGHT, WIDTH)  # compile the kernel
    reps = 20
    t = time.perf_counter()
    for _ in range(reps):
        latent = edi.latent_log_image(f.image, events, f.t_us, window, 0.2, HEIGHT, WIDTH)
    per_frame = (time.perf_counter() - t) / reps
    times = np.arange(f.t_us, frames[1].t_us + 1, 1000)
    t = time.perf_counter()
    for _ in range(reps):
        edi.latent_log_sequence(latent, f.t_us, times, events, 0.2)
    per_seq = (time.perf_counter() - t) / reps
    t = time.perf_counter()
    est = edi.estimate_contrast(np.stack([g.image for g in frames]), np.array([g.t_us for g in frames]), 10_000, events)
    t_est = time.perf_counter() - t
    print(f"EDI latent_log_image 240x180: {per_frame * 1e3:.1f} ms per frame ({n_in} events in the exposure)")
    print(f"latent_log_sequence, {times.size} images every 1 ms: {per_seq * 1e3:.1f} ms ({events.size} events)")
    print(f"estimate_contrast, 3 frames, {est.grid.size}-point grid + golden section: {t_est * 1e3:.0f} ms")


def bench_slicing() -> None:
    rng = np.random.default_rng(0)
    n_tracks = 100

    def truth(t_us: np.ndarray, h: np.ndarray) -> np.ndarray:
        t = t_us * 1e-6
        x = 50.0 + h + 800.0 * t + 3.0 * np.sin(2 * np.pi * 30.0 * t + h)
        y = 60.0 - 400.0 * t + 5000.0 * t**2 + 0.0 * h
        return np.stack(np.broadcast_arrays(x, y), axis=-1)

    tracks = []
    for h in range(n_tracks):  # asynchronous samples ~every 0.4 ms, tracks starting/ending inside the batch
        a, b = int(rng.integers(0, 10_000)), int(rng.integers(30_000, 40_001))
        t = np.unique(np.concatenate([[a, b], rng.integers(a, b + 1, (b - a) // 400)]))
        tracks.append((t, truth(t.astype(np.float64), np.float64(h))))
    ids, t_us, xy = bspline.concat_tracks(tracks)
    truth_at = None
    for noise in (0.0, 0.2):
        obs = xy + rng.normal(0.0, noise, xy.shape) if noise else xy
        sigma = max(noise, 0.01)
        bspline.slice_trajectories(ids, t_us, obs, 0, 40_000, sigma_px=sigma)
        reps = 10
        t0 = time.perf_counter()
        for _ in range(reps):
            out = bspline.slice_trajectories(ids, t_us, obs, 0, 40_000, sigma_px=sigma)
        dt = (time.perf_counter() - t0) / reps
        truth_at = truth(out.t_us[:, None].astype(np.float64), np.arange(n_tracks)[None, :].astype(np.float64))
        err = np.linalg.norm(out.xy - truth_at, axis=2)[out.valid]
        d2 = np.nanmax(np.abs(np.diff(out.xy, 2, axis=0)))
        d2_true = np.max(np.abs(np.diff(truth_at, 2, axis=0)))
        print(f"slice {n_tracks} tracks ({t_us.size} samples, noise {noise} px, sigma_px {sigma}) over 40 ms at 1 kHz: "
              f"{dt * 1e3:.1f} ms; error rms {np.sqrt(np.mean(err**2)):.4f} px, max {err.max():.4f} px; "
              f"max |2nd difference| {d2:.3f} px (truth {d2_true:.3f})")  # fmt: skip


def bench_real(path: Path = Path(__file__).resolve().parents[2] / "tests" / "data" / "real" / "davis346_lab_aps.aedat4") -> None:
    """EDI on the real DAVIS346 recording (no ground truth): C estimate and that the output is finite."""
    try:
        from eventcap.io.readers import read_recording
    except ImportError as exc:  # the readers are another part of the project
        print(f"real recording: skipped ({exc})")
        return
    if not path.exists():
        print(f"real recording: skipped ({path} not found)")
        return
    rec = read_recording(path)
    fr = rec.frames
    t = time.perf_counter()
    est = edi.estimate_contrast(fr.images, fr.t_us, fr.exposure_us, rec.events)
    t_est = time.perf_counter() - t
    t = time.perf_counter()
    latents = edi.sharpen_frames(fr.images, fr.t_us, fr.exposure_us, rec.events, est.c)
    per_frame = (time.perf_counter() - t) / len(latents)
    change = np.abs(edi.to_linear(latents) - fr.images).mean()
    print(
        f"real {rec.width}x{rec.height} ({path.name}): {len(latents)} frames, exposure {fr.exposure_us.tolist()} us; "
        f"C estimate {est.c:.3f} from {est.n_pixels} pixels in {t_est * 1e3:.0f} ms; EDI {per_frame * 1e3:.1f} ms "
        f"per frame; finite: {bool(np.isfinite(latents).all())}; mean |EDI - frame| {change:.4f}"
    )


if __name__ == "__main__":
    bench_psnr()
    bench_speed()
    bench_slicing()
    bench_real()
