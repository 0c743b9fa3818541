"""The factor interface (eventcap/energy/factor.py, problem.py): every registered term's value, gradient and Hessian
against finite differences, in both parametrisations of the poses (a spline's control points and one pose per
frame), the declared block-banded sparsity, and a new term added as one class and one config entry."""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import pytest

from eventcap.body.skeleton import NUM_JOINTS, NUM_POSE_PARAMS, pose_bounds
from eventcap.energy.correspondences import find_correspondences
from eventcap.energy.errors import EnergyError
from eventcap.energy.event_search import EventIndex
from eventcap.energy.factor import FACTORS, Factor, Layout, Linearization, Window
from eventcap.energy.terms import factors_from_config
from eventcap.energy.ipopt import IpoptSettings
from eventcap.energy.problem import FactorProblem, FramePoses, SplinePoses, coupling_band
from eventcap.energy.sil import find_silhouette_correspondences
from eventcap.energy.spline import UniformCubicBSpline
from eventcap.energy.terms import ORDER
from eventcap_refine.spec import SilhouetteRefineConfig
from eventcap_solve.spec import BatchSolveConfig
from eventcap_spline.spec import SplineSolveConfig
from helpers.derivatives import assert_derivatives_match_fd
from helpers.spline_scene import H_US, T_SIL, scene, silhouette_events

SETTINGS = IpoptSettings(max_iter=100, tol=1e-6, mumps_pivot_order=0)
LAMBDAS = tuple(f"lambda_{n}" for n in ORDER)


def only(config_cls, term: str, **changes):
    """The stage config with every term's weight 0 but ``term``'s (1), no proximal term, and the changes."""
    names = {f.name for f in dataclasses.fields(config_cls)}
    zero = {n: 0.0 for n in LAMBDAS if n in names}
    damp = {"lambda_damp": 0.0} if "lambda_damp" in names else {}
    return config_cls(**{**zero, **damp, f"lambda_{term}": 1.0, **changes})


@functools.lru_cache(maxsize=1)
def window_data():
    """The spline test scene's window with every term's data: detections, correspondences of exact tracks, the
    silhouette at 9 frames against exact boundary events, stillness, a gain per parameter, a context pull."""
    rec, det, t_det, t_us, S, xy, valid = scene()
    n_seg = int((t_det[-1] - t_det[0]) // H_US)
    spl = UniformCubicBSpline(int(t_det[0]), H_US, n_seg)
    rng = np.random.default_rng(0)
    lo, hi = pose_bounds()
    gt = rec.ground_truth
    tk = np.linspace(t_det[0], t_det[-1], 25).astype(np.int64) // 1000 * 1000
    C = np.clip(spl.fit(tk, gt.poses[np.searchsorted(gt.t_us, tk)], smooth=1e-6) + rng.normal(0, 0.03, (
        n_seg + 3, 33)), lo + 1e-3, hi - 1e-3)
    corr = find_correspondences(rec.template, rec.camera, spl.evaluate(C, t_us), xy, valid)
    t_sil = t_us[T_SIL]
    index = EventIndex(silhouette_events(), rec.camera.width, rec.camera.height, t_sil, 10_000, 0)
    sc = find_silhouette_correspondences(rec.template, rec.camera, spl.evaluate(C, t_sil), index, 4.0, 8)[0]
    assert corr.n > 500 and sc.n > 1000
    r2 = np.random.default_rng(1)
    window = Window(spl.t0_us, spl.t1_us, t_det_us=t_det, detections=det, t_cor_us=t_us, correspondences=corr,
                    phi=(rng.random((t_us.size - 1, NUM_JOINTS)) < 0.5).astype(float), t_sil_us=t_sil, silhouette=sc,
                    ref_joints=rng.normal(0, 0.3, (t_sil.size, NUM_JOINTS, 3)) + np.array([0, 1.0, 0]),
                    knots_us=spl.t0_us + H_US * np.arange(n_seg + 1, dtype=np.int64),
                    stillness=rng.uniform(0, 2, (n_seg, 24)) * (rng.random((n_seg, 24)) < 0.5),
                    estimate=lambda t: spl.evaluate(C, t), prior_gain=rng.uniform(1.0, 50.0, 33),
                    pull=(spl.evaluate(C, t_det) + r2.normal(0, 0.05, (t_det.size, 33)),
                          r2.uniform(0, 3, (t_det.size, 33)) * (r2.random((t_det.size, 33)) < 0.67)))
    # the floor a centimetre above the start's median lowest sole point: some points in contact, some below it
    from eventcap.energy.floor import sole_points

    window.floor_y = float(np.median(sole_points(spl.evaluate(C, window.knots_us), rec.template)[..., 1].min(1))) + 0.01
    layout = Layout(n_seg=n_seg, n_det=t_det.size, n_cor=t_us.size, n_sil=t_sil.size)
    return rec, spl, C, window, layout


SPLINE_TERMS = ["2d", "3d", "cor", "sil", "still", "prior", "context", "damp", "temp", "stab", "floor", "slide",
                "bones"]


@pytest.mark.parametrize("term", SPLINE_TERMS)
def test_every_factor_on_a_spline_matches_finite_differences(term):
    """Each term alone (λ = 1) over a spline's control points: the problem's gradient and its Hessian (in the
    declared sparsity, exactly as IPOPT sees them) against central differences of its value."""
    rec, spl, C, window, layout = window_data()
    changes = {"sil_loss": "l2"} if term == "sil" else {}  # the Huber loss: on frames, with its kink in a gap
    if term in ("floor", "slide"):  # the scene's feet move: contact wherever they are slower than 3 m/s (and no
        # random stillness, which leaves no two neighbouring knots in contact)
        changes = {"contact_speed_mps": 3.0, "contact_height_m": 0.2}
        window = dataclasses.replace(window, stillness=None)
    if term == "damp":
        config = dataclasses.replace(only(SplineSolveConfig, "prior"), lambda_prior=0.0, lambda_damp=1.0)
    elif term in ("temp", "stab"):  # terms of other solves work on a spline too
        config = only(BatchSolveConfig if term == "temp" else SilhouetteRefineConfig, term)
    else:
        config = only(SplineSolveConfig, term, **changes)
    factors = factors_from_config(config, rec.template, rec.camera, layout)
    assert [f.name for f in factors] == ([] if term == "damp" else [term])
    prob = FactorProblem(SplinePoses(spl.n_seg), factors, SETTINGS, damp=1.0 if term == "damp" else 0.0,
                         band=coupling_band(SplinePoses(spl.n_seg, spl), window.t_cor_us))
    rng = np.random.default_rng(2)
    x = np.concatenate([C.ravel(), rng.normal(0, 0.05, prob.nA)])
    prob.set_window(spl, window, x + rng.normal(0, 0.01, x.shape))
    _check(prob, x, term, [0, 4, 6, prob.n_units - 1], rng)


@pytest.mark.parametrize("term,loss", [("2d", None), ("3d", None), ("cor", None), ("cor_frozen", None),
                                       ("temp", None), ("damp", None), ("sil", "l2"), ("sil", "huber"),
                                       ("stab", None), ("2d_robust", None)])
def test_every_factor_on_frames_matches_finite_differences(term, loss):
    """Each term alone over one pose per frame (the paper's batch solve and the refinement): the same check, with
    E_cor both coupled and with its source side frozen (w/o_batch), E_2D least-squares and Cauchy-robust."""
    rec, spl, C, window, _ = window_data()
    t_us = window.t_cor_us
    name = term.split("_")[0]
    if name in ("sil", "stab"):
        config = only(SilhouetteRefineConfig, name, **({"sil_loss": loss} if loss else {}))
    elif term == "damp":
        config = dataclasses.replace(only(BatchSolveConfig, "2d"), lambda_2d=0.0, lambda_damp=1.0)
    else:
        config = only(BatchSolveConfig, name, robust_2d_px=2.0 if term == "2d_robust" else 0.0)
    sil_frames = np.isin(t_us, window.t_sil_us)
    # detection frames must be frames of this problem: the first and last of the window's tracking frames
    layout = Layout(n_frames=t_us.size, n_det=2, n_cor=t_us.size, n_sil=int(sil_frames.sum()))
    w = dataclasses.replace(window, t_det_us=t_us[[0, -1]], detections=window.detections.rows([1, 2]),
                            cor_relative=term != "cor_frozen")
    rng = np.random.default_rng(3)
    poses = spl.evaluate(C, t_us)
    if loss == "huber":  # δ in the widest gap between residuals: none crosses the kink within the steps
        probe = factors_from_config(only(SilhouetteRefineConfig, "sil"), rec.template, rec.camera, layout)[0]
        probe.prepare(w)
        r = np.sort(np.abs(probe.residuals(probe._points(probe.kernels.transforms(poses[sil_frames])))[0]))
        mid = r[r.size // 4: 3 * r.size // 4]
        k = int(np.argmax(np.diff(mid)))
        assert mid[k + 1] - mid[k] > 1e-6
        config = dataclasses.replace(config, sil_huber_px=0.5 * (mid[k] + mid[k + 1]) * probe.scale ** -1)
    prob = FactorProblem(FramePoses(t_us.size), factors_from_config(config, rec.template, rec.camera, layout),
                         SETTINGS, damp=1.0 if term == "damp" else 0.0, damp_aux=False)
    x = np.concatenate([poses.ravel(), rng.normal(0, 0.05, prob.nA)])
    prob.set_window(t_us, w, x + rng.normal(0, 0.01, x.shape))
    frames = [int(np.flatnonzero(sil_frames)[1]), 0, t_us.size // 2, t_us.size - 1]
    _check(prob, x, term, frames, rng)


def _check(prob: FactorProblem, x, label, units, rng):
    import casadi as ca

    f = lambda v: float(prob.objective(v))
    grad = lambda v: np.asarray(prob.gradient(v)[1]).ravel()
    g = grad(x)
    Hu = np.asarray(ca.DM(prob.hessian(x)).full())
    H = np.triu(Hu) + np.triu(Hu, 1).T
    assert f(x) > 0 and np.abs(g).max() > 0, label
    coords = np.concatenate([rng.choice(NUM_POSE_PARAMS, 5, replace=False) + NUM_POSE_PARAMS * u for u in units]
                            + [prob.nU + np.arange(min(prob.nA, 6))])
    assert_derivatives_match_fd(f, grad, x, g, H, coords, 1e-4, label)
    # Nothing outside the declared sparsity: the dense Hessian of every block equals what IPOPT gets.
    full = prob.dense_hessian(x)
    assert np.abs(full - H).max() <= 1e-12 * max(1.0, np.abs(full).max()), label


def test_a_coupling_across_a_knot_widens_the_band_and_a_narrower_problem_refuses_it():
    """Coupled samples (E_cor) a knot interval apart touch control points 4 apart: the band of such a window is 4,
    3 when every coupled pair has its later sample on a knot (the fourth basis function is exactly 0 there); a
    problem built for 3 refuses a window that needs 4, naming the factor."""
    rec, spl, C, window, layout = window_data()
    poses = SplinePoses(spl.n_seg, spl)
    on_grid = window.t_cor_us  # 1 ms steps from a knot: a pair straddling a knot ends on it
    assert coupling_band(poses, on_grid) == 3
    off = on_grid[::5] + 2_500  # 5 ms steps, 2.5 ms past the knots: pairs straddle them
    assert coupling_band(poses, off) == 4
    factors = factors_from_config(only(SplineSolveConfig, "cor"), rec.template, rec.camera,
                                  dataclasses.replace(layout, n_cor=off.size))
    prob = FactorProblem(poses, factors, SETTINGS, band=3)
    w = dataclasses.replace(window, t_cor_us=off, correspondences=window.correspondences.__class__.empty())
    with pytest.raises(EnergyError, match="factor cor couples samples 4 units apart; the problem was built for 3"):
        prob.set_window(spl, w, np.zeros(prob.nx))


# ------------------------------------------------------------------------------------------------ a new term
class ToyHold(Factor):
    """λ_toy Σ_d ‖S(t_d) - S_toy‖² at the detection frames: a new term, written as one class."""

    name = "toy"
    settings = ("toy_target",)

    def __init__(self, weight, config, template, camera, layout):
        super().__init__(weight, config, template, camera, layout)
        self.target = np.full(NUM_POSE_PARAMS, float(config.toy_target))

    @staticmethod
    def size(layout):
        return layout.n_det

    def prepare(self, window):
        self.t_us = np.asarray(window.need("t_det_us", "E_toy"), dtype=np.int64)

    def linearize(self, S, aux, order):
        R = S - self.target
        lin = Linearization(self.weight * float(np.sum(R * R)))
        if order >= 1:
            lin.grad = 2.0 * self.weight * R
        if order >= 2:
            lin.diag = np.broadcast_to(2.0 * self.weight * np.eye(NUM_POSE_PARAMS), (self.n, 33, 33)).copy()
        return lin


@dataclasses.dataclass
class ToyConfig(SplineSolveConfig):
    """The one config entry (and the setting the class reads)."""

    lambda_toy: float = 0.0
    toy_target: float = 0.0


def test_a_new_term_is_one_class_and_one_config_entry():
    """ToyHold registers itself by its name; a config with lambda_toy > 0 makes the spline solve use it (its
    energy reported, its pull visible in the solution) without a change anywhere else; weight 0 leaves it out."""
    from eventcap_spline.solve import SplineSolver, solve_window

    assert FACTORS["toy"] is ToyHold
    rec, det, t_det, t_us, S, xy, valid = scene(exact=True)
    n_seg = int((t_det[-1] - t_det[0]) // H_US)
    spl = UniformCubicBSpline(int(t_det[0]), H_US, n_seg)
    layout = Layout(n_seg=n_seg, n_det=t_det.size, n_cor=t_us.size)
    res = {}
    for lam in (0.0, 1e3):
        cfg = ToyConfig(lambda_toy=lam, toy_target=0.0, icp_rounds=1, lambda_sil=0.0, lambda_still=0.0,
                        lambda_context=0.0)
        solver = SplineSolver(rec.template, rec.camera, layout, cfg)
        assert ("toy" in [f.name for f in solver.factors]) == (lam > 0)
        res[lam] = solve_window(solver, spl, t_det, det, t_us, xy, valid)
        assert res[lam].solves[-1].status == "Solve_Succeeded"
    held = np.abs(spl.evaluate(res[1e3].control, t_det)[:, :27]).mean()
    free = np.abs(spl.evaluate(res[0.0].control, t_det)[:, :27]).mean()
    assert held < 0.2 * free, (held, free)


def test_a_factor_name_is_taken_once_and_bad_weights_are_named():
    with pytest.raises(TypeError, match="factor name '2d' of .* is already"):
        type("Other2D", (Factor,), {"name": "2d", "size": staticmethod(lambda layout: 1),
                                    "prepare": lambda self, w: None, "linearize": lambda self, S, a, o: None})
    rec, spl, C, window, layout = window_data()
    with pytest.raises(EnergyError, match=r"lambda_prior: expected a finite weight >= 0, got nan"):
        factors_from_config(SplineSolveConfig(lambda_prior=float("nan")), rec.template, rec.camera, layout)
    with pytest.raises(EnergyError, match="E_2D: the window has no detections"):
        f = factors_from_config(only(SplineSolveConfig, "2d"), rec.template, rec.camera, layout)[0]
        f.prepare(Window(0, 1))
