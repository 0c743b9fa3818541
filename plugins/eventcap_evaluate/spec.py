"""Spec of the evaluate stage (paper Sec. 4, Table 1). Declarations only: the implementation loads when it runs."""

from __future__ import annotations

from dataclasses import dataclass

from eventcap.analysis.metrics import END_EFFECTORS

from eventcap.artifacts import Metrics
from eventcap.artifacts.pose import JointErrors, PoseSequence
from eventcap.artifacts.recording import Recording
from eventcap.body.template import Template
from eventcap.core.stage import Port, StageSpec, param


@dataclass
class EvaluateConfig:
    every: int = param(10, ge=1, help="AE and STD over every n-th tracking frame of the joined motion (paper: 10)")
    align: str = param("procrustes", help="procrustes: rigid (rotation + translation) alignment to the truth per "
                                          "frame, as the paper | none: raw world-space distances")
    join: str = param("later", help="a tracking frame two batches share (their boundary): later (the later "
                                    "batch's pose) | mean (the average of the batches' poses)")
    velocity_window_ms: float = param(10.0, gt=0, help="MPJVE and acceleration error: central differences over this "
                                                 "window (x(t+h) - x(t-h)) / 2h, h = half of it, ms")
    end_effectors: list[str] = param(default_factory=lambda: list(END_EFFECTORS),
                                     help="joints whose peak speed per batch is measured (feet, wrists, hands)")
    peak_min_speed_mps: float = param(0.5, ge=0, help="a (batch, end effector) pair counts in the peak-speed error only "
                                                "if its true peak speed exceeds this, m/s: a relative error of a "
                                                "joint that does not move is not defined")
    fast_speed_mps: float = param(3.0, gt=0, help="peak_speed_err_fast: the peak-speed error over the (batch, end "
                                                  "effector) pairs whose true peak reaches this, m/s (the fast "
                                                  "moments between two intensity frames)")


EVALUATE = StageSpec(
    name="evaluate", kind="evaluate", version=6,
    description="mean per-joint 3D error (AE, Procrustes-aligned) and its STD on every 10th frame, AE.raw / "
                "AE.nonRaw, per-joint errors, data rate (MB/s) against 1000 fps frames; velocity error (MPJVE), acceleration "
                "error and end-effector peak speed per batch, root-relative (all, the fast ones, signed by true speed); the root-relative error split along the "
                "camera's line of sight (depth) and the image plane; the body's limb lengths and girdle widths against "
                "the truth (and the stated template's, when wired)",
    config=EvaluateConfig,
    inputs={"recording": Port(Recording, "the recording, with ground truth and the actor template"),
            "poses": Port(PoseSequence, "the estimated poses of every batch", all_batches=True),
            "stated": Port(Template, "the template as the user gave it (before the body stage): its segment lengths "
                                     "are measured beside the body's", optional=True)},
    outputs={"metrics": Port(Metrics), "errors": Port(JointErrors)},
    run="eventcap_evaluate._impl:run",
)
