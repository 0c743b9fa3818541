"""The motion prior and the context pull (not in the paper): what a window's spline knows besides its observations.

- :class:`MotionPrior` — λ_prior Σ_p g_p ∫ (S_p^(k)(t))² dt over the window, k = 2 (acceleration) or 3 (jerk),
  g_p a gain per pose parameter (the inertia each turns, times the smoothing the fits around the window call for).
  Evaluated at the 3 Gauss points of every knot interval, which integrate a cubic spline's k-th derivative squared
  exactly (:data:`eventcap.energy.spline.GAUSS3`).
- :class:`ContextPull` — λ_context Σ_d Σ_p w_dp (S_p(t_d) - g_p(t_d))² at the window's detection frames: each pose
  parameter held near the smoothing spline g through its per-frame fits around the window, as much as those fits
  know more than the frame's own (w), gated by how still the events show the bones it turns.

:func:`choose_prior_gains` chooses both factors' data from the per-frame fits around a window (no ground truth):
each parameter's fits are samples of a smoothing-spline model y = f + noise, whose smoothing lam_p is chosen by
REML or GCV (:mod:`eventcap.analysis.smoothing`): large where the fits vary no more than their noise (a limb at rest, an
angle the detections cannot tell), small where the parameter moves. In the window's energy a parameter's detections
weigh about a_p (the detection terms' curvature, the mean diagonal of their Hessian at the window's fits / 2) per
rad², so the same trade-off there is a prior weight of a_p · lam_p; the gain is that over λ_prior, clipped to
[1, gain_max]: the prior never gets weaker than its default, and static parameters stop wiggling with the
detections' noise. The context pull's target is the same smoothing splines' values at the window's frames, and
its weight a_p (1 / h_dp - 1), h_dp the smoother's leverage of frame d (1 / h_dp is what the smoother's estimate
at d weighs in frames): a parameter the frames call static (h ≈ 2 / K of K frames) is held near the line through
all K fits, which the window's few frames and its acceleration prior cannot tell (a trend within a window costs the
prior nothing); one that moves (h → 1) is not held.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from eventcap.body.skeleton import DOF_JOINT, NUM_POSE_PARAMS, PARENTS
from eventcap.analysis.smoothing import MIN_KNOTS, GcvCurve, check_criterion

from .errors import EnergyError
from .factor import Factor, Layout, Linearization, Window
from .silence import Silence, knot_gauss_times
from .spline import PRIOR_ORDERS

_NP = NUM_POSE_PARAMS


class MotionPrior(Factor):
    """λ_prior Σ_p g_p ∫ (S_p^(k))² dt (module doc); k from ``prior`` (acceleration | jerk), g the window's
    ``prior_gain`` (1 when the window has none)."""

    name = "prior"
    settings = ("prior",)

    def __init__(self, weight, config, template, camera, layout):
        if config.prior not in PRIOR_ORDERS:
            raise EnergyError(f"prior: expected one of {sorted(PRIOR_ORDERS)}, got {config.prior!r}")
        self.derivative = PRIOR_ORDERS[config.prior]
        super().__init__(weight, config, template, camera, layout)
        self.w = np.zeros((self.n, _NP))

    @staticmethod
    def size(layout: Layout) -> int:
        return 3 * layout.n_seg

    def prepare(self, window: Window) -> None:
        t_q, _, w_q = knot_gauss_times(window.need("knots_us", "the motion prior"))
        if t_q.size != self.n:
            raise EnergyError(f"the motion prior: expected {self.n // 3} knot intervals, got {t_q.size // 3}")
        gain = np.ones(_NP) if window.prior_gain is None else np.asarray(window.prior_gain, dtype=np.float64)
        if gain.shape != (_NP,) or not np.all(np.isfinite(gain) & (gain > 0)):
            raise EnergyError(f"the motion prior: expected a positive gain per pose parameter ({_NP},), got "
                              f"{np.shape(window.prior_gain)}")
        self.t_us, self.w = t_q, w_q[:, None] * gain[None, :]

    def linearize(self, S, aux, order):
        WS = self.w * S
        lin = Linearization(self.weight * float(np.sum(WS * S)))
        if order >= 1:
            lin.grad = (2.0 * self.weight) * WS
        if order >= 2:
            lin.diag = np.zeros((self.n, _NP, _NP))
            idx = np.arange(_NP)
            lin.diag[:, idx, idx] = (2.0 * self.weight) * self.w
        return lin


class ContextPull(Factor):
    """λ_context Σ_d Σ_p w_dp (S_p(t_d) - g_dp)² at the window's detection frames (module doc); (g, w) the window's
    ``pull``."""

    name = "context"

    @staticmethod
    def size(layout: Layout) -> int:
        return layout.n_det

    def prepare(self, window: Window) -> None:
        self.t_us = np.asarray(window.need("t_det_us", "the context pull"), dtype=np.int64)
        if window.pull is None:  # no context for this window: nothing to hold
            self.target, self.w = np.zeros((self.n, _NP)), np.zeros((self.n, _NP))
            return
        target, weight = (np.asarray(v, dtype=np.float64) for v in window.pull)
        if (target.shape != (self.n, _NP) or weight.shape != target.shape or not np.all(np.isfinite(target))
                or not np.all(np.isfinite(weight) & (weight >= 0))):
            raise EnergyError(f"the context pull: expected a target and weights >= 0 of shape ({self.n}, {_NP}), "
                              f"got {target.shape} and {weight.shape}")
        self.target, self.w = target, weight

    def linearize(self, S, aux, order):
        R = S - self.target
        WR = self.w * R
        lin = Linearization(self.weight * float(np.sum(WR * R)))
        if order >= 1:
            lin.grad = (2.0 * self.weight) * WR
        if order >= 2:
            lin.diag = np.zeros((self.n, _NP, _NP))
            idx = np.arange(_NP)
            lin.diag[:, idx, idx] = (2.0 * self.weight) * self.w
        return lin


# --------------------------------------------------------------------------------------------- their data
@dataclass(frozen=True)
class PriorGain:
    """The motion prior's gain per pose parameter of one window and the context pull, from the fits around it."""

    gain: np.ndarray  #: (33,) in [1, gain_max]
    lam: np.ndarray  #: (33,) smoothing parameter of each parameter's fits (s³; NaN: too few fits)
    curvature: np.ndarray  #: (33,) the detection terms' curvature a_p at the window's fits
    n_fits: int  #: fits in the context
    pull: tuple[np.ndarray, np.ndarray] | None = None  #: the context pull's (target, frames' worth 1/h - 1), each
    #: (D, 33); its weight is curvature · frames' worth (None: off)


def choose_prior_gains(t_ctx_us: np.ndarray, fits: np.ndarray, curvature: Callable[[], np.ndarray],
                       lam_prior: float, gain_max: float, criterion: str, t_det_us: np.ndarray | None = None,
                       window_fits: np.ndarray | None = None,
                       unwrap: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None) -> PriorGain:
    """The gains (and, with t_det_us, the context pull) from the per-frame fits (K, 33) at times t_ctx_us (K,)
    around a window (module doc). curvature(): the detection terms' curvature a_p (33,) at the window's fits
    (called only when needed); window_fits (D, 33): the fits at the window's frames t_det_us, the pull's target
    where the smoother has no value; unwrap(S, ref): the root angles of S moved to ref's branch."""
    K = len(t_ctx_us)
    want_pull = t_det_us is not None
    gains_on = lam_prior > 0 and gain_max > 1
    if K < MIN_KNOTS or not (gains_on or want_pull):
        return PriorGain(np.ones(_NP), np.full(_NP, np.nan), np.full(_NP, np.nan), K)
    t = np.asarray(t_ctx_us, dtype=np.int64)
    curve = GcvCurve((t - t[0]) * 1e-6)
    a = curvature()
    gain, lam = gains_from_fits(t, fits, a, lam_prior if gains_on else 1.0, gain_max if gains_on else 1.0,
                                criterion, curve)
    pull = None
    if want_pull:
        g, h = smoothed_at(t, fits, lam, np.asarray(t_det_us, dtype=np.int64), curve)
        frames = np.zeros_like(g)
        for d in np.flatnonzero(np.isfinite(h[:, 0])):
            if unwrap is not None:
                g[d] = unwrap(g[d], window_fits[d])
            frames[d] = np.maximum(1.0 / h[d] - 1.0, 0.0)
        pull = (np.where(np.isfinite(g), g, window_fits), frames)
    return PriorGain(gain, lam, a, K, pull)


def _gating_joints() -> list[np.ndarray]:
    """Per pose parameter, the joints whose bones it turns: a joint angle's the children of its joint, the root's
    rotation and translation the pelvis and its children."""
    root = np.concatenate([[0], np.flatnonzero(PARENTS == 0)])
    return [np.flatnonzero(PARENTS == j) for j in DOF_JOINT] + [root] * (_NP - len(DOF_JOINT))


_GATING = _gating_joints()


def still_gate(silence: Silence, t_us: np.ndarray, floor: float) -> np.ndarray:
    """(len(t_us), 33) in [floor, 1]: how still each pose parameter is at t_us by the events, the least stillness of
    the bones it turns (:func:`_gating_joints`) in the knot interval holding t, as floor + (1 - floor) · stillness
    (floor 0: the stillness itself; 1: every parameter 1, no gate)."""
    if not (isinstance(floor, (int, float)) and not isinstance(floor, bool) and 0.0 <= floor <= 1.0):
        raise EnergyError(f"still_gate: floor: expected a number in [0, 1], got {floor!r}")
    k = np.clip(np.searchsorted(silence.edges_us, np.asarray(t_us, dtype=np.int64), side="right") - 1, 0,
                silence.stillness.shape[0] - 1)
    st = silence.stillness[k]
    gate = np.stack([st[:, j].min(axis=1) for j in _GATING], axis=1)
    return gate if floor == 0.0 else floor + (1.0 - floor) * gate


def smoothed_at(t_us: np.ndarray, fits: np.ndarray, lam: np.ndarray, t_at_us: np.ndarray,
                curve: GcvCurve | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(g, h), both (len(t_at_us), P): the cubic smoothing splines through each column p of fits (K, P) at times
    t_us (K,) with smoothing parameter lam_p (s³), and their leverage (hat-matrix diagonal, in (0, 1]), at those
    of t_us that t_at_us names (:meth:`eventcap.analysis.smoothing.GcvCurve.fitted`; curve: the GcvCurve of t_us if already
    built); NaN rows where t_at_us is not among t_us."""
    t = np.asarray(t_us, dtype=np.int64)
    curve = GcvCurve((t - t[0]) * 1e-6) if curve is None else curve
    rows = np.searchsorted(t, t_at_us)
    hit = (rows < t.size) & (t[np.minimum(rows, t.size - 1)] == t_at_us)
    g = np.full((len(t_at_us), np.shape(fits)[1]), np.nan)
    h = np.full_like(g, np.nan)
    g[hit], h[hit] = curve.fitted(fits, lam, rows[hit])
    return g, h


def gains_from_fits(t_us: np.ndarray, fits: np.ndarray, curvature: np.ndarray, lam_prior: float,
                    gain_max: float, criterion: str, curve: GcvCurve | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(gain (P,), lam (P,)): each column p of fits (K, P) at times t_us (K,) gets the smoothing parameter lam_p
    (s³) of a cubic smoothing spline through it chosen by ``criterion`` (reml | gcv), and the gain
    clip(curvature_p · lam_p / lam_prior, 1, gain_max) (module doc; curve: the GcvCurve of t_us if already
    built)."""
    check_criterion(criterion)
    t = np.asarray(t_us, dtype=np.int64)
    curve = GcvCurve((t - t[0]) * 1e-6) if curve is None else curve
    Y = np.asarray(fits, dtype=np.float64)
    lam = curve.choose_each(Y, criterion)
    return np.clip(np.asarray(curvature) * lam / lam_prior, 1.0, float(gain_max)), lam


__all__ = ["ContextPull", "MotionPrior", "PriorGain", "choose_prior_gains", "gains_from_fits", "smoothed_at",
           "still_gate"]
