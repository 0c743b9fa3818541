"""E_flow (not in the paper): the silhouette's edge moves as fast as the events say it does.

An edge sweeping the sensor fires events whose times rise along its motion: near a boundary point, the events of a
short time window lie on a plane t = a·x + b·y + c, whose gradient g = (a, b) points along the edge's motion (the
local plane fit of event-based normal flow, Benosman et al. 2014). E_flow compares the edge's speed along that
direction with the image velocity of the template's boundary point:

    E_flow = ½ Σ_f Σ_b ρ(u_bᵀ Jπ_b J3_b S'(t_f) - s_b) / σ²

at the samples t_f (every ``step_ms`` of the solved batches' tracking frames), for every boundary point b of the
posed template (:mod:`.boundary`) whose events fit a plane: at least ``min_events`` events within ``radius_px``
(a square) and ± ``half_ms``, the plane explaining at least ``min_fit`` of their times' spread (R²: an edge sweeping
the patch, not noise or texture), its direction u_b = g / |g| within ``min_cos`` of the boundary's normal, and the
edge it describes passing within ``max_offset_px`` of the point at t_f. The speed s_b (px/s) is the events'
position along u_b regressed on their time, cov(d, t) / var(t): their times are exact where their pixels are
whole numbers, so this slope is not diluted as 1 / |g| is (which overstates the speed by a quarter to a half: the
pixels' rounding lies in its regressor). S'(t) is the pose's velocity (per second), Jπ_b J3_b the Jacobian of the
point's pixel with respect to the pose at the current estimate, held through a solve and measured again at each ICP
round, and ρ the Cauchy loss of scale ``loss_scale`` σ (another limb's edge inside the patch is an outlier).

Why a velocity: E_sil pulls the boundary onto the closest event of a few milliseconds, an association that at a
solve's estimate errs by more than the edge moves in a millisecond; the plane's slope is measured from tens of
events over ±10 ms and depends little on where exactly the estimate puts the edge.

How it is computed: per sample, the moments of the events' pixel coordinates and times (Σ1, Σx, Σy, Σx², Σy², Σxy,
Σt, Σxt, Σyt, Σt²) summed over every pixel's square by box filters (OpenCV), so each boundary point's plane is a
3 × 3 solve.
"""

from __future__ import annotations

import time

import cv2
import numpy as np

from eventcap.body.skeleton import NUM_POSE_PARAMS
from eventcap.camera import Camera

from .boundary import boundary_samples
from .errors import EnergyError
from .factor import Factor, Linearization
from .kernels import premultiplied_weights, shared_kernels
from .settings import FlowNoise
from .sil import window_sil_frames

_NP = NUM_POSE_PARAMS
_MOMENTS = ("n", "x", "y", "xx", "yy", "xy", "t", "xt", "yt", "tt")


def normal_flow(events: np.ndarray, width: int, height: int, t_us: int, pixels: np.ndarray, radius_px: int,
                half_ms: float, min_events: int) -> dict[str, np.ndarray]:
    """The events' local plane at each of ``pixels`` (B, 2) (x, y) at time ``t_us``: the events within
    ``radius_px`` (a square) and ± ``half_ms`` of it, t = a (x - x_b) + b (y - y_b) + c (t in ms from t_us).

    Returns arrays of B: ``ok`` (at least ``min_events`` events, a plane that exists), ``u`` (B, 2) the unit
    direction of the times' rise (where the edge moves), ``speed_dt`` its normal speed (px/s, the position along u
    regressed on time), ``speed`` the plane's own 1000 / |g| (diluted by the pixels' rounding), ``r2`` the share of
    the times' spread the plane explains, ``offset_px`` where the edge is at t_us along u from the pixel, ``n`` the
    events counted."""
    pixels = np.asarray(pixels, dtype=np.int64)
    B = pixels.shape[0]
    t = np.asarray(events["t"], dtype=np.int64)
    half_us = int(round(half_ms * 1000))
    sel = slice(int(np.searchsorted(t, t_us - half_us)), int(np.searchsorted(t, t_us + half_us, side="right")))
    x = np.asarray(events["x"][sel], dtype=np.float64)
    y = np.asarray(events["y"][sel], dtype=np.float64)
    tm = (t[sel] - t_us) / 1000.0
    flat = np.asarray(events["y"][sel], dtype=np.int64) * width + np.asarray(events["x"][sel], dtype=np.int64)
    k = 2 * int(radius_px) + 1
    values = {"n": None, "x": x, "y": y, "xx": x * x, "yy": y * y, "xy": x * y, "t": tm, "xt": x * tm, "yt": y * tm,
              "tt": tm * tm}
    px, py = pixels[:, 0], pixels[:, 1]
    m = {}
    for name in _MOMENTS:
        img = np.bincount(flat, weights=values[name], minlength=width * height).reshape(height, width)
        m[name] = cv2.boxFilter(img, -1, (k, k), normalize=False, borderType=cv2.BORDER_CONSTANT)[py, px]
    n = m["n"]
    fx, fy = px.astype(np.float64), py.astype(np.float64)
    # moments about the boundary pixel
    sx, sy = m["x"] - fx * n, m["y"] - fy * n
    sxx = m["xx"] - 2 * fx * m["x"] + fx * fx * n
    syy = m["yy"] - 2 * fy * m["y"] + fy * fy * n
    sxy = m["xy"] - fx * m["y"] - fy * m["x"] + fx * fy * n
    sxt, syt = m["xt"] - fx * m["t"], m["yt"] - fy * m["t"]
    A = np.empty((B, 3, 3))
    A[:, 0] = np.stack([sxx, sxy, sx], -1)
    A[:, 1] = np.stack([sxy, syy, sy], -1)
    A[:, 2] = np.stack([sx, sy, n], -1)
    rhs = np.stack([sxt, syt, m["t"]], -1)
    ok = n >= min_events
    ok &= np.abs(np.linalg.det(np.where(ok[:, None, None], A, np.eye(3)))) > 1e-6
    A[~ok], rhs[~ok] = np.eye(3), 0.0
    beta = np.linalg.solve(A, rhs[..., None])[..., 0]
    g = beta[:, :2]
    gn = np.linalg.norm(g, axis=1)
    ok &= gn > 1e-9
    nn = np.maximum(n, 1.0)
    sse = np.maximum(m["tt"] - np.sum(beta * rhs, axis=1), 0.0)
    var = m["tt"] / nn - (m["t"] / nn) ** 2
    r2 = np.where(var > 1e-12, 1.0 - sse / nn / np.maximum(var, 1e-12), 0.0)
    safe = np.maximum(gn, 1e-9)
    u = g / safe[:, None]
    # the position along u regressed on time: cov(d, t) / var(t), d = (x - x_b, y - y_b)·u (px per ms)
    cov_dt = (u[:, 0] * (sxt - sx * m["t"] / nn) + u[:, 1] * (syt - sy * m["t"] / nn)) / nn
    v_dt = 1000.0 * cov_dt / np.maximum(var, 1e-12)
    # where the edge is at t_us: the plane's zero along u, -c / |g| px from the pixel (c: the plane's time there)
    offset = -beta[:, 2] / safe
    return {"ok": ok, "u": u, "speed": np.where(ok, 1000.0 / safe, 0.0), "speed_dt": np.where(ok, v_dt, 0.0),
            "r2": np.where(ok, r2, 0.0), "n": n, "offset_px": np.where(ok, offset, np.inf)}


def pixel_jacobians(camera: Camera, points: np.ndarray, eps_m: float = 1e-6) -> np.ndarray:
    """∂π/∂X (P, 2, 3) of the camera's projection at world points (P, 3), by central differences (the projection
    is smooth in front of the camera; distortion included)."""
    P = np.asarray(points, dtype=np.float64)
    out = np.empty((P.shape[0], 2, 3))
    for a in range(3):
        d = np.zeros(3)
        d[a] = eps_m
        out[:, :, a] = (camera.project(P + d) - camera.project(P - d)) / (2 * eps_m)
    return out


class NormalFlow(Factor):
    """E_flow (module doc): ½ Σ_f Σ_b ρ(u_bᵀ Jπ_b J3_b S'(t_f) - s_b) / σ², the template's boundary points' normal
    image speed against the events' local planes, measured again at each ICP round where the estimate puts the
    boundary, with the Jacobians held there; the loss's exact derivatives in the velocities."""

    name = "flow"
    needs = ("track_times_us", "events")
    Config = None
    Noise = FlowNoise
    derivative = 1

    @classmethod
    def noise_precision(cls, config, camera) -> float:
        return 0.5 / float(config.sigma_px_s) ** 2

    def __init__(self, config, template, camera, n):
        super().__init__(config, template, camera, n)
        self.kernels = shared_kernels(template.rest_joints, self.n)
        self._clear()
        self.events = None

    def _clear(self) -> None:
        self.rows: dict[str, np.ndarray] = {}
        self.n_boundary = self.n_measured = 0
        self.seconds: dict[str, float] = {}

    @classmethod
    def samples(cls, inputs, config) -> np.ndarray:
        return window_sil_frames(inputs.track_times_us, float(config.step_ms))

    def collect(self, inputs) -> None:
        super().collect(inputs)
        self._clear()
        self.events = None
        if inputs.events is None:
            return
        ev = inputs.events
        t = np.asarray(ev["t"], dtype=np.int64)
        if t.size and np.any(np.diff(t) < 0):
            ev = ev[np.argsort(t, kind="stable")]
        cam = self.camera
        if ev.size and (int(ev["x"].max()) >= cam.width or int(ev["y"].max()) >= cam.height):
            raise EnergyError(f"E_flow: an event lies outside the {cam.width}x{cam.height} sensor")
        self.events = ev

    def relinearize(self, estimate) -> None:
        if self.events is None or not estimate.associate:
            return
        c = self.config
        t0 = time.perf_counter()
        S = estimate.poses(self.t_us)
        bs = boundary_samples(self.template, self.camera, S)
        self.n_boundary = bs.n
        keep = np.zeros(bs.n, dtype=bool)
        u, speed = np.zeros((bs.n, 2)), np.zeros(bs.n)
        bounds = np.searchsorted(bs.frame, np.arange(self.n + 1))
        for f in range(self.n):
            sl = slice(bounds[f], bounds[f + 1])
            if sl.stop == sl.start:
                continue
            fl = normal_flow(self.events, self.camera.width, self.camera.height, int(self.t_us[f]), bs.pixel[sl],
                             int(c.radius_px), float(c.half_ms), int(c.min_events))
            keep[sl] = (fl["ok"] & (fl["r2"] >= float(c.min_fit)) & (np.abs(fl["offset_px"]) <= float(c.max_offset_px))
                        & (np.abs(np.sum(fl["u"] * bs.normal[sl], axis=1)) >= float(c.min_cos)))
            u[sl], speed[sl] = fl["u"], fl["speed_dt"]
        t1 = time.perf_counter()
        frame = bs.frame[keep]
        WX = premultiplied_weights(bs.rest_points[keep], bs.weights[keep])  # (P, 96)
        G, dG = self.kernels.transforms_jac(np.ascontiguousarray(S, dtype=np.float64))
        a = np.zeros((frame.size, _NP))
        fb = np.searchsorted(frame, np.arange(self.n + 1))
        for f in np.flatnonzero(np.diff(fb)):  # frame by frame: dG of one frame at a time
            sl = slice(fb[f], fb[f + 1])
            points = WX[sl] @ G[f]  # (P_f, 3)
            J3 = (WX[sl] @ dG[f].reshape(dG.shape[1], -1)).reshape(-1, 3, _NP)  # ∂point/∂S
            a[sl] = np.einsum("pi,pic,pcq->pq", u[keep][sl], pixel_jacobians(self.camera, points), J3)
        self.rows = {"frame": frame, "a": a, "speed": speed[keep]}
        self.n_measured = int(frame.size)
        self.seconds = {"flow": t1 - t0, "jacobians": time.perf_counter() - t1}

    def _residuals(self, S: np.ndarray) -> np.ndarray:
        """u_bᵀ Jπ_b J3_b S'(t_f) - s_b (px/s) of every kept measurement, S the velocities at the samples."""
        rows = self.rows
        if not rows or not rows["frame"].size:
            return np.zeros(0)
        return np.einsum("pq,pq->p", rows["a"], S[rows["frame"]]) - rows["speed"]

    def linearize(self, S, aux, order):
        """Σ ρ(r_b) with ρ the Cauchy loss of scale c = ``loss_scale`` σ, c² log(1 + r²/c²) (r² for ``loss_scale``
        0), times the noise's precision ½ / σ²; exact gradient and Hessian (the Cauchy loss's is indefinite beyond
        c: IPOPT regularises)."""
        r = self._residuals(S)
        c2 = (float(self.config.loss_scale) * float(self.config.sigma_px_s)) ** 2
        if c2 > 0:
            q = 1.0 + r * r / c2
            rho, d1, d2 = c2 * np.log(q), 2.0 * r / q, 2.0 * (1.0 - r * r / c2) / (q * q)
        else:
            rho, d1, d2 = r * r, 2.0 * r, np.full(r.shape, 2.0)
        lin = Linearization(self.weight * float(rho.sum()))
        if not r.size:
            if order >= 1:
                lin.grad = np.zeros_like(S)
            if order >= 2:
                lin.diag = np.zeros((self.n, _NP, _NP))
            return lin
        frame, a = self.rows["frame"], self.rows["a"]
        if order >= 1:
            lin.grad = np.zeros_like(S)
            np.add.at(lin.grad, frame, (self.weight * d1)[:, None] * a)
        if order >= 2:
            lin.diag = np.zeros((self.n, _NP, _NP))
            np.add.at(lin.diag, frame, (self.weight * d2)[:, None, None] * a[:, :, None] * a[:, None, :])
        return lin

    def report(self) -> dict:
        return {"n_flow": self.n_measured, "n_flow_boundary": self.n_boundary}

    def describe(self) -> str | None:
        return (f"E_flow at {self.n} frames: {self.n_measured} of {self.n_boundary} boundary points with an edge's "
                f"normal flow in the events (last round)")


__all__ = ["NormalFlow", "normal_flow", "pixel_jacobians"]
