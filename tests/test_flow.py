"""E_flow (eventcap/energy/flow.py): the events' local plane gives an edge's normal speed and direction; noise is no
edge; the factor predicts each boundary point's image velocity (px/s) from the pose's velocity (units per second) as
finite differences of the posed points do, and its derivatives are those of its value."""

from __future__ import annotations

import numpy as np
import pytest

from eventcap.energy.flow import NormalFlow, normal_flow, pixel_jacobians
from eventcap.energy.settings import FlowNoise
from eventcap.energy.window import Estimate, WindowInputs
from eventcap.events import EVENT_DTYPE

from helpers.spline_scene import scene

W = H = 64


def edge_events(speed_px_ms: float, angle_deg: float, t0_us: int = 50_000, jitter_us: float = 0.0, seed: int = 0):
    """A straight edge sweeping a W x H sensor at ``speed_px_ms`` along ``angle_deg`` (image x right, y down): each
    pixel fires as the edge crosses its centre (and a second event 300 µs later), through the pixel (32, 32) at
    t0_us."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:H, 0:W]
    th = np.radians(angle_deg)
    d = (x - 32) * np.cos(th) + (y - 32) * np.sin(th)
    t = t0_us + d.ravel() / speed_px_ms * 1000.0 + rng.normal(0, jitter_us, d.size)
    ev = np.zeros(2 * d.size, EVENT_DTYPE)
    ev["x"], ev["y"] = np.tile(x.ravel(), 2), np.tile(y.ravel(), 2)
    ev["t"] = np.round(np.concatenate([t, t + 300])).astype(np.int64)
    ev["p"] = 1
    ev = ev[(ev["t"] >= 0)]
    return ev[np.argsort(ev["t"], kind="stable")]


@pytest.mark.parametrize("speed,angle", [(0.2, 0.0), (0.5, 30.0), (1.0, 120.0), (0.8, -75.0)])
def test_a_sweeping_edge_gives_its_normal_speed_and_direction(speed, angle):
    ev = edge_events(speed, angle, jitter_us=100.0)
    fl = normal_flow(ev, W, H, 50_000, np.array([[32, 32], [30, 35]]), radius_px=6, half_ms=10.0, min_events=8)
    assert fl["ok"].all() and (fl["r2"] > 0.9).all()
    th0 = np.radians(angle)  # where the edge is at 50 ms: through (32, 32); (30, 35) lies -2 cos + 3 sin px along u
    assert np.allclose(fl["offset_px"], [0.0, -(-2 * np.cos(th0) + 3 * np.sin(th0))], atol=0.3)
    th = np.radians(angle)
    assert np.allclose(fl["u"], [np.cos(th), np.sin(th)], atol=0.03)
    assert np.allclose(fl["speed_dt"], 1000 * speed, rtol=0.05)  # px/s


def test_noise_is_not_an_edge_and_too_few_events_fit_nothing():
    rng = np.random.default_rng(1)
    ev = np.zeros(20_000, EVENT_DTYPE)
    ev["x"], ev["y"] = rng.integers(0, W, ev.size), rng.integers(0, H, ev.size)
    ev["t"] = np.sort(rng.integers(0, 100_000, ev.size))
    px = np.stack(np.meshgrid(np.arange(8, 56, 4), np.arange(8, 56, 4)), -1).reshape(-1, 2)
    fl = normal_flow(ev, W, H, 50_000, px, radius_px=6, half_ms=10.0, min_events=8)
    assert fl["ok"].mean() > 0.9 and np.mean(fl["r2"] >= 0.6) < 0.02
    few = normal_flow(ev[:40], W, H, 50_000, px, radius_px=6, half_ms=10.0, min_events=8)
    assert not few["ok"].any() and (few["speed_dt"] == 0).all()


def test_pixel_jacobians_match_the_pinhole():
    rec = scene()[0]
    cam = rec.camera
    P = np.array([[0.1, 1.2, 0.0], [-0.3, 0.8, 0.4]])
    J = pixel_jacobians(cam, P)
    h = 1e-4
    for a in range(3):
        d = np.zeros(3)
        d[a] = h
        fd = (cam.project(P + d) - cam.project(P - d)) / (2 * h)
        assert np.allclose(J[:, :, a], fd, rtol=1e-5, atol=1e-6)


def test_the_factor_compares_the_boundary_points_image_velocity_with_the_flow(monkeypatch):
    """The spline scene (a fast high_knees, its true poses): with every boundary point given a flow along x of 0 px/s
    (the measurement replaced, ``min_cos`` 0 to keep them all), E_flow's rows predict each point's x image velocity
    from the pose's velocity (units per second) as finite differences of the posed points' pixels do; the energy
    is the squared mismatch, its gradient and Hessian those of its value."""
    from eventcap.energy import flow as flow_module
    from eventcap.energy.boundary import boundary_samples
    from eventcap.energy.kernels import premultiplied_weights, shared_kernels

    rec, _, t_det, t_us, S = scene()[:5]
    gt = rec.ground_truth

    def poses(t, deriv=0):
        t = np.asarray(t, dtype=np.float64)
        if deriv == 0:
            return np.stack([np.interp(t, gt.t_us, gt.poses[:, k]) for k in range(33)], -1)
        return (poses(t + 500.0) - poses(t - 500.0)) / 1e-3  # per second

    def along_x(events, width, height, t_us, pixels, *args):
        B = len(pixels)
        return {"ok": np.ones(B, bool), "u": np.tile([1.0, 0.0], (B, 1)), "speed_dt": np.zeros(B),
                "r2": np.ones(B), "n": np.full(B, 10.0), "offset_px": np.zeros(B)}

    monkeypatch.setattr(flow_module, "normal_flow", along_x)
    ev = np.zeros(1, EVENT_DTYPE)
    inputs = WindowInputs(int(t_det[0]), int(t_det[-1]), track_times_us=(t_us,), events=ev)
    cfg = FlowNoise(gain=1.0, min_cos=0.0, sigma_px_s=50.0, loss_scale=0.0)
    f = NormalFlow(cfg, rec.template, rec.camera, NormalFlow.samples(inputs, cfg).size)
    f.collect(inputs)
    f.relinearize(Estimate(poses, 0, inputs, rec.template, rec.camera))
    bs = boundary_samples(rec.template, rec.camera, poses(f.t_us))
    assert f.n_measured == bs.n > 500
    WX = premultiplied_weights(bs.rest_points, bs.weights)
    kern = shared_kernels(rec.template.rest_joints, f.n)

    def pixels(Sx):
        G = kern.transforms(np.ascontiguousarray(Sx))
        return rec.camera.project(np.einsum("bk,bkc->bc", WX, G[bs.frame]))

    vx = (pixels(poses(f.t_us + 100.0)) - pixels(poses(f.t_us - 100.0)))[:, 0] / 2e-4  # px/s
    V = poses(f.t_us, 1)
    pred = np.einsum("pq,pq->p", f.rows["a"], V[f.rows["frame"]])
    assert np.abs(vx).max() > 100  # the knee moves
    assert np.allclose(pred, vx, rtol=0.02, atol=2.0)
    lin = f.linearize(V, None, 2)
    assert np.isclose(lin.value, 0.5 / 50.0 ** 2 * np.sum(pred ** 2), rtol=1e-9)
    rng = np.random.default_rng(0)
    dV = rng.normal(0, 1.0, V.shape)
    h = 1e-3
    fd = (f.linearize(V + h * dV, None, 0).value - f.linearize(V - h * dV, None, 0).value) / (2 * h)
    assert np.isclose(fd, np.sum(lin.grad * dV), rtol=1e-6)
    g2 = f.linearize(V + h * dV, None, 1).grad
    assert np.allclose((g2 - lin.grad) / h, np.einsum("fab,fb->fa", lin.diag, dV), rtol=1e-5, atol=1e-6)
    # the Cauchy loss: quadratic near 0, logarithmic beyond its scale (c = 2 σ = 100 px/s)
    f.config = FlowNoise(gain=1.0, min_cos=0.0, sigma_px_s=50.0, loss_scale=2.0)
    c2 = 100.0 ** 2
    assert np.isclose(f.linearize(V, None, 0).value, 0.5 / 50.0 ** 2 * np.sum(c2 * np.log1p(pred ** 2 / c2)))
