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
flow          E_flow, edges' normal flow (not in the paper)   flow.NormalFlow              spline
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
from dataclasses import dataclass
from typing import Any

import numpy as np

from eventcap.body.template import Template
from eventcap.camera import Camera

from . import bones, cor, detections, floor, flow, prior, sil, silence  # noqa: F401  (each module registers its factors)
from .detections import DetectionWeights
from .errors import EnergyError
from .factor import FACTORS, Factor
from .settings import NoiseConfig


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


@dataclass(frozen=True)
class Term:
    """One term of a solve that is on: its name, its factor class and its settings (the factor's Config or Noise)."""

    name: str
    factor_class: type[Factor]
    settings: Any

    @property
    def switch(self) -> str:
        """The setting that turns it off (relative to its group): ``gain`` (a noise model) or ``weight``."""
        return "gain" if isinstance(self.settings, NoiseConfig) else "weight"


@dataclass(frozen=True, eq=False)
class TermSet:
    """A solve's ``terms`` group decoded once (:func:`term_configs`): the terms that are on, in order, and what the
    solve derives from them. ``group`` is the group as configured (the per-frame fits read E_2D's and E_3D's settings
    from it even when their gain is 0)."""

    group: Any
    on: tuple[Term, ...]

    @classmethod
    def decode(cls, group: Any) -> TermSet:
        return cls(group, tuple(Term(name, cls, cfg) for name, cls, cfg in term_configs(group)))

    def samples(self, inputs) -> dict[str, np.ndarray]:
        """Each term's sample times in a window with these inputs (:meth:`Factor.samples`), by name, in order."""
        return {t.name: np.asarray(t.factor_class.samples(inputs, t.settings)) for t in self.on}

    def factors(self, template: Template, camera: Camera, sizes: Mapping[str, int]) -> list[Factor]:
        """The factors of a problem of these sizes (name -> number of samples): every term that is on and has
        samples, built with its settings, in order."""
        return [t.factor_class(t.settings, template, camera, int(sizes[t.name])) for t in self.on
                if int(sizes.get(t.name, 0)) >= 1]

    def detection_weights(self, camera: Camera) -> DetectionWeights:
        """How the per-frame fits weigh the detections (E_2D's and E_3D's settings)."""
        return DetectionWeights.from_terms(self.group, camera)

    def check(self, inputs, where: str) -> None:
        """EnergyError (status invalid_config) naming the first term that is on but would have nothing to read in a
        window with these inputs (:meth:`Factor.missing`: an input or evidence the solve does not provide, a kind of
        detection the detector does not give, a noise model nobody states), and the setting that turns it off.
        ``where``: the solve's config key (``stages.solve``). Evidence a solve offers under a rule of its own is not
        missing when that rule withholds it (no smoothing evidence below ``smoothing.min_fps``, no floor where no fit
        succeeded): the factor then holds nothing there, and the solve's log says so."""
        for t in self.on:
            gone = t.factor_class.missing(inputs, t.settings)
            if gone is None:
                continue
            key = f"{where}.terms.{t.name}"
            fix = f"set {key}.{t.switch}=0 to solve without it" + ("" if gone.instead is None else
                                                                    f", or {key}.{gone.instead}")
            raise EnergyError(f"{key} is on ({t.switch} {t.settings.factor_weight:g}), but {gone.reason}: {fix}",
                              status="invalid_config")


def sample_times(terms: Any, inputs) -> dict[str, np.ndarray]:
    """Each term's sample times in a window with these inputs (:meth:`Factor.samples`), by name, in order."""
    return TermSet.decode(terms).samples(inputs)


def factors_from_config(terms: Any, template: Template, camera: Camera, sizes: Mapping[str, int]) -> list[Factor]:
    """The factors of a solve: every term of its ``terms`` group that is on (:func:`term_configs`) and has samples
    in a problem of these sizes (name -> number of samples), each built with its settings, in the group's order."""
    return TermSet.decode(terms).factors(template, camera, sizes)


__all__ = ["FACTORS", "Term", "TermSet", "factors_from_config", "sample_times", "term_configs"]
