"""Cubic smoothing splines through per-frame pose fits, their smoothing chosen from the fits alone (REML or GCV).

A careful user with only the intensity frames would not interpolate the per-frame fits linearly: each fit is a few
centimetres off, independently from frame to frame, and a smoothing spline through them averages that noise while
following the motion. For a parameter's fits y_i at times x_i the spline f minimises

    sum_i (y_i - f(x_i))^2 + lam * integral f''(x)^2 dx          (scipy.interpolate.make_smoothing_spline)

with x in seconds, so lam is in s³ whatever the parameter's unit. lam is chosen from the fits alone by generalised
cross-validation (GCV, Craven & Wahba 1979): f = H(lam) y = (I + lam K)^-1 y at the knots (K the spline's
penalty matrix, :func:`penalty_matrix`), and

    GCV(lam) = n · sum_c |(I - H) y_c|^2 / (n - tr H)^2

summed over the columns c that share one lam (a group of parameters: all angles, the root translation, or each
parameter alone). With few fits GCV is noisy and tends to undersmooth; pooling many columns steadies it. It is minimised over a grid of log lam (20 points per decade). Never
from ground truth. The other criterion is the restricted (marginal) likelihood (REML, e.g. Wood 2011,
J. R. Stat. Soc. B 73: GCV is prone to undersmoothing when data are few), see :meth:`GcvCurve.reml`. GCV is the
stage's default (the comparison: docs/results/settings.md, smooth). The residual variance
estimate sum |(I - H) y|^2 / (n - tr H) per column tells the fits' noise.
"""

from __future__ import annotations


import numpy as np

from eventcap.analysis.smoothing import MIN_KNOTS, GcvChoice, GcvCurve, check_criterion

#: The parameter groups sharing one smoothing parameter with ``pool=group`` (skeleton layout S = [theta (27), root
#: rotation (3), root translation (3)]): all angles (joint angles and root rotation, radians) and the root
#: translation (metres). The root rotation alone is too few columns: its GCV can choose interpolation
#: (docs/results/implementation.md).
GROUPS: dict[str, slice] = {"angles": slice(0, 30), "root_translation": slice(30, 33)}
ROOT_ROTATION = slice(27, 30)
POOLS = ("group", "parameter")


def unwrap_root_rotation(poses: np.ndarray) -> np.ndarray:
    """Poses (K, 33) with the root's Euler angles unwrapped along time (no jump of 2π between neighbours), so a
    spin is smoothed as a spin and not across a wrap."""
    out = np.array(poses, dtype=np.float64, copy=True)
    out[:, ROOT_ROTATION] = np.unwrap(out[:, ROOT_ROTATION], axis=0)
    return out


def smooth_poses(t_knots_us: np.ndarray, fits: np.ndarray, t_eval_us: np.ndarray, pool: str, lam: float,
                 criterion: str) -> tuple[np.ndarray, dict[str, GcvChoice]]:
    """Smoothing splines through pose fits (K, 33) at times t_knots_us (K,), evaluated at t_eval_us (T,).

    pool: ``group`` (one lam per parameter group, :data:`GROUPS`) or ``parameter`` (one per parameter); lam > 0
    fixes lam (s³) for all, else it is chosen by ``criterion`` (reml | gcv). Root rotation angles are unwrapped
    first. Returns poses (T, 33) and the
    choice per group (or per parameter index as a string)."""
    from scipy.interpolate import make_smoothing_spline

    if pool not in POOLS:
        raise ValueError(f"pool: expected one of {', '.join(POOLS)}, got {pool!r}")
    check_criterion(criterion)
    t = np.asarray(t_knots_us, dtype=np.int64)
    if t.size < MIN_KNOTS:
        raise ValueError(f"a smoothing spline needs at least {MIN_KNOTS} knots (intensity frames), got {t.size}")
    if np.any(np.diff(t) <= 0):
        raise ValueError("knot times must increase")
    Y = unwrap_root_rotation(fits)
    if not np.all(np.isfinite(Y)):
        raise ValueError("the fits hold non-finite values")
    x = (t - t[0]) * 1e-6
    xe = (np.asarray(t_eval_us, dtype=np.int64) - t[0]) * 1e-6
    if pool == "group":
        cols = {name: np.arange(Y.shape[1])[sl] for name, sl in GROUPS.items()}
    else:
        cols = {str(c): np.array([c]) for c in range(Y.shape[1])}
    out = np.empty((xe.size, Y.shape[1]))
    choices: dict[str, GcvChoice] = {}
    curve = GcvCurve(x)
    for name, c in cols.items():
        if lam > 0:
            g, tr, rss = curve.score(Y[:, c], lam)
            ch = GcvChoice(lam=float(lam), dof=tr, sigma=np.sqrt(rss / max(x.size - tr, 1e-9)), gcv=g)
        else:
            ch = curve.choose_by(Y[:, c], criterion)
        out[:, c] = make_smoothing_spline(x, Y[:, c], lam=ch.lam)(xe)
        choices[name] = ch
    return out, choices
