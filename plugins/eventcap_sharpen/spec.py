"""Spec of the sharpen stage: EDI, latent sharp log images at the intensity frames from the blurry frames and the
events (paper Sec. 3.1, Eq. 2; Pan et al. 2019). Declarations only."""

from __future__ import annotations

from dataclasses import dataclass

from eventcap.artifacts.recording import Recording
from eventcap.artifacts.tracking import LatentFrames
from eventcap.core.stage import Port, StageSpec, param


@dataclass
class EdiConfig:
    contrast: float = param(0.0, ge=0, help="contrast threshold C; 0 = estimate one C for the recording (Pan et al.)")
    c_min: float = param(0.05, gt=0, help="lower end of the automatic search for C")
    c_max: float = param(0.5, gt=0, help="upper end of the automatic search for C")
    eps: float = param(1e-3, gt=0, help="offset of the log image, L = log(I + eps)")


EDI = StageSpec(
    name="edi", kind="sharpen", version=1,
    description="EDI: latent sharp log images at frame times from blurry frames + events (Eq. 2)",
    config=EdiConfig, inputs={"recording": Port(Recording)}, outputs={"latent": Port(LatentFrames)},
    run="eventcap_sharpen._impl:run_edi",
)
