"""E_sil (paper Sec. 3.3, Eq. 9-13): the silhouette of the posed template against the events, shared by the solves
that use it (the refinement stage, the spline solve).

For poses S_f at F frames, with the template's silhouette boundary pixels s_b of each frame, their outward normals
n_b and surface points v_b (:mod:`.boundary`) and the closest event u_b of each s_b (Eq. 12-13,
:mod:`.event_search`):

    λ_sil Σ_b ρ(n_bᵀ(π(v_b(S_f)) - u_b) / f) + λ_stab Σ_l ‖J_l(S_f) - J_l(Ŝ_f)‖²                           (Eq. 9-11)

- E_sil (Eq. 11): the point-to-line (2D "point-to-plane") distance of the projected surface point to its event,
  along the boundary normal. ρ is the loss: ``l2`` (ρ(r) = r², the paper) or ``huber`` (r² for |r| <= δ, else
  2δ|r| - δ², δ = ``sil_huber_px``): events from texture inside the body or from the background that happen to be the
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
from .errors import EnergyError
from .event_search import EventIndex
from .factor import Factor, Linearization
from .loss import residual_loss
from .settings import LOSSES, SilConfig, SilNoise, StabConfig
from .kernels import premultiplied_weights, shared_kernels

_NP = NUM_POSE_PARAMS


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
    """ρ(r²), its first and second derivative in r, elementwise, for ``l2`` (r²) or ``huber`` (r² inside |r| <= δ,
    2δ|r| - δ² outside): :func:`eventcap.energy.loss.residual_loss`."""
    if loss not in LOSSES:
        raise ValueError(f"loss: expected one of {LOSSES}, got {loss!r}")
    return residual_loss(r, loss, delta)


# --------------------------------------------------------------------------------------------- the factors
def sil_frames(t_us: np.ndarray, step_ms: float) -> np.ndarray:
    """E_sil's frames of a batch: its tracking frames t_us every ``step_ms`` (rounded to frames), its first and last
    included."""
    t_us = np.asarray(t_us, dtype=np.int64)
    if t_us.size < 2:
        return t_us
    k = max(1, int(round(step_ms * 1000 / max(1, int(np.median(np.diff(t_us)))))))
    return np.unique(np.append(t_us[::k], t_us[-1]))


def window_sil_frames(track_times_us, step_ms: float) -> np.ndarray:
    """The frames of a window's batches (their tracking frames, one array per batch) every ``step_ms``
    (:func:`sil_frames` of each batch, together, sorted)."""
    parts = [sil_frames(t, step_ms) for t in track_times_us]
    return np.unique(np.concatenate(parts)) if parts else np.zeros(0, dtype=np.int64)


class SilhouetteToEvents(Factor):
    """E_sil (Eq. 11): λ_sil Σ_b ρ(n_bᵀ(π(v_b(S_f)) - u_b) / f) at its frames (module doc), ρ the loss ``loss``
    (l2 | huber, threshold ``huber_px``); the boundary's closest events are searched again at each ICP round;
    exact block-diagonal Hessian."""

    name = "sil"
    needs = ("track_times_us", "events")
    Config = SilConfig
    Noise = SilNoise

    @classmethod
    def noise_precision(cls, config, camera) -> float:
        # residuals are focal-normalised: σ_px / f of them
        return 0.5 * camera.fx * camera.fy / float(config.sigma_px) ** 2

    def __init__(self, config, template, camera: Camera, n: int):
        from ._sil_kernels import camera_params

        super().__init__(config, template, camera, n)
        self.loss = str(config.loss)
        self.huber_px = (float(config.loss_scale) * float(config.sigma_px) if self.noisy
                         else float(config.huber_px))
        if self.loss not in LOSSES:
            raise EnergyError(f"terms.sil.loss: expected one of {LOSSES}, got {self.loss!r}")
        if self.loss == "huber" and not self.huber_px > 0:
            raise EnergyError(f"terms.sil.huber_px: the Huber loss needs a threshold > 0 pixels, got "
                              f"{self.huber_px!r}")
        self.kernels = shared_kernels(template.rest_joints, self.n)
        self.cam = camera_params(camera)
        self.scale = 1.0 / math.sqrt(camera.fx * camera.fy)
        self.delta = self.huber_px * self.scale
        self.index: EventIndex | None = None
        self.n_boundary, self.seconds = 0, {}
        self.set_correspondences(SilhouetteCorrespondences.empty())

    @classmethod
    def samples(cls, inputs, config) -> np.ndarray:
        return window_sil_frames(inputs.track_times_us, float(config.step_ms))

    def collect(self, inputs) -> None:
        super().collect(inputs)
        self.set_correspondences(SilhouetteCorrespondences.empty())
        self.index, self.n_boundary, self.seconds = None, 0, {}
        if inputs.events is None:
            return
        c, cam = self.config, self.camera
        window_us = (int(inputs.t1_us - inputs.t0_us) if c.window_ms is None
                     else int(round(float(c.window_ms) * 1000)))
        t0 = time.perf_counter()
        try:
            self.index = EventIndex(inputs.events, cam.width, cam.height, self.t_us, window_us, int(c.denoise_us))
        except ValueError as exc:
            raise EnergyError(f"E_sil: the events: {exc}") from exc
        self.seconds = {"index": time.perf_counter() - t0}

    def relinearize(self, estimate) -> None:
        if self.index is None or not estimate.associate:
            return
        c = self.config
        corr, self.n_boundary, secs = find_silhouette_correspondences(
            self.template, self.camera, estimate.poses(self.t_us), self.index, float(c.dist), int(c.patch_px))
        self.seconds = {**self.seconds, **{k: self.seconds.get(k, 0.0) + v for k, v in secs.items()}}
        self.set_correspondences(corr)

    def report(self) -> dict:
        out = {"n_silhouette": int(self.corr.n), "n_boundary": int(self.n_boundary)}
        if self.index is not None:
            out.update(events_searched=int(self.index.n_events), events_dropped=int(self.index.n_unsupported))
        return out

    def describe(self) -> str | None:
        return (f"E_sil at {self.n} frames: {self.corr.n} of {self.n_boundary} silhouette boundary pixels matched to "
                f"an event (last round)")

    def set_correspondences(self, corr: SilhouetteCorrespondences) -> None:
        from ._sil_kernels import sparse_premultiplied

        if corr.n and (corr.frame.min() < 0 or corr.frame.max() >= self.n or np.any(np.diff(corr.frame) < 0)):
            raise EnergyError(f"E_sil: correspondences' frames must be sorted and lie in [0, {self.n})")
        self.corr = corr
        # Premultiplied weights WX (P, 96), point = WX · G, kept as their nonzeros (~15%: 2-9 joints per point).
        self.nz_idx, self.nz_val = sparse_premultiplied(corr.rest_points, corr.weights)
        self.frame = np.ascontiguousarray(corr.frame, dtype=np.int64)
        self.normal = np.ascontiguousarray(corr.normal, dtype=np.float64)
        self.target = np.ascontiguousarray(corr.target_px, dtype=np.float64)
        bounds = np.searchsorted(corr.frame, np.arange(self.n + 1))
        self.slices = [(f, slice(bounds[f], bounds[f + 1])) for f in range(self.n) if bounds[f + 1] > bounds[f]]
        most = int(np.diff(bounds).max()) if self.n else 0
        self._buffers = (np.empty((most, 3 * _NP)), np.empty((most, 3 * _NP)))  # J3 and B·J3 of one frame
        self._cache: dict = {}

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

    def per_frame(self, S: np.ndarray) -> np.ndarray:
        """Unweighted E_sil (with the loss) per frame (n,)."""
        out = np.zeros(self.n)
        if self.corr.n:
            rho = robust_loss(self.residuals(self._points(self.kernels.transforms(S)))[0], self.loss, self.delta)[0]
            np.add.at(out, self.corr.frame, rho)
        return out

    def _first_order(self, S: np.ndarray) -> dict:
        from ._sil_kernels import sparse_accumulate

        key = S.tobytes()
        if self._cache.get("key") == key:
            return self._cache
        G, dG = self.kernels.transforms_jac(S)
        lamG = np.zeros((self.n, 4 * NUM_JOINTS, 3))  # ∂E/∂G per frame
        c = {"key": key, "dG": dG, "value": 0.0}
        if self.corr.n:
            r, gr, hr = self.residuals(self._points(G), 2)
            rho, d1, d2 = robust_loss(r, self.loss, self.delta)
            sparse_accumulate(self.nz_idx, self.nz_val, self.frame, (self.weight * d1)[:, None] * gr, lamG)
            c.update(value=self.weight * float(rho.sum()), d1=d1, d2=d2, gr=gr, hr=hr)
        # ∂E/∂S_f = Σ_{a,c} ∂E/∂G[f,a,c] · ∂G[f,a,c]/∂S_f: points are linear in G.
        c["g"] = np.matmul(lamG.reshape(self.n, 1, -1), dG.reshape(self.n, -1, _NP))[:, 0, :]
        c["lamG"] = lamG
        self._cache = c
        return c

    def linearize(self, S, aux, order):
        S = np.ascontiguousarray(S, dtype=np.float64)
        if order == 0:
            return Linearization(self.weight * float(self.per_frame(S).sum()))
        c = self._first_order(S)
        lin = Linearization(c["value"], c["g"])
        if order >= 2:
            lin.diag = self._hessian(S, c)
        return lin

    def _hessian(self, S: np.ndarray, c: dict) -> np.ndarray:
        from ._sil_kernels import point_jacobians

        dGm = c["dG"].reshape(self.n, 4 * NUM_JOINTS, 3 * _NP)
        diag = np.zeros((self.n, _NP, _NP))
        if self.corr.n:
            # Σ_p J3_pᵀ B_p J3_p per frame, with J3_p = ∂point/∂S = WX_p · ∂G and the point-space Hessian of
            # λ ρ(r): B_p = λ (ρ'' ∇r ∇rᵀ + ρ' ∇²r). Frame by frame, so that J3 and B·J3 stay in cache.
            c2, c1 = self.weight * c["d2"], self.weight * c["d1"]
            gr, hr = c["gr"], c["hr"]
            J3, BJ = self._buffers
            for f, sl in self.slices:
                m = sl.stop - sl.start
                point_jacobians(self.nz_idx[sl], self.nz_val[sl], f, dGm, c2[sl], gr[sl], c1[sl], hr[sl], J3[:m],
                                BJ[:m])
                diag[f] = J3[:m].reshape(-1, _NP).T @ BJ[:m].reshape(-1, _NP)
        diag += self.kernels.contracted_hessian(S, c["lamG"])
        return diag


class JointStability(Factor):
    """E_stab (Eq. 10): λ_stab Σ_f Σ_l ‖J_l(S_f) - J_l(Ŝ_f)‖², the 24 joints held near the window's reference joints
    (the refinement's: where the batch solve put them), at the reference's times."""

    name = "stab"
    needs = ("reference_us", "reference_joints")
    Config = StabConfig

    def __init__(self, config, template, camera, n):
        super().__init__(config, template, camera, n)
        self.kernels = shared_kernels(template.rest_joints, self.n)
        self.WXJ = premultiplied_weights(template.rest_joints, np.eye(NUM_JOINTS))  # (24, 96): J_l = WXJ_l · G
        self.ref = np.zeros((self.n, NUM_JOINTS, 3))

    @classmethod
    def samples(cls, inputs, config) -> np.ndarray:
        t = inputs.reference_us
        return np.zeros(0, dtype=np.int64) if t is None else t

    def collect(self, inputs) -> None:
        super().collect(inputs)
        ref = np.asarray(inputs.need("reference_joints", "E_stab"), dtype=np.float64)
        if ref.shape != (self.n, NUM_JOINTS, 3):
            raise EnergyError(f"E_stab: reference joints: expected shape ({self.n}, 24, 3), got {ref.shape}")
        self.ref = ref

    def per_frame(self, S: np.ndarray) -> np.ndarray:
        d = self.WXJ @ self.kernels.transforms(np.ascontiguousarray(S, dtype=np.float64)) - self.ref
        return np.sum(d * d, axis=(1, 2))

    def linearize(self, S, aux, order):
        S = np.ascontiguousarray(S, dtype=np.float64)
        if order == 0:
            return Linearization(self.weight * float(self.per_frame(S).sum()))
        G, dG = self.kernels.transforms_jac(S)
        dJ = self.WXJ @ G - self.ref
        lamG = self.WXJ.T @ ((2.0 * self.weight) * dJ)  # ∂E/∂J (F, 24, 3) carried to G
        g = np.matmul(lamG.reshape(self.n, 1, -1), dG.reshape(self.n, -1, _NP))[:, 0, :]
        lin = Linearization(self.weight * float(np.sum(dJ * dJ)), g)
        if order >= 2:
            JJ = (self.WXJ @ dG.reshape(self.n, 4 * NUM_JOINTS, 3 * _NP)).reshape(self.n, -1, _NP)
            lin.diag = ((2.0 * self.weight) * np.matmul(np.swapaxes(JJ, 1, 2), JJ)
                        + self.kernels.contracted_hessian(S, lamG))
        return lin


def find_silhouette_correspondences(template: Template, camera: Camera, poses: np.ndarray, index: EventIndex,
                                    dist: float, patch_px: int,
                                    sigma_px: float = NORMAL_SIGMA_PX) -> tuple[SilhouetteCorrespondences, int, dict]:
    """One correspondence search: boundary samples of ``poses`` (F, 33) and their closest events (Eq. 12-13: within
    ``patch_px`` and the index's time window, λ_dist = ``dist`` weighing time against distance).

    Returns (matched correspondences, number of boundary samples, seconds per phase).
    """
    t0 = time.perf_counter()
    samples = boundary_samples(template, camera, poses, sigma_px)
    t1 = time.perf_counter()
    m = index.closest(samples.frame, samples.pixel, dist, patch_px)
    corr = SilhouetteCorrespondences(frame=samples.frame[m.found], rest_points=samples.rest_points[m.found],
                           weights=samples.weights[m.found], normal=samples.normal[m.found],
                           target_px=m.target_px[m.found])
    return corr, samples.n, {"boundary": t1 - t0, "search": time.perf_counter() - t1}


__all__ = ["LOSSES", "JointStability", "SilConfig", "SilhouetteCorrespondences", "SilhouetteToEvents", "StabConfig",
           "sil_frames", "window_sil_frames",
           "find_silhouette_correspondences", "robust_loss"]
