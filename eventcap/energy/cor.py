"""E_cor (paper Eq. 5, event correspondences) and E_temp (Eq. 8) as factors over the poses of consecutive frames:
value, gradient and exact block-tridiagonal Hessian (derivation in the batch solve's module doc,
plugins/eventcap_solve/batch.py).

E_cor = Σ_c w_c ‖(π(v_c(S_j)) - π(v_c(S_i)) - (p_{j,h} - p_{i,h})) / f‖² over correspondences c = (i, j, h),
v_c(S) = WX_c · G(S). This is Eq. 5 with the surface point v_{i,h} tied to the pose S_i it was found with
(π(v_{i,h}(S_i)) = p_{i,h} by construction). With ``cor_relative`` False (the w/o_batch mode) the source side is
held where it was found (π(v(S_i)) = p_{i,h}), so each residual depends on S_j alone.
E_temp = Σ_i Σ_l φ_{i,l} ‖J_l(S_i) - J_l(S_{i+1})‖², with joint positions J_l = WXJ_l · G (linear in G too).
Both pose their points through the same per-frame skinning transforms G(S), their Jacobian and one contraction of
their second derivatives (:class:`eventcap.energy.kernels.SkinningKernels`, shared by the two factors of a problem
and memoised per poses). Both couple only neighbouring frames: the Hessian is block-tridiagonal.
"""

from __future__ import annotations

import math
import numpy as np

from eventcap.body.skeleton import NUM_JOINTS, NUM_POSE_PARAMS
from eventcap.camera import Camera

from eventcap.body.kinematics import joint_positions
from .correspondences import Correspondences, correspondence_change_px, temporal_indicator
from .errors import EnergyError
from .factor import Factor, Linearization
from .loss import irls_weight
from .settings import CorConfig, CorNoise, TempConfig
from .kernels import premultiplied_weights, project_derivatives, shared_kernels

_NP = NUM_POSE_PARAMS


class CorrespondencePoints:
    """E_cor's data in the form it is evaluated: point instances (each correspondence's point at its frame j, and
    each distinct source point (i, h) once at its frame i), sorted by frame for one matrix product per frame."""

    def __init__(self, corr: Correspondences, n_frames: int, relative: bool, point_weight=None):
        self.relative, self.F = bool(relative), int(n_frames)
        P = corr.n
        j, i = corr.frame, corr.source
        if P and (min(j.min(), i.min()) < 0 or max(j.max(), i.max()) >= self.F):
            raise EnergyError(f"correspondence frames must lie in [0, {self.F}), got [{min(j.min(), i.min())}, "
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
        w = np.ones(P) if point_weight is None else np.asarray(point_weight, np.float64)
        if w.shape != (P,) or not np.all((w >= 0) & (w <= 1)):
            raise EnergyError(f"E_cor: expected a weight in [0, 1] per correspondence ({P},), got shape {w.shape}")
        self.w, self.P = w, P
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
        self.pair_order = np.argsort(pair, kind="stable")
        pb = np.searchsorted(pair[self.pair_order], np.arange(self.F))
        self.pair_slices = [(k, slice(pb[k], pb[k + 1])) for k in range(self.F - 1) if pb[k + 1] > pb[k]]

    def points(self, G: np.ndarray) -> np.ndarray:
        pts = np.empty((self.frame.size, 3))
        for f, sl in self.slices:
            pts[sl] = self.WX[sl] @ G[f]
        return pts


class EventCorrespondences(Factor):
    """E_cor (paper Eq. 5): λ_cor Σ_c w_c ‖(π(v_c(S_j)) - π(v_c(S_i)) - (p_j - p_i)) / f‖² (module doc), at the
    window's correspondence frames (its tracks' frames); the correspondences are the estimate's
    (:meth:`eventcap.energy.window.Estimate.correspondences`), searched again at each ICP round; exact
    block-tridiagonal Hessian."""

    name = "cor"
    needs = ("tracks",)
    Config = CorConfig
    Noise = CorNoise
    couples_neighbours = True

    @classmethod
    def noise_precision(cls, config, camera) -> float:
        # residuals are focal-normalised: σ_px / f of them
        return 0.5 * camera.fx * camera.fy / float(config.sigma_px) ** 2

    def robust_px(self) -> float:
        """The Cauchy scale of the correspondences' reweighting, px (0: least squares)."""
        if self.noisy:
            return float(self.config.loss_scale) * float(self.config.sigma_px)
        return float(self.config.robust_px)

    def __init__(self, config, template, camera: Camera, n: int):
        super().__init__(config, template, camera, n)
        self.kernels = shared_kernels(template.rest_joints, self.n)
        self.scale = 1.0 / math.sqrt(camera.fx * camera.fy)
        self.corr = Correspondences.empty()
        self.data = CorrespondencePoints(self.corr, self.n, True)
        self._cache: dict = {}

    @classmethod
    def samples(cls, inputs, config) -> np.ndarray:
        tracks = inputs.tracks
        return np.zeros(0, dtype=np.int64) if tracks is None else tracks.t_us

    def collect(self, inputs) -> None:
        super().collect(inputs)
        self.set_correspondences(Correspondences.empty())

    def relinearize(self, estimate) -> None:
        corr = estimate.correspondences()
        weight = None
        robust = self.robust_px()
        if robust > 0 and estimate.round > 0 and corr.n:  # weights by the residuals at the last solution
            self.set_correspondences(corr, relative=True)
            e2 = np.sum(self.residuals_px(estimate.poses(self.t_us)) ** 2, axis=1)
            weight = irls_weight(e2 / robust ** 2, "cauchy")
        self.set_correspondences(corr, estimate.coupled, weight)

    def association_change(self, estimate) -> float | None:
        if estimate.round == 0:
            return None
        S = estimate.poses(self.t_us)
        new = estimate.correspondences()
        return correspondence_change_px(self.corr, self.residuals_px_of(self.corr, S, estimate.coupled), new,
                                        self.residuals_px_of(new, S, estimate.coupled))

    def report(self) -> dict:
        return {"n_correspondences": int(self.corr.n)}

    def set_correspondences(self, corr: Correspondences, relative: bool = True, point_weight=None) -> None:
        self.corr = corr
        self.data = CorrespondencePoints(corr, self.n, relative, point_weight)
        self._cache = {}

    @property
    def n_correspondences(self) -> int:
        return self.data.P

    def _residuals(self, G: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Normalised residuals r (P, 2) and the instance points."""
        d = self.data
        pts = d.points(G)
        uv = project_derivatives(self.camera, pts, 0)
        if d.relative:
            r = (uv[d.t_idx] - uv[d.s_idx] - d.dq) * self.scale
        else:
            r = (uv[d.t_idx] - d.target) * self.scale
        return r, pts

    def residuals_px(self, S: np.ndarray) -> np.ndarray:
        """Each correspondence's image residual (P, 2) in pixels at the poses S (n, 33), unweighted: where the model
        moves its point minus where the track moved (relative form), or minus where the track is (fixed source)."""
        return self._residuals(self.kernels.transforms(S))[0] / self.scale

    def residuals_px_of(self, corr: Correspondences, S: np.ndarray, relative: bool = True) -> np.ndarray:
        """:meth:`residuals_px` of another set of correspondences (P, 2), this factor's own set left as it is."""
        own, cache = self.data, self._cache
        try:
            self.data = CorrespondencePoints(corr, self.n, relative)
            return self.residuals_px(S)
        finally:
            self.data, self._cache = own, cache

    def _first_order(self, S: np.ndarray) -> dict:
        key = S.tobytes()
        if self._cache.get("key") == key:
            return self._cache
        d = self.data
        G, dG = self.kernels.transforms_jac(S)
        r, pts = self._residuals(G)
        dGm = dG.reshape(self.n, 4 * NUM_JOINTS, 3 * _NP)
        _, Jp = project_derivatives(self.camera, pts, 1)
        Jp *= self.scale
        wr = (2.0 * self.weight) * d.w[:, None] * r  # (P, 2)
        u = np.zeros((pts.shape[0], 3))  # gradient w.r.t. each instance point
        u[d.t_idx] += np.matmul(wr[:, None, :], Jp[d.t_idx])[:, 0, :]
        if d.relative:
            np.add.at(u, d.s_idx, -np.matmul(wr[:, None, :], Jp[d.s_idx])[:, 0, :])
        J3 = np.empty((pts.shape[0], 3, _NP))  # d(point)/dS
        g = np.zeros((self.n, _NP))
        for f, sl in d.slices:
            J3[sl] = (d.WX[sl] @ dGm[f]).reshape(-1, 3, _NP)
            g[f] += u[sl].reshape(-1) @ J3[sl].reshape(-1, _NP)
        value = self.weight * float(np.sum(d.w * np.sum(r * r, axis=1)))
        self._cache = {"key": key, "value": value, "g": g, "pts": pts, "r": r, "u": u, "J3": J3, "Jp": Jp}
        return self._cache

    def linearize(self, S, aux, order):
        S = np.ascontiguousarray(S, dtype=np.float64)
        if order == 0:
            c = self._cache
            if c.get("key") == S.tobytes():
                return Linearization(c["value"])
            r = self._residuals(self.kernels.transforms(S))[0]
            return Linearization(self.weight * float(np.sum(self.data.w * np.sum(r * r, axis=1))))
        c = self._first_order(S)
        lin = Linearization(c["value"], c["g"])
        if order >= 2:
            lin.diag, lin.upper = self._hessian(S, c)
        return lin

    def _hessian(self, S: np.ndarray, c: dict) -> tuple[np.ndarray, np.ndarray]:
        d = self.data
        diag = np.zeros((self.n, _NP, _NP))
        upper = np.zeros((self.n - 1, _NP, _NP))
        lamG = np.zeros((self.n, 4 * NUM_JOINTS, 3))  # gradient w.r.t. G, contracted with ∂²G below
        if d.P:
            _, _, Hp = project_derivatives(self.camera, c["pts"], 2)
            Hp *= self.scale
            Jp, r, J3, u = c["Jp"], c["r"], c["J3"], c["u"]
            wr = (2.0 * self.weight) * d.w[:, None] * r
            w2 = (2.0 * self.weight) * d.w[:, None, None]
            t, s_ = d.t_idx, d.s_idx
            # Point-space Hessian per instance: 2λw (JᵀJ ± Σ_a r_a H_a) (+ at frame j, - at frame i).
            Jt, Js = Jp[t], Jp[s_]
            Bp = np.zeros((Jp.shape[0], 3, 3))
            Bp[t] += w2 * np.matmul(np.swapaxes(Jt, 1, 2), Jt) + wr[:, 0, None, None] * Hp[t, 0] \
                + wr[:, 1, None, None] * Hp[t, 1]
            if d.relative:
                np.add.at(Bp, s_, w2 * np.matmul(np.swapaxes(Js, 1, 2), Js) - wr[:, 0, None, None] * Hp[s_, 0]
                          - wr[:, 1, None, None] * Hp[s_, 1])
            for f, sl in d.slices:
                Jf = J3[sl]
                diag[f] = Jf.reshape(-1, _NP).T @ np.matmul(Bp[sl], Jf).reshape(-1, _NP)
                lamG[f] = d.WX[sl].T @ u[sl]
            # Cross-frame blocks: d²/dp_lo dp_hi of w‖r‖² = -2w J_loᵀ J_hi (r is a difference of the two).
            lo, hi = d.lo[d.pair_order], d.hi[d.pair_order]
            C = -w2[d.pair_order] * np.matmul(np.swapaxes(Jp[lo], 1, 2), Jp[hi])
            R = np.matmul(C, J3[hi])
            L = J3[lo]
            for k, sl in d.pair_slices:
                upper[k] = L[sl].reshape(-1, _NP).T @ R[sl].reshape(-1, _NP)
        diag += self.kernels.contracted_hessian(S, lamG)
        return diag, upper


class TemporalStability(Factor):
    """E_temp (paper Eq. 8): λ_temp Σ_i Σ_l φ_{i,l} ‖J_l(S_i) - J_l(S_{i+1})‖² over consecutive correspondence
    frames, φ the indicator of joints held still (:func:`.correspondences.temporal_indicator` of the estimate's
    correspondences; 0 for joints that moved more than ``still_m`` between the start's ends, and for all when the
    correspondences do not couple the frames)."""

    name = "temp"
    needs = ("tracks",)
    Config = TempConfig
    couples_neighbours = True

    def __init__(self, config, template, camera, n):
        super().__init__(config, template, camera, n)
        self.kernels = shared_kernels(template.rest_joints, self.n)
        self.WXJ = premultiplied_weights(template.rest_joints, np.eye(NUM_JOINTS))  # (24, 96): J_l = WXJ_l · G
        self.phi = np.zeros((max(self.n - 1, 0), NUM_JOINTS))
        self.moved = None

    @classmethod
    def samples(cls, inputs, config) -> np.ndarray:
        tracks = inputs.tracks
        return np.zeros(0, dtype=np.int64) if tracks is None else tracks.t_us

    def collect(self, inputs) -> None:
        super().collect(inputs)
        self.phi = np.zeros((self.n - 1, NUM_JOINTS))
        self.moved = None
        self._inputs = inputs

    def relinearize(self, estimate) -> None:
        if not estimate.coupled:  # each frame on its own: nothing couples frames
            self.phi = np.zeros((self.n - 1, NUM_JOINTS))
            return
        phi = temporal_indicator(estimate.correspondences(), self.n, str(self.config.scope))
        still_m = float(self.config.still_m)
        if still_m > 0:
            if self.moved is None:
                ends = self._inputs.need("start", "E_temp")(self.t_us[[0, -1]])
                J = joint_positions(ends, self.template.rest_joints)
                self.moved = np.linalg.norm(J[1] - J[0], axis=1) > still_m
            phi[:, self.moved] = 0.0
        self.set_indicator(phi)

    def set_indicator(self, phi: np.ndarray) -> None:
        phi = np.asarray(phi, dtype=np.float64)
        if phi.shape != (self.n - 1, NUM_JOINTS):
            raise EnergyError(f"E_temp: expected phi of shape ({self.n - 1}, 24), got {phi.shape}")
        self.phi = phi

    def linearize(self, S, aux, order):
        S = np.ascontiguousarray(S, dtype=np.float64)
        if order == 0:
            J = self.WXJ @ self.kernels.transforms(S)
            dJ = J[:-1] - J[1:]
            return Linearization(self.weight * float(np.sum(self.phi * np.sum(dJ * dJ, axis=2))))
        G, dG = self.kernels.transforms_jac(S)
        J = self.WXJ @ G  # (F, 24, 3)
        dJ = J[:-1] - J[1:]
        value = self.weight * float(np.sum(self.phi * np.sum(dJ * dJ, axis=2)))
        dGm = dG.reshape(self.n, 4 * NUM_JOINTS, 3 * _NP)
        pd = (2.0 * self.weight) * self.phi[:, :, None] * dJ  # (F-1, 24, 3): gradient w.r.t. each joint position
        uJ = np.zeros((self.n, NUM_JOINTS, 3))
        uJ[:-1] += pd
        uJ[1:] -= pd
        JJ = (self.WXJ @ dGm).reshape(self.n, NUM_JOINTS, 3, _NP)  # d(joint)/dS
        g = np.matmul(uJ.reshape(self.n, 1, -1), JJ.reshape(self.n, -1, _NP))[:, 0, :]
        lin = Linearization(value, g)
        if order >= 2:
            F1 = self.n - 1
            w2t = (2.0 * self.weight) * self.phi  # (F-1, 24)
            A, Bn = JJ[:-1], JJ[1:]  # d(J_l(S_i))/dS_i and d(J_l(S_{i+1}))/dS_{i+1}
            Aw = (A * w2t[:, :, None, None]).reshape(F1, -1, _NP)
            Bw = (Bn * w2t[:, :, None, None]).reshape(F1, -1, _NP)
            A, Bn = A.reshape(F1, -1, _NP), Bn.reshape(F1, -1, _NP)
            AwT = np.swapaxes(Aw, 1, 2)
            diag = np.zeros((self.n, _NP, _NP))
            diag[:-1] += AwT @ A
            diag[1:] += np.swapaxes(Bw, 1, 2) @ Bn
            diag += self.kernels.contracted_hessian(S, self.WXJ.T @ uJ)
            lin.diag, lin.upper = diag, -(AwT @ Bn)
        return lin


__all__ = ["CorConfig", "CorrespondencePoints", "EventCorrespondences", "TempConfig", "TemporalStability"]
