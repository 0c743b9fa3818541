"""The person's body from the detections (issues 43 and 54; eventcap/body/proportions.py, stage proportions).

On detections of an ANNY actor who is not the template (its 2D points projected, its 3D joints as they are, or
with a simulated detector's errors): the floor gives the pelvis's depth from the sole points at the ankle; the
stature and each segment come with a standard error, and move from the template's only as far as their evidence
weighs against the prior of human proportions (a quarter second of a noisy detector barely moves them, more images
move them further and narrow their SD); a stated height is kept and the proportions fitted at it; a stated body is
kept whole; the log says what moved, by how much, on what evidence, and why the rest did not; the body's posterior
is carried to its rest joints (``Template.rest_spread``); evaluate measures the body's segments against the truth
beside the stated template's."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import pytest

from eventcap.artifacts.pose import Detections
from eventcap.artifacts.recording import EventStream, GroundTruth, Recording
from eventcap.body.anny import anny_rest_joints, anny_template
from eventcap.body.kinematics import joint_positions, landmark_positions
from eventcap.body.motions import motion_poses
from eventcap.body.proportions import (
    DETECTOR_DEFINITIONS,
    DETECTOR_SPREAD,
    KINDS,
    PHENOTYPE_SD,
    SEGMENTS,
    STATURE_SD_M,
    DetectorSpread,
    fit_body,
    floor_depths,
    foot_geometry,
    image_noise,
    rest_spread,
    seen_segments,
    segment_lengths,
)
from eventcap.camera import Camera, look_at
from eventcap.core.stage import StageContext
from eventcap.core.testing import StageConformance
from eventcap.events import EVENT_DTYPE

ACTOR = dict(height_m=1.62, build=0.3, muscle=0.4, sex=-0.7)
START = dict(height_m=1.75, build=0.0, muscle=0.0, sex=0.0)
#: What exact projections share within a capture: next to nothing.
EXACT = DetectorSpread(segment={k: 0.01 for k in KINDS}, floor=0.005)
TEMPLATE = anny_template()
FEET = foot_geometry(TEMPLATE.rest_joints, TEMPLATE.rest_landmarks)


def camera(height_m: float, distance_m: float = 3.5, size=(640, 480), f=500.0) -> Camera:
    R, t = look_at((0.0, height_m, distance_m), (0.0, 0.9, 0.0))
    return Camera(size[0], size[1], f, f, (size[0] - 1) / 2, (size[1] - 1) / 2, np.zeros(5), R, t)


@pytest.fixture(scope="module")
def actor():
    body = anny_template(**ACTOR, seed=2)
    t = np.arange(25) / 25.0
    S = motion_poses("jumping_jack", t, seed=1, template=body)
    return body, t, S


def detections(body, S, cam, t, noise: np.random.Generator | None = None, px=2.0, bias_m=0.04, sigma_m=0.025):
    """Exact detections of the body posed by S (2D projected, 3D root-relative in world axes), or with a simulated
    detector's errors (``noise``): 2D Gaussian px per axis, a fixed 3D offset per joint and per-image 3D noise."""
    L = landmark_positions(S, body)
    J = joint_positions(S, body.rest_joints)
    n = S.shape[0]
    kp, j3 = cam.project(L), J - J[:, :1]
    if noise is not None:
        kp = kp + noise.normal(0.0, px, kp.shape)
        off = noise.normal(0.0, bias_m, (24, 3))
        j3 = j3 + off + noise.normal(0.0, sigma_m, j3.shape)
        j3 = j3 - j3[:, :1]
    return Detections(t_us=(np.asarray(t) * 1e6).astype(np.int64), keypoints_2d=kp.astype(np.float32),
                      confidence_2d=np.ones(L.shape[:2], np.float32), joints_3d=j3,
                      confidence_3d=np.ones((n, 24), np.float32), detector="exact projections (test)")


def err_cm(rest, truth=ACTOR) -> float:
    truth = segment_lengths(anny_rest_joints(**truth))
    got = segment_lengths(rest)
    return 100 * float(np.median([abs(got[k] - truth[k]) for k in SEGMENTS]))


def args(det):
    return det.keypoints_2d, det.confidence_2d, det.joints_3d, det.confidence_3d


def test_the_floor_gives_the_pelvis_depth_from_the_sole_points_at_the_ankle(actor):
    body, _, _ = actor
    t = np.arange(25) / 25.0
    S = motion_poses("karate_kick", t, seed=0, template=body)  # one foot on the floor throughout
    cam = camera(1.6)
    det = detections(body, S, cam, t)
    fz = floor_depths(cam, *args(det), foot_geometry(body.rest_joints, body.rest_landmarks))
    truth = cam.to_camera(joint_positions(S, body.rest_joints)[:, 0])[:, 2]
    # the heels and big toes lie 6 and 21 cm behind and ahead of the ankle: their mean alone put the person 2-3 %
    # nearer (the stature 2-3 % short); from the ankle the depth is right to a few mm
    assert np.isfinite(fz).all() and np.max(np.abs(fz / truth - 1)) < 0.005, np.abs(fz / truth - 1).max()


def test_an_image_counts_as_much_as_its_noise_allows():
    g = image_noise(np.array([10.0, 20.0, 40.0, 40.0]), np.array([1.0, 1.0, 1.0, 0.7]))
    assert g[0] == pytest.approx(2 * g[1]) and g[1] == pytest.approx(2 * g[2])  # 2D points' error over the length
    assert g[3] > 3 * g[2]  # out of the image plane (tan 45.6 deg ~ 1.02), the 3D direction's error dominates


def test_exact_detections_give_the_actors_body_within_its_standard_errors(actor):
    body, t, S = actor
    cam = camera(1.6)
    det = detections(body, S, cam, t)
    seen = seen_segments(cam, *args(det))
    assert all(len(seen.image[n]) >= 3 for n in ("l_thigh", "r_thigh", "shoulders", "hips"))
    fz = floor_depths(cam, *args(det), FEET)
    est = fit_body(seen, START, ("height_m", "sex", "muscle"), floor_z=fz, camera_height_m=1.6, spread=EXACT)
    assert est.scale_from == "floor" and est.estimated == ("height_m", "sex", "muscle")
    sd = est.sd("height_m")
    assert 0.005 < sd < 0.03 and abs(est.height_m - 1.62) < 2 * sd, (est.height_m, sd)  # measured 1.636 +- 0.010
    st = est.stature
    # the jumps put the floor's point behind the feet: those images are left out of the floor's evidence
    assert st.template == 1.75 and st.prior_sd == STATURE_SD_M and st.share > 0.9 and 15 <= st.images < 25
    assert est.noise["off_floor"] == 25 - st.images
    assert abs(st.seen - 1.62) < 2 * st.seen_se  # the floor alone, without the stature's prior
    before, after = err_cm(anny_rest_joints(**START)), err_cm(anny_rest_joints(**est.params()))
    assert before > 3.0 and after < 0.7, (before, after)  # measured 3.05 -> 0.56
    truth = segment_lengths(anny_rest_joints(**ACTOR))
    z = [(m.posterior - truth[n]) / m.posterior_sd for n, m in est.segments.items()]
    assert np.mean(np.abs(z) < 2) >= 0.9, np.round(z, 2)


def test_a_quarter_second_moves_nothing_and_longer_captures_move_as_far_as_their_evidence_weighs():
    """The template filmed (nothing to correct), with a simulated detector's errors: 7 images of a quarter second
    keep the template and say why; a second (25 images) and four (100) move it within 2 SD of the truth, the
    longer one on more evidence (a narrower SD, a larger share). What the detector shares within a capture (its
    fixed 3D offsets) bounds what more images can add."""
    cam = camera(1.0, 3.0, size=(240, 180), f=199.0)  # the default capture's geometry
    spread, defs = DETECTOR_SPREAD["simulated"], DETECTOR_DEFINITIONS["simulated"]  # its errors, as simulated here
    out = {}
    for n_img in (7, 25, 100):
        t = np.arange(n_img) / 25.0
        S = motion_poses("karate_kick", t, seed=0, template=TEMPLATE)
        det = detections(TEMPLATE, S, cam, t, noise=np.random.default_rng(3))
        out[n_img] = fit_body(seen_segments(cam, *args(det)), START, ("height_m", "sex", "muscle"),
                              floor_z=floor_depths(cam, *args(det), FEET), camera_height_m=1.0, spread=spread,
                              definitions=defs, t_us=det.t_us)
    short = out[7]
    assert short.estimated == () and short.params() == START and "span 0.28 s: too few poses" in short.why
    # nothing seen narrows the prior: the body stays as uncertain as people are
    assert short.uncertain == ("height_m", "sex", "muscle") and short.sd("height_m") == pytest.approx(STATURE_SD_M)
    assert 0.2 < short.sd("sex") < PHENOTYPE_SD
    for n_img in (25, 100):
        est = out[n_img]
        assert est.estimated == ("height_m", "sex", "muscle")
        assert abs(est.height_m - 1.75) < 2 * est.sd("height_m")
    assert out[100].sd("height_m") < out[25].sd("height_m") and out[100].stature.share > out[25].stature.share


def test_a_low_camera_keeps_the_stature_and_a_stated_height_fits_the_proportions_at_it(actor):
    body, t, S = actor
    low = camera(0.6)
    det = detections(body, S, low, t)
    est = fit_body(seen_segments(low, *args(det)), START, ("height_m", "sex", "muscle"),
                   floor_z=floor_depths(low, *args(det), FEET), camera_height_m=0.6, spread=EXACT)
    assert est.height_m == 1.75 and "height_m" not in est.estimated and est.stature is None
    assert est.sd("height_m") == pytest.approx(STATURE_SD_M)  # kept, with the prior's spread
    assert est.scale_from.startswith("template default (the camera 0.60 m high") and "too low" in est.scale_from
    cam = camera(1.6)
    det = detections(body, S, cam, t)
    told = fit_body(seen_segments(cam, *args(det)), {**START, "height_m": 1.62}, ("sex", "muscle"), spread=EXACT)
    assert told.height_m == 1.62 and told.scale_from == "stated" and told.estimated == ("sex", "muscle")
    assert told.sex < -0.4 and told.sd("sex") < 0.2  # the actor's narrower shoulders and shorter forearms
    assert err_cm(anny_rest_joints(**told.params())) < 0.3 < err_cm(anny_rest_joints(**{**START, "height_m": 1.62}))


def test_the_rest_spread_carries_the_posterior_to_the_rest_joints(actor):
    body, t, S = actor
    cam = camera(1.6)
    det = detections(body, S, cam, t)
    est = fit_body(seen_segments(cam, *args(det)), START, ("height_m", "sex", "muscle"),
                   floor_z=floor_depths(cam, *args(det), FEET), camera_height_m=1.6, spread=EXACT)
    D = rest_spread(est, anny_rest_joints)
    assert D.shape == (3, 24, 3) and np.isfinite(D).all()
    # the head's height (the stature up to the head's top) varies as the stature's SD says
    head = 15
    sd_head = float(np.sqrt(np.sum(D[:, head, 1] ** 2)))
    assert sd_head == pytest.approx(est.sd("height_m") * anny_rest_joints(**est.params())[head, 1] / est.height_m,
                                    rel=0.15)
    none = dataclasses.replace(est, cov=None, estimated=())
    assert rest_spread(none, anny_rest_joints).shape == (0, 24, 3)


def recording(cam, world=""):
    return Recording(events=EventStream(events=np.zeros(0, EVENT_DTYPE), width=cam.width, height=cam.height),
                     camera=cam, world=world)


def run_stage(template, rec, det, caplog, **config):
    from eventcap.core.config import build_config
    from eventcap.core.registry import load_registry
    from eventcap_body._impl import run_proportions

    cfg = build_config(load_registry().get("proportions"), config, "stages.body")
    with caplog.at_level(logging.INFO):
        return run_proportions({"recording": rec, "detections": det, "template": template}, cfg,
                               StageContext("body", "proportions"))


def test_the_stage_says_what_moved_by_how_much_on_what_evidence_and_why_the_rest_did_not(actor, caplog):
    body, t, S = actor
    cam = camera(1.6)
    det, rec = detections(body, S, cam, t), recording(cam)
    unsaid = anny_template(seed=5)
    out = run_stage(unsaid, rec, det, caplog)
    got = out["template"]
    assert out["recording"].template is got and np.array_equal(got.vertex_albedo, unsaid.vertex_albedo)
    assert got.rest_spread is not None and got.rest_spread.shape == (3, 24, 3)
    # an unknown detector ("exact projections" is not in the table) is taken to err as the worst measured one, so
    # the stature moves about two thirds of the way the floor says (the jumps put it 3 cm too tall)
    assert err_cm(got.rest_joints) < 2.0 < err_cm(unsaid.rest_joints)
    assert abs(float(np.ptp(got.vertices[:, 1])) - 1.62) < 0.1
    text = caplog.text
    assert "body: stature 1.750 -> " in text and "the floor and the camera's height alone" in text
    assert "the evidence weighs" in text and "segment lengths (cm), template -> posterior +- SD" in text
    assert "moved: " in text and "stated: nothing" in text
    # a stated height is kept exactly; a whole stated body is kept as it is; estimate=false keeps the template
    caplog.clear()
    stated = dataclasses.replace(anny_template(1.66), stated=("height_m",))
    kept_h = run_stage(stated, rec, det, caplog)["template"]
    assert float(np.ptp(kept_h.vertices[:, 1])) == pytest.approx(1.66, abs=1e-9) and kept_h.stated == ("height_m",)
    assert "body: stature" not in caplog.text and "body: sex +0.000 -> " in caplog.text
    scan = dataclasses.replace(anny_template(1.9), stated=("shape",))
    assert run_stage(scan, rec, det, caplog)["template"] is scan
    assert run_stage(unsaid, rec, det, caplog, estimate=False)["template"] is unsaid
    # without the camera's extrinsics (a level world assumed) the stature cannot be told: it stays, the log says so
    caplog.clear()
    level = run_stage(unsaid, recording(cam, world="assumed_level"), det, caplog)["template"]
    assert float(np.ptp(level.vertices[:, 1])) == pytest.approx(1.75, abs=1e-6)
    assert "the stature is the template's (1.750 m)" in caplog.text
    # its stature kept, with the prior's spread in its rest joints (the head's height varies by the stature's SD)
    head = float(np.sqrt(np.sum(level.rest_spread[:, 15, 1] ** 2)))
    assert head == pytest.approx(STATURE_SD_M * level.rest_joints[15, 1] / 1.75, rel=0.05)


def test_a_segment_not_seen_says_why_it_did_not_move(actor, caplog):
    body, t, S = actor
    cam = camera(1.6)
    det = detections(body, S, cam, t)
    hidden = det.confidence_2d.copy()
    from eventcap.body.skeleton import LANDMARK_INDEX

    hidden[:, LANDMARK_INDEX["l_wrist"]] = 0.0  # the left forearm is never seen
    det = dataclasses.replace(det, confidence_2d=hidden)
    run_stage(anny_template(seed=5), recording(cam), det, caplog)
    line = next(r.getMessage() for r in caplog.records if "segment lengths" in r.getMessage())
    assert "l_forearm 24.5 -> " in line
    assert "(not seen across the line of sight in 3 images: it follows the rest of the body)" in line


def test_evaluate_measures_the_body_and_the_stated_template_against_the_truth(actor):
    from eventcap_evaluate._impl import body_errors

    body, t, S = actor
    J = joint_positions(S, body.rest_joints)
    L = landmark_positions(S, body)
    gt = GroundTruth(t_us=(t * 1e6).astype(np.int64), poses=S, joints=J, landmarks=L, frame_poses=S[:2],
                     frame_joints=J[:2], height=480, width=640)
    out = body_errors(gt, body, anny_template())
    assert out["body_error_mm"] < 1e-6
    assert out["stated_body_error_mm"] == pytest.approx(10 * err_cm(anny_rest_joints(**START)), rel=1e-6)
    assert set(out["stated_body_error_by_segment_mm"]) == set(SEGMENTS)


class TestProportionsConformance(StageConformance):
    stage_name = "proportions"
    sensitive = ("stature_sd_m", 0.03)

    def make_inputs(self):
        body = anny_template(**ACTOR, seed=2)
        t = np.arange(20) / 25.0
        S = motion_poses("jumping_jack", t, seed=1, template=body)
        cam = camera(1.6)
        return {"recording": recording(cam), "detections": detections(body, S, cam, t), "template": anny_template()}


def test_the_body_is_one_per_capture_from_all_its_images_in_every_pipeline():
    """Issue 54, item 4: over a chunked long capture the body node runs once, whole, on every image's detections
    (the detect node is whole too), before the chunks' solves read it: a resume finds it cached like any whole node."""
    from pathlib import Path

    import yaml

    from eventcap.core.registry import load_registry

    spec = load_registry().get("proportions")
    assert not spec.per_batch and not spec.plan
    root = Path(__file__).resolve().parents[1] / "conf" / "pipeline"
    with_body = 0
    for f in sorted(root.glob("*.yaml")):
        nodes = ((yaml.safe_load(f.read_text()) or {}).get("pipeline") or {}).get("nodes") or {}
        if "body" not in nodes:
            continue
        with_body += 1
        assert nodes["body"]["inputs"]["detections"] == "detect.detections", f.name
        assert not load_registry().get("simulated").per_batch
        for name, node in nodes.items():  # every solve reads the body's recording, none the source's
            if name in ("solve", "fits", "odometry") and "recording" in node.get("inputs", {}):
                assert node["inputs"]["recording"] == "body.recording", (f.name, name)
    assert with_body >= 9
