"""The factor interface (eventcap/energy/factor.py, window.py, problem.py): every registered term's value, gradient
and Hessian against finite differences, in both parametrisations of the poses (a spline's control points and one
pose per frame), the declared block-banded sparsity; a factor owns its data (it collects it from the window's
inputs and relinearises at the estimate); the solves never name a term; a new term is one module and one config
entry."""

from __future__ import annotations

import ast
import dataclasses
import functools
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from eventcap.body.skeleton import NUM_JOINTS, NUM_POSE_PARAMS, pose_bounds
from eventcap.core.stage import group, param
from eventcap.energy.errors import EnergyError
from eventcap.energy.factor import FACTORS, Factor, FactorConfig, Linearization, NoiseConfig
from eventcap.energy.floor import sole_points
from eventcap.energy.ipopt import IpoptSettings
from eventcap.energy.prior import ContextSmoothing
from eventcap.energy.problem import FactorProblem, FramePoses, SplinePoses, coupling_band
from eventcap.energy.spline import UniformCubicBSpline
from eventcap.energy.terms import factors_from_config, sample_times, term_configs
from eventcap.energy.window import Estimate, Tracks, WindowInputs
from eventcap_refine.spec import RefineTerms
from eventcap_solve.spec import BatchTerms
from eventcap_spline.spec import SplineSolveConfig, SplineTerms
from helpers.derivatives import assert_derivatives_match_fd
from helpers.spline_scene import H_US, scene, scene_inputs, silhouette_events

ROOT = Path(__file__).resolve().parents[1]
SETTINGS = IpoptSettings(max_iter=100, tol=1e-6, mumps_pivot_order=0)


def only(terms_cls, term: str, **changes):
    """A solve's terms group with every weight (or a noise model's gain) 0 but ``term``'s (1), and its settings
    changed (``weight`` names the gain of a noise-modelled term)."""
    kw = {}
    for f in dataclasses.fields(terms_cls):
        cfg = f.default_factory()
        key = "gain" if isinstance(cfg, NoiseConfig) else "weight"
        mine = {(key if k == "weight" else k): v for k, v in changes.items()}
        extra = {key: 1.0, **mine} if f.name == term else {key: 0.0}
        kw[f.name] = dataclasses.replace(cfg, **extra)
    return terms_cls(**kw)


@functools.lru_cache(maxsize=1)
def window_data():
    """The spline test scene's window with every term's data: detections, exact tracks, exact boundary events, the
    stillness, a context smoothing, a floor a centimetre above the start's lowest sole points, reference joints."""
    rec, det, t_det, t_us, S, xy, valid = scene()
    n_seg = int((t_det[-1] - t_det[0]) // H_US)
    spl = UniformCubicBSpline(int(t_det[0]), H_US, n_seg)
    rng = np.random.default_rng(0)
    lo, hi = pose_bounds()
    gt = rec.ground_truth
    tk = np.linspace(t_det[0], t_det[-1], 25).astype(np.int64) // 1000 * 1000
    C = np.clip(spl.fit(tk, gt.poses[np.searchsorted(gt.t_us, tk)], smooth=1e-6) + rng.normal(0, 0.03, (
        n_seg + 3, 33)), lo + 1e-3, hi - 1e-3)
    curve = (lambda t, deriv=0: spl.evaluate(C, t, deriv))
    r2 = np.random.default_rng(1)
    knots = spl.t0_us + H_US * np.arange(n_seg + 1, dtype=np.int64)
    floor_y = float(np.median(sole_points(curve(knots), rec.template)[..., 1].min(1))) + 0.01
    still = rng.uniform(0, 2, (n_seg, 24)) * (rng.random((n_seg, 24)) < 0.5)
    ctx = ContextSmoothing(lam=np.ones(33), curvature=r2.uniform(0.5, 2.0, 33), n_fits=10,
                           target=spl.evaluate(C, t_det) + r2.normal(0, 0.05, (t_det.size, 33)),
                           frames=r2.uniform(0, 3, (t_det.size, 33)) * (r2.random((t_det.size, 33)) < 0.67))
    evidence = {"stillness": lambda: SimpleNamespace(stillness=still, edges_us=knots), "smoothing": lambda: ctx,
                "floor_y": lambda: floor_y, "fit_translation": lambda: r2.normal(0, 0.05, (t_det.size, 3))}
    inputs = WindowInputs(spl.t0_us, spl.t1_us, knots_us=knots, t_det_us=t_det, detections=det,
                          tracks=Tracks(t_us, xy, valid), track_times_us=(t_us,), events=silhouette_events(),
                          reference_us=t_us[::5], reference_joints=rng.normal(0, 0.3, (9, NUM_JOINTS, 3))
                          + np.array([0, 1.0, 0]), evidence=evidence)
    inputs.start = curve
    return rec, spl, C, inputs


def _factors(terms, inputs, rec, frames: np.ndarray | None = None):
    times = sample_times(terms, inputs)
    return factors_from_config(terms, rec.template, rec.camera, {k: t.size for k, t in times.items()})


SPLINE_TERMS = ["landmarks_2d", "joints_3d", "cor", "sil", "flow", "still", "prior", "context", "damp", "temp", "stab",
                "floor", "slide", "bones"]


@pytest.mark.parametrize("term", SPLINE_TERMS)
def test_every_factor_on_a_spline_matches_finite_differences(term):
    """Each term alone (weight 1) over a spline's control points, its data collected from the window's inputs and
    relinearised at the start: the problem's gradient and its Hessian (in the declared sparsity, exactly as IPOPT
    sees them) against central differences of its value."""
    rec, spl, C, inputs = window_data()
    if term == "damp":
        terms = only(SplineTerms, "prior", weight=0.0)
    elif term in ("temp", "stab"):  # terms of other solves work on a spline too
        terms = only(BatchTerms if term == "temp" else RefineTerms, term)
    elif term == "sil":
        terms = only(SplineTerms, "sil", loss="l2")  # the Huber loss: on frames, with its kink in a gap
    elif term == "flow":  # the scene's events fire at every boundary pixel every ms: no edge sweeps; keep every fit
        terms = only(SplineTerms, "flow", min_fit=0.0, min_cos=0.0, max_offset_px=1e6)
    else:
        terms = only(SplineTerms, term)
    if term in ("floor", "slide"):  # the scene's feet move: contact wherever they are slower than 3 m/s (and no
        # random stillness, which leaves no two neighbouring knots in contact)
        inputs = _with(inputs, contact=SimpleNamespace(speed_mps=3.0, height_m=0.2), stillness=None)
    factors = _factors(terms, inputs, rec)
    assert [f.name for f in factors] == ([] if term == "damp" else [term])
    prob = FactorProblem(SplinePoses(spl.n_seg), factors, SETTINGS, damp=1.0 if term == "damp" else 0.0,
                         band=coupling_band(SplinePoses(spl.n_seg, spl), inputs.tracks.t_us))
    for f in factors:
        f.collect(inputs)
        f.relinearize(Estimate(inputs.start, 1, inputs, rec.template, rec.camera))
    rng = np.random.default_rng(2)
    _random_indicator(factors, rng)
    x = np.concatenate([C.ravel(), rng.normal(0, 0.05, prob.nA)])
    prob.set_window(spl, x + rng.normal(0, 0.01, x.shape))
    _check(prob, x, term, [0, 4, 6, prob.n_units - 1], rng)


def _with(inputs: WindowInputs, contact=None, stillness=...):
    """A copy of the window's inputs with another contact setting or stillness evidence."""
    out = WindowInputs(inputs.t0_us, inputs.t1_us, knots_us=inputs.knots_us, t_det_us=inputs.t_det_us,
                       detections=inputs.detections, tracks=inputs.tracks, track_times_us=inputs.track_times_us,
                       events=inputs.events, reference_us=inputs.reference_us,
                       reference_joints=inputs.reference_joints, contact=contact or inputs.contact,
                       evidence=dict(inputs._providers))
    if stillness is not ...:
        out.offer("stillness", lambda: stillness)
    out.start = inputs.start
    return out


@pytest.mark.parametrize("term,loss", [("landmarks_2d", None), ("joints_3d", None), ("cor", None),
                                       ("cor_frozen", None), ("temp", None), ("damp", None), ("sil", "l2"),
                                       ("sil", "huber"), ("stab", None), ("landmarks_2d_robust", None)])
def test_every_factor_on_frames_matches_finite_differences(term, loss):
    """Each term alone over one pose per frame (the paper's batch solve and the refinement): the same check, with
    E_cor both coupled and with its source side held (w/o_batch), E_2D least-squares and Cauchy-robust."""
    rec, spl, C, window = window_data()
    t_us = window.tracks.t_us
    name = term.removesuffix("_frozen").removesuffix("_robust")
    if name in ("sil", "stab"):
        terms = only(RefineTerms, name, **({"loss": loss, "step_ms": 5.0} if name == "sil" else {}))
    elif term == "damp":
        terms = only(BatchTerms, "landmarks_2d", weight=0.0)
    else:
        terms = only(BatchTerms, name, **({"robust_px": 2.0 if term.endswith("_robust") else 0.0}
                                          if name == "landmarks_2d" else {}))
    # detection frames must be frames of this problem: the first and last of the window's tracking frames
    inputs = WindowInputs(int(t_us[0]), int(t_us[-1]), frames_us=t_us, t_det_us=t_us[[0, -1]],
                          detections=window.detections.rows([1, 2]), tracks=window.tracks, track_times_us=(t_us,),
                          events=window.events, reference_us=t_us, reference_joints=np.repeat(
                              window.reference_joints[:1], t_us.size, axis=0),
                          evidence={"fit_translation": lambda: np.zeros((2, 3))})
    poses = spl.evaluate(C, t_us)
    rows = {int(t): i for i, t in enumerate(t_us)}
    inputs.start = lambda t, deriv=0: poses[[rows[int(v)] for v in np.asarray(t).ravel()]]
    factors = _factors(terms, inputs, rec)
    est = Estimate(inputs.start, 1, inputs, rec.template, rec.camera, coupled=term != "cor_frozen")
    for f in factors:
        f.collect(inputs)
        f.relinearize(est)
    if loss == "huber":  # δ in the widest gap between residuals: none crosses the kink within the steps
        probe = factors[0]
        r = np.sort(np.abs(probe.residuals(probe._points(probe.kernels.transforms(inputs.start(probe.t_us))))[0]))
        mid = r[r.size // 4: 3 * r.size // 4]
        k = int(np.argmax(np.diff(mid)))
        assert mid[k + 1] - mid[k] > 1e-6
        terms = only(RefineTerms, "sil", loss="huber", step_ms=5.0, huber_px=0.5 * (mid[k] + mid[k + 1]) / probe.scale)
        factors = _factors(terms, inputs, rec)
        for f in factors:
            f.collect(inputs)
            f.relinearize(est)
    prob = FactorProblem(FramePoses(t_us.size), factors, SETTINGS, damp=1.0 if term == "damp" else 0.0,
                         damp_aux=False)
    rng = np.random.default_rng(3)
    _random_indicator(factors, rng)
    x = np.concatenate([poses.ravel(), rng.normal(0, 0.05, prob.nA)])
    prob.set_window(t_us, x + rng.normal(0, 0.01, x.shape))
    sil_frames = np.isin(t_us, t_us[::5])
    frames = [int(np.flatnonzero(sil_frames)[1]), 0, t_us.size // 2, t_us.size - 1]
    _check(prob, x, term, frames, rng)


def _random_indicator(factors, rng) -> None:
    """E_temp held at random joints and frames (the exact tracks of the scene leave no part without
    correspondences: the estimate's own indicator is all zeros there)."""
    for f in factors:
        if f.name == "temp":
            f.set_indicator((rng.random((f.n - 1, NUM_JOINTS)) < 0.5).astype(float))


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
    rec, spl, C, inputs = window_data()
    poses = SplinePoses(spl.n_seg, spl)
    on_grid = inputs.tracks.t_us  # 1 ms steps from a knot: a pair straddling a knot ends on it
    assert coupling_band(poses, on_grid) == 3
    off = on_grid[::5] + 2_500  # 5 ms steps, 2.5 ms past the knots: pairs straddle them
    assert coupling_band(poses, off) == 4
    shifted = _with(inputs)
    shifted.tracks = Tracks(off, inputs.tracks.xy[::5], inputs.tracks.valid[::5])
    factors = _factors(only(SplineTerms, "cor"), shifted, rec)
    prob = FactorProblem(poses, factors, SETTINGS, damp=0.0, band=3)
    factors[0].collect(shifted)
    with pytest.raises(EnergyError, match="factor cor couples samples 4 units apart; the problem was built for 3"):
        prob.set_window(spl)


def test_a_factor_owns_its_data_and_relinearises_at_the_estimate():
    """E_cor's correspondences come from the estimate at each round (searched once for every factor that asks: E_cor
    and E_temp share them); E_sil matches the silhouette at the estimate; the floor terms' contacts follow the
    estimate; a round without association leaves the tracks' and the silhouette's data empty. Each factor reports
    its own counts."""
    rec, spl, C, inputs = window_data()
    terms = SplineTerms()  # the defaults: every term but the context pull and the bones on
    factors = _factors(terms, inputs, rec)
    names = [f.name for f in factors]
    assert names == ["landmarks_2d", "joints_3d", "cor", "sil", "still", "prior", "floor", "slide"]
    for f in factors:
        f.collect(inputs)
    est = Estimate(inputs.start, 0, inputs, rec.template, rec.camera)
    for f in factors:
        f.relinearize(est)
    reports = {f.name: f.report() for f in factors}
    corr = est.correspondences()
    assert reports["cor"]["n_correspondences"] == corr.n > 500
    assert est.correspondences() is corr  # searched once per round
    assert reports["sil"]["n_silhouette"] > 1000 and reports["sil"]["n_boundary"] >= reports["sil"]["n_silhouette"]
    cor = next(f for f in factors if f.name == "cor")
    temp = FACTORS["temp"](FACTORS["temp"].Config(weight=1.0), rec.template, rec.camera, inputs.tracks.t_us.size)
    temp.collect(inputs)
    temp.relinearize(est)
    assert temp.phi.shape == (inputs.tracks.t_us.size - 1, NUM_JOINTS) and cor.corr is corr
    # another estimate: other correspondences and contacts
    moved = (lambda t, deriv=0: inputs.start(t, deriv) + (0.05 if deriv == 0 else 0.0))
    est2 = Estimate(moved, 1, inputs, rec.template, rec.camera)
    floor = next(f for f in factors if f.name == "floor")
    before = floor.contact.copy()
    for f in factors:
        f.relinearize(est2)
    assert cor.corr is est2.correspondences() and cor.corr is not corr
    assert not np.array_equal(floor.contact, before)
    # no association (icp_rounds 0): the tracks and the silhouette give nothing, the stillness still holds
    quiet = Estimate(inputs.start, 0, inputs, rec.template, rec.camera, associate=False)
    sil = next(f for f in factors if f.name == "sil")
    fresh = _factors(terms, inputs, rec)
    for f in fresh:
        f.collect(inputs)
        f.relinearize(quiet)
    rep = {f.name: f.report() for f in fresh}
    assert rep["cor"]["n_correspondences"] == 0 and rep["sil"]["n_silhouette"] == 0
    assert sil.corr.n > 0  # the other factors' data are theirs
    still = next(f for f in fresh if f.name == "still")
    assert np.abs(still.M).max() > 0


def test_the_solves_never_name_a_term():
    """No solve (the spline, the paper's batch solve, the refinement) names a term: no term's name appears as a
    string in their modules (their specs declare the terms they use, and the old keys' new names), and none asks
    its problem for a factor by name."""
    names = set(FACTORS)
    files = [p for p in (*sorted((ROOT / "plugins" / "eventcap_spline").glob("*.py")),
                         ROOT / "plugins" / "eventcap_solve" / "batch.py",
                         ROOT / "plugins" / "eventcap_solve" / "_impl.py",
                         *sorted((ROOT / "plugins" / "eventcap_refine").glob("*.py"))) if p.name != "spec.py"]
    found = []
    for path in files:
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value in names:
                found.append(f"{path.relative_to(ROOT)}:{node.lineno}: {node.value!r}")
            if isinstance(node, ast.Attribute) and node.attr == "factor" and isinstance(node.ctx, ast.Load):
                found.append(f"{path.relative_to(ROOT)}:{node.lineno}: .factor(...)")
    assert not found, "solves that name a term:\n" + "\n".join(found)


# ------------------------------------------------------------------------------------------------ a new term
@dataclasses.dataclass
class ToyConfig(FactorConfig):
    """The new term's settings: its weight and its target."""

    weight: float = param(0.0, ge=0, help="weight of the toy term")
    target: float = param(0.0, help="the value every pose parameter is held at, rad or m")


class ToyHold(Factor):
    """λ_toy Σ_d ‖S(t_d) - target‖² at the detection frames: a new term, written as one class."""

    name = "toy"
    Config = ToyConfig

    def __init__(self, config, template, camera, n):
        super().__init__(config, template, camera, n)
        self.target = np.full(NUM_POSE_PARAMS, float(config.target))

    @classmethod
    def samples(cls, inputs, config):
        return inputs.need("t_det_us", "E_toy")

    def linearize(self, S, aux, order):
        R = S - self.target
        lin = Linearization(self.weight * float(np.sum(R * R)))
        if order >= 1:
            lin.grad = 2.0 * self.weight * R
        if order >= 2:
            lin.diag = np.broadcast_to(2.0 * self.weight * np.eye(NUM_POSE_PARAMS), (self.n, 33, 33)).copy()
        return lin

    def report(self):
        return {"n_toy": self.n}


@dataclasses.dataclass
class ToyTerms(SplineTerms):
    toy: ToyConfig = group(ToyConfig, help="the toy term")  # the one config entry


@dataclasses.dataclass
class ToySolveConfig(SplineSolveConfig):
    terms: ToyTerms = group(ToyTerms, help="the terms, with the toy")


def test_a_new_term_is_one_class_and_one_config_entry():
    """ToyHold registers itself by its name; a solve whose terms list it with weight > 0 uses it (its energy and
    count reported, its pull visible in the solution) without a change anywhere else; weight 0 leaves it out."""
    from eventcap_spline.solve import SplineSolver, solve_window


    assert FACTORS["toy"] is ToyHold
    rec, det, t_det, t_us, S, xy, valid = scene(exact=True)
    n_seg = int((t_det[-1] - t_det[0]) // H_US)
    spl = UniformCubicBSpline(int(t_det[0]), H_US, n_seg)
    res = {}
    for lam in (0.0, 1e6):  # the detections are exact (their noise the terms' floor): the toy must outweigh them
        cfg = ToySolveConfig(icp_rounds=1)
        cfg.terms.toy.weight = lam
        cfg.terms.sil.gain = cfg.terms.still.gain = cfg.terms.context.gain = 0.0
        inputs = scene_inputs(spl, xy, valid)
        inputs.detections = det
        times = sample_times(cfg.terms, inputs)
        from eventcap.energy.factor import Layout

        layout = Layout(n_seg=n_seg, sizes=tuple((k, t.size) for k, t in times.items()),
                        band=coupling_band(SplinePoses(n_seg, spl), t_us))
        solver = SplineSolver(rec.template, rec.camera, layout, cfg)
        assert ("toy" in [f.name for f in solver.factors]) == (lam > 0)
        res[lam] = solve_window(solver, spl, inputs)
        assert res[lam].solves[-1].status == "Solve_Succeeded"
    assert res[1e6].energies["toy"] > 0 and res[1e6].energies["n_toy"] == t_det.size
    assert "toy" not in res[0.0].energies
    held = np.abs(spl.evaluate(res[1e6].control, t_det)[:, :27]).mean()
    free = np.abs(spl.evaluate(res[0.0].control, t_det)[:, :27]).mean()
    assert held < 0.2 * free, (held, free)


def test_a_factor_name_is_taken_once_and_bad_weights_and_missing_data_are_named():
    with pytest.raises(TypeError, match="factor name 'landmarks_2d' of .* is already"):
        type("Other2D", (Factor,), {"name": "landmarks_2d", "samples": classmethod(lambda c, i, g: np.zeros(1)),
                                    "linearize": lambda self, S, a, o: None})
    rec, spl, C, inputs = window_data()
    terms = SplineTerms()
    terms.prior.gain = float("nan")
    with pytest.raises(EnergyError, match=r"terms.prior.gain: expected a finite number >= 0, got nan"):
        _factors(terms, inputs, rec)
    f = _factors(only(SplineTerms, "landmarks_2d"), inputs, rec)[0]
    with pytest.raises(EnergyError, match="E_2D: the window has no detections"):
        empty = WindowInputs(0, 1, t_det_us=inputs.t_det_us)
        f.collect(empty)
    # a terms group whose entry names no factor, or holds another factor's settings, is refused naming it

    @dataclasses.dataclass
    class Wrong:
        nothing: FactorConfig = group(FactorConfig, weight=1.0, help="no such factor")

    with pytest.raises(EnergyError, match=r"terms.nothing: no factor of that name \(registered: .*landmarks_2d"):
        term_configs(Wrong())

    @dataclasses.dataclass
    class Swapped:
        prior: FactorConfig = group(FACTORS["cor"].Config, help="E_cor's settings under the prior's name")

    with pytest.raises(EnergyError, match=r"terms.prior: expected the settings PriorNoise of factor MotionPrior, "
                                          r"got CorConfig"):
        term_configs(Swapped())
