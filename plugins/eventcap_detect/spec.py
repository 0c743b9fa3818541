"""Specs of the detect stages (paper Sec. 3.2): `blazepose`, `simulated` and `detections_file`. Declarations only."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from eventcap.artifacts.pose import Detections
from eventcap.artifacts.recording import Recording
from eventcap.artifacts.tracking import LatentFrames
from eventcap.core.stage import Port, StageSpec, param

#: BlazePose's noise model shipped with the stage, measured on tuning captures (benchmarks/accuracy/detector_noise.py)
SHIPPED_NOISE = Path(__file__).resolve().parent / "models" / "blazepose_noise.json"


def noise_files(value: str) -> list[str]:
    """The file a ``noise`` setting names (``shipped``: the table shipped with the stage): its digest is part of the
    stage's cache key, so a changed table detects again (the detections carry the noise they state)."""
    return [str(SHIPPED_NOISE if value == "shipped" else value)]


@dataclass
class ViewChecksConfig:
    """What is in view and the checks against the events, shared by the detectors of real images
    (plugins/eventcap_detect/checks.py)."""

    checks: list[str] = param(default_factory=lambda: ["outside", "parts", "region", "scale", "agree"],
                              help="checks that reject a detection: outside (too few landmarks in the image) | "
                                   "parts (head and ankle in view, no hip) | region (a whole body that does not "
                                   "fit the moving region around it) | scale (a whole body too small for its own "
                                   "head and shoulders) | agree (images made from the events: too few of them "
                                   "show the person in the same place); [] = none")
    border_px: float = param(0.0, help="a landmark is in view when at least this far inside the image, px")
    min_in_view: int = param(3, help="check outside: fewer landmarks in the image reject the detection")
    region_ratio: float = param(0.5, help="check region: a whole body smaller than this x the moving region it "
                                          "lies in is rejected")
    edge_ratio: float = param(0.15, help="check region: a moving region reaching an image edge that a whole body "
                                         "keeps more than this share of the image away from rejects it")
    head_ratio: float = param(0.35, help="check scale: ear-to-ear width over this x the torso (neck to mid-hip) "
                                         "rejects a whole body")
    shoulder_ratio: float = param(0.9, help="check scale: shoulder width over this x the torso rejects a whole "
                                            "body")
    check_window_us: int = param(40000, help="check region: the events within this window around an image make "
                                             "its moving region, us")
    min_found: float = param(0.5, ge=0, le=1, help="the stage stops when fewer than this share of the images hold "
                                                   "an accepted detection (nothing to solve)", affects_result=False)


@dataclass
class SimulatedDetectorConfig:
    seed: int = param(0, ge=0, help="seed of the simulated detector's errors (with the run's ctx.rng)")
    sigma_px: float = param(2.0, ge=0, help="std of the Gaussian 2D error per image axis, pixels (before blur scaling)")
    outlier_prob: float = param(0.02, ge=0, le=1, help="probability that a 2D keypoint is an outlier (a wrong location)")
    outlier_radius_px: float = param(30.0, ge=0, help="outliers lie uniformly within this radius of the true point")
    flip_prob: float = param(0.02, ge=0, le=1, help="probability that a left/right keypoint pair is swapped (per frame and pair)")
    blur_gain: float = param(0.1, ge=0, help="2D error grows as 1 + blur_gain * (image motion during the exposure, px)")
    sigma_m: float = param(0.025, ge=0, help="std of the per-frame 3D joint error per axis, metres")
    bias_m: float = param(0.04, ge=0, help="std of a fixed random 3D offset per joint, drawn once per sequence, metres")
    confidence: float = param(0.9, gt=0, le=1, help="2D confidence of a sharp, correct keypoint (divided by the blur factor)")
    outlier_confidence: float = param(0.3, ge=0, le=1, help="factor on the confidence of outliers")
    confidence_3d: float = param(0.9, gt=0, le=1, help="3D confidence of a sharp joint inside the image (divided by the blur "
                                           "factor)")
    at: str = param("frames", help="frames: at the intensity frames (the method) | tracking: at every tracking "
                                   "frame, as if detected on sharp latent images (for the *_all baseline, "
                                   "stages/solve=all)", choices=("frames", "tracking"))
    tracking_step_us: int = param(1000, gt=0, help="with at=tracking: the tracking frame step, us")
    occlusion: bool = param(True, help="keypoints hidden by the body (z-buffer of the recording's template) get "
                                       "confidence 0")
    occlusion_margin_m: float = param(0.15, ge=0, help="a keypoint is hidden when the surface in front of it is nearer "
                                                 "than its depth minus this margin (joints lie inside the body)")
    min_found: float = param(0.5, ge=0, le=1, help="the stage stops when fewer than this share of the images hold "
                                                   "a detection", affects_result=False)


@dataclass
class DetectionsFileConfig(ViewChecksConfig):
    path: str = param("", help="detections: a folder of OpenPose JSON files (one per frame), a .json, .npz or "
                               ".csv file", file=True)
    format: str = param("auto", help="openpose | npz | csv | auto (folder or .json = openpose, else by extension)",
                        choices=("openpose", "npz", "csv", "auto"))
    layout: str = param("body25", help="keypoint layout of the file: body25 (OpenPose BODY_25, 25 points) | "
                                       "coco18 (OpenPose COCO, 18 points)", choices=("body25", "coco18"))
    mapping: dict[str, str] = param(default_factory=dict,
                                    help="overrides of the layout's keypoint -> landmark mapping: file keypoint "
                                         "(index '4' or layout name 'RWrist') -> landmark name or '' (ignore it)")
    match: str = param("order", help="OpenPose folders: order (n-th file in natural order = n-th frame) | number "
                                     "(the last number in the file name is the frame number)",
                       choices=("order", "number"))
    first_frame: int = param(0, ge=0, help="frame number (file names, 'frame' arrays/columns) of the recording's first "
                                     "intensity frame")
    time_tolerance_us: int = param(500, ge=0, help="rows with t_us are matched to the frame within this distance")
    path_3d: str = param("", help="optional npz/csv whose 3D joints replace those of `path` (e.g. VNect output "
                                   "next to OpenPose JSON)", file=True)
    frame_3d: str = param("world", help="axes of the root-relative 3D joints in the files: world | camera "
                                        "(rotated into world axes with the recording's camera)",
                          choices=("world", "camera"))
    unit_3d: str = param("m", help="unit of the 3D joints in the files: m | mm", choices=("m", "mm"))
    noise_px: float = param(1.0, gt=0, help="the detector's 2D noise per image axis from image to image, px (the "
                                            "default: a detector of BlazePose's class on sharp images)")
    offset_px: float = param(2.0, ge=0, help="the spread per image axis of a landmark's offset that stays over the "
                                           "capture, px (where the detector puts a hip or a shoulder)")
    noise_3d_mm: float = param(25.0, gt=0, help="the detector's noise of each root-relative 3D joint per axis from "
                                                "image to image, mm")
    offset_3d_mm: float = param(50.0, ge=0, help="the spread per axis of a 3D joint's offset that stays over the "
                                               "capture, mm (a monocular 3D network's idea of the body)")


@dataclass
class BlazePoseConfig(ViewChecksConfig):
    model: str = param("full", help="landmark network: full (the larger, more exact one) | lite (faster, less exact)",
                       choices=("full", "lite"))
    noise: str = param("shipped", file=noise_files,
                       help="the noise model the detections state, per kind of image (raw frames, latent images, "
                            "images made from the events): a JSON table of the shipped one's form, or shipped (the "
                            "stage's own table)")
    at: str = param("latent", help="images it looks at: frames (the raw, blurred intensity frames: the paper's "
                                   "*_linear) | latent (EDI latent images at the frame times: the method) | "
                                   "tracking (EDI latent images every tracking_step_us: the paper's *_all)",
                   choices=("frames", "latent", "tracking"))
    tracking_step_us: int = param(1000, gt=0, help="with at=tracking: the step between images, us")
    track: bool = param(True, help="take each image's crop from the previous pose (the model's own auxiliary "
                                   "points); false: find the person anew in every image")
    find: str = param("detector", help="how a lost person is found: detector (BlazePose's person detector, then "
                                       "the events if it sees nobody) | events (the box of the moving pixels); "
                                       "last, the landmark model on the whole image")
    events_window_us: int = param(20000, gt=0, help="events within this window around an image make its event box, us")
    detector_threshold: float = param(0.5, ge=0, le=1, help="minimum score of a person-detector box")
    presence_threshold: float = param(0.5, ge=0, le=1, help="minimum pose flag of the landmark model: below it, the person "
                                                "is lost")
    gamma: float = param(1.0, gt=0, help="the networks get linear intensity ** (1 / gamma); 1: linear, above 1 "
                                   "brightens the dark tones, below 1 darkens them")
    landmark_presence: float = param(0.5, help="a landmark is in view when the network's presence output (that "
                                               "it lies in the image) is at least this, and it lies in the image")
    event_images: list[str] = param(default_factory=lambda: ["reconstruction", "counts:25", "counts:50",
                                                             "surface:25", "surface:50"],
                                    help="when its images were reconstructed from the events (an event-only "
                                         "camera): the images of each moment it tries, keeping the one the network "
                                         "scores best: reconstruction (the high-pass image) | counts:MS (events per "
                                         "pixel over the last MS ms, 1-500) | surface:MS (a time surface over MS "
                                         "ms); [] = the reconstruction alone")
    min_agree: int = param(2, ge=1, help="check agree: of the images made from the events of a moment "
                                         "(event_images), at least this many must show the person where the kept "
                                         "pose puts them, or the pose lie next to such a pose of the moment before "
                                         "or after; 1 accepts a pose seen in one image alone")
    agree_ratio: float = param(0.2, gt=0, help="check agree: two images (of one moment, or of "
                                               "neighbouring moments) show the person in the same place when their "
                                               "poses' median landmark distance is at most this share of the kept "
                                               "pose's size (its box's diagonal)")


BLAZEPOSE = StageSpec(
    name="blazepose", kind="detect", version=12,
    description="BlazePose GHUM 3D (MediaPipe Pose) on the CPU, offline: 2D landmarks + root-relative 3D joints, "
                "with its noise model (models/blazepose_noise.json)",
    config=BlazePoseConfig,
    inputs={"recording": Port(Recording),
            "latent": Port(LatentFrames, optional=True, doc="EDI latent images (at=latent | tracking)")},
    outputs={"detections": Port(Detections)},
    run="eventcap_detect._impl:run_blazepose",
)

SIMULATED = StageSpec(
    name="simulated", kind="detect", version=3,
    description="simulated CNN detector: ground-truth projections + noise, outliers, flips, blur, 3D bias; its "
                "noise model is the one it simulates",
    config=SimulatedDetectorConfig, inputs={"recording": Port(Recording)},
    outputs={"detections": Port(Detections)},
    run="eventcap_detect._impl:run_simulated",
)

FILE = StageSpec(
    name="detections_file", kind="detect", version=6,
    description="2D/3D detections produced elsewhere (OpenPose JSON, npz, csv), aligned with the frames; their "
                "noise as the settings state it",
    config=DetectionsFileConfig, inputs={"recording": Port(Recording)},
    outputs={"detections": Port(Detections)},
    run="eventcap_detect._impl:run_file",
)
