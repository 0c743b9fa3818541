"""BlazePose GHUM 3D (MediaPipe Pose) on the CPU, offline: a person detector, then a landmark model on a crop.

The two networks are Google's, shipped as TensorFlow Lite files in ``models/`` (Apache-2.0, from the npm package
``@mediapipe/pose``; see ``models/README.md``) and run with ``ai-edge-litert``'s interpreter. What is ours is the
glue around them, written from the published model cards and the structure of the models' tensors:

- **person detector** (``pose_detection.tflite``, 224x224 RGB in [-1, 1], letterboxed): an SSD with 2254 anchors,
  each giving a score and a box plus four key points; the first two key points are the hip centre and a point on
  the circle that holds the whole body. The region of interest (ROI) is a square of side 2.5 x their distance,
  centred at the hips and rotated so that the body stands upright in the crop.
- **landmark model** (``pose_landmark_{lite,full}.tflite``, 256x256 RGB in [0, 1]): 39 points x (x, y, z,
  visibility, presence) in crop pixels, a pose-presence flag, and 39 "world" points in metres centred between the
  hips, in the crop's axes. Points 0-32 are the body landmarks; 33 and 34 are auxiliary points (hip centre and
  body-circle point, like the detector's) from which the next frame's ROI is taken, so the detector runs only when
  the person is lost.

Everything is deterministic: one interpreter thread, no randomness, no state besides the previous ROI.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

MODELS_DIR = Path(__file__).resolve().parent / "models"
DETECTOR_FILE = "pose_detection.tflite"
LANDMARK_FILES = {"lite": "pose_landmark_lite.tflite", "full": "pose_landmark_full.tflite"}

#: BlazePose's 33 body landmarks, in the model's output order.
BLAZEPOSE_NAMES: tuple[str, ...] = (
    "nose", "left_eye_inner", "left_eye", "left_eye_outer", "right_eye_inner", "right_eye", "right_eye_outer",
    "left_ear", "right_ear", "mouth_left", "mouth_right", "left_shoulder", "right_shoulder", "left_elbow",
    "right_elbow", "left_wrist", "right_wrist", "left_pinky", "right_pinky", "left_index", "right_index",
    "left_thumb", "right_thumb", "left_hip", "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle",
    "left_heel", "right_heel", "left_foot_index", "right_foot_index",
)
NUM_BLAZEPOSE = 33
_DET_SIZE = 224
_LMK_SIZE = 256
_ROI_SCALE = 1.25  # the ROI square is 1.25 x the body circle's diameter


def _sigmoid(x: np.ndarray) -> np.ndarray:
    from scipy.special import expit

    return expit(np.asarray(x, dtype=np.float64))


def ssd_anchors(size: int = _DET_SIZE, strides=(8, 16, 32, 32, 32)) -> np.ndarray:
    """Anchor centres (n, 2) of the person detector, normalised to [0, 1], in the model's output order.

    Each layer puts two anchors on every cell of its grid; consecutive layers of the same stride share one grid
    (so the three stride-32 layers give six anchors per 7x7 cell). The boxes have a fixed unit size.
    """
    centres = []
    i = 0
    while i < len(strides):
        j = i
        while j < len(strides) and strides[j] == strides[i]:
            j += 1
        per_cell = 2 * (j - i)
        n = int(math.ceil(size / strides[i]))
        ys, xs = np.meshgrid((np.arange(n) + 0.5) / n, (np.arange(n) + 0.5) / n, indexing="ij")
        grid = np.stack([xs.ravel(), ys.ravel()], axis=1)
        centres.append(np.repeat(grid, per_cell, axis=0))
        i = j
    return np.concatenate(centres, axis=0)


@dataclass(frozen=True)
class Roi:
    """A rotated square in image pixels: centre, side, rotation (radians, the crop's up is rotated by it)."""

    cx: float
    cy: float
    size: float
    rotation: float

    def crop_matrix(self, out: int) -> np.ndarray:
        """2x3 affine map from crop pixels (0..out) to image pixels."""
        c, s = math.cos(self.rotation), math.sin(self.rotation)
        k = self.size / out
        # image = centre + R @ ((u - out/2) * k, (v - out/2) * k)
        a = np.array([[c * k, -s * k], [s * k, c * k]])
        b = np.array([self.cx, self.cy]) - a @ np.array([out / 2, out / 2])
        return np.hstack([a, b[:, None]])

    def to_image(self, uv: np.ndarray, out: int) -> np.ndarray:
        """Crop pixel coordinates (..., 2) to image pixels."""
        m = self.crop_matrix(out)
        return uv @ m[:, :2].T + m[:, 2]

    def overlaps(self, width: int, height: int) -> bool:
        """Whether the square meets the image (its centre may lie outside: a portrait's hips are below it)."""
        half = self.size / 2
        return (4 < self.size < 8 * max(width, height) and -half < self.cx < width + half
                and -half < self.cy < height + half)


def roi_from_points(centre: np.ndarray, circle: np.ndarray) -> Roi:
    """The ROI of a body from its hip centre and a point on its enclosing circle (image pixels): a square of side
    1.25 x the circle's diameter, rotated so that centre -> circle point points up in the crop."""
    d = np.asarray(circle, float) - np.asarray(centre, float)
    radius = float(np.hypot(d[0], d[1]))
    # the angle that turns the image so that the vector centre -> circle points straight up (-y)
    rotation = math.atan2(d[1], d[0]) + math.pi / 2
    rotation = (rotation + math.pi) % (2 * math.pi) - math.pi
    return Roi(float(centre[0]), float(centre[1]), 2.0 * radius * _ROI_SCALE, rotation)


@dataclass(frozen=True)
class Pose:
    """One detection in image pixels: 33 landmarks (x, y), their visibility and presence in [0, 1], the pose flag,
    33 world landmarks (metres, hip-centred, camera axes: x right, y down, z away), and the ROI it came from."""

    xy: np.ndarray
    visibility: np.ndarray
    presence: np.ndarray
    flag: float
    world: np.ndarray
    roi: Roi
    aux_xy: np.ndarray  # the two auxiliary points (hip centre, body-circle point) for the next ROI

    def next_roi(self) -> Roi:
        return roi_from_points(self.aux_xy[0], self.aux_xy[1])


def _interpreter(path: Path):
    from ai_edge_litert.interpreter import Interpreter

    if not path.is_file():
        raise FileNotFoundError(f"BlazePose model file {path} is missing (the package should ship it)")
    it = Interpreter(model_path=str(path), num_threads=1)
    it.allocate_tensors()
    return it


def to_rgb8(image: np.ndarray, gamma: float = 1.0) -> np.ndarray:
    """A grey image (linear intensity in [0, 1]) as the 8-bit RGB the networks were trained on.

    ``gamma`` 1 passes the linear intensity (the default: docs/results/settings.md); 2.2 would gamma-encode it
    like a consumer camera."""
    im = np.clip(np.asarray(image, dtype=np.float32), 0.0, 1.0)
    if gamma != 1.0:
        im = im ** (1.0 / gamma)
    g = np.round(im * 255.0).astype(np.uint8)
    return np.repeat(g[..., None], 3, axis=-1)


class BlazePose:
    """The detector + landmark networks, with the previous frame's ROI (tracking mode)."""

    def __init__(self, model: str = "full", detector_threshold: float = 0.5, presence_threshold: float = 0.5):
        if model not in LANDMARK_FILES:
            raise ValueError(f"BlazePose model: expected one of {sorted(LANDMARK_FILES)}, got {model!r}")
        self.model = model
        self.detector_threshold = float(detector_threshold)
        self.presence_threshold = float(presence_threshold)
        self._det = _interpreter(MODELS_DIR / DETECTOR_FILE)
        self._lmk = _interpreter(MODELS_DIR / LANDMARK_FILES[model])
        self._anchors = ssd_anchors()
        self._det_in = self._det.get_input_details()[0]["index"]
        det_out = sorted(self._det.get_output_details(), key=lambda d: int(d["shape"][-1]))
        self._det_scores, self._det_boxes = det_out[0]["index"], det_out[1]["index"]
        self._lmk_in = self._lmk.get_input_details()[0]["index"]
        outs = {int(np.prod(d["shape"][1:])): d["index"] for d in self._lmk.get_output_details()}
        self._lmk_xyz, self._lmk_flag, self._lmk_world = outs[195], outs[1], outs[117]

    # -- the person detector ------------------------------------------------------------------------------------
    def detect_person(self, rgb: np.ndarray) -> tuple[Roi, float] | None:
        """The most confident person in the image as an ROI (and its score), or None."""
        h, w = rgb.shape[:2]
        scale = _DET_SIZE / max(h, w)
        nh, nw = int(round(h * scale)), int(round(w * scale))
        resized = cv2.resize(rgb, (nw, nh), interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR)
        pad_y, pad_x = (_DET_SIZE - nh) // 2, (_DET_SIZE - nw) // 2
        canvas = np.zeros((_DET_SIZE, _DET_SIZE, 3), np.float32)
        canvas[pad_y:pad_y + nh, pad_x:pad_x + nw] = resized.astype(np.float32) / 127.5 - 1.0
        self._det.set_tensor(self._det_in, canvas[None])
        self._det.invoke()
        scores = _sigmoid(self._det.get_tensor(self._det_scores)[0, :, 0])
        best = np.flatnonzero(scores >= self.detector_threshold)
        if best.size == 0:
            return None
        raw = self._det.get_tensor(self._det_boxes)[0]
        # key points 0 (hips) and 1 (body circle) of every candidate, in detector pixels
        kp = raw[:, 4:8].reshape(-1, 2, 2) + (self._anchors * _DET_SIZE)[:, None, :]
        # weighted non-maximum suppression reduced to the one person we want: average the candidates whose boxes
        # overlap the best one, weighted by score (steadier than the single best anchor)
        top = int(best[np.argmax(scores[best])])
        boxes = raw[best, :4].copy()
        boxes[:, :2] += self._anchors[best] * _DET_SIZE
        iou = _iou(boxes, boxes[np.searchsorted(best, top)])
        group = best[iou >= 0.3]
        wts = scores[group][:, None, None]
        pts = (kp[group] * wts).sum(axis=0) / wts.sum()
        pts = (pts - np.array([pad_x, pad_y])) / scale  # back to image pixels
        return roi_from_points(pts[0], pts[1]), float(scores[top])

    # -- the landmark model -------------------------------------------------------------------------------------
    def landmarks(self, rgb: np.ndarray, roi: Roi) -> Pose:
        """Run the landmark model on the ROI's crop of the image."""
        m = roi.crop_matrix(_LMK_SIZE)
        crop = cv2.warpAffine(rgb, m, (_LMK_SIZE, _LMK_SIZE), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                              borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        self._lmk.set_tensor(self._lmk_in, (crop.astype(np.float32) / 255.0)[None])
        self._lmk.invoke()
        raw = self._lmk.get_tensor(self._lmk_xyz)[0].reshape(39, 5)
        flag = float(self._lmk.get_tensor(self._lmk_flag).ravel()[0])
        world = self._lmk.get_tensor(self._lmk_world)[0].reshape(39, 3)[:NUM_BLAZEPOSE].astype(np.float64)
        xy = roi.to_image(raw[:, :2].astype(np.float64), _LMK_SIZE)
        # world points come in the crop's axes: turn them back by the ROI's rotation (about the camera axis)
        c, s = math.cos(roi.rotation), math.sin(roi.rotation)
        world = world.copy()
        world[:, :2] = world[:, :2] @ np.array([[c, s], [-s, c]])
        return Pose(xy=xy[:NUM_BLAZEPOSE], visibility=_sigmoid(raw[:NUM_BLAZEPOSE, 3]),
                    presence=_sigmoid(raw[:NUM_BLAZEPOSE, 4]), flag=flag, world=world, roi=roi,
                    aux_xy=xy[33:35])


def _iou(boxes: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """IoU of centre-size boxes (n, 4) with one box (4,)."""
    lo = np.maximum(boxes[:, :2] - boxes[:, 2:4] / 2, ref[:2] - ref[2:4] / 2)
    hi = np.minimum(boxes[:, :2] + boxes[:, 2:4] / 2, ref[:2] + ref[2:4] / 2)
    inter = np.prod(np.clip(hi - lo, 0, None), axis=1)
    union = np.prod(boxes[:, 2:4], axis=1) + np.prod(ref[2:4]) - inter
    return inter / np.maximum(union, 1e-9)


# -- from BlazePose's 33 landmarks to the skeleton's landmarks and joints ---------------------------------------------
#: Skeleton landmark (BODY_25 order, eventcap.body.skeleton.LANDMARK_NAMES) -> the BlazePose landmarks it is taken
#: from (the mean of two where BODY_25 has a point BlazePose does not: OpenPose's neck and mid-hip are midpoints of
#: the shoulders and hips). The small toes have no counterpart and are left out (confidence 0).
LANDMARK_FROM_BLAZEPOSE: dict[str, tuple[str, ...]] = {
    "nose": ("nose",),
    "neck": ("left_shoulder", "right_shoulder"),
    "r_shoulder": ("right_shoulder",),
    "r_elbow": ("right_elbow",),
    "r_wrist": ("right_wrist",),
    "l_shoulder": ("left_shoulder",),
    "l_elbow": ("left_elbow",),
    "l_wrist": ("left_wrist",),
    "mid_hip": ("left_hip", "right_hip"),
    "r_hip": ("right_hip",),
    "r_knee": ("right_knee",),
    "r_ankle": ("right_ankle",),
    "l_hip": ("left_hip",),
    "l_knee": ("left_knee",),
    "l_ankle": ("left_ankle",),
    "r_eye": ("right_eye",),
    "l_eye": ("left_eye",),
    "r_ear": ("right_ear",),
    "l_ear": ("left_ear",),
    "l_big_toe": ("left_foot_index",),
    "l_heel": ("left_heel",),
    "r_big_toe": ("right_foot_index",),
    "r_heel": ("right_heel",),
}
#: Skeleton joint (SMPL order) -> BlazePose world landmarks. The pelvis is the midpoint of the hips (the world
#: landmarks' own origin), a hand the midpoint of the index and little-finger knuckles, a foot the toe tip
#: ("foot index"). The spine, neck, collars and head have no BlazePose counterpart and are left out.
JOINT_FROM_BLAZEPOSE: dict[str, tuple[str, ...]] = {
    "pelvis": ("left_hip", "right_hip"),
    "l_hip": ("left_hip",),
    "r_hip": ("right_hip",),
    "l_knee": ("left_knee",),
    "r_knee": ("right_knee",),
    "l_ankle": ("left_ankle",),
    "r_ankle": ("right_ankle",),
    "l_foot": ("left_foot_index",),
    "r_foot": ("right_foot_index",),
    "l_shoulder": ("left_shoulder",),
    "r_shoulder": ("right_shoulder",),
    "l_elbow": ("left_elbow",),
    "r_elbow": ("right_elbow",),
    "l_wrist": ("left_wrist",),
    "r_wrist": ("right_wrist",),
    "l_hand": ("left_index", "left_pinky"),
    "r_hand": ("right_index", "right_pinky"),
}


def mapping_matrix(mapping: dict[str, tuple[str, ...]], targets: tuple[str, ...]) -> np.ndarray:
    """(len(targets), 33) averaging weights: row i averages the BlazePose landmarks target i is taken from; rows
    of targets without a counterpart are zero."""
    index = {n: i for i, n in enumerate(BLAZEPOSE_NAMES)}
    w = np.zeros((len(targets), NUM_BLAZEPOSE))
    for name, sources in mapping.items():
        if name not in targets:
            raise KeyError(f"mapping target {name!r} is not one of {targets}")
        for src in sources:
            w[targets.index(name), index[src]] = 1.0 / len(sources)
    return w


def mapped(w: np.ndarray, points: np.ndarray, confidence: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points (33, d) and confidences (33,) mapped by the weights of :func:`mapping_matrix`: positions are the
    weighted means, a confidence is the smallest of its sources' (0 where there is no counterpart)."""
    pos = w @ points
    src = w > 0
    conf = np.where(src, confidence[None, :], np.inf).min(axis=1)
    return pos, np.where(src.any(axis=1), conf, 0.0)


# -- a sequence of images: tracking, losing and re-finding the person -------------------------------------------------
def events_roi(events: np.ndarray, t_us: int, window_us: int, width: int, height: int,
               min_pixels: int = 40) -> Roi | None:
    """An upright ROI around the moving actor, from the events within ``window_us`` around ``t_us``: the box
    holding the 2nd-98th percentiles of the pixels that fired at least twice (isolated noise events do not) or, on a
    sparse sensor where too few did, of the pixels that fired beside two others, grown to the landmark model's
    framing. None when too few pixels fired (nothing moves)."""
    t = events["t"]
    a, b = np.searchsorted(t, [t_us - window_us // 2, t_us + window_us // 2])
    ev = events[a:b]
    if ev.size == 0:
        return None
    counts = np.bincount(ev["y"].astype(np.int64) * width + ev["x"], minlength=width * height)
    active = np.flatnonzero(counts >= 2)
    if active.size < min_pixels:  # a sparse sensor (a DVS128): the pixels that fired next to others that fired
        from scipy import ndimage

        fired = (counts >= 1).reshape(height, width)
        near = ndimage.uniform_filter(fired.astype(np.float32), size=3, mode="constant") * 9.0
        clustered = np.flatnonzero((fired & (near >= 3.0 - 1e-3)).ravel())  # itself and two of its 8 neighbours
        active = clustered if clustered.size >= min_pixels else active
    if active.size < min_pixels:
        return None
    ys, xs = np.divmod(active, width)
    x0, x1 = np.percentile(xs, [2, 98])
    y0, y1 = np.percentile(ys, [2, 98])
    # the body circle's diameter is about the body's longer side; the ROI adds the model's 1.25 framing
    side = max(x1 - x0, y1 - y0) + 1.0
    return Roi(float((x0 + x1) / 2), float((y0 + y1) / 2), side * _ROI_SCALE, 0.0)


@dataclass
class SequenceResult:
    """Per image: the pose (None where the person was not found) and how its ROI was found."""

    poses: list
    found_by: list  # "tracked" | "detector" | "events" | "image" | ""
    losses: list  # (index, flag) where tracking lost the person
    seconds: float
    #: per image, how many of the images tried at that moment (the ``alternatives``) show the kept pose: their own
    #: pose within ``agree_ratio`` of its size (the kept one counts); 1 without alternatives, 0 where none was found
    agreeing: list
    #: per image, how many images were tried at that moment
    tried: list


#: The body landmarks (BlazePose order) two poses are compared on: the nose, shoulders, elbows, wrists, hips, knees
#: and ankles (the face's and hands' small points would weigh a head many times over).
AGREE_POINTS = (0, 11, 12, 13, 14, 15, 16, 23, 24, 25, 26, 27, 28)


def agreeing_poses(best, others, ratio: float) -> int:
    """How many of ``others`` (poses of the same moment in other images; None where none was found) put the body
    where ``best`` does: the median distance over :data:`AGREE_POINTS` at most ``ratio`` x the diagonal of
    ``best``'s box over them. ``best`` itself is not counted."""
    ref = np.asarray(best.xy, float)[AGREE_POINTS, :2]
    size = float(np.hypot(*(ref.max(axis=0) - ref.min(axis=0))))
    n = 0
    for pose in others:
        if pose is None or pose is best:
            continue
        d = np.hypot(*(np.asarray(pose.xy, float)[AGREE_POINTS, :2] - ref).T)
        n += int(np.median(d) <= ratio * size)
    return n


def detect_sequence(net: BlazePose, images, times_us: np.ndarray, *, track: bool = True, find: str = "detector",
                    events: np.ndarray | None = None, events_window_us: int = 20000, gamma: float = 1.0,
                    log=None, alternatives=None, agree_ratio: float = 0.2) -> SequenceResult:
    """Run the landmark model over a time-ordered sequence of grey images (linear intensity in [0, 1]).

    With ``track``, each image's ROI comes from the previous pose's auxiliary points while its pose flag stays at
    or above ``net.presence_threshold``; otherwise (and on the first image) the person is found again: by the
    person detector (``find='detector'``, falling back to the events when the detector sees nobody), or from the
    events alone (``find='events'``); then the box where the person was last seen (followed through a short loss);
    last, the landmark model looks at the whole image.

    ``alternatives(i, image)``: other images of the same moment to try, as (name, image) pairs (images made from the
    events, :mod:`eventcap.imaging.event_images`); the pose the network scores best (its pose flag) over them is
    kept, and ``found_by`` says which image gave it (``"tracked@counts:25"``)."""
    import time

    if find not in ("detector", "events"):
        raise ValueError(f"find: expected 'detector' or 'events', got {find!r}")
    if find == "events" and events is None:
        raise ValueError("find='events' needs the recording's events")
    poses, found_by, losses, agreeing, tried = [], [], [], [], []
    prev, last_roi = None, None
    t0 = time.perf_counter()
    for i, image in enumerate(images):
        candidates = [("", image)] if alternatives is None else list(alternatives(i, image))
        best, best_how, lost_flag, found = None, "", None, []
        for name, img in candidates:
            pose, how, flag = _pose_in(net, to_rgb8(img, gamma), prev if track else None, last_roi, find, events,
                                       int(times_us[i]), events_window_us)
            found.append(pose)
            if flag is not None:
                lost_flag = flag if lost_flag is None else max(lost_flag, flag)
            if pose is not None and (best is None or pose.flag > best.flag):
                best, best_how = pose, (f"{how}@{name}" if name else how)
        agreeing.append(0 if best is None else 1 + agreeing_poses(best, found, agree_ratio))
        tried.append(len(candidates))
        if track and prev is not None and (best is None or not best_how.startswith("tracked")):
            losses.append((i, 0.0 if lost_flag is None else lost_flag))
        if log is not None and best is None and prev is not None:
            log(f"lost the person at image {i} (t = {int(times_us[i])} us)")
        if log is not None and best is not None and prev is None and i > 0:
            log(f"found the person again at image {i} (t = {int(times_us[i])} us) by the {best_how}")
        poses.append(best)
        found_by.append(best_how)
        prev = best
        if best is not None:
            last_roi = best.roi
    return SequenceResult(poses, found_by, losses, time.perf_counter() - t0, agreeing, tried)


def _pose_in(net: BlazePose, rgb: np.ndarray, prev, last_roi, find: str, events, t_us: int, window_us: int):
    """One image's pose: (pose or None, how it was found, the tracked crop's flag when tracking lost it)."""
    h, w = rgb.shape[:2]
    lost = None
    if prev is not None:
        roi = prev.next_roi()
        if roi.overlaps(w, h):
            cand = net.landmarks(rgb, roi)
            if cand.flag >= net.presence_threshold:
                return cand, "tracked", None
            lost = cand.flag
        else:
            lost = 0.0
    rois = []
    if find == "detector":
        found = net.detect_person(rgb)
        if found is not None:
            rois.append((found[0], "detector"))
    if events is not None:
        roi = events_roi(events, t_us, window_us, w, h)
        if roi is not None:
            rois.append((roi, "events"))
    if last_roi is not None and last_roi.overlaps(w, h):
        rois.append((last_roi, "last box"))  # the person's box followed through a short loss
    # last: the whole image as one crop (a small actor that barely moves is missed by both above; the landmark
    # model still finds it there, and its own framing then zooms in)
    rois.append((Roi(w / 2, h / 2, float(max(w, h)), 0.0), "image"))
    for roi, origin in rois:
        cand = net.landmarks(rgb, roi)
        if cand.flag >= net.presence_threshold:
            # one more pass on the crop the model itself frames (a found box is coarser than a tracked one)
            again = net.landmarks(rgb, cand.next_roi()) if cand.next_roi().overlaps(w, h) else cand
            return (again if again.flag >= net.presence_threshold else cand), origin, lost
    return None, "", lost
