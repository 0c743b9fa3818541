"""Artifacts of Sec. 3.2-3.3: joint detections at intensity frames and the estimated skeletal motion."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from .base import Artifact, ArtifactError, array, attr


@dataclass(frozen=True, eq=False)
class Detections(Artifact):
    """2D landmarks (the skeleton's BODY_25 order, incl. the 4 face landmarks) and root-relative 3D joints (SMPL
    order, relative to the pelvis) at each intensity frame, with confidences in [0, 1] (0 = not detected).

    What is in view: ``in_view`` marks the landmarks that are observations (inside the image and, for a detector
    that says so, present in it); the others have confidence 0, and so have the 3D joints no landmark in view
    supports. ``image_status`` says per image why it holds a detection or not: ``ok``, ``no_person`` (the
    detector found nobody) or the name of the check that rejected it (``outside``, ``region``, ``scale``: see
    ``plugins/eventcap_detect/checks.py``); a rejected image has no observation at all (confidence 0 everywhere), its
    positions kept as the detector gave them, to look at.

    The detector's noise model (GTSAM's word), in two parts: ``sigma_2d_px`` each landmark's noise per image axis in
    each image, independent from image to image (white), and ``bias_2d_px`` the spread of its offset that stays the
    same over a capture (a detector's own idea of where a hip is, a lean it keeps); ``sigma_3d_m`` and ``bias_3d_m``
    the same for each root-relative joint, per axis of the camera (x right, y down, z along the line of sight: a
    monocular network knows depth least); ``outlier_share`` the share of landmarks it places anywhere (outliers,
    left/right flips), and ``noise_model`` where the figures come from (what the simulated detector simulates, what
    BlazePose measured on tuning captures, what a file states or the documented default). The solve weighs each
    observation by it: n images of one point tell its white noise n times over, its offset once. Schemas before v4
    had none: their caches are refused and recomputed."""

    schema_version: ClassVar[int] = 4
    t_us: np.ndarray = array("int64", ("n",), units="us", doc="time of the intensity frame")
    keypoints_2d: np.ndarray = array("float32", ("n", "l", 2), units="px")
    confidence_2d: np.ndarray = array("float32", ("n", "l"))
    joints_3d: np.ndarray = array("float64", ("n", 24, 3), units="m, relative to the pelvis")
    confidence_3d: np.ndarray = array("float32", ("n", 24))
    in_view: np.ndarray = array("bool", ("n", "l"), optional=True,
                                doc="landmark in the image and seen there (an observation); None: not stated "
                                    "(read as confidence_2d > 0)")
    detector: str = attr(default="", doc="what produced them (simulated detectors say so)")
    image_status: tuple = attr(default=(), doc="per image: ok | no_person | the check that rejected it; empty: "
                                               "not stated")
    person_up: tuple = attr(default=(), doc="the person's mean vertical over the accepted detections, camera axes "
                                            "(x right, y down, z forward), unit; empty: not measured")
    sigma_2d_px: np.ndarray = array("float32", ("n", "l"), units="px", optional=True,
                                    doc="each landmark's noise per image axis in each image (the noise model)")
    sigma_3d_m: np.ndarray = array("float32", ("n", 24, 3), units="m", optional=True,
                                   doc="each root-relative 3D joint's noise along each camera axis (x, y, z) in each "
                                       "image (the noise model)")
    bias_2d_px: np.ndarray = array("float32", ("l",), units="px", optional=True,
                                   doc="each landmark's offset that stays over the capture, its spread per axis")
    bias_3d_m: np.ndarray = array("float32", (24, 3), units="m", optional=True,
                                  doc="each root-relative joint's offset that stays over the capture, its spread along "
                                      "each camera axis")
    outlier_share: float = attr(default=0.0, doc="share of the landmarks the detector places anywhere (outliers and "
                                                 "left/right flips)")
    noise_model: str = attr(default="", doc="where the noise model comes from; empty: not stated")
    world_R: np.ndarray = array("float64", (3, 3), optional=True,
                                doc="the world->camera rotation the detect stage set from the person's vertical "
                                    "(a recording without extrinsics, Recording.world 'assumed_level'): joints_3d "
                                    "are in that world's axes, and every stage that places the body uses it "
                                    "(eventcap.worldframe.upright); None: the recording's camera")

    def validate(self) -> None:
        super().validate()
        for name in ("confidence_2d", "confidence_3d"):
            c = getattr(self, name)
            if c.size and (c.min() < 0 or c.max() > 1):
                raise ArtifactError(f"Detections.{name}: expected values in [0, 1], got [{c.min()}, {c.max()}]")
        n = self.t_us.shape[0]
        if self.image_status and len(self.image_status) != n:
            raise ArtifactError(f"Detections.image_status: expected one entry per image ({n}), got "
                                f"{len(self.image_status)}")
        if self.world_R is not None and not np.allclose(self.world_R @ self.world_R.T, np.eye(3), atol=1e-6):
            raise ArtifactError("Detections.world_R: expected a rotation matrix (R R^T = I)")
        if self.person_up and len(self.person_up) != 3:
            raise ArtifactError(f"Detections.person_up: expected 3 numbers or none, got {self.person_up!r}")
        for name in ("sigma_2d_px", "sigma_3d_m", "bias_2d_px", "bias_3d_m"):
            s = getattr(self, name)
            if s is not None and s.size and not np.all(np.isnan(s) | (s >= 0)):
                raise ArtifactError(f"Detections.{name}: expected noise figures >= 0 (NaN: unknown), got "
                                    f"{np.nanmin(s)}")
        if not 0.0 <= float(self.outlier_share) <= 1.0:
            raise ArtifactError(f"Detections.outlier_share: expected a share in [0, 1], got {self.outlier_share}")
        if self.in_view is not None and self.in_view.size and (self.confidence_2d[~self.in_view] > 0).any():
            i, j = np.argwhere(~self.in_view & (self.confidence_2d > 0))[0]
            raise ArtifactError(f"Detections: landmark {j} of image {i} is not in view but has confidence "
                                f"{self.confidence_2d[i, j]} (a landmark out of view is not an observation)")

    def observed(self) -> np.ndarray:
        """(n, l) bool: the landmarks that are observations (``in_view``, or confidence > 0 when not stated)."""
        return self.in_view.copy() if self.in_view is not None else self.confidence_2d > 0


@dataclass(frozen=True, eq=False)
class PoseSequence(Artifact):
    """Skeleton parameters S = [theta (27), root rotation (3), root translation (3)] at every tracking frame of a
    batch (or of a whole recording), with how the solve went."""

    schema_version: ClassVar[int] = 1
    t_us: np.ndarray = array("int64", ("f",), units="us")
    poses: np.ndarray = array("float64", ("f", 33), units="rad, m; nan: not estimated (a gap)")
    sigma_mm: np.ndarray = array("float32", ("f", 24), units="mm; nan: unknown", optional=True,
                                 doc="each joint's σ from the solve's own curvature (eventcap.energy.laplace: the "
                                     "Laplace approximation, the energy read as a negative log-likelihood, after a "
                                     "per-frame rigid alignment), not yet calibrated (the confidence stage scales "
                                     "it); NaN where unknown; None: the solve gives none")
    status: str = attr(default="", doc="solver status of the last solve; 'gap': nothing was observed, nothing is "
                                       "estimated (poses NaN); 'in_window': no frames, another batch's window "
                                       "estimates this batch (the spline solve's window_step)")
    iterations: int = attr(default=0)
    energies: dict = attr(default_factory=dict, doc="final value of each energy term")


@dataclass(frozen=True, eq=False)
class JointErrors(Artifact):
    """3D error of each joint of an estimated motion against the ground truth, at the evaluated tracking frames
    (paper Sec. 4): ``sampled`` marks the every-n-th frames the AE is taken over, ``raw`` those at intensity-frame
    times. A frame's AE is the mean over its joints."""

    schema_version: ClassVar[int] = 1
    t_us: np.ndarray = array("int64", ("f",), units="us")
    error_m: np.ndarray = array("float64", ("f", 24), units="m", doc="per-joint distance, SMPL joint order")
    sampled: np.ndarray = array("bool", ("f",), doc="one of the every-n-th tracking frames")
    raw: np.ndarray = array("bool", ("f",), doc="at the time of an intensity frame")
    align: str = attr(default="procrustes", doc="alignment before measuring: procrustes (per frame) | none")

    def validate(self) -> None:
        super().validate()
        if self.error_m.size and self.error_m.min() < 0:
            raise ArtifactError("JointErrors.error_m: distances must be >= 0")


@dataclass(frozen=True, eq=False)
class JointConfidence(Artifact):
    """What an estimated motion is worth, per frame and joint (:mod:`eventcap.analysis.uncertainty`): the uncertainty in
    millimetres (the RMS 3D distance to the truth one expects after a per-frame rigid alignment, calibrated: the
    error lies within 2 of it about 90-97 % of the time), from the solve's own curvature inflated where the
    detections, the events and the estimate disagree and for joints out of view; and the confidence in [0, 1] derived
    from it. Below 0.5 a joint is unobserved or not trusted; a gap (no estimate) has confidence 0 and uncertainty
    NaN. Schema v1 had no uncertainty: its caches are refused and recomputed."""

    schema_version: ClassVar[int] = 2
    t_us: np.ndarray = array("int64", ("f",), units="us")
    confidence: np.ndarray = array("float32", ("f", 24), doc="in [0, 1], SMPL joint order")
    uncertainty_mm: np.ndarray = array("float32", ("f", 24), units="mm; nan: no estimate (a gap)",
                                       doc="SMPL joint order; NaN where the frame has no estimate (a gap)")
    estimated: np.ndarray = array("bool", ("f",), doc="the frame has an estimate (False: a gap)")

    def validate(self) -> None:
        super().validate()
        c = self.confidence
        if c.size and (c.min() < 0 or c.max() > 1):
            raise ArtifactError(f"JointConfidence.confidence: expected values in [0, 1], got [{c.min()}, {c.max()}]")
        u = self.uncertainty_mm
        est = np.asarray(self.estimated, dtype=bool)
        if u.size and (np.any(u[np.isfinite(u)] < 0) or not np.isfinite(u[est]).all()):
            raise ArtifactError("JointConfidence.uncertainty_mm: expected finite values >= 0 at every estimated frame")
