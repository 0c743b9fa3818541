"""Fusing the detections of many frames through event odometry (an extension, not in the paper).

The batch solve of Sec. 3.2 keeps each batch's two detection fits and so can only improve the frames between
them. Its gain over ``linear`` is bounded by the interpolation error, which at 25 fps is a few mm, against ~34 mm
of detector error at the frames on our synthetic captures. Linking many detection frames through the events can
average that error instead. Two stages do it, after a solve in mode ``odometry`` (batch.py):

- ``fuse`` (whole recording) reads every batch's odometry. S_0 of batch k is the fit at intensity frame k, and
  S_N − S_0 is the event-only step to frame k+1. It solves a pose graph over the intensity-frame poses X_k, per
  pose parameter::

      min_X  sum_k w_k |X_k - fit_k|^2 + rho sum_k |X_{k+1} - X_k - step_k|^2

  w_k = 1 where there is a fit (the last frame has none: its detection belongs to no batch's S_0). rho = 0 in the
  config means estimated from the data alone (:func:`innovation_rho`).
- ``place`` (per batch) puts each batch's event trajectory onto the graph: anchored at X_k, with the mismatch at
  frame N spread linearly, so batch k ends exactly where batch k+1 starts.

The estimate of rho needs many batches (the fusion against linear: docs/results/implementation.md).
"""

from __future__ import annotations

import numpy as np

from eventcap.artifacts.pose import PoseSequence
from eventcap.body.skeleton import THETA_SLICE
from eventcap.core.stage import StageFailed

#: Below this many steps between fitted frames, an estimated rho is flagged as unreliable in the log.
FEW_STEPS = 10


def pose_graph(fits: np.ndarray, steps: np.ndarray, rho: float, fit_weights: np.ndarray | None = None) -> np.ndarray:
    """argmin_X sum_k w_k |X_k - fits_k|^2 + rho sum_k |X_{k+1} - X_k - steps_k|^2, per parameter: (K+1, P).

    fits (K+1, P) (rows with weight 0 are ignored), steps (K, P), fit_weights (K+1,) default all 1. The problem
    must be determined: at least one fit, and rho > 0 unless every frame has one."""
    fits = np.asarray(fits, dtype=np.float64)
    n = fits.shape[0]
    w = np.ones(n) if fit_weights is None else np.asarray(fit_weights, dtype=np.float64)
    D = np.zeros((n - 1, n))
    D[np.arange(n - 1), np.arange(n - 1)] = -1.0
    D[np.arange(n - 1), np.arange(1, n)] = 1.0
    A = np.diag(w) + rho * D.T @ D
    rhs = w[:, None] * np.nan_to_num(fits) + rho * D.T @ np.asarray(steps, dtype=np.float64)
    return np.linalg.solve(A, rhs)


def innovation_rho(fits: np.ndarray, steps: np.ndarray) -> float:
    """The pose graph's weight estimated from the data alone, without ground truth.

    The innovation r_k = fits_{k+1} - fits_k - steps_k = e_{k+1} - e_k - o_k mixes the fits' errors e and the
    odometry's errors o. If both are independent over k, Var(r) = 2 var(e) + var(o) and Cov(r_k, r_{k+1}) =
    -var(e); rho = var(e) / var(o), pooled over the joint angles (the root's parameters have other units; per
    parameter, the small variances of a few dozen batches are too noisy).
    Needs at least 3 steps (ValueError otherwise)."""
    r = (np.diff(fits, axis=0) - steps)[:, THETA_SLICE]
    if r.shape[0] < 3:
        raise ValueError(f"estimating rho needs at least 3 steps between fitted frames, got {r.shape[0]}")
    r = r - r.mean(axis=0)
    var_r = np.mean(r * r, axis=0)
    var_e = np.maximum(-np.mean(r[:-1] * r[1:], axis=0), 0.0)
    var_o = np.maximum(var_r - 2.0 * var_e, 0.0)
    return float(var_e.sum() / max(var_o.sum(), 1e-12))


def place(x0: np.ndarray, x1: np.ndarray, shape: np.ndarray, t_us: np.ndarray) -> np.ndarray:
    """A batch's relative trajectory shape (N+1, P) (shape[0] = 0) anchored at x0, its end moved onto x1 by a
    correction growing linearly in time: (N+1, P), first row x0, last row x1."""
    t = np.asarray(t_us, dtype=np.float64)
    a = ((t - t[0]) / (t[-1] - t[0]))[:, None]
    return x0[None, :] + shape + a * (x1 - x0 - shape[-1])[None, :]


def run_fuse(inputs, config, ctx):
    from .batch import unwrap_root

    seq = inputs["odometry"]
    K = len(seq)
    if K < 1:
        raise StageFailed("fuse: no batches of odometry", status="invalid_input")
    t_frames, fits, steps = [], [], []
    for k in range(K):
        ps = seq[k]
        t = np.asarray(ps.t_us, dtype=np.int64)
        if t_frames and t[0] != t_frames[-1]:
            raise StageFailed(f"fuse: batch {seq.batches[k].index} starts at t = {int(t[0])} us, but the batch "
                              f"before it ends at {int(t_frames[-1])} us: the batches must be contiguous",
                              status="invalid_input")
        S0 = unwrap_root(ps.poses[0], fits[-1]) if fits else ps.poses[0]
        if not t_frames:
            t_frames.append(int(t[0]))
        t_frames.append(int(t[-1]))
        fits.append(S0)
        steps.append(ps.poses[-1] - ps.poses[0])
        ctx.report(k + 1, K)
    fits.append(np.full_like(fits[0], np.nan))  # frame K: no batch starts there
    fits, steps = np.stack(fits), np.stack(steps)
    w = np.r_[np.ones(K), 0.0]
    if config.rho > 0:
        rho, how = float(config.rho), "from the config"
    else:
        try:
            rho, how = innovation_rho(fits[:K], steps[:K - 1]), "estimated from the innovations"
        except ValueError as exc:
            raise StageFailed(f"fuse: {exc} ({K} batches); give stages.fuse.rho > 0", status="invalid_input") from exc
    X = pose_graph(fits, steps, rho, w)
    ctx.log.info("fuse: %d batches, rho %.3g (%s)", K, rho, how)
    if config.rho <= 0 and K - 1 < FEW_STEPS:
        ctx.log.warning("fuse: rho estimated from only %d steps is unreliable (on short captures the fusion can "
                        "be worse than linear); set stages.fuse.rho", K - 1)
    ctx.stats.update({"rho": rho, "rho_estimated": config.rho <= 0})
    return {"anchors": PoseSequence(t_us=np.asarray(t_frames, dtype=np.int64), poses=X, status="fused",
                                    iterations=0, energies={"rho": rho})}


def run_place(inputs, config, ctx):
    odo, anchors = inputs["odometry"], inputs["anchors"]
    t = np.asarray(odo.t_us, dtype=np.int64)
    ta = np.asarray(anchors.t_us, dtype=np.int64)
    k = int(np.searchsorted(ta, t[0]))
    if k + 1 >= ta.size or ta[k] != t[0] or ta[k + 1] != t[-1]:
        raise StageFailed(f"place: the fused anchors have no frames at this batch's ends (t = {int(t[0])} and "
                          f"{int(t[-1])} us)", status="invalid_input")
    poses = place(anchors.poses[k], anchors.poses[k + 1], odo.poses - odo.poses[0], t)
    return {"poses": PoseSequence(t_us=t.copy(), poses=poses, status=odo.status, iterations=odo.iterations,
                                  energies=dict(odo.energies))}
