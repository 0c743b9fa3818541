"""The uncertainty in millimetres (eventcap/analysis/uncertainty.py) and how it is judged: the ranking and calibration
measures on cases with known answers, the detections' residuals on exact and moved detections, the pieces of the
model, and the confidence stage's uncertainty on the truth against a motion whose arm is wrong."""

from __future__ import annotations

import numpy as np
import pytest

from eventcap.analysis.uncertainty import (
    UncertaintyModel,
    at_times,
    between_frames,
    confidence_of,
    coverage,
    detection_residuals,
    fill_from_neighbours,
    joined_sigma,
    joint_uncertainty,
    out_of_view,
    sparsification,
    spearman,
)
from eventcap.artifacts.pose import PoseSequence
from eventcap.body.skeleton import JOINT_INDEX, NUM_JOINTS
from helpers.poses import detect, posed_recording
from helpers.spline_scene import EXACT


def test_spearman_sparsification_and_coverage_on_known_rankings():
    rng = np.random.default_rng(0)
    e = rng.gamma(2.0, 20.0, 5000)
    assert spearman(e, e) == pytest.approx(1.0)
    assert spearman(-e, e) == pytest.approx(-1.0)
    oracle = sparsification(e, e)
    assert oracle["ratio"] == pytest.approx(0.0, abs=1e-12) and np.allclose(oracle["curve"], oracle["oracle"])
    rand = sparsification(rng.random(e.size), e)
    assert rand["ratio"] == pytest.approx(1.0, abs=0.1)  # a random order: no better than random
    assert np.isclose(rand["random"][0], e.mean()) and rand["curve"][0] == pytest.approx(e.mean())
    noisy = e * np.exp(rng.normal(0, 0.5, e.size))  # a ranking with noise: in between
    assert 0.0 < sparsification(noisy, e)["ratio"] < 0.6 and 0.5 < spearman(noisy, e) < 1.0
    # calibration: Gaussian 3D errors of per-axis σ: the RMS distance is sqrt(3) σ, and within 2 of it 99.3 % of the
    # time (χ² with 3 degrees of freedom below 12)
    sig = rng.uniform(5, 50, 20000)
    err = np.linalg.norm(rng.normal(0, 1, (sig.size, 3)) * sig[:, None], axis=1)
    assert coverage(np.sqrt(3) * sig, err, 2.0) == pytest.approx(0.9926, abs=0.003)
    assert coverage(sig, err, 1.0) == pytest.approx(0.1987, abs=0.01)  # χ²₃ below 1
    # pairs with a NaN on either side are left out; unequal sizes refused
    assert coverage([1.0, np.nan, 1.0], [0.5, 0.1, 3.0]) == 0.5
    with pytest.raises(ValueError, match="differ in size: 2 and 3"):
        spearman([1, 2], [1, 2, 3])


def test_time_interpolation_and_the_fraction_between_frames():
    t_det = np.array([0, 1000, 2000])
    v = np.array([[10.0, np.nan], [20.0, 4.0], [np.nan, 8.0]])
    got = at_times(np.array([0, 500, 1000, 1500, 2000, 2500]), t_det, v)
    assert np.allclose(got[:, 0], [10, 15, 20, 20, 20, 20])  # held beyond the last frame that has a value
    assert np.allclose(got[:, 1], [4, 4, 4, 6, 8, 8])
    m = between_frames(np.array([-1, 0, 250, 500, 1000, 1750, 2000, 2001]), t_det)
    assert np.allclose(m, [1, 0, 0.75, 1, 0, 0.75, 0, 1])


def test_a_joint_without_a_value_of_its_own_takes_its_neighbours():
    v = np.full((1, NUM_JOINTS), np.nan)
    has = np.zeros(NUM_JOINTS, bool)
    for name, x in (("spine1", 10.0), ("spine3", 30.0), ("l_wrist", 7.0)):
        v[0, JOINT_INDEX[name]] = x
        has[JOINT_INDEX[name]] = True
    out = fill_from_neighbours(v, has)
    assert out[0, JOINT_INDEX["spine2"]] == pytest.approx(20.0)  # between spine1 and spine3
    assert out[0, JOINT_INDEX["l_hand"]] == pytest.approx(7.0)  # its wrist's


def test_the_detections_residuals_are_zero_on_exact_detections_and_the_move_in_mm():
    rec = posed_recording("jumping_jack", n_frames=4, speed=1.0, with_template=True)
    det = detect("simulated", rec, **EXACT)
    gt = rec.ground_truth
    P = gt.poses[np.searchsorted(gt.t_us, det.t_us)]
    r2, r3 = detection_residuals(rec.template, rec.camera, P, det.keypoints_2d, det.observed(), det.joints_3d,
                                 det.confidence_3d)
    assert r2.shape == r3.shape == (det.t_us.size, NUM_JOINTS)
    assert np.nanmax(r2) < 2.0 and np.nanmax(r3) < 1.0  # exact detections: within rounding (float32 pixels)
    # the right wrist's 3D detection 80 mm off, its 2D landmark 10 px off: those joints' residuals say so in mm
    j3 = det.joints_3d.copy()
    w = JOINT_INDEX["r_wrist"]
    j3[:, w, 0] += 0.08
    kp = det.keypoints_2d.copy()
    from eventcap.body.skeleton import LANDMARK_INDEX

    kp[:, LANDMARK_INDEX["r_wrist"], 0] += 10.0
    r2m, r3m = detection_residuals(rec.template, rec.camera, P, kp, det.observed(), j3, det.confidence_3d)
    seen = det.observed()[:, LANDMARK_INDEX["r_wrist"]]
    z = rec.camera.depth(gt.joints[np.searchsorted(gt.t_us, det.t_us), w])
    want2 = 10.0 * z / (0.5 * (rec.camera.fx + rec.camera.fy)) * 1000.0
    assert np.allclose(r2m[seen, w], want2[seen], rtol=0.05, atol=1.0)
    # the best translation takes 1/24 of the move (its mean over the detected joints): the rest is the residual
    assert np.allclose(r3m[:, w], 80.0 * (1 - 1 / 24), atol=1.5)
    others = [j for j in range(NUM_JOINTS) if j != w]
    assert np.nanmax(r3m[:, others]) < 80.0 / 24 + 1.0
    # a frame without an estimate has no residual; nor does an undetected joint
    P2 = P.copy()
    P2[1] = np.nan
    c3 = det.confidence_3d.copy()
    c3[:, JOINT_INDEX["head"]] = 0.0
    r2n, r3n = detection_residuals(rec.template, rec.camera, P2, det.keypoints_2d, det.observed(), det.joints_3d, c3)
    assert np.isnan(r2n[1]).all() and np.isnan(r3n[1]).all() and np.isnan(r3n[:, JOINT_INDEX["head"]]).all()


def test_the_uncertainty_adds_its_parts_as_variances_and_out_of_view_raises_it():
    m = UncertaintyModel(scale=0.5, detection_2d=1.0, detection_3d=0.5, events=0.0, unseen_mm=150.0, floor_mm=5.0,
                         fallback_mm=80.0)
    T = 3
    sig = np.full((T, NUM_JOINTS), 60.0)
    sig[1, 0] = np.nan  # none from the solve: the fallback stands for it
    r2 = np.full((T, NUM_JOINTS), np.nan)
    r2[:, 1] = 40.0
    r3 = np.zeros((T, NUM_JOINTS))
    r3[:, 2] = 80.0
    est = np.array([True, True, False])
    u = joint_uncertainty(m, sig, r2, r3, np.zeros((T, NUM_JOINTS)), est)
    assert u[0, 0] == pytest.approx(np.hypot(30.0, 5.0))
    assert u[1, 0] == pytest.approx(np.hypot(80.0, 5.0))
    assert u[0, 1] == pytest.approx(np.sqrt(30.0 ** 2 + 40.0 ** 2 + 5.0 ** 2))
    assert u[0, 2] == pytest.approx(np.sqrt(30.0 ** 2 + 40.0 ** 2 + 5.0 ** 2))
    assert np.isnan(u[2]).all()  # a gap: no estimate, no uncertainty
    seen = np.ones((T, NUM_JOINTS), bool)
    seen[0, 3] = False
    v = out_of_view(u, seen, m.unseen_mm)
    assert v[0, 3] == pytest.approx(np.hypot(u[0, 3], 150.0)) and v[0, 0] == u[0, 0] and np.isnan(v[2]).all()
    seen[0, 4] = False  # out of view, ranked by its own: the one with the larger σ stays the more uncertain
    u[0, 4] = 2.0 * u[0, 3]
    v = out_of_view(u, seen, m.unseen_mm)
    assert v[0, 4] > v[0, 3] > 150.0
    c = confidence_of(v, 100.0)
    assert c[0, 3] < 0.5 < c[0, 0] and np.all(c[2] == 0.0)
    assert confidence_of(np.array([100.0]), 100.0)[0] == pytest.approx(0.5)


def test_the_solves_sigma_is_joined_over_batches_as_the_poses_are():
    a = PoseSequence(t_us=np.array([0, 1000, 2000]), poses=np.zeros((3, 33)),
                     sigma_mm=np.full((3, 24), 10.0, np.float32))
    b = PoseSequence(t_us=np.array([2000, 3000]), poses=np.zeros((2, 33)), sigma_mm=np.full((2, 24), 30.0, np.float32))
    c = PoseSequence(t_us=np.array([3000, 4000]), poses=np.zeros((2, 33)))  # a solve without σ
    t = np.array([0, 1000, 2000, 3000, 4000])
    got = joined_sigma([b, a, c], t)
    assert got[:, 0].tolist()[:3] == [10.0, 10.0, 30.0]  # the shared frame: the later batch's, as join_batches
    assert np.isnan(got[3:]).all()
    assert joined_sigma([c], t[3:]) is None


def test_the_bodys_uncertainty_is_its_rest_spread_carried_to_the_posed_joints_less_the_alignment():
    """A body estimated from the detections (Template.rest_spread): a spread that only moves the whole skeleton
    adds nothing (the rigid alignment takes it away); a 1 % uniform scale adds 1 % of each joint's distance from
    the joints' mean, posed; the parts add as variances; an exact body adds nothing."""
    import dataclasses

    from eventcap.analysis.uncertainty import body_mm
    from eventcap.body.anny import anny_template
    from eventcap.body.kinematics import joint_positions
    from eventcap.body.motions import motion_poses

    tpl = anny_template()
    P = motion_poses("karate_kick", np.arange(5) / 25.0, seed=0, template=tpl)
    P[2] = np.nan  # a gap
    assert body_mm(tpl, P) is None
    move = np.broadcast_to(np.array([0.01, 0.02, -0.01]), (24, 3))
    assert np.nanmax(body_mm(dataclasses.replace(tpl, rest_spread=move[None]), P)) < 1e-6
    grow = 0.01 * (tpl.rest_joints - tpl.rest_joints[0])
    got = body_mm(dataclasses.replace(tpl, rest_spread=grow[None]), P)
    assert np.isnan(got[2]).all()
    ok = np.array([0, 1, 3, 4])
    J = joint_positions(P[ok], tpl)
    want = 10.0 * np.linalg.norm(J - J.mean(axis=1, keepdims=True), axis=-1)  # 1 % of the distance, mm
    assert np.allclose(got[ok], want, rtol=1e-6)
    both = body_mm(dataclasses.replace(tpl, rest_spread=np.stack([grow, grow])), P)
    assert np.allclose(both[ok], np.sqrt(2) * want)
    m = UncertaintyModel(scale=1.0, detection_2d=0.0, detection_3d=0.0, events=0.0, unseen_mm=300.0, floor_mm=0.0,
                         fallback_mm=80.0, body=1.0)
    sig = np.full((5, NUM_JOINTS), 30.0)
    z = np.zeros((5, NUM_JOINTS))
    est = np.isfinite(P).all(axis=1)
    u = joint_uncertainty(m, sig, z, z, z, est, got)
    assert np.allclose(u[ok], np.hypot(30.0, want))
    assert np.allclose(joint_uncertainty(dataclasses.replace(m, body=0.0), sig, z, z, z, est, got)[ok], 30.0)


def test_the_motion_between_the_frames_is_each_joints_move_over_its_interval_less_the_bodys():
    """A body that only translates moves no joint relative to the joints' mean (the rigid alignment takes it): step 0;
    a turned arm moves its hand by the chord of the turn over the interval it turns in, and 4τ(1 - τ) is 0 at the
    frames and 1 half way."""
    from eventcap.analysis.uncertainty import motion_mm
    from eventcap.body.kinematics import joint_positions
    from eventcap.body.skeleton import DOF_INDEX, JOINT_INDEX
    from helpers.poses import posed_recording

    tpl = posed_recording("jumping_jack", n_frames=4, speed=1.0, with_template=True).template
    t = np.arange(0, 201_000, 1_000, dtype=np.int64)
    P = np.zeros((t.size, 33))
    P[:, 30] = np.linspace(0.0, 0.5, t.size)  # the root moves 0.5 m (S[30:33]: its translation)
    t_det = np.array([0, 100_000, 200_000])
    m, step = motion_mm(tpl, t, P, t_det)
    assert m.shape == (t.size,) and step.shape == (t.size, 24)
    assert m[0] == m[100] == m[200] == 0.0 and m[50] == pytest.approx(1.0) and m[150] == pytest.approx(1.0)
    assert np.allclose(step, 0.0, atol=1e-6)
    Q = np.zeros((t.size, 33))
    Q[100:, DOF_INDEX["r_shoulder_flex"]] = np.linspace(0.0, 1.0, 101)  # the arm turns in the second interval only
    _, step = motion_mm(tpl, t, Q, t_det)
    J0, J1 = joint_positions(Q[[100, 200]], tpl)
    rel0, rel1 = J0 - J0.mean(axis=0), J1 - J1.mean(axis=0)
    hand = JOINT_INDEX["r_hand"]
    assert np.allclose(step[:100], 0.0, atol=1e-6)
    assert step[150, hand] == pytest.approx(np.linalg.norm(rel1[hand] - rel0[hand]) * 1000.0, rel=1e-6)
    assert step[150, hand] > 100.0
    P[60:70] = np.nan  # no estimate: NaN there
    _, step = motion_mm(tpl, t, P, t_det)
    assert np.isnan(step[60:70]).all() and np.isfinite(step[100:]).all()


def test_the_detector_kind_is_the_word_before_the_colon_and_a_table_gives_its_entry_or_the_default():
    from eventcap.analysis.uncertainty import CALIBRATED, calibration, detector_kind

    assert detector_kind("blazepose: BlazePose GHUM 3D full on latent images") == "blazepose"
    assert detector_kind("simulated: ground-truth projections") == "simulated"
    assert detector_kind("file: a.json (openpose, layout body25)") == "file" and detector_kind("") == ""
    entry = {k: 1.0 for k in CALIBRATED}
    table = {"default": "simulated", "detectors": {"simulated": entry, "blazepose": {**entry, "scale": 2.0}}}
    none = {"factor_by_fps": [], "factor_by_view": {}}
    assert calibration(table, "blazepose") == ("blazepose", {**entry, "scale": 2.0, **none})
    assert calibration(table, "file") == ("simulated", {**entry, **none})
    with pytest.raises(ValueError, match=r"kind 'blazepose': trusted_mm must be a number >= 0, got None"):
        calibration({"detectors": {"blazepose": {**entry, "trusted_mm": None}}}, "blazepose")


def test_the_view_is_event_only_without_frames_and_a_close_up_below_the_share_in_the_image():
    from eventcap.analysis.uncertainty import CLOSE_UP_SHARE, view_of

    assert view_of(None, 1.0) == view_of(float("nan"), 0.3) == view_of(0.0, 1.0) == "event_only"
    assert view_of(25.0, 1.0) == view_of(10.0, CLOSE_UP_SHARE) == "whole_frames"
    assert view_of(25.0, CLOSE_UP_SHARE - 0.01) == view_of(10.0, 0.0) == "close_up"


def test_a_calibration_by_frame_rate_is_interpolated_in_log_fps_and_bad_rates_are_named():
    """factor_by_fps: each rate's factor on the kind's parts; between two calibrated rates linear in log(fps), the
    nearest one's beyond them, 1 (the pooled) for a capture without intensity frames or a table without rates."""
    from eventcap.analysis.uncertainty import CALIBRATED, calibration, frame_rate, rate_factor

    entry = {**{k: 1.0 for k in CALIBRATED}, "factor_by_fps": {"25": 1.1, "10": 0.9}}
    _, cal = calibration({"detectors": {"simulated": entry}}, "simulated")
    points = cal["factor_by_fps"]
    assert points == [(10.0, 0.9), (25.0, 1.1)]
    assert rate_factor(points, 10.0) == pytest.approx(0.9) and rate_factor(points, 25.0) == pytest.approx(1.1)
    mid = np.sqrt(10.0 * 25.0)  # half way in log fps
    assert rate_factor(points, mid) == pytest.approx(1.0)
    assert rate_factor(points, 5.0) == pytest.approx(0.9) and rate_factor(points, 100.0) == pytest.approx(1.1)
    assert rate_factor(points, None) == 1.0 and rate_factor([], 25.0) == 1.0
    assert frame_rate(np.arange(5) * 40_000 + 7) == pytest.approx(25.0) and frame_rate([3]) is None
    for bad in ({"fast": 1.0}, {"10": 0.0}, {"-5": 1.0}, {"10": True}):
        with pytest.raises(ValueError, match="factor_by_fps expects frame rates > 0"):
            calibration({"detectors": {"simulated": {**entry, "factor_by_fps": bad}}}, "simulated")
