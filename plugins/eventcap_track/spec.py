"""Specs of the Sec. 3.1 stages track (EKLT, KLT on latent images, the oracle) and slice (B-spline); sharpen (EDI)
is in eventcap_sharpen."""

from __future__ import annotations

from dataclasses import dataclass

from eventcap.artifacts import BatchPlan
from eventcap.artifacts.pose import Detections
from eventcap.artifacts.recording import Recording
from eventcap.artifacts.tracking import LatentFrames, SlicedTracks, Tracks
from eventcap.core.stage import Port, StageSpec, param


@dataclass
class FeatureRegionConfig:
    """Where a tracker detects its features (shared by the track stages)."""

    roi: str = param("actor", help="where features are detected: actor (around the 2D detections of the batch's "
                                   "frames, if the node gets detections) | image (everywhere)")
    roi_margin_px: float = param(12.0, ge=0, help="the actor region: bounding box of the confident 2D keypoints grown by "
                                            "this margin")


@dataclass
class EkltStageConfig(FeatureRegionConfig):
    patch_px: int = param(25, ge=5, odd=True, help="side of the feature patch (odd)")
    max_features: int = param(100, ge=1, help="Shi-Tomasi corners detected per start image")
    min_distance_px: float = param(10.0, ge=0, help="minimum distance between corners")
    quality_level: float = param(0.01, gt=0, le=1, help="relative corner quality threshold")
    warp: str = param("rotation", help="patch warp: translation | rotation | affine",
                     choices=("translation", "rotation", "affine"))
    update_every: int = param(60, ge=1, help="events in a patch between two updates")
    max_cost: float = param(0.8, gt=0, help="drop a track when 1 - cos(predicted, measured increments) exceeds this")
    lag_gain: float = param(0.45, ge=0, help="compensation of the DVS threshold lag (0 = off)")
    stitch_px: float = param(4.0, ge=0, help="forward/backward tracks are stitched at mid-batch within this distance")
    relocate_radius_px: int = param(6, ge=0, help="half-side of the patch that finds forward points on the end image "
                                    "(backward starts); keep it inside a limb")
    direction: str = param("both", help="both (forward + backward, stitched) | forward | backward",
                          choices=("both", "forward", "backward"))


@dataclass
class KltStageConfig(FeatureRegionConfig):
    max_features: int = param(100, ge=1, help="Shi-Tomasi corners detected on the start image")
    min_distance_px: float = param(10.0, ge=0, help="minimum distance between corners")
    quality_level: float = param(0.01, gt=0, le=1, help="relative corner quality threshold")
    step_us: int = param(1000, gt=0, help="spacing of the EDI latent images LK runs on")
    window_px: int = param(21, ge=3, help="Lucas-Kanade window")
    max_level: int = param(3, ge=0, help="pyramid levels")


@dataclass
class OracleTrackConfig:
    max_tracks: int = param(300, ge=1, help="at most this many of the recording's ground-truth surface points")
    noise_px: float = param(0.0, ge=0, help="std of Gaussian noise added to every sample, px (0 = exact)")
    seed: int = param(0, ge=0, help="seed of the noise")


@dataclass
class SliceConfig:
    rate_hz: float = param(1000.0, gt=0, help="tracking frame rate (samples per second)")
    sigma_px: float = param(0.2, gt=0, help="expected noise of the tracked positions (weights the data term)")
    accel_px_s2: float = param(1e5, gt=0, help="expected acceleration scale (weights the smoothness penalty)")
    knot_spacing_us: int = param(2000, gt=0, help="largest spacing of the spline knots")


BSPLINE = StageSpec(
    name="bspline", kind="slice", version=2,
    description="smoothing B-spline per track, sampled at every tracking frame (1 ms)",
    config=SliceConfig, inputs={"tracks": Port(Tracks), "batches": Port(BatchPlan)},
    outputs={"sliced": Port(SlicedTracks)}, per_batch=True,
    run="eventcap_track._impl:run_bspline",
)

EKLT = StageSpec(
    name="eklt", kind="track", version=3,
    description="EKLT: asynchronous photometric feature tracking with events, forward + backward, stitched",
    config=EkltStageConfig,
    inputs={"recording": Port(Recording, window=0, without=("frames", "ground_truth")),
            "latent": Port(LatentFrames, window=0),
            "batches": Port(BatchPlan),
            "detections": Port(Detections, optional=True, doc="2D keypoints that place the actor region")},
    outputs={"tracks": Port(Tracks)}, per_batch=True,
    run="eventcap_track._impl:run_eklt",
)

KLT_LATENT = StageSpec(
    name="klt_latent", kind="track", version=2,
    description="baseline: pyramidal Lucas-Kanade on EDI latent images every 1 ms (the naive approach)",
    config=KltStageConfig,
    inputs={"recording": Port(Recording, window=0, without=("frames", "ground_truth")),
            "latent": Port(LatentFrames, window=0),
            "batches": Port(BatchPlan),
            "detections": Port(Detections, optional=True, doc="2D keypoints that place the actor region")},
    outputs={"tracks": Port(Tracks)}, per_batch=True,
    run="eventcap_track._impl:run_klt_latent",
)

ORACLE = StageSpec(
    name="oracle", kind="track", version=1,
    description="SIMULATED: ground-truth surface-point tracks of a synthetic recording (an oracle, to measure the "
                "solver apart from the tracker; not a method)",
    config=OracleTrackConfig,
    # latent and detections are accepted and unused, so the stage drops into the pipelines that wire a tracker's
    # inputs (default, no_refine) with just stages/track=oracle.
    inputs={"recording": Port(Recording), "latent": Port(LatentFrames, optional=True), "batches": Port(BatchPlan),
            "detections": Port(Detections, optional=True, doc="unused (accepted so the default pipeline wires it)")},
    outputs={"tracks": Port(Tracks)}, per_batch=True,
    run="eventcap_track._impl:run_oracle",
)
