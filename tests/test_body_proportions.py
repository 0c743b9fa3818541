"""The person's proportions from the detections (issue 43, item 3; eventcap/body/proportions.py, stage proportions).

On exact detections of an ANNY actor who is not the template (its 2D points projected, its 3D joints as they are):
the segments seen across the line of sight give the actor's limb lengths and girdle widths; the floor and the
camera's height give its stature when the camera looks down steeply enough, and not otherwise (the log says why);
a stated height is kept and the proportions fitted at it; a stated body is kept whole; evaluate measures the
body's segments against the truth beside the stated template's."""

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
from eventcap.body.proportions import SEGMENTS, fit_body, floor_depths, seen_segments, segment_lengths
from eventcap.camera import Camera, look_at
from eventcap.core.stage import StageContext
from eventcap.core.testing import StageConformance
from eventcap.events import EVENT_DTYPE

ACTOR = dict(height_m=1.62, build=0.3, muscle=0.4, sex=-0.7)
START = dict(height_m=1.75, build=0.0, muscle=0.0, sex=0.0)


def camera(height_m: float, distance_m: float = 3.5) -> Camera:
    R, t = look_at((0.0, height_m, distance_m), (0.0, 0.9, 0.0))
    return Camera(640, 480, 500.0, 500.0, 319.5, 239.5, np.zeros(5), R, t)


@pytest.fixture(scope="module")
def actor():
    body = anny_template(**ACTOR, seed=2)
    t = np.arange(25) / 25.0
    S = motion_poses("jumping_jack", t, seed=1, template=body)
    return body, t, S


def detections(body, S, cam, t):
    L = landmark_positions(S, body)
    J = joint_positions(S, body.rest_joints)
    n = S.shape[0]
    return Detections(t_us=(t * 1e6).astype(np.int64), keypoints_2d=cam.project(L).astype(np.float32),
                      confidence_2d=np.ones(L.shape[:2], np.float32), joints_3d=J - J[:, :1],
                      confidence_3d=np.ones((n, 24), np.float32), detector="exact projections (test)")


def err_cm(rest) -> float:
    truth = segment_lengths(anny_rest_joints(**ACTOR))
    got = segment_lengths(rest)
    return 100 * float(np.median([abs(got[k] - truth[k]) for k in SEGMENTS]))


def args(det):
    return det.keypoints_2d, det.confidence_2d, det.joints_3d, det.confidence_3d


def test_exact_detections_give_the_actors_segments_and_stature_from_the_floor(actor):
    body, t, S = actor
    cam = camera(1.6)
    det = detections(body, S, cam, t)
    seen = seen_segments(cam, *args(det))
    assert all(len(seen.image[n]) >= 3 for n in ("l_thigh", "r_thigh", "shoulders", "hips"))
    fz = floor_depths(cam, *args(det))
    truth_z = cam.to_camera(joint_positions(S, body.rest_joints)[:, 0])[:, 2]
    assert np.nanmedian(np.abs(fz / truth_z - 1)) < 0.03  # the pelvis's depth from the sole on the floor
    est = fit_body(seen, START, ("height_m", "sex", "muscle"), floor_z=fz, camera_height_m=1.6)
    assert est.scale_from == "floor" and est.estimated == ("height_m", "sex", "muscle")
    assert est.height_m == pytest.approx(1.62, abs=0.03)
    before, after = err_cm(anny_rest_joints(**START)), err_cm(anny_rest_joints(**est.params()))
    assert before > 3.0 and after < 0.6, (before, after)  # measured 3.05 -> 0.46


def test_a_low_camera_keeps_the_stature_and_a_stated_height_fits_the_proportions_at_it(actor):
    body, t, S = actor
    low = camera(0.6)
    det = detections(body, S, low, t)
    est = fit_body(seen_segments(low, *args(det)), START, ("height_m", "sex", "muscle"),
                   floor_z=floor_depths(low, *args(det)), camera_height_m=0.6)
    assert est.height_m == 1.75 and "height_m" not in est.estimated
    assert est.scale_from.startswith("template default (the camera 0.60 m high") and "too low" in est.scale_from
    cam = camera(1.6)
    det = detections(body, S, cam, t)
    told = fit_body(seen_segments(cam, *args(det)), {**START, "height_m": 1.62}, ("sex", "muscle"), prior_sigma=0.5)
    assert told.height_m == 1.62 and told.scale_from == "stated"
    assert told.sex < -0.5  # the actor's narrower shoulders and shorter forearms: a female body (measured -0.68)
    assert err_cm(anny_rest_joints(**told.params())) < 0.15 < err_cm(anny_rest_joints(**{**START, "height_m": 1.62}))


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


def test_the_stage_keeps_what_is_stated_and_says_what_it_estimated_from_what(actor, caplog):
    body, t, S = actor
    cam = camera(1.6)
    det, rec = detections(body, S, cam, t), recording(cam)
    unsaid = anny_template(seed=5)
    out = run_stage(unsaid, rec, det, caplog)
    got = out["template"]
    assert out["recording"].template is got and np.array_equal(got.vertex_albedo, unsaid.vertex_albedo)
    assert err_cm(got.rest_joints) < 0.7 and float(np.ptp(got.vertices[:, 1])) == pytest.approx(1.62, abs=0.03)
    text = caplog.text
    assert "body: estimated stature" in text and "from the floor and the camera's height" in text
    assert "segments seen across the line of sight" in text and "kept: nothing stated" in text
    # a stated height is kept exactly; a whole stated body is kept as it is; estimate=false keeps the template
    stated = dataclasses.replace(anny_template(1.66), stated=("height_m",))
    kept_h = run_stage(stated, rec, det, caplog)["template"]
    assert float(np.ptp(kept_h.vertices[:, 1])) == pytest.approx(1.66, abs=1e-9) and kept_h.stated == ("height_m",)
    scan = dataclasses.replace(anny_template(1.9), stated=("shape",))
    assert run_stage(scan, rec, det, caplog)["template"] is scan
    assert run_stage(unsaid, rec, det, caplog, estimate=False)["template"] is unsaid
    # without the camera's extrinsics (a level world assumed) the stature cannot be told: it stays, the log says so
    caplog.clear()
    level = run_stage(unsaid, recording(cam, world="assumed_level"), det, caplog)["template"]
    assert float(np.ptp(level.vertices[:, 1])) == pytest.approx(1.75, abs=1e-6)
    assert "the stature is the template's (1.750 m)" in caplog.text


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
    sensitive = ("prior_sigma", 0.3)

    def make_inputs(self):
        body = anny_template(**ACTOR, seed=2)
        t = np.arange(8) / 25.0
        S = motion_poses("jumping_jack", t, seed=1, template=body)
        cam = camera(1.6)
        return {"recording": recording(cam), "detections": detections(body, S, cam, t), "template": anny_template()}
