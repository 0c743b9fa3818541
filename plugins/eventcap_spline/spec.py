"""Spec of the spline solve (not in the paper): a continuous-time pose trajectory per window of batches.
Declarations only: the solver loads when it runs."""

from __future__ import annotations

from dataclasses import dataclass

from eventcap.artifacts import BatchPlan
from eventcap.artifacts.pose import Detections, PoseSequence
from eventcap.artifacts.recording import Recording
from eventcap.artifacts.tracking import SlicedTracks
from eventcap.core.stage import Port, StageSpec, param


@dataclass
class SplineSolveConfig:
    half_window: int = param(2, ge=0, help="batches on each side of the batch being solved: the window spans "
                                     "2·half_window + 1 batches (shifted inwards at the ends of the recording)")
    window_step: int = param(1, ge=1, help="batches between the middles of consecutive windows: the batches are cut "
                                           "into runs of window_step, each kept by one window of 2·half_window + 1 "
                                           "batches around the run's middle batch, which solves it (the others solve "
                                           "nothing: status in_window); runs whose windows are the same batches "
                                           "(shifted inwards at the recording's ends) are one run; stitch blends "
                                           "the windows. At most 2·half_window (windows must overlap); 1: a window "
                                           "per batch")
    knot_ms: float = param(10.0, gt=0, help="knot spacing of the cubic B-spline, ms (control points every knot_ms)")
    prior: str = param("acceleration", help="motion prior: acceleration | jerk (∫‖S''‖² or ∫‖S'''‖² dt)",
                       choices=("acceleration", "jerk"))
    lambda_prior: float = param(1e-4, ge=0, help="weight of the motion prior, the integral of the squared acceleration "
                                          "(or jerk) of the poses (rad and m, time in s); 5e-4 until the event-"
                                          "silence term held the resting joints, 1e-4 measured better with it "
                                          "(docs/spline-solve.md)")
    prior_inertia: float = param(1.5, ge=0, help="exponent of the motion prior's gain per rotation, (I_p / mean I)^x, "
                                           "I_p the inertia of the body that pose parameter turns (de Leva's "
                                           "segments on the actor's bones, eventcap.body.segments): light parts "
                                           "(forearm, foot) may accelerate more than the trunk; 0 = λ_prior for all")
    prior_inertia_cap: float = param(1.0, ge=1, finite=False, help="largest of those gains (1: parts lighter than the mean are held "
                                               "less, none more; .inf: the gains' geometric mean is 1)")
    prior_inertia_floor: float = param(0.04, ge=0, le=1, help="smallest of those gains (0.04: the ankles, ~0.002 by their "
                                                  "inertia, are held like the elbows; their jitter was most of the "
                                                  "25 fps velocity error the lighter prior added)")
    prior_gain_max: float = param(10.0, ge=1, help="largest gain of the motion prior per pose parameter, chosen per window "
                                             "from the per-frame fits around it (each parameter's smoothing by "
                                             "prior_gain_criterion, scaled by the detections' curvature; see "
                                             "solve.prior_gain): static parameters get up to this much more "
                                             "smoothing; 1 = λ_prior for all")
    prior_gain_criterion: str = param("gcv", choices=("reml", "gcv"),
                                      help="how each parameter's fits choose its smoothing for those gains: gcv | "
                                           "reml (eventcap.analysis.smoothing; REML held fast_wave's waving arm at 25 fps)")
    prior_gain_min_fps: float = param(20.0, ge=0, help="choose those gains (and the context pull) only when the intensity "
                                                 "frames come at least this often (frames per second; 0 = always): "
                                                 "at 10 fps the fits undersample the punches and kicks, whose "
                                                 "parameters would be held as if at rest")
    prior_context_s: float = param(1.0, ge=0, help="seconds of intensity frames on each side of the window whose fits "
                                             "choose the prior's gains and the context pull")
    lambda_context: float = param(0.03, ge=0, help="weight of the context pull: each pose parameter held near the "
                                             "smoothing spline through its per-frame fits around the window "
                                             "(smoothing as for the gains), as much as those fits know more than the "
                                             "frame's own (solve.prior_gain) and as still as the events show the "
                                             "bones it turns (solve.still_gate): a static part does not drift within "
                                             "a window; 0 = off; only from prior_gain_min_fps, like the gains")
    context_gate_floor: float = param(0.1, ge=0, le=1, help="the context pull's event gate never below this: a part the events "
                                                "show moving is still held this fraction of what its fits know (0 = "
                                                "the events alone gate, the default before; 1 = no gate)")
    lambda_still: float = param(0.1, ge=0, help="weight of the event-silence term: the squared image velocity (px/s) of "
                                         "every joint whose bone made no more events than the background, per knot "
                                         "interval, weighted by that stillness (eventcap.energy.silence); 0 = off")
    still_radius_px: int = param(6, ge=0, help="half side of the box of pixels whose events are counted around each "
                                         "sample along a bone (event silence)")
    still_rate_hz: float = param(2.0, gt=0, help="events per pixel per second above the background at which a joint's "
                                           "stillness falls to 1/e (event silence)")
    still_hold_ms: float = param(20.0, ge=0, help="a joint counts as still only as much as in its least still moment "
                                           "within ± this many ms (rounded to knot intervals): brief silences of a "
                                           "moving limb the estimate misplaces do not hold it (event silence)")
    still_sweep_ms: float = param(50.0, ge=0, help="a knot interval's events are counted around the bones wherever the "
                                             "estimate puts them within ± this many ms (rounded to knot intervals), "
                                             "the most active place counting: a limb the estimate has at the right "
                                             "place at the wrong time is not called still (event silence; 0 = only "
                                             "the interval's own place)")
    lambda_floor: float = param(100.0, ge=0, help="weight of the floor term: each sole point (heels, toes) in contact on "
                                            "the floor, none below it (m²; eventcap.energy.floor); the floor's "
                                            "height is estimated over the capture from the per-frame fits; 0 = off. "
                                            "BlazePose, karate_kick seed 0 at 10 fps, with lambda_slide 1: AE 60.5 -> "
                                            "55.0 mm, depth error 58.6 -> 50.9 mm (docs/spline-solve.md)")
    lambda_slide: float = param(1.0, ge=0, help="weight of the no-sliding term: a sole point in contact does not move "
                                          "along the floor (its horizontal speed squared over the contact, m²/s; "
                                          "eventcap.energy.floor); 0 = off")
    contact_speed_mps: float = param(0.3, gt=0, help="contact: a sole point's contact falls to 1/e at this speed in the "
                                               "current estimate, m/s (eventcap.energy.floor)")
    contact_height_m: float = param(0.05, gt=0, help="contact: ... and at this height above the floor, m")
    lambda_bones: float = param(0.0, ge=0, help="weight of the foreshortening term: each limb bone's depth extent "
                                          "from its length and its 2D points, the sign (which end is nearer) from "
                                          "the 3D detections (m²; eventcap.energy.bones); 0 = off. BlazePose, "
                                          "karate_kick seed 0 at 10 fps: 10 alone AE 60.5 -> 58.0 mm, depth 58.6 -> "
                                          "54.4 mm; with the widths and the floor 53.9 -> 55.2, 49.0 -> 52.4: off")
    bones_sign_m: float = param(0.05, gt=0, help="foreshortening: the 3D detections' depth noise, m: a bone whose "
                                           "detected ends differ less in depth has an uncertain sign and weighs less")
    bones_2d_px: float = param(2.0, gt=0, help="foreshortening: the 2D points' noise, px (BlazePose on our actor: median "
                                         "2D error 1.7-2.6 px, NOTES.md): a bone whose depth extent this noise "
                                         "spreads by more than bones_sign_m weighs less")
    landmarks: str = param("widths", choices=("template", "widths"),
                           help="the hip and shoulder landmarks of E_2D: the template's joints (template), or where "
                                "the detector puts them on this person, their widths measured over the capture from "
                                "the detections and the per-frame fits (widths; eventcap.energy.landmarks). BlazePose, "
                                "karate_kick seed 0 at 10 fps: AE 60.5 -> 58.4 mm, depth error 58.6 -> 55.3 mm")
    lambda_2d: float = param(200.0, ge=0, help="weight of E_2D at every intensity frame of the window (focal-normalised)")
    robust_2d_px: float = param(2.0, ge=0, help="Cauchy loss scale of E_2D per landmark, px (0 = least squares)")
    lambda_3d: float = param(1.0, ge=0, help="weight of E_3D at every intensity frame of the window (metres)")
    lambda_cor: float = param(500.0, ge=0, help="weight of E_cor, the event correspondences of this batch's tracks "
                                          "(measured on karate_kick, 25 fps, with cor_step 5: EKLT 50 / 500 / 2000 "
                                          "gave AE 26.0 / 25.8 / 26.0 mm, exact tracks 25.8 / 24.5 / 24.1 mm)")
    cor_step: int = param(5, ge=1, help="tracking frames between the two frames of a correspondence (1 = adjacent "
                                  "frames, as the batch solve; 5 measured better and 5x cheaper: larger "
                                  "displacements against the same pixel noise)")
    tracks: str = param("own", choices=("window", "own"),
                        help="whose event tracks E_cor uses: only the batches the window keeps (own: its run of "
                             "window_step batches), or every batch of the window (window; about twice the solve "
                             "time). Measured on the full suite "
                             "at 10 fps: with EKLT tracks window is no better (lambda_cor 100: a wash; 500: worse), "
                             "with exact tracks (stages/track=oracle) it cut MPJVE 210 -> 184 mm/s and the median "
                             "peak-speed error 16% -> 12% (docs/spline-solve.md)")
    robust_cor_px: float = param(0.0, ge=0, help="Cauchy scale (px) of E_cor's residuals: from the second ICP round on, "
                                           "each correspondence is weighted 1 / (1 + (e/σ)²) by its residual e at the "
                                           "previous round's solution (0 = least squares)")
    lambda_sil: float = param(10.0, ge=0, help="weight of E_sil (paper Sec. 3.3, not in its batch solve): the silhouette "
                                         "boundary of the estimate at the batch's frames every sil_step_ms against "
                                         "its closest events, point-to-line, focal-normalised (0 = off). Full suite, "
                                         "10 fps: 0 / 10 gave AE 27.0 / 25.5 mm, MPJVE 248 / 235 mm/s; 25 fps: "
                                         "23.8 / 22.8 mm, 265 / 247 mm/s; 3 and 20 on karate and boxing no better")
    sil_step_ms: float = param(5.0, gt=0, help="E_sil at the batch's tracking frames this many ms apart (ends "
                                               "included)")
    sil_window_ms: float = param(10.0, gt=0, help="E_sil: a boundary pixel's closest event within ± half this of its "
                                                  "frame")
    sil_patch_px: int = param(8, ge=1, help="E_sil: ... and within a square of this side around it (paper: 8)")
    sil_loss: str = param("huber", choices=("l2", "huber"),
                          help="E_sil: loss on the point-to-line residuals: l2 (the paper) | huber")
    sil_huber_px: float = param(1.0, gt=0, help="E_sil: Huber loss threshold, px")
    sil_dist: float = param(4.0, ge=0, help="E_sil: λ_dist of the closest event search (paper Eq. 12): the squared "
                                            "time offset in window lengths against the squared distance in pixels")
    icp_rounds: int = param(2, ge=0, help="alternations of correspondence search and solve (ICP; 0: one solve of the "
                                          "detections and the prior, no events)")
    icp_settle_px: float = param(0.0, ge=0, help="end the ICP rounds early when a round's correspondence search has "
                                                 "settled: the RMS change (px) of the E_cor residuals at the last "
                                                 "solution between the new correspondences and those it was solved "
                                                 "with (eventcap.energy.correspondences.correspondence_change_px) "
                                                 "below this skips the round's solve and ends the rounds (E_sil keeps "
                                                 "the last solve's silhouette matches); 0 = every round. Tuning "
                                                 "captures at 25 fps: 0.003 / 0.03 / 0.1 px skipped 18 / 47 / 69% of "
                                                 "the second solves, MPJVE +3.5 / +4.0 / +4.9% (docs/spline-solve.md)")
    edge_margin_px: float = param(1.0, ge=0, help="tracks nearer than this to a silhouette edge give no "
                                                  "correspondence")
    lambda_damp: float = param(1e-4, ge=0, help="proximal pull of the control points towards each solve's start")
    limits: dict[str, list[float]] = param(
        default_factory=dict, help="joint-limit overrides {parameter name: [min, max]} (radians; metres for root_t*)")
    max_iter: int = param(200, ge=1, affects_result=False, help="IPOPT iteration limit per solve; reaching it fails the "
                                                          "window (failures are never cached)")
    tol: float = param(1e-6, gt=0, help="IPOPT convergence tolerance")
    mumps_pivot_order: int = param(0, ge=0, le=7, help="MUMPS ordering (0 AMD ... 7 auto), pinned for reproducibility")


SPLINE = StageSpec(
    name="spline", kind="solve", version=10,  # 8: factors; gaps; no estimate beyond the observed frames; 9: floor,
    # widths; 10: window_step (a batch another window keeps returns no frames)
    description="continuous-time solve (not in the paper): a cubic B-spline in the 33 pose parameters over a "
                "window of batches, fitted to the detections at every intensity frame (robust, soft), the event "
                "correspondences of this batch's tracks (or the window's), the event silence and a motion prior, "
                "joint limits on the control points (CasADi + IPOPT); "
                "the output is the window's whole curve at the tracking rate (the stitch stage blends the windows)",
    config=SplineSolveConfig,
    inputs={"recording": Port(Recording),
            "sliced": Port(SlicedTracks, "every batch's tracks (a window reads those of its batches)",
                           all_batches=True),
            "detections": Port(Detections),
            "batches": Port(BatchPlan)},
    outputs={"poses": Port(PoseSequence)}, per_batch=True,
    run="eventcap_spline._impl:run_spline",
)


@dataclass
class StitchConfig:
    taper: float = param(0.5, gt=0, le=0.5, help="fraction of a window's length over which its blending weight rises from 0 to 1 "
                                   "at each of its ends (0.5: a bump over the whole window); a window's end at the "
                                   "start or end of the recording is not tapered")


STITCH = StageSpec(
    name="stitch", kind="fuse", version=3,  # 3: windows advancing by several batches; windows that only touch
    description="the spline solve's overlapping windows blended into one motion over the whole recording, each "
                "window weighted by a C² bump over its span (no seam where batches meet; not in the paper)",
    config=StitchConfig,
    inputs={"windows": Port(PoseSequence, "every batch's spline-solve window", all_batches=True)},
    outputs={"motion": Port(PoseSequence, doc="the joined motion at every tracking frame")},
    run="eventcap_spline.stitch:run_stitch",
)


@dataclass
class CutConfig:
    pass


CUT = StageSpec(
    name="cut", kind="fuse", version=1,
    description="a batch's frames of the stitched whole-recording motion",
    config=CutConfig,
    inputs={"motion": Port(PoseSequence, "the stitch stage's motion"), "batches": Port(BatchPlan)},
    outputs={"poses": Port(PoseSequence)}, per_batch=True,
    run="eventcap_spline.stitch:run_cut",
)
