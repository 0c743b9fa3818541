"""The event-silence prior (not in the paper): a body part that makes no events is not moving.

An edge of log contrast c that crosses a pixel makes about |c| / C events there (C the contrast threshold), so a
limb moving at v px/s makes events along its outline and texture at a rate that grows with v; a limb at rest makes
only the sensor's background activity. Per-frame detection fits cannot tell a resting limb from a slowly moving one
(each fit is a few centimetres off, independently), and a spline through them wiggles; the events can.

How it is measured, per time bin k (the spline's knot intervals) and joint j:

- the bones are projected at the bin's middle from the current estimate (the smoothing spline through the
  per-frame fits, a few pixels off), and sampled at a few points along each bone, away from its ends;
- the events of the bin are counted in a (2r+1)² box around every sample; a bone's *activity* is their mean
  density, in events per pixel per second; joint j's is that of the bone ending at j (the pelvis: the most active
  of its bones to the hips and the spine), since a bone at rest holds both its ends;
- the background rate is the same density over the pixels far from the actor (its projected joints' box plus a
  margin), so flicker and sensor noise are not taken for motion;
- the stillness is s = exp(-max(0, activity - background - 2σ) / rate_hz) in [0, 1], σ the standard deviation of
  the background's density in one box over one bin (Poisson): a noisy sensor's fluctuations are not motion;
- with a hold, a joint is only as still as in its least still bin nearby: a limb that the estimate misplaces by a
  few pixels is silent in its band only in moments;
- with a sweep, a bin's events are counted around the bones wherever the estimate puts them in the bins nearby,
  the most active place counting: between two intensity frames the estimate has a fast limb on its path but not
  on time, and its place at the moment can be silent while the limb's events are a few bins' places away
  (what the hold and the sweep changed: docs/results/implementation.md).

The term (in the spline solve) is λ_still Σ_k Σ_j s_j(k) ∫_bin k ‖d/dt π(x_j(S(t)))‖² dt: the image velocity (px/s)
of every joint the events call still, linearised at the solve's start (d/dt π(x_j) = J_j(S) S'(t) with the Jacobian
J_j held fixed through one solve, a Gauss-Newton form). It constrains what the events see, a joint's image motion,
whatever combination of pose parameters makes it: a root rotation that shakes still legs is penalised, a shoulder
twist that swings the forearm and not the upper arm is not. Motion along the line of sight makes no events and is
left alone: a 3D velocity (tried) also stills limbs swinging towards the camera, which broke the spins and kicks.
A body passing in front of a resting one makes events there: the resting
one is then not called still, which only loses the help, never forces a moving part to rest. A moving part whose
outline and texture cross no pixels looks still; the term is soft.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import cv2
import numpy as np
from scipy.ndimage import minimum_filter1d

from eventcap.body.kinematics import joint_positions
from eventcap.body.skeleton import NUM_JOINTS, NUM_POSE_PARAMS, PARENTS

from .errors import EnergyError
from .factor import Factor, Linearization
from .settings import StillNoise, StillnessConfig
from .kernels import Buffered
from .spline import GAUSS3


@dataclass(frozen=True)
class Silence:
    """Event activity and stillness of each joint per time bin (bins: [edges[k], edges[k+1]) µs)."""

    edges_us: np.ndarray  #: (K+1,) int64 bin edges
    activity_hz: np.ndarray  #: (K, 24) events per pixel per second around the bone ending at each joint (the
    #: pelvis: its most active bone; inf: a bone not in view)
    background_hz: float  #: events per pixel per second far from the actor
    stillness: np.ndarray  #: (K, 24) in [0, 1]: 1 = no more events than the background


def measure_silence(events: np.ndarray, edges_us: np.ndarray, joints_px: np.ndarray, height: int, width: int, *,
                    radius_px: int, rate_hz: float, hold_bins: int, sweep_bins: int, n_samples: int = 4,
                    margin_px: float = 20.0) -> Silence:
    """Stillness of every joint per bin (see the module doc).

    events: structured events (t µs, x, y, p) of the bins' span (others are ignored); edges_us: (K+1,) increasing;
    joints_px: (K, 24, 2) the 24 joints projected at each bin's middle (NaN: behind the camera, left out);
    radius_px: half side of the box counted around each sample; rate_hz: activity above the background (events per
    pixel per second) at which the stillness falls to 1/e; n_samples per bone between 20% and 80% of its length;
    margin_px around the joints' box beyond which pixels are background; hold_bins: a joint is only as still in
    bin k as in its least still bin within k ± hold_bins (a joint must be silent for a while: a limb that the
    estimate places a few pixels off its true path, e.g. a fast oscillation the frames cannot follow, is silent
    in its band only in moments, and a motion's onset is not held back); sweep_bins: bin k's events are counted
    around the bones as projected in each bin k' within k ± sweep_bins and a bone's activity is the largest of
    those (the estimate's path around the moment, not only its place at it: a limb the estimate gets at the right
    place at the wrong time is not called still)."""
    edges = np.asarray(edges_us, dtype=np.int64)
    K = edges.size - 1
    J = np.asarray(joints_px, dtype=np.float64)
    if K < 1 or np.any(np.diff(edges) <= 0):
        raise ValueError(f"measure_silence: expected >= 2 increasing bin edges, got {edges.size}")
    if J.shape != (K, NUM_JOINTS, 2):
        raise ValueError(f"measure_silence: joints_px: expected shape ({K}, {NUM_JOINTS}, 2), got {J.shape}")
    if not (np.isfinite(rate_hz) and rate_hz > 0 and n_samples >= 1):
        raise ValueError(f"measure_silence: expected rate_hz > 0, n_samples >= 1, got {rate_hz!r}, {n_samples!r}")
    for name, v in (("radius_px", radius_px), ("hold_bins", hold_bins), ("sweep_bins", sweep_bins)):
        if isinstance(v, bool) or int(v) != v or v < 0:
            raise ValueError(f"measure_silence: {name}: expected an integer >= 0, got {v!r}")
    r = int(radius_px)
    t = events["t"]
    keep = (t >= edges[0]) & (t < edges[-1])
    ev = events[keep]
    ex, ey = ev["x"].astype(np.int64), ev["y"].astype(np.int64)
    cut = np.searchsorted(ev["t"], edges)  # events of bin k: ev[cut[k]:cut[k + 1]] (sorted by time)
    dur_s = np.diff(edges) * 1e-6
    # background: pixels outside the joints' box (over all bins) + margin, per pixel per second
    fin = J[np.isfinite(J).all(-1)]
    if fin.size:
        lo, hi = fin.min(0) - margin_px, fin.max(0) + margin_px
        xx, yy = np.meshgrid(np.arange(width), np.arange(height))
        bg = (xx < lo[0]) | (xx > hi[0]) | (yy < lo[1]) | (yy > hi[1])
    else:
        bg = np.ones((height, width), dtype=bool)
    counts = np.bincount(ey * width + ex, minlength=height * width).reshape(height, width)
    background = float(counts[bg].sum() / (bg.sum() * dur_s.sum())) if bg.any() else 0.0
    # the mean box density at samples along every bone, per bin: (K, 24) (bone by child joint; 0 is no bone)
    f = 0.2 + 0.6 * (np.arange(n_samples) + 0.5) / n_samples
    child = np.arange(1, NUM_JOINTS)
    P = J[:, PARENTS[child]][:, :, None] * (1 - f)[None, None, :, None] + J[:, child][:, :, None] * f[None, None, :, None]
    ok = np.isfinite(P).all(-1)
    xi = np.clip(np.rint(np.where(ok, P[..., 0], 0)), 0, width - 1).astype(np.int64)
    yi = np.clip(np.rint(np.where(ok, P[..., 1], 0)), 0, height - 1).astype(np.int64)
    # the box's area (clipped at the border) turns counts into density
    area = ((np.minimum(yi + r + 1, height) - np.maximum(yi - r, 0)) *
            (np.minimum(xi + r + 1, width) - np.maximum(xi - r, 0)))
    # bin k's events are looked up at the bones of bins k + o, o in -sweep..sweep (clipped to the bins)
    offsets = np.arange(-int(sweep_bins), int(sweep_bins) + 1)
    dens = np.zeros((K, offsets.size) + xi.shape[1:])
    box = (2 * r + 1, 2 * r + 1)
    for k in range(K):  # the events of bin k within the box around every pixel (zero outside the image)
        a, z = cut[k], cut[k + 1]
        img = np.bincount(ey[a:z] * width + ex[a:z], minlength=height * width).reshape(height, width)
        D = cv2.boxFilter(img.astype(np.float32), -1, box, normalize=False, borderType=cv2.BORDER_CONSTANT)
        kk = np.clip(k + offsets, 0, K - 1)
        dens[k] = np.where(ok[kk], D[yi[kk], xi[kk]] / area[kk], 0.0)
    kk = np.clip(np.arange(K)[:, None] + offsets[None, :], 0, K - 1)  # (K, O)
    bone_n = np.zeros((K, offsets.size, NUM_JOINTS))
    bone_sum = np.zeros((K, offsets.size, NUM_JOINTS))
    bone_sum[..., 1:] = dens.sum(-1)
    bone_n[..., 1:] = ok[kk].sum(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        per_place = np.where(bone_n > 0, bone_sum / np.maximum(bone_n, 1), np.inf) / dur_s[:, None, None]
    activity = per_place.max(1)
    activity[:, 0] = activity[:, np.flatnonzero(PARENTS == 0)].max(1)  # the pelvis: its bones to hips and spine
    # Poisson noise of the background's count in one box over one bin, as a density: activity within 2 of its
    # standard deviations of the background is not motion
    sd = np.sqrt(background / ((2 * r + 1) ** 2 * dur_s))[:, None]
    excess = np.maximum(activity - background - 2.0 * sd, 0.0)
    still = np.exp(-excess / float(rate_hz))
    if hold_bins > 0:
        still = minimum_filter1d(still, size=2 * int(hold_bins) + 1, axis=0, mode="nearest")
    return Silence(edges_us=edges, activity_hz=activity, background_hz=background, stillness=still)


def measure_stillness(poses, knots_us: np.ndarray, template, camera, events: np.ndarray,
                      config: StillnessConfig) -> Silence:
    """The joints' stillness per knot interval of a window (:func:`measure_silence`), the bones projected at each
    interval's middle from ``poses`` (a function of times: the solve's start)."""
    edges = np.asarray(knots_us, dtype=np.int64)
    mids = (edges[:-1] + edges[1:]) // 2
    knot_ms = float(np.median(np.diff(edges))) / 1000.0
    joints = joint_positions(poses(mids), template.rest_joints)
    return measure_silence(events, edges, camera.project(joints), camera.height, camera.width,
                           radius_px=int(config.radius_px), rate_hz=float(config.rate_hz),
                           hold_bins=int(round(config.hold_ms / knot_ms)),
                           sweep_bins=int(round(config.sweep_ms / knot_ms)))


def knot_gauss_times(knots_us: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The 3 Gauss-Legendre points of every knot interval: (times µs (3·K,) float, interval of each (3·K,),
    quadrature weight in seconds of each (3·K,)); exact for polynomials of degree <= 5 over each interval."""
    edges = np.asarray(knots_us, dtype=np.int64)
    K = edges.size - 1
    h = np.diff(edges).astype(np.float64)
    seg = np.repeat(np.arange(K), 3)
    g, wq = GAUSS3
    return edges[seg] + h[seg] * np.tile(g, K), seg, np.tile(wq, K) * h[seg] * 1e-6


class EventSilence(Factor):
    """E_still (module doc): λ_still Σ_k Σ_j s_j(k) ∫_k ‖J_j(S_ref(t)) S'(t)‖² dt, the image velocity (px/s) of every
    joint the events call still (the window's stillness evidence, per knot interval and joint), with the Jacobian J_j
    of joint j's pixel held at the current estimate through a solve (Gauss-Newton, a fixed quadratic form in the
    velocities). Samples: the 3 Gauss points of every knot interval (exact for the cubic spline's velocities)."""

    name = "still"
    needs = ("knots_us", "events")  # its evidence, the stillness, is measured in the events
    Config = None
    Noise = StillNoise
    derivative = 1

    @classmethod
    def noise_precision(cls, config, camera) -> float:
        # the integral of the squared image speed (px/s) of still joints
        return 0.5 / float(config.sigma_px_s) ** 2

    def __init__(self, config, template, camera, n):
        super().__init__(config, template, camera, n)
        S = ca.SX.sym("S", NUM_POSE_PARAMS)
        px = camera.project_sym(joint_positions(S, template.rest_joints).T)  # (2, 24)
        jac = ca.densify(ca.jacobian(ca.reshape(px, 2 * NUM_JOINTS, 1), S))
        self._joint_px_jac = Buffered(ca.Function("joint_px_jac", [S], [jac]).map(self.n))
        self.M = np.zeros((self.n, NUM_POSE_PARAMS, NUM_POSE_PARAMS))
        self.stillness = None

    @classmethod
    def samples(cls, inputs, config) -> np.ndarray:
        knots = inputs.knots_us
        return np.zeros(0, dtype=np.int64) if knots is None else knot_gauss_times(knots)[0]

    def collect(self, inputs) -> None:
        t_q, self._seg, self._w_q = knot_gauss_times(inputs.need("knots_us", "E_still"))
        if t_q.size != self.n:
            raise EnergyError(f"E_still: built for {self.n // 3} knot intervals, the window has {t_q.size // 3}")
        self.t_us = t_q
        self.M = np.zeros((self.n, NUM_POSE_PARAMS, NUM_POSE_PARAMS))
        self._inputs, self.stillness = inputs, None

    def relinearize(self, estimate) -> None:
        sil = self._inputs.evidence("stillness")
        if sil is None:  # no events for this window: nothing is known still
            self.M = np.zeros((self.n, NUM_POSE_PARAMS, NUM_POSE_PARAMS))
            return
        still = np.asarray(sil.stillness, dtype=np.float64)
        if still.shape != (self.n // 3, NUM_JOINTS):
            raise EnergyError(f"E_still: expected stillness of shape ({self.n // 3}, {NUM_JOINTS}), got {still.shape}")
        if not np.all(np.isfinite(still) & (still >= 0)):
            raise EnergyError("E_still: stillness must be finite and >= 0")
        self.stillness = still
        Jq = self._joint_px_jac(estimate.poses(self.t_us))[0].reshape(self.n, NUM_POSE_PARAMS, NUM_JOINTS, 2)
        wjq = still[self._seg] * self._w_q[:, None]  # (Q, 24)
        self.M = np.einsum("qajx,qj,qbjx->qab", Jq, wjq, Jq)

    def linearize(self, S, aux, order):
        MV = np.einsum("qab,qb->qa", self.M, S)  # S: the velocities at the Gauss points
        lin = Linearization(self.weight * float(np.sum(S * MV)))
        if order >= 1:
            lin.grad = (2.0 * self.weight) * MV
        if order >= 2:
            lin.diag = (2.0 * self.weight) * self.M
        return lin


__all__ = ["EventSilence", "Silence", "StillNoise", "StillnessConfig", "knot_gauss_times", "measure_silence",
           "measure_stillness"]
