"""Spec of the `reconstruct` stage: images from events alone at the batch boundaries. Declarations only."""

from __future__ import annotations

from dataclasses import dataclass

from eventcap.artifacts import BatchPlan
from eventcap.artifacts.recording import Recording
from eventcap.artifacts.tracking import LatentFrames
from eventcap.core.stage import Port, StageSpec, param


@dataclass
class ReconstructConfig:
    cutoff_rad_s: float = param(3.0, ge=0, help="decay rate of the per-pixel high-pass filter (Scheerlinck et al. 2018), "
                                           "rad/s: the images remember about 1/cutoff s of events; 0 = direct "
                                           "integration")
    baseline: str = param("median", help="median: subtract each pixel's median over the recording (removes the "
                                         "fading traces where the actor was; uses the whole recording) | none")
    contrast: float = param(0.2, gt=0, help="log-intensity step of one event (the sensor's contrast threshold C)")
    smooth_px: float = param(0.0, ge=0, help="std of a Gaussian applied to each image, px (0 = none)")
    eps: float = param(1e-3, gt=0, help="offset of the log images, L = log(I + eps)")
    base_intensity: float = param(0.5, gt=0, lt=1, help="linear intensity shown where nothing changed (the filter's 0)")
    exposure_us: int = param(0, ge=0, help="exposure the images declare to the detector, us (the simulated detector's "
                                     "blur model reads it): 0 = sharp, as a reconstruction has no motion blur (its "
                                     "other flaws, missing static texture and traces, no blur model can see)")


RECONSTRUCT = StageSpec(
    name="reconstruct", kind="sharpen", version=2,
    description="images from events alone (per-pixel high-pass filter, Scheerlinck et al. 2018) at every batch "
                "boundary: latent log images for the tracker and a recording whose frames they are, for the detector",
    config=ReconstructConfig, inputs={"recording": Port(Recording), "batches": Port(BatchPlan)},
    outputs={"latent": Port(LatentFrames), "recording": Port(Recording)},
    run="eventcap_reconstruct._impl:run_reconstruct",
)
