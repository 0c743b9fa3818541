"""The robust losses of the energy's terms, in one place (as Ceres' ``LossFunction``): ρ(s) of a squared whitened
residual s = r² / σ² and its first two derivatives, for every term that is not least squares.

    l2       ρ(s) = s
    huber    ρ(s) = s                      for s <= a²,   2 a √s - a²      beyond   (linear in |r| beyond a)
    cauchy   ρ(s) = a² log(1 + s / a²)                                              (logarithmic beyond a)

``a`` is the loss's scale in sigmas: the residual (in sigmas) up to which the loss is about quadratic. Each is
ρ(s) ≈ s for small s, so a term's energy ½ Σ ρ(r² / σ²) is the negative log-likelihood of Gaussian noise for its
inliers. :func:`residual_loss` gives the same loss as a function of a signed residual r (ρ(r²) and its derivatives
in r: the form a term with an exact Hessian in its residuals needs); :func:`rho_expression` the CasADi expression of
the Cauchy loss (the detection terms' exact Hessians).
"""

from __future__ import annotations

import numpy as np

#: The losses :func:`rho` knows.
LOSSES = ("l2", "huber", "cauchy")
#: A squared scale so large that the Cauchy loss is least squares to double precision at the residuals of a fit.
L2_SCALE2 = 1e12


def check_loss(kind: str) -> str:
    """kind itself if it is a loss of :data:`LOSSES`, else ValueError naming them."""
    if kind not in LOSSES:
        raise ValueError(f"loss: expected one of {', '.join(LOSSES)}, got {kind!r}")
    return kind


def rho(s: np.ndarray, kind: str, a: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ρ(s), ρ'(s), ρ''(s) elementwise for squared whitened residuals s >= 0, loss ``kind`` of scale ``a`` (module
    doc)."""
    check_loss(kind)
    s = np.asarray(s, dtype=np.float64)
    if kind == "l2":
        return s.copy(), np.ones_like(s), np.zeros_like(s)
    if not a > 0:
        raise ValueError(f"loss scale: expected a scale > 0 for {kind}, got {a!r}")
    a2 = a * a
    if kind == "cauchy":
        q = 1.0 + s / a2
        return a2 * np.log1p(s / a2), 1.0 / q, -1.0 / (a2 * q * q)
    inside = s <= a2
    root = np.sqrt(np.maximum(s, a2))
    return (np.where(inside, s, 2.0 * a * root - a2), np.where(inside, 1.0, a / root),
            np.where(inside, 0.0, -0.5 * a / (root * root * root)))


def residual_loss(r: np.ndarray, kind: str, a: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ρ(r²), d/dr ρ(r²) = 2 r ρ'(s) and d²/dr² ρ(r²) = 2 ρ'(s) + 4 r² ρ''(s) elementwise for signed residuals r
    (already whitened, or in the units of ``a``)."""
    r = np.asarray(r, dtype=np.float64)
    s = r * r
    v, d1, d2 = rho(s, kind, a)
    return v, 2.0 * r * d1, 2.0 * d1 + 4.0 * s * d2


def irls_weight(s: np.ndarray, kind: str, a: float = 1.0) -> np.ndarray:
    """ρ'(s): the weight iteratively reweighted least squares gives a residual with squared whitened value s (1 for
    an inlier, smaller for an outlier)."""
    return rho(s, kind, a)[1]


def rho_expression(sq, s2):
    """The Cauchy loss s2 · log(1 + sq / s2) of a squared residual sq at squared scale s2, as a CasADi expression
    (sq, s2 symbols or values, in the same units; s2 = :data:`L2_SCALE2` times the residuals' scale is least
    squares)."""
    import casadi as ca

    return s2 * ca.log1p(sq / s2)


__all__ = ["L2_SCALE2", "LOSSES", "check_loss", "irls_weight", "residual_loss", "rho", "rho_expression"]
