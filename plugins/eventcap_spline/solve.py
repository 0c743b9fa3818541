"""The spline solve (not in the paper): one continuous-time pose trajectory over a window of several batches.

    min_C,t'  Σ_d λ_2D E_2D(S(t_d)) + λ_3D E_3D(S(t_d), t'_d)          every intensity frame d of the window
              + λ_cor E_cor(S(t_0), S(t_s), S(t_2s), ...)               the batch's (or window's) tracks (ICP)
              + λ_prior Σ_p ∫ (S_p^(k)(t))² dt                           motion prior, k = 2 or 3, exact
              + λ_still Σ_j ∫ s_j(t) ‖d/dt π(x_j(S(t)))‖² dt            event silence: joints without events rest
              + Σ_d Σ_p w_dp (S_p(t_d) - g_p(t_d))²                     context pull: g the smoothed fits around
              + λ_damp ‖x - x_start‖²
    s.t.      θ_min <= C_i <= θ_max  for every control point i           (exact joint limits on S(t))

S(t) = Σ_i B_i(t) C_i is a uniform cubic B-spline in the 33 pose parameters (:mod:`eventcap.energy.spline`), so
the unknowns are the n_seg + 3 control points instead of 1,000 poses per second, and the motion is C² at any rate.

Why. The paper's batches are pinned at both ends to per-frame detection fits that are 3-7 cm off, independently
from frame to frame (NOTES.md): the 1 kHz motion between them cannot be smooth, and no batch can average that
noise. Here detections enter as soft, robust observations at every intensity frame of the window, the events add
the relative motion within the batch, and the prior keeps velocities smooth; averaging the detector's noise over
several frames is where the accuracy comes from.

Terms (all from :mod:`eventcap.energy`): E_2D (Cauchy-robust) and E_3D of one frame are CasADi SX expressions of
(S, t') whose value, gradient and 36×36 Hessian are one mapped CasADi function; E_cor is the numpy energy of the
batch solve (:class:`eventcap.energy.cor.CorrespondenceEnergy`, relative form, exact block-tridiagonal Hessian) at
the spline's poses at the correspondence frames; the prior is a fixed quadratic form; E_still
(:mod:`eventcap.energy.silence`: s_j(t) is joint j's stillness measured from the events around its bones) is the
joints' image velocity linearised at each solve's start, a fixed quadratic form too (Gauss-Newton); the context
pull (:func:`prior_gain`, gated by :func:`still_gate`) is a fixed quadratic form at the detection frames. Every term is a
function of poses S = B C, linear in C, so the chain rule is a product with the (sparse) basis: g_C = Bᵀ g_S and
H_C = Bᵀ H_S B. IPOPT sees the sum through numpy callbacks (value, gradient, exact Hessian with a banded sparsity:
control points i and j interact only when |i - j| <= 3, plus the t' of each detection frame).

Built once per run (:class:`SplineProblem`, keyed by the window's sizes); each window's data are handed to the
numpy callbacks before its solve. Correspondences are re-searched at the current spline (ICP), as in the batch
solve. Every IPOPT status is checked (:func:`eventcap.energy.ipopt.run_ipopt`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import casadi as ca
import numpy as np

from eventcap.body.kinematics import joint_positions
from eventcap.body.skeleton import NUM_JOINTS, NUM_POSE_PARAMS
from eventcap.body.template import Template
from eventcap.camera import Camera
from eventcap.energy.cor import CorrespondenceEnergy
from eventcap.energy.event_search import DENOISE_US, EventIndex
from eventcap.energy.sil import (
    SilhouetteCorrespondences,
    SilhouetteEnergy,
    SilhouetteWeights,
    find_silhouette_correspondences,
)
from eventcap.energy.correspondences import Correspondences, find_correspondences
from eventcap.energy.detections import (
    FrameDetections,
    FrameFitter,
    det_symbols,
    det_values,
    detection_terms,
    unwrap_root,
)
from eventcap.energy.ipopt import IpoptSettings, NumpyCallback, SolveStats, checked_bounds, run_ipopt
from eventcap.energy.kernels import Buffered, SkinningKernels
from eventcap.energy.silence import Silence, SilenceSettings, measure_silence
from eventcap.energy.spline import GAUSS3, PRIOR_ORDERS, UniformCubicBSpline
from eventcap.smoothing import MIN_KNOTS, GcvCurve, check_criterion
from eventcap.stage import StageFailed

_NP = NUM_POSE_PARAMS
#: Per-frame fits of this process, by (fitter, weights, detections of the frame): each frame is in several windows.
_FITS: dict = {}


@dataclass(frozen=True)
class SplineWeights:
    """λ of the spline energy (units: as in the batch solve; the prior per (unit/s^k)²·s)."""

    d2: float = 200.0
    d3: float = 1.0
    cor: float = 500.0
    prior: float = 5e-4
    damp: float = 1e-4
    still: float = 0.0  #: event silence: per (px/s)²·s of the image velocity of a joint the events call still (0: off)
    sil: float = 0.0  #: E_sil: per boundary pixel, focal-normalised point-to-line distance to its closest event (0: off)
    context: float = 0.0  #: pull towards the smoothed fits of the frames around the window, × what they know (0: off)

    def __post_init__(self) -> None:
        for name in ("d2", "d3", "cor", "prior", "damp", "still", "sil", "context"):
            v = getattr(self, name)
            if isinstance(v, bool) or not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"SplineWeights.{name}: expected a finite number >= 0, got {v!r}")


@dataclass(frozen=True)
class SilhouetteSettings:
    """How E_sil's data are found (:mod:`eventcap.energy.sil`): the closest event (Eq. 12-13) of each boundary pixel
    of the estimate's silhouette within ``patch_px`` and within ± window_us / 2 of the frame, λ_dist weighing time
    against distance, events without a neighbour within ± denoise_us dropped as noise; the loss and its δ (px)."""

    window_us: int = 10_000
    patch_px: int = 8
    dist: float = 4.0
    denoise_us: int = DENOISE_US
    loss: str = "huber"
    huber_px: float = 1.0

    def weights(self, sil: float) -> SilhouetteWeights:
        return SilhouetteWeights(sil=sil, stab=0.0, dist=self.dist, loss=self.loss, huber_px=self.huber_px)


@dataclass(frozen=True)
class WindowResult:
    """The solved spline of one window and how it was obtained."""

    spline: UniformCubicBSpline
    control: np.ndarray  #: (n_ctrl, 33) control points
    t_prime: np.ndarray  #: (D, 3) t' of E_3D per detection frame
    fits: np.ndarray  #: (D, 33) the per-frame fits (root angles unwrapped along the window) it started from
    energies: dict
    solves: tuple[SolveStats, ...]  #: the spline solves (one per ICP round)
    seconds: dict
    fits_computed: int = 0  #: per-frame fits computed for this window (the others came from neighbouring windows)
    prior_gain: np.ndarray | None = None  #: (33,) the prior's gain per parameter (None: 1)
    silence: Silence | None = None  #: the events' stillness per knot interval and joint (None: term off)
    pull_frames: np.ndarray | None = None  #: (D, 33) the context pull in frames' worth, 1/h - 1 (None: off)


def _banded_triu(n_ctrl: int, n_t: int):
    """Upper-triangular sparsity of the Hessian: 33×33 blocks of control points with |i - j| <= 3, every (C, t')
    entry, the t' × t' upper triangle. Returns (sparsity, rows, cols) with rows/cols in CasADi's nonzero order."""
    nC = n_ctrl * _NP
    r, c = np.triu_indices(nC + n_t)
    keep = (c >= nC) | (np.abs(r // _NP - c // _NP) <= 3)
    r, c = r[keep], c[keep]
    order = np.lexsort((r, c))
    r, c = r[order], c[order]
    return ca.Sparsity.triplet(nC + n_t, nC + n_t, r.tolist(), c.tolist()), r, c


class SplineProblem:
    """The spline NLP for windows of ``n_seg`` knot intervals, ``n_det`` detection frames and ``n_cor`` frames of
    correspondences, built once (template, camera, sizes, prior order, settings, bounds)."""

    def __init__(self, template: Template, camera: Camera, n_seg: int, n_det: int, n_cor: int,
                 settings: IpoptSettings = IpoptSettings(), lower=None, upper=None, robust_px: float = 2.0,
                 prior: str = "acceleration", n_sil: int = 0):
        if prior not in PRIOR_ORDERS:
            raise ValueError(f"prior: expected one of {sorted(PRIOR_ORDERS)}, got {prior!r}")
        for name, v, least in (("n_seg", n_seg, 1), ("n_det", n_det, 1), ("n_cor", n_cor, 2), ("n_sil", n_sil, 0)):
            if isinstance(v, bool) or int(v) != v or v < least:
                raise ValueError(f"SplineProblem: {name} must be an integer >= {least}, got {v!r}")
        t0 = time.perf_counter()
        self.template, self.camera, self.settings = template, camera, settings
        self.n_seg, self.n_det, self.n_cor, self.n_sil = int(n_seg), int(n_det), int(n_cor), int(n_sil)
        self.n_ctrl = self.n_seg + 3
        self.order = PRIOR_ORDERS[prior]
        self.lower, self.upper = checked_bounds(lower, upper, "SplineProblem")
        self.nC, self.nT = self.n_ctrl * _NP, 3 * self.n_det
        self.nx = self.nC + self.nT
        self.fitter = FrameFitter(template, camera, settings, self.lower, self.upper, robust_px)
        # --- E_2D + E_3D of one frame: value, gradient, Hessian in (S, t'), mapped over the detection frames
        S, tp, lam = ca.SX.sym("S", _NP), ca.SX.sym("tp", 3), ca.SX.sym("lam", 2)
        det = det_symbols("")
        e2, e3 = detection_terms(template, camera, S, tp, *det, robust_px=float(robust_px))
        z = ca.vertcat(S, tp)
        e = lam[0] * e2 + lam[1] * e3
        H, g = ca.hessian(e, z)
        # Three mapped functions, so a line search's values and IPOPT's gradients do not pay for the Hessian
        # (measured: the Hessian is most of the cost of one frame's terms).
        args = [z, *det, lam]
        self._det_value = Buffered(ca.Function("E_det", args, [e, e2, e3]).map(self.n_det))
        self._det_grad = Buffered(ca.Function("E_det_grad", args, [e, g, e2, e3]).map(self.n_det))
        self._det_hess = Buffered(ca.Function("E_det_hess", args, [ca.densify(H)]).map(self.n_det))
        # --- E_still: the Jacobian of the 24 projected joints, mapped over the 3 Gauss points of every knot interval
        px = camera.project_sym(joint_positions(S, template.rest_joints).T)  # (2, 24)
        self._joint_px_jac = Buffered(ca.Function("joint_px_jac", [S], [ca.densify(ca.jacobian(
            ca.reshape(px, 2 * NUM_JOINTS, 1), S))]).map(3 * self.n_seg))
        # --- E_cor at n_cor frames
        self.cor = CorrespondenceEnergy(camera, SkinningKernels(template.rest_joints, self.n_cor),
                                        template.rest_joints)
        # --- E_sil at n_sil frames (none: no silhouette term)
        self.sil = (SilhouetteEnergy(camera, SkinningKernels(template.rest_joints, self.n_sil), template.rest_joints)
                    if self.n_sil else None)
        # --- the NLP: x = [C (n_ctrl × 33, row-major); t' (n_det × 3)], data through set_window
        self._sp, hr, hc = _banded_triu(self.n_ctrl, self.nT)
        # where each nonzero sits in [Hcc (n, n, 33, 33), Hct (nC, nT), Htt (nT, nT)] raveled one after another
        nC, nT, n = self.nC, self.nT, self.n_ctrl
        cc, ct = (hr < nC) & (hc < nC), (hr < nC) & (hc >= nC)
        self._gather = np.where(
            cc, ((hr // _NP) * n + hc // _NP) * _NP * _NP + (hr % _NP) * _NP + hc % _NP,
            np.where(ct, n * n * _NP * _NP + hr * nT + (hc - nC),
                     n * n * _NP * _NP + nC * nT + (hr - nC) * nT + (hc - nC)))
        self._cache: dict = {}
        self._data = None
        nx = self.nx
        self._callbacks = [
            NumpyCallback("E_spline", nx, [ca.Sparsity.dense(1, 1)], lambda v: [self._eval(v, 0)["value"]]),
            NumpyCallback("E_spline_grad", nx, [ca.Sparsity.dense(1, 1), ca.Sparsity.dense(nx, 1)],
                          lambda v: [self._eval(v, 1)["value"], self._eval(v, 1)["grad"]]),
            NumpyCallback("E_spline_hess", nx, [self._sp], lambda v: [self._hessian_values(v)]),
        ]
        cb_f, cb_g, cb_h = self._callbacks
        X, P = ca.MX.sym("x", nx), ca.MX.sym("p", 0)
        lam_f, lam_g = ca.MX.sym("lam_f"), ca.MX.sym("lam_g", 0)
        val, grad = cb_g(X)
        grad_f = ca.Function("grad_f", [X, P], [val, grad], ["x", "p"], ["f", "grad_f_x"])
        hess_lag = ca.Function("hess_lag", [X, P, lam_f, lam_g], [lam_f * cb_h(X)],
                               ["x", "p", "lam_f", "lam_g"], ["hess_gamma_x_x"])
        #: Objective, gradient and upper-triangular Hessian exactly as IPOPT sees them (for derivative checks).
        self.objective = ca.Function("objective", [X], [cb_f(X)])
        self.gradient = ca.Function("gradient", [X], [val, grad])
        self.hessian = ca.Function("hessian", [X], [cb_h(X)])
        opts = dict(settings.options(True), grad_f=grad_f, hess_lag=hess_lag)
        self.solver = ca.nlpsol("spline", "ipopt", {"x": X, "p": P, "f": cb_f(X)}, opts)
        self.build_seconds = time.perf_counter() - t0

    # ------------------------------------------------------------------ data of one window
    def set_window(self, spline: UniformCubicBSpline, t_det_us, det: FrameDetections, t_cor_us,
                   corr: Correspondences, weights: SplineWeights, x_ref: np.ndarray,
                   prior_gain: np.ndarray | None = None, still: np.ndarray | None = None,
                   cor_weight: np.ndarray | None = None, t_sil_us=None,
                   sil: tuple[SilhouetteCorrespondences, SilhouetteSettings] | None = None,
                   pull: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        """Hand one window's data to the energy: the spline basis, detections at t_det_us (n_det rows),
        correspondences between the frames at t_cor_us (n_cor), weights, the proximal term's reference x, the
        motion prior's gain per pose parameter (33,) (its weight is λ_prior · gain_p; default 1), and the
        event-silence weights still (n_seg, 24): λ_still times each joint's stillness per knot interval
        (E_still = Σ_s Σ_j still[s, j] ∫_s ‖J_j(S_ref(t)) S'(t)‖² dt, the image velocity of joint j in px/s
        linearised at x_ref; :mod:`eventcap.energy.silence`; None: no such term), and a weight in [0, 1] per
        correspondence (corr.n,) (None: 1 each). E_sil (weights.sil > 0): its data at the n_sil frames t_sil_us,
        (silhouette correspondences, settings); None: no such term. pull: the context pull's (target, weight), each
        (n_det, 33): Σ_d Σ_p weight[d, p] (S_p(t_d) - target[d, p])² (:func:`prior_gain`); None: no such term."""
        if spline.n_seg != self.n_seg:
            raise ValueError(f"set_window: the problem was built for {self.n_seg} knot intervals, got {spline.n_seg}")
        if det.n != self.n_det or np.size(t_det_us) != self.n_det:
            raise ValueError(f"set_window: expected {self.n_det} detection frames, got {det.n} rows at "
                             f"{np.size(t_det_us)} times")
        if np.size(t_cor_us) != self.n_cor:
            raise ValueError(f"set_window: expected {self.n_cor} correspondence frames, got {np.size(t_cor_us)}")
        x_ref = np.asarray(x_ref, dtype=np.float64)
        if x_ref.shape != (self.nx,):
            raise ValueError(f"set_window: expected x_ref of shape ({self.nx},), got {x_ref.shape}")
        gain = np.ones(_NP) if prior_gain is None else np.asarray(prior_gain, dtype=np.float64)
        if gain.shape != (_NP,) or not np.all(np.isfinite(gain) & (gain > 0)):
            raise ValueError(f"set_window: expected a positive prior gain per pose parameter ({_NP},), got "
                             f"{np.shape(prior_gain)}")
        form = None
        if still is not None:
            still = np.asarray(still, dtype=np.float64)
            if still.shape != (self.n_seg, NUM_JOINTS) or not np.all(np.isfinite(still) & (still >= 0)):
                raise ValueError(f"set_window: expected event-silence weights >= 0 of shape ({self.n_seg}, "
                                 f"{NUM_JOINTS}), got {still.shape}")
            form = self._still_form(spline, x_ref[:self.nC].reshape(self.n_ctrl, _NP), still)
        if cor_weight is not None:
            cor_weight = np.asarray(cor_weight, dtype=np.float64)
            if cor_weight.shape != (corr.n,) or not np.all((cor_weight >= 0) & (cor_weight <= 1)):
                raise ValueError(f"set_window: expected a weight in [0, 1] per correspondence ({corr.n},), got "
                                 f"shape {cor_weight.shape}")
        self.cor.set_correspondences(corr, relative=True, point_weight=cor_weight)
        Bs = None
        if sil is not None and weights.sil > 0:
            if self.sil is None or np.size(t_sil_us) != self.n_sil:
                raise ValueError(f"set_window: the problem was built for {self.n_sil} silhouette frames, got "
                                 f"{np.size(t_sil_us)}")
            self.sil.set_data(sil[0], np.zeros((self.n_sil, NUM_JOINTS, 3)), sil[1].weights(weights.sil))
            Bs = spline.basis(t_sil_us)
        if pull is not None:
            pull = tuple(np.asarray(v, dtype=np.float64) for v in pull)
            target, weight = pull
            if (target.shape != (self.n_det, _NP) or weight.shape != target.shape or not np.all(np.isfinite(target))
                    or not np.all(np.isfinite(weight) & (weight >= 0))):
                raise ValueError(f"set_window: expected the context pull's target and weights >= 0 of shape "
                                 f"({self.n_det}, {_NP}), got {[np.shape(v) for v in pull]}")
        dv = [det_values(det, d) for d in range(self.n_det)]
        self._data = {
            "Bd": spline.basis(t_det_us), "Be": spline.basis(t_cor_us), "Q": spline.gram(self.order),
            "wp": weights.prior * gain, "still": form,
            "det": [np.concatenate([v[k] for v in dv]) for k in range(4)],
            "lam_det": np.tile([weights.d2, weights.d3], self.n_det), "w": weights, "x_ref": x_ref,
            "phi": np.zeros((self.n_cor - 1, NUM_JOINTS)), "lam_cor": np.array([weights.cor, 0.0]), "Bs": Bs,
            "pull": pull,
        }
        self._cache = {}

    def _still_form(self, spline: UniformCubicBSpline, C_ref: np.ndarray, still: np.ndarray) -> dict:
        """E_still as a fixed quadratic form in C: at the 3 Gauss points q of every knot interval s,
        M_q = h w_q Σ_j still[s, j] J_jᵀ J_j (33×33, J_j the 2×33 Jacobian of joint j's pixel at S_ref(t_q)), so
        E = Σ_q (B'_q C)ᵀ M_q (B'_q C); its Hessian blocks (n_ctrl, n_ctrl, 33, 33) are summed per interval."""
        g, wq = GAUSS3[0], GAUSS3[1] * spline.h_s
        seg = np.repeat(np.arange(self.n_seg), 3)
        t_q = spline.t0_us + spline.h_us * (seg + np.tile(g, self.n_seg))
        Sq = spline.evaluate(C_ref, t_q)
        Jq = self._joint_px_jac(Sq)[0].reshape(3 * self.n_seg, _NP, NUM_JOINTS, 2)  # (48, 33·Q) column-major
        wjq = still[seg] * np.tile(wq, self.n_seg)[:, None]  # (Q, 24)
        M = np.einsum("qajx,qj,qbjx->qab", Jq, wjq, Jq)
        B1 = spline.basis(t_q, 1)
        # Hessian: 2 Σ_q b_q b_qᵀ ⊗ M_q, with each interval's 4 control points (local basis values)
        loc = B1[np.arange(seg.size)[:, None], seg[:, None] + np.arange(4)[None, :]]  # (Q, 4)
        blocks = 2.0 * np.einsum("qa,qb,qxy->qabxy", loc, loc, M).reshape(self.n_seg, 3, 4, 4, _NP, _NP).sum(1)
        H = np.zeros((self.n_ctrl, self.n_ctrl, _NP, _NP))
        s_idx = np.arange(self.n_seg)
        for a in range(4):
            for b in range(4):
                H[s_idx + a, s_idx + b] += blocks[:, a, b]
        return {"B1": B1, "M": M, "H": H}

    def _split(self, x):
        return x[:self.nC].reshape(self.n_ctrl, _NP), x[self.nC:].reshape(self.n_det, 3)

    def _eval(self, x, order: int) -> dict:
        """Value (order 0) and gradient (order 1) of the energy at x, with its pieces (cached per x)."""
        if self._data is None:
            raise RuntimeError("SplineProblem: set_window() must be called before evaluating the energy")
        x = np.asarray(x, dtype=np.float64)
        key = x.tobytes()
        c = self._cache
        if c.get("key") == key and c.get("order", -1) >= order:
            return c
        D = self._data
        w: SplineWeights = D["w"]
        C, T = self._split(x)
        Sd, Se = D["Bd"] @ C, D["Be"] @ C
        z = np.concatenate([Sd, T], axis=1)
        if order == 0:
            e, e2, e3 = self._det_value(z, *D["det"], D["lam_det"])
        else:
            e, g, e2, e3 = self._det_grad(z, *D["det"], D["lam_det"])
        QC = D["Q"] @ C * D["wp"]  # λ_prior · gain_p · Q C_p per parameter p
        e_prior = float(np.sum(C * QC))  # the weighted prior
        e_still, g_still = 0.0, None
        if D["still"] is not None:
            B1, M = D["still"]["B1"], D["still"]["M"]
            V = B1 @ C  # (Q, 33) velocities at the Gauss points
            MV = np.einsum("qab,qb->qa", M, V)
            e_still = float(np.sum(V * MV))
            g_still = 2.0 * (B1.T @ MV)
        e_pull, WR = 0.0, None
        if D["pull"] is not None:
            R = Sd - D["pull"][0]
            WR = D["pull"][1] * R
            e_pull = float(np.sum(WR * R))
        dx = x - D["x_ref"]
        Ss = None if D["Bs"] is None else D["Bs"] @ C
        out = {"key": key, "order": order, "z": z, "Se": Se, "Ss": Ss, "sil_w": 0.0,
               "det": float(e.sum()), "2d": float(e2.sum()), "3d": float(e3.sum()), "prior": e_prior,
               "still": e_still, "pull": e_pull, "damp": float(dx @ dx)}
        if order == 0:
            out["cor_w"] = self.cor.value(Se, D["phi"], D["lam_cor"])
            if Ss is not None:
                out["sil_w"] = self.sil.value(Ss)
        else:
            out["cor_w"], gS = self.cor.gradient(Se, D["phi"], D["lam_cor"])
            gz = g.reshape(self.n_det, _NP + 3)
            gC = D["Bd"].T @ gz[:, :_NP] + D["Be"].T @ gS + 2.0 * QC
            if g_still is not None:
                gC += g_still
            if WR is not None:
                gC += 2.0 * (D["Bd"].T @ WR)
            if Ss is not None:
                out["sil_w"], gSs = self.sil.gradient(Ss)
                gC += D["Bs"].T @ gSs
            grad = np.concatenate([gC.ravel(), gz[:, _NP:].ravel()]) + (2.0 * w.damp) * dx
            out["grad"] = grad
        out["value"] = (out["det"] + out["cor_w"] + out["sil_w"] + e_prior + e_still + e_pull
                        + w.damp * out["damp"])
        self._cache = out
        return out

    def _hessian_parts(self, x) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The Hessian of the energy at x in three parts: control-point blocks (n_ctrl, n_ctrl, 33, 33) for every
        pair (i, j), the (C, t') block (nC, nT) and the t' block (nT, nT)."""
        c = self._eval(x, 1)
        D = self._data
        n = self.n_ctrl
        nn = n * n
        # detections: S_d = b_dᵀ C
        Bd = D["Bd"]
        Hd = self._det_hess(c["z"], *D["det"], D["lam_det"])[0].reshape(self.n_det, _NP + 3, _NP + 3)
        Wd = (Bd[:, :, None] * Bd[:, None, :]).reshape(self.n_det, nn)
        Hcc = Wd.T @ Hd[:, :_NP, :_NP].reshape(self.n_det, -1)
        # correspondences: S_f = b_fᵀ C, block-tridiagonal in f (upper block u_f couples f and f+1)
        diag, upper = self.cor.hessian(c["Se"], D["phi"], D["lam_cor"])
        Be = D["Be"]
        Hcc += ((Be[:, :, None] * Be[:, None, :]).reshape(self.n_cor, nn).T @ diag.reshape(self.n_cor, -1))
        Hcc += ((Be[:-1, :, None] * Be[1:, None, :]).reshape(self.n_cor - 1, nn).T
                @ upper.reshape(self.n_cor - 1, -1))
        Hcc += ((Be[1:, :, None] * Be[:-1, None, :]).reshape(self.n_cor - 1, nn).T
                @ upper.transpose(0, 2, 1).reshape(self.n_cor - 1, -1))
        if c["Ss"] is not None:  # silhouette: S_s = b_sᵀ C, block-diagonal in s
            Bs = D["Bs"]
            Hcc += (Bs[:, :, None] * Bs[:, None, :]).reshape(self.n_sil, nn).T @ self.sil.hessian(c["Ss"]).reshape(
                self.n_sil, -1)
        Hcc = Hcc.reshape(n, n, _NP, _NP)
        # prior (2 Q ⊗ diag(λ_prior · gain)) and proximal term on the diagonal; event silence (its fixed blocks)
        w = D["w"]
        diag_idx = np.arange(_NP)
        Hcc[:, :, diag_idx, diag_idx] += 2.0 * D["Q"][:, :, None] * D["wp"][None, None, :]
        if D["pull"] is not None:  # context pull: 2 Σ_d b_d b_dᵀ ⊗ diag(weight_d)
            Hcc[:, :, diag_idx, diag_idx] += 2.0 * (Wd.T @ D["pull"][1]).reshape(n, n, _NP)
        if D["still"] is not None:
            Hcc += D["still"]["H"]
        ii = np.arange(n)
        Hcc[ii[:, None], ii[:, None], diag_idx[None, :], diag_idx[None, :]] += 2.0 * w.damp
        Hct = np.einsum("di,dab->iadb", Bd, Hd[:, :_NP, _NP:]).reshape(self.nC, self.nT)
        Htt = np.zeros((self.nT, self.nT))
        for d in range(self.n_det):
            Htt[3 * d:3 * d + 3, 3 * d:3 * d + 3] = Hd[d, _NP:, _NP:]
        Htt[np.diag_indices(self.nT)] += 2.0 * w.damp
        return Hcc, Hct, Htt

    def _hessian(self, x) -> np.ndarray:
        """The full (symmetric, dense) Hessian of the energy at x, every block included (for checks: IPOPT gets
        :meth:`_hessian_values`)."""
        Hcc, Hct, Htt = self._hessian_parts(x)
        nC = self.nC
        Hx = np.zeros((self.nx, self.nx))
        Hx[:nC, :nC] = Hcc.transpose(0, 2, 1, 3).reshape(nC, nC)
        Hx[:nC, nC:] = Hct
        Hx[nC:, :nC] = Hct.T
        Hx[nC:, nC:] = Htt
        return Hx

    def _hessian_values(self, x) -> np.ndarray:
        """The Hessian's nonzeros in the declared sparsity's order, gathered from its parts (no dense matrix)."""
        Hcc, Hct, Htt = self._hessian_parts(x)
        return np.concatenate([Hcc.ravel(), Hct.ravel(), Htt.ravel()])[self._gather]

    # ------------------------------------------------------------------ solving
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        lbx = np.concatenate([np.tile(self.lower, self.n_ctrl), np.full(self.nT, -np.inf)])
        ubx = np.concatenate([np.tile(self.upper, self.n_ctrl), np.full(self.nT, np.inf)])
        return lbx, ubx

    def solve(self, x0: np.ndarray, what: str) -> tuple[np.ndarray, SolveStats]:
        lbx, ubx = self.bounds()
        x0 = np.clip(np.asarray(x0, dtype=np.float64), lbx, ubx)
        return run_ipopt(self.solver, x0, np.zeros(0), lbx, ubx, what)


def fit_window(problem: SplineProblem, det: FrameDetections,
               weights: SplineWeights) -> tuple[np.ndarray, np.ndarray, list[SolveStats], int]:
    """Per-frame fits (E_2D + E_3D, the paper's initialisation) at every detection frame of the window, with the
    root angles unwrapped along the window: (S (D, 33), t' (D, 3), stats, how many were computed here rather than
    taken from this process's earlier windows)."""
    S = np.zeros((det.n, _NP))
    T = np.zeros((det.n, 3))
    stats = []
    computed = 0
    for d in range(det.n):
        (s, t, st), new = frame_fit(problem, det, d, weights)
        computed += new
        S[d], T[d] = (unwrap_root(s, S[d - 1]) if d else s), t
        stats.append(st)
    return S, T, stats, computed


def frame_fit(problem: SplineProblem, det: FrameDetections, d: int, weights: SplineWeights):
    """The per-frame fit of detection frame d, ((S, t', stats), whether it was computed now). A frame's fit is a
    deterministic function of its detections, so neighbouring windows of this process share it."""
    key = (id(problem.fitter), weights.d2, weights.d3, *(v.tobytes() for v in det_values(det, d)))
    if key in _FITS:
        return _FITS[key], 0
    if len(_FITS) > 512:
        _FITS.clear()
    _FITS[key] = problem.fitter.fit(det, d, weights.d2, weights.d3, 1e-3)
    return _FITS[key], 1


@dataclass(frozen=True)
class PriorGain:
    """The motion prior's gain per pose parameter of one window, chosen from the per-frame fits around it."""

    gain: np.ndarray  #: (33,) in [1, gain_max]
    lam: np.ndarray  #: (33,) REML smoothing parameter of each parameter's fits (s³)
    curvature: np.ndarray  #: (33,) mean diagonal of the detection terms' Hessian at the window's fits / 2 (NaN:
    #: not needed, too few fits)
    n_fits: int  #: fits in the context
    fits_computed: int
    pull: tuple[np.ndarray, np.ndarray] | None = None  #: the context pull's (target, frames' worth 1/h - 1), each
    #: (D, 33); its weight is weights.context · curvature · frames' worth (None: off)


def prior_gain(problem: SplineProblem, t_ctx_us: np.ndarray, det_ctx: FrameDetections, window_fits: np.ndarray,
               window_tp: np.ndarray, det: FrameDetections, weights: SplineWeights, gain_max: float,
               criterion: str = "reml", t_det_us: np.ndarray | None = None) -> PriorGain:
    """How much stiffer than λ_prior the prior of each pose parameter should be, from the data alone.

    The per-frame fits y_p(t_k) at the intensity frames around the window (t_ctx_us, their detections det_ctx)
    are each parameter's samples of a smoothing-spline model, y = f + noise with ∫ f''² penalised by lam_p; lam_p
    is chosen by REML or GCV (``criterion``, :mod:`eventcap.smoothing`): large where the fits vary no more than
    their noise (a limb at rest, an angle the detections cannot tell), small where the parameter moves. In the
    window's energy a parameter's detections weigh about a_p (the detection terms' curvature, mean diagonal of their
    Hessian at the window's fits / 2) per rad², so the same trade-off there is a prior weight of a_p · lam_p; the
    gain is that over λ_prior, clipped to [1, gain_max]: the prior never gets weaker than its default, and static
    parameters stop wiggling with the detections' noise. Frames of the context whose fit fails are left out.

    The context pull (weights.context > 0, the window's detection frames t_det_us): the same smoothing splines'
    values g_p(t_d) at the window's frames, and how much more than the frame's own detections they know there:
    a_p (1 / h_dp - 1), h_dp the smoother's leverage of frame d (its hat matrix' diagonal; 1 / h_dp is what the
    smoother's estimate at d weighs in frames). A parameter the frames call static (heavy smoothing, h ≈ 2 / K of
    K frames) is held near the line through all K fits, which the window's few frames and its acceleration prior
    cannot tell (a trend within a window costs the prior nothing); one that moves (h → 1) is not held. Returned as
    PriorGain.pull = (g, 1 / h - 1) per window frame; a frame whose fit failed gets 0 frames' worth."""
    S, computed = [], 0
    keep = []
    for d in range(det_ctx.n):
        try:
            (s, _, _), new = frame_fit(problem, det_ctx, d, weights)
        except StageFailed:
            continue
        computed += new
        S.append(unwrap_root(s, S[-1]) if S else s)
        keep.append(d)
    want_pull = weights.context > 0 and t_det_us is not None
    if len(keep) < MIN_KNOTS or ((weights.prior <= 0 or gain_max <= 1) and not want_pull):
        return PriorGain(np.ones(_NP), np.full(_NP, np.nan), np.full(_NP, np.nan), len(keep), computed)
    z = np.concatenate([window_fits, window_tp], axis=1)
    dv = [det_values(det, d) for d in range(det.n)]
    H = problem._det_hess(z, *[np.concatenate([v[k] for v in dv]) for k in range(4)],
                          np.tile([weights.d2, weights.d3], det.n))[0].reshape(det.n, _NP + 3, _NP + 3)
    a = np.maximum(np.einsum("dpp->dp", H[:, :_NP, :_NP]).mean(0) / 2.0, 0.0)
    t_keep, Y = np.asarray(t_ctx_us, dtype=np.int64)[keep], np.stack(S)
    curve = GcvCurve((t_keep - t_keep[0]) * 1e-6)
    gains_on = weights.prior > 0 and gain_max > 1  # else only lam is wanted (for the pull): the gains stay 1
    gain, lam = gains_from_fits(t_keep, Y, a, weights.prior if gains_on else 1.0, gain_max if gains_on else 1.0,
                                criterion, curve)
    pull = None
    if want_pull:
        g, h = smoothed_at(t_keep, Y, lam, np.asarray(t_det_us, dtype=np.int64), curve)
        frames = np.zeros_like(g)
        for d in np.flatnonzero(np.isfinite(h[:, 0])):
            g[d] = unwrap_root(g[d], window_fits[d])
            frames[d] = np.maximum(1.0 / h[d] - 1.0, 0.0)
        pull = (np.where(np.isfinite(g), g, window_fits), frames)
    return PriorGain(gain, lam, a, len(keep), computed, pull)


def _gating_joints() -> list[np.ndarray]:
    """Per pose parameter, the joints whose bones it turns: a joint angle's the children of its joint, the root's
    rotation and translation the pelvis and its children."""
    from eventcap.body.skeleton import DOF_JOINT, PARENTS

    root = np.concatenate([[0], np.flatnonzero(PARENTS == 0)])
    return [np.flatnonzero(PARENTS == j) for j in DOF_JOINT] + [root] * (_NP - len(DOF_JOINT))


_GATING = _gating_joints()


def still_gate(silence: Silence, t_us: np.ndarray, floor: float = 0.0) -> np.ndarray:
    """(len(t_us), 33) in [floor, 1]: how still each pose parameter is at t_us by the events, the least stillness of
    the bones it turns (:func:`_gating_joints`) in the knot interval holding t, as floor + (1 - floor) · stillness
    (floor 0: the stillness itself; 1: every parameter 1, no gate)."""
    if not (isinstance(floor, (int, float)) and not isinstance(floor, bool) and 0.0 <= floor <= 1.0):
        raise ValueError(f"still_gate: floor: expected a number in [0, 1], got {floor!r}")
    k = np.clip(np.searchsorted(silence.edges_us, np.asarray(t_us, dtype=np.int64), side="right") - 1, 0,
                silence.stillness.shape[0] - 1)
    st = silence.stillness[k]
    gate = np.stack([st[:, j].min(axis=1) for j in _GATING], axis=1)
    return gate if floor == 0.0 else floor + (1.0 - floor) * gate


def smoothed_at(t_us: np.ndarray, fits: np.ndarray, lam: np.ndarray, t_at_us: np.ndarray,
                curve: GcvCurve | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(g, h), both (len(t_at_us), P): the cubic smoothing splines through each column p of fits (K, P) at times
    t_us (K,) with smoothing parameter lam_p (s³), and their leverage (hat-matrix diagonal, in (0, 1]), at those
    of t_us that t_at_us names (:meth:`eventcap.smoothing.GcvCurve.fitted`; curve: the GcvCurve of t_us if already
    built); NaN rows where t_at_us is not among t_us."""
    t = np.asarray(t_us, dtype=np.int64)
    curve = GcvCurve((t - t[0]) * 1e-6) if curve is None else curve
    rows = np.searchsorted(t, t_at_us)
    hit = (rows < t.size) & (t[np.minimum(rows, t.size - 1)] == t_at_us)
    g = np.full((len(t_at_us), np.shape(fits)[1]), np.nan)
    h = np.full_like(g, np.nan)
    g[hit], h[hit] = curve.fitted(fits, lam, rows[hit])
    return g, h


def gains_from_fits(t_us: np.ndarray, fits: np.ndarray, curvature: np.ndarray, lam_prior: float,
                    gain_max: float, criterion: str = "reml",
                    curve: GcvCurve | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(gain (P,), lam (P,)): each column p of fits (K, P) at times t_us (K,) gets the smoothing parameter lam_p
    (s³) of a cubic smoothing spline through it chosen by ``criterion`` (reml | gcv), and the gain
    clip(curvature_p · lam_p / lam_prior, 1, gain_max) of :func:`prior_gain` (curve: the GcvCurve of t_us if
    already built)."""
    check_criterion(criterion)
    t = np.asarray(t_us, dtype=np.int64)
    curve = GcvCurve((t - t[0]) * 1e-6) if curve is None else curve
    Y = np.asarray(fits, dtype=np.float64)
    lam = curve.choose_each(Y, criterion)
    return np.clip(np.asarray(curvature) * lam / lam_prior, 1.0, float(gain_max)), lam


def solve_window(problem: SplineProblem, spline: UniformCubicBSpline, t_det_us: np.ndarray, det: FrameDetections,
                 t_cor_us: np.ndarray, xy: np.ndarray, valid: np.ndarray, weights: SplineWeights = SplineWeights(),
                 icp_rounds: int = 2, edge_margin_px: float = 1.0, what: str = "window",
                 context: tuple[np.ndarray, FrameDetections] | None = None, gain_max: float = 1.0,
                 events: np.ndarray | None = None, silence: SilenceSettings = SilenceSettings(),
                 robust_cor_px: float = 0.0, t_sil_us: np.ndarray | None = None,
                 silhouette: SilhouetteSettings = SilhouetteSettings(),
                 base_gain: np.ndarray | None = None, gain_criterion: str = "reml",
                 context_gate_floor: float = 0.0) -> WindowResult:
    """Solve one window: fits at its detection frames, a smoothing spline through them as the start, then
    ``icp_rounds`` alternations of correspondence search (at the current spline's poses at t_cor_us, with the
    tracks xy (n_cor, H, 2) / valid (n_cor, H)) and IPOPT. StageFailed on a failed solve.

    context: (times, detections) of the intensity frames around the window from which the prior's gain per
    parameter is chosen (:func:`prior_gain`, up to gain_max, by gain_criterion); None: the prior is λ_prior for
    every parameter. With weights.context > 0 the same context also sets the context pull (:func:`prior_gain`),
    times each parameter's stillness by the events at each frame (:func:`still_gate`, never below
    context_gate_floor; ungated without the silence).

    events: the recording's events over the window, for the event-silence term (used when weights.still > 0): each
    joint's stillness per knot interval, measured around the start spline's projected bones (:func:`window_silence`).

    robust_cor_px > 0: from the second ICP round on, each correspondence is weighted by the Cauchy weight
    1 / (1 + (e/σ)²) of its image residual e (px) at the previous round's solution, σ = robust_cor_px (iteratively
    reweighted least squares: a track the others and the detections disagree with pulls less).

    E_sil (weights.sil > 0, with events and the problem's n_sil frames t_sil_us): every ICP round also matches the
    silhouette boundary of the current spline at t_sil_us to its closest events (settings ``silhouette``).

    base_gain: the motion prior's fixed gain per pose parameter (33,) (e.g. the inertia each turns,
    :func:`eventcap.body.segments.inertia_prior_gain`), times the chosen gains of ``context``; None: 1."""
    if not (math.isfinite(robust_cor_px) and robust_cor_px >= 0):
        raise ValueError(f"robust_cor_px: expected a Cauchy scale in pixels >= 0, got {robust_cor_px!r}")
    if int(icp_rounds) != icp_rounds or icp_rounds < 0:
        raise ValueError(f"icp_rounds: expected an integer >= 0, got {icp_rounds!r}")
    seconds = {}
    t0 = time.perf_counter()
    fits, tps, _, n_fits = fit_window(problem, det, weights)
    gain = None
    pull_target, pull_frames = None, None
    if context is not None and (gain_max > 1 or weights.context > 0):
        pg = prior_gain(problem, context[0], context[1], fits, tps, det, weights, gain_max, gain_criterion, t_det_us)
        gain, n_fits = pg.gain, n_fits + pg.fits_computed
        if pg.pull is not None:
            pull_target, pull_frames = pg.pull
    if base_gain is not None:
        gain = np.asarray(base_gain, dtype=np.float64) * (1.0 if gain is None else gain)
    solves = []
    # Start: a penalised spline through the fits (the same prior; fits weighted as ~1 per rad² of error).
    smooth = max(weights.prior, 1e-12) * (1.0 if gain is None else gain)
    C = spline.fit(t_det_us, fits, smooth=smooth, deriv=problem.order)
    C = np.clip(C, problem.lower, problem.upper)
    x = np.concatenate([C.ravel(), tps.ravel()])
    seconds["fit"] = time.perf_counter() - t0
    sil, still_w = None, None
    if weights.still > 0 and events is not None:
        t1 = time.perf_counter()
        sil, still_w = window_silence(problem, spline, C, events, weights.still, silence)
        seconds["silence"] = time.perf_counter() - t1
        if pull_frames is not None:  # a part the events see move is not held to the frames' smoother
            pull_frames = pull_frames * still_gate(sil, t_det_us, context_gate_floor)
    pull = None if pull_frames is None else (pull_target, weights.context * pg.curvature * pull_frames)
    seconds["correspondences"] = seconds["solve"] = 0.0
    corr = Correspondences.empty()
    index, sil_data, n_boundary = None, None, 0
    if weights.sil > 0 and problem.n_sil and events is not None:
        t1 = time.perf_counter()
        t_sil_us = np.asarray(t_sil_us, dtype=np.int64)
        cam = problem.camera
        index = EventIndex(events, cam.width, cam.height, t_sil_us, int(silhouette.window_us),
                           int(silhouette.denoise_us))
        seconds["silhouette"] = time.perf_counter() - t1
    for r in range(int(icp_rounds)):
        t1 = time.perf_counter()
        C = x[:problem.nC].reshape(problem.n_ctrl, _NP)
        Se = spline.evaluate(C, t_cor_us)
        corr = find_correspondences(problem.template, problem.camera, Se, xy, valid, edge_margin_px)
        if index is not None:
            t3 = time.perf_counter()
            sc, n_boundary, _ = find_silhouette_correspondences(problem.template, problem.camera,
                                                                spline.evaluate(C, t_sil_us), index,
                                                                silhouette.weights(weights.sil), int(silhouette.patch_px))
            sil_data = (sc, silhouette)
            seconds["silhouette"] += time.perf_counter() - t3
        cor_w = None
        if robust_cor_px > 0 and r > 0 and corr.n:
            problem.cor.set_correspondences(corr, relative=True)
            e2 = np.sum(problem.cor.residuals_px(Se) ** 2, axis=1)
            cor_w = 1.0 / (1.0 + e2 / float(robust_cor_px) ** 2)
        t2 = time.perf_counter()
        problem.set_window(spline, t_det_us, det, t_cor_us, corr, weights, x, gain, still_w, cor_w, t_sil_us, sil_data,
                           pull)
        x, st = problem.solve(x, f"{what}: spline solve (ICP round {r + 1})")
        solves.append(SolveStats(st.status, st.iterations, st.seconds, corr.n))
        seconds["correspondences"] += t2 - t1
        seconds["solve"] += time.perf_counter() - t2
    if icp_rounds == 0:  # detections and prior only (no events)
        problem.set_window(spline, t_det_us, det, t_cor_us, corr, weights, x, gain, still_w, pull=pull)
        x, st = problem.solve(x, f"{what}: spline solve (no correspondences)")
        solves.append(st)
    c = problem._eval(x, 0)
    energies = {"2d": c["2d"], "3d": c["3d"], "cor": c["cor_w"] / weights.cor if weights.cor else 0.0,
                "prior": c["prior"] / weights.prior if weights.prior else 0.0,
                "still": c["still"] / weights.still if weights.still else 0.0,
                "sil": c["sil_w"] / weights.sil if weights.sil else 0.0,
                "context": c["pull"] / weights.context if weights.context else 0.0, "total": c["value"],
                "n_correspondences": corr.n, "n_silhouette": sil_data[0].n if sil_data else 0,
                "n_boundary": n_boundary}
    C, T = problem._split(x)
    return WindowResult(spline=spline, control=C.copy(), t_prime=T.copy(), fits=fits, energies=energies,
                        solves=tuple(solves), seconds=seconds, fits_computed=n_fits, prior_gain=gain,
                        silence=sil, pull_frames=pull_frames)


def window_silence(problem: SplineProblem, spline: UniformCubicBSpline, C: np.ndarray, events: np.ndarray,
                   weight: float, settings: SilenceSettings = SilenceSettings()) -> tuple[Silence, np.ndarray]:
    """The event-silence term of one window: (the joints' stillness per knot interval, its weights (n_seg, 24) =
    weight · stillness). The bones are projected at each interval's middle from the spline with control points C
    (:mod:`eventcap.energy.silence`)."""
    edges = spline.t0_us + spline.h_us * np.arange(spline.n_seg + 1, dtype=np.int64)
    mids = (edges[:-1] + edges[1:]) // 2
    joints = joint_positions(spline.evaluate(C, mids), problem.template.rest_joints)
    cam = problem.camera
    sil = measure_silence(events, edges, cam.project(joints), cam.height, cam.width, settings.radius_px,
                          settings.rate_hz, hold_bins=settings.hold_bins, sweep_bins=settings.sweep_bins)
    return sil, float(weight) * sil.stillness


__all__ = ["PriorGain", "SplineProblem", "SplineWeights", "WindowResult", "fit_window", "frame_fit", "gains_from_fits",
           "prior_gain", "solve_window", "window_silence"]
