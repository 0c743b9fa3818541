"""The detection terms E_2D (Eq. 6, optionally Cauchy-robust) and E_3D (Eq. 7) of one frame, the one-frame fit to
them (the paper's initialisation) with its closed-form start, and the detections' per-frame container.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import casadi as ca
import numpy as np

from eventcap.body.kinematics import joint_positions, landmark_positions
from eventcap.body.skeleton import (
    JOINT_INDEX,
    LANDMARK_INDEX,
    LANDMARK_ON_JOINT,
    NUM_JOINTS,
    NUM_LANDMARKS,
    NUM_POSE_PARAMS,
    pose_bounds,
)
from eventcap.body.template import Template
from eventcap.camera import Camera

from .errors import EnergyError, SolveFailed
from .factor import Factor, Linearization, Missing
from .loss import L2_SCALE2, rho_expression
from .settings import Joints3DConfig, Joints3DNoise, Landmarks2DConfig, Landmarks2DNoise, NoiseConfig
from .ipopt import IpoptSettings, SolveStats, run_ipopt
from .kernels import Buffered

_NP = NUM_POSE_PARAMS
#: λ_damp of the per-frame fits (the paper's initialisation): a proximal pull towards the closed-form start, which
#: keeps the angles nothing observes (a straight arm's twist) from drifting in a cold-started solve.
FIT_DAMP = 1e-3
#: Torso joints whose 3D detections fix the initial root rotation (rigid enough in any pose).
_TORSO = tuple(JOINT_INDEX[n] for n in ("pelvis", "l_hip", "r_hip", "spine1", "spine2", "spine3", "neck",
                                         "l_collar", "r_collar", "l_shoulder", "r_shoulder"))
#: (landmark index, joint index) pairs of landmarks that sit on a joint: the 2D/3D detections they share.
_ON_JOINT = tuple((LANDMARK_INDEX[lm], JOINT_INDEX[j]) for lm, j in LANDMARK_ON_JOINT.items())

@dataclass(frozen=True)
class FrameDetections:
    """Detections at D frames (2D landmarks in BODY_25 order, root-relative 3D joints in SMPL order).

    keypoints_2d (D, 25, 2) pixels; confidence_2d (D, 25) in [0, 1]; joints_3d (D, 24, 3) metres relative to the
    pelvis; confidence_3d (D, 24) in [0, 1]. Confidence 0 = not detected (the value is then ignored, NaN allowed).
    The detector's noise model, when it states one: sigma_2d_px (D, 25) each landmark's white noise per image axis
    (px), sigma_3d_m (D, 24, 3) each joint's along each camera axis (m); bias_2d_px (25,) and bias_3d_m (24, 3) the
    spread of the offsets that stay over a capture.
    """

    keypoints_2d: np.ndarray
    confidence_2d: np.ndarray
    joints_3d: np.ndarray
    confidence_3d: np.ndarray
    sigma_2d_px: np.ndarray | None = None
    sigma_3d_m: np.ndarray | None = None
    bias_2d_px: np.ndarray | None = None
    bias_3d_m: np.ndarray | None = None

    def __post_init__(self) -> None:
        kp = np.asarray(self.keypoints_2d, dtype=np.float64)
        D = kp.shape[0] if kp.ndim == 3 else -1
        shapes = {"keypoints_2d": (D, NUM_LANDMARKS, 2), "confidence_2d": (D, NUM_LANDMARKS),
                  "joints_3d": (D, NUM_JOINTS, 3), "confidence_3d": (D, NUM_JOINTS),
                  "sigma_2d_px": (D, NUM_LANDMARKS), "sigma_3d_m": (D, NUM_JOINTS, 3)}
        for name, shape in shapes.items():
            if getattr(self, name) is None and name.startswith("sigma"):
                continue
            a = np.asarray(getattr(self, name), dtype=np.float64)
            if a.shape != shape or D < 1:
                raise ValueError(f"FrameDetections.{name}: expected shape {shape} (D frames, BODY_25 landmarks, "
                                 f"SMPL joints), got {a.shape}")
            object.__setattr__(self, name, a)
        for name, shape in (("bias_2d_px", (NUM_LANDMARKS,)), ("bias_3d_m", (NUM_JOINTS, 3))):
            if getattr(self, name) is not None:
                a = np.asarray(getattr(self, name), dtype=np.float64)
                if a.shape != shape:
                    raise ValueError(f"FrameDetections.{name}: expected shape {shape}, got {a.shape}")
                object.__setattr__(self, name, a)

    @property
    def n(self) -> int:
        return int(self.keypoints_2d.shape[0])

    def rows(self, idx) -> FrameDetections:
        idx = np.atleast_1d(np.asarray(idx))
        pick = lambda a: None if a is None else a[idx]  # noqa: E731
        return FrameDetections(self.keypoints_2d[idx], self.confidence_2d[idx], self.joints_3d[idx],
                               self.confidence_3d[idx], pick(self.sigma_2d_px), pick(self.sigma_3d_m),
                               self.bias_2d_px, self.bias_3d_m)

    def observed_counts(self) -> tuple[np.ndarray, np.ndarray]:
        """(25,), (24,): in how many of these frames each landmark and each joint is observed (confidence > 0)."""
        return (self.confidence_2d > 0).sum(axis=0), (self.confidence_3d > 0).sum(axis=0)

    def problems(self) -> list[str]:
        """What makes these detections unusable (non-finite values where confidence > 0, bad confidences)."""
        out = []
        for name, cname in (("keypoints_2d", "confidence_2d"), ("joints_3d", "confidence_3d")):
            c = getattr(self, cname)
            if not np.all(np.isfinite(c)) or c.min() < 0 or c.max() > 1:
                out.append(f"{cname} must be finite values in [0, 1]")
                continue
            bad = (c > 0) & ~np.all(np.isfinite(getattr(self, name)), axis=-1)
            if bad.any():
                d, k = (int(v[0]) for v in np.nonzero(bad))
                out.append(f"{name} is not finite at detection frame {d}, entry {k} (confidence {c[d, k]:.2f})")
        return out


def select_detections(detections, times_us) -> FrameDetections:
    """Rows of a Detections artifact at the given times (exact match), as FrameDetections (with the detector's noise
    model where it states one); ValueError if missing."""
    t = np.asarray(detections.t_us, dtype=np.int64)
    want = np.asarray(times_us, dtype=np.int64).ravel()
    idx = np.searchsorted(t, want)
    ok = (idx < t.size) & (t[np.minimum(idx, max(t.size - 1, 0))] == want) if t.size else np.zeros(want.size, bool)
    if not ok.all():
        missing = want[~ok]
        raise ValueError(f"detections: no detection row at t = {missing[:5].tolist()} us "
                         f"({missing.size} of {want.size} times missing; detections cover {t.size} frames)")
    s2, s3 = getattr(detections, "sigma_2d_px", None), getattr(detections, "sigma_3d_m", None)
    return FrameDetections(detections.keypoints_2d[idx], detections.confidence_2d[idx], detections.joints_3d[idx],
                           detections.confidence_3d[idx], None if s2 is None else s2[idx],
                           None if s3 is None else s3[idx], getattr(detections, "bias_2d_px", None),
                           getattr(detections, "bias_3d_m", None))


def detection_times(detections, t0_us: int, t1_us: int) -> np.ndarray:
    """The times of a Detections artifact within [t0_us, t1_us] (intensity frames, and images between them where
    the detector looked at some)."""
    t = np.asarray(detections.t_us, dtype=np.int64)
    return t[(t >= int(t0_us)) & (t <= int(t1_us))]


# --------------------------------------------------------------------------------------------- closed-form guess
def _euler_from_matrix(R: np.ndarray) -> np.ndarray:
    """(yaw, pitch, roll) with R = R_y(yaw) R_x(pitch) R_z(roll) (skeleton convention)."""
    pitch = math.asin(float(np.clip(-R[1, 2], -1.0, 1.0)))
    yaw = math.atan2(R[0, 2], R[2, 2])
    roll = math.atan2(R[1, 0], R[1, 1])
    return np.array([yaw, pitch, roll])


def initial_guess(template: Template, camera: Camera, det: FrameDetections, d: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Closed-form start (S (33,), t' (3,)) for fitting detection frame d: joint angles zero (clipped into the
    bounds), root rotation by weighted Kabsch of the torso joints of the 3D detection against the rest skeleton,
    pelvis position by linear least squares on the rays of the 2D detections of joints (with their 3D offsets).
    """
    lo, hi = pose_bounds()
    S = np.clip(np.zeros(_NP), lo, hi)
    rest = template.rest_joints - template.rest_joints[0]
    P3, c3 = det.joints_3d[d], det.confidence_3d[d]
    idx = np.array([j for j in _TORSO if c3[j] > 0])
    R = np.eye(3)
    if idx.size >= 3:
        w = c3[idx]
        A, B = rest[idx], P3[idx]
        A0 = A - np.average(A, axis=0, weights=w)
        B0 = B - np.average(B, axis=0, weights=w)
        U, _, Vt = np.linalg.svd((B0 * w[:, None]).T @ A0)
        D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
        R = U @ D @ Vt
    S[27:30] = _euler_from_matrix(R)
    # Pelvis position T: rays of detected 2D joints through (R-posed or detected) 3D offsets from the pelvis.
    offsets = np.where(c3[:, None] > 0, np.nan_to_num(P3), rest @ R.T)
    rows, rhs, wts = [], [], []
    kp, c2 = det.keypoints_2d[d], det.confidence_2d[d]
    for lm, j in _ON_JOINT:
        if c2[lm] <= 0:
            continue
        xn, yn = camera.undistort_points(kp[lm][None])[0]
        for k, v in ((0, xn), (1, yn)):
            a = camera.R[k] - v * camera.R[2]
            rows.append(a)
            rhs.append(-(a @ offsets[j]) - (camera.t[k] - v * camera.t[2]))
            wts.append(c2[lm])
    if len(rows) >= 3:
        sw = np.sqrt(np.asarray(wts))[:, None]
        T = np.linalg.lstsq(np.asarray(rows) * sw, np.asarray(rhs) * sw[:, 0], rcond=None)[0]
    else:
        T = template.rest_joints[0].copy()
    S[30:33] = T - template.rest_joints[0]
    return S, T


def interpolate_poses(S0: np.ndarray, SN: np.ndarray, t_us: np.ndarray) -> np.ndarray:
    """Linear interpolation of S_0 and S_N at the tracking frame times (N+1, 33), proportional to time."""
    t = np.asarray(t_us, dtype=np.float64)
    a = ((t - t[0]) / (t[-1] - t[0]))[:, None]
    return (1.0 - a) * S0[None, :] + a * SN[None, :]


def unwrap_root(S: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """S with its root Euler angles moved by multiples of 2π to the nearest equivalent of ref's."""
    out = S.copy()
    d = out[27:30] - ref[27:30]
    out[27:30] -= 2.0 * np.pi * np.round(d / (2.0 * np.pi))
    return out




# --------------------------------------------------------------------------------------------- E_2D, E_3D of a frame
def keypoint_expression(template: Template, camera: Camera, S, kp, w2, s2):
    """E_2D of one frame as a CasADi expression of the pose S (33): kp (25, 2) the landmarks (px), w2 (25, 1) each
    one's weight per px² and s2 (25, 1) its Cauchy loss's squared scale in px² (symbols or values): Σ_l w2_l ·
    s2_l log(1 + e_l² / s2_l), e_l the landmark's image error in px (:func:`eventcap.energy.loss.rho_expression`;
    s2 = :data:`eventcap.energy.loss.L2_SCALE2`: least squares). :class:`DetectionWeights` gives w2 and s2."""
    L = landmark_positions(S, template)  # (25, 3)
    uv = camera.project_sym(L.T)  # (2, 25)
    r2 = uv - kp.T
    sq = ca.sum1(r2 * r2)  # (1, 25) squared landmark errors, px²
    return ca.sum2(w2.T * rho_expression(sq, s2.T))


def joint_expression(template: Template, camera: Camera, S, tp, j3, w3):
    """E_3D of one frame as a CasADi expression of the pose S (33) and the auxiliary translation t' (3): j3 (24, 3)
    root-relative joints in metres (world axes), w3 (24, 3) their weights per m² along each camera axis (x right,
    y down, z along the line of sight: Σ_j Σ_a w3_ja ((R r_j)_a)², R the camera's rotation)."""
    J = joint_positions(S, template.rest_joints)  # (24, 3)
    r3 = J - (j3 + ca.repmat(tp.T, NUM_JOINTS, 1))
    rc = ca.mtimes(r3, ca.DM(np.asarray(camera.R, dtype=np.float64).T))  # camera axes
    return ca.sum1(ca.sum2(w3 * rc * rc))


def det_symbols(prefix: str):
    """SX symbols of one frame's detection data: kp (25, 2), w2 (25, 1), s2 (25, 1), j3 (24, 3), w3 (24, 3)."""
    return (ca.SX.sym(f"{prefix}kp", NUM_LANDMARKS, 2), ca.SX.sym(f"{prefix}w2", NUM_LANDMARKS, 1),
            ca.SX.sym(f"{prefix}s2", NUM_LANDMARKS, 1), ca.SX.sym(f"{prefix}j3", NUM_JOINTS, 3),
            ca.SX.sym(f"{prefix}w3", NUM_JOINTS, 3))


@dataclass(frozen=True)
class DetectionWeights:
    """How one frame's detections weigh in E_2D and E_3D, from a solve's ``terms`` (either kind of settings,
    :mod:`eventcap.energy.settings`), without the terms' λ or gain:

    - weighted (the paper's): a landmark weighs c_l / f² per px² (focal-normalised residuals), its Cauchy scale
      ``robust_px`` (0: least squares); a joint c_j per m²;
    - noise (the spline solve's): a landmark weighs ½ / σ_l² per px², σ_l² = w_l² + n_l b_l² with w_l the
      detector's white noise for that landmark and image (or ``sigma_px``, never below ``min_sigma_px``), b_l the
      spread of its offset over a capture and n_l the frames of the solve that observe it (n images tell the white
      noise n times over, the offset once: the variance of their mean is w² / n + b²), and its loss's scale
      ``loss_scale`` σ_l; a joint ½ / σ_j² per m² alike. Only whether a confidence is > 0 counts (an observation or
      none): how good it is, is the noise model's.

    lam2 and lam3 are the terms' λ or gain (0: the term is not in the solve)."""

    lam2: float
    lam3: float
    noise2: Landmarks2DNoise | None = None
    noise3: Joints3DNoise | None = None
    robust_px: float = 0.0
    focal2: float = 1.0

    @classmethod
    def from_terms(cls, terms, camera: Camera) -> DetectionWeights:
        c2 = getattr(terms, Keypoints2D.name, None)
        c3 = getattr(terms, Joints3D.name, None)
        noise2 = c2 if isinstance(c2, Landmarks2DNoise) else None
        noise3 = c3 if isinstance(c3, Joints3DNoise) else None
        return cls(lam2=0.0 if c2 is None else float(c2.factor_weight),
                   lam3=0.0 if c3 is None else float(c3.factor_weight), noise2=noise2, noise3=noise3,
                   robust_px=0.0 if c2 is None or noise2 is not None else float(c2.robust_px),
                   focal2=float(camera.fx * camera.fy))

    def sigma_2d(self, det: FrameDetections, d: int, n: np.ndarray | float = 1.0) -> np.ndarray:
        """(25,) each landmark's noise at detection frame d among n frames that observe it (white and offset:
        class doc; n = 0: the white noise alone), px (noise settings only)."""
        c = self.noise2
        if c.sigma_px is not None:
            return np.full(NUM_LANDMARKS, max(float(c.sigma_px), float(c.min_sigma_px)))
        if det.sigma_2d_px is None:
            raise EnergyError("E_2D: the detections state no 2D noise model: set stages.solve.terms.landmarks_2d."
                              "sigma_px (px)")
        white = np.maximum(np.nan_to_num(det.sigma_2d_px[d], nan=np.inf), float(c.min_sigma_px))
        bias = np.zeros(NUM_LANDMARKS) if det.bias_2d_px is None else np.nan_to_num(det.bias_2d_px)
        return np.sqrt(white**2 + np.asarray(n, dtype=np.float64) * bias**2)

    def sigma_3d(self, det: FrameDetections, d: int, n: np.ndarray | float = 1.0) -> np.ndarray:
        """(24, 3) each joint's noise along each camera axis at detection frame d among n frames that observe it
        (class doc), m (noise settings only)."""
        c = self.noise3
        if c.sigma_mm is not None:
            return np.full((NUM_JOINTS, 3), 1e-3 * max(float(c.sigma_mm), float(c.min_sigma_mm)))
        if det.sigma_3d_m is None:
            raise EnergyError("E_3D: the detections state no 3D noise model: set stages.solve.terms.joints_3d."
                              "sigma_mm (mm)")
        white = np.maximum(np.nan_to_num(det.sigma_3d_m[d], nan=np.inf), 1e-3 * float(c.min_sigma_mm))
        bias = np.zeros((NUM_JOINTS, 3)) if det.bias_3d_m is None else np.nan_to_num(det.bias_3d_m)
        n = np.asarray(n, dtype=np.float64)
        return np.sqrt(white**2 + (n[:, None] if n.ndim else n) * bias**2)

    def values(self, det: FrameDetections, d: int, counts: tuple | None = None) -> list[np.ndarray]:
        """Detection frame d as the values of :func:`det_symbols` (column-major): kp, w2, s2, j3, w3; entries not
        observed weigh 0 (their possibly NaN values zeroed, so that they never poison the sums). counts: how many
        frames of the solve observe each landmark and joint ((25,), (24,); None: this frame alone, a per-frame fit;
        0: the white noise alone)."""
        c2, c3 = det.confidence_2d[d], det.confidence_3d[d]
        n2, n3 = (1.0, 1.0) if counts is None else counts
        kp = np.where(c2[:, None] > 0, det.keypoints_2d[d], 0.0)
        j3 = np.where(c3[:, None] > 0, det.joints_3d[d], 0.0)
        if self.noise2 is not None and self.lam2 > 0:
            sig = self.sigma_2d(det, d, n2)
            w2 = np.where(c2 > 0, 0.5 / sig**2, 0.0)
            scale = float(self.noise2.loss_scale) * sig if self.noise2.loss != "l2" else np.full(sig.shape, np.inf)
            s2 = np.minimum(scale**2, L2_SCALE2)
        else:
            w2 = c2 / self.focal2
            s2 = np.full(NUM_LANDMARKS, self.robust_px**2 if self.robust_px > 0 else L2_SCALE2)
        if self.noise3 is not None and self.lam3 > 0:
            w3 = np.where(c3[:, None] > 0, 0.5 / self.sigma_3d(det, d, n3) ** 2, 0.0)
        else:  # isotropic: the same weight along every axis, whatever the camera
            w3 = np.repeat(np.asarray(c3, dtype=np.float64)[:, None], 3, axis=1)
        return [kp.ravel(order="F"), w2, s2, j3.ravel(order="F"), w3.ravel(order="F")]

    def key(self) -> tuple:
        """What the fits' cache keys by (every setting that changes a frame's weights)."""
        return (self.lam2, self.lam3, repr(self.noise2), repr(self.noise3), self.robust_px, self.focal2)


def det_values(det: FrameDetections, d: int, weights: DetectionWeights) -> list[np.ndarray]:
    """Detection frame d as the values of :func:`det_symbols` (:meth:`DetectionWeights.values`)."""
    return weights.values(det, d)


class _MappedTerm:
    """Value, gradient and dense Hessian of a one-frame CasADi expression e(z, data...), mapped over n frames as
    three functions (a line search's values and IPOPT's gradients do not pay for the Hessian, which is most of the
    cost of one frame's terms)."""

    def __init__(self, name: str, e, z, data: list, n: int):
        H, g = ca.hessian(e, z)
        args = [z, *data]
        self.value = Buffered(ca.Function(f"{name}", args, [e]).map(n))
        self.grad = Buffered(ca.Function(f"{name}_grad", args, [e, g]).map(n))
        self.hess = Buffered(ca.Function(f"{name}_hess", args, [ca.densify(H)]).map(n))
        self.n, self.nz = n, z.numel()

    def __call__(self, z: np.ndarray, data: list[np.ndarray], order: int):
        """(values (n,), gradients (n, nz) or None, Hessians (n, nz, nz) or None)."""
        if order == 0:
            return self.value(z, *data)[0], None, None
        e, g = self.grad(z, *data)
        H = self.hess(z, *data)[0].reshape(self.n, self.nz, self.nz) if order >= 2 else None
        return e, g.reshape(self.n, self.nz), H


#: The kinds of detection a factor reads: their confidences, the noise model a detector states for them, and the
#: setting of a factor's noise model that states one instead.
_KINDS = {"2D landmarks": ("confidence_2d", "sigma_2d_px", "sigma_px"),
          "3D joints": ("confidence_3d", "sigma_3d_m", "sigma_mm")}


def detections_missing(inputs, config, reads: tuple[str, ...], noise: bool = True) -> Missing | None:
    """What the window's detections lack for a factor that reads these kinds (:data:`_KINDS`): a kind the detector
    gives nowhere in the window while it gives the other (a detector of 2D landmarks only, or of 3D joints only), or
    (noise: the factor weighs them by the detector's noise) a noise model neither the detections nor the factor's
    settings state. A window where nothing is detected lacks nothing here: it is a gap, not a mistake."""
    det = inputs.detections
    seen = {kind: bool(np.any(getattr(det, conf) > 0)) for kind, (conf, _, _) in _KINDS.items()}
    for kind in reads:
        if not seen[kind] and any(seen.values()):
            other = next(k for k in _KINDS if k != kind)
            return Missing(f"the window's detections hold no {kind} ({_KINDS[kind][0]} 0 at every frame: a detector "
                           f"of {other} only)")
    for kind in reads if noise and isinstance(config, NoiseConfig) else ():
        _, stated, setting = _KINDS[kind]
        if seen[kind] and getattr(det, stated) is None and getattr(config, setting) is None:
            unit = "px" if kind.startswith("2D") else "mm"
            return Missing(f"the window's detections state no {kind[:2]} noise model", f"{setting}=<{unit}>")
    return None


class Keypoints2D(Factor):
    """E_2D (paper Eq. 6) at every detection frame: Σ_d Σ_l w_dl ρ(‖π(L_l(S_d)) - P2D_dl‖²) over the BODY_25
    landmarks (:class:`DetectionWeights`): weighted, λ_2D c_dl / f² with the Cauchy loss of scale ``robust_px``
    (0: squares); as a noise model, ½ / σ_dl² with the detector's noise σ_dl and the loss of scale ``loss_scale``
    σ_dl. Exact Hessian (CasADi)."""

    name = "landmarks_2d"
    needs = ("t_det_us", "detections")
    Config = Landmarks2DConfig
    Noise = Landmarks2DNoise
    observes_detections = True

    def __init__(self, config, template, camera, n):
        super().__init__(config, template, camera, n)
        S = ca.SX.sym("S", _NP)
        kp, w2, s2, _, _ = det_symbols("")
        e = keypoint_expression(template, camera, S, kp, w2, s2)
        self._fn = _MappedTerm("E_2d", e, S, [kp, w2, s2], self.n)
        self._weights = DetectionWeights(lam2=self.gain, lam3=0.0, noise2=config if self.noisy else None,
                                         robust_px=0.0 if self.noisy else float(config.robust_px),
                                         focal2=float(camera.fx * camera.fy))
        self._data: list[np.ndarray] = []

    @classmethod
    def samples(cls, inputs, config) -> np.ndarray:
        return inputs.need("t_det_us", "E_2D")

    @classmethod
    def missing(cls, inputs, config) -> Missing | None:
        return super().missing(inputs, config) or detections_missing(inputs, config, ("2D landmarks",))

    def collect(self, inputs) -> None:
        super().collect(inputs)
        det = inputs.need("detections", "E_2D")
        if det.n != self.n:
            raise EnergyError(f"E_2D: expected {self.n} detection frames, got {det.n}")
        counts = det.observed_counts()
        dv = [self._weights.values(det, d, counts) for d in range(det.n)]
        self._data = [np.concatenate([v[k] for v in dv]) for k in (0, 1, 2)]

    def linearize(self, S, aux, order):
        e, g, H = self._fn(S, self._data, order)
        w = self.weight
        return Linearization(w * float(e.sum()), None if g is None else w * g, None if H is None else w * H)


class Joints3D(Factor):
    """E_3D (paper Eq. 7) at every detection frame: Σ_d Σ_l w_dl ‖J_l(S_d) - (P3D_dl + t'_d)‖², P3D the
    root-relative 3D detections (:class:`DetectionWeights`: λ_3D c_dl weighted, ½ / σ_dl² with the detector's noise),
    t'_d an auxiliary translation per frame (this factor's own variables, started at the per-frame fits' t')."""

    name = "joints_3d"
    needs = ("t_det_us", "detections")
    Config = Joints3DConfig
    Noise = Joints3DNoise
    aux_size = 3
    observes_detections = True

    def __init__(self, config, template, camera, n):
        super().__init__(config, template, camera, n)
        S, tp = ca.SX.sym("S", _NP), ca.SX.sym("tp", 3)
        _, _, _, j3, w3 = det_symbols("")
        e = joint_expression(template, camera, S, tp, j3, w3)
        self._fn = _MappedTerm("E_3d", e, ca.vertcat(S, tp), [j3, w3], self.n)
        self._weights = DetectionWeights(lam2=0.0, lam3=self.gain, noise3=config if self.noisy else None,
                                         focal2=float(camera.fx * camera.fy))
        self._data: list[np.ndarray] = []

    @classmethod
    def samples(cls, inputs, config) -> np.ndarray:
        return inputs.need("t_det_us", "E_3D")

    @classmethod
    def missing(cls, inputs, config) -> Missing | None:
        return super().missing(inputs, config) or detections_missing(inputs, config, ("3D joints",))

    def collect(self, inputs) -> None:
        super().collect(inputs)
        det = inputs.need("detections", "E_3D")
        if det.n != self.n:
            raise EnergyError(f"E_3D: expected {self.n} detection frames, got {det.n}")
        counts = det.observed_counts()
        dv = [self._weights.values(det, d, counts) for d in range(det.n)]
        self._data = [np.concatenate([v[k] for v in dv]) for k in (3, 4)]

    def start_aux(self, inputs) -> np.ndarray | None:
        t = inputs.evidence("fit_translation")
        return None if t is None else np.nan_to_num(np.asarray(t, dtype=np.float64))

    def linearize(self, S, aux, order):
        z = np.concatenate([S, aux], axis=1)
        e, g, H = self._fn(z, self._data, order)
        w = self.weight
        lin = Linearization(w * float(e.sum()))
        if g is not None:
            lin.grad, lin.aux_grad = w * g[:, :_NP], w * g[:, _NP:]
        if H is not None:
            lin.diag, lin.cross, lin.aux_diag = w * H[:, :_NP, :_NP], w * H[:, :_NP, _NP:], w * H[:, _NP:, _NP:]
        return lin


class FrameFitter:
    """The one-frame fit of a pose to its detections (E_2D + E_3D, the paper's initialisation), built once; the
    detections weigh as a solve's terms say (:class:`DetectionWeights`).

    lower/upper: bounds (33,) of the pose parameters; settings: pinned IPOPT options (cold-started fits).
    """

    def __init__(self, template: Template, camera: Camera, settings: IpoptSettings, lower: np.ndarray,
                 upper: np.ndarray):
        self.template, self.camera, self.settings = template, camera, settings
        self.lower, self.upper = lower, upper
        S = ca.SX.sym("S", _NP)
        tp = ca.SX.sym("tp", 3)
        lam = ca.SX.sym("lam", 3)  # 2D, 3D, damp
        ref = ca.SX.sym("ref", _NP)
        kp, w2, s2, j3, w3 = det = det_symbols("")
        e2 = keypoint_expression(template, camera, S, kp, w2, s2)
        e3 = joint_expression(template, camera, S, tp, j3, w3)
        p = ca.vertcat(lam, ref, *[ca.vec(v) for v in det])
        x = ca.vertcat(S, tp)
        f = lam[0] * e2 + lam[1] * e3 + lam[2] * ca.sumsqr(S - ref)
        self.solver = ca.nlpsol("fit_frame", "ipopt", {"x": x, "p": p, "f": f}, settings.options(False))
        self.terms = ca.Function("fit_terms", [x, p], [e2, e3])

    def fit(self, det: FrameDetections, d: int, weights: DetectionWeights, damp: float,
            start: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray, SolveStats]:
        """Fit one pose to detection frame d, weighed as ``weights`` say, with the proximal pull λ_damp: (S (33,),
        t' (3,), stats).

        start: (S, t') warm start; default :func:`initial_guess`, from which E_3D alone is fitted first.
        """
        if det.confidence_2d[d].max() <= 0 and det.confidence_3d[d].max() <= 0:
            raise SolveFailed(f"detection frame {d}: nothing detected (all confidences 0): cannot fit a pose",
                              status="no_detections")
        lbx = np.concatenate([self.lower, np.full(3, -np.inf)])
        ubx = np.concatenate([self.upper, np.full(3, np.inf)])
        d2, d3 = weights.lam2, weights.lam3
        stages = [(d2, d3)]
        if start is None:
            start = initial_guess(self.template, self.camera, det, d)
            # From the closed-form guess (a T-pose), the projection term has many poor local minima (limbs
            # swung to the wrong side); the 3D term alone has few. Fit it first, then everything.
            if det.confidence_3d[d].max() > 0 and d3 > 0:
                stages.insert(0, (0.0, d3))
        values = weights.values(det, d)
        x = np.concatenate([np.clip(start[0], self.lower, self.upper), start[1]])
        its, secs = 0, 0.0
        for w2, w3 in stages:
            p = np.concatenate([[w2, w3, damp], x[:_NP], *values])
            x, stats = run_ipopt(self.solver, x, p, lbx, ubx, f"fit of detection frame {d}")
            its, secs = its + stats.iterations, secs + stats.seconds
        return x[:_NP], x[_NP:], replace(stats, iterations=its, seconds=secs)
