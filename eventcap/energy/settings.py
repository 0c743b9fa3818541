"""The settings of the energy's terms and of the evidence they share, declared once (light to import: a stage's
spec names them without loading a solver).

A term's settings come in one of two kinds, each a dataclass its factor class accepts (:mod:`.factor`):

- a **noise model** (:class:`NoiseConfig`, the spline solve's): the term is weighted by the noise of what it reads,
  in its own units (a detector's 2D noise in px, its 3D noise in mm, the event tracks' noise in px, ...), and its
  energy is the negative log-likelihood of its residuals, ½ Σ ρ(r² / σ²) with ρ a robust loss of scale
  ``loss_scale`` sigmas (:mod:`.loss`), as GTSAM's noise models and Ceres' loss functions weigh a factor. A perfect
  source is followed, a noisy one smoothed, and the Laplace uncertainty of the solve means what it says. ``gain``
  multiplies the precision (1: as the noise says; 0: the term is off);
- a **weight** (:class:`FactorConfig`, the paper's solves: the batch solve and the refinement): the term's λ of the
  paper's Eq. 4 and 9 on focal-normalised image residuals and metres, as the paper weighs its terms.

A solve's config lists the terms it uses as groups of its ``terms`` group, in the order they are summed. The
evidence a solve measures once for its factors has its settings here too: the joints' stillness in the events, the
smoothing of the fits around a window, the sole points' contact.
"""

from __future__ import annotations

from dataclasses import dataclass

from eventcap.params import param

#: E_sil's losses on the point-to-line residuals
LOSSES = ("l2", "huber")
#: the motion prior's orders: the derivative of the poses it penalises
PRIOR_ORDERS = {"acceleration": 2, "jerk": 3}
#: E_temp's scopes: "batch" — a part without any correspondence in the whole batch is held still at every frame pair
#: (the paper); "pair" — per frame pair (i, i+1), a part without correspondences evaluated at S_i or S_{i+1}
PHI_SCOPES = ("batch", "pair")


#: The robust losses of noise-modelled terms (:mod:`.loss`): l2 (Gaussian noise) | cauchy | huber.
NOISE_LOSSES = ("l2", "cauchy", "huber")


@dataclass
class FactorConfig:
    """The settings every weighted factor has: its weight. A factor's own ``Config`` subclasses this and adds its
    settings."""

    weight: float = param(0.0, ge=0, help="the term's weight λ (0: off)")

    @property
    def factor_weight(self) -> float:
        return self.weight


@dataclass
class NoiseConfig:
    """The settings every noise-modelled factor has: its gain on the precision its noise model gives (module doc)."""

    gain: float = param(1.0, ge=0, help="the term's precision (1 / σ² of its noise model) times this, dimensionless "
                                        "(1: as the noise says; 0: the term is off)")

    @property
    def factor_weight(self) -> float:
        return self.gain


@dataclass
class Landmarks2DConfig(FactorConfig):
    """E_2D's settings."""

    weight: float = param(200.0, ge=0, help="weight of E_2D at every detection frame (image residuals in "
                                            "focal-normalised units: λ 200 makes a 1 px error cost as much as 7 cm in "
                                            "E_3D at weight 1)")
    robust_px: float = param(2.0, ge=0, help="Cauchy loss scale per landmark, px: quadratic below it, logarithmic "
                                             "for outliers and left/right flips (0: least squares, the paper)")


@dataclass
class Joints3DConfig(FactorConfig):
    """E_3D's settings."""

    weight: float = param(1.0, ge=0, help="weight of E_3D at every detection frame (residuals in metres)")


@dataclass
class CorConfig(FactorConfig):
    """E_cor's settings."""

    weight: float = param(50.0, ge=0, help="weight of E_cor, the event tracks' correspondences (image residuals in "
                                           "focal-normalised units; the paper's λ_adj)")
    robust_px: float = param(0.0, ge=0, help="Cauchy scale of the residuals, px: from the second ICP round on, each "
                                             "correspondence weighs 1 / (1 + (e/σ)²) by its residual e at the previous "
                                             "round's solution (0: least squares)")


@dataclass
class TempConfig(FactorConfig):
    """E_temp's settings."""

    weight: float = param(80.0, ge=0, help="weight of E_temp, the joints of parts without correspondences held "
                                           "still between consecutive frames (metres)")
    scope: str = param("batch", choices=PHI_SCOPES, help="which joints count as without correspondences: batch "
                                                         "(none in the whole batch, the paper) | pair (none between "
                                                         "the two frames)")
    still_m: float = param(0.03, ge=0, help="only joints that moved less than this between the start's first and "
                                            "last frame are held, metres (0: every joint without correspondences, "
                                            "the paper's literal indicator)")


@dataclass
class SilSearch:
    """How E_sil finds the closest event of each silhouette boundary pixel (paper Eq. 12-13)."""

    step_ms: float = param(5.0, gt=0, help="E_sil at the solved batches' tracking frames this many ms apart (first "
                                           "and last included; at most every frame)")
    window_ms: float | None = param(10.0, gt=0, help="a boundary pixel's closest event within ± half this many ms "
                                                     "of its frame (null: the window's span, the paper's T)")
    patch_px: int = param(8, ge=1, help="... and within a square of this side around it, pixels (the paper: 8)")
    dist: float = param(4.0, ge=0, help="λ_dist of the closest-event search (paper Eq. 12): the squared time "
                                        "offset in window lengths against the squared distance in pixels")
    denoise_us: int = param(5000, ge=0, help="events without another event in their 3x3 pixel neighbourhood within "
                                             "this many µs are not searched (a background-activity filter; 0: all)")


@dataclass
class SilConfig(SilSearch, FactorConfig):
    """E_sil's settings (weighted: the paper's refinement)."""

    weight: float = param(10.0, ge=0, help="weight of E_sil, the silhouette boundary's point-to-line distances to "
                                           "its closest events (focal-normalised image units)")
    loss: str = param("huber", choices=LOSSES, help="loss on the point-to-line residuals: l2 (the paper) | huber")
    huber_px: float = param(1.0, gt=0, help="Huber threshold, px: beyond it a residual counts linearly")


@dataclass
class StabConfig(FactorConfig):
    """E_stab's settings."""

    weight: float = param(5.0, ge=0, help="weight of E_stab, the joints held near the reference poses' (metres)")


@dataclass
class Landmarks2DNoise(NoiseConfig):
    """E_2D weighted by the detector's 2D noise (module doc)."""

    sigma_px: float | None = param(None, gt=0, help="each landmark's 2D noise per image axis, px (null: the noise "
                                                    "model the detector states per landmark and image)")
    min_sigma_px: float = param(0.5, gt=0, help="no landmark is followed closer than this, px (the skeleton's own "
                                                "error against a detector's landmark; a floor under a stated noise "
                                                "of 0)")
    loss: str = param("cauchy", choices=NOISE_LOSSES, help="robust loss on the whitened residuals: l2 | cauchy | "
                                                           "huber (outliers and left/right flips)")
    loss_scale: float = param(3.0, gt=0, help="the loss's scale in sigmas: quadratic below it")


@dataclass
class Joints3DNoise(NoiseConfig):
    """E_3D weighted by the detector's 3D noise (module doc)."""

    sigma_mm: float | None = param(None, gt=0, help="each root-relative 3D joint's noise per axis, mm (null: the "
                                                    "noise model the detector states per joint and image)")
    min_sigma_mm: float = param(5.0, gt=0, help="no 3D joint is followed closer than this, mm (the skeleton's own "
                                                "error against a detector's joint)")


@dataclass
class CorNoise(NoiseConfig):
    """E_cor weighted by the event tracks' noise."""

    sigma_px: float = param(1.0, gt=0, help="noise of a track's displacement between the two frames of a "
                                            "correspondence, per image axis, px")
    loss_scale: float = param(3.0, ge=0, help="Cauchy scale in sigmas: from the second ICP round on, each "
                                              "correspondence weighs 1 / (1 + (e/(scale σ))²) by its residual e at "
                                              "the previous round's solution (0: least squares)")


@dataclass
class SilNoise(SilSearch, NoiseConfig):
    """E_sil weighted by the noise of a boundary point's distance to its closest event."""

    sigma_px: float = param(2.0, gt=0, help="noise of a boundary point's distance to its event along the normal, px")
    loss: str = param("huber", choices=LOSSES, help="loss on the whitened residuals: l2 | huber")
    loss_scale: float = param(1.0, gt=0, help="Huber threshold in sigmas: beyond it a residual counts linearly")


@dataclass
class FlowNoise(NoiseConfig):
    """E_flow weighted by the noise of the normal flow the events measure at the silhouette's boundary."""

    sigma_px_s: float = param(60.0, gt=0, help="noise of a boundary point's normal image speed as the events measure "
                                               "it, px/s")
    loss_scale: float = param(2.0, ge=0, help="Cauchy loss scale in sigmas: quadratic below it, logarithmic for "
                                              "edges of something else (0: least squares)")
    step_ms: float = param(5.0, gt=0, help="E_flow at the solved batches' tracking frames this many ms apart, ms")
    radius_px: int = param(6, ge=1, help="the events within this many pixels of a boundary point (a square) give its "
                                         "flow, px")
    half_ms: float = param(10.0, gt=0, help="... and within ± this many ms of the frame, ms")
    min_events: int = param(8, ge=4, help="fewest events a plane is fitted to")
    min_fit: float = param(0.6, ge=0, le=1, help="share of the events' time spread the fitted plane must explain (R²): "
                                                 "an edge sweeping the patch, not noise or texture")
    min_cos: float = param(0.7, ge=0, le=1, help="the flow's direction within this cosine of the boundary's normal")
    max_offset_px: float = param(3.0, gt=0, help="the fitted edge passes within this many pixels of the boundary "
                                                 "point at the frame's time, px")


@dataclass
class StillNoise(NoiseConfig):
    """E_still weighted by the noise of a still joint's image speed."""

    sigma_px_s: float = param(30.0, gt=0, help="image speed a joint the events call still may still have, px/s "
                                               "(per axis)")


@dataclass
class PriorNoise(NoiseConfig):
    """The motion prior as a process noise chosen from the data: each pose parameter a white-noise-acceleration
    process whose power q_p the restricted likelihood chooses on the per-frame fits around the window, their
    frame-to-frame noise known from the detector's (eventcap.energy.prior)."""

    order: str = param("acceleration", choices=tuple(PRIOR_ORDERS),
                       help="what the prior penalises: acceleration | jerk (the second or third derivative; the power "
                            "is chosen from the fits for acceleration only, jerk takes q_default)")
    pool: str = param("parameter", choices=("parameter", "group"),
                      help="one process power per pose parameter, or per group (the angles, the root's translation)")
    q_default: float = param(1e3, gt=0, help="the process power where the fits around a window are too few to "
                                             "choose it, (rad or m)² / s³ (acceleration) or / s⁵ (jerk)")
    q_max_ratio: float = param(100.0, ge=1, help="a parameter's power within this factor of its group's (a parameter "
                                                 "the fits barely see would otherwise take any value)")
    q_min: float = param(1e-3, gt=0, help="the least process power, (rad or m)² / s³: fits of a body at rest choose "
                                          "none, and an infinitely stiff prior leaves the solve without a scale")
    moving_gain: float = param(1.0, gt=0, le=1, help="where the events show the bones a parameter turns moving (the "
                                                      "window's stillness evidence), its prior weighs this much of "
                                                      "the fits' choice; where they show them still, all of it (1: "
                                                      "the events do not gate the prior)")


@dataclass
class ContextNoise(NoiseConfig):
    """The context pull as a gain (off by default: the prior's process power comes from the same fits)."""

    gain: float = param(0.0, ge=0, help="the context pull's weight on its evidence (the fits' smoother around the "
                                        "window), dimensionless (0: off)")
    gate_floor: float = param(0.1, ge=0, le=1, help="the events' gate never below this: a part the events show "
                                                    "moving is still held this fraction (0: the events alone gate; "
                                                    "1: no gate)")


@dataclass
class FloorNoise(NoiseConfig):
    """The floor term weighted by its noise."""

    sigma_mm: float = param(10.0, gt=0, help="how far a sole point in contact may be from the floor, mm")


@dataclass
class SlideNoise(NoiseConfig):
    """The no-sliding term weighted by its noise."""

    sigma_mm_s: float = param(50.0, gt=0, help="how fast a sole point in contact may still slide along the floor, "
                                               "mm/s")


@dataclass
class BonesNoise(NoiseConfig):
    """The foreshortening term (off by default)."""

    gain: float = param(0.0, ge=0, help="weight of the foreshortening term on its own noise model (the 2D points' "
                                        "noise_2d_px and the 3D sign's sign_m), dimensionless (0: off)")
    sign_m: float = param(0.05, gt=0, help="the 3D detections' depth noise, m: a bone whose detected ends differ less "
                                           "in depth has an uncertain sign and weighs less")
    noise_2d_px: float = param(2.0, gt=0, help="the 2D points' noise, px: a bone whose depth extent this noise spreads "
                                               "by more than sign_m weighs less")


@dataclass
class StillnessConfig:
    """How the joints' stillness is measured in the events around a window's start (module doc)."""

    radius_px: int = param(6, ge=0, help="half side of the box of pixels whose events are counted around each "
                                         "sample along a bone, pixels")
    rate_hz: float = param(2.0, gt=0, help="events per pixel per second above the background at which a joint's "
                                           "stillness falls to 1/e")
    hold_ms: float = param(20.0, ge=0, help="a joint is only as still as in its least still moment within ± this "
                                            "many ms (rounded to knot intervals): brief silences of a moving limb "
                                            "the estimate misplaces do not hold it")
    sweep_ms: float = param(50.0, ge=0, help="a knot interval's events are counted around the bones wherever the "
                                             "estimate puts them within ± this many ms (rounded to knot intervals), "
                                             "the most active place counting (0: only the interval's own place)")


@dataclass
class SmoothingConfig:
    """How the per-frame fits around a window choose each pose parameter's smoothing (the window's context evidence,
    module doc), for the motion prior's gains and the context pull."""

    seconds: float = param(1.0, ge=0, help="seconds of intensity frames on each side of the window whose fits are "
                                           "smoothed")
    min_fps: float = param(20.0, ge=0, help="only when the intensity frames come at least this often, frames per "
                                            "second (below, the fits undersample fast limbs, which would be held as "
                                            "if at rest; 0: always)")
    criterion: str = param("gcv", choices=("reml", "gcv"), help="how each parameter's fits choose their smoothing: "
                                                                "gcv | reml (eventcap.analysis.smoothing)")


@dataclass
class ContactConfig:
    """When a sole point (heel, toes) counts as in contact with the floor, in the current estimate."""

    speed_mps: float = param(0.3, gt=0, help="a sole point's contact falls to 1/e at this speed, m/s")
    height_m: float = param(0.05, gt=0, help="... and at this height above the floor, m")



@dataclass
class IpoptConfig:
    """The IPOPT options a solve states (the rest are pinned by eventcap.energy.ipopt.IpoptSettings)."""

    max_iter: int = param(200, ge=1, affects_result=False,
                          help="iteration limit per solve; reaching it fails the unit (failures are never cached, "
                               "so raising it recomputes only what failed)")
    tol: float = param(1e-6, gt=0, help="convergence tolerance (IPOPT's scaled NLP error)")
    mumps_pivot_order: int = param(0, ge=0, le=7, help="MUMPS ordering (0 AMD ... 7 auto), pinned for "
                                                       "reproducibility across machines")
    barrier: str = param("monotone", choices=("monotone", "adaptive"),
                         help="the barrier of a solve from a fresh start: monotone from a tiny mu (few "
                              "iterations on short windows) | adaptive (IPOPT's own, from mu 0.1; fewer iterations "
                              "on long windows). A solve that starts from an earlier solution (a later ICP round) is "
                              "monotone either way")


__all__ = ["BonesNoise", "ContextNoise", "CorNoise", "FloorNoise", "FlowNoise", "Joints3DNoise", "Landmarks2DNoise", "NOISE_LOSSES",
           "NoiseConfig", "PriorNoise", "SilNoise", "SilSearch", "SlideNoise", "StillNoise", "IpoptConfig", "ContactConfig", "CorConfig", "FactorConfig", "Joints3DConfig", "LOSSES", "Landmarks2DConfig", "PHI_SCOPES", "PRIOR_ORDERS", "SilConfig", "SmoothingConfig", "StabConfig", "StillnessConfig", "TempConfig"]
