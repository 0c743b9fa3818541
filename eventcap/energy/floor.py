"""The floor and foot contact (not in the paper): what one camera knows about depth from the ground the feet stand on.

A foot that rests on the floor is at the floor's height and does not slide. The camera sees the foot's ray; the
floor cuts that ray at one depth, so a resting foot's depth (and, through the legs, the body's) follows from its
2D position and the floor, which the detector's metric depth does not give to better than ~7 cm. As in PhysCap
(Shimada et al., SIGGRAPH Asia 2020) and the contact heads of WHAM (CVPR 2024) and GVHMR (SIGGRAPH Asia 2024), but
with contact measured from the data instead of learned:

- **the floor** (:func:`floor_height`): world y is up (the project's convention; a level world for uncalibrated
  recordings), so the floor is the plane y = h. h is the median over the capture's intensity frames of the lowest
  sole point (heels and toes of the template's landmarks) of each frame's per-frame fit: most of the time a foot
  is on the floor, and the median of many independent fits averages their few centimetres of noise;
- **contact** (:func:`contact_weights`), per knot of the window's spline and sole point, in [0, 1]: the product of
  how slowly the point moves in the current estimate (exp(-(v / v0)²), v0 = ``contact.speed_mps``), how near the
  floor it is there (exp(-(max(0, y - h) / dh)²), dh = ``contact.height_m``) and how still the events show the foot
  (the event-silence stillness of the ankle and foot joints, :mod:`.silence`; 1 when it is not measured);
- :class:`FloorContact` (``floor``): λ_floor Σ_k Σ_s [c_ks (y_s(S_k) - h)² + max(0, h - y_s(S_k))²] at the knots:
  a sole point in contact is on the floor, and none is below it (metres²);
- :class:`FootSlide` (``slide``): λ_slide Σ_k Σ_s c_ks c_(k+1)s ‖Δ_xz p_s‖² / Δt between neighbouring knots: a
  sole point in contact does not slide along the floor (its horizontal speed squared, integrated over the
  contact; m²/s).

The contact weights are associated with the estimate at each ICP round, like E_cor's correspondences.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from eventcap.body.kinematics import landmark_positions
from eventcap.body.skeleton import JOINT_INDEX, LANDMARK_INDEX, NUM_POSE_PARAMS

from .errors import EnergyError
from .factor import Factor, Linearization
from .settings import FloorNoise, SlideNoise

_NP = NUM_POSE_PARAMS
#: The sole points: heels and toes (BODY_25 landmarks of the template).
SOLE_LANDMARKS = ("l_big_toe", "l_small_toe", "l_heel", "r_big_toe", "r_small_toe", "r_heel")
_SOLE = np.array([LANDMARK_INDEX[n] for n in SOLE_LANDMARKS])
#: The joints whose event stillness tells whether each sole point's foot moves (ankle and foot of its side).
_FOOT_JOINTS = {s: [JOINT_INDEX[f"{s[0]}_ankle"], JOINT_INDEX[f"{s[0]}_foot"]] for s in SOLE_LANDMARKS}


def sole_points(S: np.ndarray, template) -> np.ndarray:
    """World positions (T, 6, 3) of the sole points (:data:`SOLE_LANDMARKS`) of poses S (T, 33)."""
    return landmark_positions(np.atleast_2d(S), template)[:, _SOLE]


def floor_height(sole_y: np.ndarray) -> float | None:
    """The floor's height (world y, m) from the sole points' heights (K, 6) of K per-frame fits over a capture: the
    median over the frames of each frame's lowest sole point (module doc); None without a finite frame."""
    y = np.asarray(sole_y, dtype=np.float64)
    if y.ndim != 2 or y.shape[1] != len(SOLE_LANDMARKS):
        raise EnergyError(f"floor_height: expected sole heights of shape (K, {len(SOLE_LANDMARKS)}), got {y.shape}")
    low = np.min(y, axis=1)
    low = low[np.isfinite(low)]
    return float(np.median(low)) if low.size else None


def contact_weights(points: np.ndarray, speed: np.ndarray, floor_y: float, speed_mps: float, height_m: float,
                    stillness: np.ndarray | None = None) -> np.ndarray:
    """(K, 6) in [0, 1]: how surely each sole point is in contact at K knots (module doc) from its position (K, 6, 3)
    and speed (K, 6) m/s in the current estimate, the floor's height, and the event stillness (K, 24) of the joints
    at the knots (None: not measured)."""
    if not (speed_mps > 0 and height_m > 0):
        raise EnergyError(f"contact: expected a speed and a height > 0, got {speed_mps!r} m/s, {height_m!r} m")
    above = np.maximum(points[..., 1] - floor_y, 0.0)
    c = np.exp(-(np.asarray(speed) / speed_mps) ** 2) * np.exp(-(above / height_m) ** 2)
    if stillness is not None:
        st = np.clip(np.asarray(stillness, dtype=np.float64), 0.0, 1.0)
        c = c * np.stack([st[:, _FOOT_JOINTS[s]].min(axis=1) for s in SOLE_LANDMARKS], axis=1)
    return c


def knot_stillness(stillness: np.ndarray | None, n_knots: int) -> np.ndarray | None:
    """The stillness (n_seg, 24) per knot interval at the n_seg + 1 knots: the least of the intervals meeting there."""
    if stillness is None:
        return None
    st = np.asarray(stillness, dtype=np.float64)
    if st.shape[0] + 1 != n_knots:
        raise EnergyError(f"contact: stillness of {st.shape[0]} knot intervals for {n_knots} knots")
    return np.minimum(np.vstack([st[:1], st]), np.vstack([st, st[-1:]]))


def contact_at(poses, knots_us: np.ndarray, template, floor_y: float, stillness: np.ndarray | None,
               config) -> np.ndarray:
    """(K, 6) in [0, 1]: each sole point's contact at the K knots (:func:`contact_weights`) in the estimate
    ``poses`` (a function of times), its speed from differences a quarter knot interval either side; stillness:
    the joints' (n_seg, 24) per knot interval (None: not measured); config: speed_mps and height_m
    (:class:`eventcap.energy.window.ContactConfig`)."""
    knots = np.asarray(knots_us, dtype=np.int64)
    dt_s = float(np.median(np.diff(knots))) * 1e-6 if knots.size > 1 else 1.0
    h = max(1, int(dt_s * 1e6) // 4)
    p = sole_points(poses(knots), template)
    ta, tb = np.maximum(knots - h, knots[0]), np.minimum(knots + h, knots[-1])
    v = (sole_points(poses(tb), template) - sole_points(poses(ta), template)) / ((tb - ta) * 1e-6)[:, None, None]
    st = knot_stillness(stillness, knots.size)
    return contact_weights(p, np.linalg.norm(v, axis=-1), floor_y, float(config.speed_mps), float(config.height_m),
                           st)


class _Contact(Factor):
    """Shared by the floor terms: samples at the window's knots, the estimate's contact weights (:func:`contact_at`,
    computed once per estimate for both terms) at each round."""

    def __init__(self, config, template, camera, n):
        super().__init__(config, template, camera, n)
        self.floor_y = 0.0
        self.contact = np.zeros((self.n, len(SOLE_LANDMARKS)))
        self.dt_s = 1.0
        self.active = False

    @classmethod
    def samples(cls, inputs, config) -> np.ndarray:
        knots = inputs.knots_us
        return np.zeros(0, dtype=np.int64) if knots is None else knots

    def collect(self, inputs) -> None:
        super().collect(inputs)
        knots = self.t_us
        self.dt_s = float(np.median(np.diff(knots))) * 1e-6 if knots.size > 1 else 1.0
        self.contact = np.zeros((self.n, len(SOLE_LANDMARKS)))
        self.active = False
        self._inputs = inputs

    def relinearize(self, estimate) -> None:
        floor_y = self._inputs.evidence("floor_y")
        self.active = floor_y is not None
        if not self.active:  # no floor known: nothing to hold
            self.contact = np.zeros((self.n, len(SOLE_LANDMARKS)))
            return
        self.floor_y = float(floor_y)
        inputs, t = self._inputs, self.t_us
        still = inputs.evidence("stillness")
        self.contact = estimate.memo(("contact", t.tobytes()), lambda: contact_at(
            estimate.poses, t, self.template, self.floor_y, None if still is None else still.stillness, inputs.contact))

    def report(self) -> dict:
        return {f"{self.name}_contact": float(self.contact.mean())} if self.active else {}


def _zero(S, order) -> Linearization:
    n = S.shape[0]
    return Linearization(0.0, np.zeros_like(S) if order >= 1 else None,
                         np.zeros((n, _NP, _NP)) if order >= 2 else None)


def _sole_expression(template, S):
    """The sole points (6, 3) of the pose S (33,) as a CasADi expression."""
    L = landmark_positions(S, template)
    return ca.vertcat(*[L[int(i), :] for i in _SOLE])


class FloorContact(_Contact):
    """λ_floor Σ_k Σ_s [c_ks (y_s - h)² + max(0, h - y_s)²] at the knots (module doc). Exact Hessian (CasADi)."""

    name = "floor"
    needs = ("knots_us",)  # no floor known (no fit succeeded, none offered): nothing to hold, by rule
    Config = None
    Noise = FloorNoise

    @classmethod
    def noise_precision(cls, config, camera) -> float:
        return 0.5 / (1e-3 * float(config.sigma_mm)) ** 2  # the residuals are heights, m

    def __init__(self, config, template, camera, n):
        from .detections import _MappedTerm

        super().__init__(config, template, camera, n)
        S, c, h = ca.SX.sym("S", _NP), ca.SX.sym("c", len(SOLE_LANDMARKS)), ca.SX.sym("h")
        y = _sole_expression(template, S)[:, 1]
        below = ca.fmax(h - y, 0)
        e = ca.sum1(c * (y - h) ** 2 + below ** 2)
        self._fn = _MappedTerm("E_floor", e, S, [c, h], self.n) if self.n else None

    def linearize(self, S, aux, order):
        if not self.active:  # no floor known for this window
            return _zero(S, order)
        data = [self.contact.ravel(), np.full(self.n, self.floor_y)]
        e, g, H = self._fn(S, data, order)
        w = self.weight
        return Linearization(w * float(e.sum()), None if g is None else w * g, None if H is None else w * H)


class FootSlide(_Contact):
    """λ_slide Σ_k Σ_s c_ks c_(k+1)s ‖Δ_xz p_s‖² / Δt between neighbouring knots (module doc). Exact Hessian."""

    name = "slide"
    needs = ("knots_us",)  # no floor known (no fit succeeded, none offered): nothing to hold, by rule
    Config = None
    Noise = SlideNoise

    @classmethod
    def noise_precision(cls, config, camera) -> float:
        return 0.5 / (1e-3 * float(config.sigma_mm_s)) ** 2  # the integral of the squared sliding speed, m/s
    couples_neighbours = True

    def __init__(self, config, template, camera, n):
        from .detections import _MappedTerm

        super().__init__(config, template, camera, n)
        S0, S1 = ca.SX.sym("S0", _NP), ca.SX.sym("S1", _NP)
        c, inv_dt = ca.SX.sym("c", len(SOLE_LANDMARKS)), ca.SX.sym("inv_dt")
        d = _sole_expression(template, S1) - _sole_expression(template, S0)
        e = inv_dt * ca.sum1(c * (d[:, 0] ** 2 + d[:, 2] ** 2))
        self._fn = _MappedTerm("E_slide", e, ca.vertcat(S0, S1), [c, inv_dt], self.n - 1) if self.n > 1 else None

    def linearize(self, S, aux, order):
        w = self.weight
        if self._fn is None or not self.active:
            return _zero(S, order)
        pair = self.contact[:-1] * self.contact[1:]
        e, g, H = self._fn(np.concatenate([S[:-1], S[1:]], axis=1),
                           [pair.ravel(), np.full(self.n - 1, 1.0 / self.dt_s)], order)
        lin = Linearization(w * float(e.sum()))
        if g is not None:
            grad = np.zeros_like(S)
            grad[:-1] += g[:, :_NP]
            grad[1:] += g[:, _NP:]
            lin.grad = w * grad
        if H is not None:
            diag = np.zeros((self.n, _NP, _NP))
            diag[:-1] += H[:, :_NP, :_NP]
            diag[1:] += H[:, _NP:, _NP:]
            lin.diag, lin.upper = w * diag, w * H[:, :_NP, _NP:]
        return lin


__all__ = ["SOLE_LANDMARKS", "FloorContact", "FloorNoise", "FootSlide", "SlideNoise", "contact_at", "contact_weights",
           "floor_height", "knot_stillness", "sole_points"]
