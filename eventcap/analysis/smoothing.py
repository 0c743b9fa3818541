"""Smoothing splines' smoothing parameter chosen from the data alone: generalised cross-validation (GCV) and the
restricted (marginal) likelihood (REML) of a cubic smoothing spline through samples y_i at times x_i,

    sum_i (y_i - f(x_i))^2 + lam * integral f''(x)^2 dx          (x in seconds, lam in s³)

shared by the frames-only smoother (plugins/eventcap_smooth) and the spline solve's per-parameter motion prior
(plugins/eventcap_spline). With the smoother's values at the knots f = H(lam) y = (I + lam K)^-1 y (K the natural
cubic spline's penalty matrix, :func:`penalty_matrix`):

    GCV(lam) = n · sum_c |(I - H) y_c|^2 / (n - tr H)^2              (Craven & Wahba 1979)

summed over the columns c that share one lam. GCV tends to undersmooth when the samples are few; REML (e.g. Wood
2011, J. R. Stat. Soc. B 73) does not, see :meth:`GcvCurve.reml`. Never from ground truth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MIN_KNOTS = 5  # a smoothing spline needs at least 5 knots (scipy's make_smoothing_spline too)
CRITERIA = ("reml", "gcv")  # how lam is chosen from the data: :meth:`GcvCurve.choose_reml` | :meth:`GcvCurve.choose`


def check_criterion(criterion: str) -> str:
    """criterion itself if it is one of :data:`CRITERIA`, else ValueError naming them."""
    if criterion not in CRITERIA:
        raise ValueError(f"criterion: expected one of {', '.join(CRITERIA)}, got {criterion!r}")
    return criterion


@dataclass(frozen=True)
class GcvChoice:
    lam: float          # the smoothing parameter (s³)
    dof: float          # tr H: effective number of parameters (2: a straight line .. n: interpolation)
    sigma: np.ndarray   # residual standard deviation per column, sqrt(RSS / (n - tr H))
    gcv: float


def penalty_matrix(x: np.ndarray) -> np.ndarray:
    """K (n, n) with integral f''² = y^T K y for the natural cubic spline interpolating y at knots x (Green &
    Silverman 1994, Sec. 2.1: K = Q R^-1 Q^T). The smoothing spline's values at the knots are (I + lam K)^-1 y."""
    x = np.asarray(x, dtype=np.float64)
    n = x.size
    h = np.diff(x)
    Q = np.zeros((n, n - 2))
    j = np.arange(n - 2)
    Q[j, j] = 1.0 / h[:-1]
    Q[j + 1, j] = -1.0 / h[:-1] - 1.0 / h[1:]
    Q[j + 2, j] = 1.0 / h[1:]
    R = np.diag((h[:-1] + h[1:]) / 3.0) + np.diag(h[1:-1] / 6.0, 1) + np.diag(h[1:-1] / 6.0, -1)
    return Q @ np.linalg.solve(R, Q.T)


class GcvCurve:
    """GCV and REML of every lam for the columns of some Y at fixed knots, from one eigendecomposition
    K = U diag(d) U^T: H(lam) = U diag(1 / (1 + lam d)) U^T, so after one projection U^T Y, tr H and the residuals
    cost O(n·C) per lam, and the whole grid of lam is two small matrix products (:meth:`table`)."""

    def __init__(self, x: np.ndarray):
        self.x = np.asarray(x, dtype=np.float64)
        if self.x.size < MIN_KNOTS:
            raise ValueError(f"a smoothing spline needs at least {MIN_KNOTS} knots, got {self.x.size}")
        d, self.U = np.linalg.eigh(penalty_matrix(self.x))
        self.d = np.maximum(d, 0.0)  # two zero eigenvalues (straight lines), the rest positive

    def score(self, Y: np.ndarray, lam: float) -> tuple[float, float, np.ndarray]:
        """(GCV, tr H, RSS per column) for the columns of Y (n, C)."""
        n = self.x.size
        z = self.U.T @ np.asarray(Y, dtype=np.float64).reshape(n, -1)
        shrink = lam * self.d / (1.0 + lam * self.d)  # eigenvalues of I - H
        rss = np.sum((shrink[:, None] * z) ** 2, axis=0)
        tr = float(np.sum(1.0 / (1.0 + lam * self.d)))
        return float(n * rss.sum() / max(n - tr, 1e-9) ** 2), tr, rss

    def fitted(self, Y: np.ndarray, lam: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(values, leverage), both (len(rows), C): each column c of Y (n, C) smoothed with its own lam[c], H(lam_c) y_c,
        and H(lam_c)'s diagonal, at the knots ``rows``."""
        U = self.U[np.asarray(rows, dtype=np.int64)]  # (r, n)
        shrink = 1.0 / (1.0 + np.asarray(lam, dtype=np.float64)[None, :] * self.d[:, None])  # (n, C): H's eigenvalues
        z = self.U.T @ np.asarray(Y, dtype=np.float64).reshape(self.x.size, -1)
        return U @ (shrink * z), (U * U) @ shrink

    def grid(self, decades: tuple[float, float] = (-4.0, 10.0), per_decade: int = 20) -> np.ndarray:
        """The lam the criteria try: h³ · 10^k, k in ``decades`` (h the median knot spacing: from near interpolation
        to near a straight line), ``per_decade`` points per decade."""
        h3 = float(np.median(np.diff(self.x))) ** 3
        ks = np.linspace(decades[0], decades[1], int(round((decades[1] - decades[0]) * per_decade)) + 1)
        return np.array([h3 * 10.0**k for k in ks])  # scalar powers: the same lam, to the bit, as chosen before

    def table(self, Y: np.ndarray, lams: np.ndarray, criterion: str, pooled: bool = True) -> np.ndarray:
        """The criterion (reml | gcv) of every lam in ``lams`` (L,) for the columns of Y (n, C), all at once:
        (L,) when the columns share one lam (``pooled``), else (L, C), each column on its own. One projection
        z = U^T Y serves every lam: the residuals' and the penalised components' sums of squares are
        (L, n) @ (n, C) products. Equal to :meth:`score` (GCV) and :meth:`reml` lam by lam."""
        check_criterion(criterion)
        n = self.x.size
        z2 = (self.U.T @ np.asarray(Y, dtype=np.float64).reshape(n, -1)) ** 2  # (n, C)
        ld = np.asarray(lams, dtype=np.float64)[:, None] * self.d[None, :]  # (L, n)
        if criterion == "gcv":
            rss = (ld / (1.0 + ld)) ** 2 @ z2  # (L, C): |(I - H) y_c|^2
            tr = np.sum(1.0 / (1.0 + ld), axis=1)
            den = np.maximum(n - tr, 1e-9) ** 2
            return n * rss.sum(axis=1) / den if pooled else n * rss / den[:, None]
        pen = self.d > 1e-9 * self.d.max()
        w = ld[:, pen] / (1.0 + ld[:, pen])  # (L, m): 1 / variance factor of the penalised components
        q = w @ z2[pen]  # (L, C)
        m, C = int(pen.sum()), z2.shape[1]
        logdet = np.sum(np.log(w), axis=1)
        if pooled:
            return m * C * np.log(np.maximum(q.sum(axis=1), 1e-300) / (m * C)) - C * logdet
        return m * np.log(np.maximum(q, 1e-300) / m) - logdet[:, None]

    def _choose(self, Y: np.ndarray, criterion: str, decades: tuple[float, float], per_decade: int) -> GcvChoice:
        """The lam of :meth:`grid` minimising ``criterion`` for the columns of Y together, with its GCV summary."""
        lams = self.grid(decades, per_decade)
        lam = float(lams[int(np.argmin(self.table(Y, lams, criterion)))])
        g, tr, rss = self.score(Y, lam)
        return GcvChoice(lam=lam, dof=tr, sigma=np.sqrt(rss / max(self.x.size - tr, 1e-9)), gcv=g)

    def choose(self, Y: np.ndarray, decades: tuple[float, float] = (-4.0, 10.0), per_decade: int = 20) -> GcvChoice:
        """The lam minimising GCV for the columns of Y, over :meth:`grid`."""
        return self._choose(Y, "gcv", decades, per_decade)

    def reml(self, Y: np.ndarray, lam: float) -> float:
        """-2 log restricted (marginal) likelihood of the columns of Y (n, C) for one lam, up to a constant, with
        the noise variance profiled out (one per call: the columns share it). In the eigenbasis z = U^T y the
        penalised components are independent with variance sigma² (1 + lam d_i) / (lam d_i); the two unpenalised
        ones (straight lines) carry no information on lam and are left out (restricted likelihood)."""
        return float(self.table(Y, np.array([lam]), "reml")[0])

    def choose_reml(self, Y: np.ndarray, decades: tuple[float, float] = (-4.0, 10.0),
                    per_decade: int = 20) -> GcvChoice:
        """The lam maximising the restricted likelihood (REML) on the same grid as :meth:`choose`. With few fits
        GCV often picks near-interpolation (measured: 10 of 11 degrees of freedom on dance_spin's 0.4 s, MPJVE
        1768 mm/s), REML does not (2.2, MPJVE 366 mm/s) and agrees with GCV where GCV is sound."""
        return self._choose(Y, "reml", decades, per_decade)

    def choose_by(self, Y: np.ndarray, criterion: str) -> GcvChoice:
        """The lam that ``criterion`` (reml | gcv, :data:`CRITERIA`) chooses for the columns of Y."""
        return self.choose_reml(Y) if check_criterion(criterion) == "reml" else self.choose(Y)

    def power(self, Y: np.ndarray, lam: np.ndarray) -> np.ndarray:
        """(C,): the process power q_c = sigma_c² / lam_c of each column c of Y (n, C) at its smoothing lam_c (s³):
        its noise variance sigma_c² the restricted likelihood's estimate at that lam (the mean over the penalised
        components of z_i² lam d_i / (1 + lam d_i), the components' variance being sigma² (1 + lam d_i) / (lam d_i) =
        sigma² + q / d_i). Where the samples are noise-free, lam -> 0 and q tends to their own roughness, the mean of
        z_i² d_i: a finite power either way."""
        n = self.x.size
        z2 = (self.U.T @ np.asarray(Y, dtype=np.float64).reshape(n, -1)) ** 2  # (n, C)
        pen = self.d > 1e-9 * self.d.max()
        ld = np.asarray(lam, dtype=np.float64)[None, :] * self.d[pen][:, None]  # (m, C)
        return np.mean(z2[pen] * self.d[pen][:, None] / (1.0 + ld), axis=0)

    def choose_each(self, Y: np.ndarray, criterion: str) -> np.ndarray:
        """(C,): the lam ``criterion`` chooses for each column of Y (n, C) on its own, as :meth:`choose_by` would
        column by column, in one pass over the grid."""
        lams = self.grid()
        return lams[np.argmin(self.table(Y, lams, criterion, pooled=False), axis=0)]
