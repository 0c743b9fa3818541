"""Spec of the confidence stage: an uncertainty in millimetres per frame and joint of the estimated motion, and the
confidence derived from it, from what the run observed (no ground truth). Declarations only."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from eventcap.artifacts.pose import Detections, JointConfidence, PoseSequence
from eventcap.artifacts.recording import Recording
from eventcap.core.stage import Port, StageSpec, param


#: the calibration table shipped with the stage (per detector kind; docs/results/uncertainty.md)
SHIPPED_CALIBRATION = Path(__file__).resolve().parent / "calibration.json"


def calibration_files(value: str) -> list[str]:
    """The file a ``calibration`` setting names (``shipped``: the table shipped with the stage): its digest is part
    of the stage's cache key, so a changed table recomputes the uncertainty."""
    return [str(SHIPPED_CALIBRATION if value == "shipped" else value)]


_FROM_TABLE = "; null: the detector kind's calibration (stages.confidence.calibration)"


@dataclass
class ConfidenceConfig:
    calibration: str = param("shipped", file=calibration_files,
                             help="the uncertainty's calibration per detector kind: a JSON table {\"detectors\": "
                                  "{kind: {scale, detection_2d, detection_3d, events, motion, speed, between_mm, "
                                  "floor_mm, trusted_mm, unseen_mm, source}}, \"default\": kind for a detector "
                                  "nobody calibrated}; the kind is the word before the colon of the detections' "
                                  "detector (simulated, blazepose, file); shipped: the stage's own table "
                                  "(plugins/eventcap_confidence/calibration.json)")
    scale: float | None = param(None, gt=0, help="calibration of the solve's own σ (its Laplace approximation, the "
                                                 "energy read as a negative log-likelihood): the σ in the uncertainty "
                                                 "is this times the solve's (dimensionless)" + _FROM_TABLE)
    detection_2d: float | None = param(None, ge=0, help="weight of the detected landmarks' reprojection residual, "
                                                        "carried to the joint's depth (mm), in the uncertainty (added "
                                                        "as a variance; dimensionless)" + _FROM_TABLE)
    detection_3d: float | None = param(None, ge=0, help="weight of the 3D detection's residual after the best "
                                                        "translation (mm) in the uncertainty (added as a variance; "
                                                        "dimensionless)" + _FROM_TABLE)
    events: float | None = param(None, ge=0, help="weight of the joint's image displacement the events leave "
                                                  "unconfirmed between two intensity frames (mm at its depth) in the "
                                                  "uncertainty (added as a variance; dimensionless)" + _FROM_TABLE)
    motion: float | None = param(None, ge=0, help="weight of the joint's displacement between its two intensity "
                                                  "frames (relative to the joints' mean, mm) times 4τ(1 - τ), τ the "
                                                  "fraction of the interval (far in time from a detection and fast), "
                                                  "in the uncertainty (added as a variance; dimensionless)"
                                                  + _FROM_TABLE)
    speed: float | None = param(None, ge=0, help="weight of the joint's displacement between its two intensity frames "
                                                 "(mm) at every time, the frames included (fast motion, which also "
                                                 "blurs the image), in the uncertainty (added as a variance; "
                                                 "dimensionless)" + _FROM_TABLE)
    between_mm: float | None = param(None, ge=0, help="the uncertainty added half way between two intensity frames "
                                                      "(4τ(1 - τ) times it, added as a variance), mm" + _FROM_TABLE)
    body: float = param(1.0, ge=0, help="weight of the body's own uncertainty (a body estimated from the detections: "
                                        "its rest joints' posterior spread carried to each posed joint, mm) in the "
                                        "uncertainty (added as a variance; dimensionless; 0: left out)")
    floor_mm: float | None = param(None, ge=0, help="the least uncertainty of any joint, mm (added as a variance)"
                                                    + _FROM_TABLE)
    fallback_mm: float = param(100.0, gt=0, help="the uncertainty that stands for the solve's σ where the solve "
                                                 "gives none (a solve without a Laplace approximation), mm")
    trusted_mm: float | None = param(None, gt=0, help="the uncertainty at which the confidence is 0.5: confidence = "
                                                      "1 / (1 + (u / trusted_mm)²), mm; above it a joint is not "
                                                      "trusted" + _FROM_TABLE)
    unseen_mm: float | None = param(None, gt=0, help="the least uncertainty of a joint out of view (outside the image "
                                                     "with the body around it), mm; at least trusted_mm, so that such "
                                                     "a joint is never marked observed" + _FROM_TABLE
                                                     + "; given trusted_mm alone: the table's unseen / trusted "
                                                       "ratio times it")
    view_margin: float = param(1.0, ge=0, help="a joint counts as in view when the ball of this many times its "
                                               "uncertainty around it (or of its body's depth, if larger) projects "
                                               "inside every image edge (dimensionless)")
    bin_ms: float = param(10.0, gt=0, help="time bins of the event support, ms")
    event_radius_px: int = param(6, ge=0, help="events counted in this half-side box around samples along each bone "
                                               "(eventcap.energy.silence.measure_silence)")
    event_rate_hz: float = param(2.0, gt=0, help="events per pixel per second above the background at which a bone "
                                                 "counts as 1 - 1/e seen by the events")


CONFIDENCE = StageSpec(
    name="confidence", kind="analyse", version=6,
    description="uncertainty (mm) per frame and joint of the estimated motion: the solve's own σ (its Laplace "
                "approximation, calibrated per detector kind) inflated where the detections, the events and the "
                "estimate disagree, between the frames where the joint moves fast, and for joints out of view; the "
                "confidence in [0, 1] derived from it (no ground truth; below 0.5: not trusted)",
    config=ConfidenceConfig,
    inputs={"recording": Port(Recording), "detections": Port(Detections),
            "poses": Port(PoseSequence, "the motion's per-batch poses", all_batches=True)},
    outputs={"confidence": Port(JointConfidence)},
    run="eventcap_confidence._impl:run_confidence",
)
