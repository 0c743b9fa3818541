"""Every term of the pose energy this package defines, registered as factors (:mod:`.factor`) in this order.

Importing this module registers them; :func:`factors_from_config` builds a solve's factors from its config.

=========  ==============================================  ===========================  =====================
name       term                                            class                        used by
=========  ==============================================  ===========================  =====================
2d         E_2D, 2D landmarks (Eq. 6, Cauchy-robust)       detections.Keypoints2D       spline, batch
3d         E_3D, root-relative 3D joints (Eq. 7)           detections.Joints3D          spline, batch
cor        E_cor, event-track correspondences (Eq. 5)      cor.EventCorrespondences     spline, batch
temp       E_temp, parts without tracks held (Eq. 8)       cor.TemporalStability        batch
sil        E_sil, silhouette to events (Eq. 11)            sil.SilhouetteToEvents       spline, refine
stab       E_stab, joints near the solve's (Eq. 10)        sil.JointStability           refine
still      E_still, event silence (not in the paper)       silence.EventSilence         spline
prior      motion prior (not in the paper)                 prior.MotionPrior            spline
context    context pull (not in the paper)                 prior.ContextPull            spline
floor      on the floor in contact, never below it         floor.FloorContact           spline
slide      no sliding in contact                           floor.FootSlide              spline
bones      bones' depth extents (foreshortening)           bones.BoneDepth              spline
=========  ==============================================  ===========================  =====================
"""

from __future__ import annotations

from . import detections  # noqa: F401  (each module registers its factors, in the order of the table)
from . import cor  # noqa: F401, I001
from . import sil  # noqa: F401
from . import silence  # noqa: F401
from . import prior  # noqa: F401
from . import floor  # noqa: F401
from . import bones  # noqa: F401
from collections.abc import Mapping
from typing import Any

from eventcap.body.template import Template
from eventcap.camera import Camera

from .factor import FACTORS, Factor, Layout, weight_key

#: This package's factors in the order a solve sums them (and lays out their auxiliary variables).
ORDER = ("2d", "3d", "cor", "temp", "sil", "stab", "still", "prior", "context", "floor", "slide", "bones")

def factors_from_config(config: Any, template: Template, camera: Camera, layout: Layout,
                        allowed: tuple[str, ...] | None = None,
                        overrides: Mapping[str, float] | None = None) -> list[Factor]:
    """The factors of a solve: every registered factor whose weight ``lambda_<name>`` the config states and is > 0
    (this package's in the order of :data:`eventcap.energy.terms.ORDER`, then others by name; ``allowed`` restricts them to these names), each built with the config (its settings)
    and the layout. overrides: weights to use instead of the config's (e.g. a mode that turns a term off)."""
    out = []
    names = sorted(FACTORS, key=lambda n: (ORDER.index(n) if n in ORDER else len(ORDER), n))
    for name in names:
        cls = FACTORS[name]
        if allowed is not None and name not in allowed:
            continue
        key = weight_key(name)
        if overrides and name in overrides:
            w = overrides[name]
        elif hasattr(config, key):
            w = getattr(config, key)
        else:
            continue
        if cls.size(layout) < 1:  # no samples in this layout (e.g. E_sil without silhouette frames)
            continue
        if isinstance(w, (int, float)) and not isinstance(w, bool) and w == 0:  # off (and nothing to build)
            continue
        out.append(cls(w, config, template, camera, layout))
    return out


__all__ = ["FACTORS", "ORDER", "factors_from_config"]
