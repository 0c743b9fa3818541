"""Spec of the Sec. 3.3 stage: event-based pose refinement. Declarations only: the solver loads when it runs."""

from __future__ import annotations

from dataclasses import dataclass

from eventcap.artifacts import BatchPlan
from eventcap.artifacts.pose import Detections, PoseSequence
from eventcap.artifacts.recording import Recording
from eventcap.core.stage import Port, StageSpec, group, param
from eventcap.energy.settings import IpoptConfig, SilConfig, StabConfig


@dataclass
class RefineTerms:
    """The terms of the refinement (paper Eq. 9), in the order they are summed (each: its weight, 0 = off, and its
    settings)."""

    sil: SilConfig = group(SilConfig, weight=1.0, step_ms=1.0, window_ms=None, loss="l2",
                           help="E_sil (Eq. 11): every frame's silhouette boundary against its closest events within "
                                "the batch (the paper's window T: window_ms null)")
    stab: StabConfig = group(StabConfig, help="E_stab (Eq. 10): the joints held near the batch solve's")


@dataclass
class SilhouetteRefineConfig:
    icp_iterations: int = param(4, ge=1, help="ICP iterations: render the estimate, find the closest event of every "
                                        "silhouette boundary pixel, solve (paper Sec. 3.3)")
    limits: dict[str, list[float]] = param(
        default_factory=dict, help="joint-limit overrides {parameter name: [min, max]} in radians (metres for "
                                   "root_t*), as in the solve stage; default skeleton.pose_bounds()")
    terms: RefineTerms = group(RefineTerms, help="the terms of the refinement: each one's weight (0: off) and settings")
    ipopt: IpoptConfig = group(IpoptConfig, max_iter=100, tol=1e-4, help="IPOPT's options for every solve")


#: Settings that moved when the config was nested: {old key: new key}.
REFINE_RENAMED = {
    "lambda_sil": "terms.sil.weight", "lambda_stab": "terms.stab.weight", "sil_dist": "terms.sil.dist",
    "sil_patch_px": "terms.sil.patch_px", "denoise_us": "terms.sil.denoise_us", "sil_loss": "terms.sil.loss",
    "sil_huber_px": "terms.sil.huber_px", "max_iter": "ipopt.max_iter", "tol": "ipopt.tol",
    "mumps_pivot_order": "ipopt.mumps_pivot_order"}


SILHOUETTE = StageSpec(
    name="silhouette", kind="refine", version=3,
    description="event-based pose refinement per tracking frame: silhouette boundary to closest event ICP, "
                "point-to-line E_sil + E_stab, joint limits (Sec. 3.3, CasADi + IPOPT)",
    config=SilhouetteRefineConfig,
    inputs={"recording": Port(Recording), "poses": Port(PoseSequence, doc="the solve's poses of the same batch"),
            "batches": Port(BatchPlan),
            "detections": Port(Detections, optional=True, doc="the detections the poses were solved with: the "
                                                              "world they are in (Detections.world_R)")},
    outputs={"poses": Port(PoseSequence)}, per_batch=True,
    run="eventcap_refine._impl:run_refine",
    renamed=REFINE_RENAMED,
)
