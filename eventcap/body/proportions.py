"""The person's proportions from what one camera saw: limb lengths and girdle widths, and a body fitted to them.

Not in the paper (it scanned each actor). A user can give a height at most; the segments the detections show
over a capture tell the rest:

- **the measured segments** (:data:`SEGMENTS`): upper arms, forearms, thighs and shins (each side) and the shoulder
  and hip widths, between landmarks that sit on joints (BODY_25 points on SMPL joints);
- **a seen length per image** (:func:`seen_segments`): the segment along the direction the 3D detection gives it,
  its ends on the two 2D points' rays (:func:`eventcap.camera.seen_length`, perspective included), its middle at the
  depth of the person's pelvis plus the 3D detection's depth offset of that middle. Only images where the segment
  lies mostly across the line of sight count (its share across >= :data:`MIN_ACROSS`): along the line of sight the
  2D points say little about the length;
- **the depth of the pelvis** per image: from the floor when the camera's height above it is known (a world from
  the camera's extrinsics: the floor is y = 0): the sole point of the supporting foot (the lower one in the 3D
  detection) lies on the floor, so its ray meets the floor at its depth (:func:`floor_depths`). Otherwise it is
  unknown, and the fit solves it per image, which leaves the overall scale to what was stated (the template's
  height);
- **a detector's own definitions** (:data:`DETECTOR_DEFINITIONS`): a detector puts some points elsewhere than the
  template's joints (BlazePose: hips and shoulders nearer together); its seen lengths are divided by the share
  found on the tuning captures before they are compared with a body's;
- **the fit** (:func:`fit_body`): ANNY's phenotypes (the stature, ``sex`` and ``muscle``; ``build`` moves no joint
  by more than 2 mm and is left as it is) that best explain the seen lengths, robustly (soft-L1 on the relative
  length error), with weak priors towards ANNY's mean body, within ANNY's ranges. What the user stated is not fitted.

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
#: A segment counts in an image where this share of its 3D direction lies across the line of sight.
MIN_ACROSS = 0.7
#: A segment with fewer images than this is not measured.
MIN_IMAGES = 3
#: Where a detector puts its points against the template's joints: seen length / true length per segment, on the
#: open benchmark's tuning captures (seeds 0-19; docs/results/body.md). A detector
#: not listed is taken to put them on the joints (the simulated detector does).
DETECTOR_DEFINITIONS: dict[str, dict[str, float]] = {
    # BlazePose GHUM (full): the medians over the 10 whole-body tuning captures with frames, left and right averaged
    # (per capture they spread by about +-8 %)
    "blazepose": {"l_upper_arm": 0.944, "r_upper_arm": 0.944, "l_forearm": 0.989, "r_forearm": 0.989,
                  "l_thigh": 0.936, "r_thigh": 0.936, "l_shin": 0.938, "r_shin": 0.938, "shoulders": 0.876,
                  "hips": 0.870},
}
#: The floor tells the person's depth only when the camera looks down on it steeply enough: the camera's height
#: over the person's distance at least this (a ray's depth error per pixel grows as distance / height; chosen on the
#: tuning captures: docs/results/implementation.md).
MIN_FLOOR_ELEVATION = 0.3
#: The sole points of each foot (heels and big toes), BODY_25 landmarks.
_SOLES = {"l": ("l_heel", "l_big_toe"), "r": ("r_heel", "r_big_toe")}


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


@dataclass(frozen=True)
class SeenSegments:
    """Per segment, the images where it was seen across the line of sight: ``image`` (K,) indices into the
    detections' images; ``unit`` (K,) its seen length (m) were its middle 1 m away; ``offset`` (K,) the depth of its
    middle minus the pelvis's (m, from the 3D detection). Its seen length at pelvis depth z: unit * (z + offset)."""

    image: dict = field(default_factory=dict)  #: name -> (K,) int
    unit: dict = field(default_factory=dict)  #: name -> (K,) seen length (m) of the segment at 1 m depth
    offset: dict = field(default_factory=dict)  #: name -> (K,) depth of its middle relative to the pelvis (m)

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
            out.image[name], out.unit[name], out.offset[name] = (np.zeros(0, int), np.zeros(0), np.zeros(0))
            continue
        v = J3c[idx, ja] - J3c[idx, jb]
        across = np.linalg.norm(v[:, :2], axis=1) / np.maximum(np.linalg.norm(v, axis=1), 1e-9)
        n = camera.undistort_points(np.asarray(keypoints_2d, dtype=np.float64)[idx][:, [la, lb]])
        unit = seen_length(n[:, 0], n[:, 1], v, np.ones(idx.size))
        use = (across >= MIN_ACROSS) & np.isfinite(unit) & (unit > 0)
        out.image[name] = idx[use]
        out.unit[name] = unit[use]
        out.offset[name] = 0.5 * (J3c[idx, ja, 2] + J3c[idx, jb, 2])[use]
    return out


def floor_depths(camera, keypoints_2d: np.ndarray, confidence_2d: np.ndarray, joints_3d: np.ndarray,
                 confidence_3d: np.ndarray, sole_height_m: float = 0.03) -> np.ndarray:
    """(N,) depth (m, camera axes) of the pelvis per image from the floor y = 0 of a world given by the camera's
    extrinsics: the supporting foot (the lower one in the 3D detection, world y up) has its sole points on the
    floor (at ``sole_height_m``: a heel's or a toe's height above the sole), so their rays meet the floor at their
    depth; the pelvis lies the 3D detection's offset from them. NaN where no sole point of that foot is detected or
    its ray does not meet the floor in front of the camera."""
    J3 = np.asarray(joints_3d, dtype=np.float64)
    N = J3.shape[0]
    out = np.full(N, np.nan)
    R, t = np.asarray(camera.R, dtype=np.float64), np.asarray(camera.t, dtype=np.float64)
    centre = -R.T @ t  # camera centre, world
    kp = np.asarray(keypoints_2d, dtype=np.float64)
    for i in range(N):
        feet = [(s, JOINT_INDEX[f"{s}_ankle"]) for s in ("l", "r")
                if confidence_3d[i, JOINT_INDEX[f"{s}_ankle"]] > 0 and np.isfinite(J3[i, JOINT_INDEX[f"{s}_ankle"]]).all()]
        if not feet:
            continue
        side, ankle = min(feet, key=lambda f: J3[i, f[1], 1])
        soles = [LANDMARK_INDEX[n] for n in _SOLES[side] if confidence_2d[i, LANDMARK_INDEX[n]] > 0]
        if not soles:
            continue
        n = camera.undistort_points(kp[i, soles])  # (k, 2) normalised
        rays = np.concatenate([n, np.ones((len(soles), 1))], axis=1) @ R  # world directions (R^T d)
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = (sole_height_m - centre[1]) / rays[:, 1]  # camera depth of the floor point (ray scaled by z = 1)
        lam = lam[np.isfinite(lam) & (lam > 0)]
        if lam.size == 0:
            continue
        z_sole = float(np.mean(lam))
        # the pelvis: the 3D detection's offset from the ankle, in camera axes (the ankle is ~ the soles' depth)
        out[i] = z_sole + float(((J3[i, 0] - J3[i, ankle]) @ R.T)[2])
    return out


#: The phenotypes a fit may estimate (ANNY's; ``build`` moves no joint by more than 2 mm: never fitted).
FITTED_PHENOTYPES = ("sex", "muscle")
#: The statures a fit may reach (m): adults, within ANNY's range.
STATURE_RANGE_M = (1.40, 2.10)
#: Robust loss scale of the relative length residuals (soft-L1): a seen length this far off counts less.
RESIDUAL_SCALE = 0.08


@dataclass(frozen=True)
class BodyEstimate:
    """What the fit found: the body's parameters, what was estimated from what, and the seen lengths behind it."""

    height_m: float
    build: float
    muscle: float
    sex: float
    estimated: tuple  #: the parameters estimated (the others as the template states or defaults them)
    scale_from: str  #: where the stature comes from: "stated", "floor" (with the images used), "template default"
    images: int  #: images with at least one seen segment
    seen: dict  #: segment -> images it was seen in across the line of sight
    measured_m: dict  #: segment -> median seen length at the fitted depths, definitions removed (m)
    floor_images: int = 0  #: images whose pelvis depth the floor gave (scale_from "floor")

    def params(self) -> dict:
        return {"height_m": self.height_m, "build": self.build, "muscle": self.muscle, "sex": self.sex}


def fit_body(seen: SeenSegments, start: dict, free: tuple, floor_z: np.ndarray | None = None,
             definitions: dict | None = None, prior_sigma: float = 0.1, iterations: int = 3,
             rest_joints=None, camera_height_m: float | None = None) -> BodyEstimate:
    """ANNY's parameters that explain the seen segments (module doc).

    start: the template's height_m, build, muscle, sex (kept where not free); free: which of "height_m",
    "sex", "muscle" to estimate (height_m only with ``floor_z``, the pelvis depth per image from the floor; NaN
    where unknown); definitions: segment -> the detector's seen/true length share (1 where absent);
    prior_sigma: the phenotypes' prior spread around ANNY's mean (0). ``rest_joints(height_m, build, muscle,
    sex)`` gives a body's rest joints (default: :func:`eventcap.body.anny.anny_rest_joints`);
    ``camera_height_m`` the camera's height over the floor (with ``floor_z``): below :data:`MIN_FLOOR_ELEVATION`
    times the person's distance the stature is not estimated (``scale_from`` says why)."""
    from scipy.optimize import least_squares

    if rest_joints is None:
        from eventcap.body.anny import anny_rest_joints as rest_joints
    definitions = definitions or {}
    names = [n for n in SEGMENTS if len(seen.image.get(n, ())) >= MIN_IMAGES]
    params = dict(start)
    pheno = [p for p in FITTED_PHENOTYPES if p in free]
    scale_from = "stated" if "height_m" not in free else "template default"
    if "height_m" in free and floor_z is not None and camera_height_m is not None:
        fz = np.asarray(floor_z, dtype=np.float64)
        dist = float(np.nanmedian(fz)) if np.isfinite(fz).any() else float("nan")
        if not np.isfinite(dist):
            scale_from = "template default (no sole of a supporting foot seen on the floor)"
            floor_z = None
        elif camera_height_m < MIN_FLOOR_ELEVATION * dist:
            scale_from = (f"template default (the camera {camera_height_m:.2f} m high, the person ~{dist:.1f} m away: "
                          f"too low for the floor to tell the depth, below {MIN_FLOOR_ELEVATION} x the distance)")
            floor_z = None
    images = sorted(set(np.concatenate([seen.image[n] for n in names]).tolist())) if names else []
    counts = {n: int(len(seen.image.get(n, ()))) for n in SEGMENTS}
    if not names:
        return BodyEstimate(**params, estimated=(), scale_from=scale_from, images=0, seen=counts, measured_m={})
    col = {f: i for i, f in enumerate(images)}
    idx = {n: np.array([col[f] for f in seen.image[n]]) for n in names}
    c = np.array([definitions.get(n, 1.0) for n in names])
    n_img = len(images)

    def lengths(p: dict) -> np.ndarray:
        L = segment_lengths(rest_joints(p["height_m"], p["build"], p["muscle"], p["sex"]))
        return np.array([L[n] for n in names]) * c

    def residuals(x: np.ndarray, height: float) -> np.ndarray:
        p = {**params, "height_m": height, **dict(zip(pheno, x[:len(pheno)]))}
        z = x[len(pheno):]
        B = lengths(p)
        r = np.concatenate([(seen.unit[n] * (z[idx[n]] + seen.offset[n]) - B[k]) / B[k] for k, n in enumerate(names)])
        # soft-L1 on the lengths (a residual whose square is the robust cost), a Gaussian prior on the phenotypes in
        # the same units (RESIDUAL_SCALE per prior_sigma)
        robust = np.sign(r) * np.sqrt(2.0 * RESIDUAL_SCALE ** 2 * (np.sqrt(1.0 + (r / RESIDUAL_SCALE) ** 2) - 1.0))
        return np.concatenate([robust, np.asarray(x[:len(pheno)]) / prior_sigma * RESIDUAL_SCALE])

    # the depths a start body would be seen at: each image's median over its segments
    B0 = lengths(params)
    per = [[] for _ in range(n_img)]
    for k, n in enumerate(names):
        for i, u, o in zip(idx[n], seen.unit[n], seen.offset[n]):
            per[i].append(B0[k] / u - o)
    z0 = np.array([np.median(v) for v in per])
    x = np.concatenate([[params[p] for p in pheno], z0])
    lo = np.concatenate([[-1.0] * len(pheno), np.full(n_img, 0.05)])
    hi = np.concatenate([[1.0] * len(pheno), np.full(n_img, np.inf)])
    x = np.clip(x, lo + 1e-9, hi)
    height = float(params["height_m"])
    floor_images = 0
    estimated = list(pheno)
    for _ in range(iterations if "height_m" in free and floor_z is not None else 1):
        sol = least_squares(residuals, x, args=(height,), bounds=(lo, hi),
                            x_scale=np.concatenate([[0.5] * len(pheno), np.maximum(z0, 0.1) * 0.1]))
        x = sol.x
        if "height_m" not in free or floor_z is None:
            break
        fz = np.asarray(floor_z, dtype=np.float64)[images]
        ok = np.isfinite(fz) & (fz > 0)
        if ok.sum() < MIN_IMAGES:
            scale_from = f"template default (the supporting foot's sole seen on the floor in {int(ok.sum())} images)"
            break
        # the model at `height` is seen at depth z; the person at the floor's depth is k times as tall
        k = float(np.median(fz[ok] / x[len(pheno):][ok]))
        height = float(np.clip(height * k, *STATURE_RANGE_M))
        floor_images = int(ok.sum())
        scale_from = "floor"
        x = np.concatenate([x[:len(pheno)], x[len(pheno):] * k])
        if "height_m" not in estimated:
            estimated.insert(0, "height_m")
    if scale_from == "floor":  # the last stature's proportions
        sol = least_squares(residuals, x, args=(height,), bounds=(lo, hi),
                            x_scale=np.concatenate([[0.5] * len(pheno), np.maximum(x[len(pheno):], 0.1) * 0.1]))
        x = sol.x
    params.update({"height_m": height, **{p: float(v) for p, v in zip(pheno, x[:len(pheno)])}})
    z = x[len(pheno):]
    measured = {n: float(np.median(seen.unit[n] * (z[idx[n]] + seen.offset[n]))) / definitions.get(n, 1.0)
                for n in names}
    return BodyEstimate(**{k: float(v) for k, v in params.items()}, estimated=tuple(estimated),
                        scale_from=scale_from, images=n_img, seen=counts, measured_m=measured,
                        floor_images=floor_images)
