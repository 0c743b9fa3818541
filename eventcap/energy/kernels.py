"""Numeric kernels of the image and skinning terms: closed-form projection derivatives and the per-frame skinning
transforms G(S) with their Jacobian and contracted second derivatives (compiled, :mod:`._skin_kernels`).

Every term on surface points (E_cor, E_sil) poses its points as WX · G(S) with premultiplied skinning weights WX.
"""

from __future__ import annotations

import functools

import logging

import casadi as ca
import numpy as np

from eventcap.body.kinematics import global_transforms
from eventcap.body.skeleton import NUM_JOINTS, NUM_POSE_PARAMS
from eventcap.camera import Camera
from eventcap.memo import ProcessCache

_NP = NUM_POSE_PARAMS
_log = logging.getLogger("eventcap.energy.kernels")


def project_derivatives(camera: Camera, points: np.ndarray, order: int = 2):
    """Camera projection of world points with its derivatives, numpy, in closed form (same model as
    :meth:`Camera.project`: pinhole + OpenCV distortion).

    points (P, 3) metres. Returns pixels (P, 2); with order >= 1 also the Jacobian (P, 2, 3) px/m; with order 2
    also the Hessian (P, 2, 3, 3). Points must be in front of the camera.
    """
    p = np.asarray(points, dtype=np.float64)
    c = p @ camera.R.T + camera.t
    iz = 1.0 / c[:, 2]
    x, y = c[:, 0] * iz, c[:, 1] * iz
    k1, k2, p1, p2, k3 = camera.dist
    r2 = x * x + y * y
    rad = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * rad + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * rad + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    uv = np.stack([camera.fx * xd + camera.cx, camera.fy * yd + camera.cy], axis=1)
    if order == 0:
        return uv
    n = p.shape[0]
    drad = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d rad / d r2
    Dd = np.empty((n, 2, 2))  # d (xd, yd) / d (x, y)
    Dd[:, 0, 0] = rad + 2.0 * x * x * drad + 2.0 * p1 * y + 6.0 * p2 * x
    Dd[:, 0, 1] = 2.0 * x * y * drad + 2.0 * p1 * x + 2.0 * p2 * y
    Dd[:, 1, 0] = Dd[:, 0, 1]
    Dd[:, 1, 1] = rad + 2.0 * y * y * drad + 6.0 * p1 * y + 2.0 * p2 * x
    Dn = np.zeros((n, 2, 3))  # d (x, y) / d camera coordinates
    Dn[:, 0, 0] = iz
    Dn[:, 0, 2] = -x * iz
    Dn[:, 1, 1] = iz
    Dn[:, 1, 2] = -y * iz
    f = np.array([camera.fx, camera.fy])
    FDd = f[None, :, None] * Dd
    J = np.matmul(FDd, Dn) @ camera.R
    if order == 1:
        return uv, J
    d2rad = 2.0 * k2 + 6.0 * k3 * r2
    # Second derivatives of xd (a = 0) and yd (a = 1) w.r.t. (x, y).
    xd_xx = 6.0 * x * drad + 4.0 * x**3 * d2rad + 6.0 * p2
    xd_xy = yd_xx = 2.0 * y * drad + 4.0 * x * x * y * d2rad + 2.0 * p1
    xd_yy = yd_xy = 2.0 * x * drad + 4.0 * x * y * y * d2rad + 2.0 * p2
    yd_yy = 6.0 * y * drad + 4.0 * y**3 * d2rad + 6.0 * p1
    Hd = np.stack([np.stack([xd_xx, xd_xy, xd_xy, xd_yy], axis=1), np.stack([yd_xx, yd_xy, yd_xy, yd_yy], axis=1)],
                  axis=1).reshape(n, 2, 2, 2)
    # Second derivatives of x = cx/cz and y = cy/cz w.r.t. camera coordinates: only the z row/column.
    iz2 = iz * iz
    Hn = np.zeros((n, 2, 3, 3))
    Hn[:, 0, 0, 2] = Hn[:, 0, 2, 0] = -iz2
    Hn[:, 0, 2, 2] = 2.0 * x * iz2
    Hn[:, 1, 1, 2] = Hn[:, 1, 2, 1] = -iz2
    Hn[:, 1, 2, 2] = 2.0 * y * iz2
    DnT = np.swapaxes(Dn, 1, 2)
    H_cam = np.empty((n, 2, 3, 3))
    for a in range(2):
        H_cam[:, a] = (FDd[:, a, 0, None, None] * Hn[:, 0] + FDd[:, a, 1, None, None] * Hn[:, 1]
                       + f[a] * np.matmul(np.matmul(DnT, Hd[:, a]), Dn))
    H = np.matmul(np.matmul(camera.R.T, H_cam), camera.R)
    return uv, J, H


# --------------------------------------------------------------------------------------------- FK kernels
class Buffered:
    """A CasADi function evaluated on numpy arrays through its zero-copy buffer (no DM conversion per call)."""

    def __init__(self, fn: ca.Function):
        self.fn = fn
        self.args = [np.zeros(fn.sparsity_in(i).nnz()) for i in range(fn.n_in())]
        self.res = [np.zeros(fn.sparsity_out(i).nnz()) for i in range(fn.n_out())]
        self._buf, self._eval = fn.buffer()
        for i, a in enumerate(self.args):
            self._buf.set_arg(i, memoryview(a))
        for i, r in enumerate(self.res):
            self._buf.set_res(i, memoryview(r))

    def __call__(self, *args: np.ndarray) -> list[np.ndarray]:
        for dst, src in zip(self.args, args):
            dst[:] = np.asarray(src, dtype=np.float64).ravel()
        self._eval()
        if self._buf.ret() != 0:
            raise FloatingPointError(f"CasADi function {self.fn.name()} failed to evaluate")
        return [r.copy() for r in self.res]


class SkinningKernels:
    """Per frame, the 24 skinning transforms as a (96, 3) matrix G with posed point = WX · G (WX the premultiplied
    weights of a point, see :func:`premultiplied_weights`), their Jacobian and contracted second derivatives.

    All over the F frames of a window (one call each). Layouts (numpy, C order):
    ``G (F, 96, 3)``, ``dG (F, 96, 3, 33)``, ``hess (F, 33, 33)`` of Σ_{a,c} Λ[f, a, c] G[f, a, c].

    Compiled kernels in closed form (:mod:`._skin_kernels`, numba, cached on disk once per machine): nothing is built
    per window shape. Where they cannot run (numba fails to compile them), the CasADi graph of the same transforms
    (:class:`CasadiSkinning`, built per number of frames) stands in, and the log says so once.
    """

    def __init__(self, rest_joints: np.ndarray, n_frames: int):
        self.rest = np.ascontiguousarray(rest_joints, dtype=np.float64)
        if self.rest.shape != (NUM_JOINTS, 3):
            raise ValueError(f"rest joints: expected shape (24, 3), got {self.rest.shape}")
        self.F = int(n_frames)
        self._fallback: CasadiSkinning | None = None if _compiled() is not None else CasadiSkinning(self.rest, self.F)
        self._memo: tuple = (None, None)  # the last poses' (G, dG): factors sharing these kernels reuse them

    def _poses(self, S: np.ndarray) -> np.ndarray:
        S = np.ascontiguousarray(S, dtype=np.float64).reshape(-1, _NP)
        if S.shape[0] != self.F:
            raise ValueError(f"skinning kernels of {self.F} frames: got poses of shape {S.shape}")
        return S

    def transforms(self, S: np.ndarray) -> np.ndarray:
        S = self._poses(S)
        key, val = self._memo
        if key is not None and key == S.tobytes():
            return val[0]
        if self._fallback is not None:
            return self._fallback.transforms(S)
        k = _compiled()
        G = np.empty((self.F, 4 * NUM_JOINTS, 3))
        k.skin_transforms(S, self.rest, *k.tables()[:4], G)
        return G

    def transforms_jac(self, S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        S = self._poses(S)
        key = S.tobytes()
        if self._memo[0] == key:
            return self._memo[1]
        if self._fallback is not None:
            val = self._fallback.transforms_jac(S)
        else:
            k = _compiled()
            val = (np.empty((self.F, 4 * NUM_JOINTS, 3)), np.empty((self.F, 4 * NUM_JOINTS, 3, _NP)))
            k.skin_jacobian(S, self.rest, *k.tables()[:5], *val)
        self._memo = (key, val)
        return val

    def contracted_hessian(self, S: np.ndarray, lam: np.ndarray) -> np.ndarray:
        S = self._poses(S)
        lam = np.ascontiguousarray(lam, dtype=np.float64).reshape(self.F, 4 * NUM_JOINTS, 3)
        if self._fallback is not None:
            return self._fallback.contracted_hessian(S, lam)
        k = _compiled()
        H = np.empty((self.F, _NP, _NP))
        k.skin_contracted_hessian(S, lam, self.rest, *k.tables(), H)
        return H


class CasadiSkinning:
    """The skinning transforms, their Jacobian and contracted Hessian as CasADi graphs of
    :func:`eventcap.body.kinematics.global_transforms`, mapped over n_frames (the reference of the compiled
    kernels, and their stand-in where numba cannot compile them). Same layouts as :class:`SkinningKernels`."""

    def __init__(self, rest_joints: np.ndarray, n_frames: int):
        S = ca.SX.sym("S", _NP)
        T = global_transforms(S, rest_joints)
        G = ca.vertcat(*[T[j][:3, :].T for j in range(NUM_JOINTS)])  # (96, 3): [R^T; b^T] per joint
        g = ca.vec(G.T)  # index a*3 + c
        dg = ca.densify(ca.jacobian(g, S).T)  # (33, 288): column-major gives (a, c, s) C order
        lam = ca.SX.sym("lam", 3, 4 * NUM_JOINTS)
        hess = ca.densify(ca.hessian(ca.dot(ca.vec(lam), g), S)[0])
        self.F = n_frames
        self._g = Buffered(ca.Function("skin_G", [S], [g]).map(n_frames))
        self._dg = Buffered(ca.Function("skin_dG", [S], [g, dg]).map(n_frames))
        self._h = Buffered(ca.Function("skin_d2G", [S, lam], [hess]).map(n_frames))

    def transforms(self, S: np.ndarray) -> np.ndarray:
        return self._g(S)[0].reshape(self.F, 4 * NUM_JOINTS, 3)

    def transforms_jac(self, S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        g, dg = self._dg(S)
        return g.reshape(self.F, 4 * NUM_JOINTS, 3), dg.reshape(self.F, 4 * NUM_JOINTS, 3, _NP)

    def contracted_hessian(self, S: np.ndarray, lam: np.ndarray) -> np.ndarray:
        return self._h(S, lam)[0].reshape(self.F, _NP, _NP)


@functools.cache
def _compiled():
    """The compiled kernels' module, compiled (or loaded from numba's cache) on first use; None when numba cannot
    compile them (logged once: the CasADi graphs stand in, slower)."""
    try:
        from . import _skin_kernels as k

        G, dG, H = np.empty((1, 4 * NUM_JOINTS, 3)), np.empty((1, 4 * NUM_JOINTS, 3, _NP)), np.empty((1, _NP, _NP))
        S, rest = np.zeros((1, _NP)), np.zeros((NUM_JOINTS, 3))
        k.skin_transforms(S, rest, *k.tables()[:4], G)
        k.skin_jacobian(S, rest, *k.tables()[:5], G, dG)
        k.skin_contracted_hessian(S, np.zeros_like(G), rest, *k.tables(), H)
        return k
    except Exception as exc:  # noqa: BLE001 - numba missing, its errors, a missing LLVM: fall back, say so
        hint = " (is numba installed? it is a dependency of eventcap)" if isinstance(exc, ImportError) else ""
        _log.warning("the compiled skinning kernels cannot run here (%s: %s)%s: the CasADi graphs stand in for "
                     "them (slower; same results)", type(exc).__name__, exc, hint)
        return None


#: Skinning kernels by (rest joints, frames): the factors of one problem (E_cor, E_temp, E_sil, E_stab at the
#: same frames) share them, and their memo of the last poses. Bounded: windows of many shapes come and go.
_KERNELS = ProcessCache("energy.kernels", maxsize=16)


def shared_kernels(rest_joints: np.ndarray, n_frames: int) -> SkinningKernels:
    """The skinning kernels of n_frames frames for these rest joints, one per process (keyed by value)."""
    key = (np.asarray(rest_joints, dtype=np.float64).tobytes(), int(n_frames))
    return _KERNELS.get(key, lambda: SkinningKernels(rest_joints, int(n_frames)))[0]


def premultiplied_weights(rest_points: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(P, 96) products w_pj · [x_p, 1]_k at index 4j + k: posed points are ``WX @ G`` for the G above."""
    X = np.concatenate([rest_points, np.ones((rest_points.shape[0], 1))], axis=1)
    return (weights[:, :, None] * X[:, None, :]).reshape(rest_points.shape[0], 4 * NUM_JOINTS)

