"""Spec of the Sec. 3.3 stage: event-based pose refinement. Declarations only: the solver loads when it runs."""

from __future__ import annotations

from dataclasses import dataclass

from eventcap.artifacts import BatchPlan
from eventcap.artifacts.pose import Detections, PoseSequence
from eventcap.artifacts.recording import Recording
from eventcap.core.stage import Port, StageSpec, param


@dataclass
class SilhouetteRefineConfig:
    icp_iterations: int = param(4, ge=1, help="ICP iterations: render the estimate, find the closest event of every "
                                        "silhouette boundary pixel, solve (paper Sec. 3.3)")
    lambda_sil: float = param(1.0, ge=0, help="weight of E_sil, the point-to-line distances of boundary points to their "
                                        "events (image residuals in focal-normalised units, as the solve)")
    lambda_stab: float = param(5.0, ge=0, help="weight of E_stab, joints held near the batch solve's (metres)")
    sil_dist: float = param(4.0, ge=0, help="λ_dist of the closest event search (Eq. 12): weight of the squared time "
                                            "offset in batch durations against the squared distance in pixels")
    sil_patch_px: int = param(8, ge=1, help="side of the square searched around each boundary pixel, pixels (centred "
                                            "on the pixel: offsets -sil_patch_px/2..sil_patch_px/2)")
    denoise_us: int = param(5000, ge=0, help="drop events without another event in their 3x3 pixel neighbourhood "
                                             "within this many microseconds before searching (background-activity "
                                             "filter, not in the paper; 0 = search all events)")
    sil_loss: str = param("l2", help="loss on the point-to-line residuals: l2 (the paper) | huber",
                          choices=("l2", "huber"))
    sil_huber_px: float = param(1.0, gt=0, help="Huber threshold in pixels (sil_loss=huber): beyond it residuals "
                                                "count linearly")
    limits: dict[str, list[float]] = param(
        default_factory=dict, help="joint-limit overrides {parameter name: [min, max]} in radians (metres for "
                                   "root_t*), as in the solve stage; default skeleton.pose_bounds()")
    max_iter: int = param(100, ge=1, affects_result=False,
                          help="IPOPT iteration limit per solve; reaching it fails the batch. Not part of the cache "
                               "key (failures are never cached)")
    tol: float = param(1e-4, gt=0, help="IPOPT convergence tolerance (scaled NLP error)")
    mumps_pivot_order: int = param(0, ge=0, le=7, help="MUMPS ordering (0 AMD ... 7 auto), pinned for reproducibility")


SILHOUETTE = StageSpec(
    name="silhouette", kind="refine", version=2,  # 2: its terms are factors (sums in another order)
    description="event-based pose refinement per tracking frame: silhouette boundary to closest event ICP, "
                "point-to-line E_sil + E_stab, joint limits (Sec. 3.3, CasADi + IPOPT)",
    config=SilhouetteRefineConfig,
    inputs={"recording": Port(Recording), "poses": Port(PoseSequence, doc="the solve's poses of the same batch"),
            "batches": Port(BatchPlan),
            "detections": Port(Detections, optional=True, doc="the detections the poses were solved with: the "
                                                              "world they are in (Detections.world_R)")},
    outputs={"poses": Port(PoseSequence)}, per_batch=True,
    run="eventcap_refine._impl:run_refine",
)
