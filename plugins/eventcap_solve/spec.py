"""Spec of the Sec. 3.2 stage: hybrid pose batch optimisation. Declarations only: the solver loads when it runs."""

from __future__ import annotations

from dataclasses import dataclass

from eventcap.artifacts import BatchPlan
from eventcap.artifacts.pose import Detections, PoseSequence
from eventcap.artifacts.recording import Recording
from eventcap.artifacts.tracking import SlicedTracks
from eventcap.core.stage import Port, StageSpec, group, param
from eventcap.energy.settings import CorConfig, IpoptConfig, Joints3DConfig, Landmarks2DConfig, TempConfig


@dataclass
class BatchTracks:
    """Which event tracks a batch's E_cor uses, and where."""

    max_tracks: int = param(0, ge=0, help="use at most this many tracks per batch, those valid at the most frames "
                                          "(0: all)")
    edge_margin_px: float = param(1.0, ge=0, help="tracks nearer than this to a silhouette or self-occlusion edge "
                                                  "of the current estimate give no correspondence, px (0: keep all)")


@dataclass
class BatchTerms:
    """The terms of the batch energy (paper Eq. 4), in the order they are summed (each: its weight, 0 = off, and its
    settings)."""

    landmarks_2d: Landmarks2DConfig = group(Landmarks2DConfig, help="E_2D (Eq. 6) at frames 0 and N")
    joints_3d: Joints3DConfig = group(Joints3DConfig, help="E_3D (Eq. 7) at frames 0 and N")
    cor: CorConfig = group(CorConfig, help="E_cor (Eq. 5): the event tracks' correspondences between every two frames")
    temp: TempConfig = group(TempConfig, help="E_temp (Eq. 8): parts without correspondences held still")


@dataclass
class BatchSolveConfig:
    mode: str = param("batch", help="batch (the method) | per_frame (w/o_batch) | linear (*_linear: fits at the two "
                                    "intensity frames, interpolated) | all (*_all: detections at every frame) | "
                                    "odometry (events only from S_0's fit, for the fuse stage; not in the paper)",
                     choices=("batch", "per_frame", "linear", "all", "odometry"))
    icp_rounds: int = param(2, ge=1, help="alternations of correspondence search and solve (ICP)")
    damp: float = param(1e-3, ge=0, help="proximal pull of every frame's pose towards each solve's start (rad and m "
                                         "alike; not in the paper: it keeps angles nothing observes from drifting)")
    boundary: str = param("fixed", choices=("fixed", "free"),
                          help="fixed: S_0 and S_N stay at their detection fits, shared with the neighbouring batches "
                               "(continuous joined motion) | free: solved too")
    limits: dict[str, list[float]] = param(
        default_factory=dict, help="joint-limit overrides {parameter name: [min, max]} in radians (metres for "
                                   "root_t*), e.g. a subject's reduced range: {l_knee_flex: [0.0, 2.0]}")
    tracks: BatchTracks = group(BatchTracks, help="which event tracks E_cor uses")
    terms: BatchTerms = group(BatchTerms, help="the terms of the energy: each one's weight (0: off) and settings")
    ipopt: IpoptConfig = group(IpoptConfig, max_iter=100, help="IPOPT's options for every solve of a batch")


#: Settings that moved when the config was nested: {old key: new key}.
BATCH_RENAMED = {
    "lambda_cor": "terms.cor.weight", "lambda_2d": "terms.landmarks_2d.weight",
    "robust_2d_px": "terms.landmarks_2d.robust_px", "lambda_3d": "terms.joints_3d.weight",
    "lambda_temp": "terms.temp.weight", "lambda_damp": "damp", "phi_scope": "terms.temp.scope",
    "max_tracks": "tracks.max_tracks", "edge_margin_px": "tracks.edge_margin_px", "still_m": "terms.temp.still_m",
    "max_iter": "ipopt.max_iter", "tol": "ipopt.tol", "mumps_pivot_order": "ipopt.mumps_pivot_order"}


BATCH = StageSpec(
    name="batch", kind="solve", version=3,
    description="hybrid batch optimisation of all 1 kHz poses of a batch: event correspondences, 2D/3D detections, "
                "temporal term, joint limits (Sec. 3.2, CasADi + IPOPT)",
    config=BatchSolveConfig,
    inputs={"recording": Port(Recording), "sliced": Port(SlicedTracks), "detections": Port(Detections),
            "batches": Port(BatchPlan)},
    outputs={"poses": Port(PoseSequence)}, per_batch=True,
    run="eventcap_solve._impl:run_batch",
    renamed=BATCH_RENAMED,
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
