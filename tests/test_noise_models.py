"""Noise models instead of tuned weights (issue "the events add"): the one loss module, how a detector's noise model
weighs its observations (white noise per image, an offset per capture), the motion prior's process power chosen by
the restricted likelihood with the fits' noise known, the detectors stating their noise, and the old weights refused
with their new names."""

from __future__ import annotations

import math

import numpy as np
import pytest

from eventcap.analysis.smoothing import GcvCurve
from eventcap.energy import loss
from eventcap.energy.detections import DetectionWeights, FrameDetections
from eventcap.energy.prior import process_noise
from eventcap.energy.settings import CorNoise, Joints3DNoise, Landmarks2DNoise, SilNoise
from eventcap.energy.terms import FACTORS


# -- the loss module ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", loss.LOSSES)
def test_every_loss_is_quadratic_for_inliers_and_its_derivatives_match_finite_differences(kind):
    """rho(s) ~ s near 0 for every loss; rho' and rho'' against central differences in s; the residual form's
    derivatives in r against differences in r; Huber grows linearly in |r| beyond its scale, Cauchy
    logarithmically."""
    a = 2.0
    s = np.array([1e-4, 0.3, 1.7, 3.9, 4.1, 9.0, 30.0])
    v, d1, d2 = loss.rho(s, kind, a)
    h = 1e-6
    vp, d1p, _ = loss.rho(s + h, kind, a)
    vm, d1m, _ = loss.rho(s - h, kind, a)
    np.testing.assert_allclose(d1, (vp - vm) / (2 * h), rtol=1e-5, atol=1e-9)
    np.testing.assert_allclose(d2, (d1p - d1m) / (2 * h), rtol=1e-4, atol=1e-7)
    assert v[0] == pytest.approx(s[0], rel=1e-4)
    r = np.array([-7.0, -2.5, -0.3, 0.4, 1.9, 2.1, 6.0])
    f, g, H = loss.residual_loss(r, kind, a)
    fp, gp, _ = loss.residual_loss(r + h, kind, a)
    fm, gm, _ = loss.residual_loss(r - h, kind, a)
    np.testing.assert_allclose(g, (fp - fm) / (2 * h), rtol=1e-5, atol=1e-8)
    np.testing.assert_allclose(H, (gp - gm) / (2 * h), rtol=1e-4, atol=1e-6)
    big = loss.rho(np.array([100.0**2]), kind, a)[0][0]
    expect = {"l2": 1e4, "huber": 2 * a * 100 - a * a, "cauchy": a * a * math.log1p(1e4 / (a * a))}[kind]
    assert big == pytest.approx(expect)
    with pytest.raises(ValueError, match=r"loss: expected one of l2, huber, cauchy, got 'tukey'"):
        loss.rho(s, "tukey")


def test_the_irls_weight_is_the_loss_slope():
    s = np.array([0.0, 1.0, 9.0, 100.0])
    np.testing.assert_allclose(loss.irls_weight(s, "cauchy", 1.0), 1.0 / (1.0 + s))
    np.testing.assert_allclose(loss.irls_weight(s, "l2"), 1.0)


# -- a detector's noise model weighs its observations -------------------------------------------------------------
def _frames(n: int, white_px: float, bias_px: float, white_m: float, bias_m: float) -> FrameDetections:
    rng = np.random.default_rng(0)
    return FrameDetections(rng.uniform(0, 100, (n, 25, 2)), np.ones((n, 25)), rng.normal(0, 0.3, (n, 24, 3)),
                           np.ones((n, 24)), np.full((n, 25), white_px), np.full((n, 24, 3), white_m),
                           np.full(25, bias_px), np.full((24, 3), bias_m))


def test_white_noise_counts_per_image_a_capture_offset_once():
    """A landmark seen in n frames with white noise w and a capture offset of spread b weighs 1 / (2 (w² + n b²)) per
    px² in each: the n frames together then weigh 1 / (2 (w² / n + b²)), the precision of their mean (n images tell
    the white noise n times over, the offset once). A per-frame fit (counts None) takes w² + b². The floor holds a
    stated noise of 0 at the skeleton's own error; the Cauchy scale is loss_scale sigmas."""
    det = _frames(10, 0.7, 1.6, 0.02, 0.05)
    w = DetectionWeights(1.0, 1.0, Landmarks2DNoise(), Joints3DNoise(), focal2=200.0**2)
    counts = det.observed_counts()
    assert counts[0].tolist() == [10] * 25 and counts[1].tolist() == [10] * 24
    kp, w2, s2, j3, w3 = w.values(det, 3, counts)
    assert w2[0] == pytest.approx(0.5 / (0.7**2 + 10 * 1.6**2))
    assert w3[5] == pytest.approx(0.5 / (0.02**2 + 10 * 0.05**2))
    assert s2[0] == pytest.approx(9.0 * (0.7**2 + 10 * 1.6**2))  # (3 sigma)²
    assert 10 * w2[0] == pytest.approx(0.5 / (0.7**2 / 10 + 1.6**2))
    _, w2_fit, _, _, w3_fit = w.values(det, 3)
    assert w2_fit[0] == pytest.approx(0.5 / (0.7**2 + 1.6**2)) and w3_fit[5] == pytest.approx(0.5 / (0.02**2 + 0.05**2))
    _, w2_white, _, _, _ = w.values(det, 3, (np.zeros(25), np.zeros(24)))
    assert w2_white[0] == pytest.approx(0.5 / 0.7**2)
    exact = _frames(4, 0.0, 0.0, 0.0, 0.0)
    _, w2, s2, _, w3 = w.values(exact, 0, exact.observed_counts())
    assert w2[0] == pytest.approx(0.5 / 0.5**2) and w3[3] == pytest.approx(0.5 / 0.005**2)  # the floors
    # an unobserved landmark weighs nothing, whatever its noise
    det.confidence_2d[3, 7] = 0.0
    assert w.values(det, 3, det.observed_counts())[1][7] == 0.0
    # a stated sigma overrides the detector's; without either the term names the setting
    w_fixed = DetectionWeights(1.0, 1.0, Landmarks2DNoise(sigma_px=4.0), Joints3DNoise(sigma_mm=80.0))
    _, w2, _, _, w3 = w_fixed.values(det, 0, det.observed_counts())
    assert w2[0] == pytest.approx(0.5 / 16.0) and w3[1] == pytest.approx(0.5 / 0.08**2)
    bare = FrameDetections(det.keypoints_2d, det.confidence_2d, det.joints_3d, det.confidence_3d)
    with pytest.raises(Exception, match=r"the detections state no 2D noise model: set stages.solve.terms."
                                        r"landmarks_2d.sigma_px"):
        w.values(bare, 0)


def test_the_paper_weights_are_kept_as_they_were():
    """A weighted E_2D (the paper's batch solve) weighs a landmark c / f² per px² with the Cauchy scale robust_px:
    the same energy as the focal-normalised residual's, λ c (r / f)²."""
    from eventcap.energy.settings import Joints3DConfig, Landmarks2DConfig
    from types import SimpleNamespace

    terms = SimpleNamespace(landmarks_2d=Landmarks2DConfig(weight=200.0, robust_px=2.0),
                            joints_3d=Joints3DConfig(weight=1.0))
    cam = SimpleNamespace(fx=199.0, fy=198.0)
    w = DetectionWeights.from_terms(terms, cam)
    assert (w.lam2, w.lam3, w.robust_px) == (200.0, 1.0, 2.0) and w.noise2 is None
    det = _frames(3, 1.0, 1.0, 0.01, 0.01)
    det.confidence_2d[1] = 0.5
    _, w2, s2, _, w3 = w.values(det, 1, det.observed_counts())
    assert w2[0] == pytest.approx(0.5 / (199.0 * 198.0)) and s2[0] == 4.0 and w3[0] == 1.0


def test_each_noise_modelled_term_weighs_its_residuals_by_its_sigma():
    """The factors whose noise is one number convert it into the precision of their residuals' units: E_cor and
    E_sil on focal-normalised residuals (½ f² / σ_px²); a gain multiplies it; gain 0 leaves a term out."""
    from types import SimpleNamespace

    cam = SimpleNamespace(fx=200.0, fy=200.0)
    assert FACTORS["cor"].noise_precision(CorNoise(sigma_px=2.0), cam) == pytest.approx(0.5 * 200.0**2 / 4.0)
    assert FACTORS["sil"].noise_precision(SilNoise(sigma_px=4.0), cam) == pytest.approx(0.5 * 200.0**2 / 16.0)
    from eventcap.energy.terms import term_configs
    from eventcap_spline.spec import SplineTerms

    terms = SplineTerms()
    terms.cor.gain = 0.0
    assert "cor" not in [name for name, _, _ in term_configs(terms)]


# -- the prior's process power --------------------------------------------------------------------------------------
def _iwp(q: float, t: np.ndarray, rng) -> np.ndarray:
    """Samples of a white-noise acceleration (integrated Wiener) process of power q at times t (s)."""
    x, v, out = 0.0, 0.0, [0.0]
    for h in np.diff(t):
        cov = q * np.array([[h**3 / 3, h**2 / 2], [h**2 / 2, h]])
        dx, dv = rng.multivariate_normal([v * h, 0.0], cov)
        x, v = x + dx, v + dv
        out.append(x)
    return np.array(out)


def test_the_restricted_likelihood_recovers_a_motions_power():
    """Fits of white-noise-acceleration motions of power q, sampled at 25 Hz for 4 s with white noise: the chosen
    power is within a factor 3 of q pooled over 30 parameters; with noise-free samples it is the samples' own
    roughness; fits that are noise about a still pose call for almost none."""
    rng = np.random.default_rng(3)
    t = np.arange(100) * 0.04
    t_us = (t * 1e6).astype(np.int64)
    for q in (0.5, 50.0):
        Y = np.stack([_iwp(q, t, rng) for _ in range(33)], axis=1)
        pn = process_noise(t_us, Y + rng.normal(0, 0.01, Y.shape), pool="group")
        assert q / 3 < pn.q[0] < 3 * q and pn.n_fits == 100
        exact = process_noise(t_us, Y, pool="group")
        assert q / 3 < exact.q[0] < 3 * q
    still = process_noise(t_us, rng.normal(0, 0.05, (100, 33)), pool="group")
    assert np.all(still.q < 1e-2)
    assert process_noise(np.arange(4) * 40_000, np.zeros((4, 33))).q is None  # too few fits


def test_a_parameters_power_stays_within_its_groups_range():
    rng = np.random.default_rng(4)
    t = np.arange(50) * 0.04
    t_us = (t * 1e6).astype(np.int64)
    Y = np.stack([_iwp(5.0, t, rng) for _ in range(33)], axis=1)
    Y[:, 7] = 0.0  # a parameter that never moves
    pn = process_noise(t_us, Y, pool="parameter", max_ratio=100.0)
    group = process_noise(t_us, Y, pool="group").q[0]
    assert pn.q[7] == pytest.approx(group / 100.0, rel=1e-6) and group / 3 < pn.q[0] < 3 * group


def test_the_power_is_the_restricted_likelihoods_noise_over_the_smoothing():
    """GcvCurve.power at lam: sigma² / lam with sigma² the profile REML estimate (the penalised components' z_i²
    scaled by lam d_i / (1 + lam d_i), averaged), checked against the formula by hand on 9 uneven samples."""
    t = np.sort(np.random.default_rng(5).uniform(0, 1, 9))
    curve = GcvCurve(t)
    y = np.sin(3 * t)[:, None]
    pen = curve.d > 1e-9 * curve.d.max()
    z2 = (curve.U.T @ y[:, 0]) ** 2
    for lam in (1e-6, 1e-3, 1.0):
        sigma2 = np.mean(z2[pen] * lam * curve.d[pen] / (1 + lam * curve.d[pen]))
        assert curve.power(y, np.array([lam]))[0] == pytest.approx(sigma2 / lam, rel=1e-9)


def test_blazepose_states_its_measured_noise_per_image_kind_and_camera_axis(tmp_path):
    """The detector's table (models/blazepose_noise.json, measured by benchmarks/accuracy/detector_noise.py): 2D white
    noise per landmark, the capture's offset apart; 3D an effective figure per joint and camera axis, the pelvis
    exact (the measured 3D kept beside: depth, z, is BlazePose's worst axis); latent images between the frames take
    the latent figures, images made from the events their own (the raw frames' where it has none); a kind the table
    lacks is named."""
    import json

    from eventcap_detect._impl import blazepose_noise
    from eventcap_detect.spec import SHIPPED_NOISE

    frames = np.array([0, 100_000, 200_000])
    m = blazepose_noise("tracking", np.array([0, 50_000, 100_000]), frames)
    assert m.sigma_2d_px.shape == (3, 25) and m.sigma_3d_m.shape == (3, 24, 3)
    assert m.bias_2d_px.shape == (25,) and m.bias_3d_m.shape == (24, 3)
    np.testing.assert_array_equal(m.sigma_3d_m[:, 0], 0.0)
    np.testing.assert_array_equal(m.bias_3d_m[0], 0.0)
    np.testing.assert_array_equal(m.sigma_3d_m[1], m.sigma_3d_m[0])  # between = latent
    assert 0.1 < np.median(m.sigma_2d_px) < 3.0 and 0.3 < np.median(m.bias_2d_px) < 5.0
    # the 3D: an effective figure (no offset); the measured ones kept beside, depth the worst axis
    np.testing.assert_allclose(m.sigma_3d_m[:, 1:], 0.745)
    np.testing.assert_array_equal(m.bias_3d_m, 0.0)
    table = json.loads(SHIPPED_NOISE.read_text())
    bias = np.array(table["measured_3d"]["bias_3d_mm"]["latent"])[1:]
    assert np.median(bias[:, 2]) > 2 * np.median(bias[:, :2])
    # images made from the events (an event-only camera): their own figures where the table measures them, else the
    # raw frames'
    events = blazepose_noise("frames", frames, np.zeros(0, np.int64), event_images=True)
    want = "events" if "events" in table["landmarks_2d_px"] else "frames"
    inflate = np.sqrt(table["inflation_2d"][want])
    np.testing.assert_allclose(events.sigma_2d_px[0], np.array(table["landmarks_2d_px"][want]) * inflate)
    np.testing.assert_allclose(events.bias_2d_px, np.array(table["bias_2d_px"][want]) * inflate)
    no_events = {k: ({kk: vv for kk, vv in v.items() if kk != "events"} if isinstance(v, dict) else v)
                 for k, v in table.items()}
    no_events["landmarks_2d_px"]["frames"] = [9.0] * 25
    plain = tmp_path / "plain.json"
    plain.write_text(json.dumps(no_events))
    m = blazepose_noise("frames", frames, np.zeros(0, np.int64), plain, event_images=True)
    np.testing.assert_allclose(m.sigma_2d_px, 9.0 * np.sqrt(table["inflation_2d"]["frames"]))
    del table["landmarks_2d_px"]["frames"]
    bad = tmp_path / "noise.json"
    bad.write_text(json.dumps(table))
    with pytest.raises(ValueError, match=r"noise.json: landmarks_2d_px: no figure for the 'frames' images "
                                         r"\(expected one of \['events', 'latent'\]\)"):
        blazepose_noise("frames", frames, frames, bad)


def test_blazepose_noise_table_is_in_the_detect_stage_key_and_a_table_given_is_stated(tmp_path):
    """The table the detections state their noise from is part of the stage's cache key (a changed table detects
    again); a table given in the config (stages.detect.noise) is the one read."""
    import json

    from eventcap.core.config import build_config, file_digests
    from eventcap.core.registry import load_registry
    from eventcap_detect._impl import blazepose_noise
    from eventcap_detect.spec import SHIPPED_NOISE, noise_files

    spec = load_registry().get("blazepose")
    table = json.loads(SHIPPED_NOISE.read_text())
    a = file_digests(spec, build_config(spec, {}, "stages.detect"), "stages.detect")
    other = tmp_path / "noise.json"
    table["landmarks_2d_px"]["latent"] = [5.0] * 25
    other.write_text(json.dumps(table))
    b = file_digests(spec, build_config(spec, {"noise": str(other)}, "stages.detect"), "stages.detect")
    assert set(a) == set(b) == {"noise"} and a != b
    assert noise_files("shipped") == [str(SHIPPED_NOISE)]
    frames = np.array([0, 100_000])
    m = blazepose_noise("latent", frames, frames, noise_files(str(other))[0])
    np.testing.assert_allclose(m.sigma_2d_px, 5.0 * np.sqrt(table["inflation_2d"]["latent"]))
