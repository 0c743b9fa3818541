"""The settings of the energy's terms and of the evidence they share, declared once (light to import: a stage's
spec names them without loading a solver).

Each term's settings are one dataclass whose ``weight`` is its λ (:class:`FactorConfig`); its factor class names it
as ``Config`` (:mod:`.factor`). A solve's config lists the terms it uses as groups of its ``terms`` group, in the
order they are summed, each with the defaults that solve states differently (e.g. E_cor's weight 500 in the spline
solve, 50 in the paper's batch solve). The evidence a solve measures once for its factors has its settings here too:
the joints' stillness in the events, the smoothing of the fits around a window, the sole points' contact.
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


@dataclass
class FactorConfig:
    """The settings every factor has: its weight. A factor's own ``Config`` subclasses this and adds its settings."""

    weight: float = param(0.0, ge=0, help="the term's weight λ (0: off)")


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
class SilConfig(FactorConfig):
    """E_sil's settings."""

    weight: float = param(10.0, ge=0, help="weight of E_sil, the silhouette boundary's point-to-line distances to "
                                           "its closest events (focal-normalised image units)")
    step_ms: float = param(5.0, gt=0, help="E_sil at the solved batches' tracking frames this many ms apart (first "
                                           "and last included; at most every frame)")
    window_ms: float | None = param(10.0, gt=0, help="a boundary pixel's closest event within ± half this many ms "
                                                     "of its frame (null: the window's span, the paper's T)")
    patch_px: int = param(8, ge=1, help="... and within a square of this side around it, pixels (the paper: 8)")
    dist: float = param(4.0, ge=0, help="λ_dist of the closest-event search (paper Eq. 12): the squared time "
                                        "offset in window lengths against the squared distance in pixels")
    denoise_us: int = param(5000, ge=0, help="events without another event in their 3x3 pixel neighbourhood within "
                                             "this many µs are not searched (a background-activity filter; 0: all)")
    loss: str = param("huber", choices=LOSSES, help="loss on the point-to-line residuals: l2 (the paper) | huber")
    huber_px: float = param(1.0, gt=0, help="Huber threshold, px: beyond it a residual counts linearly")


@dataclass
class StabConfig(FactorConfig):
    """E_stab's settings."""

    weight: float = param(5.0, ge=0, help="weight of E_stab, the joints held near the reference poses' (metres)")


@dataclass
class StillConfig(FactorConfig):
    """E_still's settings (how stillness is measured is the solve's ``stillness`` group)."""

    weight: float = param(0.1, ge=0, help="weight of E_still: the squared image velocity (px/s) of every joint the "
                                          "events call still, per knot interval, weighted by that stillness")


@dataclass
class PriorConfig(FactorConfig):
    """The motion prior's settings."""

    weight: float = param(1e-4, ge=0, help="weight of the motion prior, the integral of the squared acceleration (or "
                                           "jerk) of the poses (rad and m, time in s)")
    order: str = param("acceleration", choices=tuple(PRIOR_ORDERS),
                       help="what the prior penalises: acceleration | jerk (the second or third derivative)")
    inertia: float = param(1.5, ge=0, help="exponent x of each rotation's gain (I_p / mean I)^x, I_p the inertia of "
                                           "the body that pose parameter turns (de Leva's segments on the actor's "
                                           "bones): light parts may accelerate more than the trunk (0: one gain)")
    inertia_cap: float = param(1.0, ge=1, finite=False, help="largest of those gains (1: parts lighter than the "
                                                             "mean are held less, none more; .inf: no cap)")
    inertia_floor: float = param(0.04, ge=0, le=1, help="smallest of those gains")
    gain_max: float = param(10.0, ge=1, help="largest gain per pose parameter chosen from the per-frame fits around "
                                             "the window (the window's context evidence): parameters the fits call "
                                             "static get up to this much more smoothing (1: no chosen gains)")


@dataclass
class ContextConfig(FactorConfig):
    """The context pull's settings."""

    weight: float = param(0.03, ge=0, help="weight of the context pull: each pose parameter held near the smoothing "
                                           "spline through its per-frame fits around the window, as much as those "
                                           "fits know more than the frame's own, and as still as the events show the "
                                           "bones it turns")
    gate_floor: float = param(0.1, ge=0, le=1, help="the events' gate never below this: a part the events show "
                                                    "moving is still held this fraction (0: the events alone gate; "
                                                    "1: no gate)")


@dataclass
class FloorConfig(FactorConfig):
    """The floor term's settings (contact: the solve's ``contact`` group)."""

    weight: float = param(100.0, ge=0, help="weight of the floor term: each sole point (heels, toes) in contact on "
                                            "the floor, none below it (m²); the floor's height is estimated over the "
                                            "capture from the per-frame fits")


@dataclass
class SlideConfig(FactorConfig):
    """The no-sliding term's settings (contact: the solve's ``contact`` group)."""

    weight: float = param(1.0, ge=0, help="weight of the no-sliding term: a sole point in contact does not move "
                                          "along the floor (its horizontal speed squared over the contact, m²/s)")


@dataclass
class BonesConfig(FactorConfig):
    """The foreshortening term's settings."""

    weight: float = param(0.0, ge=0, help="weight of the foreshortening term: each limb bone's depth extent from its "
                                          "length and its 2D points, the sign (which end is nearer) from the 3D "
                                          "detections (m²)")
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


__all__ = ["BonesConfig", "IpoptConfig", "ContactConfig", "ContextConfig", "CorConfig", "FactorConfig", "FloorConfig", "Joints3DConfig", "LOSSES", "Landmarks2DConfig", "PHI_SCOPES", "PRIOR_ORDERS", "PriorConfig", "SilConfig", "SlideConfig", "SmoothingConfig", "StabConfig", "StillConfig", "StillnessConfig", "TempConfig"]
