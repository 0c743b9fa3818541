"""Every term of the pose energy this package defines, registered as factors (:mod:`.factor`) in this order.

Importing this module registers them; :func:`eventcap.energy.factor.factors_from_config` does so before it looks.

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
from .factor import FACTORS

#: This package's factors in the order a solve sums them (and lays out their auxiliary variables).
ORDER = ("2d", "3d", "cor", "temp", "sil", "stab", "still", "prior", "context", "floor", "slide", "bones")

__all__ = ["FACTORS", "ORDER"]
