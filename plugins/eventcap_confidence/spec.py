"""Spec of the confidence stage: a confidence per frame and joint of the estimated motion, from what the run
observed (no ground truth). Declarations only."""

from __future__ import annotations

from dataclasses import dataclass

from eventcap.artifacts.pose import Detections, JointConfidence, PoseSequence
from eventcap.artifacts.recording import Recording
from eventcap.core.stage import Port, StageSpec, param


@dataclass
class ConfidenceConfig:
    detection_frac: float = param(0.05, gt=0, help="a detected landmark supports its joint as exp(-(r/r0)²), r the "
                                                   "estimate's reprojection residual, r0 this fraction of the "
                                                   "person's height in the image")
    still_frac: float = param(0.05, ge=0, help="a joint whose estimated image position moves less than this fraction "
                                               "of the body's image height between two intensity frames was still: "
                                               "the frames' support holds between them without events")
    bin_ms: float = param(10.0, gt=0, help="time bins of the event support, ms")
    event_radius_px: int = param(6, ge=0, help="events counted in this half-side box around samples along each bone "
                                               "(eventcap.energy.silence.measure_silence)")
    event_rate_hz: float = param(2.0, gt=0, help="events per pixel per second above the background at which a bone "
                                                 "counts as 1 - 1/e seen by the events")


CONFIDENCE = StageSpec(
    name="confidence", kind="analyse", version=1,
    description="confidence per frame and joint of the estimated motion from measurable support: detections "
                "agreeing with it at the intensity frames, events along its bones between them, the joint in view "
                "(no ground truth; below 0.5: unobserved or not trusted)",
    config=ConfidenceConfig,
    inputs={"recording": Port(Recording), "detections": Port(Detections),
            "poses": Port(PoseSequence, "the motion's per-batch poses", all_batches=True)},
    outputs={"confidence": Port(JointConfidence)},
    run="eventcap_confidence._impl:run_confidence",
)
