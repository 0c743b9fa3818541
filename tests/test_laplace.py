"""The Laplace approximation of a solve (eventcap/energy/laplace.py): the block-banded factorisation and selected
inverse against dense algebra, the shift of an indefinite Hessian, the auxiliary variables' elimination, the joints'
Jacobian against finite differences, the per-frame rigid alignment to first order, and on a problem whose energy is
a negative log-likelihood, the joints' σ against the spread of solutions over many draws of its data."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from eventcap.analysis.metrics import procrustes_align
from eventcap.body.kinematics import joint_positions
from eventcap.body.skeleton import NUM_POSE_PARAMS, pose_bounds
from eventcap.energy.factor import Factor, FactorConfig, Linearization
from eventcap.energy.ipopt import IpoptSettings
from eventcap.energy.laplace import (
    banded_cholesky,
    banded_inverse,
    joint_jacobians,
    joint_sigma_mm,
    laplace_covariance,
    rigid_projector,
    schur_banded,
)
from eventcap.energy.problem import FactorProblem, FramePoses
from eventcap.params import param
from helpers.poses import posed_recording

M = NUM_POSE_PARAMS


def dense(Hb: np.ndarray) -> np.ndarray:
    """The symmetric matrix of upper blocks Hb[i, d] = H(i, i + d)."""
    n, b1, m = Hb.shape[:3]
    H = np.zeros((n * m, n * m))
    for i in range(n):
        for d in range(min(b1, n - i)):
            j = i + d
            H[i * m:(i + 1) * m, j * m:(j + 1) * m] = Hb[i, d]
            H[j * m:(j + 1) * m, i * m:(i + 1) * m] = Hb[i, d].T
    return H


def band_of(H: np.ndarray, n: int, b1: int, m: int) -> np.ndarray:
    return np.stack([np.stack([H[i * m:(i + 1) * m, (i + d) * m:(i + d + 1) * m] if i + d < n else np.zeros((m, m))
                               for d in range(b1)]) for i in range(n)])


def random_banded(n: int = 7, b: int = 3, m: int = M, seed: int = 0, ridge: float = 1.0) -> np.ndarray:
    """Upper blocks of a random symmetric positive definite block-banded matrix: A Aᵀ with A block-lower-banded."""
    rng = np.random.default_rng(seed)
    A = np.zeros((n * m, n * m))
    for i in range(n):
        for d in range(b // 2 + 1):
            if i - d >= 0:
                A[i * m:(i + 1) * m, (i - d) * m:(i - d + 1) * m] = rng.normal(size=(m, m))
    return band_of(A @ A.T + ridge * np.eye(n * m), n, b + 1, m)


def test_banded_factor_and_selected_inverse_equal_the_dense_inverse():
    Hb = random_banded()
    Lb, shift = banded_cholesky(Hb)
    assert shift == 0.0
    H = dense(Hb)
    n, b1 = Lb.shape[:2]
    L = np.zeros_like(H)
    for i in range(n):
        for d in range(min(b1, n - i)):
            L[(i + d) * M:(i + d + 1) * M, i * M:(i + 1) * M] = Lb[i, d]  # Lb[i, d] = L(i + d, i)
    assert np.allclose(L, np.linalg.cholesky(H), atol=1e-10)  # the same (unique) factor: no fill beyond the band
    S = banded_inverse(Lb)
    want = band_of(np.linalg.inv(H), 7, 4, M)
    assert np.abs(S - want).max() < 1e-10 * np.abs(want).max()


def test_an_indefinite_matrix_is_shifted_just_enough_to_leave_the_floor():
    H = dense(random_banded(n=5, b=2, seed=1, ridge=0.0))
    w, V = np.linalg.eigh(H)
    w[0] = -2e-3  # one direction of negative curvature, the rest as they were
    Hb = band_of((V * w) @ V.T, 5, 3, M)  # no longer banded exactly: keep the band (the test of the shift only)
    Hd = dense(Hb)
    lam = np.linalg.eigvalsh(Hd)[0]
    assert lam < 0
    with pytest.raises(np.linalg.LinAlgError, match="not positive definite"):
        banded_cholesky(Hb)
    Lb, shift = banded_cholesky(Hb, floor=1e-4)
    assert -lam + 1e-4 <= shift <= 1.011 * -lam + 1e-4  # just enough (to 1 %), plus the floor
    S = banded_inverse(Lb)
    want = band_of(np.linalg.inv(Hd + shift * np.eye(Hd.shape[0])), 5, 3, M)
    assert np.abs(S - want).max() < 1e-7 * np.abs(want).max()


def test_the_auxiliary_variables_are_eliminated_exactly():
    rng = np.random.default_rng(2)
    n, b1, nA = 6, 4, 9
    Hb = random_banded(n=n, b=b1 - 1, seed=3, ridge=50.0)
    Hua = np.zeros((n * M, nA))
    for a in range(nA):  # each auxiliary variable meets 4 neighbouring units (a detection frame's t')
        u0 = a % (n - 3)
        Hua[u0 * M:(u0 + 4) * M, a] = rng.normal(size=4 * M)
    Haa = np.diag(rng.uniform(20, 40, nA))
    got = schur_banded(Hb, Hua, Haa)
    want = dense(Hb) - Hua @ np.linalg.solve(Haa, Hua.T)
    assert np.abs(dense(got) - want).max() < 1e-9 * np.abs(want).max()
    wide = Hua.copy()
    wide[0, 0] = wide[(n - 1) * M, 0] = 1.0  # one aux variable touching units 0 and n - 1
    with pytest.raises(Exception, match="couples units 5 apart, beyond the Hessian's band 3"):
        schur_banded(Hb, wide, Haa)


def test_the_joints_jacobian_matches_finite_differences():
    rec = posed_recording("jumping_jack", n_frames=3, with_template=True)
    P = rec.ground_truth.poses[[10, 40]]
    D = joint_jacobians(P, rec.template)
    assert D.shape == (2, 72, M)
    h = 1e-6
    for k in range(M):
        e = np.zeros(M)
        e[k] = h
        fd = (joint_positions(P + e, rec.template) - joint_positions(P - e, rec.template)).reshape(2, 72) / (2 * h)
        assert np.allclose(D[:, :, k], fd, atol=1e-6), k


def test_the_rigid_projector_is_what_a_procrustes_alignment_removes_to_first_order():
    rec = posed_recording("jumping_jack", n_frames=3, with_template=True)
    X = joint_positions(rec.ground_truth.poses[[25]], rec.template)  # (1, 24, 3)
    P = rigid_projector(X)[0]
    assert np.allclose(P @ P, P) and np.isclose(np.trace(P), 6.0)
    rng = np.random.default_rng(4)
    for _ in range(5):
        e = rng.normal(0, 1e-3, (24, 3))  # 1 mm errors
        aligned = procrustes_align(X[0] + e, X[0]) - X[0]
        first = (e.reshape(-1) - P @ e.reshape(-1)).reshape(24, 3)
        assert np.abs(aligned - first).max() < 2e-5  # second order in 1 mm: 0.02 mm
    c = X[0].mean(axis=0)
    for move in (np.tile([0.1, -0.2, 0.05], (24, 1)), np.cross([0.3, -0.1, 0.2], X[0] - c)):  # translation, turn
        assert np.allclose(P @ move.reshape(-1), move.reshape(-1))  # all rigid: the alignment removes it


@dataclasses.dataclass
class GaussConfig(FactorConfig):
    weight: float = param(1.0, ge=0, help="λ")


class GaussianPoses(Factor):
    """λ Σ_k ‖S_k - y_k‖², y_k per frame: with y_k = truth + N(0, 1/(2λ)), exactly a negative log-likelihood."""

    name = "laplace_gauss_test"
    Config = GaussConfig

    @classmethod
    def samples(cls, inputs, config):
        return inputs.frames_us

    def linearize(self, S, aux, order):
        R = S - self.y
        lin = Linearization(self.weight * float(np.sum(R * R)))
        if order >= 1:
            lin.grad = 2.0 * self.weight * R
        if order >= 2:
            lin.diag = np.broadcast_to(2.0 * self.weight * np.eye(M), (self.n, M, M)).copy()
        return lin


def test_on_an_energy_that_is_a_likelihood_the_joints_sigma_is_the_spread_of_the_solutions():
    """E = λ Σ ‖S_k - y_k‖², y_k = truth + noise of variance 1/(2λ) per parameter: the solution is y, its error the
    noise; the Laplace σ of each joint (after the per-frame rigid alignment) must be the RMS of the aligned joint
    errors over many draws (the Gaussian's, to first order in the noise)."""
    rec = posed_recording("jumping_jack", n_frames=3, with_template=True)
    truth = rec.ground_truth.poses[[10, 30, 50]]
    lam, n = 2e5, 3  # σ 1.6 mrad per angle, 1.6 mm per translation
    f = GaussianPoses(GaussConfig(weight=lam), rec.template, rec.camera, n)
    f.t_us = np.arange(n, dtype=np.int64) * 1000
    lo, hi = pose_bounds()
    prob = FactorProblem(FramePoses(n), [f], IpoptSettings(max_iter=5, tol=1e-6, mumps_pivot_order=0), lo - 10,
                         hi + 10, damp=0.0)
    prob.set_window(f.t_us)
    rng = np.random.default_rng(5)
    draws, sd = 400, 1.0 / np.sqrt(2 * lam)
    errs = np.zeros((draws, n, 24))
    for k in range(draws):
        f.y = truth + rng.normal(0, sd, truth.shape)  # the solution: y (the minimum of E)
        J, Jt = joint_positions(f.y, rec.template), joint_positions(truth, rec.template)
        errs[k] = np.linalg.norm(np.stack([procrustes_align(a, b) for a, b in zip(J, Jt)]) - Jt, axis=-1) * 1000
    f.y = truth
    cov = laplace_covariance(prob, truth.ravel())
    assert cov.shift == 0.0
    sigma = cov.joint_sigma_mm(np.eye(n), truth, rec.template)
    rms = np.sqrt((errs ** 2).mean(axis=0))
    assert sigma.shape == (n, 24) and np.all(sigma > 0.1)
    assert np.abs(sigma / rms - 1).max() < 0.15  # 400 draws: the RMS itself is known to about 3.5 %
    world = joint_sigma_mm(cov.pose_covariance(np.eye(n)), truth, rec.template, align="none")
    assert np.all(world >= sigma - 1e-9)  # the alignment only removes variance


def test_the_joint_limits_bound_what_no_term_observes():
    """A term that observes only the first 20 angles: without a prior the others are held by the proximal pull alone
    (variance 1 / (2 λ_damp)); with the limits read as a prior of weight w, by it: variance (max - min)² / (12 w)."""
    from eventcap.energy.laplace import limits_precision

    rec = posed_recording("jumping_jack", n_frames=3, with_template=True)
    lo, hi = pose_bounds()
    f = GaussianPoses(GaussConfig(weight=100.0), rec.template, rec.camera, 2)
    f.t_us = np.array([0, 1000])
    f.y = rec.ground_truth.poses[[10, 20]]
    mask = np.zeros(M)
    mask[:20] = 1.0
    f.linearize = lambda S, aux, order, f=f: Linearization(
        0.0, None, np.broadcast_to(2.0 * f.weight * np.diag(mask), (f.n, M, M)).copy() if order >= 2 else None)
    prob = FactorProblem(FramePoses(2), [f], IpoptSettings(max_iter=5, tol=1e-6, mumps_pivot_order=0), lo, hi,
                         damp=1e-4)
    prob.set_window(f.t_us)
    x = f.y.ravel()
    var0 = np.diag(laplace_covariance(prob, x).block(0, 0))
    assert np.allclose(var0[:20], 1.0 / (200.0 + 2e-4)) and np.allclose(var0[20:], 1.0 / 2e-4)
    p = limits_precision(lo, hi, 0.01)
    assert np.all(p[27:] == 0) and np.allclose(p[:27], 0.12 / (hi[:27] - lo[:27]) ** 2)
    var = np.diag(laplace_covariance(prob, x, p).block(0, 0))
    assert np.allclose(var[20:27], 1.0 / (p[20:27] + 2e-4))  # the limits' spread over the weight
    assert np.allclose(var[27:], 1.0 / 2e-4) and np.allclose(var[:20], 1.0 / (200.0 + p[:20] + 2e-4))
    with pytest.raises(Exception, match=r"expected a prior precision >= 0 per pose parameter \(33,\)"):
        laplace_covariance(prob, x, np.ones(5))
