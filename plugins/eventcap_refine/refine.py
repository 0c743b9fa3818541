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
IPOPT's and CasADi's overhead 41 times per ICP iteration): the factors E_sil and E_stab of :mod:`eventcap.energy`
(:class:`eventcap.energy.sil.SilhouetteToEvents`, :class:`eventcap.energy.sil.JointStability`, shared with the
spline solve) summed over one pose per frame by :class:`eventcap.energy.problem.FactorProblem`, built once per
process for a template, camera, frame count and config, and solved by IPOPT (exact Hessian, MUMPS, pinned options),
warm-started from the previous ICP iteration. The energy is evaluated exactly — value, gradient and Hessian: per
frame, the 24 skinning transforms G(S) (96×3), their Jacobian and the contraction of their second derivatives come
from CasADi kernels (:class:`eventcap.energy.kernels.SkinningKernels`); each surface point is v = WX·G
(premultiplied weights, kept sparse: a point is weighted to 2-9 of the 24 joints), its Jacobian WX·∂G; the
residuals' derivatives w.r.t. the point (camera model of :meth:`Camera.project`, closed form) and the per-point
products are compiled loops (:mod:`eventcap.energy._sil_kernels`, checked against
``eventcap.energy.kernels.project_derivatives`` and finite differences in the tests). The correspondences are
handed to the factors per solve, never rebuilt into the NLP. Every solve's status is checked: anything but success
raises :class:`eventcap.energy.errors.SolveFailed` with IPOPT's status.

What it achieves (synthetic captures, benchmarks/accuracy/bench_refine.py). Events pin the silhouette to about a pixel
(1.5 cm at 3 m): the refinement corrects estimates whose silhouettes are off by pixels, and cannot improve ones
that are already better than that — there it adds up to a pixel's worth of noise, which E_stab keeps small.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from eventcap.body.kinematics import joint_positions
from eventcap.body.skeleton import NUM_POSE_PARAMS
from eventcap.body.template import Template
from eventcap.camera import Camera
from eventcap.energy.errors import EnergyError
from eventcap.energy.ipopt import IpoptSettings, SolveStats, bounds_with
from eventcap.energy.problem import FactorProblem, FramePoses
from eventcap.energy.terms import factors_from_config, sample_times
from eventcap.energy.window import Estimate, WindowInputs

_NP = NUM_POSE_PARAMS


# --------------------------------------------------------------------------------------------- the problem
def _frames(t_us: np.ndarray, poses: np.ndarray):
    """The poses (F, 33) at their frames t_us as a function of times (which must be frames)."""
    rows = {int(t): i for i, t in enumerate(np.asarray(t_us, dtype=np.int64))}
    P = np.array(poses, dtype=np.float64)
    return lambda t, deriv=0: P[[rows[int(v)] for v in np.asarray(t).ravel()]]


def refine_window(t_us, events, poses, template: Template, span_us: tuple[int, int] | None = None) -> WindowInputs:
    """A batch's inputs for the refinement's factors: one pose per tracking frame t_us (F,), the events, the
    reference joints of the poses to refine (F, 33); span_us: the window of Eq. 12-13 (default t_0..t_N)."""
    t_us = np.asarray(t_us, dtype=np.int64)
    t0, t1 = (int(t_us[0]), int(t_us[-1])) if span_us is None else span_us
    ref = None if poses is None else joint_positions(np.asarray(poses, dtype=np.float64), template.rest_joints)
    return WindowInputs(t0, t1, frames_us=t_us, track_times_us=(t_us,), events=events, reference_us=t_us,
                        reference_joints=ref)


class RefineProblem:
    """The refinement NLP of one batch (F frames), built once per (template, camera, F, config). ``config``: the
    stage's config (plugins/eventcap_refine/spec.py, SilhouetteRefineConfig), the one source of every setting."""

    def __init__(self, template: Template, camera: Camera, frames: int, config, t_us: np.ndarray | None = None):
        """t_us: the batches' tracking times the problem is sized for (each term's samples among them); default a
        1 kHz grid of ``frames`` frames."""
        if not isinstance(template, Template):
            raise EnergyError(f"RefineProblem: expected a Template, got {type(template).__name__}")
        if not isinstance(camera, Camera):
            raise EnergyError(f"RefineProblem: expected a Camera, got {type(camera).__name__}")
        if isinstance(frames, bool) or int(frames) != frames or frames < 1:
            raise EnergyError(f"RefineProblem: frames (tracking frames per batch) must be an integer >= 1, "
                              f"got {frames!r}")
        t0 = time.perf_counter()
        self.template, self.camera, self.F, self.config = template, camera, int(frames), config
        lo, hi = bounds_with(config.limits, "stages.refine.limits")
        settings = IpoptSettings.from_config(config.ipopt)
        t_us = np.arange(self.F, dtype=np.int64) * 1000 if t_us is None else np.asarray(t_us, dtype=np.int64)
        if t_us.shape != (self.F,):
            raise EnergyError(f"RefineProblem: expected {self.F} tracking times, got {t_us.shape}")
        shape = refine_window(t_us, None, None, template)
        sizes = {k: t.size for k, t in sample_times(config.terms, shape).items()}
        factors = factors_from_config(config.terms, template, camera, sizes)
        self.problem = FactorProblem(FramePoses(self.F), factors, settings, lo, hi, damp=0.0, name="refine")
        self.lower, self.upper = self.problem.lower, self.problem.upper
        self.build_seconds = time.perf_counter() - t0

    @property
    def factors(self):
        return self.problem.factors

    def solve(self, start: np.ndarray, what: str = "refinement") -> tuple[np.ndarray, SolveStats]:
        """Minimise E_refine (the factors' current data) from ``start`` (F, 33), within the bounds."""
        start = np.asarray(start, dtype=np.float64)
        if start.shape != (self.F, _NP):
            raise EnergyError(f"solve: expected a start of shape ({self.F}, 33), got {start.shape}")
        x, stats = self.problem.solve(np.clip(start, self.lower, self.upper).ravel(), what)
        return x.reshape(self.F, _NP), stats

    def terms(self, S: np.ndarray) -> dict:
        """Each term's unweighted value at the poses S (F, 33) (the factors' current data), and the weighted total."""
        x = np.asarray(S, dtype=np.float64).ravel()
        t = self.problem.terms(x)
        return {**t, "total": float(sum(f.weight * t[f.name] for f in self.problem.factors))}


# --------------------------------------------------------------------------------------------- a batch
@dataclass(frozen=True)
class IcpStats:
    """One ICP iteration: association and solve."""

    boundary: int  #: boundary pixels (with a normal) over all frames
    matched: int  #: of which have an event in their patch and window
    status: str
    iterations: int
    seconds: dict  #: wall time: relinearize (render, samples, search), solve


@dataclass(frozen=True)
class RefineResult:
    poses: np.ndarray  #: (F, 33) refined S_0..S_N
    status: str  #: status of the last solve
    iterations: int  #: IPOPT iterations, all solves
    energies: dict  #: each term (unweighted, last association) and the weighted total, at the start and end
    icp: tuple[IcpStats, ...] = ()
    seconds: dict = field(default_factory=dict)  #: wall time per phase, summed over the ICP iterations
    events: int = 0  #: events in the span of the batch's windows
    events_dropped: int = 0  #: of which were dropped as unsupported noise (denoise_us)


def refine_batch(problem: RefineProblem, t_us: np.ndarray, poses: np.ndarray, events: np.ndarray,
                 window_us: int | None = None) -> RefineResult:
    """Refine the poses (F, 33) of one batch at tracking frame times t_us (F,) against the recording's events, with
    the problem's config (icp_iterations; the terms' settings: E_sil's search patch, λ_dist and noise filter).

    window_us: T of Eq. 12-13 (default t_N - t_0, the batch duration). Raises EnergyError on unusable input,
    SolveFailed on an unsuccessful IPOPT solve.
    """
    c = problem.config
    t_us, poses = _checked(problem, t_us, poses)
    t_start = time.perf_counter()
    span = None if window_us is None else (int(t_us[0]), int(t_us[0]) + int(window_us))
    inputs = refine_window(t_us, events, poses, problem.template, span)
    for f in problem.factors:
        f.collect(inputs)
    problem.problem.set_window(t_us)
    seconds = {"index": time.perf_counter() - t_start, "relinearize": 0.0, "solve": 0.0}
    S = np.clip(poses, problem.lower, problem.upper)
    icp: list[IcpStats] = []
    before = None
    for it in range(int(c.icp_iterations)):
        t1 = time.perf_counter()
        est = Estimate(_frames(t_us, S), it, inputs, problem.template, problem.camera)
        for f in problem.factors:
            f.relinearize(est)
        problem.problem.set_reference(S.ravel())
        counts = _counts(problem)
        secs = {"relinearize": time.perf_counter() - t1}
        if before is None:
            before = problem.terms(S)
        S, st = problem.solve(S, f"refinement, ICP iteration {it + 1}")
        secs["solve"] = st.seconds
        for k, v in secs.items():
            seconds[k] += v
        icp.append(IcpStats(boundary=counts.get("n_boundary", 0), matched=counts.get("n_silhouette", 0),
                            status=st.status, iterations=st.iterations, seconds=secs))
    energies = {**{f"{k}_start": v for k, v in before.items()}, **problem.terms(S)}
    counts = _counts(problem)
    return RefineResult(poses=S, status=icp[-1].status, iterations=sum(s.iterations for s in icp), energies=energies,
                        icp=tuple(icp), seconds=seconds, events=int(counts.get("events_searched", 0)),
                        events_dropped=int(counts.get("events_dropped", 0)))


def _counts(problem: RefineProblem) -> dict:
    out: dict = {}
    for f in problem.factors:
        out.update(f.report())
    return out


def _checked(problem: RefineProblem, t_us, poses) -> tuple[np.ndarray, np.ndarray]:
    t_us = np.asarray(t_us)
    poses = np.asarray(poses, dtype=np.float64)
    F = problem.F
    if t_us.shape != (F,) or not np.issubdtype(t_us.dtype, np.integer):
        raise EnergyError(f"refine input: expected {F} integer tracking frame times (µs), got {t_us.dtype} "
                          f"{t_us.shape}")
    if F > 1 and np.any(np.diff(t_us) <= 0):
        raise EnergyError("refine input: tracking frame times must increase")
    if poses.shape != (F, _NP):
        raise EnergyError(f"refine input: expected poses of shape ({F}, 33), got {poses.shape}")
    if not np.all(np.isfinite(poses)):
        f = int(np.flatnonzero(~np.all(np.isfinite(poses), axis=1))[0])
        raise EnergyError(f"refine input: the pose of tracking frame {f} is not finite")
    return t_us, poses


__all__ = ["RefineProblem", "RefineResult", "refine_batch"]
