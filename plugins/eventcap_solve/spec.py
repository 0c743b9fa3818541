"""Spec of the Sec. 3.2 stage: hybrid pose batch optimisation. Declarations only: the solver loads when it runs."""

from __future__ import annotations

from dataclasses import dataclass

from eventcap.artifacts import BatchPlan
from eventcap.artifacts.pose import Detections, PoseSequence
from eventcap.artifacts.recording import Recording
from eventcap.artifacts.tracking import SlicedTracks
from eventcap.core.stage import Port, StageSpec, param


@dataclass
class BatchSolveConfig:
    mode: str = param("batch", help="batch (the method) | per_frame (w/o_batch) | linear (*_linear: fits at the two "
                                    "intensity frames, interpolated) | all (*_all: detections at every frame) | "
                                    "odometry (events only from S_0's fit, for the fuse stage; not in the paper)",
                     choices=("batch", "per_frame", "linear", "all", "odometry"))
    icp_rounds: int = param(2, ge=1, help="alternations of correspondence search and solve (ICP)")
    lambda_cor: float = param(50.0, ge=0, help="weight of E_cor, the event correspondences (paper's λ_adj)")
    lambda_2d: float = param(200.0, ge=0, help="weight of E_2D (image residuals in focal-normalised units)")
    robust_2d_px: float = param(2.0, ge=0, help="Cauchy loss scale of E_2D per landmark, px (0 = least squares, the "
                                          "paper): limits the pull of detector outliers and left/right flips")
    lambda_3d: float = param(1.0, ge=0, help="weight of E_3D (metres)")
    lambda_temp: float = param(80.0, ge=0, help="weight of E_temp, holding joints of parts without correspondences")
    lambda_damp: float = param(1e-3, ge=0, help="weight of the proximal term towards each solve's start (not in the paper)")
    phi_scope: str = param("batch", help="E_temp indicator: batch (paper: per batch) | pair (per frame pair)",
                          choices=("batch", "pair"))
    max_tracks: int = param(0, ge=0, help="use at most this many tracks per batch, the longest (0 = all)")
    edge_margin_px: float = param(1.0, ge=0, help="tracks nearer than this to a silhouette/self-occlusion edge of the "
                                            "current estimate give no correspondence (0 = keep all)")
    boundary: str = param("fixed", help="fixed: S_0 and S_N stay at their detection fits, shared with the "
                                        "neighbouring batches (continuous joined motion) | free: solved too")
    still_m: float = param(0.03, ge=0, help="E_temp holds only joints that moved less than this between the end fits, "
                                      "metres (0 = every joint without correspondences, the paper's literal phi)")
    limits: dict[str, list[float]] = param(
        default_factory=dict, help="joint-limit overrides {parameter name: [min, max]} in radians (metres for "
                                   "root_t*), e.g. a subject's reduced range: {l_knee_flex: [0.0, 2.0]}")
    max_iter: int = param(100, ge=1, affects_result=False,
                          help="IPOPT iteration limit per solve; reaching it fails the batch. Not part of the cache "
                               "key: a solve that converges within any cap gives the same poses, and failures are "
                               "never cached, so raising the cap recomputes only the batches that failed")
    tol: float = param(1e-6, gt=0, help="IPOPT convergence tolerance")
    mumps_pivot_order: int = param(0, ge=0, le=7, help="MUMPS ordering (0 AMD ... 7 auto), pinned for reproducibility")


BATCH = StageSpec(
    name="batch", kind="solve", version=2,  # 2: its terms are factors (sums in another order)
    description="hybrid batch optimisation of all 1 kHz poses of a batch: event correspondences, 2D/3D detections, "
                "temporal term, joint limits (Sec. 3.2, CasADi + IPOPT)",
    config=BatchSolveConfig,
    inputs={"recording": Port(Recording), "sliced": Port(SlicedTracks), "detections": Port(Detections),
            "batches": Port(BatchPlan)},
    outputs={"poses": Port(PoseSequence)}, per_batch=True,
    run="eventcap_solve._impl:run_batch",
)


@dataclass
class FuseConfig:
    rho: float = param(0.0, ge=0, help="weight of the event odometry against the detection fits in the pose graph "
                                 "(0 = estimated from the data: innovation variance and lag-1 covariance)")


FUSE = StageSpec(
    name="fuse", kind="fuse", version=1,
    description="pose graph over the intensity frames: every batch's detection fit and event-only odometry "
                "(solve mode odometry) fused across batches (not in the paper; see eventcap_solve.fusion)",
    config=FuseConfig,
    inputs={"odometry": Port(PoseSequence, "every batch's solve in mode odometry", all_batches=True)},
    outputs={"anchors": Port(PoseSequence, doc="the fused poses at the intensity frames")},
    run="eventcap_solve.fusion:run_fuse",
)


@dataclass
class PlaceConfig:
    pass


PLACE = StageSpec(
    name="place", kind="fuse", version=1,
    description="a batch's event trajectory placed onto the fused poses at its two intensity frames (the end "
                "mismatch spread linearly), so the joined motion is continuous",
    config=PlaceConfig,
    inputs={"odometry": Port(PoseSequence, "this batch's solve in mode odometry"),
            "anchors": Port(PoseSequence, "the fuse stage's poses at the intensity frames")},
    outputs={"poses": Port(PoseSequence)}, per_batch=True,
    run="eventcap_solve.fusion:run_place",
)
