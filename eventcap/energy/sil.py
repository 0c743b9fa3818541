"""E_sil (paper Sec. 3.3, Eq. 9-13): the silhouette of the posed template against the events, shared by the solves
that use it (the refinement stage, the spline solve).

For poses S_f at F frames, with the template's silhouette boundary pixels s_b of each frame, their outward normals
n_b and surface points v_b (:mod:`.boundary`) and the closest event u_b of each s_b (Eq. 12-13,
:mod:`.event_search`):

    λ_sil Σ_b ρ(n_bᵀ(π(v_b(S_f)) - u_b) / f) + λ_stab Σ_l ‖J_l(S_f) - J_l(Ŝ_f)‖²                           (Eq. 9-11)

- E_sil (Eq. 11): the point-to-line (2D "point-to-plane") distance of the projected surface point to its event,
  along the boundary normal. ρ is the loss: ``l2`` (ρ(r) = r², the paper) or ``huber`` (r² for |r| <= δ, else
  2δ|r| - δ², δ = ``huber_px``): events from texture inside the body or from the background that happen to be the
  nearest ones then pull linearly instead of quadratically.
- E_stab (Eq. 10): the 24 joints stay close to reference joints J(Ŝ_f) (λ_stab = 0: no such term).

Units: image residuals are divided by the focal length f = sqrt(fx·fy) in pixels (focal-normalised image units),
3D residuals are metres. Boundary pixels without any event in their patch and window give no correspondence.

How it is computed: value, gradient and exact Hessian, per frame (frames do not interact: the Hessian is block
diagonal). The 24 skinning transforms G(S) (96×3), their Jacobian and the contraction of their second derivatives
come from :class:`eventcap.energy.kernels.SkinningKernels`; each surface point is v = WX·G (premultiplied weights,
kept sparse: a point is weighted to 2-9 of the 24 joints), its Jacobian WX·∂G; the residuals' derivatives w.r.t.
the point (camera model of :meth:`Camera.project`, closed form) and the per-point products are compiled loops
(:mod:`._sil_kernels`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from eventcap.body.skeleton import NUM_JOINTS, NUM_POSE_PARAMS
from eventcap.body.template import Template
from eventcap.camera import Camera

from .boundary import NORMAL_SIGMA_PX, boundary_samples
from .event_search import EventIndex

_NP = NUM_POSE_PARAMS
LOSSES = ("l2", "huber")


@dataclass(frozen=True)
class SilhouetteWeights:
    """λ of Eq. 9 and Eq. 12 and the loss of E_sil (units: module doc)."""

    sil: float = 1.0
    stab: float = 5.0
    dist: float = 4.0  # λ_dist of the closest event search (Eq. 12)
    loss: str = "l2"
    huber_px: float = 1.0  # δ of the Huber loss, pixels

    def __post_init__(self) -> None:
        for name in ("sil", "stab", "dist", "huber_px"):
            v = getattr(self, name)
            if isinstance(v, bool) or not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"SilhouetteWeights.{name}: expected a finite number >= 0, got {v!r}")
        if self.loss not in LOSSES:
            raise ValueError(f"loss: expected one of {LOSSES}, got {self.loss!r}")
        if self.loss == "huber" and not self.huber_px > 0:
            raise ValueError(f"huber_px: the Huber loss needs a threshold > 0 pixels, got {self.huber_px!r}")


@dataclass(frozen=True)
class SilhouetteCorrespondences:
    """E_sil data of a batch: one row per matched boundary pixel b. P rows, sorted by frame."""

    frame: np.ndarray  #: (P,) int64
    rest_points: np.ndarray  #: (P, 3) rest-space v_b, metres
    weights: np.ndarray  #: (P, 24) skinning weights
    normal: np.ndarray  #: (P, 2) n_b, unit
    target_px: np.ndarray  #: (P, 2) u_b, pixels

    @property
    def n(self) -> int:
        return int(self.frame.shape[0])

    @classmethod
    def empty(cls) -> SilhouetteCorrespondences:
        return cls(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, NUM_JOINTS)), np.zeros((0, 2)),
                   np.zeros((0, 2)))


def robust_loss(r: np.ndarray, loss: str, delta: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ρ(r), ρ'(r), ρ''(r) elementwise for ``l2`` (r²) or ``huber`` (r² inside |r| <= δ, 2δ|r| - δ² outside)."""
    if loss == "l2":
        return r * r, 2.0 * r, np.full_like(r, 2.0)
    if loss == "huber":
        a = np.abs(r)
        inside = a <= delta
        return (np.where(inside, r * r, 2.0 * delta * a - delta * delta),
                np.where(inside, 2.0 * r, 2.0 * delta * np.sign(r)), np.where(inside, 2.0, 0.0))
    raise ValueError(f"loss: expected one of {LOSSES}, got {loss!r}")


# --------------------------------------------------------------------------------------------- the energy (numpy)
class SilhouetteEnergy:
    """E_refine of all F frames as a function of the poses S (F, 33): value, gradient and exact Hessian blocks.

    Data (:meth:`set_data`): the correspondences, the reference joints J(Ŝ) (F, 24, 3) and the weights.
    """

    def __init__(self, camera: Camera, kernels, rest_joints: np.ndarray):
        from eventcap.energy.kernels import premultiplied_weights

        from ._sil_kernels import camera_params

        self.camera, self.kernels, self.F = camera, kernels, kernels.F
        self.cam = camera_params(camera)
        self.scale = 1.0 / math.sqrt(camera.fx * camera.fy)
        self.WXJ = premultiplied_weights(rest_joints, np.eye(NUM_JOINTS))  # (24, 96): J_l = WXJ_l · G
        self.set_data(SilhouetteCorrespondences.empty(), np.zeros((self.F, NUM_JOINTS, 3)), SilhouetteWeights())

    def set_data(self, corr: SilhouetteCorrespondences, ref_joints: np.ndarray, weights: SilhouetteWeights) -> None:
        ref_joints = np.asarray(ref_joints, dtype=np.float64)
        if ref_joints.shape != (self.F, NUM_JOINTS, 3):
            raise ValueError(f"reference joints: expected shape ({self.F}, 24, 3), got {ref_joints.shape}")
        if corr.n and (corr.frame.min() < 0 or corr.frame.max() >= self.F or np.any(np.diff(corr.frame) < 0)):
            raise ValueError(f"correspondences: frames must be sorted and lie in [0, {self.F})")
        self.corr, self.ref, self.w = corr, ref_joints, weights
        from ._sil_kernels import sparse_premultiplied

        # Premultiplied weights WX (P, 96), point = WX · G, kept as their nonzeros (~15%: 2-9 joints per point).
        self.nz_idx, self.nz_val = sparse_premultiplied(corr.rest_points, corr.weights)
        self.frame = np.ascontiguousarray(corr.frame, dtype=np.int64)
        self.normal = np.ascontiguousarray(corr.normal, dtype=np.float64)
        self.target = np.ascontiguousarray(corr.target_px, dtype=np.float64)
        self.delta = weights.huber_px * self.scale
        bounds = np.searchsorted(corr.frame, np.arange(self.F + 1))
        self.slices = [(f, slice(bounds[f], bounds[f + 1])) for f in range(self.F) if bounds[f + 1] > bounds[f]]
        most = int(np.diff(bounds).max()) if self.F else 0
        self._buffers = (np.empty((most, 3 * _NP)), np.empty((most, 3 * _NP)))  # J3 and B·J3 of one frame
        self._cache: dict = {}

    # -------------------------------------------------------------- pieces
    def _points(self, G: np.ndarray) -> np.ndarray:
        from ._sil_kernels import sparse_points

        pts = np.empty((self.corr.n, 3))
        sparse_points(self.nz_idx, self.nz_val, self.frame, np.ascontiguousarray(G), pts)
        return pts

    def residuals(self, pts: np.ndarray, order: int = 0):
        """Normalised point-to-line residuals r (P,) of the surface points pts (P, 3), and with order >= 1 their
        gradient (P, 3), with order 2 their Hessian (P, 3, 3) w.r.t. the points."""
        from ._sil_kernels import residual_derivatives

        P = pts.shape[0]
        r, gr = np.empty(P), np.empty((P, 3) if order >= 1 else (0, 3))
        hr = np.empty((P, 3, 3) if order >= 2 else (0, 3, 3))
        residual_derivatives(np.ascontiguousarray(pts), self.normal, self.target, self.cam, self.scale, int(order),
                             r, gr, hr)
        return r, gr, hr

    def terms(self, S: np.ndarray) -> dict:
        """Unweighted E_sil (with the loss) and E_stab, per frame: {'sil': (F,), 'stab': (F,)}."""
        S = np.asarray(S, dtype=np.float64).reshape(self.F, _NP)
        G = self.kernels.transforms(S)
        sil = np.zeros(self.F)
        if self.corr.n:
            rho = robust_loss(self.residuals(self._points(G))[0], self.w.loss, self.delta)[0]
            np.add.at(sil, self.corr.frame, rho)
        d = self.WXJ @ G - self.ref
        return {"sil": sil, "stab": np.sum(d * d, axis=(1, 2))}

    def value(self, S: np.ndarray) -> float:
        t = self.terms(S)
        return float(self.w.sil * t["sil"].sum() + self.w.stab * t["stab"].sum())

    def _first_order(self, S: np.ndarray) -> dict:
        from ._sil_kernels import sparse_accumulate

        key = S.tobytes()
        if self._cache.get("key") == key:
            return self._cache
        G, dG = self.kernels.transforms_jac(S)
        lamG = np.zeros((self.F, 4 * NUM_JOINTS, 3))  # ∂E/∂G per frame
        value = 0.0
        c = {"key": key, "dG": dG}
        if self.corr.n:
            pts = self._points(G)
            r, gr, hr = self.residuals(pts, 2)
            rho, d1, d2 = robust_loss(r, self.w.loss, self.delta)
            a = (self.w.sil * d1)[:, None] * gr  # ∂E/∂point
            sparse_accumulate(self.nz_idx, self.nz_val, self.frame, a, lamG)
            value += self.w.sil * float(rho.sum())
            c.update(d1=d1, d2=d2, gr=gr, hr=hr)
        J = self.WXJ @ G
        dJ = J - self.ref
        value += self.w.stab * float(np.sum(dJ * dJ))
        lamG += self.WXJ.T @ ((2.0 * self.w.stab) * dJ)  # ∂E/∂J (F, 24, 3) carried to G
        # ∂E/∂S_f = Σ_{a,c} ∂E/∂G[f,a,c] · ∂G[f,a,c]/∂S_f: points and joints are linear in G.
        g = np.matmul(lamG.reshape(self.F, 1, -1), dG.reshape(self.F, -1, _NP))[:, 0, :]
        c.update(value=value, g=g, lamG=lamG)
        self._cache = c
        return c

    # -------------------------------------------------------------- what IPOPT calls
    def gradient(self, S: np.ndarray) -> tuple[float, np.ndarray]:
        c = self._first_order(np.asarray(S, dtype=np.float64).reshape(self.F, _NP))
        return c["value"], c["g"]

    def hessian(self, S: np.ndarray) -> np.ndarray:
        """Exact Hessian as diagonal blocks (F, 33, 33) (frames do not interact)."""
        from ._sil_kernels import point_jacobians

        S = np.asarray(S, dtype=np.float64).reshape(self.F, _NP)
        c = self._first_order(S)
        dGm = c["dG"].reshape(self.F, 4 * NUM_JOINTS, 3 * _NP)
        diag = np.zeros((self.F, _NP, _NP))
        if self.corr.n:
            # Σ_p J3_pᵀ B_p J3_p per frame, with J3_p = ∂point/∂S = WX_p · ∂G and the point-space Hessian of
            # λ ρ(r): B_p = λ (ρ'' ∇r ∇rᵀ + ρ' ∇²r). Frame by frame, so that J3 and B·J3 stay in cache.
            c2, c1 = self.w.sil * c["d2"], self.w.sil * c["d1"]
            gr, hr = c["gr"], c["hr"]
            J3, BJ = self._buffers
            for f, sl in self.slices:
                n = sl.stop - sl.start
                point_jacobians(self.nz_idx[sl], self.nz_val[sl], f, dGm, c2[sl], gr[sl], c1[sl], hr[sl], J3[:n],
                                BJ[:n])
                diag[f] = J3[:n].reshape(-1, _NP).T @ BJ[:n].reshape(-1, _NP)
        JJ = (self.WXJ @ dGm).reshape(self.F, -1, _NP)  # ∂J/∂S per frame (F, 72, 33)
        diag += (2.0 * self.w.stab) * np.matmul(np.swapaxes(JJ, 1, 2), JJ)
        diag += self.kernels.contracted_hessian(S, c["lamG"])
        return diag




def find_silhouette_correspondences(template: Template, camera: Camera, poses: np.ndarray, index: EventIndex,
                         weights: SilhouetteWeights, patch_px: int,
                         sigma_px: float = NORMAL_SIGMA_PX) -> tuple[SilhouetteCorrespondences, int, dict]:
    """One correspondence search: boundary samples of ``poses`` (F, 33) and their closest events.

    Returns (matched correspondences, number of boundary samples, seconds per phase).
    """
    t0 = time.perf_counter()
    samples = boundary_samples(template, camera, poses, sigma_px)
    t1 = time.perf_counter()
    m = index.closest(samples.frame, samples.pixel, weights.dist, patch_px)
    corr = SilhouetteCorrespondences(frame=samples.frame[m.found], rest_points=samples.rest_points[m.found],
                           weights=samples.weights[m.found], normal=samples.normal[m.found],
                           target_px=m.target_px[m.found])
    return corr, samples.n, {"boundary": t1 - t0, "search": time.perf_counter() - t1}


__all__ = ["LOSSES", "SilhouetteCorrespondences", "SilhouetteEnergy", "SilhouetteWeights",
           "find_silhouette_correspondences", "robust_loss"]
