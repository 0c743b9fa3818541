"""Event-based pose refinement (paper Sec. 3.3, Eq. 9-13): silhouette-to-event ICP on every tracking frame.

For each tracking frame f of a batch, starting from the batch solve's pose Ŝ_f (Sec. 3.2):

    E_refine(S_f) = λ_sil Σ_b ρ(n_bᵀ(π(v_b(S_f)) - u_b) / f) + λ_stab Σ_l ‖J_l(S_f) - J_l(Ŝ_f)‖²       (Eq. 9-11)

minimised subject to the joint bounds θ_min <= θ_f <= θ_max (skeleton.pose_bounds, or the config's overrides),
alternating with the correspondence search as in ICP (``icp_iterations``, 4 by default): pose the template with
the current S_f, find its silhouette boundary pixels s_b, their outward normals n_b and surface points v_b
(:mod:`eventcap.energy.boundary`), the closest event u_b of each s_b (Eq. 12-13, :mod:`eventcap.energy.event_search`),
then solve with those fixed. The energy is :class:`eventcap.energy.sil.SilhouetteEnergy` (shared with the spline solve).
Boundary pixels without any event in their patch and window are left out (counted in the diagnostics).

- E_sil (Eq. 11): the point-to-line (2D "point-to-plane") distance of the projected surface point to its event,
  along the boundary normal. ρ is the loss: ``l2`` (ρ(r) = r², the paper) or ``huber`` (r² for |r| <= δ, else
  2δ|r| - δ², δ = ``huber_px``): events from texture inside the body or from the background that happen to be the
  nearest ones then pull linearly instead of quadratically.
- E_stab (Eq. 10): the 24 joints stay close to where the batch solve put them.

Units (as in the batch solve): image residuals are divided by the focal length f = sqrt(fx·fy) in
pixels (focal-normalised image units, ≈ radians; 1 px ≈ 5 mrad for the DAVIS240C), 3D residuals are metres.
With the paper's λ_sil = 1, λ_stab = 5 a boundary pixel off by 1 px costs as much as one joint off by 2.2 mm
(1/f² = 5·d², d = 1 / (f √5) m), and ~280 boundary pixels of a body (240×180 image, 3 m away) moved by 1 px
together cost about as much as all 24 joints moved by 1.5 cm (= 1 px at 3 m): E_stab keeps the refinement a
correction of the batch result, as in the paper, not a re-fit to the events alone.

How it is computed. All frames of a batch are one NLP over the F·33 pose parameters (frames do not interact: the
Hessian is block diagonal; one NLP needs as many IPOPT iterations as the slowest frame, 41 separate ones would pay
IPOPT's and CasADi's overhead 41 times per ICP iteration), built once per process for a template, camera and frame
count (~0.1 s), and solved by IPOPT (exact Hessian, MUMPS, the batch solver's pinned options
:class:`eventcap.energy.ipopt.IpoptSettings` with tol = :data:`TOL`), warm-started from the previous ICP iteration.
The energy is evaluated exactly — value, gradient and Hessian — as in the batch solver's E_cor: per frame, the 24
skinning transforms G(S) (96×3), their Jacobian and the contraction of their second derivatives come from the
solver's CasADi kernels (:class:`eventcap.energy.kernels.SkinningKernels`); each surface point is v = WX·G
(premultiplied weights, kept sparse: a point is weighted to 2-9 of the 24 joints), its Jacobian WX·∂G; the
residuals' derivatives w.r.t. the point (camera model of :meth:`Camera.project`, closed form) and the per-point
products are compiled loops (:mod:`eventcap.energy._sil_kernels`, checked against ``eventcap.energy.kernels.project_derivatives`` and
finite differences in the tests). IPOPT sees the energy through CasADi callbacks plugged in as ``grad_f`` /
``hess_lag``; the correspondences are handed to the energy object per solve, never rebuilt into the NLP. Every
solve's status is checked: anything but success raises :class:`eventcap.stage.StageFailed` with IPOPT's status.

What it achieves (synthetic captures, benchmarks/bench_refine.py). Events pin the silhouette to about a pixel
(1.5 cm at 3 m): the refinement corrects estimates whose silhouettes are off by pixels, and cannot improve ones
that are already better than that — there it adds up to a pixel's worth of noise, which E_stab keeps small.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from eventcap.body.kinematics import joint_positions
from eventcap.body.skeleton import NUM_POSE_PARAMS
from eventcap.body.template import Template
from eventcap.camera import Camera
from eventcap.stage import StageFailed

from eventcap.energy.event_search import DENOISE_US, EventIndex
from eventcap.energy.sil import (
    SilhouetteCorrespondences,
    SilhouetteEnergy,
    SilhouetteWeights,
    find_silhouette_correspondences,
)

_NP = NUM_POSE_PARAMS
#: IPOPT's convergence tolerance for the refinement (scaled NLP error). Measured on synthetic batches: 1e-4 and
#: 1e-6 give the same poses to 0.01 mm, with 3-4 instead of 5-6 iterations per solve.
TOL = 1e-4


def default_settings():
    """The pinned IPOPT options of the refinement: the batch solver's, with tol = :data:`TOL`."""
    from eventcap.energy.ipopt import IpoptSettings

    return IpoptSettings(tol=TOL)


def _block_diagonal_triu(n_blocks: int, size: int):
    """Upper-triangle sparsity of a block-diagonal matrix and the (row, col) within a block of each nonzero, in
    CasADi's column-major order (block by block, column by column)."""
    rr, cc = [], []
    for c in range(size):
        for r in range(c + 1):
            rr.append(r), cc.append(c)
    r_in, c_in = np.array(rr), np.array(cc)
    rows = (np.arange(n_blocks)[:, None] * size + r_in[None, :]).ravel()
    cols = (np.arange(n_blocks)[:, None] * size + c_in[None, :]).ravel()
    sp = ca.Sparsity.triplet(n_blocks * size, n_blocks * size, rows.tolist(), cols.tolist())
    r_chk, c_chk = sp.get_triplet()
    assert np.array_equal(r_chk, rows) and np.array_equal(c_chk, cols), "unexpected CasADi nonzero order"
    return sp, r_in, c_in


# --------------------------------------------------------------------------------------------- the problem
@dataclass(frozen=True)
class SolveStats:
    status: str
    iterations: int
    seconds: float


class RefineProblem:
    """The refinement NLP of one batch (F frames), built once per (template, camera, F, settings, bounds).

    settings: :class:`eventcap.energy.ipopt.IpoptSettings` (pinned IPOPT options; warm-started solves).
    lower/upper: bounds of the 33 pose parameters (default :func:`skeleton.pose_bounds`).
    """

    def __init__(self, template: Template, camera: Camera, frames: int, settings=None,
                 lower: np.ndarray | None = None, upper: np.ndarray | None = None, kernels=None):
        from eventcap.energy.ipopt import NumpyCallback, checked_bounds
        from eventcap.energy.kernels import SkinningKernels

        if not isinstance(template, Template):
            raise ValueError(f"RefineProblem: expected a Template, got {type(template).__name__}")
        if not isinstance(camera, Camera):
            raise ValueError(f"RefineProblem: expected a Camera, got {type(camera).__name__}")
        if isinstance(frames, bool) or int(frames) != frames or frames < 1:
            raise ValueError(f"RefineProblem: frames (tracking frames per batch) must be an integer >= 1, "
                             f"got {frames!r}")
        t0 = time.perf_counter()
        self.template, self.camera, self.F = template, camera, int(frames)
        self.settings = settings if settings is not None else default_settings()
        self.lower, self.upper = checked_bounds(lower, upper, "RefineProblem")
        self.kernels = kernels if kernels is not None else SkinningKernels(template.rest_joints, self.F)
        if self.kernels.F != self.F:
            raise ValueError(f"RefineProblem: kernels for {self.kernels.F} frames, problem for {self.F}")
        self.energy = ne = SilhouetteEnergy(camera, self.kernels, template.rest_joints)
        nx = _NP * self.F
        sp_h, r_in, c_in = _block_diagonal_triu(self.F, _NP)

        def grad(v):
            value, g = ne.gradient(v)
            return [value, g.ravel()]

        def hess(v):
            return [ne.hessian(v)[:, r_in, c_in].ravel()]

        self._callbacks = [
            NumpyCallback("E_refine", nx, [ca.Sparsity.dense(1, 1)], lambda v: [ne.value(v)]),
            NumpyCallback("E_refine_grad", nx, [ca.Sparsity.dense(1, 1), ca.Sparsity.dense(nx, 1)], grad),
            NumpyCallback("E_refine_hess", nx, [sp_h], hess),
        ]
        cb_f, cb_g, cb_h = self._callbacks
        X, P = ca.MX.sym("x", nx), ca.MX.sym("p", 0)
        lam_f, lam_g = ca.MX.sym("lam_f"), ca.MX.sym("lam_g", 0)
        f_mx = cb_f(X)
        val, g = cb_g(X)
        grad_f = ca.Function("grad_f", [X, P], [val, g], ["x", "p"], ["f", "grad_f_x"])
        hess_lag = ca.Function("hess_lag", [X, P, lam_f, lam_g], [lam_f * cb_h(X)],
                               ["x", "p", "lam_f", "lam_g"], ["hess_gamma_x_x"])
        #: Objective, gradient and (upper-triangular) Hessian exactly as IPOPT sees them (for derivative checks).
        self.objective = ca.Function("objective", [X], [f_mx])
        self.gradient = ca.Function("gradient", [X], [val, g])  # (value, gradient): the callback fills both
        self.hessian = ca.Function("hessian", [X], [cb_h(X)])
        opts = dict(self.settings.options(True), grad_f=grad_f, hess_lag=hess_lag)
        self._solver = ca.nlpsol("refine", "ipopt", {"x": X, "p": P, "f": f_mx}, opts)
        self.build_seconds = time.perf_counter() - t0

    def set_data(self, corr: SilhouetteCorrespondences, ref_joints: np.ndarray, weights: SilhouetteWeights) -> None:
        self.energy.set_data(corr, ref_joints, weights)

    def solve(self, start: np.ndarray, what: str = "refinement") -> tuple[np.ndarray, SolveStats]:
        """Minimise E_refine (data: :meth:`set_data`) from ``start`` (F, 33), within the bounds."""
        from eventcap.energy.ipopt import SUCCESS_STATUSES

        start = np.asarray(start, dtype=np.float64)
        if start.shape != (self.F, _NP):
            raise ValueError(f"solve: expected a start of shape ({self.F}, 33), got {start.shape}")
        x0 = np.clip(start, self.lower, self.upper).ravel()
        t0 = time.perf_counter()
        try:
            res = self._solver(x0=x0, lbx=np.tile(self.lower, self.F), ubx=np.tile(self.upper, self.F))
        except RuntimeError as exc:  # CasADi refuses ill-posed input before IPOPT runs
            raise StageFailed(f"{what}: the solver refused the problem: {exc}", status="Invalid_Problem_Definition",
                              details={"error": str(exc)}) from exc
        st = self._solver.stats()
        stats = SolveStats(status=str(st.get("return_status", "unknown")), iterations=int(st.get("iter_count", 0)),
                           seconds=time.perf_counter() - t0)
        if stats.status not in SUCCESS_STATUSES:
            raise StageFailed(f"{what}: IPOPT did not converge (status {stats.status} after {stats.iterations} "
                              f"iterations)", status=stats.status, details={"iterations": stats.iterations})
        x = np.asarray(res["x"], dtype=np.float64).reshape(self.F, _NP)
        if not np.all(np.isfinite(x)):
            raise StageFailed(f"{what}: IPOPT returned non-finite poses (status {stats.status})", status="non_finite")
        return x, stats


# --------------------------------------------------------------------------------------------- a batch
@dataclass(frozen=True)
class IcpStats:
    """One ICP iteration: correspondence search and solve."""

    boundary: int  #: boundary pixels (with a normal) over all frames
    matched: int  #: of which have an event in their patch and window
    status: str
    iterations: int
    seconds: dict  #: wall time: boundary (render + samples), search, solve


@dataclass(frozen=True)
class RefineResult:
    poses: np.ndarray  #: (F, 33) refined S_0..S_N
    status: str  #: status of the last solve
    iterations: int  #: IPOPT iterations, all solves
    energies: dict  #: E_sil, E_stab (unweighted, last correspondences) and the weighted total, at the start and end
    icp: tuple[IcpStats, ...] = ()
    seconds: dict = field(default_factory=dict)  #: wall time per phase, summed over the ICP iterations
    events: int = 0  #: events in the span of the batch's windows
    events_dropped: int = 0  #: of which were dropped as unsupported noise (denoise_us)


def refine_batch(problem: RefineProblem, t_us: np.ndarray, poses: np.ndarray, events: np.ndarray,
                 weights: SilhouetteWeights = SilhouetteWeights(), icp_iterations: int = 4, patch_px: int = 8,
                 window_us: int | None = None, denoise_us: int = DENOISE_US) -> RefineResult:
    """Refine the poses (F, 33) of one batch at tracking frame times t_us (F,) against the recording's events.

    window_us: T of Eq. 12-13 (default t_N - t_0, the batch duration). denoise_us: events without another event in
    their 3×3 pixel neighbourhood within ±denoise_us are not searched (0: all are, the paper; see :mod:`.search`).
    Raises StageFailed on unusable input or an unsuccessful IPOPT solve.
    """
    t_us = np.asarray(t_us)
    poses = np.asarray(poses, dtype=np.float64)
    F = problem.F
    if t_us.shape != (F,) or not np.issubdtype(t_us.dtype, np.integer):
        raise StageFailed(f"refine input: expected {F} integer tracking frame times (µs), got {t_us.dtype} "
                          f"{t_us.shape}", status="invalid_input")
    if F > 1 and np.any(np.diff(t_us) <= 0):
        raise StageFailed("refine input: tracking frame times must increase", status="invalid_input")
    if poses.shape != (F, _NP):
        raise StageFailed(f"refine input: expected poses of shape ({F}, 33), got {poses.shape}",
                          status="invalid_input")
    if not np.all(np.isfinite(poses)):
        f = int(np.flatnonzero(~np.all(np.isfinite(poses), axis=1))[0])
        raise StageFailed(f"refine input: the pose of tracking frame {f} is not finite", status="invalid_input")
    if isinstance(icp_iterations, bool) or int(icp_iterations) != icp_iterations or icp_iterations < 1:
        raise ValueError(f"icp_iterations: expected an integer >= 1, got {icp_iterations!r}")
    T = int(t_us[-1] - t_us[0]) if window_us is None else int(window_us)
    t_start = time.perf_counter()
    try:
        index = EventIndex(events, problem.camera.width, problem.camera.height, t_us, T, denoise_us)
    except ValueError as exc:
        raise StageFailed(f"refine input: {exc}", status="invalid_input") from exc
    seconds = {"index": time.perf_counter() - t_start, "boundary": 0.0, "search": 0.0, "solve": 0.0}
    ref = joint_positions(poses, problem.template.rest_joints)  # J_l(Ŝ_f) of E_stab
    S = np.clip(poses, problem.lower, problem.upper)
    icp: list[IcpStats] = []
    before = None
    corr = SilhouetteCorrespondences.empty()
    for it in range(int(icp_iterations)):
        corr, n_boundary, secs = find_silhouette_correspondences(problem.template, problem.camera, S, index, weights, patch_px)
        problem.set_data(corr, ref, weights)
        if before is None:
            before = _energies(problem, S, weights)
        S, st = problem.solve(S, f"refinement, ICP iteration {it + 1}")
        secs["solve"] = st.seconds
        for k, v in secs.items():
            seconds[k] += v
        icp.append(IcpStats(boundary=n_boundary, matched=corr.n, status=st.status, iterations=st.iterations,
                            seconds=secs))
    after = _energies(problem, S, weights)
    energies = {**{f"{k}_start": v for k, v in before.items()}, **after}
    return RefineResult(poses=S, status=icp[-1].status, iterations=sum(s.iterations for s in icp), energies=energies,
                        icp=tuple(icp), seconds=seconds, events=index.n_events, events_dropped=index.n_unsupported)


def _energies(problem: RefineProblem, S: np.ndarray, weights: SilhouetteWeights) -> dict:
    t = problem.energy.terms(S)
    sil, stab = float(t["sil"].sum()), float(t["stab"].sum())
    return {"sil": sil, "stab": stab, "total": weights.sil * sil + weights.stab * stab}


__all__ = ["RefineProblem", "RefineResult", "refine_batch"]
