"""The confidence stage (plugins/eventcap_confidence): per frame and joint, an uncertainty in millimetres and the
confidence derived from it, without ground truth. Conformance, and its answer on the truth against a motion whose
arm is wrong (eventcap/analysis/uncertainty.py holds the measures; tests/test_uncertainty.py tests them;
tests/test_gaps.py the frames without an estimate and the joints out of view)."""

from __future__ import annotations

import numpy as np
import pytest

from eventcap.artifacts import BatchPlan
from eventcap.artifacts.pose import PoseSequence
from eventcap.core.config import build_config
from eventcap.core.registry import load_registry
from eventcap.core.stage import StageContext
from eventcap.core.testing import StageConformance
from helpers.poses import detect, posed_recording
from helpers.spline_scene import EXACT, BatchSeq


def inputs(arm_rad: float = 0.0, sigma_mm: float | None = 20.0, rest_spread=None):
    """3 batches of a jumping jack with exact detections at its 4 intensity frames (no events), and the true motion
    per batch with the right shoulder turned by arm_rad, each frame with a solve's σ of sigma_mm (None: none)."""
    from eventcap.body.skeleton import DOF_INDEX

    import dataclasses

    rec = posed_recording("jumping_jack", n_frames=4, speed=1.0, with_template=True)
    det = detect("simulated", rec, **EXACT)
    if rest_spread is not None:  # a body estimated from the detections, known to within its posterior
        rec = dataclasses.replace(rec, template=dataclasses.replace(rec.template, rest_spread=rest_spread))
    plan = BatchPlan.between_frames(rec.frames.t_us)
    gt, poses = rec.ground_truth, []
    for k in range(len(plan)):
        b = plan.batch(k)
        t = np.arange(b.t0_us, b.t1_us + 1, 1_000, dtype=np.int64)
        S = gt.poses[np.searchsorted(gt.t_us, t)].copy()
        S[:, DOF_INDEX["r_shoulder_flex"]] += arm_rad
        sig = None if sigma_mm is None else np.full((t.size, 24), sigma_mm, np.float32)
        poses.append(PoseSequence(t_us=t, poses=S, sigma_mm=sig, status="Solve_Succeeded"))
    return {"recording": rec, "detections": det, "poses": BatchSeq(poses, plan.batches())}


def confidence(arm_rad: float = 0.0, sigma_mm: float | None = 20.0, rest_spread=None, **config):
    spec = load_registry().get("confidence")
    return spec.load_run()(inputs(arm_rad, sigma_mm, rest_spread), build_config(spec, config, "stages.confidence"),
                           StageContext(node="confidence", stage="confidence"))["confidence"]


class TestConfidenceConformance(StageConformance):
    stage_name = "confidence"
    sensitive = ("scale", 2.0)

    def make_inputs(self):
        return inputs()


WEIGHTS = {"scale": 1.5, "detection_2d": 0.5, "detection_3d": 0.5, "floor_mm": 5.0, "events": 0.0, "trusted_mm": 100.0,
           "motion": 0.0, "speed": 0.0, "between_mm": 0.0}


def test_the_uncertainty_is_the_solves_sigma_on_the_truth_and_grows_where_the_detections_disagree():
    from eventcap.body.skeleton import JOINT_INDEX

    true, off = confidence(**WEIGHTS), confidence(1.0, **WEIGHTS)
    frames = np.searchsorted(true.t_us, inputs()["recording"].frames.t_us)
    assert true.uncertainty_mm.shape == true.confidence.shape == (121, 24) and true.estimated.all()
    # on the truth with exact detections: the calibrated σ and the floor (30 and 5 mm), within the residuals' rounding
    assert np.allclose(true.uncertainty_mm, np.hypot(1.5 * 20.0, 5.0), atol=1.5)
    assert (true.confidence > 0.9).all()  # 30 mm of a trusted 100 mm
    # the right arm turned by 1 rad: the detections disagree there (tens of cm at the wrist), not at the left arm
    arm = [JOINT_INDEX[n] for n in ("r_elbow", "r_wrist", "r_hand")]
    left = [JOINT_INDEX[n] for n in ("l_elbow", "l_wrist", "l_hand")]
    wrist = JOINT_INDEX["r_wrist"]
    assert (off.uncertainty_mm[np.ix_(frames, arm)] > true.uncertainty_mm[np.ix_(frames, arm)] + 5.0).all()
    assert (off.uncertainty_mm[frames, wrist] > 2.0 * true.uncertainty_mm[frames, wrist]).all()
    assert off.confidence[frames, wrist].mean() < true.confidence[frames, wrist].mean() - 0.2
    # (the other joints take a little: the 3D detections' best translation is their mean offset, the arm's included)
    assert np.allclose(off.uncertainty_mm[np.ix_(frames, left)], true.uncertainty_mm[np.ix_(frames, left)], atol=6.0)


def test_without_the_solves_sigma_the_fallback_stands_for_it(caplog):
    c = confidence(sigma_mm=None, **WEIGHTS, fallback_mm=70.0)
    assert np.allclose(c.uncertainty_mm, np.hypot(70.0, 5.0), atol=1.5)
    assert "the poses carry no σ of their solve" in caplog.text


def test_settings_that_cannot_work_are_refused_by_name():
    from eventcap.core.stage import StageFailed

    with pytest.raises(StageFailed, match=r"stages.confidence.unseen_mm: expected at least trusted_mm \(100 mm"):
        confidence(unseen_mm=50.0, trusted_mm=100.0)


def test_a_body_estimated_from_the_detections_adds_its_own_uncertainty():
    """The template carries its posterior (rest_spread): a 3 % uncertain scale adds, as a variance, 3 % of each
    posed joint's distance from the joints' mean (what the rigid alignment leaves); stages.confidence.body=0 leaves
    it out."""
    from eventcap.body.kinematics import joint_positions

    rec = posed_recording("jumping_jack", n_frames=4, speed=1.0, with_template=True)
    rest = rec.template.rest_joints
    spread = (0.03 * (rest - rest.mean(axis=0)))[None]
    exact, body = confidence(**WEIGHTS), confidence(rest_spread=spread, **WEIGHTS)
    extra = np.sqrt(np.maximum(body.uncertainty_mm.astype(float) ** 2 - exact.uncertainty_mm.astype(float) ** 2, 0))
    gt = rec.ground_truth
    J = joint_positions(gt.poses[np.searchsorted(gt.t_us, body.t_us)], rest)
    want = 30.0 * np.linalg.norm(J - J.mean(axis=1, keepdims=True), axis=-1)  # 3 % of the distance, mm
    assert want.max() > 10.0 and np.allclose(extra, want, atol=0.5)
    off = confidence(rest_spread=spread, **WEIGHTS, body=0.0)
    assert np.allclose(off.uncertainty_mm, exact.uncertainty_mm)


def _table(tmp_path, detectors: dict, default: str = "simulated"):
    import json

    entry = {"scale": 1.0, "detection_2d": 0.0, "detection_3d": 0.0, "events": 0.0, "motion": 0.0, "speed": 0.0,
             "between_mm": 0.0, "floor_mm": 0.0, "trusted_mm": 100.0, "unseen_mm": 120.0}
    path = tmp_path / "calibration.json"
    path.write_text(json.dumps({"default": default,
                                "detectors": {k: {**entry, **v} for k, v in detectors.items()}}))
    return str(path)


def test_the_calibration_is_the_detector_kinds_and_a_setting_given_takes_its_place(tmp_path):
    """Exact detections by the simulated detector, a solve's σ of 20 mm: the table's entry for kind 'simulated'
    scales it (2 x 20 = 40 mm), not the other kinds'; a kind without an entry takes the table's default; a setting
    given in the config replaces the table's."""
    table = _table(tmp_path, {"simulated": {"scale": 2.0}, "blazepose": {"scale": 0.1}})
    c = confidence(calibration=table)
    assert np.allclose(c.uncertainty_mm, 40.0, atol=1.5)
    assert np.allclose(c.confidence, 1.0 / (1.0 + (c.uncertainty_mm / 100.0) ** 2))
    other = _table(tmp_path, {"blazepose": {"scale": 0.5, "trusted_mm": 50.0, "unseen_mm": 60.0}}, default="blazepose")
    c = confidence(calibration=other)
    assert np.allclose(c.uncertainty_mm, 10.0, atol=1.5)
    assert np.allclose(c.confidence, 1.0 / (1.0 + (c.uncertainty_mm / 50.0) ** 2))
    assert np.allclose(confidence(calibration=table, scale=3.0).uncertainty_mm, 60.0, atol=1.5)
    # trusted_mm given alone (above the table's unseen_mm, 120): unseen keeps the table's ratio (1.2), not refused
    c = confidence(calibration=table, trusted_mm=200.0)
    assert np.allclose(c.confidence, 1.0 / (1.0 + (c.uncertainty_mm / 200.0) ** 2))
    # by frame rate: this capture's 25 fps takes its factor (2 x 1.5 x 20 = 60 mm), trusted_mm stays the table's;
    # a scale given in the config is taken as it is
    rated = _table(tmp_path, {"simulated": {"scale": 2.0, "factor_by_fps": {"10": 0.5, "25": 1.5}}})
    c = confidence(calibration=rated)
    assert np.allclose(c.uncertainty_mm, 60.0, atol=1.5)
    assert np.allclose(c.confidence, 1.0 / (1.0 + (c.uncertainty_mm / 100.0) ** 2))
    assert np.allclose(confidence(calibration=rated, scale=3.0).uncertainty_mm, 60.0, atol=1.5)
    # by view: this whole-body capture with frames takes whole_frames' factor (2 x 1.5 x 0.5 x 20 = 30 mm), not the
    # close-up's or the event-only camera's
    viewed = _table(tmp_path, {"simulated": {"scale": 2.0, "factor_by_fps": {"10": 0.5, "25": 1.5},
                                             "factor_by_view": {"whole_frames": 0.5, "close_up": 3.0,
                                                                "event_only": 4.0}}})
    assert np.allclose(confidence(calibration=viewed).uncertainty_mm, 30.0, atol=1.5)


def test_the_view_is_what_the_method_sees():
    """A capture's view (what its uncertainty is calibrated for) comes from what the method sees, not the truth: the
    whole body in the image with frames, the same poses from a camera without frames, the body moved down by a third
    of the image so that its legs leave it (a close-up), and detections that saw only the upper body."""
    from eventcap.analysis.confidence import joints_in_view
    from eventcap_confidence._impl import capture_view

    rec = posed_recording("jumping_jack", n_frames=4, speed=1.0, with_template=True)
    gt, cam = rec.ground_truth, rec.camera
    P = gt.poses[::50].copy()
    assert capture_view(rec, P, 25.0) == "whole_frames" and capture_view(rec, P, None) == "event_only"
    z = float(cam.depth(gt.poses[:1, 30:33])[0])
    P[:, 30:33] += 0.35 * cam.height * z / cam.fy * np.asarray(cam.R)[1]  # the image's y points down
    share = joints_in_view(rec.template, cam, P).mean()
    assert 0.2 < share < 0.8
    assert capture_view(rec, P, 25.0) == "close_up" and capture_view(rec, P, None) == "event_only"
    P[:2] = np.nan  # frames without an estimate do not count
    assert capture_view(rec, P, 10.0) == "close_up"
    # the detections: a detector that saw only the upper body makes a close-up of an estimate drawn whole
    import dataclasses

    from eventcap.body.skeleton import LANDMARK_NAMES

    det = detect("simulated", rec, **EXACT)
    whole = gt.poses[::50]
    assert capture_view(rec, whole, 25.0, det) == "whole_frames"
    low = [i for i, n in enumerate(LANDMARK_NAMES) if any(k in n for k in ("hip", "knee", "ankle", "heel", "foot"))]
    conf, seen = np.array(det.confidence_2d, copy=True), det.observed()
    conf[:, low], seen[:, low] = 0.0, False
    top = dataclasses.replace(det, confidence_2d=conf, in_view=seen if det.in_view is not None else None)
    assert top.observed().any(axis=1).all() and top.observed().mean() < 0.8
    assert capture_view(rec, whole, 25.0, top) == "close_up"


def test_a_calibration_table_that_cannot_work_is_refused_naming_what_is_wrong(tmp_path):
    from eventcap.core.stage import StageFailed

    with pytest.raises(StageFailed, match=r"no entry for detector kind 'simulated' and no default entry"):
        confidence(calibration=_table(tmp_path, {"blazepose": {}}, default=""))
    with pytest.raises(StageFailed, match=r"detector kind 'simulated': scale must be a number >= 0, got 'x'"):
        confidence(calibration=_table(tmp_path, {"simulated": {"scale": "x"}}))
    with pytest.raises(StageFailed, match=r"factor_by_view expects a view \(whole_frames, close_up, event_only\) as "
                                          r"key and a factor > 0, got 'closeup'"):
        confidence(calibration=_table(tmp_path, {"simulated": {"factor_by_view": {"closeup": 2.0}}}))
    with pytest.raises(StageFailed, match=r"factor_by_view .* got 'event_only'"):
        confidence(calibration=_table(tmp_path, {"simulated": {"factor_by_view": {"event_only": 0}}}))
    bad = tmp_path / "bad.json"
    bad.write_text("[1, 2]")
    with pytest.raises(StageFailed, match=r"stages.confidence.calibration: .*bad.json: expected an object"):
        confidence(calibration=str(bad))


def test_the_shipped_calibration_has_every_detector_kind_and_its_table_is_in_the_cache_key(tmp_path):
    """simulated and blazepose each have their own entry, detections from a file take the documented default, and
    every entry is one the stage accepts (unseen at least trusted); the table's content is part of the key."""
    import json

    from eventcap.analysis.uncertainty import calibration
    from eventcap.core.config import file_digests
    from eventcap_confidence.spec import SHIPPED_CALIBRATION

    table = json.loads(SHIPPED_CALIBRATION.read_text())
    assert {"simulated", "blazepose"} <= set(table["detectors"])
    assert calibration(table, "file")[0] == table["default"] in table["detectors"]
    for kind in table["detectors"]:
        name, cal = calibration(table, kind)
        assert name == kind and cal["unseen_mm"] >= cal["trusted_mm"] > 0 and cal["scale"] > 0
        assert table["detectors"][kind]["source"]
    spec = load_registry().get("confidence")
    a = file_digests(spec, build_config(spec, {}, "stages.confidence"), "stages.confidence")
    other = tmp_path / "other.json"
    other.write_text(json.dumps({**table, "about": "changed"}))
    b = file_digests(spec, build_config(spec, {"calibration": str(other)}, "stages.confidence"), "stages.confidence")
    assert set(a) == set(b) == {"calibration"} and a != b
