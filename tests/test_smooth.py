"""The frames-only smoothing baseline (plugins/eventcap_smooth, pipeline=frames_smooth): the spline's penalty
against scipy, the GCV choice on synthetic noise of known variance, root rotations that wrap, the stages and their
conformance, and the pipeline config."""

from __future__ import annotations

import numpy as np
import pytest

from eventcap.artifacts.pose import PoseSequence
from eventcap.analysis.motion import wrap_angle
from eventcap.core.stage import StageContext, StageFailed
from eventcap.core.testing import StageConformance
from eventcap_smooth._impl import frame_fits, run_smooth, run_split
from eventcap_smooth.smoothing import smooth_poses

from eventcap.analysis.smoothing import GcvCurve, penalty_matrix
from eventcap_smooth.spec import SmoothConfig, SplitConfig

FRAME_US = 40_000  # 25 fps


def truth(x: np.ndarray) -> np.ndarray:
    return 0.5 * np.sin(2 * np.pi * 1.3 * x) + 0.2 * np.cos(2 * np.pi * 0.4 * x)


def test_penalty_matrix_gives_scipys_smoothing_spline():
    from scipy.interpolate import make_smoothing_spline

    rng = np.random.default_rng(0)
    x = np.sort(rng.uniform(0.0, 2.0, 30))
    y = rng.normal(size=30)
    K = penalty_matrix(x)
    for lam in (1e-5, 1e-3, 1e-1):
        assert np.allclose(np.linalg.solve(np.eye(30) + lam * K, y), make_smoothing_spline(x, y, lam=lam)(x),
                           atol=1e-8)
    # straight lines cost nothing: K annihilates 1 and x
    scale = np.abs(K).max()
    assert np.abs(K @ np.ones(30)).max() < 1e-12 * scale and np.abs(K @ x).max() < 1e-12 * scale


def test_gcv_on_noise_of_known_variance():
    """Fits every 40 ms over 2 s = a smooth motion + white noise of sigma 5 cm (27 columns, one lam): the GCV choice
    (no truth involved) estimates sigma within 10%, halves the error of the raw fits, and is within 5% of the error
    of the best lam in hindsight (chosen with the truth)."""
    from scipy.interpolate import make_smoothing_spline

    rng = np.random.default_rng(1)
    t_us = np.arange(51, dtype=np.int64) * FRAME_US
    x = t_us * 1e-6
    sigma = 0.05
    Y = truth(x)[:, None] + rng.normal(0.0, sigma, (51, 27))
    ch = GcvCurve(x).choose(Y)
    assert ch.sigma.mean() == pytest.approx(sigma, rel=0.1)
    assert 4 < ch.dof < 40  # neither a straight line nor interpolation
    xe = np.arange(0, 2_000_001, 1_000) * 1e-6
    err = lambda lam: np.sqrt(np.mean((make_smoothing_spline(x, Y, lam=lam)(xe) - truth(xe)[:, None]) ** 2))  # noqa
    assert err(ch.lam) < 0.6 * sigma
    best = min(err(ch.lam * 10.0**k) for k in np.linspace(-3, 3, 61))
    assert err(ch.lam) < 1.05 * best
    # more noise -> more smoothing
    assert GcvCurve(x).choose(truth(x)[:, None] + rng.normal(0.0, 4 * sigma, (51, 27))).lam > ch.lam
    # the restricted likelihood (stages.smooth.criterion=reml) on the same fits: sound too (here it smooths a little
    # less than GCV: 8% above the best error)
    re = GcvCurve(x).choose_reml(Y)
    assert re.sigma.mean() == pytest.approx(sigma, rel=0.15) and err(re.lam) < min(1.15 * best, 0.6 * sigma)


def test_reml_does_not_interpolate_few_fits_where_gcv_may():
    """11 fits (0.4 s at 25 fps) of 3 parameters with white noise, 40 seeds: GCV interpolates (more than 8 of 11
    degrees of freedom) in 4 of them, REML in none, and REML's error always stays below the noise."""
    from scipy.interpolate import make_smoothing_spline

    x = np.arange(11) * FRAME_US * 1e-6
    xe = np.linspace(0.0, x[-1], 401)
    slow = lambda x: 0.15 * np.sin(2 * np.pi * 1.3 * x)  # noqa: E731
    gcv_dof, reml_dof = [], []
    for seed in range(40):
        Y = slow(x)[:, None] + np.random.default_rng(seed).normal(0.0, 0.05, (11, 3))
        c = GcvCurve(x)
        gcv_dof.append(c.choose(Y).dof)
        r = c.choose_reml(Y)
        reml_dof.append(r.dof)
        assert np.sqrt(np.mean((make_smoothing_spline(x, Y, lam=r.lam)(xe) - slow(xe)[:, None]) ** 2)) < 0.05
    assert sum(d > 8 for d in gcv_dof) == 4 and max(reml_dof) < 5



def test_the_criteria_of_the_whole_grid_equal_them_lam_by_lam_and_each_column_gets_its_own_choice():
    """GcvCurve.table (every lam at once) equals score (GCV) and reml lam by lam, pooled and column by column;
    choose_each gives each column the lam choose_by gives it alone; and a bad criterion is named."""
    rng = np.random.default_rng(3)
    x = np.sort(rng.choice(np.arange(200), 37, replace=False)) * 0.013
    Y = np.cumsum(rng.normal(0.0, 0.1, (37, 6)), axis=0) + rng.normal(0.0, 0.05, (37, 6))
    Y[:, 5] = 0.3 * x - 0.1 + rng.normal(0.0, 0.05, 37)  # a straight line and noise: smoothed most
    c = GcvCurve(x)
    lams = c.grid()
    assert lams.size == 281 and lams[0] == pytest.approx(np.median(np.diff(x)) ** 3 * 1e-4)
    for crit, one in (("gcv", lambda Z, lam: c.score(Z, lam)[0]), ("reml", c.reml)):
        pooled = c.table(Y, lams, crit)
        each = c.table(Y, lams, crit, pooled=False)
        assert pooled.shape == (281,) and each.shape == (281, 6)
        for i in (0, 77, 140, 280):
            assert pooled[i] == pytest.approx(one(Y, lams[i]), rel=1e-9)
            assert each[i] == pytest.approx([one(Y[:, k:k + 1], lams[i]) for k in range(6)], rel=1e-9)
        chosen = c.choose_each(Y, crit)
        assert np.array_equal(chosen, [c.choose_by(Y[:, k:k + 1], crit).lam for k in range(6)])
        assert chosen[5] > 100 * np.median(chosen[:5])
    with pytest.raises(ValueError, match="criterion: expected one of reml, gcv, got 'aic'"):
        c.choose_each(Y, "aic")

def test_smooth_poses_groups_and_parameters():
    rng = np.random.default_rng(2)
    t_us = np.arange(31, dtype=np.int64) * FRAME_US
    x = t_us * 1e-6
    clean = np.zeros((31, 33))
    clean[:, :27] = truth(x)[:, None]
    clean[:, 30:] = 0.3 * x[:, None]  # the root walks at 0.3 m/s
    noisy = clean + np.r_[np.full(30, 0.05), np.full(3, 0.01)] * rng.normal(size=(31, 33))
    t_eval = np.arange(0, t_us[-1] + 1, 1_000, dtype=np.int64)
    want = np.interp(t_eval, t_us, np.zeros(31))  # shape only
    for pool in ("group", "parameter"):
        out, choices = smooth_poses(t_us, noisy, t_eval, pool, 0.0, "reml")
        assert out.shape == (want.size, 33)
        assert len(choices) == (2 if pool == "group" else 33)
        on_knots = out[np.searchsorted(t_eval, t_us)]
        assert np.sqrt(np.mean((on_knots - clean) ** 2)) < 0.7 * np.sqrt(np.mean((noisy - clean) ** 2))
    # a fixed lam, the same for all groups
    out, choices = smooth_poses(t_us, noisy, t_eval, "group", 1e-3, "reml")
    assert {c.lam for c in choices.values()} == {1e-3}
    with pytest.raises(ValueError, match="pool: expected one of group, parameter, got 'x'"):
        smooth_poses(t_us, noisy, t_eval, "x", 0.0, "reml")
    with pytest.raises(ValueError, match="criterion: expected one of reml, gcv, got 'aic'"):
        smooth_poses(t_us, noisy, t_eval, "group", 0.0, "aic")
    gcv, _ = smooth_poses(t_us, noisy, t_eval, "group", 0.0, "gcv")
    assert np.sqrt(np.mean((gcv[np.searchsorted(t_eval, t_us)] - clean) ** 2)) < np.sqrt(np.mean((noisy - clean) ** 2))
    with pytest.raises(ValueError, match="at least 5 knots"):
        smooth_poses(t_us[:4], noisy[:4], t_eval, "group", 0.0, "reml")
    bad = noisy.copy()
    bad[3, 5] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        smooth_poses(t_us, bad, t_eval, "group", 0.0, "reml")


def test_root_rotation_that_wraps_is_smoothed_as_a_spin():
    """The root turns at 4 rad/s; its fits are reported in [-π, π) (a jump of 2π every ~1.6 s). Smoothed, the yaw
    follows the spin (error well below the noise, modulo 2π), instead of cutting across the wrap."""
    rng = np.random.default_rng(3)
    t_us = np.arange(51, dtype=np.int64) * FRAME_US
    x = t_us * 1e-6
    yaw = 4.0 * x
    fits = np.zeros((51, 33))
    fits[:, 27] = wrap_angle(yaw + rng.normal(0.0, 0.05, 51))
    t_eval = np.arange(0, t_us[-1] + 1, 1_000, dtype=np.int64)
    out, _ = smooth_poses(t_us, fits, t_eval, "group", 0.0, "reml")
    err = wrap_angle(out[:, 27] - 4.0 * t_eval * 1e-6)
    assert np.abs(err).max() < 0.1 and np.sqrt(np.mean(err**2)) < 0.03


# -- the stages -----------------------------------------------------------------------------------------------------
def linear_batches(fits: np.ndarray, step_us: int = 1_000) -> list[PoseSequence]:
    """What solve mode linear gives: per batch, the fits at its two frames, interpolated at every tracking frame."""
    out = []
    for k in range(fits.shape[0] - 1):
        t = np.arange(k * FRAME_US, (k + 1) * FRAME_US + 1, step_us, dtype=np.int64)
        a = ((t - t[0]) / FRAME_US)[:, None]
        out.append(PoseSequence(t_us=t, poses=(1 - a) * fits[k] + a * fits[k + 1], status="linear"))
    return out


def noisy_fits(n: int = 11, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    x = np.arange(n) * FRAME_US * 1e-6
    clean = np.zeros((n, 33))
    clean[:, :27] = truth(x)[:, None]
    return clean, clean + rng.normal(0.0, 0.05, (n, 33))


def test_frame_fits_takes_each_frame_once_in_time_order():
    _, fits = noisy_fits(6)
    parts = linear_batches(fits)
    t, S = frame_fits([parts[3], parts[0], parts[1], parts[2], parts[4]])
    assert np.array_equal(t, np.arange(6) * FRAME_US)
    assert np.allclose(S, fits)


def test_smooth_and_split_stages():
    clean, fits = noisy_fits(11)
    parts = linear_batches(fits)
    ctx = StageContext(node="smooth", stage="smooth")
    motion = run_smooth({"fits": parts}, SmoothConfig(), ctx)["motion"]
    assert motion.t_us.size == 10 * 40 + 1 and motion.status == "smoothed"
    assert set(motion.energies) == {"lam_angles", "lam_root_translation", "dof_angles", "dof_root_translation"}
    at_frames = motion.poses[np.searchsorted(motion.t_us, np.arange(11) * FRAME_US)]
    assert np.sqrt(np.mean((at_frames - clean) ** 2)) < np.sqrt(np.mean((fits - clean) ** 2))
    for k in (0, 4):
        got = run_split({"frames": parts[k], "motion": motion}, SplitConfig(), ctx)["poses"]
        assert np.array_equal(got.t_us, parts[k].t_us)
        assert np.array_equal(got.poses, motion.poses[k * 40:(k + 1) * 40 + 1])
    off = PoseSequence(t_us=parts[0].t_us + 500, poses=parts[0].poses)
    with pytest.raises(StageFailed, match=r"split: the motion has no frame at t = 500 us \(41 of this batch's 41"):
        run_split({"frames": off, "motion": motion}, SplitConfig(), ctx)
    with pytest.raises(StageFailed, match=r"smooth: 4 intensity frames with a fit \(3 batches\); a smoothing spline "
                                          r"needs at least 5") as e:
        run_smooth({"fits": parts[:3]}, SmoothConfig(), ctx)
    assert e.value.status == "invalid_input"


class TestSmoothConformance(StageConformance):
    stage_name = "smooth"
    sensitive = ("pool", "parameter")

    def make_inputs(self):
        return {"fits": linear_batches(noisy_fits(8)[1], step_us=4_000)}


class TestSplitConformance(StageConformance):
    stage_name = "split"

    def make_inputs(self):
        parts = linear_batches(noisy_fits(8)[1], step_us=4_000)
        motion = run_smooth({"fits": parts}, SmoothConfig(), StageContext(node="s", stage="smooth"))["motion"]
        return {"frames": parts[0], "motion": motion}


def test_frames_smooth_pipeline_composes_and_validates():
    """pipeline=frames_smooth: fits in mode linear, smooth, split (its node solve), evaluate."""
    from eventcap.apps.benchmark import compose_run
    from eventcap.apps.cli import config_dir
    from eventcap.core.pipeline import build_pipeline
    from eventcap.core.registry import load_registry

    data, _ = compose_run(config_dir(), ["pipeline=frames_smooth",
                                         "stages.smooth.pool=parameter"])
    assert data["stages"]["fits"]["mode"] == "linear" and data["stages"]["smooth"]["pool"] == "parameter"
    assert data["stages"]["smooth"]["criterion"] == "gcv"  # the stronger baseline on the 2 s suite
    nodes = {n.name: n for n in build_pipeline(data, load_registry())}
    assert nodes["fits"].spec.name == "batch" and nodes["fits"].config.mode == "linear"
    assert nodes["smooth"].spec.name == "smooth" and nodes["solve"].spec.name == "split"
    assert nodes["evaluate"].inputs["poses"].node == "solve"
    assert data["outputs"]["poses"] == "solve.poses"
    # the default DAG is the spline solve's (pipeline=spline); pipeline=paper keeps the paper's solve + refine
    paper, _ = compose_run(config_dir(), ["pipeline=paper"])
    default, _ = compose_run(config_dir(), [])
    spline, _ = compose_run(config_dir(), ["pipeline=spline"])
    assert default["pipeline"] == spline["pipeline"] and default["outputs"]["poses"] == "cut.poses"
    assert {"solve", "refine"} <= set(paper["pipeline"]["nodes"]) and "refine" not in default["pipeline"]["nodes"]
    assert paper["outputs"]["poses"] == "refine.poses"
