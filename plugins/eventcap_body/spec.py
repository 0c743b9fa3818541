"""Spec of the body stage (the node ``body``). Declarations only: the fit loads when the stage runs."""

from __future__ import annotations

from dataclasses import dataclass

from eventcap.artifacts.pose import Detections
from eventcap.artifacts.recording import Recording
from eventcap.body.template import Template
from eventcap.core.stage import Port, StageSpec, param


@dataclass
class ProportionsConfig:
    estimate: bool = param(True, help="estimate what the template does not state (the stature, ANNY's sex and muscle) "
                                      "from the detections; false: the template as given")
    scale_from_floor: bool = param(True, help="estimate an unstated stature from the floor and the camera's height "
                                              "(a world from the camera's extrinsics, its floor y = 0); false: the "
                                              "template's default stature")
    stature_sd_m: float = param(0.092, gt=0, help="SD of the prior of an unstated stature around the template's, "
                                                 "metres (default: adults' spread, eventcap/body/proportions.py)")


PROPORTIONS = StageSpec(
    name="proportions", kind="body", version=7,
    description="the person's body: the stature, limb lengths and girdle widths seen over the capture, each with a "
                "standard error, moved from the template's as far as the evidence weighs against a prior of human "
                "proportions (a Bayesian update of ANNY's stature and phenotypes where the template does not state "
                "them; its posterior as the template's rest_spread; not in the paper)",
    config=ProportionsConfig,
    inputs={"recording": Port(Recording, "the recording the solves read (its camera; its template is replaced)"),
            "detections": Port(Detections, "2D landmarks and 3D joints at the intensity frames"),
            "template": Port(Template, "the template as the user gave it (what it states is kept)")},
    outputs={"recording": Port(Recording, doc="the same recording carrying the person's body as its template"),
             "template": Port(Template, doc="the person's body, with its uncertainty (rest_spread) when estimated")},
    run="eventcap_body._impl:run_proportions",
)
