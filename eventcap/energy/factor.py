"""The factor interface: every term of the pose energy is one :class:`Factor`, every solve a sum of factors.

As GTSAM's ``NoiseModelFactor`` or Ceres's ``CostFunction``: a factor is one named term with one weight. It reads
its data for a window (:meth:`Factor.prepare`), and at its own sample times gives its value, its gradient and its
Hessian (exact or Gauss-Newton) in pose space (:meth:`Factor.linearize`). A factor never knows how the poses are
parametrised (a B-spline's control points, or one pose per frame): :class:`eventcap.energy.problem.FactorProblem`
maps the poses at every factor's samples to the decision variables and sums the factors. A new term is one class
(a subclass of :class:`Factor` registers itself by its ``name``) and one config entry, its weight
``lambda_<name>`` in the config of a solve: every solve uses the registered factors whose weight its config
states and is > 0 (:func:`eventcap.energy.terms.factors_from_config`).

Hessian layout of one factor with n samples (each sample a 33-vector of pose parameters, or its derivative):
``diag`` (n, 33, 33) the blocks of each sample with itself, ``upper`` (n-1, 33, 33) the blocks of sample k with
sample k+1 (factors that couple neighbouring samples, as E_cor), and for factors with auxiliary variables of their
own (E_3D's translation t' per sample, ``aux_size`` values each): ``aux_grad`` (n, a), ``cross`` (n, 33, a) and
``aux_diag`` (n, a, a).
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from eventcap.body.skeleton import NUM_POSE_PARAMS
from eventcap.body.template import Template
from eventcap.camera import Camera

from .errors import EnergyError

_NP = NUM_POSE_PARAMS

#: Every registered factor class by its name (filled when a subclass is defined).
FACTORS: dict[str, type[Factor]] = {}




@dataclass
class Linearization:
    """One factor's (weighted) value at its samples and, as asked, its derivatives there (module doc)."""

    value: float
    grad: np.ndarray | None = None  #: (n, 33)
    diag: np.ndarray | None = None  #: (n, 33, 33)
    upper: np.ndarray | None = None  #: (n - 1, 33, 33), blocks (k, k + 1)
    aux_grad: np.ndarray | None = None  #: (n, a)
    cross: np.ndarray | None = None  #: (n, 33, a)
    aux_diag: np.ndarray | None = None  #: (n, a, a)


@dataclass(frozen=True)
class Layout:
    """The sizes a problem is built for (fixed per built problem; each window's data must fit them).

    n_seg: knot intervals of a spline (0: poses per frame); n_frames: pose frames of a per-frame problem (0: a
    spline); n_det: detection frames; n_cor: tracking frames with correspondences; n_sil: frames of E_sil; band:
    how many units apart the Hessian's blocks reach (:func:`eventcap.energy.problem.coupling_band`)."""

    n_seg: int = 0
    n_frames: int = 0
    n_det: int = 0
    n_cor: int = 0
    n_sil: int = 0
    band: int | None = None  #: how far the Hessian's blocks reach (None: the parametrisation's default)


@dataclass
class Window:
    """What a window (or batch) of a solve knows; each factor reads the fields it needs in :meth:`Factor.prepare`.

    Fields a solve does not fill stay None; a factor that needs a missing one raises :class:`EnergyError`."""

    t0_us: int  #: the span of the poses (the spline's, or the first and last frame's)
    t1_us: int
    t_det_us: np.ndarray | None = None  #: (D,) detection frames
    detections: Any = None  #: FrameDetections at t_det_us
    t_cor_us: np.ndarray | None = None  #: (n_cor,) frames of the correspondences
    correspondences: Any = None  #: Correspondences between those frames (index into t_cor_us)
    cor_weight: np.ndarray | None = None  #: (P,) a weight in [0, 1] per correspondence (None: 1)
    cor_relative: bool = True  #: E_cor couples both frames of a correspondence (False: its source side held)
    phi: np.ndarray | None = None  #: (n_cor - 1, 24) E_temp's indicator
    t_sil_us: np.ndarray | None = None  #: (n_sil,) frames of E_sil
    silhouette: Any = None  #: SilhouetteCorrespondences at t_sil_us
    ref_joints: np.ndarray | None = None  #: (n_sil, 24, 3) E_stab's reference joints
    knots_us: np.ndarray | None = None  #: (n_seg + 1,) knot times of a spline (integrals over its intervals)
    stillness: np.ndarray | None = None  #: (n_seg, 24) in [0, 1]: each joint's stillness by the events per interval
    estimate: Callable[[np.ndarray], np.ndarray] | None = None  #: the current estimate's poses (T, 33) at times (T,)
    events: np.ndarray | None = None  #: the recording's events over the window
    prior_gain: np.ndarray | None = None  #: (33,) the motion prior's gain per pose parameter
    pull: tuple[np.ndarray, np.ndarray] | None = None  #: context pull (target, weight), each (D, 33)
    floor_y: float | None = None  #: the floor's height (world y, m) over the capture (None: not known)
    extra: dict = field(default_factory=dict)  #: data of factors not listed here, by their name

    def need(self, name: str, who: str):
        v = getattr(self, name)
        if v is None:
            raise EnergyError(f"{who}: the window has no {name} (this solve does not provide it)")
        return v


class Factor(ABC):
    """One term of the pose energy (module doc). Subclasses set ``name`` (their weight is the config's
    ``lambda_<name>``), implement :meth:`size`, :meth:`prepare` and :meth:`linearize`, and list the config keys
    they read besides their weight in ``settings``."""

    name: ClassVar[str]
    #: the derivative of the poses the factor sees at its samples (0: poses, 1: velocities, 2: accelerations ...)
    derivative: ClassVar[int] = 0
    #: auxiliary variables per sample that belong to this factor alone (E_3D's t': 3)
    aux_size: ClassVar[int] = 0
    #: whether the Hessian has blocks between neighbouring samples (k, k + 1)
    couples_neighbours: ClassVar[bool] = False
    #: config keys (besides the weight) the factor reads in its constructor
    settings: ClassVar[tuple[str, ...]] = ()

    def __init_subclass__(cls, **kw):
        super().__init_subclass__(**kw)
        name = cls.__dict__.get("name")
        if name is not None:
            other = FACTORS.get(name)
            if other is not None and other.__qualname__ != cls.__qualname__:
                raise TypeError(f"factor name {name!r} of {cls.__qualname__} is already {other.__qualname__}'s")
            FACTORS[name] = cls

    def __init__(self, weight: float, config: Any, template: Template, camera: Camera, layout: Layout):
        if isinstance(weight, bool) or not (isinstance(weight, (int, float)) and math.isfinite(weight) and weight >= 0):
            raise EnergyError(f"lambda_{self.name}: expected a finite weight >= 0, got {weight!r}")
        self.weight = float(weight)
        self.template, self.camera, self.layout = template, camera, layout
        self.n = int(self.size(layout))
        self.t_us = np.zeros(self.n, dtype=np.int64)

    @staticmethod
    @abstractmethod
    def size(layout: Layout) -> int:
        """Number of samples of this factor in a problem of this layout (fixed when the problem is built)."""

    @abstractmethod
    def prepare(self, window: Window) -> None:
        """Take this factor's data from the window and set its sample times ``self.t_us`` (n,)."""

    @abstractmethod
    def linearize(self, S: np.ndarray, aux: np.ndarray | None, order: int) -> Linearization:
        """Weighted value (order 0), gradient (1) and Hessian blocks (2) at the poses S (n, 33) of the samples
        (the ``derivative``-th derivative), with the factor's auxiliary variables aux (n, aux_size)."""

    def value(self, S: np.ndarray, aux: np.ndarray | None = None) -> float:
        return self.linearize(S, aux, 0).value

    def unweighted(self, S: np.ndarray, aux: np.ndarray | None = None) -> float:
        """The term itself (value / weight; 0 with weight 0): what solves report."""
        return self.value(S, aux) / self.weight if self.weight else 0.0


def weight_key(name: str) -> str:
    """The config key of a factor's weight."""
    return f"lambda_{name}"


__all__ = ["FACTORS", "Factor", "Layout", "Linearization", "Window", "weight_key"]
