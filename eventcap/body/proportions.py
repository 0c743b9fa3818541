"""The person's body from what one camera saw: the stature, limb lengths and girdle widths, each with a standard
error, moved from the template's only as far as the evidence weighs against a prior of human proportions.

Not in the paper (it scanned each actor). A user can give a height at most; the segments the detections show over
a capture tell the rest, as far as they can:

- **the measured segments** (:data:`SEGMENTS`): upper arms, forearms, thighs and shins (each side) and the shoulder
  and hip widths, between landmarks that sit on joints (BODY_25 points on SMPL joints);
- **a seen length per image** (:func:`seen_segments`): the segment along the direction the 3D detection gives it,
  its ends on the two 2D points' rays (:func:`eventcap.camera.seen_length`, perspective included), its middle at the depth of the person's pelvis plus
  the 3D detection's depth offset of that middle. Only images where the segment lies mostly across the line of
  sight count (its share across >= :data:`MIN_ACROSS`); each counts as much as its noise allows
  (:func:`image_noise`): a short segment in the image carries the 2D points' error over few pixels, and one out of
  the image plane the 3D detection's depth error times the tangent of its angle out of it;
- **the depth of the person per image** from the floor, when the camera's height above it is known (a world from
  the camera's extrinsics, the floor y = 0; :func:`floor_depths`): the sole points (heels, big toes) of the
  supporting foot lie on the floor at their rest heights, so their rays meet it at their depths; the ankle lies
  the template's foot geometry from them (turned to the foot's direction in the 3D detection), the pelvis the 3D
  detection's offset from the ankle. A foot off the floor puts the floor's point behind it, so images whose floor
  depth lies more than :data:`OFF_FLOOR_SIGMAS` of the floor's spread beyond the segments' are taken to be off it. Otherwise the depth is
  unknown per image and the stature cannot be told;
- **a detector's own definitions** (:data:`DETECTOR_DEFINITIONS`): where a detector puts its points against the
  template's joints (BlazePose: hips and shoulders nearer together); its seen lengths are divided by them;
- **what a detector shares within a capture** (:data:`DETECTOR_SPREAD`): the error of a segment's seen length that
  more images of the same capture do not average out (a learned detector's bias for this person and view), and
  that of the depth from the floor (the 3D detection's ankle offset); taken from the tuning captures.

**The model** (:func:`fit_body`), in logs: every seen length = the body's segment x the detector's definition x
exp(β_s, the detector's error on this segment in this capture) x exp(noise of the image); the pelvis depth of
every image is free, or, with the floor, observed with its own noise and a per-capture error φ. The images' noise
is the spread of what was seen: the robust spread (MAD) of the residuals, shaped per observation by its length in
pixels and how far across the line of sight it lies (:func:`image_noise`), and inflated by the images' correlation in time (consecutive images err alike: the
lag-1 correlation of the residuals ρ gives the effective number of images, n (1 - ρ) / (1 + ρ)). Observations more
than :data:`OUTLIER_SIGMAS` of their spread away are left out (flipped sides, wrong points).

**The prior** is the template's body with the spread of human bodies around it, from the 2012 anthropometric survey
of U.S. Army personnel (ANSUR II: C. C. Gordon et al., "2012 Anthropometric Survey of U.S. Army Personnel: Methods
and Summary Statistics", NATICK/TR-15/007, 2014; its public data files, 4,082 men and 1,986 women), half men and
half women: the stature ~ N(the template's, :data:`STATURE_SD_M`) (men 1756 +- 68.5 mm, women 1628.5 +- 64.2 mm);
at a given stature, the logs of the six segment kinds' lengths ~ N(the template's at that stature,
:data:`PROPORTION_COV`), the residual covariance of each log length regressed on log stature (upper arm:
acromion-radiale length; forearm: radiale-stylion length; thigh: trochanterion height - lateral femoral epicondyle
height; shin: lateral femoral epicondyle height - lateral malleolus height; shoulders: biacromial breadth; hips:
bicristal breadth). A template's body is ANNY's (stature, sex, muscle; ``build`` moves no joint by more than 2 mm
and is left as it is), so the prior of the proportions is that density over ANNY's shapes, with each phenotype
within :data:`PHENOTYPE_SD` of the template's (ANNY's own range).

**The posterior**: the most probable stature, sex and muscle given both (robust Gauss-Newton), their covariance from
its Hessian with the images' depths and the detector's errors marginalised (a Schur complement), each segment's
length and standard error by the delta method. Each quantity moves from the template's as far as its evidence
weighs: ``share`` = 1 - σ_post² / σ_prior², 0 where nothing was seen. What the user stated is not estimated.

Every value used is from the detections, the camera and the template: never the ground truth.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from eventcap.body.skeleton import JOINT_INDEX, LANDMARK_INDEX, PARENTS
from eventcap.camera import seen_length

#: The measured segments: name -> (joint a, joint b); each joint carries a BODY_25 landmark on it.
SEGMENTS: dict[str, tuple[str, str]] = {
    "l_upper_arm": ("l_shoulder", "l_elbow"), "r_upper_arm": ("r_shoulder", "r_elbow"),
    "l_forearm": ("l_elbow", "l_wrist"), "r_forearm": ("r_elbow", "r_wrist"),
    "l_thigh": ("l_hip", "l_knee"), "r_thigh": ("r_hip", "r_knee"),
    "l_shin": ("l_knee", "l_ankle"), "r_shin": ("r_knee", "r_ankle"),
    "shoulders": ("l_shoulder", "r_shoulder"), "hips": ("l_hip", "r_hip"),
}
LIMBS = tuple(n for n in SEGMENTS if n not in ("shoulders", "hips"))
GIRDLES = ("shoulders", "hips")
#: The kinds of segment the prior knows (left and right alike): segment -> kind.
KINDS = ("upper_arm", "forearm", "thigh", "shin", "shoulders", "hips")
KIND_OF: dict[str, str] = {n: n[2:] if n[:2] in ("l_", "r_") else n for n in SEGMENTS}
#: A segment counts in an image where this share of its 3D direction lies across the line of sight.
MIN_ACROSS = 0.7
#: A segment with fewer images than this is not measured.
MIN_IMAGES = 3
#: The shape of an image's noise on a seen length (:func:`image_noise`): the 2D points' error over the segment's
#: length in the image (px), and the relative error per unit of the tangent of its angle out of the image plane.
#: Fitted on the tuning captures' residuals (docs/results/body.md); a capture's own spread scales them.
NOISE_PX = 2.8
NOISE_TAN = 0.22
#: An observation this many of its standard deviations from the fit is an outlier (a flipped side, a wrong point).
OUTLIER_SIGMAS = 4.0
#: An image whose floor depth lies this many of the floor's SDs beyond the depth its segments give is taken to be off
#: the floor (a jump: the floor's point then lies behind the foot).
OFF_FLOOR_SIGMAS = 3.0
#: What a detector's seen lengths come out as against the true ones, seen / true per segment: where it puts its points
#: against the template's joints (BlazePose: hips and shoulders nearer together), and how much its 3D directions'
#: errors shorten the seen length (a direction off by an angle projects the segment shorter). Measured on the tuning
#: captures (docs/results/body.md); a detector not listed is taken to give the true lengths.
DETECTOR_DEFINITIONS: dict[str, dict[str, float]] = {
    # BlazePose GHUM (full): the medians over the 10 whole-body tuning captures with frames of the open benchmark,
    # left and right averaged (per capture they spread by about +-8 %)
    "blazepose": {"l_upper_arm": 0.944, "r_upper_arm": 0.944, "l_forearm": 0.989, "r_forearm": 0.989,
                  "l_thigh": 0.936, "r_thigh": 0.936, "l_shin": 0.938, "r_shin": 0.938, "shoulders": 0.876,
                  "hips": 0.870},
    # the simulated detector (its points on the joints, its 3D joints off by a fixed 4 cm per axis): exp of the mean
    # log error per kind over the suite's tuning captures (seeds 0-1 of its 6 motions, 1 s) and 6 draws of the
    # detector's errors each (benchmarks/accuracy/bench_body.py --spread --draws 5)
    "simulated": {"l_upper_arm": 0.972, "r_upper_arm": 0.972, "l_forearm": 0.949, "r_forearm": 0.949,
                  "l_thigh": 1.007, "r_thigh": 1.007, "l_shin": 1.004, "r_shin": 1.004, "shoulders": 1.036,
                  "hips": 1.030},
}


@dataclass(frozen=True)
class DetectorSpread:
    """What a detector's errors share within one capture, which more images do not average out: ``segment`` per
    kind (:data:`KINDS`) the SD over captures of the log of a segment's seen length (its mean over the capture's
    images against the truth, the definitions removed), ``floor`` the SD of the log of the person's depth from the
    floor (its median over the images against the truth); both less what the images' own noise explains (the fit
    adds that from the capture's own spread)."""

    segment: dict
    floor: float

    def of(self, name: str) -> float:
        """The spread of a segment (by its kind)."""
        return float(self.segment[KIND_OF[name]])


#: Per detector (by the start of its name), taken from the tuning captures (docs/results/body.md).
DETECTOR_SPREAD: dict[str, DetectorSpread] = {
    # the same captures and draws as its definitions (a 1 s capture; span_factor scales them)
    "simulated": DetectorSpread(segment={"upper_arm": 0.13, "forearm": 0.23, "thigh": 0.027, "shin": 0.024,
                                         "shoulders": 0.05, "hips": 0.023}, floor=0.016),
    # the open benchmark's whole-body tuning captures with frames whose body nobody told (seeds 0, 2, 8, 16; one
    # capture each, so rounded up): the floor from seeds 0, 2 and 8 (16's clip floats 19 cm above the floor)
    "blazepose": DetectorSpread(segment={"upper_arm": 0.11, "forearm": 0.08, "thigh": 0.05, "shin": 0.07,
                                         "shoulders": 0.06, "hips": 0.06}, floor=0.04),
}
#: The time over which a capture's poses change enough to err a segment differently (s): see :func:`span_factor`.
POSE_TIME_S = 1.0
#: Images spanning less than this (s) move nothing: too few poses to tell the body from its detector's errors, and
#: shorter than the spreads were measured on (a quarter second of 7 images: the template stays).
MIN_SPAN_S = 0.75
#: A detector not listed: the largest spreads of those measured, per kind.
UNKNOWN_SPREAD = DetectorSpread(segment={k: max(s.segment[k] for s in DETECTOR_SPREAD.values()) for k in KINDS},
                                floor=max(s.floor for s in DETECTOR_SPREAD.values()))


def detector_spread(detector: str) -> tuple[DetectorSpread, str]:
    """The spread of a detector (:data:`DETECTOR_SPREAD`, by the start of its name) and which; unknown: the largest."""
    for name, spread in DETECTOR_SPREAD.items():
        if str(detector).lower().startswith(name):
            return spread, name
    return UNKNOWN_SPREAD, ""


#: The floor tells the person's depth only when the camera looks down on it steeply enough: the camera's height
#: over the person's distance at least this (a ray's depth error per pixel grows as distance / height; chosen on the
#: tuning captures: docs/results/implementation.md).
MIN_FLOOR_ELEVATION = 0.3
#: The sole points of each foot (heels and big toes), BODY_25 landmarks.
_SOLES = {"l": ("l_heel", "l_big_toe"), "r": ("r_heel", "r_big_toe")}

# --------------------------------------------------------------------------------------------- the prior (ANSUR II)
#: SD of the adult stature, half men and half women (ANSUR II, module doc): 92.1 mm.
STATURE_SD_M = 0.092
#: SD of the log length of each segment kind (:data:`KINDS`) at a given stature, and their correlations: the
#: residuals of log length regressed on log stature over ANSUR II's men and women (weighted half each; module doc).
_KIND_SD = np.array([0.0328, 0.0437, 0.0490, 0.0431, 0.0492, 0.0685])
_KIND_CORR = np.array([
    [1.00, 0.31, 0.18, 0.36, 0.01, 0.07],
    [0.31, 1.00, 0.25, 0.26, 0.23, -0.18],
    [0.18, 0.25, 1.00, 0.05, -0.06, -0.12],
    [0.36, 0.26, 0.05, 1.00, -0.26, 0.01],
    [0.01, 0.23, -0.06, -0.26, 1.00, -0.03],
    [0.07, -0.18, -0.12, 0.01, -0.03, 1.00],
])
PROPORTION_COV = _KIND_CORR * np.outer(_KIND_SD, _KIND_SD)
PROPORTION_COV.setflags(write=False)


def segment_lengths(rest_joints: np.ndarray) -> dict[str, float]:
    """Length (m) of every segment of :data:`SEGMENTS` in a rest skeleton (24, 3)."""
    J = np.asarray(rest_joints, dtype=np.float64)
    return {n: float(np.linalg.norm(J[JOINT_INDEX[a]] - J[JOINT_INDEX[b]])) for n, (a, b) in SEGMENTS.items()}


def rest_skeleton_from_motion(poses: np.ndarray, joints: np.ndarray) -> np.ndarray:
    """The rest skeleton (24, 3; pelvis at the origin) a posed motion was made with: each bone vector turned back by
    its parent's rotation (joint positions are linear in the rest skeleton), the median over the frames given.
    poses (T, 33), joints (T, 24, 3) of the same skeleton (e.g. a capture's ground truth)."""
    from eventcap.body.kinematics import global_transforms

    S = np.atleast_2d(np.asarray(poses, dtype=np.float64))
    P = np.asarray(joints, dtype=np.float64).reshape(S.shape[0], 24, 3)
    R = global_transforms(S, np.zeros((24, 3)))[..., :3, :3]  # rotations do not depend on the rest skeleton
    rest = np.zeros((24, 3))
    for j in range(1, 24):
        p = int(PARENTS[j])
        bone = np.einsum("tji,tj->ti", R[:, p], P[:, j] - P[:, p])
        rest[j] = rest[p] + np.median(bone, axis=0)
    return rest


def image_noise(pixels: np.ndarray, across: np.ndarray) -> np.ndarray:
    """The shape of an image's relative noise on a seen length (a capture's spread scales it): sqrt((NOISE_PX /
    pixels)² + (NOISE_TAN tan ψ)²), pixels its length in the image, across = cos ψ the share of its direction
    across the line of sight. The 2D points err by a few pixels whatever the length; the length is the image length
    over cos ψ, so a depth error of the 3D direction errs it by tan ψ times that error over the length."""
    a = np.clip(np.asarray(across, dtype=np.float64), 1e-3, 1.0)
    tan = np.sqrt(np.maximum(1.0 - a * a, 0.0)) / a
    px = np.maximum(np.asarray(pixels, dtype=np.float64), 1.0)
    return np.sqrt((NOISE_PX / px) ** 2 + (NOISE_TAN * tan) ** 2)


@dataclass(frozen=True)
class SeenSegments:
    """Per segment, the images where it was seen across the line of sight: ``image`` (K,) indices into the
    detections' images; ``unit`` (K,) its seen length (m) were its middle 1 m away; ``offset`` (K,) the depth of its
    middle minus the pelvis's (m, from the 3D detection); ``across`` (K,) the share of its 3D direction across the
    line of sight; ``pixels`` (K,) its length in the image (px). Its seen length at pelvis depth z:
    unit * (z + offset)."""

    image: dict = field(default_factory=dict)  #: name -> (K,) int
    unit: dict = field(default_factory=dict)  #: name -> (K,) seen length (m) of the segment at 1 m depth
    offset: dict = field(default_factory=dict)  #: name -> (K,) depth of its middle relative to the pelvis (m)
    across: dict = field(default_factory=dict)  #: name -> (K,) share of its direction across the line of sight
    pixels: dict = field(default_factory=dict)  #: name -> (K,) its length in the image, px

    def counts(self) -> dict[str, int]:
        return {n: int(len(v)) for n, v in self.image.items()}


def seen_segments(camera, keypoints_2d: np.ndarray, confidence_2d: np.ndarray, joints_3d: np.ndarray,
                  confidence_3d: np.ndarray) -> SeenSegments:
    """Each segment's seen length at unit depth, per image where both ends are detected in 2D and 3D and the 3D
    detection puts it across the line of sight (module doc). keypoints_2d (N, 25, 2) px, confidence_2d (N, 25),
    joints_3d (N, 24, 3) root-relative in world axes (m), confidence_3d (N, 24)."""
    out = SeenSegments()
    R = np.asarray(camera.R, dtype=np.float64)
    J3c = np.asarray(joints_3d, dtype=np.float64) @ R.T  # root-relative, camera axes
    for name, (a, b) in SEGMENTS.items():
        ja, jb, la, lb = JOINT_INDEX[a], JOINT_INDEX[b], LANDMARK_INDEX[a], LANDMARK_INDEX[b]
        ok = ((confidence_2d[:, la] > 0) & (confidence_2d[:, lb] > 0) & (confidence_3d[:, ja] > 0)
              & (confidence_3d[:, jb] > 0) & np.isfinite(J3c[:, [ja, jb]]).all(axis=(1, 2)))
        idx = np.flatnonzero(ok)
        if idx.size == 0:
            out.image[name], out.unit[name], out.offset[name], out.across[name], out.pixels[name] = (
                np.zeros(0, int), np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0))
            continue
        v = J3c[idx, ja] - J3c[idx, jb]
        across = np.linalg.norm(v[:, :2], axis=1) / np.maximum(np.linalg.norm(v, axis=1), 1e-9)
        kp = np.asarray(keypoints_2d, dtype=np.float64)[idx][:, [la, lb]]
        n = camera.undistort_points(kp)
        unit = seen_length(n[:, 0], n[:, 1], v, np.ones(idx.size))
        use = (across >= MIN_ACROSS) & np.isfinite(unit) & (unit > 0)
        out.image[name] = idx[use]
        out.unit[name] = unit[use]
        out.offset[name] = 0.5 * (J3c[idx, ja, 2] + J3c[idx, jb, 2])[use]
        out.across[name] = across[use]
        out.pixels[name] = np.linalg.norm(kp[:, 0] - kp[:, 1], axis=1)[use]
    return out


@dataclass(frozen=True)
class FootGeometry:
    """Where each sole point lies against its ankle in a rest body: ``height`` (m above the floor) and ``offset``
    (2,) its horizontal offset (x, z) from the ankle in the rest body's axes, and ``axis`` (side -> (2,)) the unit
    horizontal direction of the rest foot (ankle to the ``foot`` joint): a posed foot turns them with it."""

    height: dict
    offset: dict
    axis: dict


def foot_geometry(rest_joints: np.ndarray, rest_landmarks: np.ndarray) -> FootGeometry:
    """The sole points' rest geometry (:class:`FootGeometry`) of a template (rest joints (24, 3), rest landmarks
    (25, 3); feet flat on y = 0)."""
    J = np.asarray(rest_joints, dtype=np.float64)
    L = np.asarray(rest_landmarks, dtype=np.float64)
    height, offset, axis = {}, {}, {}
    for s, names in _SOLES.items():
        a = J[JOINT_INDEX[f"{s}_ankle"]]
        f = (J[JOINT_INDEX[f"{s}_foot"]] - a)[[0, 2]]
        axis[s] = f / max(float(np.linalg.norm(f)), 1e-9)
        for n in names:
            p = L[LANDMARK_INDEX[n]]
            height[n] = float(p[1])
            offset[n] = (p - a)[[0, 2]]
    return FootGeometry(height=height, offset=offset, axis=axis)


def floor_depths(camera, keypoints_2d: np.ndarray, confidence_2d: np.ndarray, joints_3d: np.ndarray,
                 confidence_3d: np.ndarray, feet: FootGeometry) -> np.ndarray:
    """(N,) depth (m, camera axes) of the pelvis per image from the floor y = 0 of a world given by the camera's
    extrinsics: the supporting foot (the lower ankle in the 3D detection, world y up) has its sole points on the
    floor at their rest heights (``feet``), so their rays meet it at their depths; the ankle lies their rest offsets
    from them, turned to the foot's direction in the 3D detection (ankle to foot joint); the pelvis the 3D
    detection's offset from the ankle. NaN where no sole point of that foot is detected or its ray does not meet
    the floor in front of the camera."""
    J3 = np.asarray(joints_3d, dtype=np.float64)
    N = J3.shape[0]
    out = np.full(N, np.nan)
    R = np.asarray(camera.R, dtype=np.float64)
    centre = np.asarray(camera.center, dtype=np.float64)
    kp = np.asarray(keypoints_2d, dtype=np.float64)
    for i in range(N):
        feet_i = [(s, JOINT_INDEX[f"{s}_ankle"]) for s in ("l", "r")
                  if confidence_3d[i, JOINT_INDEX[f"{s}_ankle"]] > 0 and np.isfinite(J3[i, JOINT_INDEX[f"{s}_ankle"]]).all()]
        if not feet_i:
            continue
        side, ankle = min(feet_i, key=lambda f: J3[i, f[1], 1])
        names = [n for n in _SOLES[side] if confidence_2d[i, LANDMARK_INDEX[n]] > 0]
        if not names:
            continue
        n = camera.undistort_points(kp[i, [LANDMARK_INDEX[m] for m in names]])  # (k, 2) normalised
        rays = np.concatenate([n, np.ones((len(names), 1))], axis=1) @ R  # world directions (R^T d)
        h = np.array([feet.height[m] for m in names])
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = (h - centre[1]) / rays[:, 1]  # camera depth of each sole point on the floor (ray scaled by z = 1)
        # the foot's turn about the vertical: its rest axis onto the detected ankle-to-foot direction
        foot = JOINT_INDEX[f"{side}_foot"]
        d = (J3[i, foot] - J3[i, ankle])[[0, 2]] if confidence_3d[i, foot] > 0 else np.zeros(2)
        if np.isfinite(d).all() and np.linalg.norm(d) > 1e-6:
            d = d / np.linalg.norm(d)
            a0 = feet.axis[side]
            c, s = float(a0 @ d), float(a0[0] * d[1] - a0[1] * d[0])
            turn = np.array([[c, -s], [s, c]])
        else:
            turn = np.eye(2)
        off = np.array([turn @ feet.offset[m] for m in names])  # (k, 2) world x, z
        off_cam = (np.stack([off[:, 0], np.zeros(len(names)), off[:, 1]], axis=1) @ R.T)[:, 2]
        z_ankle = lam - off_cam
        z_ankle = z_ankle[np.isfinite(lam) & (lam > 0)]
        if z_ankle.size == 0:
            continue
        out[i] = float(np.mean(z_ankle)) + float(((J3[i, 0] - J3[i, ankle]) @ R.T)[2])
    return out


#: The phenotypes a fit may estimate (ANNY's; ``build`` moves no joint by more than 2 mm: never fitted).
FITTED_PHENOTYPES = ("sex", "muscle")
#: The statures a fit may reach (m): adults, within ANNY's range.
STATURE_RANGE_M = (1.40, 2.10)
#: ANNY's phenotypes range over [-1, 1] (a uniform there has an SD of 0.58): a prior of this SD around the template's
#: keeps a phenotype the segments cannot tell where it is (muscle moves no measured segment above 0, but the mesh).
PHENOTYPE_SD = 0.5


@dataclass(frozen=True)
class Moved:
    """One quantity's update: the template's value and its prior SD, what the evidence alone says (``seen``, its
    standard error ``seen_se``; None: not seen), the posterior and its SD, in metres (a stature, a segment's
    length). ``images``: how many images carry the evidence, ``effective``: as independent ones."""

    template: float
    prior_sd: float
    posterior: float
    posterior_sd: float
    seen: float | None = None
    seen_se: float | None = None
    images: int = 0
    effective: float = 0.0

    @property
    def share(self) -> float:
        """How far all the evidence weighs on it: 1 - σ_post² / σ_prior² (0: the prior alone, 1: the evidence alone);
        a segment's includes what the stature's evidence and the other segments' tell."""
        return float(max(0.0, 1.0 - (self.posterior_sd / self.prior_sd) ** 2)) if self.prior_sd > 0 else 0.0

    @property
    def weight(self) -> float:
        """How far its own evidence weighs against the prior, alone: σ_prior² / (σ_prior² + SE²) (0: not seen)."""
        if self.seen_se is None or self.prior_sd <= 0:
            return 0.0
        return float(self.prior_sd ** 2 / (self.prior_sd ** 2 + self.seen_se ** 2))


@dataclass(frozen=True)
class BodyEstimate:
    """What the fit found: the body's parameters, their posterior covariance, and per quantity what moved, by how
    much and on what evidence (:class:`Moved`)."""

    height_m: float
    build: float
    muscle: float
    sex: float
    estimated: tuple  #: the parameters updated (the others as the template states or defaults them)
    scale_from: str  #: where the stature comes from: "stated", "floor", or why the template's is kept
    images: int  #: images with at least one seen segment
    seen: dict  #: segment -> images it was seen in across the line of sight
    measured_m: dict  #: segment -> its seen length (the evidence's estimate, definitions removed), m
    floor_images: int = 0  #: images whose pelvis depth the floor gave (scale_from "floor")
    cov: np.ndarray | None = None  #: covariance of ``uncertain`` (height_m in m, the phenotypes in units)
    uncertain: tuple = ()  #: the parameters not stated, in ``cov``'s order (those not estimated: their prior's)
    segments: dict = field(default_factory=dict)  #: segment -> Moved
    stature: Moved | None = None  #: the stature's update (None: not estimated)
    noise: dict = field(default_factory=dict)  #: the images' spread: sigma, rho, outliers, sigma_floor
    why: str = ""  #: why nothing was estimated (estimated empty)

    def params(self) -> dict:
        return {"height_m": self.height_m, "build": self.build, "muscle": self.muscle, "sex": self.sex}

    def sd(self, name: str) -> float:
        """The SD of a parameter not stated (the posterior's, or the prior's where not estimated); 0 when stated."""
        if self.cov is None or name not in self.uncertain:
            return 0.0
        k = self.uncertain.index(name)
        return float(np.sqrt(max(self.cov[k, k], 0.0)))


def _robust_sd(x: np.ndarray) -> float:
    x = np.asarray(x, dtype=np.float64)
    x = x[np.isfinite(x)]
    if x.size < 2:
        return float("nan")
    return float(1.4826 * np.median(np.abs(x - np.median(x))))


def _lag1(r: np.ndarray, seg: np.ndarray, img: np.ndarray) -> float:
    """Lag-1 correlation of residuals r of consecutive images (index difference 1) of the same segment."""
    a, b = [], []
    for k in np.unique(seg):
        m = np.flatnonzero(seg == k)
        o = m[np.argsort(img[m])]
        nxt = np.flatnonzero(np.diff(img[o]) == 1)
        a.append(r[o[nxt]])
        b.append(r[o[nxt + 1]])
    a, b = np.concatenate(a) if a else np.zeros(0), np.concatenate(b) if b else np.zeros(0)
    if a.size < 5:
        return 0.0
    a, b = a - a.mean(), b - b.mean()
    den = float(np.sqrt((a * a).sum() * (b * b).sum()))
    return float((a * b).sum() / den) if den > 0 else 0.0


def span_factor(span_s: float) -> float:
    """How a detector's per-capture spread (measured on 1 s captures) scales with the time its images span: part of it
    follows the pose (a fixed 3D offset errs a segment by how it lies), which more poses average out, part stays:
    sqrt((1 + POSE_TIME_S / span) / (1 + POSE_TIME_S)), 1.58 x on a quarter second, 0.74 x on 10 s."""
    span = max(float(span_s), 0.04)
    return float(np.sqrt((1.0 + POSE_TIME_S / span) / (1.0 + POSE_TIME_S)))


def prior_cov(start: dict, free: tuple, rest_joints, stature_sd_m: float = STATURE_SD_M,
              proportion_cov: np.ndarray = PROPORTION_COV) -> tuple[tuple, np.ndarray]:
    """The prior's covariance of the free parameters around the template's (``free`` among height_m, sex, muscle):
    the stature's SD ``stature_sd_m``; the phenotypes' from the prior of the proportions at that stature
    (``proportion_cov`` of :data:`KINDS`' log lengths) and :data:`PHENOTYPE_SD`, at the template (their inverse
    Hessian). (names, cov); the stature and the phenotypes are taken independent."""
    names = tuple(q for q in ("height_m", "sex", "muscle") if q in free)
    cov = np.zeros((len(names), len(names)))
    pheno = [q for q in names if q != "height_m"]
    if "height_m" in names:
        cov[0, 0] = stature_sd_m ** 2
    if pheno:
        def kinds_of(p):
            L = segment_lengths(rest_joints(p["height_m"], p["build"], p["muscle"], p["sex"]))
            ll = np.log([L[n] for n in SEGMENTS])
            return np.array([np.mean([ll[i] for i, n in enumerate(SEGMENTS) if KIND_OF[n] == k]) for k in KINDS])

        J = np.zeros((len(KINDS), len(pheno)))
        for j, q in enumerate(pheno):
            up, dn = dict(start), dict(start)
            up[q], dn[q] = min(start[q] + 1e-3, 1.0), max(start[q] - 1e-3, -1.0)
            J[:, j] = (kinds_of(up) - kinds_of(dn)) / (up[q] - dn[q])
        H = J.T @ np.linalg.solve(np.asarray(proportion_cov, dtype=np.float64), J) + np.eye(len(pheno)) / PHENOTYPE_SD ** 2
        k = [names.index(q) for q in pheno]
        cov[np.ix_(k, k)] = np.linalg.inv(H)
    return names, cov


def _floor_for_stature(free: tuple, floor_z: np.ndarray | None, camera_height_m: float | None,
                       images: list) -> tuple[np.ndarray | None, str]:
    """Whether the floor can tell the stature: (the pelvis depth per image from the floor, None where it cannot;
    where the stature comes from meanwhile: "stated", "template default", or why the floor cannot tell it). It can
    with ``floor_z`` and ``camera_height_m`` given, the camera at least :data:`MIN_FLOOR_ELEVATION` times the
    person's distance high, and a supporting foot's sole seen on the floor in :data:`MIN_IMAGES` of the ``images``
    with segments."""
    if "height_m" not in free:
        return None, "stated"
    if floor_z is None or camera_height_m is None:
        return None, ("template default (without the floor and the camera's height one camera cannot tell the "
                      "stature)")
    fz_all = np.asarray(floor_z, dtype=np.float64)
    dist = float(np.nanmedian(fz_all)) if np.isfinite(fz_all).any() else float("nan")
    if not np.isfinite(dist):
        return None, "template default (no sole of a supporting foot seen on the floor)"
    if camera_height_m < MIN_FLOOR_ELEVATION * dist:
        return None, (f"template default (the camera {camera_height_m:.2f} m high, the person ~{dist:.1f} m "
                      f"away: too low for the floor to tell the depth, below {MIN_FLOOR_ELEVATION} x the "
                      "distance)")
    ok = np.isfinite(fz_all[images]) & (fz_all[images] > 0) if images else np.zeros(0, bool)
    if int(ok.sum()) < MIN_IMAGES:
        return None, (f"template default (the supporting foot's sole seen on the floor in {int(ok.sum())} images "
                      f"with segments; needs {MIN_IMAGES})")
    return fz_all, "template default"


def _images_span_s(t_us: np.ndarray | None, images: list) -> float:
    """The time the images cover (s): from the first to the last plus their median interval (1 s without times)."""
    if t_us is None or len(images) <= 1:
        return 1.0
    times = np.asarray(t_us, dtype=np.float64)[images]
    return float(np.ptp(times) + np.median(np.diff(times))) / 1e6


#: Per segment kind: the indices of its segments in :data:`SEGMENTS`.
_KIND_IDX = {k: [i for i, n in enumerate(SEGMENTS) if KIND_OF[n] == k] for k in KINDS}


@dataclass
class _BodyFit:
    """One fit's observations (one per seen segment and image: the log of its seen length), the layout of its
    parameters and the model it fits (:func:`fit_body`). The parameters: θ (``theta``, the body) | β (the
    detector's error on each seen segment) | φ (the floor's error, 1 with the floor) | ln z (each image's depth)."""

    params: dict  #: the template's body (the prior's centre)
    theta: list  #: the body's parameters estimated
    pheno: list  #: the phenotypes among them
    names: list  #: the seen segments (each in at least MIN_IMAGES images)
    rest_joints: object  #: rest_joints(height_m, build, muscle, sex): a body's rest joints
    n_images: int  #: the images with segments
    use_floor: bool  #: whether the floor gives the depths (and the stature)
    seg: np.ndarray  #: per observation: its segment (index into names)
    img: np.ndarray  #: per observation: its image (index into the images with segments)
    unit: np.ndarray  #: per observation: the seen length at unit depth
    off: np.ndarray  #: per observation: the segment's depth offset from the pelvis (m)
    g: np.ndarray  #: per observation: its noise relative to the others (:func:`image_noise`)
    ln_c: np.ndarray  #: per seen segment: the log of the detector's seen/true length share
    sd_beta: np.ndarray  #: per seen segment: the prior SD of the detector's error on it (log)
    sd_phi: float  #: the prior SD of the floor's error (log)
    fz: np.ndarray  #: per image: the pelvis depth from the floor (m; NaN where unknown)
    fimg: np.ndarray  #: the images whose floor depth counts (narrowed to those on the floor before the final fit)
    obs_idx: np.ndarray  #: per seen segment: its index in SEGMENTS
    W_prop: np.ndarray  #: Wᵀ W = the inverse of the proportions' prior covariance
    sd_lnH: float  #: the stature's prior SD (log)
    ln_H0: float  #: the template's log stature
    lo: np.ndarray  #: the parameters' lower bounds
    hi: np.ndarray  #: the parameters' upper bounds
    memo: dict = field(default_factory=dict)  #: the bodies' log lengths computed so far

    @property
    def o_beta(self) -> int:
        return len(self.theta)

    @property
    def o_phi(self) -> int:
        return len(self.theta) + len(self.names)

    @property
    def o_z(self) -> int:
        return self.o_phi + (1 if self.use_floor else 0)

    @property
    def size(self) -> int:
        return self.o_z + self.n_images

    def body_of(self, x_theta) -> dict:
        return {**self.params, **dict(zip(self.theta, (float(v) for v in x_theta)))}

    def log_lengths(self, p: dict) -> np.ndarray:
        """The log lengths of :data:`SEGMENTS` of the body p."""
        key = (round(p["height_m"], 12), round(p["build"], 12), round(p["muscle"], 12), round(p["sex"], 12))
        if key not in self.memo:
            L = segment_lengths(self.rest_joints(p["height_m"], p["build"], p["muscle"], p["sex"]))
            self.memo[key] = np.log(np.array([L[n] for n in SEGMENTS]))
        return self.memo[key]

    @staticmethod
    def kinds(ll: np.ndarray) -> np.ndarray:
        return np.array([ll[_KIND_IDX[k]].mean() for k in KINDS])

    def residuals(self, x, sig_obs, sig_floor, keep, flat_stature=False):
        """The whitened residuals: the observations kept, the floor's depths (with the floor), the stature's prior
        (unless ``flat_stature``), the floor's error, the proportions' and phenotypes' priors, the detector's errors."""
        T, o_beta, o_phi, o_z = len(self.theta), self.o_beta, self.o_phi, self.o_z
        seg, img, fimg, fz = self.seg, self.img, self.fimg, self.fz
        p = self.body_of(x[:T])
        ll = self.log_lengths(p)
        beta, lz = x[o_beta:o_phi], x[o_z:]
        depth = np.maximum(np.exp(lz)[img] + self.off, 0.05)
        r = [((np.log(self.unit * depth) - self.ln_c[seg] - ll[self.obs_idx][seg] - beta[seg]) / sig_obs)[keep]]
        if self.use_floor:
            r.append((lz[fimg] - np.log(fz[fimg]) - x[o_phi]) / sig_floor)
            if not flat_stature:
                r.append(np.array([(np.log(p["height_m"]) - self.ln_H0) / self.sd_lnH]))
            r.append(np.array([x[o_phi] / self.sd_phi]))
        if self.pheno:
            # the template's proportions at this stature
            ref = self.log_lengths({**p, **{q: self.params[q] for q in self.pheno}})
            r.append(self.W_prop @ (self.kinds(ll) - self.kinds(ref)))
            r.append(np.array([(p[q] - self.params[q]) / PHENOTYPE_SD for q in self.pheno]))
        r.append(beta / self.sd_beta)
        return np.concatenate(r)

    def sparsity(self, keep, flat=False):
        """Which parameters each residual of :meth:`residuals` depends on (rows in its order)."""
        from scipy.sparse import coo_matrix

        T, S, o_beta, o_phi, o_z, fimg = len(self.theta), len(self.names), self.o_beta, self.o_phi, self.o_z, self.fimg
        rows, cols = [], []

        def add(r, c):
            rows.append(np.asarray(r, dtype=np.int64).ravel())
            cols.append(np.asarray(c, dtype=np.int64).ravel())

        ki = np.flatnonzero(keep)
        m = ki.size
        r_obs = np.arange(m)
        add(np.repeat(r_obs, T), np.tile(np.arange(T), m))  # the body
        add(r_obs, o_beta + self.seg[ki])  # the detector's error on the segment
        add(r_obs, o_z + self.img[ki])  # the image's depth
        rr = m
        if self.use_floor:
            r_f = rr + np.arange(len(fimg))
            add(r_f, o_z + fimg)
            add(r_f, np.full(len(fimg), o_phi))
            rr += len(fimg)
            if not flat:
                add(np.full(T, rr), np.arange(T))  # the stature's prior
                rr += 1
            add([rr], [o_phi])
            rr += 1
        if self.pheno:
            k = len(KINDS) + len(self.pheno)
            add(np.repeat(rr + np.arange(k), T), np.tile(np.arange(T), k))
            rr += k
        add(rr + np.arange(S), o_beta + np.arange(S))
        rr += S
        return coo_matrix((np.ones(sum(r.size for r in rows), dtype=int), (np.concatenate(rows), np.concatenate(cols))),
                          shape=(rr, self.size)).tocsr()


def _body_fit(seen: SeenSegments, names: list, counts: dict, images: list, params: dict, theta: list, pheno: list,
              fz_all: np.ndarray | None, definitions: dict, spread: DetectorSpread, k_span: float, rest_joints,
              stature_sd_m: float, proportion_cov: np.ndarray) -> _BodyFit:
    """The observations of the seen segments ``names`` in ``images`` and the fit's layout and bounds
    (:class:`_BodyFit`); the detector's spread scaled by ``k_span`` (:func:`span_factor`)."""
    col = {f: i for i, f in enumerate(images)}
    N, S, T = len(images), len(names), len(theta)
    use_floor = fz_all is not None
    fz = fz_all[images] if use_floor else np.full(N, np.nan)
    P = T + S + (1 if use_floor else 0) + N
    lo = np.full(P, -np.inf)
    hi = np.full(P, np.inf)
    for j, q in enumerate(theta):
        lo[j], hi[j] = STATURE_RANGE_M if q == "height_m" else (-1.0, 1.0)
    lo[P - N:] = np.log(0.1)
    return _BodyFit(
        params=params, theta=theta, pheno=pheno, names=names, rest_joints=rest_joints, n_images=N, use_floor=use_floor,
        seg=np.concatenate([np.full(counts[n], k) for k, n in enumerate(names)]),
        img=np.concatenate([[col[f] for f in seen.image[n]] for n in names]).astype(np.int64),
        unit=np.concatenate([seen.unit[n] for n in names]),
        off=np.concatenate([seen.offset[n] for n in names]),
        g=image_noise(np.concatenate([seen.pixels[n] for n in names]),
                      np.concatenate([seen.across[n] for n in names])),
        ln_c=np.log([definitions.get(n, 1.0) for n in names]),
        sd_beta=np.array([spread.of(n) for n in names]) * k_span, sd_phi=spread.floor * k_span,
        fz=fz, fimg=np.flatnonzero(np.isfinite(fz) & (fz > 0)),
        obs_idx=np.array([list(SEGMENTS).index(n) for n in names]),
        W_prop=np.linalg.cholesky(np.linalg.inv(np.asarray(proportion_cov, dtype=np.float64))).T,
        sd_lnH=stature_sd_m / params["height_m"], ln_H0=np.log(params["height_m"]), lo=lo, hi=hi)


def _start(fit: _BodyFit) -> tuple[np.ndarray, np.ndarray]:
    """The fit's start, the template at the seen depths (with the floor: at the stature the floor implies, the
    template seen at the floor's depths), within the bounds; (x, the template's log lengths of :data:`SEGMENTS`)."""
    T, N, o_z, fz, fimg, params = len(fit.theta), fit.n_images, fit.o_z, fit.fz, fit.fimg, fit.params
    ll0 = fit.log_lengths(params)
    z0 = np.full(N, np.nan)
    per = np.exp(fit.ln_c + ll0[fit.obs_idx])[fit.seg] / fit.unit - fit.off
    for i in range(N):
        z0[i] = np.median(per[fit.img == i])
    z0 = np.maximum(z0, 0.1)
    x = np.zeros(fit.size)
    x[:T] = [params[q] for q in fit.theta]
    x[o_z:] = np.log(z0)
    if fit.use_floor:
        k = float(np.exp(np.median(np.log(fz[fimg]) - np.log(z0[fimg]))))
        x[0] = float(np.clip(params["height_m"] * k, *STATURE_RANGE_M))
        x[o_z:] += np.log(k)
    return np.clip(x, fit.lo + 1e-9, fit.hi - 1e-9), ll0


def _start_spread(fit: _BodyFit, x: np.ndarray) -> tuple[float, float]:
    """The images' spread at the start x, both in logs: (the observations' per unit of ``fit.g``, the floor's; 1
    without the floor)."""
    T, o_z, seg, fimg = len(fit.theta), fit.o_z, fit.seg, fit.fimg
    r0 = (np.log(fit.unit * np.maximum(np.exp(x[o_z:])[fit.img] + fit.off, 0.05)) - fit.ln_c[seg]
          - fit.log_lengths(fit.body_of(x[:T]))[fit.obs_idx][seg])
    sigma = max(_robust_sd(r0 / fit.g), 0.05)
    sig_f = max(_robust_sd(x[o_z:][fimg] - np.log(fit.fz[fimg])), 0.005) if fit.use_floor else 1.0
    return sigma, sig_f


def _solve(fit: _BodyFit, x, keep, sig_obs, sig_floor, loss, flat=False):
    """The fit from x (scipy's least_squares, sparse trust region): the observations ``keep`` with the noise
    ``sig_obs``, the floor's with ``sig_floor``; ``flat``: without the stature's prior."""
    from scipy.optimize import least_squares

    return least_squares(fit.residuals, x, args=(sig_obs, sig_floor, keep, flat), bounds=(fit.lo, fit.hi), loss=loss,
                         f_scale=2.5, jac_sparsity=fit.sparsity(keep, flat), method="trf", x_scale="jac",
                         max_nfev=200)


def _seen_spread(fit: _BodyFit, x: np.ndarray) -> tuple[dict, float, np.ndarray, float]:
    """The observations' spread around the robust fit x: (its body, sigma per unit of ``fit.g``, which observations
    are kept (within :data:`OUTLIER_SIGMAS`), the kept residuals' lag-1 correlation ρ in [0, 0.9])."""
    T, o_z, seg, img, g = len(fit.theta), fit.o_z, fit.seg, fit.img, fit.g
    p = fit.body_of(x[:T])
    lz = x[o_z:]
    res = (np.log(fit.unit * np.maximum(np.exp(lz)[img] + fit.off, 0.05)) - fit.ln_c[seg]
           - fit.log_lengths(p)[fit.obs_idx][seg] - x[fit.o_beta:fit.o_phi][seg])
    sigma = max(_robust_sd(res / g), 0.05)
    keep = np.abs(res) <= OUTLIER_SIGMAS * sigma * g
    rho = float(np.clip(_lag1(res[keep] / g[keep], seg[keep], img[keep]), 0.0, 0.9))
    return p, sigma, keep, rho


def _floor_spread(fit: _BodyFit, x: np.ndarray, p: dict, keep: np.ndarray, sigma: float) -> tuple[float, float, float]:
    """The floor's noise per image around the robust fit x (body p): its depth against the depth the image's
    segments alone give the body (the fit's own depths follow the floor, so its residuals would understate it); the
    segments' own noise in that depth counts too, which keeps it on the safe side. A foot off the floor (a jump, a
    kick) puts the floor's point behind it: the floor then says too far, never too near. So the floor's spread is
    read below its middle (median - 16th percentile: one SD of a normal) and images more than
    :data:`OFF_FLOOR_SIGMAS` of it beyond are taken to be off the floor: ``fit.fimg`` is narrowed to the others.
    (the spread, the lag-1 correlation ρ of the images kept, the spread inflated by it)."""
    seg, img, N, fimg = fit.seg, fit.img, fit.n_images, fit.fimg
    seg_z = np.log(np.maximum(np.exp(fit.ln_c + fit.log_lengths(p)[fit.obs_idx] + x[fit.o_beta:fit.o_phi])[seg]
                              / fit.unit - fit.off, 0.05))
    w_z = keep / (sigma * fit.g) ** 2
    w_sum = np.bincount(img, weights=w_z, minlength=N)
    lz_seg = np.where(w_sum > 0, np.bincount(img, weights=w_z * seg_z, minlength=N) / np.maximum(w_sum, 1e-12),
                      np.nan)
    d = np.log(fit.fz[fimg]) + x[fit.o_phi] - lz_seg[fimg]
    ok = np.isfinite(d)
    m = float(np.median(d[ok]))
    sig_f = max(float(m - np.percentile(d[ok], 16)), 0.005)
    fkeep = ok & (d <= m + OFF_FLOOR_SIGMAS * sig_f) & (d >= m - OUTLIER_SIGMAS * sig_f)
    dd = np.where(ok, d - m, 0.0)
    rho_f = float(np.clip(_lag1(dd[fkeep], np.zeros(int(fkeep.sum()), int), fimg[fkeep]), 0.0, 0.9))
    fit.fimg = fimg[fkeep]
    return sig_f, rho_f, sig_f * float(np.sqrt((1.0 + rho_f) / (1.0 - rho_f)))


def _covariance(sol, o_z: int) -> np.ndarray:
    """The posterior covariance of the parameters before ``o_z`` (the body, the detector's and the floor's errors)
    from the fit's Jacobian, the images' depths marginalised (a Schur complement)."""
    J = sol.jac.tocsc() if hasattr(sol.jac, "tocsc") else np.asarray(sol.jac)
    Jg = J[:, :o_z].toarray() if hasattr(J, "toarray") else J[:, :o_z]
    Jz = J[:, o_z:]
    A = Jg.T @ Jg
    Bm = np.asarray((Jz.T @ Jg)).T if hasattr(Jz, "toarray") else Jg.T @ Jz  # (Pg, N)
    D = np.asarray(Jz.multiply(Jz).sum(axis=0)).ravel() if hasattr(Jz, "multiply") else (Jz ** 2).sum(axis=0)
    Schur = A - (Bm / np.maximum(D, 1e-12)) @ Bm.T
    return np.linalg.pinv(Schur)


def _grad_log_lengths(fit: _BodyFit, p: dict, unc: tuple) -> np.ndarray:
    """The gradient of each segment's log length at the body p with respect to the parameters ``unc`` (central
    differences, within their ranges)."""
    G = np.zeros((len(SEGMENTS), len(unc)))
    for j, q in enumerate(unc):
        h = 1e-4 if q == "height_m" else 1e-3
        lo_q, hi_q = STATURE_RANGE_M if q == "height_m" else (-1.0, 1.0)
        up = {**p, q: min(p[q] + h, hi_q)}
        dn = {**p, q: max(p[q] - h, lo_q)}
        G[:, j] = (fit.log_lengths(up) - fit.log_lengths(dn)) / (up[q] - dn[q])
    return G


def _segment_updates(fit: _BodyFit, x: np.ndarray, p: dict, ll0: np.ndarray, cov: np.ndarray, unc: tuple,
                     keep: np.ndarray, sig_obs: np.ndarray, rho: float, spread: DetectorSpread,
                     k_span: float) -> tuple[dict, dict]:
    """Per segment, what moved and on what evidence, at the fit x (body p) with the posterior covariance ``cov`` of
    ``unc`` (lengths and SDs by the delta method): (segment -> its seen length, m; segment -> :class:`Moved`)."""
    ll = fit.log_lengths(p)
    G = _grad_log_lengths(fit, p, unc)
    G0 = _grad_log_lengths(fit, fit.params, unc)
    seg, lz = fit.seg, x[fit.o_z:]
    res = (np.log(fit.unit * np.maximum(np.exp(lz)[fit.img] + fit.off, 0.05)) - fit.ln_c[seg])  # the seen log lengths
    measured, segments = {}, {}
    kind_pos = {k: i for i, k in enumerate(KINDS)}
    var_lnH_prior = fit.sd_lnH ** 2 if "height_m" in unc else 0.0
    for j, n in enumerate(SEGMENTS):
        gH = G0[j, unc.index("height_m")] * fit.params["height_m"] if "height_m" in unc else 0.0  # d ln L / d ln H
        prior_sd = float(np.exp(ll0[j]) * np.sqrt(PROPORTION_COV[kind_pos[KIND_OF[n]], kind_pos[KIND_OF[n]]]
                                                   * (1.0 if fit.pheno else 0.0) + gH ** 2 * var_lnH_prior))
        post_sd = float(np.exp(ll[j]) * np.sqrt(max(G[j] @ cov @ G[j], 0.0)))
        moved = dict(template=float(np.exp(ll0[j])), prior_sd=prior_sd, posterior=float(np.exp(ll[j])),
                     posterior_sd=post_sd)
        if n in fit.names:
            k = fit.names.index(n)
            m = (seg == k) & keep
            v = res[m]
            w = 1.0 / (sig_obs[m] ** 2)
            mean = float((w * v).sum() / w.sum())
            n_eff = float(m.sum()) * (1.0 - rho) / (1.0 + rho)
            se = float(np.sqrt(1.0 / w.sum() + (spread.of(n) * k_span) ** 2))
            measured[n] = float(np.exp(mean))
            moved.update(seen=float(np.exp(mean)), seen_se=float(np.exp(mean) * se), images=int(m.sum()),
                         effective=n_eff)
        segments[n] = Moved(**moved)
    return measured, segments


def _stature_update(fit: _BodyFit, x: np.ndarray, Sg: np.ndarray, keep: np.ndarray, sig_obs: np.ndarray,
                    sig_f_eff: float, rho_f: float, stature_sd_m: float) -> Moved:
    """The stature's update from the floor at the fit x (posterior covariance ``Sg``); what the floor alone says is
    the same fit without the stature's prior."""
    floor_images = int(len(fit.fimg))
    alone = _solve(fit, x, keep, sig_obs, sig_f_eff, "linear", flat=True)
    Sa = _covariance(alone, fit.o_z)
    H_alone = float(alone.x[0])
    return Moved(template=fit.params["height_m"], prior_sd=stature_sd_m, posterior=float(x[0]),
                 posterior_sd=float(np.sqrt(max(Sg[0, 0], 0.0))), seen=H_alone,
                 seen_se=float(np.sqrt(max(Sa[0, 0], 0.0))), images=floor_images,
                 effective=floor_images * (1.0 - rho_f) / (1.0 + rho_f))


def fit_body(seen: SeenSegments, start: dict, free: tuple, floor_z: np.ndarray | None = None,
             definitions: dict | None = None, spread: DetectorSpread | None = None, rest_joints=None,
             camera_height_m: float | None = None, stature_sd_m: float = STATURE_SD_M,
             proportion_cov: np.ndarray = PROPORTION_COV, t_us: np.ndarray | None = None) -> BodyEstimate:
    """The body's posterior given the seen segments (module doc).

    start: the template's height_m, build, muscle, sex (the prior's centre; kept where not free); free: which of
    "height_m", "sex", "muscle" to update (height_m only with ``floor_z``, the pelvis depth per image from the
    floor, NaN where unknown, and ``camera_height_m``, the camera's height over the floor: below
    :data:`MIN_FLOOR_ELEVATION` times the person's distance the stature is not estimated and ``scale_from`` says
    why); definitions: segment -> the detector's seen/true length share (1 where absent); spread: what the
    detector's errors share within a capture (default :data:`UNKNOWN_SPREAD`); ``rest_joints(height_m, build,
    muscle, sex)`` gives a body's rest joints (default: :func:`eventcap.body.anny.anny_rest_joints`); the prior:
    ``stature_sd_m`` and ``proportion_cov`` (:data:`KINDS`' log lengths at a given stature); ``t_us`` the images'
    times (the span they cover scales the detector's spread, :func:`span_factor`; None: 1 s).

    The steps: a robust fit from the template at the seen depths (:func:`_start`, :func:`_solve`); the images'
    spread around it, the outliers left out, the correlation in time (:func:`_seen_spread`, and the floor's,
    :func:`_floor_spread`); the final fit, its covariance (:func:`_covariance`) and per quantity what moved
    (:func:`_segment_updates`, :func:`_stature_update`)."""
    if rest_joints is None:
        from eventcap.body.anny import anny_rest_joints as rest_joints
    definitions = definitions or {}
    spread = spread or UNKNOWN_SPREAD
    params = {k: float(v) for k, v in start.items()}
    counts = {n: int(len(seen.image.get(n, ()))) for n in SEGMENTS}
    names = [n for n in SEGMENTS if counts[n] >= MIN_IMAGES]
    pheno = [p for p in FITTED_PHENOTYPES if p in free]
    images = sorted(set(np.concatenate([seen.image[n] for n in names]).tolist())) if names else []
    fz_all, scale_from = _floor_for_stature(free, floor_z, camera_height_m, images)
    use_floor = fz_all is not None
    theta = (["height_m"] if use_floor else []) + pheno
    unc, cov0 = prior_cov(params, tuple(free), rest_joints, stature_sd_m, proportion_cov)
    if not names or not theta:
        return BodyEstimate(**params, estimated=(), scale_from=scale_from, images=len(images), seen=counts,
                            measured_m={}, cov=cov0, uncertain=unc,
                            why="too few segments seen across the line of sight (each needs "
                                f"{MIN_IMAGES} images): " + ", ".join(f"{n} {k}" for n, k in counts.items()))
    span_s = _images_span_s(t_us, images)
    if span_s < MIN_SPAN_S:
        return BodyEstimate(**params, estimated=(), scale_from=scale_from, images=len(images), seen=counts,
                            measured_m={}, cov=cov0, uncertain=unc,
                            why=f"the images with segments span {span_s:.2f} s: too few poses to tell "
                                f"the body from its detector's errors (it moves on >= {MIN_SPAN_S} s)",
                            noise={"span_s": span_s})
    k_span = span_factor(span_s)
    fit = _body_fit(seen, names, counts, images, params, theta, pheno, fz_all, definitions, spread, k_span,
                    rest_joints, stature_sd_m, proportion_cov)
    x, ll0 = _start(fit)
    keep = np.ones(fit.seg.size, bool)
    sigma, sig_f = _start_spread(fit, x)
    x = _solve(fit, x, keep, sigma * fit.g, sig_f, "soft_l1").x
    p, sigma, keep, rho = _seen_spread(fit, x)
    fimg_all = fit.fimg
    if use_floor:
        sig_f, rho_f, sig_f_eff = _floor_spread(fit, x, p, keep, sigma)
    else:
        rho_f, sig_f_eff = 0.0, 1.0
    sig_obs = sigma * fit.g * float(np.sqrt((1.0 + rho) / (1.0 - rho)))
    sol = _solve(fit, x, keep, sig_obs, sig_f_eff, "linear")
    x = sol.x
    Sg = _covariance(sol, fit.o_z)
    # the covariance of every parameter not stated: the posterior's where estimated, the prior's where not (an
    # unstated stature the floor cannot tell keeps its prior's spread); height_m in m
    cov = cov0.copy()
    it = [unc.index(q) for q in theta]
    cov[np.ix_(it, it)] = Sg[:len(theta), :len(theta)]
    p = fit.body_of(x[:len(theta)])
    measured, segments = _segment_updates(fit, x, p, ll0, cov, unc, keep, sig_obs, rho, spread, k_span)
    stature = None
    floor_images = 0
    if use_floor:
        stature = _stature_update(fit, x, Sg, keep, sig_obs, sig_f_eff, rho_f, stature_sd_m)
        floor_images = stature.images
        scale_from = "floor"
    noise = {"span_s": span_s, "span_factor": k_span, "sigma": sigma, "rho": rho, "outliers": int((~keep).sum()),
             "observations": int(fit.seg.size),
             "sigma_floor": sig_f if use_floor else None, "rho_floor": rho_f if use_floor else None,
             "off_floor": int(len(fimg_all) - len(fit.fimg)) if use_floor else 0}
    params.update(p)
    return BodyEstimate(**{k: float(v) for k, v in params.items()}, estimated=tuple(theta), scale_from=scale_from,
                        images=fit.n_images, seen=counts, measured_m=measured, floor_images=floor_images, cov=cov,
                        uncertain=unc, segments=segments, stature=stature, noise=noise)


def rest_spread(est: BodyEstimate, rest_joints) -> np.ndarray:
    """(K, 24, 3) m: K independent one-sigma deviations of the body's rest joints (the covariance of the parameters
    not stated, ``est.uncertain``: the posterior's, or the prior's where nothing was estimated, carried through
    ``rest_joints(height_m, build, muscle, sex)`` by central differences): the rest joints lie at rest + Σ_k ε_k
    D_k, ε_k ~ N(0, 1). K = 0 when everything is stated."""
    if est.cov is None or not est.uncertain:
        return np.zeros((0, 24, 3))
    p = est.params()
    Jac = np.zeros((24 * 3, len(est.uncertain)))
    for j, q in enumerate(est.uncertain):
        h = 1e-4 if q == "height_m" else 1e-3
        up, dn = dict(p), dict(p)
        if q == "height_m":
            up[q], dn[q] = p[q] + h, p[q] - h
        else:
            up[q], dn[q] = min(p[q] + h, 1.0), max(p[q] - h, -1.0)
        Jac[:, j] = (np.asarray(rest_joints(**up)) - np.asarray(rest_joints(**dn))).ravel() / (up[q] - dn[q])
    w, V = np.linalg.eigh(0.5 * (est.cov + est.cov.T))
    L = V * np.sqrt(np.clip(w, 0.0, None))  # columns: independent one-sigma directions of the parameters
    return (Jac @ L).T.reshape(-1, 24, 3)
