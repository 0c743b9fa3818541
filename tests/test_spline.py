"""The spline solve (not in the paper; plugins/eventcap_spline): the B-spline basis and its priors, derivatives of
every term of the spline energy against finite differences, accuracy against ground truth, the stage."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest

from eventcap.artifacts import BatchPlan
from eventcap.body.kinematics import joint_positions
from eventcap.body.skeleton import DOF_INDEX, pose_bounds
from eventcap.energy.correspondences import find_correspondences
from eventcap.energy.spline import UniformCubicBSpline
from eventcap.analysis.metrics import mean_joint_error
from eventcap.core.stage import StageFailed
from eventcap.core.testing import StageConformance
from eventcap_spline._impl import window_of
from eventcap_spline.plan import cor_frames
from eventcap.energy.errors import EnergyError
from eventcap.energy.window import Estimate, WindowInputs
from eventcap.params import nest
from helpers.spline_scene import (FAST, H_US, run_stage, scene, silhouette_events, solver,
                                  stage_inputs, stitch, window)


# ------------------------------------------------------------------------------------------------ the basis
def test_basis_is_a_partition_of_unity_and_its_derivatives_match_finite_differences():
    spl = UniformCubicBSpline(5_000, H_US, 6)
    assert spl.n_ctrl == 9 and spl.t1_us == 65_000
    t = np.linspace(5_000, 65_000, 97)
    B = spl.basis(t)
    np.testing.assert_allclose(B.sum(axis=1), 1.0, atol=1e-12)
    assert B.min() >= 0 and np.count_nonzero(B, axis=1).max() <= 4
    tin = t[1:-1] + 2.0  # off the knots by more than the difference step (the 3rd derivative jumps there)
    for k in (1, 2, 3):
        fd = (spl.basis(tin + 0.5, k - 1) - spl.basis(tin - 0.5, k - 1)) / 1e-6  # per second
        scale = np.abs(fd).max()
        np.testing.assert_allclose(spl.basis(tin, k), fd, atol=1e-5 * scale, err_msg=f"derivative {k}")
    with pytest.raises(ValueError, match="outside its span"):
        spl.basis([4_000])


@pytest.mark.parametrize("deriv", [1, 2, 3])
def test_prior_gram_matrix_is_the_exact_integral(deriv):
    spl = UniformCubicBSpline(0, H_US, 5)
    C = np.random.default_rng(deriv).normal(size=(spl.n_ctrl, 3))
    Q = spl.gram(deriv)
    t = np.linspace(0, spl.t1_us, 200_001)  # dense trapezoid: the integrand is a piecewise polynomial
    v = np.sum(spl.evaluate(C, t, deriv) ** 2, axis=1)
    numeric = np.sum(0.5 * (v[1:] + v[:-1]) * np.diff(t) * 1e-6)
    assert np.trace(C.T @ Q @ C) == pytest.approx(numeric, rel=1e-6)
    assert np.allclose(Q, Q.T) and np.all(np.abs(np.triu(Q, 4)) == 0)  # symmetric, banded


def test_fit_reproduces_a_cubic_and_smoothing_keeps_a_straight_line():
    spl = UniformCubicBSpline(0, H_US, 8)
    t = np.linspace(0, spl.t1_us, 17)
    ts = t * 1e-6
    cubic = np.stack([1 + 2 * ts - 30 * ts**2 + 400 * ts**3, -ts], axis=1)
    C = spl.fit(t, cubic, smooth=0.0, ridge=0.0)
    tq = np.linspace(0, spl.t1_us, 333)
    tqs = tq * 1e-6
    np.testing.assert_allclose(spl.evaluate(C, tq), np.stack([1 + 2 * tqs - 30 * tqs**2 + 400 * tqs**3, -tqs], 1),
                               atol=1e-9)
    line = 0.3 + 5.0 * ts
    C = spl.fit(t, line[:, None], smooth=1.0, deriv=2, ridge=0.0)  # zero acceleration: not penalised at all
    np.testing.assert_allclose(spl.evaluate(C, tq)[:, 0], 0.3 + 5.0 * tqs, atol=1e-9)


def test_fit_with_a_smoothing_per_column_equals_the_columns_fitted_one_by_one():
    spl = UniformCubicBSpline(0, H_US, 8)
    t = np.linspace(0, spl.t1_us, 9)
    Y = np.random.default_rng(3).normal(size=(9, 3))
    sm = np.array([1e-6, 1e-3, 1.0])
    C = spl.fit(t, Y, smooth=sm)
    for c in range(3):
        np.testing.assert_allclose(C[:, c], spl.fit(t, Y[:, c], smooth=sm[c]), atol=1e-10)
    # a stiffer column is smoother: its acceleration integral is smaller
    acc = np.einsum("ic,ij,jc->c", C, spl.gram(2), C)
    assert acc[2] < 1e-3 * acc[0]
    with pytest.raises(ValueError, match="2 smoothing values for 3 columns"):
        spl.fit(t, Y, smooth=sm[:2])


def test_the_context_pull_targets_the_smoothing_spline_and_weighs_what_the_other_frames_know():
    """smoothed_at is (I + lam K)^-1 y and that matrix' diagonal at the named frames, per column with its own lam;
    on the 20 fits above the resting parameter's leverage is ~0.18 (the pull ~5 frames' worth), the cleanly moving
    one's ~1 (no pull); a time not among the fits gives NaN."""
    from eventcap.analysis.smoothing import penalty_matrix

    from eventcap.energy.prior import smoothed_at

    rng = np.random.default_rng(0)
    t = np.arange(20) * 100_000
    ts = t * 1e-6
    fits = np.stack([0.3 + rng.normal(0, 0.2, 20), np.sin(2 * np.pi * ts) + rng.normal(0, 0.02, 20),
                     np.sin(2 * np.pi * ts) + rng.normal(0, 0.2, 20)], axis=1)
    from eventcap.analysis.smoothing import GcvCurve

    lam = GcvCurve(ts).choose_each(fits, "reml")
    at = np.array([t[0], t[7], t[8] + 50_000, t[19]])
    g, h = smoothed_at(t, fits, lam, at)
    K = penalty_matrix(ts)
    for p in range(3):
        H = np.linalg.inv(np.eye(20) + lam[p] * K)
        np.testing.assert_allclose(g[[0, 1, 3], p], (H @ fits[:, p])[[0, 7, 19]], atol=1e-9)
        np.testing.assert_allclose(h[[0, 1, 3], p], np.diag(H)[[0, 7, 19]], atol=1e-9)
    assert np.all(np.isnan(g[2])) and np.all(np.isnan(h[2]))
    assert 0.1 < h[1, 0] < 0.25 and h[1, 1] > 0.9, h[1]
    assert abs(g[1, 0] - 0.3) < abs(fits[7, 0] - 0.3)  # the resting one's estimate is nearer its true value


def test_windows_cover_the_batch_and_shift_inwards_at_the_ends():
    assert [window_of(10, k, 2) for k in (0, 1, 2, 5, 8, 9)] == [(0, 4), (0, 4), (0, 4), (3, 7), (5, 9), (5, 9)]
    assert window_of(3, 1, 2) == (0, 2) and window_of(1, 0, 0) == (0, 0)
    assert cor_frames(41, 1).tolist() == list(range(41))
    assert cor_frames(41, 3).tolist() == list(range(0, 41, 3)) + [40]


# ------------------------------------------------------------------------------------------------ a window


def joint_error_mm(rec, poses, truth) -> float:
    rest = rec.template.rest_joints
    return float(np.mean(1000 * mean_joint_error(joint_positions(poses, rest), joint_positions(truth, rest))))


def test_event_silence_term_is_the_image_velocity_of_the_still_joints():
    """E_still at its linearisation point = ½/σ² Σ_s Σ_j s[s, j] ∫_s ‖d/dt π(x_j(S(t)))‖² dt (σ² = ½ here), the
    joints' image velocities (px/s) by central differences of the projected joints in time."""
    from eventcap.energy.silence import EventSilence

    rec, det, t_det, t_us = scene()[:4]
    n_seg = int((t_det[-1] - t_det[0]) // H_US)
    spl = UniformCubicBSpline(int(t_det[0]), H_US, n_seg)
    gt = rec.ground_truth
    tk = np.arange(t_det[0], t_det[-1] + 1, 5_000)
    C = spl.fit(tk, gt.poses[np.searchsorted(gt.t_us, tk)], smooth=1e-6)
    still = np.zeros((n_seg, 24))
    still[2:5, 4] = 1.0  # the left knee over three knot intervals
    still[7, 21] = 3.0  # the right wrist over one
    term = EventSilence(EventSilence.Noise(sigma_px_s=0.5 ** 0.5), rec.template, rec.camera, 3 * n_seg)
    inputs = WindowInputs(spl.t0_us, spl.t1_us, knots_us=spl.t0_us + H_US * np.arange(n_seg + 1),
                          evidence={"stillness": lambda: SimpleNamespace(stillness=still)})
    curve = (lambda t, deriv=0: spl.evaluate(C, t, deriv))
    term.collect(inputs)
    term.relinearize(Estimate(curve, 0, inputs, rec.template, rec.camera))
    e = term.value(spl.evaluate(C, term.t_us, 1))
    t = np.arange(spl.t0_us, spl.t1_us, 10, dtype=np.float64) + 5.0  # 10 µs steps, interval midpoints
    rest = rec.template.rest_joints
    cam = rec.camera
    v = (cam.project(joint_positions(spl.evaluate(C, t + 1.0), rest))
         - cam.project(joint_positions(spl.evaluate(C, t - 1.0), rest))) / 2e-6  # px/s
    seg = np.minimum(((t - spl.t0_us) // H_US).astype(int), n_seg - 1)
    numeric = float(np.sum(still[seg] * np.sum(v ** 2, axis=-1)) * 10e-6)
    assert numeric > 1.0  # the knee and the wrist move in this scene
    assert e == pytest.approx(numeric, rel=0.02)
    inputs.offer("stillness", lambda: SimpleNamespace(stillness=still[:, :23]))
    with pytest.raises(EnergyError, match=r"E_still: expected stillness of shape \(\d+, 24\)"):
        term.relinearize(Estimate(curve, 0, inputs, rec.template, rec.camera))


def test_spline_through_noisy_detections_beats_the_per_frame_fits():
    """Detections with the default simulated noise: the spline over 4 frames (no events, a process power of 1e4) is
    about as near the truth in the middle batch as linear interpolation of the per-frame fits (29.6 against 28.9 mm:
    the detector's 3D offset, shared by the 4 frames, weighs the 3D less in the window than in one frame's fit; with
    the weights of before the noise models it was 0.85 x), and the joint limits hold at 1 kHz."""
    rec, det, t_det, t_us, S, xy, valid = scene()
    sol = solver(**{"icp_rounds": 0, "terms.sil.gain": 0.0, "terms.still.gain": 0.0, "terms.prior.q_default": 1e4})
    spl = UniformCubicBSpline(int(t_det[0]), H_US, sol.layout.n_seg)
    res = window(sol, spl, det, xy, valid)
    assert all(s.status == "Solve_Succeeded" for s in res.solves[-1:])
    P = spl.evaluate(res.control, t_us)
    a = ((t_us - t_us[0]) / (t_us[-1] - t_us[0]))[:, None]
    linear = (1 - a) * res.fits[1] + a * res.fits[2]
    e_spline, e_linear = joint_error_mm(rec, P, S), joint_error_mm(rec, linear, S)
    assert e_spline < 1.05 * e_linear, (e_spline, e_linear)
    lo, hi = pose_bounds()
    dense = spl.evaluate(res.control, np.arange(t_det[0], t_det[-1] + 1, 250))
    assert np.all(dense[:, :27] >= lo[:27] - 1e-7) and np.all(dense[:, :27] <= hi[:27] + 1e-7)


def test_cor_residuals_are_zero_on_exact_tracks_at_the_true_poses_and_shift_with_a_track():
    rec, det, t_det, t_us, S, xy, valid = scene()
    cor = solver().problem.factor("cor")
    corr = find_correspondences(rec.template, rec.camera, S, xy, valid)
    cor.set_correspondences(corr, relative=True)
    r = cor.residuals_px(S)
    assert r.shape == (corr.n, 2) and corr.n > 500
    assert np.percentile(np.linalg.norm(r, axis=1), 95) < 0.05  # only the rounding of the tracks' sub-pixel pick
    moved = xy.copy()
    moved[:, 7] += np.array([3.0, -4.0])[None] * ((t_us - t_us[0]) / 1000.0)[:, None] / 40.0  # 5 px by the end
    corr2 = find_correspondences(rec.template, rec.camera, S, moved, valid)
    cor.set_correspondences(corr2, relative=True)
    r2 = cor.residuals_px(S)
    mine = corr2.track == 7
    step = (corr2.frame[mine] - corr2.source[mine]) / 40.0  # the drift over each correspondence's frames
    assert mine.any()
    assert np.allclose(r2[mine], -np.array([3.0, -4.0])[None] * step[:, None], atol=0.1)


def test_silhouette_events_pull_the_spline_onto_the_true_outline():
    """E_sil against exact boundary events (no tracks): the projected joints of the middle batch move nearer the
    truth's (noisy detections leave them ~1 px off); a much larger weight is not needed to get there."""
    rec, det, t_det, t_us, S, xy, valid = scene()
    rest, cam = rec.template.rest_joints, rec.camera
    truth_px = cam.project(joint_positions(S, rest))
    err = {}
    for lam in (0.0, 1.0):  # E_sil off, and on at a boundary noise of 1 px
        sol = solver(**{"terms.sil.gain": lam, "terms.sil.sigma_px": 1.0, "icp_rounds": 3,
                        "terms.still.gain": 0.0})
        spl = UniformCubicBSpline(int(t_det[0]), H_US, sol.layout.n_seg)
        res = window(sol, spl, det, xy[:, :0], valid[:, :0], events=silhouette_events())
        assert res.solves[-1].status == "Solve_Succeeded"
        assert (res.energies.get("n_silhouette", 0) > 2000) == (lam > 0)
        px = cam.project(joint_positions(spl.evaluate(res.control, t_us), rest))
        err[lam] = float(np.mean(np.linalg.norm(px - truth_px, axis=-1)))
    assert err[0.0] > 0.9 and err[1.0] < 0.7 * err[0.0], err


def test_the_prior_weighs_each_parameter_by_its_process_power():
    """Without fits around the window the prior's process power is q_default for every parameter (reported); a
    smaller power holds the motion more: the elbow accelerates less."""
    rec, det, t_det, t_us, S, xy, valid = scene(exact=True)

    def solve(q):
        sol = solver(**{"icp_rounds": 1, "terms.still.gain": 0.0, "terms.sil.gain": 0.0, "terms.prior.q_default": q})
        spl = UniformCubicBSpline(int(t_det[0]), H_US, sol.layout.n_seg)
        res = window(sol, spl, det, xy, valid)
        assert res.solves[-1].status == "Solve_Succeeded"
        return res

    stiff, loose = solve(1.0), solve(1e4)
    np.testing.assert_allclose(stiff.reports["prior"]["prior_power"], 1.0)
    np.testing.assert_allclose(loose.reports["prior"]["prior_power"], 1e4)
    k = DOF_INDEX["l_elbow_flex"]
    acc = {n: np.abs(np.diff(r.control[:, k], 2)).max() for n, r in (("stiff", stiff), ("loose", loose))}
    assert acc["stiff"] < acc["loose"], acc


def test_robust_cor_weights_keep_drifting_tracks_from_pulling_the_motion():
    """One track in four drifts off its surface point at 0.5 px/ms: least squares (loss_scale 0) follows them, the
    Cauchy reweighting much less: the middle batch stays nearer the truth and the clean tracks' solution."""
    rec, det, t_det, t_us, S, xy, valid = scene(exact=True)
    bad = xy.copy()
    drift = (0.5 * (t_us - t_us[0]) / 1000.0)[:, None]
    bad[:, ::4, 0] += drift
    bad[:, ::4, 1] -= drift
    poses = {}
    for name, tracks, sigma in (("clean", xy, 0.0), ("least squares", bad, 0.0), ("robust", bad, 1.0)):
        sol = solver(**{"terms.cor.sigma_px": 0.2, "icp_rounds": 3, "terms.cor.loss_scale": sigma,
                        "terms.still.gain": 0.0, "terms.sil.gain": 0.0})
        spl = UniformCubicBSpline(int(t_det[0]), H_US, sol.layout.n_seg)
        res = window(sol, spl, det, tracks, valid)
        assert res.solves[-1].status == "Solve_Succeeded"
        poses[name] = spl.evaluate(res.control, t_us)
    truth = {k: joint_error_mm(rec, v, S) for k, v in poses.items()}
    to_clean = {k: joint_error_mm(rec, v, poses["clean"]) for k, v in poses.items()}
    assert truth["robust"] < 0.75 * truth["least squares"], truth
    assert to_clean["robust"] < 0.5 * to_clean["least squares"], to_clean
    with pytest.raises(ValueError, match=r"stages.solve.terms.cor.loss_scale: expected a finite number >= 0, got -1"):
        solver(**{"terms.cor.loss_scale": -1})


def test_correspondence_change_counts_kept_found_and_lost_correspondences_in_pixels():
    """The RMS over the union: a kept correspondence by how its residual changed, a new one by its residual, a lost
    one by its old residual; the same set at the same poses changes nothing."""
    from eventcap.energy.correspondences import Correspondences, correspondence_change_px

    def corr(source, frame, track):
        n = len(source)
        return dataclasses.replace(Correspondences.empty(), source=np.array(source), frame=np.array(frame),
                                   track=np.array(track), rest_points=np.zeros((n, 3)),
                                   weights=np.full((n, 24), 1 / 24), target_px=np.zeros((n, 2)),
                                   source_px=np.zeros((n, 2)), part=np.zeros(n, np.int64))

    old = corr([1, 1, 1], [0, 2, 2], [0, 0, 1])
    new = corr([3, 1, 1], [2, 2, 0], [5, 0, 0])  # (1, 0, 0) and (1, 2, 0) kept, (1, 2, 1) lost, (3, 2, 5) found
    r_old = np.array([[1.0, 0.0], [0.0, 1.0], [3.0, 4.0]])
    r_new = np.array([[0.0, 1.0], [0.0, 2.0], [1.0, 0.0]])
    assert correspondence_change_px(old, r_old, new, r_new) == pytest.approx(np.sqrt((0 + 1 + 25 + 1) / 4))
    assert correspondence_change_px(old, r_old, old, r_old) == 0.0
    assert correspondence_change_px(Correspondences.empty(), np.zeros((0, 2)), Correspondences.empty(),
                                    np.zeros((0, 2))) == 0.0
    # residuals_px_of: another set's residuals, the factor's own set untouched
    rec, det, t_det, t_us, S, xy, valid = scene()
    cor = solver().problem.factor("cor")
    a = find_correspondences(rec.template, rec.camera, S, xy, valid)
    moved = xy.copy()
    moved[:, 7] += np.array([3.0, -4.0])[None] * ((t_us - t_us[0]) / 1000.0)[:, None] / 40.0
    b = find_correspondences(rec.template, rec.camera, S, moved, valid)
    cor.set_correspondences(a, relative=True)
    r_b = cor.residuals_px_of(b, S)
    np.testing.assert_array_equal(cor.residuals_px(S), cor.residuals_px_of(a, S))
    assert cor.n_correspondences == a.n
    # only track 7's correspondences changed: by its drift over their frames (up to 5 px over the batch)
    change = correspondence_change_px(a, cor.residuals_px(S), b, r_b)
    mine = b.track == 7
    expect = np.sqrt(np.sum(np.linalg.norm(r_b[mine], axis=1) ** 2) / b.n)
    assert change == pytest.approx(expect, rel=0.05) and 0.01 < change < 0.5


def test_settled_correspondences_end_the_icp_rounds():
    """icp_settle_px above the first search's change: one solve, the same spline as icp_rounds=1; a tiny one: every
    round, each later search's change (px) reported (0: every round, unmeasured); on exact tracks the correspondences settle (the change falls)."""
    rec, det, t_det, t_us, S, xy, valid = scene()

    def solve(**change):
        sol = solver(**{"terms.sil.gain": 0.0, "terms.still.gain": 0.0, **change})
        spl = UniformCubicBSpline(int(t_det[0]), H_US, sol.layout.n_seg)
        return window(sol, spl, det, xy, valid)

    assert solve(icp_rounds=3).association_change_px == ()  # 0: every round, nothing measured (no search spent)
    every = solve(icp_rounds=3, icp_settle_px=1e-9)
    assert len(every.solves) == 3 and len(every.association_change_px) == 2
    first, second = every.association_change_px
    assert 0 < second < first < 2.0, every.cor_change_px
    one = solve(icp_rounds=1)
    settled = solve(icp_rounds=3, icp_settle_px=first * 1.01)
    assert len(settled.solves) == 1 and settled.association_change_px == pytest.approx((first,))
    np.testing.assert_array_equal(settled.control, one.control)
    assert settled.energies["n_correspondences"] == one.energies["n_correspondences"]
    between = solve(icp_rounds=3, icp_settle_px=(first + second) / 2)
    assert len(between.solves) == 2
    np.testing.assert_allclose(between.control, every.control, atol=0.05)


def test_a_window_started_from_its_solution_needs_fewer_iterations_and_lands_there():
    """solve_window(start=...): started from its own solution the window converges in a few IPOPT iterations to the
    same spline; rows with a NaN start from the fits' spline (all NaN: the cold start exactly); a start of the
    wrong shape is refused, naming both shapes."""
    rec, det, t_det, t_us, S, xy, valid = scene()
    sol = solver(**{"terms.sil.gain": 0.0, "terms.still.gain": 0.0, "icp_rounds": 2})
    spl = UniformCubicBSpline(int(t_det[0]), H_US, sol.layout.n_seg)
    cold = window(sol, spl, det, xy, valid)
    warm = window(sol, spl, det, xy, valid, start=(cold.control, cold.aux))
    assert warm.solves[0].iterations < 0.5 * cold.solves[0].iterations, (warm.solves, cold.solves)
    assert np.abs(warm.control - cold.control).max() < 0.05
    none = np.full_like(cold.control, np.nan)
    again = window(sol, spl, det, xy, valid, start=(none, {k: np.full_like(v, np.nan) for k, v in cold.aux.items()}))
    np.testing.assert_array_equal(again.control, cold.control)
    with pytest.raises(EnergyError, match=r"start: expected control points \(\d+, 33\), got \(3, 33\)"):
        window(sol, spl, det, xy, valid, start=(none[:3], cold.aux))
    with pytest.raises(EnergyError, match=r"joints_3d's auxiliary variables: expected \(4, 3\), got \(3, 3\)"):
        window(sol, spl, det, xy, valid, start=(cold.control, {"joints_3d": cold.aux["joints_3d"][:3]}))


# ------------------------------------------------------------------------------------------------ the stage


class TestSplineStageConformance(StageConformance):
    stage_name = "spline"
    config_overrides = nest(FAST)
    sensitive = ("terms.joints_3d.gain", 0.05)
    insensitive = ("ipopt.max_iter", 50)

    def make_inputs(self):
        return stage_inputs()


def test_stitch_blends_overlapping_windows_without_a_seam():
    """Three windows of a smooth motion over 3 batches (each covering its batch and its neighbours), the middle one
    0.05 rad off and the last one on another 2π branch of the root yaw. Kept per batch they would jump by 0.05 rad
    where the batches meet; blended, no 1 ms step is larger than the motion's own plus the offset spread over the
    overlap, the acceleration stays bounded (C²), and where only one window has weight it is that window."""
    from eventcap.artifacts.pose import PoseSequence
    from eventcap_spline.stitch import smootherstep

    plan = BatchPlan.between_frames(np.array([5_000, 45_000, 85_000, 125_000]))
    t = np.arange(5_000, 125_001, 1_000)
    truth = np.zeros((t.size, 33))
    truth[:, :27] = 0.3 * np.sin(2 * np.pi * 2.0 * t[:, None] * 1e-6 + np.arange(27)[None, :])
    truth[:, 27] = 3.1 + 2.0 * t * 1e-6  # yaw crossing π
    spans = [(5_000, 85_000), (5_000, 125_000), (45_000, 125_000)]
    windows = []
    for k, (a_, b_) in enumerate(spans):
        sel = (t >= a_) & (t <= b_)
        p = truth[sel].copy()
        p[:, :27] += 0.05 if k == 1 else 0.0
        p[:, 27] -= 2 * np.pi if k == 2 else 0.0
        windows.append(PoseSequence(t_us=t[sel], poses=p, status="Solve_Succeeded", iterations=1, energies={}))
    motion, cut, ctx = stitch(windows, plan)
    assert ctx.stats["seam_rad_max"] == pytest.approx(0.05)
    assert motion.t_us.tolist() == t.tolist()
    d1 = np.abs(np.diff(motion.poses, axis=0)).max()
    assert d1 < np.abs(np.diff(truth, axis=0)).max() + 0.05 / 20, d1  # the offset spread over >= 20 ms
    d2 = np.abs(np.diff(motion.poses[:, :27] - truth[:, :27], 2, axis=0)).max()
    assert d2 < 0.05 * 20 / 40**2, d2  # second differences of a smooth 40 ms blend of a 0.05 rad offset
    np.testing.assert_allclose(motion.poses[:, 27], truth[:, 27], atol=1e-12)  # every window on one branch
    # Window ends at the recording's ends are not tapered: at 125 ms windows 1 and 2 weigh 1 each.
    assert motion.poses[-1, 0] == pytest.approx(truth[-1, 0] + 0.05 / 2)
    assert [c.t_us[0] for c in cut] == plan.t0_us.tolist() and cut[1].t_us[-1] == 85_000
    assert cut[0].poses[-1].tolist() == cut[1].poses[0].tolist()
    u = np.linspace(0, 1, 101)
    assert smootherstep(u)[[0, -1]].tolist() == [0.0, 1.0] and np.all(np.diff(smootherstep(u)) >= 0)


def test_stitched_stage_output_is_smooth_where_batches_meet():
    """The three batches of the scene, each solved in its own window task with only its own batch's tracks
    (tracks=own, the default, so the windows differ): after stitch + cut, the largest 1 ms joint step is no larger than inside
    the windows, and batch 0's last frame is batch 1's first."""
    rec = scene()[0]
    outs = []
    for k in (0, 1, 2):
        inputs = stage_inputs()
        out, ctx = run_stage(inputs, inputs["batches"].batch(k), half_window=1)
        outs.append(out["poses"])
        assert ctx.stats["window"] == [0, 2] and out["poses"].status == "Solve_Succeeded"
        assert out["poses"].t_us[0] == 5_000 and out["poses"].t_us[-1] == 125_000  # the whole window
    rest = rec.template.rest_joints
    inside = max(np.linalg.norm(np.diff(joint_positions(o.poses, rest), axis=0), axis=2).max() for o in outs)
    motion, cut, ctx = stitch(outs, stage_inputs()["batches"])
    J = joint_positions(motion.poses, rest)
    assert np.linalg.norm(np.diff(J, axis=0), axis=2).max() <= 1.05 * inside
    assert cut[0].poses[-1].tolist() == cut[1].poses[0].tolist() and cut[2].t_us[-1] == 125_000
    assert ctx.stats["seam_rad_max"] > 0  # the windows did differ


def test_a_window_uses_the_tracks_of_all_its_batches():
    """tracks=window: batch 0's and batch 2's tasks of the same window (batches 0..2) see the same tracks, so they
    solve the same problem to the same curve, with the correspondences of all three batches (about 3x those of one
    batch); with tracks=own (the default) each sees only its own batch's."""
    inputs = stage_inputs()
    plan = inputs["batches"]
    out0, ctx0 = run_stage(inputs, plan.batch(0), half_window=1, **{"tracks.scope": "window"})
    out2, ctx2 = run_stage(inputs, plan.batch(2), half_window=1, **{"tracks.scope": "window"})
    np.testing.assert_array_equal(out0["poses"].poses, out2["poses"].poses)
    own = [run_stage(inputs, plan.batch(k), half_window=1, **{"tracks.scope": "own"})[1].stats["n_correspondences"]
           for k in (0, 1, 2)]
    assert ctx0.stats["n_correspondences"] == pytest.approx(sum(own), rel=0.1), (ctx0.stats, own)
    assert min(own) > 0 and ctx0.stats["n_correspondences"] > 2.5 * max(own)


def test_window_tracks_stacks_each_batch_in_its_own_columns():
    from eventcap_spline.plan import window_tracks

    sliced = stage_inputs()["sliced"]
    t, xy, valid = window_tracks(list(sliced), 4, "batch 1")
    H = [s.xy.shape[1] for s in sliced]
    assert t.tolist() == list(range(5_000, 125_001, 4_000)) and xy.shape == (31, sum(H), 2)
    # batch 1's columns: valid only at its own frames 45..85 ms, where they are its tracks at every 4th frame
    cols = slice(H[0], H[0] + H[1])
    rows = np.flatnonzero(valid[:, cols].any(1))
    assert t[rows].tolist() == list(range(45_000, 85_001, 4_000))
    np.testing.assert_array_equal(valid[rows, cols], sliced[1].valid[::4])
    np.testing.assert_array_equal(xy[rows, cols][valid[rows, cols]], sliced[1].xy[::4][sliced[1].valid[::4]])
    assert np.isnan(xy[~valid]).all()
    # the boundary frame at 45 ms holds batch 0's last and batch 1's first positions
    r = np.searchsorted(t, 45_000)
    assert valid[r, :H[0]].any() and valid[r, cols].any()
    bad = sliced[1].xy.copy()
    bad[3, np.flatnonzero(sliced[1].valid[4])[0]] = np.nan
    bad[4, np.flatnonzero(sliced[1].valid[4])[0]] = np.nan
    with pytest.raises(StageFailed, match="batch 1: a track has a non-finite position where it is marked valid"):
        window_tracks([sliced[0], SimpleNamespace(t_us=sliced[1].t_us, xy=bad, valid=sliced[1].valid)], 4,
                      "batch 1")  # (an artifact would refuse it itself)


def test_the_stage_fits_the_silhouette_at_every_sil_step_of_its_batch(caplog):
    import dataclasses

    from eventcap.artifacts.recording import EventStream

    inputs = stage_inputs()
    rec = inputs["recording"]
    events = EventStream(events=silhouette_events(), width=rec.camera.width, height=rec.camera.height)
    inputs = dict(inputs, recording=dataclasses.replace(rec, events=events))
    b = inputs["batches"].batch(1)
    with caplog.at_level("INFO"):
        out, ctx = run_stage(inputs, b, **{"terms.sil.sigma_px": 1.0, "terms.sil.step_ms": 5.0})
    e = out["poses"].energies
    assert e["n_silhouette"] > 2000 and e["n_boundary"] >= e["n_silhouette"] and e["sil"] > 0
    assert "E_sil at 9 frames" in caplog.text
    off, _ = run_stage(inputs, b, **{"terms.sil.gain": 0.0})
    assert "n_silhouette" not in off["poses"].energies and "sil" not in off["poses"].energies


def test_the_stage_chooses_the_process_power_from_the_fits_around_the_window(caplog):
    """The scene's intensity frames come at 25 fps: smoothing.min_fps 20 chooses each parameter's process power from
    the 7 fits around the window (restricted likelihood; in the stats, within q_max_ratio of its group's, none below
    q_min), 30 does not and says why: every power is then q_default, the same poses as a q_default run without fits."""
    inputs = stage_inputs(n_frames=7)  # 7 frames of context: enough for a smoothing spline (at least 5)
    b = inputs["batches"].batch(3)
    on, ctx_on = run_stage(inputs, b, **{"smoothing.min_fps": 20.0})
    q = np.array(ctx_on.stats["prior_power"])
    assert q.shape == (33,) and np.all(q >= 500.0) and len(np.unique(q)) > 3  # q_min 500
    assert q[:30].max() <= 100.0 * q[:30].min() * 100.0 + 1e-9  # each within 100x of the angles' pooled power
    with caplog.at_level("INFO"):
        off, ctx_off = run_stage(inputs, b, **{"smoothing.min_fps": 30.0, "terms.prior.q_default": 500.0})
    np.testing.assert_allclose(ctx_off.stats["prior_power"], 500.0)
    assert ("batch 3: no smoothing evidence from the fits around the window (no prior gains, no context pull): "
            "intensity frames at 25.0 fps, below stages.solve.smoothing.min_fps (30)") in caplog.text
    assert np.abs(on["poses"].poses - off["poses"].poses).max() > 1e-4
    # what `eventcap run` composes: the power from the fits from 20 fps on, one per parameter, at least 500
    from eventcap.apps.benchmark import compose_run
    from eventcap.apps.cli import config_dir

    data, _ = compose_run(config_dir(), [])
    solve = data["stages"]["solve"]
    assert solve["stage"] == "spline"
    prior = solve["terms"]["prior"]
    assert (prior["pool"], prior["q_default"], prior["q_min"], solve["smoothing"]["min_fps"]) == \
        ("parameter", 5000.0, 500.0, 20.0)


def test_the_context_pull_holds_only_what_the_events_call_still(caplog):
    """still_gate: a parameter is as still as the least still bone it turns, in the knot interval of each time (the
    right elbow's angle by the forearm, the root's by the pelvis, hips and spine). The stage: lambda_context > 0
    pulls (in the stats and the log, frames' worth per parameter >= 0) and changes the poses; below
    prior_gain_min_fps it is off like the gains and the poses equal lambda_context=0's."""
    from eventcap.body.skeleton import JOINT_INDEX
    from eventcap.energy.silence import Silence

    from eventcap.energy.prior import still_gate

    st = np.ones((4, 24))
    st[2, JOINT_INDEX["r_wrist"]] = 0.0
    st[1, JOINT_INDEX["l_hip"]] = 0.25
    sil = Silence(edges_us=np.arange(5, dtype=np.int64) * 10_000, activity_hz=np.zeros((4, 24)), background_hz=0.1,
                  stillness=st)
    gate = still_gate(sil, np.array([5_000, 15_000, 25_000, 39_999, 60_000]), 0.0)
    elbow, shoulder, yaw = DOF_INDEX["r_elbow_flex"], DOF_INDEX["r_shoulder_flex"], 27
    np.testing.assert_array_equal(gate[:, elbow], [1, 1, 0, 1, 1])
    np.testing.assert_array_equal(gate[:, yaw], [1, 0.25, 1, 1, 1])
    np.testing.assert_array_equal(gate[:, DOF_INDEX["l_hip_flex"]], 1.0)  # turns the thigh (the knee's bone)
    assert np.all(gate[:, shoulder] == 1.0) and gate.shape == (5, 33)
    # a floor under the gate: a part the events show moving is still held that fraction (1: no gate)
    floored = still_gate(sil, np.array([5_000, 15_000, 25_000, 39_999, 60_000]), 0.1)
    np.testing.assert_allclose(floored[:, elbow], [1, 1, 0.1, 1, 1])
    np.testing.assert_allclose(floored[:, yaw], [1, 0.325, 1, 1, 1])
    np.testing.assert_array_equal(still_gate(sil, np.array([25_000]), 1.0), 1.0)
    with pytest.raises(ValueError, match=r"still_gate: floor: expected a number in \[0, 1\], got 1.5"):
        still_gate(sil, np.array([25_000]), 1.5)
    inputs = stage_inputs(n_frames=7)  # 6 batches: 7 frames of context, enough for a smoothing spline
    b = inputs["batches"].batch(3)
    with caplog.at_level("INFO"):
        on, ctx_on = run_stage(inputs, b, **{"terms.context.gain": 1.0,
                                              "smoothing.min_fps": 20.0})
    frames = np.array(ctx_on.stats["context_pull_frames"])
    assert frames.shape == (33,) and np.all(frames >= 0) and frames.max() > 0.5
    assert "batch 3: context pull: median" in caplog.text
    plain, _ = run_stage(inputs, b, **{"terms.context.gain": 0.0})
    assert np.abs(on["poses"].poses - plain["poses"].poses).max() > 1e-4
    off, ctx_off = run_stage(inputs, b, **{"terms.context.gain": 1.0,
                                            "smoothing.min_fps": 30.0})
    assert "context_pull_frames" not in ctx_off.stats
    plain_off, _ = run_stage(inputs, b, **{"terms.context.gain": 0.0, "smoothing.min_fps": 30.0})
    np.testing.assert_array_equal(off["poses"].poses, plain_off["poses"].poses)
    with pytest.raises(ValueError, match=r"stages.solve.terms.context.gain: expected a finite number >= 0, "
                                         r"got -1.0"):
        run_stage(inputs, b, **{"terms.context.gain": -1.0})
    # the gate's floor, with a body busy with events everywhere (the scene has none): the events alone (floor 0)
    # hold nothing, a floor of 0.1 holds a tenth of what no gate (1) holds
    import dataclasses

    from eventcap.events import make_events

    rec = inputs["recording"]
    px = rec.camera.project(rec.ground_truth.joints).reshape(-1, 2)
    (x0, y0), (x1, y1) = np.floor(px.min(0)).astype(int) - 8, np.ceil(px.max(0)).astype(int) + 8
    rng = np.random.default_rng(0)
    n = 200_000
    t = np.sort(rng.integers(int(rec.ground_truth.t_us[0]), int(rec.ground_truth.t_us[-1]), n))
    busy = make_events(t, rng.integers(max(x0, 0), min(x1, rec.camera.width), n),
                       rng.integers(max(y0, 0), min(y1, rec.camera.height), n), rng.choice([-1, 1], n))
    inputs["recording"] = dataclasses.replace(rec, events=dataclasses.replace(rec.events, events=busy))
    frames = {}
    for floor in (0.0, 0.1, 1.0):
        _, ctx_f = run_stage(inputs, b, **{"terms.context.gain": 1.0,
                                            "terms.context.gate_floor": floor})
        frames[floor] = np.array(ctx_f.stats["context_pull_frames"])
    assert frames[1.0].max() > 0.5
    np.testing.assert_allclose(frames[0.0], 0.0, atol=1e-6)
    np.testing.assert_allclose(frames[0.1], 0.1 * frames[1.0], rtol=1e-6, atol=1e-9)
    with pytest.raises(ValueError, match=r"stages.solve.terms.context.gate_floor: expected a finite number in "
                                         r"\[0, 1\], got 2"):
        run_stage(inputs, b, **{"terms.context.gate_floor": 2})
    # what `eventcap run` composes: off (the prior's power comes from the same fits)
    from eventcap.apps.benchmark import compose_run
    from eventcap.apps.cli import config_dir

    context = compose_run(config_dir(), [])[0]["stages"]["solve"]["terms"]["context"]
    assert (context["gain"], context["gate_floor"]) == (0.0, 0.1)


def test_a_failed_window_raises_with_the_solver_status():
    inputs = stage_inputs()
    with pytest.raises(StageFailed) as err:
        run_stage(inputs, inputs["batches"].batch(0), **{"ipopt.max_iter": 1})
    assert err.value.status == "Maximum_Iterations_Exceeded" and "window of batches 0..2" in str(err.value)


def test_bad_config_and_missing_detections_are_named():
    inputs = stage_inputs()
    b = inputs["batches"].batch(0)
    # every value outside a field's declared range is refused when the config is built, before the stage runs
    for change, message in (
            ({"knot_ms": 0.0}, r"stages.solve.knot_ms: expected a finite number > 0, got 0.0"),
            ({"stillness.hold_ms": float("nan")}, r"stages.solve.stillness.hold_ms: expected a finite number >= 0, "
                                                  r"got nan"),
            ({"terms.sil.gain": -1.0}, r"stages.solve.terms.sil.gain: expected a finite number >= 0, got -1.0"),
            ({"terms.sil.step_ms": 0.0}, r"stages.solve.terms.sil.step_ms: expected a finite number > 0, got 0.0"),
            ({"terms.cor.loss_scale": -0.5}, r"stages.solve.terms.cor.loss_scale: expected a finite number >= 0, "
                                             r"got -0.5"),
            ({"terms.cor.sigma_px": 0.0}, r"stages.solve.terms.cor.sigma_px: expected a finite number > 0, got 0.0"),
            ({"icp_settle_px": -1.0}, r"stages.solve.icp_settle_px: expected a finite number >= 0, got -1.0"),
            ({"terms.prior.inertia": 1.0}, r"stages.solve.terms.prior.inertia: this setting is now "
                                           r"stages.solve.terms.prior.pool"),
            ({"terms.prior.weight": 1e-3}, r"stages.solve.terms.prior.weight: this setting is now "
                                           r"stages.solve.terms.prior.q_default"),
            ({"terms.prior.q_max_ratio": 0.5}, r"stages.solve.terms.prior.q_max_ratio: expected a finite number "
                                               r">= 1, got 0.5"),
            ({"terms.prior.moving_gain": 2.0}, r"stages.solve.terms.prior.moving_gain: expected a finite number "
                                               r"in \(0, 1\], got 2.0"),
            ({"smoothing.min_fps": -1.0}, r"stages.solve.smoothing.min_fps: expected a finite number >= 0, got -1.0"),
            ({"stillness.rate_hz": 0.0}, r"stages.solve.stillness.rate_hz: expected a finite number > 0, got 0.0"),
            ({"stillness.radius_px": -1}, r"stages.solve.stillness.radius_px: expected an integer >= 0, got -1"),
            ({"stillness.radius_px": 2.5}, r"stages.solve.stillness.radius_px: expected an integer >= 0, got 2.5"),
            ({"lambda_sil": 1.0}, r"stages.solve.lambda_sil: this setting is now stages.solve.terms.sil.sigma_px"),
            ({"terms": 3}, r"stages.solve.terms: a group of settings \(bones, context, cor"),
            ({"terms.sill.weight": 1.0}, r"stages.solve.terms.sill: no config key named 'sill' .*did you mean .*"
                                         r"'sil'")):
        with pytest.raises(ValueError, match=message):
            run_stage(inputs, b, **change)
    # what spans several settings is checked by the stage
    with pytest.raises(StageFailed, match=r"stages.solve.window_step: expected at most max\(1, 2·half_window\) = 2"):
        run_stage(inputs, b, window_step=3)
    # an unknown prior order is refused when the config is built, before anything runs
    with pytest.raises(ValueError, match=r"\.terms\.prior\.order: expected one of acceleration \| jerk, got 'snap'"):
        run_stage(inputs, b, **{"terms.prior.order": "snap"})
    few = dict(inputs, batches=BatchPlan(t0_us=np.array([5_000, 47_000]), t1_us=np.array([47_000, 85_000]),
                                         frame0=np.array([0, 1])))
    with pytest.raises(StageFailed, match="no detection row at t = \\[47000\\]"):
        run_stage(few, few["batches"].batch(0))
    # a unit that is no batch (nor chunk of batches) of the plan is named with the plan's batches
    with pytest.raises(StageFailed, match=r"none of the recording's 2 batches lies in it \(5000\.\.45000 us\)"):
        run_stage(few, b)


def test_the_stage_measures_the_detectors_widths_and_the_floor_once_per_capture_and_says_so(caplog):
    """landmarks=widths: the solve's template has the detector's hip and shoulder widths (the simulated
    detector puts them on the joints: within 10% of the template's), in the stats and the log; the floor terms: the
    floor's height over the capture in the log, near the feet of the actor standing on y = 0 (the soles' landmarks
    are a few centimetres above the mesh's soles)."""
    from eventcap.memo import clear_process_caches

    inputs = stage_inputs()
    b = inputs["batches"].batch(1)
    clear_process_caches()  # the capture's template and floor are measured once per process
    with caplog.at_level("INFO"):
        out, ctx = run_stage(inputs, b, landmarks="widths", icp_rounds=1,
                              **{"terms.floor.gain": 1.0, "terms.slide.gain": 1.0})
    w = ctx.stats["landmark_widths"]
    assert set(w) == {"l_hip-r_hip", "l_shoulder-r_shoulder"} and all(0.9 < v < 1.1 for v in w.values()), w
    assert "where the detector puts the joints, over the capture (stages.solve.landmarks=widths)" in caplog.text
    floor = [r.getMessage() for r in caplog.records if "the floor over the capture" in r.getMessage()]
    assert len(floor) == 1
    y = float(floor[0].split("y = ")[1].split(" m")[0])
    assert -0.05 < y < 0.15, floor
    assert out["poses"].energies["floor"] >= 0.0
