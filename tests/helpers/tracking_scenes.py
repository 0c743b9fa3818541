"""Simulated scenes for the event feature trackers: analytic textures at 240x180 moving with known fast motions
(translation, rotation, affine, a textured disc over a textured background), turned into events by
``eventcap.sim.events``. The true position of every texture point is known at every time, so each track is scored
against ground truth (``track_errors``, ``evaluate``).

Used by tests/test_eklt.py and benchmarks/accuracy/bench_tracking.py.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import cv2
import numpy as np

from eventcap.sim.events import SensorConfig, simulate_all

HEIGHT, WIDTH = 180, 240
LOG_EPS = 1e-3
T0_US, T1_US = 0, 40_000


def _texture(size: int, rng: np.random.Generator, n_blobs: int = 600, n_blocks: int = 60) -> np.ndarray:
    """A (size, size) float32 texture in [0.05, 0.95]: smooth noise, Gaussian blobs and a few sharp blocks.

    Contrast is moderate so that a fast full-frame motion gives event rates like a moving person
    (a few hundred thousand events per 40 ms), not a sea of events.
    """
    tex = cv2.GaussianBlur(rng.random((size, size)).astype(np.float32), (0, 0), 4.0)
    tex = (tex - tex.min()) / (tex.max() - tex.min())
    tex = 0.25 + 0.5 * tex
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
    for _ in range(n_blobs):
        cx, cy = rng.uniform(0, size, 2)
        s = rng.uniform(2.0, 5.0)
        a = rng.choice([-1.0, 1.0]) * rng.uniform(0.15, 0.4)
        r2 = (xx - cx) ** 2 + (yy - cy) ** 2
        m = r2 < (4 * s) ** 2
        tex[m] += a * np.exp(-r2[m] / (2 * s * s))
    for _ in range(n_blocks):
        y, x = rng.integers(0, size - 30, 2)
        h, w = rng.integers(6, 30, 2)
        tex[y : y + h, x : x + w] = rng.uniform(0.15, 0.85)
    # A texel of antialiasing keeps the warped render a continuous function of position.
    tex = cv2.GaussianBlur(tex, (0, 0), 0.7)
    return np.clip(tex, 0.05, 0.95).astype(np.float32)


def _affine(angle_rad: float, scale: float, shear: float, tx: float, ty: float, pivot) -> np.ndarray:
    """2x3 texture->image map: rotate/scale/shear about ``pivot`` (texture coords), then translate by (tx, ty)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    a = scale * np.array([[c, -s], [s, c]]) @ np.array([[1.0, shear], [0.0, 1.0]])
    px, py = pivot
    m = np.zeros((2, 3))
    m[:, :2] = a
    m[:, 2] = np.array([px, py]) - a @ np.array([px, py]) + np.array([tx, ty])
    return m


@dataclass(frozen=True)
class Scene:
    """A simulated moving scene with exact ground truth.

    ``render(t_us)``: (HEIGHT, WIDTH) float32 linear intensity; ``truth(xy, t_from_us, t_us)``: where the texture
    points seen at image positions ``xy`` (K, 2) at time ``t_from_us`` are at ``t_us`` -> (K, 2) px;
    ``mask(t_us)``: (HEIGHT, WIDTH) bool region where features may be detected (the "actor").
    """

    name: str
    render: Callable[[int], np.ndarray]
    truth: Callable[[np.ndarray, int, int], np.ndarray]
    mask: Callable[[int], np.ndarray]


def _apply(m: np.ndarray, xy: np.ndarray) -> np.ndarray:
    return xy @ m[:, :2].T + m[:, 2]


def _invert(m: np.ndarray) -> np.ndarray:
    return cv2.invertAffineTransform(m)


def _layer_scene(name: str, motion: Callable[[float], np.ndarray], seed: int, size: int = 600) -> Scene:
    """One full-frame textured layer moving with ``motion(t_s) -> 2x3`` texture->image map."""
    tex = _texture(size, np.random.default_rng(seed))

    def render(t_us: int) -> np.ndarray:
        m = motion(t_us * 1e-6)
        return cv2.warpAffine(tex, m, (WIDTH, HEIGHT), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)

    def truth(xy: np.ndarray, t_from_us: int, t_us: int) -> np.ndarray:
        p = _apply(_invert(motion(t_from_us * 1e-6)), np.asarray(xy, np.float64))
        return _apply(motion(t_us * 1e-6), p)

    full = np.ones((HEIGHT, WIDTH), bool)
    return Scene(name, render, truth, lambda t_us: full)


def _disc_scene(name: str, speed_px_s: float, seed: int, radius: float = 55.0, size: int = 600) -> Scene:
    """A textured disc (the "actor") moving at ``speed_px_s`` and spinning, over a slowly drifting background."""
    rng = np.random.default_rng(seed)
    bg = _texture(size, rng)
    fg = _texture(size, rng, n_blobs=900, n_blocks=80)
    centre_tex = np.array([size / 2, size / 2])
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
    # Antialiased disc edge (1 texel ramp) in texture coordinates, warped with the disc.
    alpha_tex = np.clip(radius + 0.5 - np.hypot(xx - centre_tex[0], yy - centre_tex[1]), 0.0, 1.0).astype(np.float32)
    start = np.array([75.0, 95.0])
    direction = np.array([np.cos(0.35), np.sin(0.35)])

    def disc_motion(t_s: float) -> np.ndarray:
        shift = start + direction * speed_px_s * t_s - centre_tex
        return _affine(6.0 * t_s, 1.0, 0.0, shift[0], shift[1], centre_tex)

    def bg_motion(t_s: float) -> np.ndarray:
        return _affine(0.0, 1.0, 0.0, -(size - WIDTH) / 2 - 150.0 * t_s, -(size - HEIGHT) / 2 + 80.0 * t_s, (0, 0))

    def render(t_us: int) -> np.ndarray:
        t_s = t_us * 1e-6
        md = disc_motion(t_s)
        b = cv2.warpAffine(bg, bg_motion(t_s), (WIDTH, HEIGHT), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        f = cv2.warpAffine(fg, md, (WIDTH, HEIGHT), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        a = cv2.warpAffine(alpha_tex, md, (WIDTH, HEIGHT), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        return (a * f + (1.0 - a) * b).astype(np.float32)

    def disc_centre(t_us: int) -> np.ndarray:
        return _apply(disc_motion(t_us * 1e-6), centre_tex[None])[0]

    def truth(xy: np.ndarray, t_from_us: int, t_us: int) -> np.ndarray:
        xy = np.asarray(xy, np.float64)
        on_disc = np.hypot(*(xy - disc_centre(t_from_us)).T) < radius
        out = np.empty_like(xy)
        for inside, motion in ((True, disc_motion), (False, bg_motion)):
            sel = on_disc == inside
            p = _apply(_invert(motion(t_from_us * 1e-6)), xy[sel])
            out[sel] = _apply(motion(t_us * 1e-6), p)
        return out

    def mask(t_us: int) -> np.ndarray:
        c = disc_centre(t_us)
        yy_i, xx_i = np.mgrid[0:HEIGHT, 0:WIDTH]
        return np.hypot(xx_i - c[0], yy_i - c[1]) < radius - 4.0

    return Scene(name, render, truth, mask)


def make_scene(name: str) -> Scene:
    """One of ``SCENES`` by name."""
    off = (-(600 - WIDTH) / 2, -(600 - HEIGHT) / 2)
    piv = (300.0, 300.0)

    def translate(speed: float, ang: float = 0.5):
        return lambda t: _affine(0.0, 1.0, 0.0, off[0] + speed * np.cos(ang) * t, off[1] + speed * np.sin(ang) * t, piv)

    if name == "translate_500":
        return _layer_scene(name, translate(500.0), seed=1)
    if name == "translate_1500":
        return _layer_scene(name, translate(1500.0), seed=2)
    if name == "translate_3000":
        return _layer_scene(name, translate(3000.0), seed=3)
    if name == "rotate":  # 15 rad/s about the image centre (up to ~2200 px/s at the corners) + 600 px/s drift
        return _layer_scene(
            name, lambda t: _affine(15.0 * t, 1.0, 0.0, off[0] + 600 * t, off[1] - 300 * t, piv), seed=4
        )
    if name == "affine":  # zoom 1 -> 1.2, shear 0 -> 0.15, rotation 0 -> 0.2 rad and 1200 px/s over 40 ms
        return _layer_scene(
            name, lambda t: _affine(5.0 * t, 1.0 + 5.0 * t, 3.75 * t, off[0] + 1000 * t, off[1] + 660 * t, piv), seed=5
        )
    if name == "disc_2000":
        return _disc_scene(name, 2000.0, seed=6)
    raise ValueError(f"unknown scene {name!r}; expected one of {SCENES}")


SCENES = ("translate_500", "translate_1500", "translate_3000", "rotate", "affine", "disc_2000")


def log_image(scene: Scene, t_us: int) -> np.ndarray:
    """The true (sharp) log image log(I + eps) of a scene, float32 (HEIGHT, WIDTH)."""
    return np.log(scene.render(t_us).astype(np.float32) + np.float32(LOG_EPS))


def simulate_events(scene: Scene, t0_us: int = T0_US, t1_us: int = T1_US, config: SensorConfig | None = None):
    """Simulated events of a scene (default sensor: C=0.2, sigma_C=0.03, 100 us refractory, 0.2 Hz noise)."""
    return simulate_all(scene.render, t0_us, t1_us, config or SensorConfig(log_eps=LOG_EPS))


@dataclass(frozen=True)
class Score:
    """Accuracy of a set of tracks against ground truth (errors over all (track, ms) pairs a track covers)."""

    n_tracks: int
    survival: float  # fraction of tracks that were not dropped before the end of their direction(s)
    median_px: float
    p90_px: float
    coverage: float  # mean fraction of the batch's 1 ms grid covered by a track
    lost_inside: float  # fraction of tracks dropped away from the image border (not just leaving the view)

    def __str__(self) -> str:
        return (f"tracks {self.n_tracks:4d}  survival {self.survival:5.2f} (lost inside {self.lost_inside:4.2f})  "
                f"median {self.median_px:5.2f} px  p90 {self.p90_px:5.2f} px  coverage {self.coverage:4.2f}")


def track_errors(tracks, scene: Scene, t0_us: int = T0_US, t1_us: int = T1_US, step_us: int = 1000) -> np.ndarray:
    """(K, T) px error of every track on the 1 ms grid of [t0_us, t1_us] (NaN where not covered).

    The texture point a track follows is fixed by its detection: the first sample of forward and stitched
    tracks (at t0_us), the last sample of backward tracks (at t1_us).
    """
    from eventcap_track.eklt import KIND_BACKWARD

    grid = np.arange(t0_us, t1_us + 1, step_us)
    pos = tracks.positions_at(grid)
    err = np.full(pos.shape[:2], np.nan)
    o = tracks.offsets
    for k in range(tracks.n_tracks):
        i = o[k + 1] - 1 if tracks.kind[k] == KIND_BACKWARD else o[k]
        anchor = np.array([[tracks.x[i], tracks.y[i]]])
        t_anchor = int(tracks.t_us[i])
        covered = np.isfinite(pos[k, :, 0])
        for j in np.flatnonzero(covered):
            truth = scene.truth(anchor, t_anchor, int(grid[j]))[0]
            err[k, j] = np.hypot(*(pos[k, j] - truth))
    return err


def evaluate(tracks, scene: Scene, t0_us: int = T0_US, t1_us: int = T1_US) -> Score:
    """Score of ``tracks`` (a FeatureTracks) against the scene's ground truth."""
    err = track_errors(tracks, scene, t0_us, t1_us)
    e = err[np.isfinite(err)]
    return Score(
        n_tracks=tracks.n_tracks,
        survival=float(np.mean(tracks.survived)) if tracks.n_tracks else float("nan"),
        median_px=float(np.median(e)) if e.size else float("nan"),
        p90_px=float(np.percentile(e, 90)) if e.size else float("nan"),
        coverage=float(np.mean(np.isfinite(err))) if err.size else 0.0,
        lost_inside=_lost_inside(tracks),
    )


def _lost_inside(tracks, margin_px: float = 12.0) -> float:
    """Fraction of tracks that were dropped while both their end samples lie > margin_px inside the image."""
    if tracks.n_tracks == 0:
        return float("nan")
    o = tracks.offsets
    ends = np.stack([np.c_[tracks.x[o[:-1]], tracks.y[o[:-1]]], np.c_[tracks.x[o[1:] - 1], tracks.y[o[1:] - 1]]])
    inside = ((ends[..., 0] > margin_px) & (ends[..., 0] < tracks.width - 1 - margin_px)
              & (ends[..., 1] > margin_px) & (ends[..., 1] < tracks.height - 1 - margin_px)).all(axis=0)
    return float(np.mean(~tracks.survived & inside))


def true_latents(scene: Scene, t0_us: int = T0_US, t1_us: int = T1_US, step_us: int = 1000) -> np.ndarray:
    """(n, HEIGHT, WIDTH) true log images every step_us: the best case for the frame-based baseline."""
    return np.stack([log_image(scene, t) for t in range(t0_us, t1_us + 1, step_us)])


def event_latents(log_start, events, t_start_us: int, t_end_us: int, direction: int = 1, step_us: int = 1000,
                  contrast_threshold: float = 0.2) -> np.ndarray:
    """(n, H, W) latent log images every step_us by integrating events onto a sharp image, as EDI does.

    direction=+1: ``log_start`` is at t_start_us and L(t) = L0 + C * sum of polarities in (t_start, t];
    direction=-1: ``log_start`` is at t_end_us and L(t) = L1 - C * sum of polarities in (t, t_end].
    Frame i is at t_start_us + i * step_us in both cases. Per-pixel threshold mismatch, refractory losses and
    noise of the sensor accumulate in these images: this is what the paper's "naive solution" tracks on.
    """
    h, w = log_start.shape
    times = np.arange(t_start_us, t_end_us + 1, step_us)
    ev = events[(events["t"] > t_start_us) & (events["t"] <= t_end_us)]
    # Frame index after which each event counts: events in (times[i-1], times[i]] first appear in frame i.
    idx = np.searchsorted(times, ev["t"], side="left")
    flat = idx.astype(np.int64) * (h * w) + ev["y"].astype(np.int64) * w + ev["x"]
    per_frame = np.bincount(flat, weights=ev["p"].astype(np.float64), minlength=times.size * h * w)
    cum = np.cumsum(per_frame.reshape(times.size, h, w), axis=0)  # sum over (t_start, times[i]]
    if direction == 1:
        return (log_start[None] + contrast_threshold * cum).astype(np.float32)
    return (log_start[None] - contrast_threshold * (cum[-1][None] - cum)).astype(np.float32)
