"""The factor interface: every term of the pose energy is one :class:`Factor`, every solve a sum of factors.

As GTSAM's ``NoiseModelFactor`` or Ceres's ``CostFunction``, a factor is one named term that owns its data and its
settings, and a solve never knows what a term means:

- its settings are one group of the solve's config, its :attr:`Factor.Config` (a dataclass whose ``weight`` is the
  term's λ; e.g. ``stages.solve.terms.prior.weight``), stated once in the factor's module;
- :meth:`Factor.samples` says at which times it sees the poses in a window (fixed when a problem is built);
- :meth:`Factor.collect` takes what it needs from the window's inputs (:class:`eventcap.energy.window.WindowInputs`:
  detections, tracks, events, and evidence the solve measured once for all factors), once per window;
- :meth:`Factor.relinearize` redoes what depends on the current estimate (:class:`eventcap.energy.window.Estimate`:
  the tracks' correspondences, the silhouette's closest events, a contact), at each ICP round;
- :meth:`Factor.linearize` gives its weighted value, gradient and Hessian (exact or Gauss-Newton) in pose space at
  its samples; :meth:`Factor.report` gives its counts for the solve's log and statistics.

A factor never knows how the poses are parametrised (a B-spline's control points, or one pose per frame):
:class:`eventcap.energy.problem.FactorProblem` maps the poses at every factor's samples to the decision variables
and sums the factors. A new term is one module (a subclass of :class:`Factor` registers itself by its ``name``)
and one config entry: a field ``<name>: <Factor>.Config`` in the ``terms`` group of each solve that should use it
(:func:`eventcap.energy.terms.term_configs`). A solve uses the factors of its ``terms`` whose weight is > 0, in the
order they are listed there.

Hessian layout of one factor with n samples (each sample a 33-vector of pose parameters, or its derivative):
``diag`` (n, 33, 33) the blocks of each sample with itself, ``upper`` (n-1, 33, 33) the blocks of sample k with
sample k+1 (factors that couple neighbouring samples, as E_cor), and for factors with auxiliary variables of their
own (E_3D's translation t' per sample, ``aux_size`` values each): ``aux_grad`` (n, a), ``cross`` (n, 33, a) and
``aux_diag`` (n, a, a).
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from eventcap.body.skeleton import NUM_POSE_PARAMS
from eventcap.body.template import Template
from eventcap.camera import Camera
from .errors import EnergyError
from .settings import FactorConfig, NoiseConfig

if TYPE_CHECKING:
    from .window import Estimate, WindowInputs

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
class Missing:
    """What a factor that is on lacks in a solve (:meth:`Factor.missing`): the reason, and the setting of its own
    (relative to its settings group, e.g. ``sigma_px=<px>``) that would give it what it lacks, if any."""

    reason: str
    instead: str | None = None


@dataclass(frozen=True)
class Layout:
    """The sizes a problem is built for (fixed per built problem; each window's data must fit them).

    n_seg: knot intervals of a spline (0: poses per frame); n_frames: pose frames of a per-frame problem (0: a
    spline); sizes: (factor name, number of samples) of every factor, in the solve's order; band: how many units
    apart the Hessian's blocks reach (None: the parametrisation's default; :func:`eventcap.energy.problem.coupling_band`)."""

    n_seg: int = 0
    n_frames: int = 0
    sizes: tuple[tuple[str, int], ...] = ()
    band: int | None = None

    def size(self, name: str) -> int:
        return dict(self.sizes).get(name, 0)


class Factor(ABC):
    """One term of the pose energy (module doc). Subclasses set ``name`` and ``Config`` and implement
    :meth:`samples`, :meth:`collect` and :meth:`linearize` (and :meth:`relinearize` when their data depend on the
    estimate)."""

    name: ClassVar[str]
    #: the factor's weighted settings group (a dataclass of eventcap.params.param fields, ``weight`` first: the
    #: paper's λ), or None when the factor has only a noise model
    Config: ClassVar[type | None] = FactorConfig
    #: the factor's noise-model settings group (``gain`` first, then its noise: :class:`NoiseConfig`), or None
    Noise: ClassVar[type | None] = None
    #: the derivative of the poses the factor sees at its samples (0: poses, 1: velocities, 2: accelerations ...)
    derivative: ClassVar[int] = 0
    #: auxiliary variables per sample that belong to this factor alone (E_3D's t': 3)
    aux_size: ClassVar[int] = 0
    #: whether the Hessian has blocks between neighbouring samples (k, k + 1)
    couples_neighbours: ClassVar[bool] = False
    #: whether the factor observes the detections of single frames (the per-frame fits fit these factors; their
    #: curvature at the fits is what a parameter's detections weigh, :func:`eventcap.energy.window.detection_curvature`)
    observes_detections: ClassVar[bool] = False
    #: what the factor reads from a window and cannot do without: data of the window's inputs (``tracks``,
    #: ``events``, ``detections`` ...) or evidence a solve offers (``stillness``, ``floor_y``). A solve that provides
    #: one of them not at all fails when it is built (:meth:`missing`, :meth:`eventcap.energy.terms.TermSet.check`);
    #: data that is there but empty in a window (no track, no event: a still scene) is data, not a missing input
    needs: ClassVar[tuple[str, ...]] = ()

    def __init_subclass__(cls, **kw):
        super().__init_subclass__(**kw)
        name = cls.__dict__.get("name")
        if name is not None:
            other = FACTORS.get(name)
            if other is not None and other.__qualname__ != cls.__qualname__:
                raise TypeError(f"factor name {name!r} of {cls.__qualname__} is already {other.__qualname__}'s")
            FACTORS[name] = cls

    def __init__(self, config: Any, template: Template, camera: Camera, n: int):
        noisy = isinstance(config, NoiseConfig)
        key = "gain" if noisy else "weight"
        weight = config.factor_weight
        if isinstance(weight, bool) or not (isinstance(weight, (int, float)) and math.isfinite(weight) and weight >= 0):
            raise EnergyError(f"terms.{self.name}.{key}: expected a finite number >= 0, got {weight!r}")
        self.config, self.noisy, self.gain = config, noisy, float(weight)
        self.template, self.camera = template, camera
        #: what multiplies the factor's squared residuals: its λ (weighted), or gain x the precision its noise
        #: model gives its residuals' units (:meth:`noise_precision`)
        self.weight = self.gain * (float(self.noise_precision(config, camera)) if noisy else 1.0)
        self.n = int(n)
        self.t_us = np.zeros(self.n, dtype=np.int64)

    @classmethod
    def accepts(cls, config: Any) -> bool:
        """Whether ``config`` is settings of this factor (its weighted ``Config`` or its ``Noise``)."""
        kinds = tuple(k for k in (cls.Config, cls.Noise) if k is not None)
        return isinstance(config, kinds)

    @classmethod
    def noise_precision(cls, config: Any, camera: Camera) -> float:
        """The precision ½ / σ² that the noise model of ``config`` (a :attr:`Noise`) gives one squared residual in
        the units the factor computes them in (the negative log-likelihood of Gaussian noise). 1 for a factor whose
        noise is per observation, in its data (the detection terms), or that has none of its own."""
        return 1.0

    # ------------------------------------------------------------------ a window's data
    @classmethod
    def missing(cls, inputs: WindowInputs, config: Any) -> Missing | None:
        """Why this factor, turned on, would have nothing to read in a window with these inputs (None: it has what
        it reads): what it :attr:`needs` that the solve does not provide. Subclasses add what their data must hold
        (the detection factors: the kind of detection they read, their noise model)."""
        gone = [name for name in cls.needs if not inputs.provides(name)]
        if not gone:
            return None
        return Missing(f"it reads the window's {' and '.join(gone)}, which this solve does not provide")

    @classmethod
    @abstractmethod
    def samples(cls, inputs: WindowInputs, config: Any) -> np.ndarray:
        """The times (µs: int64, or float for quadrature points) at which this factor sees the poses in a window with
        these inputs (their number fixes the size of a built problem; none: the factor sits out)."""

    def collect(self, inputs: WindowInputs) -> None:
        """Take this factor's data from the window's inputs (once per window) and set its sample times."""
        t = np.asarray(self.samples(inputs, self.config), dtype=np.int64)
        if t.shape != (self.n,):
            raise EnergyError(f"terms.{self.name}: built for {self.n} samples, the window gives {t.size}")
        self.t_us = t

    def relinearize(self, estimate: Estimate) -> None:  # noqa: B027 (optional: most factors do not move)
        """Redo what depends on the current estimate (correspondences, contacts, ...), at each ICP round."""

    def association_change(self, estimate: Estimate) -> float | None:
        """How far (px, RMS) re-associating this factor's data at ``estimate`` would move its residuals, or None for a
        factor without an association (the solve ends its ICP rounds when every factor that has one settled)."""
        return None

    def start_aux(self, inputs: WindowInputs) -> np.ndarray | None:
        """The start of this factor's auxiliary variables (n, aux_size) in a window (None: zeros)."""
        return None

    def start_penalty(self) -> tuple[int, np.ndarray] | None:
        """What this factor asks of the solve's start, a penalised spline through the per-frame fits: (derivative
        order, weight per pose parameter (33,)) of its roughness penalty, or None (the motion prior's)."""
        return None

    # ------------------------------------------------------------------ its energy
    @abstractmethod
    def linearize(self, S: np.ndarray, aux: np.ndarray | None, order: int) -> Linearization:
        """Weighted value (order 0), gradient (1) and Hessian blocks (2) at the poses S (n, 33) of the samples
        (the ``derivative``-th derivative), with the factor's auxiliary variables aux (n, aux_size)."""

    def value(self, S: np.ndarray, aux: np.ndarray | None = None) -> float:
        return self.linearize(S, aux, 0).value

    def unweighted(self, S: np.ndarray, aux: np.ndarray | None = None) -> float:
        """The term itself (value / weight: its squared residuals, weighted by their own noise where it is per
        observation; 0 with weight 0): what solves report."""
        return self.value(S, aux) / self.weight if self.weight else 0.0

    def report(self) -> dict[str, Any]:
        """Counts and measures of this window's data for the solve's statistics (JSON-able; keys unique across
        factors, e.g. ``n_correspondences``)."""
        return {}

    def describe(self) -> str | None:
        """One line for the solve's log about this window's data (None: nothing worth saying)."""
        return None


__all__ = ["FACTORS", "Factor", "FactorConfig", "Layout", "Linearization", "Missing", "NoiseConfig"]
