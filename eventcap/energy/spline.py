"""Uniform cubic B-splines in the pose parameters, and their motion priors in closed form.

A trajectory over a window [t_a, t_a + n_seg·h] is S(t) = Σ_i B_i(t) C_i with n_seg + 3 control points C_i (each a
33-vector of pose parameters) and the uniform cubic B-spline basis B_i on knots spaced h apart. S is C²: positions,
velocities and accelerations are continuous, and any rate can be sampled from it. The basis is non-negative and
sums to 1 (convex hull property), so bounds on the control points bound the whole curve: joint limits on C are
exact limits on S(t) for every t.

Motion priors: ∫ ‖S⁽ᵏ⁾(t)‖² dt over the window for k = 2 (acceleration) or 3 (jerk) is a quadratic form
Σ_p C[:, p]ᵀ Q C[:, p] in the control points. Q is computed exactly: on each knot interval the k-th derivatives of
the four non-zero basis functions are polynomials of degree 3 - k, so a 3-point Gauss-Legendre rule (exact up to
degree 5) integrates their products without error. Q is banded (|i - j| <= 3).

Times are integers in microseconds at the edges (as everywhere); the spline works in seconds inside, so
velocities are per second and the prior is in (units/s^k)²·s.
"""

from __future__ import annotations

import math

import numpy as np

from .settings import PRIOR_ORDERS  # noqa: F401 (the orders the motion prior supports)

#: 3-point Gauss-Legendre rule on [0, 1] (nodes, weights): exact for polynomials up to degree 5.
GAUSS3 = (0.5 + 0.5 * np.array([-math.sqrt(0.6), 0.0, math.sqrt(0.6)]), np.array([5.0, 8.0, 5.0]) / 18.0)


def _local_basis(tau: np.ndarray, deriv: int) -> np.ndarray:
    """(T, 4) values of the four uniform cubic B-spline pieces at local coordinates tau in [0, 1] (d/dtau^deriv)."""
    t = np.asarray(tau, dtype=np.float64)
    if deriv == 0:
        return np.stack([(1 - t) ** 3, 3 * t**3 - 6 * t**2 + 4, -3 * t**3 + 3 * t**2 + 3 * t + 1, t**3], axis=1) / 6.0
    if deriv == 1:
        return np.stack([-((1 - t) ** 2), 3 * t**2 - 4 * t, -3 * t**2 + 2 * t + 1, t**2], axis=1) / 2.0
    if deriv == 2:
        return np.stack([1 - t, 3 * t - 2, 1 - 3 * t, t], axis=1)
    if deriv == 3:
        return np.tile(np.array([-1.0, 3.0, -3.0, 1.0]), (t.size, 1))
    raise ValueError(f"B-spline derivative order: expected 0..3, got {deriv!r}")


class UniformCubicBSpline:
    """The basis of a uniform cubic B-spline starting at ``t0_us`` with knot spacing ``h_us`` and ``n_seg``
    intervals: ``n_ctrl = n_seg + 3`` control points, defined on [t0_us, t0_us + n_seg·h_us]."""

    def __init__(self, t0_us: int, h_us: int, n_seg: int):
        if isinstance(n_seg, bool) or int(n_seg) != n_seg or n_seg < 1:
            raise ValueError(f"UniformCubicBSpline: n_seg must be an integer >= 1, got {n_seg!r}")
        if not (isinstance(h_us, (int, np.integer)) and h_us > 0):
            raise ValueError(f"UniformCubicBSpline: h_us must be a positive integer (microseconds), got {h_us!r}")
        self.t0_us, self.h_us, self.n_seg = int(t0_us), int(h_us), int(n_seg)
        self.n_ctrl = self.n_seg + 3
        self.h_s = self.h_us * 1e-6

    @property
    def t1_us(self) -> int:
        return self.t0_us + self.n_seg * self.h_us

    def _locate(self, t_us) -> tuple[np.ndarray, np.ndarray]:
        t = np.asarray(t_us, dtype=np.float64).ravel()
        u = (t - self.t0_us) / self.h_us
        if t.size and (u.min() < -1e-9 or u.max() > self.n_seg + 1e-9):
            raise ValueError(f"B-spline: times [{t.min():.0f}, {t.max():.0f}] us outside its span "
                             f"[{self.t0_us}, {self.t1_us}] us")
        seg = np.clip(np.floor(u).astype(np.int64), 0, self.n_seg - 1)
        return seg, u - seg

    def basis(self, t_us, deriv: int = 0) -> np.ndarray:
        """(T, n_ctrl) dense basis matrix: S(t) = basis(t) @ C, derivatives per second^deriv."""
        seg, tau = self._locate(t_us)
        B = np.zeros((seg.size, self.n_ctrl))
        vals = _local_basis(tau, deriv) / self.h_s**deriv
        rows = np.arange(seg.size)
        for a in range(4):
            B[rows, seg + a] = vals[:, a]
        return B

    def evaluate(self, C: np.ndarray, t_us, deriv: int = 0) -> np.ndarray:
        """Values (T, ...) of the spline with control points C (n_ctrl, ...) at the times t_us."""
        C = np.asarray(C, dtype=np.float64)
        if C.shape[0] != self.n_ctrl:
            raise ValueError(f"B-spline: expected {self.n_ctrl} control points, got {C.shape[0]}")
        return np.tensordot(self.basis(t_us, deriv), C, axes=(1, 0))

    def gram(self, deriv: int) -> np.ndarray:
        """Q (n_ctrl, n_ctrl) with ∫ (d^deriv S/dt^deriv)² dt = Cᵀ Q C over the spline's span (exact)."""
        if deriv not in (1, 2, 3):
            raise ValueError(f"B-spline prior: derivative order must be 1, 2 or 3, got {deriv!r}")
        g, wq = GAUSS3  # exact for the products (degree <= 4) of these derivatives
        b = _local_basis(g, deriv)  # (3, 4)
        M = (b.T * wq) @ b / self.h_s ** (2 * deriv - 1)  # ∫_0^1 ... dτ, times h for dt, h^-2k for d/dt
        Q = np.zeros((self.n_ctrl, self.n_ctrl))
        for s in range(self.n_seg):
            Q[s:s + 4, s:s + 4] += M
        return Q

    def fit(self, t_us, values: np.ndarray, smooth, deriv: int = 2, ridge: float = 1e-9) -> np.ndarray:
        """Control points (n_ctrl, ...) of the penalised least-squares fit
        min Σ_k ‖S(t_k) - values_k‖² + smooth · ∫ ‖S^(deriv)‖² dt (+ ridge ‖C‖² so that it is always unique).
        smooth: one number, or one per column of values (K, C) (each column then has its own)."""
        B = self.basis(t_us)
        G, I = self.gram(deriv), ridge * np.eye(self.n_ctrl)
        v = np.asarray(values, dtype=np.float64)
        V = B.T @ v.reshape(v.shape[0], -1)
        if np.ndim(smooth) == 0:
            return np.linalg.solve(B.T @ B + float(smooth) * G + I, V).reshape((self.n_ctrl,) + v.shape[1:])
        sm = np.asarray(smooth, dtype=np.float64).ravel()
        if sm.size != V.shape[1]:
            raise ValueError(f"fit: {sm.size} smoothing values for {V.shape[1]} columns")
        A = (B.T @ B + I)[None] + sm[:, None, None] * G[None]
        return np.linalg.solve(A, V.T[:, :, None])[:, :, 0].T.reshape((self.n_ctrl,) + v.shape[1:])
