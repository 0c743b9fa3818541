"""Benchmark of EDI sharpening and trajectory slicing (eventcap.imaging.edi, eventcap_track.bspline).

Prints (1) a PSNR table over synthetic fast motions at 240x180 (simulated DAVIS240C-like sensor with default
noise, 10 ms exposures at 25 fps, 3 frames per motion): the blurry frame, EDI at the simulator's nominal C = 0.2,
and EDI at the C estimated per recording, all against the true sharp image ``render(t_centre)`` in linear
intensity; (2) the estimated C per motion, and where the TV-based sharpness energies would have put it;
(3) time per frame of EDI, of latent images every 1 ms over a batch, of the C search; (4) accuracy and time of
slicing 100 tracks over 40 ms at 1 kHz; (5) EDI on the real DAVIS346 file when the project's reader is there.

    python3 benchmarks/accuracy/bench_edi.py

The scene functions here are analytic, exactly box-filtered where practical (no aliasing shimmer), and are also
used by tests/test_edi.py.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "plugins"))

from eventcap.imaging import edi
from eventcap_track import bspline

from eventcap.sim.events import SensorConfig
from eventcap.sim.frames import FrameConfig, IntensityFrame, simulate_capture

HEIGHT, WIDTH = 180, 240
NOMINAL_C = 0.2  # SensorConfig's default threshold_pos / threshold_neg

Render = Callable[[int], np.ndarray]


# ---------------------------------------------------------------------------------------------- synthetic scenes


def _square_wave_integral(x: np.ndarray, period: float) -> np.ndarray:
    """∫_0^x of the indicator [mod(s, period) < period/2] ds."""
    on = period / 2
    return np.floor(x / period) * on + np.minimum(np.mod(x, period), on)


def _square_wave_pixels(x: np.ndarray, period: float) -> np.ndarray:
    """Pixel-averaged square wave: the fraction of pixel [x, x+1) that is 'on'."""
    return _square_wave_integral(x + 1.0, period) - _square_wave_integral(x, period)


def bars(speed_px_s: float, period_px: float = 24.0, lo: float = 0.15, hi: float = 0.85) -> Render:
    """Vertical bars translating right (simulated scene)."""
    xx = np.arange(WIDTH, dtype=np.float64)

    def render(t_us: int) -> np.ndarray:
        row = lo + (hi - lo) * _square_wave_pixels(xx - speed_px_s * t_us * 1e-6, period_px)
        return np.broadcast_to(row[None, :], (HEIGHT, WIDTH)).astype(np.float32)

    return render


def checkerboard(vx_px_s: float, vy_px_s: float, cell_px: float = 20.0, lo: float = 0.1, hi: float = 0.8) -> Render:
    """Checkerboard translating diagonally (simulated scene); exact pixel averages (the pattern is separable)."""
    xx = np.arange(WIDTH, dtype=np.float64)
    yy = np.arange(HEIGHT, dtype=np.float64)

    def render(t_us: int) -> np.ndarray:
        t = t_us * 1e-6
        a = _square_wave_pixels(xx - vx_px_s * t, 2 * cell_px)[None, :]
        b = _square_wave_pixels(yy - vy_px_s * t, 2 * cell_px)[:, None]
        return (lo + (hi - lo) * (a * (1 - b) + (1 - a) * b)).astype(np.float32)

    return render


def siemens_star(omega_rad_s: float, n_sectors: int = 12, radius_px: float = 85.0) -> Render:
    """A rotating Siemens star on a grey background (simulated scene); rim speed omega * radius px/s."""
    yy, xx = np.mgrid[0:HEIGHT, 0:WIDTH].astype(np.float64) + 0.5
    dx, dy = xx - WIDTH / 2, yy - HEIGHT / 2
    r, theta = np.hypot(dx, dy), np.arctan2(dy, dx)
    inside = np.clip(radius_px - r + 0.5, 0.0, 1.0)

    def render(t_us: int) -> np.ndarray:
        # r * sin(n θ) / n approximates the signed distance (px) to the nearest sector edge
        s = np.clip(0.5 + r * np.sin(n_sectors * (theta - omega_rad_s * t_us * 1e-6)) / n_sectors, 0.0, 1.0)
        return (inside * (0.1 + 0.8 * s) + (1 - inside) * 0.4).astype(np.float32)

    return render


def textured(speed_px_s: float, seed: int = 0) -> Render:
    """Smooth random texture with sharp-edged blocks, translating and rotating (the simulator benchmark's scene)."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "speed"))
    from bench_simulator import textured_scene

    return textured_scene(speed_px_s, seed)


def discs(speed_px_s: float, seed: int = 1, lo: float = 0.08, hi: float = 0.9) -> Render:
    """Bright discs on a dark background moving right, wrapping around (simulated scene)."""
    rng = np.random.default_rng(seed)
    cx, cy, rad = rng.uniform(0, WIDTH, 10), rng.uniform(15, HEIGHT - 15, 10), rng.uniform(6, 18, 10)
    yy, xx = np.mgrid[0:HEIGHT, 0:WIDTH].astype(np.float64) + 0.5

    def render(t_us: int) -> np.ndarray:
        out = np.full((HEIGHT, WIDTH), lo)
        shift = speed_px_s * t_us * 1e-6
        for x0, y0, r0 in zip(cx, cy, rad):
            x = np.mod(x0 + shift, WIDTH + 40) - 20
            out = np.maximum(out, lo + (hi - lo) * np.clip(r0 - np.hypot(xx - x, yy - y0) + 0.5, 0.0, 1.0))
        return out.astype(np.float32)

    return render


def swinging_limb(omega_rad_s: float, length_px: float = 80.0, half_width_px: float = 8.0, seed: int = 2) -> Render:
    """A striped bar (a limb) rotating about one end over a static smooth background (simulated scene)."""
    rng = np.random.default_rng(seed)
    bg = cv2.GaussianBlur(rng.random((HEIGHT, WIDTH)).astype(np.float32), (0, 0), 3.0).astype(np.float64)
    bg = 0.2 + 0.3 * (bg - bg.min()) / (bg.max() - bg.min())
    yy, xx = np.mgrid[0:HEIGHT, 0:WIDTH].astype(np.float64) + 0.5
    px, py = WIDTH / 2, HEIGHT / 2

    def render(t_us: int) -> np.ndarray:
        a = omega_rad_s * t_us * 1e-6 + 0.3
        along = (xx - px) * np.cos(a) + (yy - py) * np.sin(a)
        across = np.abs(-(xx - px) * np.sin(a) + (yy - py) * np.cos(a))
        cover = np.clip(half_width_px - across + 0.5, 0, 1) * np.clip(
            np.minimum(along + 0.5, length_px - along + 0.5), 0, 1
        )
        stripes = 0.55 + 0.35 * (np.mod(along, 16.0) < 8.0)  # clothing texture along the limb
        return (bg * (1 - cover) + stripes * cover).astype(np.float32)

    return render


def scenes() -> dict[str, Render]:
    """The benchmark's fast motions (name: render), 240x180. Speeds in px/s at the fastest point."""
    return {
        "bars 400 px/s": bars(400.0),
        "bars 150 px/s, 16 px period": bars(150.0, period_px=16.0),
        "checkerboard 360 px/s": checkerboard(300.0, 200.0),
        "siemens star 680 px/s rim": siemens_star(8.0),
        "texture 500 px/s": textured(500.0),
        "texture 1000 px/s": textured(1000.0),
        "discs 800 px/s": discs(800.0),
        "limb 960 px/s tip": swinging_limb(12.0),
    }


def capture(render: Render, duration_us: int, sensor: SensorConfig | None = None,
            frames: FrameConfig | None = None) -> tuple[np.ndarray, list[IntensityFrame]]:  # fmt: skip
    """Simulated events (EVENT_DTYPE) and intensity frames of a scene over [0, duration_us]."""
    chunks = list(simulate_capture(render, 0, duration_us, sensor, frames))
    events = np.concatenate([c.events.events for c in chunks])
    return events, [f for c in chunks for f in c.frames]


def psnr(image: np.ndarray, truth: np.ndarray) -> float:
    """PSNR (dB) of a linear image in [0, 1] against the truth (peak 1)."""
    mse = float(np.mean((np.asarray(image, np.float64) - truth) ** 2))
    return 10.0 * np.log10(1.0 / mse)


def sharpen(frame: IntensityFrame, events: np.ndarray, c: float) -> np.ndarray:
    """EDI image at the frame centre, linear intensity (H, W) float32."""
    window = edi.exposure_window(frame.t_us, frame.exposure_us)
    return edi.to_linear(edi.latent_log_image(frame.image, events, frame.t_us, window, c, HEIGHT, WIDTH))


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
