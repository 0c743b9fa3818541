"""Simulated scenes for EDI: analytic textures at 240x180 moving fast, exactly box-filtered where practical (no
aliasing shimmer), their captures and EDI images, and PSNR against the true sharp image.

Used by tests/test_edi.py, tests/test_doubtful_warnings.py, benchmarks/accuracy/bench_edi.py and
benchmarks/speed/bench_simulator.py.
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

from eventcap.imaging import edi
from eventcap.sim.events import SensorConfig
from eventcap.sim.frames import FrameConfig, IntensityFrame, simulate_capture

HEIGHT, WIDTH = 180, 240
NOMINAL_C = 0.2  # SensorConfig's default threshold_pos / threshold_neg


Render = Callable[[int], np.ndarray]


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
    return textured_scene(speed_px_s, seed)


def textured_scene(speed_px_s: float, seed: int = 0):
    """Analytic moving scene: texture translating at speed_px_s and rotating at speed_px_s / 120 rad/s."""
    rng = np.random.default_rng(seed)
    size = 600
    tex = cv2.GaussianBlur(rng.random((size, size)).astype(np.float32), (0, 0), 2.0)
    tex = (tex - tex.min()) / (tex.max() - tex.min())
    for _ in range(40):  # sharp-edged blocks, like clothing seams and limb silhouettes
        y, x = rng.integers(0, size - 40, 2)
        h, w = rng.integers(8, 40, 2)
        tex[y : y + h, x : x + w] = rng.uniform(0.0, 1.0)
    tex = (0.05 + 0.9 * tex).astype(np.float32)
    centre = (size / 2, size / 2)

    def render(t_us: int) -> np.ndarray:
        t = t_us * 1e-6
        m = cv2.getRotationMatrix2D(centre, np.degrees(speed_px_s / 120.0 * t), 1.0)
        m[0, 2] += speed_px_s * t * 0.8 - (size - WIDTH) / 2
        m[1, 2] += speed_px_s * t * 0.6 - (size - HEIGHT) / 2
        out = cv2.warpAffine(tex, m, (WIDTH, HEIGHT), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        return np.clip(out, 0.0, 1.0)

    return render


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
