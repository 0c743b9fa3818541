"""The motion prior and the context pull (not in the paper): what a window's spline knows besides its observations.

- :class:`MotionPrior` — Σ_p ½ / q_p ∫ (S_p^(k)(t))² dt over the window, k = 2 (acceleration) or 3 (jerk): each
  pose parameter a white-noise-acceleration process of power q_p (the negative log-likelihood of that process, as
  every noise-modelled term's energy is its residuals'), q_p chosen from the data: the restricted likelihood (REML)
  on the per-frame fits around the window (:func:`process_noise`). Evaluated at the 3 Gauss points of every knot
  interval, which integrate a cubic spline's k-th derivative squared exactly (:data:`eventcap.energy.spline.GAUSS3`).
  A perfect detector's fits choose the motion's own roughness, a noisy one's a smoother motion; the events then
  carry what the fits do not show. Optionally (``moving_gain`` < 1) the events gate it: where they show a part
  moving, its prior weighs less.
- :class:`ContextPull` — gain Σ_d Σ_p w_dp (S_p(t_d) - g_p(t_d))² at the window's detection frames: each pose
  parameter held near the smoothing spline g through its per-frame fits around the window, as much as those fits
  know more than the frame's own (w), gated by how still the events show the bones it turns (off by default).

:func:`context_smoothing` measures the context pull's evidence from the per-frame fits around a window (no ground
truth): each parameter's fits are samples of a smoothing-spline model y = f + noise, whose smoothing lam_p is chosen
by REML or GCV (:mod:`eventcap.analysis.smoothing`). In the window's energy a parameter's detections weigh about a_p
(the detection terms' curvature, the mean diagonal of their Hessian at the window's fits / 2) per rad²; the pull's
target is the smoothing splines' values at the window's frames, and its weight a_p (1 / h_dp - 1), h_dp the
smoother's leverage of frame d (1 / h_dp is what the smoother's estimate at d weighs in frames): a parameter the frames
call static (h ≈ 2 / K of K frames) is held near the line through all K fits; one that moves (h → 1) is not held.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from eventcap.analysis.smoothing import MIN_KNOTS, GcvCurve, check_criterion
from eventcap.body.skeleton import DOF_JOINT, NUM_POSE_PARAMS, PARENTS
from .errors import EnergyError
from .factor import Factor, Linearization
from .settings import ContextNoise, PriorNoise, SmoothingConfig
from .silence import Silence, knot_gauss_times
from .spline import PRIOR_ORDERS

_NP = NUM_POSE_PARAMS


class MotionPrior(Factor):
    """Σ_p ½ / q_p ∫ (S_p^(k))² dt times the gain (module doc); k from ``order`` (acceleration | jerk), q_p each
    parameter's process power from the window's ``context_fits`` evidence (:func:`process_noise`), ``q_default``
    where they are too few."""

    name = "prior"
    needs = ("knots_us",)  # its evidence (the fits around the window, the stillness) is optional
    Config = None
    Noise = PriorNoise

    def __init__(self, config, template, camera, n):
        if config.order not in PRIOR_ORDERS:
            raise EnergyError(f"terms.prior.order: expected one of {sorted(PRIOR_ORDERS)}, got {config.order!r}")
        self.derivative = PRIOR_ORDERS[config.order]
        super().__init__(config, template, camera, n)
        self.w = np.zeros((self.n, _NP))
        self.gain: np.ndarray | None = None
        self.n_context = 0
        self.process: ProcessNoise | None = None
        self.moving: float | None = None

    @classmethod
    def samples(cls, inputs, config) -> np.ndarray:
        knots = inputs.knots_us
        return np.zeros(0, dtype=np.int64) if knots is None else knot_gauss_times(knots)[0]

    def collect(self, inputs) -> None:
        t_q, _, w_q = knot_gauss_times(inputs.need("knots_us", "the motion prior"))
        if t_q.size != self.n:
            raise EnergyError(f"the motion prior: expected {self.n // 3} knot intervals, got {t_q.size // 3}")
        self._collect_process(inputs, t_q, w_q)

    def _collect_process(self, inputs, t_q: np.ndarray, w_q: np.ndarray) -> None:
        """g_p = ½ / q_p from the window's process evidence (:func:`process_noise`; ``q_default`` where it has
        none)."""
        q = np.full(_NP, float(self.config.q_default))
        ctx = inputs.evidence("context_fits") if self.derivative == 2 else None
        self.process, self.n_context = None, 0
        if ctx is not None:
            self.process = process_noise(ctx[0], ctx[1], str(self.config.pool), float(self.config.q_max_ratio),
                                         float(self.config.q_min))
            if self.process.q is not None:
                q, self.n_context = np.asarray(self.process.q, dtype=np.float64), self.process.n_fits
        if q.shape != (_NP,) or not np.all(np.isfinite(q) & (q > 0)):
            raise EnergyError(f"the motion prior: expected a positive process power per pose parameter ({_NP},), "
                              f"got {q}")
        self.gain = 0.5 / q
        self.t_us, self.w = t_q, w_q[:, None] * self.gain[None, :]
        self._base, self._inputs, self.moving = self.w, inputs, None

    def relinearize(self, estimate) -> None:
        """The events lead: where the window's stillness evidence (measured around the solve's start, once) shows the
        bones a parameter turns moving, its prior weighs ``moving_gain`` of the fits' choice."""
        floor = float(self.config.moving_gain)
        if floor >= 1.0 or self.moving is not None:
            return
        sil = self._inputs.evidence("stillness")
        if sil is None:
            return
        gate = still_gate(sil, self.t_us, floor)
        self.w = self._base * gate
        self.moving = float(np.mean(gate < 0.5 * (1.0 + floor)))

    def start_penalty(self) -> tuple[int, np.ndarray]:
        return self.derivative, max(self.weight, 1e-12) * (1.0 if self.gain is None else self.gain)

    def report(self) -> dict:
        return {} if self.gain is None else {"prior_power": [float(0.5 / g) for g in self.gain]}

    def describe(self) -> str | None:
        if not self.n_context:
            return "motion prior: too few fits around the window to choose its power: q_default"
        q = 0.5 / self.gain
        gated = "" if self.moving is None else (f"; {100 * self.moving:.0f}% of (time, parameter) pairs free where "
                                                f"the events show motion")
        return (f"motion prior: process power from {self.n_context} fits around the window (restricted likelihood): "
                f"median {float(np.median(q[:30])):.3g} rad²/s³ over the angles, {float(np.median(q[30:])):.3g} "
                f"m²/s³ for the root's translation{gated}")

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
    needs = ("t_det_us",)  # no smoothing evidence (smoothing.min_fps): nothing to hold, by rule
    Config = None
    Noise = ContextNoise

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


@dataclass(frozen=True)
class ProcessNoise:
    """The motion's process noise around a window (a window's evidence, :func:`process_noise`): q (33,) each pose
    parameter's white-noise acceleration power ((rad or m)² / s³; None: too few fits), lam (33,) the smoothing
    (s³) the restricted likelihood chose on the fits, n_fits."""

    q: np.ndarray | None
    lam: np.ndarray | None
    n_fits: int


#: The pose parameters sharing one smoothing with ``pool=group``: the angles (joint angles and root rotation) and
#: the root's translation (as the frames-only smoother pools them, plugins/eventcap_smooth).
POWER_GROUPS = (slice(0, 30), slice(30, 33))


def process_noise(t_us: np.ndarray, fits: np.ndarray, pool: str = "parameter", max_ratio: float = 100.0,
                  q_min: float = 1e-12) -> ProcessNoise:
    """Each pose parameter's process power q_p from the per-frame fits (K, 33) at times t_us (K,) around a window:
    the fits as y = f + e, f a white-noise acceleration of power q (a cubic smoothing spline's prior), e the fits'
    own white noise, both chosen by the restricted likelihood (REML: the smoothing lam = sigma² / q maximises it,
    :meth:`eventcap.analysis.smoothing.GcvCurve.choose_reml`, sigma² its estimate there, q = sigma² / lam:
    :meth:`~eventcap.analysis.smoothing.GcvCurve.power`), per group of parameters (``pool=group``,
    :data:`POWER_GROUPS`) or per parameter held within ``max_ratio`` of its group's. A detector's fixed offsets move
    every fit alike and are no noise here; a perfect detector's fits give their own roughness. Never from ground
    truth. No power is below ``q_min``."""
    K = len(t_us)
    if K < MIN_KNOTS:
        return ProcessNoise(None, None, K)
    t = np.asarray(t_us, dtype=np.int64)
    curve = GcvCurve((t - t[0]) * 1e-6)
    Y = np.asarray(fits, dtype=np.float64)
    lam, q = np.empty(_NP), np.empty(_NP)
    for g in POWER_GROUPS:
        cols = np.arange(_NP)[g]
        lam_g = curve.choose_reml(Y[:, g]).lam
        q_group = float(np.mean(curve.power(Y[:, g], np.full(cols.size, lam_g))))  # the pooled noise over lam
        if pool == "group":
            lam[g], q[g] = lam_g, q_group
        else:
            lam[g] = curve.choose_each(Y[:, g], "reml")
            q[g] = np.clip(curve.power(Y[:, g], lam[g]), q_group / max_ratio, q_group * max_ratio)
    return ProcessNoise(np.maximum(q, float(q_min)), lam, K)


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


__all__ = ["ContextPull", "ContextSmoothing", "MotionPrior", "POWER_GROUPS",
           "ProcessNoise", "SmoothingConfig", "context_smoothing", "process_noise", "smoothed_at",
           "still_gate"]
