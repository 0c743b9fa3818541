"""The Laplace approximation at a solve's solution: the covariance of its poses, and of the joints, in millimetres.

Read the energy E(x) of a :class:`eventcap.energy.problem.FactorProblem` as a negative log-likelihood: near its
minimum x*, p(x) ∝ exp(-E(x)) ≈ N(x*, H⁻¹) with H the Hessian of E at x* (the exact Hessian the solve gives IPOPT,
proximal pull included: it is what bounds the directions nothing observes). The energy's terms are not likelihoods of
unit noise, so H⁻¹ is right only up to a global scale: the confidence stage calibrates it
(:mod:`eventcap.analysis.uncertainty`).

Cost. x = (pose units U, auxiliary variables A). The auxiliary variables (E_3D's t' per detection frame, a few per
window) are eliminated by their Schur complement, H_U = H_UU - H_UA H_AA⁻¹ H_AU, which keeps H_UU's block band
(a detection frame's t' meets the 4 control points around it). H_U is factorised by a block-banded Cholesky
(n units of 33, band b: O(n b² 33³)), and only the blocks of Σ_U = H_U⁻¹ within the band are computed, by the
Takahashi recurrence on the factor (Takahashi, Fagan, Chin 1973; Rue and Martino's GMRF books): from the last block
row up, Σ_ij = L_iiᵀ⁻¹ (δ_ij L_ii⁻¹ - Σ_{k>i} L_kiᵀ Σ_kj) for i <= j <= i + b, which needs only blocks within the band.
A pose at t, S(t) = Σ_a B_a(t) U_a, touches at most b + 1 neighbouring units, so Cov S(t) needs nothing else.

The joints. J(S) the 24 joint positions (forward kinematics): Cov J(t) ≈ D Cov S(t) Dᵀ, D = ∂J/∂S at the estimate.
The error a solve is judged by is the evaluation's (paper Sec. 4, ``stages.evaluate.align=procrustes``): the joints
after a rigid alignment (rotation and translation, no scale) of the estimate to the truth in each frame. To first
order that alignment removes the rigid motions of the whole skeleton: the error left is (I - P) e, P the orthogonal
projection onto the 6 rigid motions (3 translations, 3 rotations about the joints' centroid) of the 72-vector of
joints. Each joint's uncertainty is then σ_j = sqrt(tr Cov_j) of its 3 × 3 block of (I - P) Cov J (I - P)ᵀ: the RMS of
its 3D distance error (E‖e_j‖² = tr Cov_j), the quantity the error is (a distance) in the unit it is (mm), rather
than the largest axis's σ, which ignores the other two axes' share of the distance.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from eventcap.body.kinematics import joint_positions
from eventcap.body.skeleton import NUM_JOINTS, NUM_POSE_PARAMS
from eventcap.memo import ProcessCache

from .errors import EnergyError

_NP = NUM_POSE_PARAMS
#: The joint Jacobians' CasADi functions by rest joints.
_FK_JACOBIANS = ProcessCache("energy.laplace.fk_jacobians", maxsize=16)


@dataclass(frozen=True)
class UnitCovariance:
    """The covariance of a problem's pose units within the Hessian's band, up to the calibrated global scale:
    ``blocks[i, d]`` = Cov(U_i, U_{i+d}) (n, band + 1, 33, 33). ``shift``: what was added to the Hessian's diagonal
    to make it positive definite (0: nothing; :func:`laplace_covariance`)."""

    blocks: np.ndarray
    shift: float = 0.0

    @property
    def n_units(self) -> int:
        return self.blocks.shape[0]

    @property
    def band(self) -> int:
        return self.blocks.shape[1] - 1

    def block(self, i: int, j: int) -> np.ndarray:
        """Cov(U_i, U_j) (33, 33) for |i - j| <= band."""
        if i <= j:
            return self.blocks[i, j - i]
        return self.blocks[j, i - j].T

    def pose_covariance(self, basis: np.ndarray) -> np.ndarray:
        """(T, 33, 33) the covariance of the poses S = basis @ U at T times (basis (T, n_units); each row's
        nonzeros within band + 1 neighbouring units: a spline's, or one pose per frame)."""
        B = np.asarray(basis, dtype=np.float64)
        if B.ndim != 2 or B.shape[1] != self.n_units:
            raise EnergyError(f"pose_covariance: expected a basis (T, {self.n_units}), got {B.shape}")
        T, k = B.shape[0], self.band + 1
        nz = B != 0
        first = np.where(nz.any(1), nz.argmax(1), 0)
        last = np.where(nz.any(1), self.n_units - 1 - nz[:, ::-1].argmax(1), 0)
        if np.any(last - first >= k):
            raise EnergyError(f"pose_covariance: a time's basis spans {int(np.max(last - first)) + 1} units, more "
                              f"than the covariance's band + 1 = {k}")
        first = np.minimum(first, max(self.n_units - k, 0))
        k = min(k, self.n_units)
        rows = np.arange(T)
        W = np.stack([B[rows, first + a] for a in range(k)], axis=1)  # (T, k)
        out = np.zeros((T, _NP, _NP))
        for a in range(k):
            for b in range(k):
                w = W[:, a] * W[:, b]
                if not np.any(w):
                    continue
                i, j = first + a, first + b
                blk = np.where((i <= j)[:, None, None], self.blocks[np.minimum(i, j), np.abs(j - i)],
                               self.blocks[np.minimum(i, j), np.abs(j - i)].transpose(0, 2, 1))
                out += w[:, None, None] * blk
        return out

    def joint_sigma_mm(self, basis: np.ndarray, poses: np.ndarray, rest_joints, align: str = "procrustes"):
        """(T, 24) each joint's σ (mm) at the poses (T, 33) = basis @ U (:func:`joint_sigma_mm`; NaN where a pose is
        NaN)."""
        return joint_sigma_mm(self.pose_covariance(basis), poses, rest_joints, align)


# --------------------------------------------------------------------------------------------- block-banded algebra
def schur_banded(Hb: np.ndarray, Hua: np.ndarray, Haa: np.ndarray) -> np.ndarray:
    """The unit blocks (n, b + 1, 33, 33) of H_UU - H_UA H_AA⁻¹ H_AU (the auxiliary variables eliminated).
    EnergyError when an auxiliary variable couples units further apart than the band (the result would leave it)."""
    n, b1 = Hb.shape[:2]
    nA = Haa.shape[0]
    if nA == 0:
        return Hb
    touch = (np.abs(Hua).reshape(n, _NP, nA).max(axis=1) > 0)  # (n, nA)
    used = touch.any(axis=0)
    if np.any(used):
        lo = touch[:, used].argmax(axis=0)
        hi = n - 1 - touch[::-1, used].argmax(axis=0)
        if np.any(hi - lo >= b1):
            raise EnergyError(f"laplace: an auxiliary variable couples units {int(np.max(hi - lo))} apart, beyond the "
                              f"Hessian's band {b1 - 1}")
    W = np.linalg.solve(Haa, Hua.T).T  # H_UA H_AA⁻¹ (nU, nA)
    U3 = Hua.reshape(n, _NP, nA)
    W3 = W.reshape(n, _NP, nA)
    out = Hb.copy()
    for d in range(min(b1, n)):
        out[:n - d, d] -= np.einsum("ipa,iqa->ipq", W3[:n - d], U3[d:])
    return out


def to_lapack_band(Hb: np.ndarray, shift: float = 0.0) -> np.ndarray:
    """LAPACK's lower band storage ab[r - c, c] = H(r, c) of the symmetric block-banded matrix with upper blocks
    Hb[i, d] = H(i, i + d) (n, b + 1, m, m), plus shift on the diagonal."""
    n, b1, m = Hb.shape[:3]
    N, bw = n * m, b1 * m - 1
    ab = np.zeros((bw + 1, N))
    p, q = np.meshgrid(np.arange(m), np.arange(m), indexing="ij")
    for d in range(min(b1, n)):
        for i in range(n - d):
            r, c = (i + d) * m + p, i * m + q  # H(i + d, i) = Hb[i, d]ᵀ, its lower part
            keep = r >= c
            ab[(r - c)[keep], c[keep]] = Hb[i, d].T[keep]
    ab[0] += shift
    return ab


def from_lapack_band(cb: np.ndarray, n: int, b1: int, m: int) -> np.ndarray:
    """The blocks Lb[i, d] = L(i + d, i) (n, b + 1, m, m) of a lower-triangular band factor in LAPACK's storage."""
    Lb = np.zeros((n, b1, m, m))
    p, q = np.meshgrid(np.arange(m), np.arange(m), indexing="ij")
    bw = cb.shape[0] - 1
    for d in range(min(b1, n)):
        for i in range(n - d):
            r, c = (i + d) * m + p, i * m + q
            keep = (r >= c) & (r - c <= bw)
            Lb[i, d][keep] = cb[(r - c)[keep], c[keep]]
    return Lb


def banded_cholesky(Hb: np.ndarray, floor: float = 0.0) -> tuple[np.ndarray, float]:
    """The block-banded Cholesky factor of H + δ I (H: upper blocks Hb[i, d] = H(i, i + d)), as blocks Lb[i, d] =
    L(i + d, i) (the same layout), and δ: 0 when H is positive definite; else the smallest shift that makes it so
    (to 1 %, by doubling from ``floor`` and then bisecting), plus ``floor``, so that its most negative direction is
    left with about ``floor``'s curvature. numpy.linalg.LinAlgError when it is not positive definite and floor is 0.
    (The factor of a block-banded matrix has the same block band: no fill-in beyond it.)"""
    from scipy.linalg import LinAlgError, cholesky_banded

    n, b1, m = Hb.shape[:3]
    ab = to_lapack_band(Hb)

    def factor(delta: float):
        try:
            return cholesky_banded(ab if not delta else ab + np.eye(ab.shape[0], 1)[:, :1] * delta, lower=True,
                                   check_finite=False)
        except LinAlgError:
            return None

    delta = 0.0
    cb = factor(0.0)
    if cb is None:
        if not floor > 0:
            raise np.linalg.LinAlgError("the matrix is not positive definite")
        hi = floor
        while (cb := factor(hi)) is None:
            hi *= 2.0
            if not np.isfinite(hi) or hi > 1e300:
                raise np.linalg.LinAlgError("the matrix is not positive definite even with a shift")
        lo = hi / 2.0
        while hi - lo > 0.01 * hi:
            mid = 0.5 * (lo + hi)
            lo, hi = (lo, mid) if factor(mid) is not None else (mid, hi)
        delta = hi + floor
        cb = factor(delta)
    return from_lapack_band(cb, n, b1, m), delta


def banded_inverse(Lb: np.ndarray) -> np.ndarray:
    """The blocks within the band of (L Lᵀ)⁻¹ from a block-banded Cholesky factor (:func:`banded_cholesky`): the
    Takahashi recurrence (module doc); the layout of the input (upper blocks [i, d] = Σ(i, i + d))."""
    n, b1 = Lb.shape[:2]
    S = np.zeros_like(Lb)
    eye = np.eye(Lb.shape[2])

    def sigma(k: int, j: int) -> np.ndarray:  # Σ(k, j), both within the computed rows (k, j > i)
        return S[k, j - k] if k <= j else S[j, k - j].T

    for i in range(n - 1, -1, -1):
        Lii_inv = np.linalg.solve(Lb[i, 0], eye)
        top = min(i + b1, n)
        for j in range(top - 1, i - 1, -1):  # Σ(i, j) from the band's edge down to i: Σ(k, i) = Σ(i, k)ᵀ first
            R = Lii_inv.copy() if j == i else np.zeros_like(eye)
            for k in range(i + 1, top):  # L(k, i)ᵀ Σ(k, j)
                R -= Lb[i, k - i].T @ sigma(k, j)
            S[i, j - i] = Lii_inv.T @ R
        S[i, 0] = 0.5 * (S[i, 0] + S[i, 0].T)
    return S


def limits_precision(lower: np.ndarray, upper: np.ndarray, weight: float) -> np.ndarray:
    """(33,) the precision of the joint limits read as a prior, times ``weight``: a uniform distribution over
    [lower, upper] has variance (upper - lower)² / 12, so each joint angle gets weight · 12 / (upper - lower)²; the
    root's 6 parameters none (the evaluation's rigid alignment removes them)."""
    lo, hi = np.asarray(lower, dtype=np.float64), np.asarray(upper, dtype=np.float64)
    out = np.zeros(_NP)
    span = hi[:27] - lo[:27]
    ok = np.isfinite(span) & (span > 0)
    out[:27][ok] = float(weight) * 12.0 / span[ok] ** 2
    return out


def laplace_covariance(problem, x: np.ndarray, prior_precision: np.ndarray | None = None) -> UnitCovariance:
    """The covariance of the problem's pose units at its solution x (module doc), within the Hessian's band.

    The solve's exact Hessian need not be positive definite at its solution (robust losses, the second-order parts
    of the image terms, a solve stopped at its tolerance): then H_U + δ I, δ just enough to make it so plus the
    proximal pull's curvature 2 λ_damp (1e-9 of H_U's mean diagonal without one) (:func:`banded_cholesky`): its
    directions of negative curvature are left as uncertain as the proximal pull alone makes a direction.

    prior_precision: (33,) added to every unit's diagonal (:func:`limits_precision`): what bounds the directions no
    term observes (a limb out of view) by the joint limits rather than by the proximal pull alone, whose curvature is
    tiny (it only keeps the solve from drifting). Without it such a limb's σ reaches metres, and the rigid alignment
    spreads that over every joint (it aligns on all 24)."""
    Hb, Hua, Haa = problem.hessian_parts(np.asarray(x, dtype=np.float64))
    Hu = schur_banded(Hb, Hua, Haa)
    if prior_precision is not None:
        p = np.asarray(prior_precision, dtype=np.float64)
        if p.shape != (_NP,) or not np.all(np.isfinite(p) & (p >= 0)):
            raise EnergyError(f"laplace: expected a prior precision >= 0 per pose parameter ({_NP},), got {p.shape}")
        Hu = Hu.copy()
        Hu[:, 0] += np.diag(p)
    floor = 2.0 * float(problem.damp)
    if floor <= 0:
        floor = 1e-9 * max(float(np.mean(np.einsum("npp->np", Hu[:, 0]))), 1e-12)
    Lb, shift = banded_cholesky(Hu, floor)
    return UnitCovariance(banded_inverse(Lb), shift)


# --------------------------------------------------------------------------------------------- to the joints
def _fk_jacobian(rest_joints, n: int) -> ca.Function:
    """∂J/∂S's CasADi function for these rest joints (or a Template's), mapped over n poses (built once each)."""
    rest = np.ascontiguousarray(getattr(rest_joints, "rest_joints", rest_joints), dtype=np.float64)

    def build():
        S = ca.SX.sym("S", _NP)
        J = joint_positions(S, rest)  # (24, 3)
        return ca.Function("fk_jacobian", [S], [ca.densify(ca.jacobian(ca.vec(J.T), S))]).map(n)

    return _FK_JACOBIANS.get((rest.tobytes(), int(n)), build)[0]


def joint_jacobians(poses: np.ndarray, rest_joints: np.ndarray) -> np.ndarray:
    """(T, 72, 33) ∂J/∂S of the 24 joints (rows joint-major: x, y, z of joint 0, then joint 1, ...) at poses (T, 33)."""
    P = np.asarray(poses, dtype=np.float64)
    out = np.asarray(_fk_jacobian(rest_joints, P.shape[0])(P.T))  # (72, 33 T)
    return out.reshape(3 * NUM_JOINTS, P.shape[0], _NP).transpose(1, 0, 2)


def rigid_projector(joints: np.ndarray) -> np.ndarray:
    """(T, 72, 72) the orthogonal projection onto the rigid motions (3 translations, 3 rotations about the
    centroid) of each frame's 24 joints (T, 24, 3): what a per-frame Procrustes alignment removes, to first order."""
    X = np.asarray(joints, dtype=np.float64)
    T = X.shape[0]
    Y = X - X.mean(axis=1, keepdims=True)
    R = np.zeros((T, NUM_JOINTS, 3, 6))
    R[:, :, :, :3] = np.eye(3)
    for k in range(3):  # ω_k × y
        w = np.zeros(3)
        w[k] = 1.0
        R[:, :, :, 3 + k] = np.cross(w, Y)
    Q, _ = np.linalg.qr(R.reshape(T, 3 * NUM_JOINTS, 6))
    return Q @ Q.transpose(0, 2, 1)


def joint_sigma_mm(pose_cov: np.ndarray, poses: np.ndarray, rest_joints: np.ndarray,
                   align: str = "procrustes") -> np.ndarray:
    """(T, 24) each joint's σ (mm): sqrt of the trace of its position covariance, from the poses' covariance
    (T, 33, 33) at the poses (T, 33) (module doc). align: procrustes (the covariance left after a per-frame rigid
    alignment, as the evaluation's error) | none (world positions). NaN where the pose or its covariance is not
    finite."""
    if align not in ("procrustes", "none"):
        raise EnergyError(f"joint_sigma_mm: align must be procrustes or none, got {align!r}")
    P = np.asarray(poses, dtype=np.float64)
    C = np.asarray(pose_cov, dtype=np.float64)
    ok = np.isfinite(P).all(axis=1) & np.isfinite(C).all(axis=(1, 2))
    out = np.full((P.shape[0], NUM_JOINTS), np.nan)
    if not ok.any():
        return out
    D = joint_jacobians(P[ok], rest_joints)
    CJ = D @ C[ok] @ D.transpose(0, 2, 1)
    if align == "procrustes":
        A = np.eye(3 * NUM_JOINTS)[None] - rigid_projector(joint_positions(P[ok], rest_joints))
        CJ = A @ CJ @ A.transpose(0, 2, 1)
    var = np.einsum("tii->ti", CJ).reshape(-1, NUM_JOINTS, 3).sum(axis=2)
    out[ok] = 1000.0 * np.sqrt(np.maximum(var, 0.0))
    return out


__all__ = ["UnitCovariance", "banded_cholesky", "banded_inverse", "joint_jacobians", "joint_sigma_mm",
           "from_lapack_band", "laplace_covariance", "limits_precision", "rigid_projector", "schur_banded", "to_lapack_band"]
