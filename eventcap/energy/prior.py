"""The motion prior and the context pull (not in the paper): what a window's spline knows besides its observations.

- :class:`MotionPrior` — λ_prior Σ_p g_p ∫ (S_p^(k)(t))² dt over the window, k = 2 (acceleration) or 3 (jerk),
  g_p a gain per pose parameter (the inertia each turns, times the smoothing the fits around the window call for).
  Evaluated at the 3 Gauss points of every knot interval, which integrate a cubic spline's k-th derivative squared
  exactly (:data:`eventcap.energy.spline.GAUSS3`).
- :class:`ContextPull` — λ_context Σ_d Σ_p w_dp (S_p(t_d) - g_p(t_d))² at the window's detection frames: each pose
  parameter held near the smoothing spline g through its per-frame fits around the window, as much as those fits
  know more than the frame's own (w), gated by how still the events show the bones it turns.

:func:`context_smoothing` measures both factors' evidence from the per-frame fits around a window (no ground truth):
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

from eventcap.analysis.smoothing import MIN_KNOTS, GcvCurve, check_criterion
from eventcap.body.segments import inertia_prior_gain
from eventcap.body.skeleton import DOF_JOINT, NUM_POSE_PARAMS, PARENTS
from .errors import EnergyError
from .factor import Factor, Linearization
from .settings import ContextConfig, PriorConfig, SmoothingConfig
from .silence import Silence, knot_gauss_times
from .spline import PRIOR_ORDERS

_NP = NUM_POSE_PARAMS


class MotionPrior(Factor):
    """λ_prior Σ_p g_p ∫ (S_p^(k))² dt (module doc); k from ``order`` (acceleration | jerk), g the inertia gain of
    each parameter times the gain the fits around the window call for (:class:`ContextSmoothing`; 1 without)."""

    name = "prior"
    Config = PriorConfig

    def __init__(self, config, template, camera, n):
        if config.order not in PRIOR_ORDERS:
            raise EnergyError(f"terms.prior.order: expected one of {sorted(PRIOR_ORDERS)}, got {config.order!r}")
        self.derivative = PRIOR_ORDERS[config.order]
        super().__init__(config, template, camera, n)
        self.w = np.zeros((self.n, _NP))
        self.gain: np.ndarray | None = None
        self.n_context = 0
        try:
            self.base = None if config.inertia == 0 else inertia_prior_gain(
                template.rest_joints, float(config.inertia), float(config.inertia_cap), float(config.inertia_floor))
        except ValueError as exc:
            raise EnergyError(f"terms.prior.inertia: {exc}") from exc

    @classmethod
    def samples(cls, inputs, config) -> np.ndarray:
        knots = inputs.knots_us
        return np.zeros(0, dtype=np.int64) if knots is None else knot_gauss_times(knots)[0]

    def collect(self, inputs) -> None:
        t_q, _, w_q = knot_gauss_times(inputs.need("knots_us", "the motion prior"))
        if t_q.size != self.n:
            raise EnergyError(f"the motion prior: expected {self.n // 3} knot intervals, got {t_q.size // 3}")
        gain, self.n_context = None, 0
        gain_max = float(self.config.gain_max)
        if self.weight > 0 and gain_max > 1:
            ctx = inputs.evidence("smoothing")
            if ctx is not None and ctx.lam is not None:
                gain = np.clip(np.asarray(ctx.curvature) * ctx.lam / self.weight, 1.0, gain_max)
                self.n_context = ctx.n_fits
        if self.base is not None:
            gain = self.base * (1.0 if gain is None else gain)
        self.gain = gain
        g = np.ones(_NP) if gain is None else np.asarray(gain, dtype=np.float64)
        if g.shape != (_NP,) or not np.all(np.isfinite(g) & (g > 0)):
            raise EnergyError(f"the motion prior: expected a positive gain per pose parameter ({_NP},), got {g.shape}")
        self.t_us, self.w = t_q, w_q[:, None] * g[None, :]

    def start_penalty(self) -> tuple[int, np.ndarray]:
        return self.derivative, max(self.weight, 1e-12) * (1.0 if self.gain is None else self.gain)

    def report(self) -> dict:
        return {} if self.gain is None else {"prior_gain": [float(v) for v in self.gain]}

    def describe(self) -> str | None:
        if not self.n_context:
            return None
        g, top = self.gain, float(self.config.gain_max)
        return (f"motion prior gains from {self.n_context} frames around the window: median "
                f"{float(np.median(g)):.3g}, {int(np.sum(g >= top * (1 - 1e-9)))} of 33 parameters at the largest "
                f"({top:g})")

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
    """λ_context Σ_d Σ_p w_dp (S_p(t_d) - g_dp)² at the window's detection frames (module doc): (g, w) from the
    window's context evidence (:class:`ContextSmoothing`), w gated by the joints' stillness (:func:`still_gate`)."""

    name = "context"
    Config = ContextConfig

    @classmethod
    def samples(cls, inputs, config) -> np.ndarray:
        t = inputs.t_det_us
        return np.zeros(0, dtype=np.int64) if t is None else t

    def collect(self, inputs) -> None:
        super().collect(inputs)
        self.target, self.w = np.zeros((self.n, _NP)), np.zeros((self.n, _NP))
        self._inputs, self.frames = inputs, None
        ctx = inputs.evidence("smoothing")
        self._ctx = None if ctx is None or ctx.target is None else ctx  # none: nothing to hold

    def relinearize(self, estimate) -> None:
        if self._ctx is None:
            return
        frames = self._ctx.frames
        sil = self._inputs.evidence("stillness")
        if sil is not None:  # a part the events see move is not held to the frames' smoother
            frames = frames * still_gate(sil, self.t_us, float(self.config.gate_floor))
        target = self._ctx.target
        held = np.isfinite(target).all(axis=1)
        self.set_pull(np.where(held[:, None], target, 0.0), self._ctx.curvature * np.where(held[:, None], frames, 0.0))
        self.frames = frames

    def set_pull(self, target: np.ndarray, weight: np.ndarray) -> None:
        """The pull's target (n, 33) and weight (n, 33) (set from the context evidence at each round)."""
        target, weight = (np.asarray(v, dtype=np.float64) for v in (target, weight))
        if (target.shape != (self.n, _NP) or weight.shape != target.shape or not np.all(np.isfinite(target))
                or not np.all(np.isfinite(weight) & (weight >= 0))):
            raise EnergyError(f"the context pull: expected a target and weights >= 0 of shape ({self.n}, {_NP}), "
                              f"got {target.shape} and {weight.shape}")
        self.target, self.w = target, weight

    def report(self) -> dict:
        return {} if self.frames is None else {"context_pull_frames": [float(v) for v in self.frames.mean(0)]}

    def describe(self) -> str | None:
        if self.frames is None:
            return None
        return f"context pull: median {float(np.median(self.frames)):.2f} frames' worth per parameter and frame"

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


# --------------------------------------------------------------------------------------------- their evidence
@dataclass(frozen=True)
class ContextSmoothing:
    """What the per-frame fits around a window say of each pose parameter (a window's evidence, module doc): lam (33,)
    each parameter's smoothing (s³; None: too few fits), curvature a_p (33,) of the detection terms at the window's
    fits, n_fits, and at the window's detection frames the smoother's value, target (D, 33), and its weight in
    frames, 1/h - 1 (D, 33)."""

    lam: np.ndarray | None
    curvature: np.ndarray | None
    n_fits: int
    target: np.ndarray | None = None
    frames: np.ndarray | None = None


def context_smoothing(t_ctx_us: np.ndarray, fits: np.ndarray, curvature: Callable[[], np.ndarray], criterion: str,
                      t_det_us: np.ndarray, window_fits: np.ndarray,
                      unwrap: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None) -> ContextSmoothing:
    """The context evidence of a window from the per-frame fits (K, 33) at times t_ctx_us (K,) around it (module
    doc). curvature(): the detection terms' curvature a_p (33,) at the window's fits (called only with enough fits);
    window_fits (D, 33): the fits at the window's frames t_det_us, the target where the smoother has no value;
    unwrap(S, ref): the root angles of S moved to ref's branch."""
    K = len(t_ctx_us)
    if K < MIN_KNOTS:
        return ContextSmoothing(None, None, K)
    check_criterion(criterion)
    t = np.asarray(t_ctx_us, dtype=np.int64)
    curve = GcvCurve((t - t[0]) * 1e-6)
    a = curvature()
    lam = curve.choose_each(np.asarray(fits, dtype=np.float64), criterion)
    g, h = smoothed_at(t, fits, lam, np.asarray(t_det_us, dtype=np.int64), curve)
    frames = np.zeros_like(g)
    for d in np.flatnonzero(np.isfinite(h[:, 0])):
        if unwrap is not None:
            g[d] = unwrap(g[d], window_fits[d])
        frames[d] = np.maximum(1.0 / h[d] - 1.0, 0.0)
    return ContextSmoothing(lam, a, K, np.where(np.isfinite(g), g, window_fits), frames)


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




__all__ = ["ContextConfig", "ContextPull", "ContextSmoothing", "MotionPrior", "PriorConfig", "SmoothingConfig",
           "context_smoothing", "gains_from_fits", "smoothed_at", "still_gate"]
