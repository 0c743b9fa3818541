"""Spec of the spline solve (not in the paper): a continuous-time pose trajectory per window of batches.
Declarations only: the solver loads when it runs."""

from __future__ import annotations

from dataclasses import dataclass

from eventcap.artifacts import BatchPlan
from eventcap.artifacts.pose import Detections, PoseSequence
from eventcap.artifacts.recording import Recording
from eventcap.artifacts.tracking import SlicedTracks
from eventcap.body.template import Template
from eventcap.core.stage import Port, StageSpec, group, param
from eventcap.energy.settings import (
    BonesNoise,
    ContactConfig,
    ContextNoise,
    CorNoise,
    FloorNoise,
    IpoptConfig,
    Joints3DNoise,
    Landmarks2DNoise,
    PriorNoise,
    SilNoise,
    SlideNoise,
    SmoothingConfig,
    FlowNoise,
    StillNoise,
    StillnessConfig,
)


@dataclass
class SplineTracks:
    """Which event tracks a window's E_cor uses, and where."""

    step: int = param(5, ge=1, help="tracking frames between the two frames of a correspondence (1: adjacent frames)")
    scope: str = param("own", choices=("window", "own"),
                       help="whose tracks: the batches the window keeps (own: its run of window_step batches) | every "
                            "batch of the window (window; about twice the solve time)")
    edge_margin_px: float = param(1.0, ge=0, help="tracks nearer than this to a silhouette or self-occlusion edge of "
                                                  "the estimate give no correspondence, px")


@dataclass
class SplineTerms:
    """The terms of the spline solve's energy, in the order they are summed: each weighted by the noise of what it
    reads (its sigma, in its own units), ``gain`` 0 turns one off (eventcap.energy.terms lists them,
    eventcap.energy.settings says how a noise model weighs)."""

    landmarks_2d: Landmarks2DNoise = group(Landmarks2DNoise, help="E_2D: the detected 2D landmarks, weighted by the "
                                                                  "detector's noise (robust)")
    joints_3d: Joints3DNoise = group(Joints3DNoise, help="E_3D: the detected root-relative 3D joints, weighted by the "
                                                         "detector's noise")
    cor: CorNoise = group(CorNoise, sigma_px=6.3, loss_scale=0.0,
                          help="E_cor: the event tracks' correspondences on the mesh (an effective noise, the "
                               "association's error at a solve's estimate included)")
    sil: SilNoise = group(SilNoise, sigma_px=44.5, loss_scale=0.0225,
                          help="E_sil (paper Sec. 3.3): the silhouette boundary against its closest events at the "
                               "solved batches' frames (an effective noise; Huber beyond 1 px)")
    flow: FlowNoise = group(FlowNoise, gain=0.0, help="E_flow (not in the paper): the silhouette boundary's normal "
                                                      "image speed against the events' local planes (off by default)")
    still: StillNoise = group(StillNoise, sigma_px_s=2.24, help="E_still (not in the paper): joints the events call "
                                                                "still do not move in the image")
    prior: PriorNoise = group(PriorNoise, q_default=5000.0, q_min=500.0, help="the motion prior (not in the paper): each pose parameter a "
                                               "white-noise acceleration whose power the fits around the window "
                                               "choose")
    context: ContextNoise = group(ContextNoise, help="the context pull (not in the paper): each parameter near the "
                                                     "smoothed fits around the window (off)")
    floor: FloorNoise = group(FloorNoise, sigma_mm=70.7, help="the floor (not in the paper): sole points in contact on it, none "
                                               "below it")
    slide: SlideNoise = group(SlideNoise, sigma_mm_s=707.0, help="no sliding (not in the paper): sole points in contact do not move "
                                               "along the floor")
    bones: BonesNoise = group(BonesNoise, help="foreshortening (not in the paper): each limb bone's depth extent "
                                               "from its length and 2D points (off)")


@dataclass
class SplineSolveConfig:
    half_window: int = param(2, ge=0, help="batches on each side of the batch being solved: the window spans "
                                     "2·half_window + 1 batches (shifted inwards at the ends of the recording)")
    window_step: int = param(1, ge=1, help="batches between the middles of consecutive windows: the batches are cut "
                                           "into runs of window_step, each kept by one window of 2·half_window + 1 "
                                           "batches around the run's middle batch, which solves it (the others solve "
                                           "nothing: status in_window); at most 2·half_window (windows must overlap "
                                           "to be blended); 1: a window per batch")
    knot_ms: float = param(10.0, gt=0, help="knot spacing of the cubic B-spline, ms (control points every knot_ms)")
    icp_rounds: int = param(2, ge=0, help="alternations of association (tracks' correspondences, silhouette events, "
                                          "contacts at the current estimate) and solve (ICP; 0: one solve without "
                                          "the events' correspondences)")
    icp_settle_px: float = param(0.0, ge=0, help="end the ICP rounds when a round's association has settled: every "
                                                 "term that associates moved its residuals at the last solution by "
                                                 "less than this RMS, px (that round's solve is skipped); 0: every "
                                                 "round, the change not measured")
    damp: float = param(1e-4, ge=0, help="proximal pull of the control points towards each solve's start (rad and m "
                                         "alike; not a term of the energy: it keeps directions nothing observes "
                                         "from drifting)")
    uncertainty_limits: float = param(0.01, ge=0, help="weight of the joint limits read as a prior (each angle's "
                                                       "variance over its range, (max - min)² / 12) in the Laplace "
                                                       "approximation of each joint's σ, relative to the energy "
                                                       "(dimensionless; 0: none, only the proximal pull bounds what "
                                                       "no term observes); not in the solve itself")
    landmarks: str = param("widths", choices=("template", "widths"),
                           help="the hip and shoulder landmarks of E_2D: the template's joints (template), or where "
                                "the detector puts them on this person, their widths measured over the capture from "
                                "the detections and the per-frame fits (widths; eventcap.energy.landmarks)")
    limits: dict[str, list[float]] = param(
        default_factory=dict, help="joint-limit overrides {parameter name: [min, max]} (radians; metres for root_t*)")
    tracks: SplineTracks = group(SplineTracks, help="which event tracks E_cor uses")
    smoothing: SmoothingConfig = group(SmoothingConfig, min_fps=20.0,
                                       help="evidence: the per-frame fits around a window (the prior's process power, "
                                            "the context pull)")
    stillness: StillnessConfig = group(StillnessConfig, help="evidence: how still the events show each joint "
                                                             "(E_still, the context pull's gate, contact)")
    contact: ContactConfig = group(ContactConfig, help="evidence: when a sole point counts as in contact with the "
                                                       "floor (the floor and slide terms)")
    terms: SplineTerms = group(SplineTerms, help="the terms of the energy: each one's noise, gain (0: off) and "
                                                 "settings")
    ipopt: IpoptConfig = group(IpoptConfig, barrier="adaptive", max_iter=1000,
                               help="IPOPT's options for every solve of a window")


#: Settings that moved when the config was nested, and the weights that became noise models: {old key: new key};
#: an old key is refused naming its new one.
_PRIOR_FROM_DATA = "terms.prior.pool"  # the prior's power per parameter is chosen from the fits around the window
SPLINE_RENAMED = {
    "lambda_2d": "terms.landmarks_2d.sigma_px", "robust_2d_px": "terms.landmarks_2d.loss_scale",
    "lambda_3d": "terms.joints_3d.sigma_mm", "lambda_cor": "terms.cor.sigma_px", "robust_cor_px": "terms.cor.loss_scale",
    "cor_step": "tracks.step", "tracks": "tracks.scope", "edge_margin_px": "tracks.edge_margin_px",
    "lambda_sil": "terms.sil.sigma_px", "sil_step_ms": "terms.sil.step_ms", "sil_window_ms": "terms.sil.window_ms",
    "sil_patch_px": "terms.sil.patch_px", "sil_loss": "terms.sil.loss", "sil_huber_px": "terms.sil.loss_scale",
    "sil_dist": "terms.sil.dist", "lambda_still": "terms.still.sigma_px_s", "still_radius_px": "stillness.radius_px",
    "still_rate_hz": "stillness.rate_hz", "still_hold_ms": "stillness.hold_ms",
    "still_sweep_ms": "stillness.sweep_ms", "prior": "terms.prior.order", "lambda_prior": "terms.prior.q_default",
    "prior_inertia": _PRIOR_FROM_DATA, "prior_inertia_cap": _PRIOR_FROM_DATA, "prior_inertia_floor": _PRIOR_FROM_DATA,
    "prior_gain_max": _PRIOR_FROM_DATA, "prior_gain_criterion": "smoothing.criterion",
    "prior_gain_min_fps": "smoothing.min_fps", "prior_context_s": "smoothing.seconds",
    "lambda_context": "terms.context.gain", "context_gate_floor": "terms.context.gate_floor",
    "lambda_floor": "terms.floor.sigma_mm", "lambda_slide": "terms.slide.sigma_mm_s", "contact_speed_mps":
    "contact.speed_mps", "contact_height_m": "contact.height_m", "lambda_bones": "terms.bones.gain",
    "bones_sign_m": "terms.bones.sign_m", "bones_2d_px": "terms.bones.noise_2d_px", "lambda_damp": "damp",
    "max_iter": "ipopt.max_iter", "tol": "ipopt.tol", "mumps_pivot_order": "ipopt.mumps_pivot_order",
    # the weights tuned for one detector, now noise models (issue "the events add")
    "terms.landmarks_2d.weight": "terms.landmarks_2d.sigma_px", "terms.landmarks_2d.robust_px":
    "terms.landmarks_2d.loss_scale", "terms.joints_3d.weight": "terms.joints_3d.sigma_mm",
    "terms.cor.weight": "terms.cor.sigma_px", "terms.cor.robust_px": "terms.cor.loss_scale",
    "terms.sil.weight": "terms.sil.sigma_px", "terms.sil.huber_px": "terms.sil.loss_scale",
    "terms.still.weight": "terms.still.sigma_px_s", "terms.prior.weight": "terms.prior.q_default",
    "terms.prior.inertia": _PRIOR_FROM_DATA, "terms.prior.inertia_cap": _PRIOR_FROM_DATA,
    "terms.prior.inertia_floor": _PRIOR_FROM_DATA, "terms.prior.gain_max": _PRIOR_FROM_DATA,
    "terms.context.weight": "terms.context.gain", "terms.floor.weight": "terms.floor.sigma_mm",
    "terms.slide.weight": "terms.slide.sigma_mm_s", "terms.bones.weight": "terms.bones.gain"}


SPLINE = StageSpec(
    name="spline", kind="solve", version=15,
    description="continuous-time solve (not in the paper): a cubic B-spline in the 33 pose parameters over a "
                "window of batches, fitted to the detections wherever they are (robust, each weighted by the "
                "detector's noise), the event correspondences of this batch's tracks (or the window's), the event "
                "silence and a motion prior whose power the data choose, joint limits on the control points "
                "(CasADi + IPOPT); "
                "the output is the window's whole curve at the tracking rate (the stitch stage blends the windows)",
    config=SplineSolveConfig,
    inputs={"recording": Port(Recording, "its events over the unit's window (the unit's batches with up to "
                                         "2·half_window batches on each side: windows shift inwards at the ends), "
                                         "its camera and template; not its frames or ground truth",
                          window=lambda config: 2 * int(config.half_window), without=("frames", "ground_truth")),
            "sliced": Port(SlicedTracks, "every batch's tracks (a window reads those of its batches)",
                           all_batches=True),
            "detections": Port(Detections),
            "batches": Port(BatchPlan, "the recording's batches"),
            "chunks": Port(BatchPlan, "the units solved one task each, a window with margins around each (the "
                                      "chunks stage's; not connected: one window per batch)", optional=True)},
    outputs={"poses": Port(PoseSequence)}, per_batch=True, plan="chunks",
    run="eventcap_spline._impl:run_spline",
    renamed=SPLINE_RENAMED,
)


@dataclass
class ChunksConfig:
    seconds: float = param(1.0, gt=0, le=3600, help="length of a chunk, s: consecutive batches are grouped until "
                                                    "they span this (a last chunk under half of it joins the one "
                                                    "before)")


CHUNKS = StageSpec(
    name="chunks", kind="plan", version=1,
    description="the recording's batches grouped into chunks of about `seconds` (not in the paper): a node cut by "
                "the chunks solves each chunk as one task, cached per chunk",
    config=ChunksConfig,
    inputs={"batches": Port(BatchPlan, "the recording's batches")},
    outputs={"chunks": Port(BatchPlan, doc="one row per chunk: its first batch's start and frame, its last batch's "
                                           "end")},
    run="eventcap_spline.chunks:run_chunks",
)


@dataclass
class StitchConfig:
    taper: float = param(0.5, gt=0, le=0.5, help="fraction of a window's length over which its blending weight rises from 0 to 1 "
                                   "at each of its ends (0.5: a bump over the whole window), or over its overlap with "
                                   "its neighbour where that is shorter; a window's end at the start or end of the "
                                   "recording is not tapered")


STITCH = StageSpec(
    name="stitch", kind="fuse", version=7,
    description="the spline solve's overlapping windows blended into one motion over the whole recording, each "
                "window weighted by a C² bump over its span (no seam where batches meet; not in the paper)",
    config=StitchConfig,
    inputs={"windows": Port(PoseSequence, "every batch's spline-solve window", all_batches=True),
            "template": Port(Template, "the body the windows pose: where they overlap, their disagreement in mm is "
                                      "added to the σ (not connected: σ blended alone)", optional=True)},
    outputs={"motion": Port(PoseSequence, doc="the joined motion at every tracking frame")},
    run="eventcap_spline.stitch:run_stitch",
)


@dataclass
class CutConfig:
    pass


CUT = StageSpec(
    name="cut", kind="fuse", version=2,
    description="a batch's frames of the stitched whole-recording motion",
    config=CutConfig,
    inputs={"motion": Port(PoseSequence, "the stitch stage's motion"), "batches": Port(BatchPlan)},
    outputs={"poses": Port(PoseSequence)}, per_batch=True,
    run="eventcap_spline.stitch:run_cut",
)
