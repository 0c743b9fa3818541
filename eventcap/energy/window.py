"""What a window of a solve observes (:class:`WindowInputs`) and its current estimate (:class:`Estimate`).

The factors (:mod:`.factor`) own their data: each takes what it needs from these. The inputs hold the solve's
inputs cut to the window (detections at its intensity frames, event tracks, events, reference poses) and the
evidence the solve measures once for every factor that asks (:meth:`WindowInputs.evidence`): the per-frame fits,
the joints' stillness in the events, the smoothing the fits around the window call for, the floor. Evidence is
measured on first request, so a factor that is off costs nothing. The estimate of one ICP round gives the poses at
any time and what is associated with them, searched once per round for every factor that asks: the tracks'
correspondences on the mesh, and what factors share through :meth:`Estimate.memo` (the sole points' contact).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from eventcap.body.template import Template
from eventcap.camera import Camera
from .correspondences import Correspondences, find_correspondences
from .errors import EnergyError
from .settings import ContactConfig


@dataclass(frozen=True)
class Tracks:
    """Event tracks at a window's correspondence frames: t_us (n,), xy (n, H, 2) pixels, valid (n, H); a track
    nearer than edge_margin_px to a silhouette edge of the estimate gives no correspondence."""

    t_us: np.ndarray
    xy: np.ndarray
    valid: np.ndarray
    edge_margin_px: float = 1.0


class WindowInputs:
    """The data of one window of a solve (module doc). Data are attributes (None when the solve has none);
    evidence is measured on request through :meth:`evidence`.

    t0_us, t1_us: the span of the poses; knots_us: a spline's knot times (None: one pose per frame); frames_us: the
    frames of a per-frame problem; t_det_us, detections: the detection frames (FrameDetections); tracks:
    :class:`Tracks`; track_times_us: the tracking frames of each batch the window solves (a tuple of arrays);
    events: the recording's events over the window; reference_us, reference_joints: joints (n, 24, 3) to hold at
    times (n,) (the refinement's); contact: :class:`ContactConfig`."""

    def __init__(self, t0_us: int, t1_us: int, *, knots_us=None, frames_us=None, t_det_us=None, detections=None,
                 tracks: Tracks | None = None, track_times_us: tuple = (), events=None, reference_us=None,
                 reference_joints=None, contact: ContactConfig | None = None,
                 evidence: Mapping[str, Callable[[], Any]] | None = None):
        self.t0_us, self.t1_us = int(t0_us), int(t1_us)
        self.knots_us = None if knots_us is None else np.asarray(knots_us, dtype=np.int64)
        self.frames_us = None if frames_us is None else np.asarray(frames_us, dtype=np.int64)
        self.t_det_us = None if t_det_us is None else np.asarray(t_det_us, dtype=np.int64)
        self.detections = detections
        self.tracks = tracks
        self.track_times_us = tuple(np.asarray(t, dtype=np.int64) for t in track_times_us)
        self.events = events
        self.reference_us = None if reference_us is None else np.asarray(reference_us, dtype=np.int64)
        self.reference_joints = reference_joints
        self.contact = ContactConfig() if contact is None else contact
        self._providers: dict[str, Callable[[], Any]] = dict(evidence or {})
        self._measured: dict[str, Any] = {}
        self.start: Callable[[np.ndarray], np.ndarray] | None = None  #: the solve's start (poses at times)

    def need(self, name: str, who: str):
        """The data ``name``, or an EnergyError naming ``who`` needs it when this solve has none."""
        v = getattr(self, name)
        if v is None:
            raise EnergyError(f"{who}: the window has no {name} (this solve does not provide it)")
        return v

    def provides(self, name: str) -> bool:
        """Whether this solve provides ``name`` at all: data that is set (a non-empty tuple of times), or evidence
        offered (:meth:`offer`), whatever it measures to."""
        if name in self._providers:
            return True
        value = getattr(self, name, None)
        return value is not None and not (isinstance(value, tuple) and not value)

    def offer(self, name: str, provider: Callable[[], Any]) -> None:
        """Offer evidence ``name``, measured by ``provider()`` on its first request."""
        self._providers[name] = provider
        self._measured.pop(name, None)

    def evidence(self, name: str) -> Any:
        """The evidence ``name`` (measured once, on first request), or None when the solve offers none: ``fits``
        ((D, 33) per-frame fits at the detection frames, NaN rows where none), ``fit_translation`` ((D, 3) their t'),
        ``context_fits`` ((times (K,), fits (K, 33)) of the detections around the window),
        ``stillness`` (:class:`eventcap.energy.silence.Silence`), ``smoothing``
        (:class:`eventcap.energy.prior.ContextSmoothing`), ``floor_y`` (the floor's height, world y, m)."""
        if name not in self._measured:
            provider = self._providers.get(name)
            self._measured[name] = None if provider is None else provider()
        return self._measured[name]

    def measured(self) -> dict[str, Any]:
        """The evidence measured so far, by name."""
        return dict(self._measured)


class Estimate:
    """The estimate of one ICP round: ``poses(t_us, deriv)`` at any time (a spline's curve, or poses at frames), and
    what is associated with it, searched once for every factor that asks. round: 0 for the first.

    coupled: whether a correspondence couples the two frames it joins (False: its source side is held where it was
    found, each frame solved on its own; the paper's w/o_batch)."""

    def __init__(self, poses: Callable[..., np.ndarray], round: int, inputs: WindowInputs, template: Template,
                 camera: Camera, coupled: bool = True, associate: bool = True):
        self._poses, self.round, self.inputs = poses, int(round), inputs
        self.template, self.camera, self.coupled, self.associate = template, camera, bool(coupled), bool(associate)
        self._memo: dict = {}

    def poses(self, t_us, deriv: int = 0) -> np.ndarray:
        return self._poses(np.asarray(t_us), deriv)

    def correspondences(self) -> Correspondences:
        """The window's tracks on the mesh at this estimate (:func:`.correspondences.find_correspondences` at the
        tracks' frames); none when this round does not associate (``associate`` False)."""
        if "cor" not in self._memo:
            tracks = self.inputs.tracks
            if not self.associate or tracks is None:
                self._memo["cor"] = Correspondences.empty()
            else:
                self._memo["cor"] = find_correspondences(self.template, self.camera, self.poses(tracks.t_us),
                                                         tracks.xy, tracks.valid, tracks.edge_margin_px)
        return self._memo["cor"]

    def memo(self, key, compute: Callable[[], Any]) -> Any:
        """What ``compute()`` gives, computed once per estimate for every factor that asks with the same key (an
        association several factors share: the sole points' contact of the floor terms)."""
        if key not in self._memo:
            self._memo[key] = compute()
        return self._memo[key]


def detection_curvature(factors, inputs: WindowInputs, fits: np.ndarray, aux: np.ndarray) -> np.ndarray:
    """a_p (33,): the mean diagonal of the Hessian of the factors that observe the detections (weighted) at the
    window's fits (D, 33) (their auxiliary variables aux (D, a): E_3D's t'), / 2: what a parameter's detections
    weigh per rad² in the window's energy (:mod:`eventcap.energy.prior`)."""
    seen = np.isfinite(fits).all(axis=1)
    diag = np.zeros(fits.shape)
    for f in factors:
        if not f.observes_detections:
            continue
        f.collect(inputs)
        a = np.nan_to_num(aux) if f.aux_size else None
        diag += np.einsum("dpp->dp", f.linearize(np.where(seen[:, None], fits, 0.0), a, 2).diag)
    return np.maximum(diag[seen].mean(0) / 2.0, 0.0)


__all__ = ["ContactConfig", "Estimate", "Tracks", "WindowInputs", "detection_curvature"]
