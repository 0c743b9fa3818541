"""The confidence stage (plugins/eventcap_confidence): per frame and joint, how much of what the run observed supports
the estimated motion, without ground truth. Conformance, and its answer on the truth against a misplaced motion
(eventcap/analysis/confidence.py holds the measures; tests/test_gaps.py the frames without an estimate)."""

from __future__ import annotations

import numpy as np

from eventcap.artifacts import BatchPlan
from eventcap.artifacts.pose import PoseSequence
from eventcap.core.config import build_config
from eventcap.core.registry import load_registry
from eventcap.core.stage import StageContext
from eventcap.core.testing import StageConformance
from helpers.poses import detect, posed_recording
from helpers.spline_scene import EXACT, BatchSeq


def inputs(shift_m: float = 0.0):
    """3 batches of a jumping jack with exact detections at its 4 intensity frames (no events), and the true motion
    per batch, moved ``shift_m`` metres along x."""
    rec = posed_recording("jumping_jack", n_frames=4, speed=1.0, with_template=True)
    det = detect("simulated", rec, **EXACT)
    plan = BatchPlan.between_frames(rec.frames.t_us)
    gt, poses = rec.ground_truth, []
    for k in range(len(plan)):
        b = plan.batch(k)
        t = np.arange(b.t0_us, b.t1_us + 1, 1_000, dtype=np.int64)
        S = gt.poses[np.searchsorted(gt.t_us, t)].copy()
        S[:, 30] += shift_m
        poses.append(PoseSequence(t_us=t, poses=S, status="Solve_Succeeded"))
    return {"recording": rec, "detections": det, "poses": BatchSeq(poses, plan.batches())}


def confidence(shift_m: float = 0.0, **config):
    spec = load_registry().get("confidence")
    return spec.load_run()(inputs(shift_m), build_config(spec, config, "stages.confidence"),
                           StageContext(node="confidence", stage="confidence"))["confidence"]


class TestConfidenceConformance(StageConformance):
    stage_name = "confidence"
    sensitive = ("detection_frac", 0.1)

    def make_inputs(self):
        return inputs()


def test_the_true_motion_is_trusted_at_the_frames_and_a_misplaced_one_is_not():
    true, off = confidence(), confidence(0.1)
    frames = np.searchsorted(true.t_us, inputs()["recording"].frames.t_us)
    assert true.confidence.shape == (121, 24) and true.estimated.all()
    assert np.all((true.confidence >= 0) & (true.confidence <= 1))
    # every joint of the true motion is supported by its detection at every intensity frame ...
    assert (true.confidence[frames] >= 0.5).all()
    # ... and none of the motion moved by 10 cm (several pixels in these images, beyond detection_frac's scale)
    assert (off.confidence[frames] < 0.5).all() and off.confidence.mean() < 0.5 * true.confidence.mean()
