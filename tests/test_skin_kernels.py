"""The compiled skinning kernels (eventcap/energy/_skin_kernels.py) against the CasADi graph of the same transforms
(the reference: eventcap.body.kinematics.global_transforms, differentiated symbolically) and finite differences."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from eventcap.body.kinematics import global_transforms
from eventcap.body.skeleton import pose_bounds
from eventcap.energy import kernels
from eventcap.energy.kernels import CasadiSkinning, SkinningKernels


@pytest.fixture(scope="module")
def rest():
    from helpers.poses import small_template

    return small_template().rest_joints


def _poses(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    lo, hi = pose_bounds()
    S = rng.uniform(-np.pi, np.pi, (n, 33))
    S[:, :27] = rng.uniform(lo[:27], hi[:27], (n, 27))
    S[:, 30:] = rng.normal(0.0, 1.0, (n, 3)) + [0.0, 0.9, 3.5]
    return S



@pytest.fixture(autouse=True)
def _compile_afresh():
    """Each test finds the kernels' compilation untried, and leaves it so (a test that breaks it, undone)."""
    kernels._compiled.cache_clear()
    yield
    kernels._compiled.cache_clear()

def test_transforms_are_the_kinematics(rest):
    S = _poses(7, 0)
    G = SkinningKernels(rest, 7).transforms(S)
    T = global_transforms(S, rest)  # (7, 24, 4, 4)
    assert G.shape == (7, 96, 3)
    R, b = G.reshape(7, 24, 4, 3)[:, :, :3, :], G.reshape(7, 24, 4, 3)[:, :, 3, :]
    np.testing.assert_allclose(np.swapaxes(R, 2, 3), T[:, :, :3, :3], atol=1e-13)
    np.testing.assert_allclose(b, T[:, :, :3, 3], atol=1e-13)


def test_jacobian_and_hessian_match_casadi(rest):
    n = 9
    S = _poses(n, 1)
    lam = np.random.default_rng(2).normal(size=(n, 96, 3))
    ref = CasadiSkinning(rest, n)
    k = SkinningKernels(rest, n)
    G, dG = k.transforms_jac(S)
    G0, dG0 = ref.transforms_jac(S)
    assert dG.shape == (n, 96, 3, 33)
    np.testing.assert_allclose(G, G0, atol=1e-13)
    np.testing.assert_allclose(dG, dG0, atol=1e-12)
    H, H0 = k.contracted_hessian(S, lam), ref.contracted_hessian(S, lam)
    assert H.shape == (n, 33, 33)
    assert np.abs(H0).max() > 1.0  # a real test: the Hessian is not zero
    np.testing.assert_allclose(H, H0, atol=1e-11 * np.abs(H0).max())
    np.testing.assert_array_equal(H, np.swapaxes(H, 1, 2))
    assert not H[:, 30:, :].any()  # G is affine in the translation


def test_derivatives_are_finite_differences(rest):
    """dG against central differences of G, and the contracted Hessian against differences of Λ·dG."""
    n, h = 3, 1e-6
    S = _poses(n, 3)
    lam = np.random.default_rng(4).normal(size=(n, 96, 3))
    k = SkinningKernels(rest, n)
    G, dG = k.transforms_jac(S)
    H = k.contracted_hessian(S, lam)
    for s in range(33):
        e = np.zeros(33)
        e[s] = h
        Gp, dGp = SkinningKernels(rest, n).transforms_jac(S + e)
        Gm, dGm = SkinningKernels(rest, n).transforms_jac(S - e)
        np.testing.assert_allclose((Gp - Gm) / (2 * h), dG[..., s], atol=1e-7)
        col = np.einsum("fac,facs->fs", lam, (dGp - dGm) / (2 * h))
        np.testing.assert_allclose(col, H[:, :, s], atol=1e-6 * max(1.0, np.abs(H).max()))


def test_the_casadi_graphs_stand_in_and_say_so(rest, monkeypatch, caplog):
    """Where numba cannot compile the kernels, the CasADi graphs give the same results and the log says so."""
    import eventcap.energy._skin_kernels as compiled

    def broken(*args):
        raise RuntimeError("no LLVM here")

    kernels._compiled.cache_clear()
    monkeypatch.setattr(compiled, "skin_jacobian", broken)
    S = _poses(4, 5)
    lam = np.random.default_rng(6).normal(size=(4, 96, 3))
    with caplog.at_level(logging.WARNING, logger="eventcap.energy.kernels"):
        k = SkinningKernels(rest, 4)
    assert "cannot run here (RuntimeError: no LLVM here)" in caplog.text
    assert "CasADi graphs stand in" in caplog.text
    assert isinstance(k._fallback, CasadiSkinning)
    kernels._compiled.cache_clear()
    monkeypatch.undo()
    good = SkinningKernels(rest, 4)
    assert good._fallback is None
    np.testing.assert_allclose(k.transforms_jac(S)[1], good.transforms_jac(S)[1], atol=1e-12)
    np.testing.assert_allclose(k.contracted_hessian(S, lam), good.contracted_hessian(S, lam), atol=1e-10)


def test_wrong_shapes_are_refused(rest):
    k = SkinningKernels(rest, 4)
    with pytest.raises(ValueError, match=r"skinning kernels of 4 frames: got poses of shape \(5, 33\)"):
        k.transforms(np.zeros((5, 33)))
    with pytest.raises(ValueError, match=r"rest joints: expected shape \(24, 3\), got \(23, 3\)"):
        SkinningKernels(np.zeros((23, 3)), 4)


def test_a_missing_numba_falls_back_and_says_so(rest, monkeypatch, caplog):
    """Without numba the kernels module cannot be imported: the CasADi graphs stand in, and the log names why."""
    import sys

    import eventcap.energy

    kernels._compiled.cache_clear()
    monkeypatch.setitem(sys.modules, "numba", None)  # `import numba` raises ImportError
    monkeypatch.delitem(sys.modules, "eventcap.energy._skin_kernels", raising=False)
    monkeypatch.delattr(eventcap.energy, "_skin_kernels", raising=False)
    S = _poses(3, 7)
    with caplog.at_level(logging.WARNING, logger="eventcap.energy.kernels"):
        k = SkinningKernels(rest, 3)
    assert "cannot run here (ModuleNotFoundError: import of numba halted" in caplog.text
    assert "is numba installed?" in caplog.text
    assert isinstance(k._fallback, CasadiSkinning)
    caplog.clear()
    SkinningKernels(rest, 3)  # said once, not per window
    assert "cannot run here" not in caplog.text
    ref = CasadiSkinning(rest, 3)
    np.testing.assert_array_equal(k.transforms_jac(S)[1], ref.transforms_jac(S)[1])
