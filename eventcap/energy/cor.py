"""E_cor (paper Eq. 5, event correspondences) and E_temp (Eq. 8) as numpy functions of the poses of consecutive
frames: value, gradient and exact block-tridiagonal Hessian (see the batch solve's module doc for the derivation).
"""

from __future__ import annotations

import math

import numpy as np

from eventcap.body.skeleton import NUM_JOINTS, NUM_POSE_PARAMS
from eventcap.camera import Camera

from .correspondences import Correspondences
from .kernels import SkinningKernels, premultiplied_weights, project_derivatives

_NP = NUM_POSE_PARAMS


class CorrespondenceEnergy:
    """λ_cor E_cor + λ_temp E_temp as functions of the poses S (F, 33): value, gradient and exact Hessian.

    E_cor = Σ_c w_c ‖(π(v_c(S_j)) - π(v_c(S_i)) - (p_{j,h} - p_{i,h})) / f‖² over correspondences c = (i, j, h),
    v_c(S) = WX_c · G(S) (data: :meth:`set_correspondences`). This is Eq. 5 with the surface point v_{i,h} tied to
    the pose S_i it was found with (π(v_{i,h}(S_i)) = p_{i,h} by construction; module doc).
    E_temp = Σ_i Σ_l φ_{i,l} ‖J_l(S_i) - J_l(S_{i+1})‖², with joint positions J_l = WXJ_l · G (linear in G too).
    Both go through the same per-frame skinning transforms G(S), their Jacobian and one contraction of their
    second derivatives. Both couple only neighbouring frames: the Hessian is block-tridiagonal.
    """

    def __init__(self, camera: Camera, kernels: SkinningKernels, rest_joints: np.ndarray):
        self.camera = camera
        self.kernels = kernels
        self.F = kernels.F
        self.scale = 1.0 / math.sqrt(camera.fx * camera.fy)
        self.WXJ = premultiplied_weights(rest_joints, np.eye(NUM_JOINTS))  # (24, 96): J_l = WXJ_l · G
        self.set_correspondences(Correspondences.empty())

    def set_correspondences(self, corr: Correspondences, relative: bool = True, point_weight=None) -> None:
        """Load E_cor's data. Point instances: each correspondence's point at its frame j, and each distinct
        source point (i, h) once at its frame i; they are sorted by frame for one matrix product per frame.

        relative=False: the source side is held at where it was found (π(v(S_i)) = p_{i,h}), so each residual
        depends on S_j alone — every frame is fitted on its own to its neighbours' points (the w/o_batch mode).
        """
        self.relative = bool(relative)
        P = corr.n
        j, i = corr.frame, corr.source
        if P and (min(j.min(), i.min()) < 0 or max(j.max(), i.max()) >= self.F):
            raise ValueError(f"correspondence frames must lie in [0, {self.F}), got [{min(j.min(), i.min())}, "
                             f"{max(j.max(), i.max())}]")
        WX = premultiplied_weights(corr.rest_points, corr.weights)
        key = i * (int(corr.track.max()) + 1 if P else 1) + corr.track
        _, first, src_of = np.unique(key, return_index=True, return_inverse=True)
        if not self.relative:
            first, src_of = first[:0], src_of[:0]
        inst_frame = np.concatenate([j, i[first]])
        order = np.argsort(inst_frame, kind="stable")
        rank = np.empty_like(order)
        rank[order] = np.arange(order.size)
        self.frame = inst_frame[order]
        self.WX = np.concatenate([WX, WX[first]])[order]
        self.t_idx = rank[:P]  # instance of each correspondence's point at frame j
        self.s_idx = rank[P + src_of.ravel()]  # ... and at its source frame i (relative form only)
        self.dq = corr.target_px - corr.source_px  # the track's displacement p_j - p_i
        self.target = corr.target_px
        self.w = np.ones(P) if point_weight is None else np.asarray(point_weight, np.float64)
        self.P = P
        bounds = np.searchsorted(self.frame, np.arange(self.F + 1))
        self.slices = [(f, slice(bounds[f], bounds[f + 1])) for f in range(self.F) if bounds[f + 1] > bounds[f]]
        # Cross-frame Hessian blocks (k, k+1): the instance at the lower and at the higher frame of each pair.
        if self.relative:
            low_first = i < j
            self.lo = np.where(low_first, self.s_idx, self.t_idx)
            self.hi = np.where(low_first, self.t_idx, self.s_idx)
            pair = np.minimum(i, j)
        else:
            self.lo = self.hi = pair = np.zeros(0, np.int64)
        porder = np.argsort(pair, kind="stable")
        self.pair_order = porder
        pb = np.searchsorted(pair[porder], np.arange(self.F))
        self.pair_slices = [(k, slice(pb[k], pb[k + 1])) for k in range(self.F - 1) if pb[k + 1] > pb[k]]
        self._cache = {}

    @property
    def n(self) -> int:
        """Number of correspondences."""
        return self.P

    # -------------------------------------------------------------- pieces
    def _points(self, G: np.ndarray) -> np.ndarray:
        pts = np.empty((self.frame.size, 3))
        for f, sl in self.slices:
            pts[sl] = self.WX[sl] @ G[f]
        return pts

    def _values(self, S: np.ndarray, phi: np.ndarray, G: np.ndarray):
        """E_cor, E_temp, normalised residuals r (P, 2), joint differences d (F-1, 24, 3), instance points."""
        pts = self._points(G)
        uv = project_derivatives(self.camera, pts, 0)
        if self.relative:
            r = (uv[self.t_idx] - uv[self.s_idx] - self.dq) * self.scale
        else:
            r = (uv[self.t_idx] - self.target) * self.scale
        e_cor = float(np.sum(self.w * np.sum(r * r, axis=1)))
        J = self.WXJ @ G  # (F, 24, 3)
        d = J[:-1] - J[1:]
        e_temp = float(np.sum(phi * np.sum(d * d, axis=2)))
        return e_cor, e_temp, r, d, pts

    def residuals_px(self, S: np.ndarray) -> np.ndarray:
        """Each correspondence's image residual (P, 2) in pixels at the poses S (F, 33), unweighted: where the model
        moves its point minus where the track moved (relative form), or minus where the track is (fixed source)."""
        r = self._values(S, np.zeros((self.F - 1, NUM_JOINTS)), self.kernels.transforms(S))[2]
        return r / self.scale

    def terms(self, S: np.ndarray, phi: np.ndarray) -> tuple[float, float]:
        """Unweighted (E_cor, E_temp)."""
        return self._values(S, phi, self.kernels.transforms(S))[:2]

    def _first_order(self, S, phi, lam):
        key = (S.tobytes(), phi.tobytes(), lam.tobytes())
        if self._cache.get("key") != key:
            G, dG = self.kernels.transforms_jac(S)
            e_cor, e_temp, r, d, pts = self._values(S, phi, G)
            dGm = dG.reshape(self.F, 4 * NUM_JOINTS, 3 * _NP)
            # E_cor: gradient w.r.t. each instance point (u), and d(point)/dS (J3).
            _, Jp = project_derivatives(self.camera, pts, 1)
            Jp *= self.scale
            wr = (2.0 * lam[0]) * self.w[:, None] * r  # (P, 2)
            u = np.zeros((pts.shape[0], 3))
            u[self.t_idx] += np.matmul(wr[:, None, :], Jp[self.t_idx])[:, 0, :]
            if self.relative:
                np.add.at(u, self.s_idx, -np.matmul(wr[:, None, :], Jp[self.s_idx])[:, 0, :])
            J3 = np.empty((pts.shape[0], 3, _NP))
            for f, sl in self.slices:
                J3[sl] = (self.WX[sl] @ dGm[f]).reshape(-1, 3, _NP)
            # E_temp: gradient w.r.t. each joint position, and d(joint)/dS.
            pd = (2.0 * lam[1]) * phi[:, :, None] * d  # (F-1, 24, 3)
            uJ = np.zeros((self.F, NUM_JOINTS, 3))
            uJ[:-1] += pd
            uJ[1:] -= pd
            JJ = (self.WXJ @ dGm).reshape(self.F, NUM_JOINTS, 3, _NP)
            g = np.matmul(uJ.reshape(self.F, 1, -1), JJ.reshape(self.F, -1, _NP))[:, 0, :]
            for f, sl in self.slices:
                g[f] += u[sl].reshape(-1) @ J3[sl].reshape(-1, _NP)
            value = lam[0] * e_cor + lam[1] * e_temp
            self._cache = {"key": key, "value": value, "g": g, "pts": pts, "r": r, "u": u, "J3": J3, "JJ": JJ,
                           "uJ": uJ, "Jp": Jp}
        return self._cache

    # -------------------------------------------------------------- what IPOPT calls
    def value(self, S, phi, lam) -> float:
        c = self._cache
        if c.get("key") == (S.tobytes(), phi.tobytes(), lam.tobytes()):
            return c["value"]
        e_cor, e_temp = self._values(S, phi, self.kernels.transforms(S))[:2]
        return float(lam[0] * e_cor + lam[1] * e_temp)

    def gradient(self, S, phi, lam) -> tuple[float, np.ndarray]:
        c = self._first_order(S, phi, lam)
        return c["value"], c["g"]

    def hessian(self, S, phi, lam) -> tuple[np.ndarray, np.ndarray]:
        """Exact Hessian as diagonal blocks (F, 33, 33) and super-diagonal blocks (F-1, 33, 33) [(i, i+1)]."""
        c = self._first_order(S, phi, lam)
        F1 = self.F - 1
        diag = np.zeros((self.F, _NP, _NP))
        upper = np.zeros((F1, _NP, _NP))
        lamG = np.zeros((self.F, 4 * NUM_JOINTS, 3))  # Λ: gradient w.r.t. G, contracted with ∂²G below
        if self.P:
            _, _, Hp = project_derivatives(self.camera, c["pts"], 2)
            Hp *= self.scale
            Jp, r, J3, u = c["Jp"], c["r"], c["J3"], c["u"]
            wr = (2.0 * lam[0]) * self.w[:, None] * r
            w2 = (2.0 * lam[0]) * self.w[:, None, None]
            t, s_ = self.t_idx, self.s_idx
            # Point-space Hessian per instance: 2λw (JᵀJ ± Σ_a r_a H_a) (+ at frame j, - at frame i).
            Jt, Js = Jp[t], Jp[s_]
            Bp = np.zeros((Jp.shape[0], 3, 3))
            Bp[t] += w2 * np.matmul(np.swapaxes(Jt, 1, 2), Jt) + wr[:, 0, None, None] * Hp[t, 0] \
                + wr[:, 1, None, None] * Hp[t, 1]
            if self.relative:
                np.add.at(Bp, s_, w2 * np.matmul(np.swapaxes(Js, 1, 2), Js) - wr[:, 0, None, None] * Hp[s_, 0]
                          - wr[:, 1, None, None] * Hp[s_, 1])
            for f, sl in self.slices:
                Jf = J3[sl]
                diag[f] = Jf.reshape(-1, _NP).T @ np.matmul(Bp[sl], Jf).reshape(-1, _NP)
                lamG[f] = self.WX[sl].T @ u[sl]
            # Cross-frame blocks: d²/dp_lo dp_hi of w‖r‖² = -2w J_loᵀ J_hi (r is a difference of the two).
            lo, hi = self.lo[self.pair_order], self.hi[self.pair_order]
            C = -w2[self.pair_order] * np.matmul(np.swapaxes(Jp[lo], 1, 2), Jp[hi])
            R = np.matmul(C, J3[hi])
            L = J3[lo]
            for k, sl in self.pair_slices:
                upper[k] = L[sl].reshape(-1, _NP).T @ R[sl].reshape(-1, _NP)
        # E_temp (its residuals are linear in the joint positions).
        JJ = c["JJ"]
        w2t = (2.0 * lam[1]) * phi  # (F-1, 24)
        A, Bn = JJ[:-1], JJ[1:]  # d(J_l(S_i))/dS_i and d(J_l(S_{i+1}))/dS_{i+1}
        Aw = (A * w2t[:, :, None, None]).reshape(F1, -1, _NP)
        Bw = (Bn * w2t[:, :, None, None]).reshape(F1, -1, _NP)
        A, Bn = A.reshape(F1, -1, _NP), Bn.reshape(F1, -1, _NP)
        AwT = np.swapaxes(Aw, 1, 2)
        diag[:-1] += AwT @ A
        diag[1:] += np.swapaxes(Bw, 1, 2) @ Bn
        upper -= AwT @ Bn
        lamG += self.WXJ.T @ c["uJ"]
        diag += self.kernels.contracted_hessian(S, lamG)
        return diag, upper

