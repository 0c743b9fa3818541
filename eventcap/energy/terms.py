"""Every term of the pose energy this package defines, registered as factors (:mod:`.factor`), and how a solve gets
its factors from its config's ``terms`` group.

Importing this module registers them. A solve's ``terms`` group (a dataclass in its stage's spec) lists the terms it
uses, each as a group of its settings named like the factor (``stages.solve.terms.cor.sigma_px``), in the order the
solve sums them; a term with weight 0 is left out (:func:`term_configs`).

============  ==============================================  ===========================  =====================
name          term                                            class                        used by
============  ==============================================  ===========================  =====================
landmarks_2d  E_2D, 2D landmarks (Eq. 6, Cauchy-robust)       detections.Keypoints2D       spline, batch
joints_3d     E_3D, root-relative 3D joints (Eq. 7)           detections.Joints3D          spline, batch
cor           E_cor, event-track correspondences (Eq. 5)      cor.EventCorrespondences     spline, batch
temp          E_temp, parts without tracks held (Eq. 8)       cor.TemporalStability        batch
sil           E_sil, silhouette to events (Eq. 11)            sil.SilhouetteToEvents       spline, refine
stab          E_stab, joints near the solve's (Eq. 10)        sil.JointStability           refine
still         E_still, event silence (not in the paper)       silence.EventSilence         spline
prior         motion prior (not in the paper)                 prior.MotionPrior            spline
context       context pull (not in the paper)                 prior.ContextPull            spline
floor         on the floor in contact, never below it         floor.FloorContact           spline
slide         no sliding in contact                           floor.FootSlide              spline
bones         bones' depth extents (foreshortening)           bones.BoneDepth              spline
============  ==============================================  ===========================  =====================
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import numpy as np

from eventcap.body.template import Template
from eventcap.camera import Camera

from . import bones, cor, detections, floor, prior, sil, silence  # noqa: F401  (each module registers its factors)
from .errors import EnergyError
from .factor import FACTORS, Factor


def term_configs(terms: Any) -> list[tuple[str, type[Factor], Any]]:
    """(name, factor class, its settings) of every term of a solve's ``terms`` group whose weight (or gain) is not 0,
    in the group's order. EnergyError for an entry that names no registered factor, or whose settings are not the factor's
    ``Config``."""
    if not dataclasses.is_dataclass(terms):
        raise EnergyError(f"terms: expected a group of term settings, got {type(terms).__name__}")
    out = []
    for f in dataclasses.fields(terms):
        cls = FACTORS.get(f.name)
        if cls is None:
            raise EnergyError(f"terms.{f.name}: no factor of that name (registered: {', '.join(sorted(FACTORS))})")
        cfg = getattr(terms, f.name)
        if not cls.accepts(cfg):
            kinds = " or ".join(k.__name__ for k in (cls.Config, cls.Noise) if k is not None)
            raise EnergyError(f"terms.{f.name}: expected the settings {kinds} of factor {cls.__qualname__}, got "
                              f"{type(cfg).__name__}")
        w = cfg.factor_weight
        if isinstance(w, (int, float)) and not isinstance(w, bool) and w == 0:  # off (and nothing to build)
            continue
        out.append((f.name, cls, cfg))
    return out


def sample_times(terms: Any, inputs) -> dict[str, np.ndarray]:
    """Each term's sample times in a window with these inputs (:meth:`Factor.samples`), by name, in order."""
    return {name: np.asarray(cls.samples(inputs, cfg)) for name, cls, cfg in term_configs(terms)}


def factors_from_config(terms: Any, template: Template, camera: Camera, sizes: Mapping[str, int]) -> list[Factor]:
    """The factors of a solve: every term of its ``terms`` group that is on (:func:`term_configs`) and has samples
    in a problem of these sizes (name -> number of samples), each built with its settings, in the group's order."""
    return [cls(cfg, template, camera, int(sizes[name])) for name, cls, cfg in term_configs(terms)
            if int(sizes.get(name, 0)) >= 1]


__all__ = ["FACTORS", "factors_from_config", "sample_times", "term_configs"]
