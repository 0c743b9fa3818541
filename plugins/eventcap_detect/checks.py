"""What is in view, and detections that do not fit what the events show (issue 35, item 2).

Every detector's landmarks (the skeleton's BODY_25 order) go through the same three steps:

1. **In view.** A landmark is an observation only where it lies inside the image (at least ``border_px`` from
   its edge) and the detector says it is there (BlazePose's presence output, a file's or the simulated
   detector's confidence > 0). Landmarks out of view get confidence 0: a partial view gives a partial detection.
2. **Checks** that reject a whole image's detection (the reason is logged per image and counted):

   - ``outside``: fewer than ``min_in_view`` landmarks in the image (the detector put the body outside it);
   - ``parts``: the head and an ankle in view but no hip: the image is convex, so the hips between them would be
     in it too (a face close-up with feet drawn on it);
   - ``region``: a whole body (head, torso and an ankle in view) that does not fit the moving region around it
     (the connected event activity it lies in, :func:`moving_region`): its size (the longer side of its
     landmarks' box) under ``region_ratio`` x the region's (a body drawn inside a face, or inside a torso that
     fills the image), or the region reaching an edge of the image that the body keeps more than ``edge_ratio`` of
     the image (plus a fifth of its own size: the head's top, the soles) away from (the person goes on beyond the
     image: the body drawn inside is not all of them);
   - ``scale``: a whole body whose height disagrees with the scale of its own head and shoulders: ear-to-ear
     width over ``head_ratio`` or shoulder width over ``shoulder_ratio`` x the torso's length (neck to mid-hip).
     The head and shoulders of a close-up with a small body folded under them give 0.4-2 and 0.9-8; whole bodies
     of the synthetic captures at most 0.28 and 0.74 (benchmarks/accuracy/bench_view_checks.py). Such a detection
     is not rejected: it is a person partly out of view (status ``close_up``), its head, shoulders and arms kept
     (:data:`UPPER_BODY`) and the lower body it drew marked unobserved.

   - ``agree``: images reconstructed from the events only (an event-only camera), where the detector tries several
     images of each moment (``stages.detect.event_images``): the pose is not corroborated (:func:`corroborated`):
     fewer than ``min_agree`` of the images show the person where the kept pose puts them (their own pose within
     ``agree_ratio`` of its size), and neither neighbouring moment holds a corroborated pose that close. A person in
     view shows in the counts, time surfaces and reconstruction alike, and is followed through the moments where
     they move so little that one image alone shows them; a shape the network took for a person (a lap seen from
     the side, a blob) mostly shows in one image (docs/results/real.md).

   Checks that need what a detection lacks (no torso, no events near it, one image per moment) do not judge it. They assume a static
   camera, as the method does: a moving camera makes the whole image fire.
3. **Enough to solve**: the stage stops when fewer than ``min_found`` of the images (default: half) hold an
   accepted detection, naming the counts (:func:`found_message`): "no person in 199 of 202 images: a person in 3". Half, because a solve pinned by fewer detections than frames it spans fabricates the rest; the
   longest run of images without a detection is logged for the solve's windows to judge.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass

import numpy as np

from eventcap.body.skeleton import JOINT_INDEX, LANDMARK_INDEX

CHECKS = ("outside", "parts", "region", "scale", "agree")
#: The status of a detection the scale check keeps as a close-up: its head, shoulders and arms are observations, the
#: lower body it drew under them is not (:data:`UPPER_BODY`).
CLOSE_UP = "close_up"
#: The joints (SMPL order) of the lower body, whose 3D detections a close-up does not observe.
LOWER_JOINTS = tuple(JOINT_INDEX[n] for n in ("pelvis", "l_hip", "r_hip", "l_knee", "r_knee", "l_ankle", "r_ankle",
                                              "l_foot", "r_foot"))
#: The landmarks a close-up keeps (head, neck, shoulders, elbows, wrists): what a head-and-shoulders view shows.
UPPER_BODY = tuple(LANDMARK_INDEX[n] for n in ("nose", "neck", "r_shoulder", "r_elbow", "r_wrist", "l_shoulder",
                                               "l_elbow", "l_wrist", "r_eye", "l_eye", "r_ear", "l_ear"))
#: How far a body's silhouette reaches beyond its landmarks' box, as a share of the box's longer side (the top of the
#: head above the eyes; the soles below the ankles)
_BEYOND_LANDMARKS = 0.2
_HEAD = tuple(LANDMARK_INDEX[n] for n in ("nose", "r_eye", "l_eye", "r_ear", "l_ear"))
_ANKLES = (LANDMARK_INDEX["r_ankle"], LANDMARK_INDEX["l_ankle"])
_NECK, _MID_HIP = LANDMARK_INDEX["neck"], LANDMARK_INDEX["mid_hip"]
_EARS = (LANDMARK_INDEX["r_ear"], LANDMARK_INDEX["l_ear"])
_SHOULDERS = (LANDMARK_INDEX["r_shoulder"], LANDMARK_INDEX["l_shoulder"])
_HIPS = (LANDMARK_INDEX["r_hip"], LANDMARK_INDEX["l_hip"], _MID_HIP)


@dataclass(frozen=True)
class ViewSettings:
    """Settings of the view checks, built from a detect stage's config (whose dataclass states their defaults and
    meaning: ``ViewChecksConfig`` in spec.py); see the module docstring."""

    checks: tuple[str, ...]
    border_px: float
    min_in_view: int
    region_ratio: float
    edge_ratio: float
    head_ratio: float
    shoulder_ratio: float
    window_us: int
    min_found: float
    min_agree: int = 2
    agree_ratio: float = 0.2

    @classmethod
    def without_checks(cls, min_found: float) -> ViewSettings:
        """Only what is in view (inside the image) and enough detections: no check rejects anything."""
        return cls(checks=(), border_px=0.0, min_in_view=0, region_ratio=0.0, edge_ratio=0.0, head_ratio=0.0,
                   shoulder_ratio=0.0, window_us=1, min_found=min_found)

    def __post_init__(self):
        unknown = sorted(set(self.checks) - set(CHECKS))
        if unknown:
            raise ValueError(f"checks: unknown check {unknown[0]!r}; known: {', '.join(CHECKS)}")
        for name in ("border_px", "region_ratio", "edge_ratio", "head_ratio", "shoulder_ratio", "min_found"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"{name}: expected a finite number >= 0, got {v!r}")
        if not 0 <= self.min_found <= 1:
            raise ValueError(f"min_found: expected a share of the images in [0, 1], got {self.min_found!r}")
        if int(self.window_us) <= 0 or int(self.min_in_view) < 0:
            raise ValueError(f"window_us > 0 and min_in_view >= 0 expected, got {self.window_us}, {self.min_in_view}")
        if int(self.min_agree) < 1:
            raise ValueError(f"min_agree: expected at least 1 image, got {self.min_agree!r}")
        if not (math.isfinite(self.agree_ratio) and self.agree_ratio > 0):
            raise ValueError(f"agree_ratio: expected a share > 0 of the body's size, got {self.agree_ratio!r}")


def inside_image(kp: np.ndarray, width: int, height: int, border_px: float = 0.0) -> np.ndarray:
    """(..., L) bool: points (..., L, 2) at least ``border_px`` inside the image, whose pixels cover
    [-0.5, width - 0.5) x [-0.5, height - 0.5) (integer coordinates are pixel centres)."""
    x, y = kp[..., 0], kp[..., 1]
    lo = float(border_px) - 0.5
    return np.isfinite(x) & np.isfinite(y) & (x >= lo) & (y >= lo) & (x < width - 0.5 - float(border_px)) & \
        (y < height - 0.5 - float(border_px))


def cell_size(width: int, height: int) -> int:
    """Side of the cells event activity is counted in: about 1/30 of the image's shorter side, at least 4 px."""
    return max(4, int(round(min(width, height) / 30)))


#: Events per cell in the window above which the quietest quarter of the cells is taken for the person rather than
#: the sensor's noise (a close-up). Below it the Poisson test alone decides: a DVXplorer's noise and leak events at
#: 1000 lux are 2-5 per 16 px cell in 40 ms, and half the busiest quarter's count would mark every cell active.
_CLOSE_UP_QUIET = 10.0


def activity_cells(events: np.ndarray, t_us: int, width: int, height: int, window_us: int) -> np.ndarray:
    """(rows, cols) bool: the cells where the events within ``window_us`` around ``t_us`` are well above the
    background: at least 3, and 4 standard deviations (Poisson) above the quietest quarter of the cells, or half
    the count of the busiest quarter when that is lower and the quietest quarter itself fires (at least
    :data:`_CLOSE_UP_QUIET` events per cell: a close-up whose every cell fires is active all over)."""
    cell = cell_size(width, height)
    gw, gh = -(-width // cell), -(-height // cell)
    t = events["t"]
    a, b = np.searchsorted(t, [t_us - window_us // 2, t_us + window_us // 2])
    ev = events[a:b]
    counts = np.bincount((ev["y"] // cell).astype(np.int64) * gw + (ev["x"] // cell).astype(np.int64),
                         minlength=gw * gh).reshape(gh, gw)
    quiet, busy = np.percentile(counts, [25, 75])
    bar = quiet + 4.0 * math.sqrt(quiet + 1.0)
    if quiet >= _CLOSE_UP_QUIET:  # the quietest quarter fires too: the person fills the image
        bar = min(bar, 0.5 * busy)
    return counts >= max(3.0, bar)


def moving_region(active: np.ndarray, box: tuple[float, float, float, float], cell: int
                  ) -> tuple[float, float, float, float] | None:
    """The box (x0, y0, x1, y1, px) of the connected event activity that meets ``box`` (grown by one cell): the
    moving silhouette around a detection. None when no active cell meets it."""
    from scipy import ndimage

    labels, _ = ndimage.label(ndimage.binary_closing(active, np.ones((3, 3)), border_value=0) | active,
                              structure=np.ones((3, 3)))
    gh, gw = active.shape
    c0 = max(0, int(box[0] // cell) - 1), max(0, int(box[1] // cell) - 1)
    c1 = min(gw - 1, int(box[2] // cell) + 1), min(gh - 1, int(box[3] // cell) + 1)
    if c1[0] < c0[0] or c1[1] < c0[1]:
        return None
    ids = np.unique(labels[c0[1]:c1[1] + 1, c0[0]:c1[0] + 1])
    ids = ids[ids > 0]
    if ids.size == 0:
        return None
    ys, xs = np.nonzero(np.isin(labels, ids))
    return float(xs.min() * cell), float(ys.min() * cell), float((xs.max() + 1) * cell), float((ys.max() + 1) * cell)


def _length(kp, a, b) -> float:
    return float(np.hypot(*(kp[a] - kp[b])))


def check_detection(kp: np.ndarray, in_view: np.ndarray, active: np.ndarray | None, cell: int,
                    settings: ViewSettings) -> tuple[str, str]:
    """(check, why) of the first check that rejects one image's detection (kp (L, 2), in_view (L,)), or ("ok", "")."""
    n_in = int(in_view.sum())
    if "outside" in settings.checks and n_in < settings.min_in_view:
        return "outside", f"{n_in} landmarks in the image (at least {settings.min_in_view})"
    head, ankle = in_view[list(_HEAD)].any(), in_view[list(_ANKLES)].any()
    if "parts" in settings.checks and head and ankle and not in_view[list(_HIPS)].any():
        return "parts", "the head and an ankle in the image, the hips between them not: the parts do not hang together"
    whole = head and ankle and in_view[[_NECK, _MID_HIP]].all()
    if not whole:
        return "ok", ""
    pts = kp[in_view]
    box = (float(pts[:, 0].min()), float(pts[:, 1].min()), float(pts[:, 0].max()), float(pts[:, 1].max()))
    size = max(box[2] - box[0], box[3] - box[1])
    torso = _length(kp, _NECK, _MID_HIP)
    if "scale" in settings.checks and torso > 0:
        if in_view[list(_EARS)].all() and _length(kp, *_EARS) > settings.head_ratio * torso:
            return CLOSE_UP, (f"the head {_length(kp, *_EARS) / torso:.2f} x the torso wide (at most "
                              f"{settings.head_ratio:g}): a close-up's head and shoulders, the body drawn under "
                              f"them not seen")
        if in_view[list(_SHOULDERS)].all() and _length(kp, *_SHOULDERS) > settings.shoulder_ratio * torso:
            return CLOSE_UP, (f"the shoulders {_length(kp, *_SHOULDERS) / torso:.2f} x the torso wide (at most "
                              f"{settings.shoulder_ratio:g}): a close-up's head and shoulders, the body drawn "
                              f"under them not seen")
    if "region" in settings.checks and active is not None:
        region = moving_region(active, box, cell)
        if region is not None:
            return _region(box, size, region, active.shape, cell, settings)
    return "ok", ""


def _region(box, size, region, grid_shape, cell, settings) -> tuple[str, str]:
    """The region check of one whole body (its landmarks' ``box`` and ``size``) against the moving ``region``."""
    moving = max(region[2] - region[0], region[3] - region[1])
    if size < settings.region_ratio * moving:
        return "region", (f"a whole body {size:.0f} px tall inside a moving region of {moving:.0f} px (at least "
                          f"{settings.region_ratio:g} x expected)")
    # the moving region reaches an edge of the image the whole body keeps well away from: the person goes on
    # beyond the image, so the body drawn inside it is not all of them. The silhouette reaches beyond the landmarks
    # (the top of the head above the eyes, the soles below the ankles: about a fifth of the body), so that much more
    # is allowed
    width, height = grid_shape[1] * cell, grid_shape[0] * cell
    sides = (("left", region[0] <= cell, box[0], width), ("top", region[1] <= cell, box[1], height),
             ("right", region[2] >= width - cell, width - box[2], width),
             ("bottom", region[3] >= height - cell, height - box[3], height))
    for side, touches, gap, extent in sides:
        if touches and gap > settings.edge_ratio * extent + _BEYOND_LANDMARKS * size:
            return "region", (f"the moving region reaches the image's {side} edge, the whole body stays {gap:.0f} "
                              f"px from it (more than {settings.edge_ratio:g} of the image + "
                              f"{_BEYOND_LANDMARKS:g} of the body)")
    return "ok", ""


def _near(kp: np.ndarray, in_view: np.ndarray, i: int, j: int, ratio: float) -> bool:
    """Whether image j's pose puts the body where image i's does: the median distance over the landmarks both see
    (at least 3) at most ``ratio`` x the diagonal of image i's landmarks' box."""
    common = in_view[i] & in_view[j]
    if common.sum() < 3:
        return False
    pts = kp[i][in_view[i]]
    size = float(np.hypot(*(pts.max(axis=0) - pts.min(axis=0))))
    return float(np.median(np.linalg.norm(kp[i][common] - kp[j][common], axis=1))) <= ratio * size


def corroborated(kp: np.ndarray, in_view: np.ndarray, found: np.ndarray, agreed: np.ndarray, ratio: float
                 ) -> np.ndarray:
    """(n,) bool: the poses something besides their own image vouches for: ``agreed`` (enough images of the moment
    show it), or next to a corroborated pose of the moment before or after that lies within ``ratio`` of its size
    (followed through time, so a person seen by several images once stays corroborated while only one image shows
    them). kp (n, L, 2) px, in_view (n, L), found (n,)."""
    ok = np.asarray(found, bool) & np.asarray(agreed, bool)
    n = ok.size
    changed = True
    while changed:
        changed = False
        for i in np.nonzero(np.asarray(found, bool) & ~ok)[0]:
            if any(0 <= j < n and ok[j] and _near(kp, in_view, i, j, ratio) for j in (i - 1, i + 1)):
                ok[i] = changed = True
    return ok


def check_images(kp: np.ndarray, in_view: np.ndarray, found: np.ndarray, t_us: np.ndarray, events: np.ndarray,
                 width: int, height: int, settings: ViewSettings, agreeing: tuple[np.ndarray, np.ndarray] | None = None
                 ) -> tuple[list[str], list[str]]:
    """Per image: its status (``ok`` | ``no_person`` | the rejecting check) and why (empty for ``ok``).
    kp (n, L, 2) px, in_view (n, L), found (n,) whether the detector gave a detection at all; ``agreeing``: per
    image, how many of the images tried at that moment show the kept pose, and how many were tried (check agree)."""
    cell = cell_size(width, height)
    judged = "agree" in settings.checks and agreeing is not None
    agreed = corroborated(kp, in_view, found, agreeing[0] >= settings.min_agree, settings.agree_ratio) \
        if judged else None
    status, why = [], []
    for i in range(t_us.size):
        if not found[i]:
            status.append("no_person")
            why.append("")
            continue
        if judged and agreeing[1][i] > 1 and not agreed[i]:
            status.append("agree")
            why.append(f"the person shows in {agreeing[0][i]} of the {agreeing[1][i]} images made from the events "
                       f"of that moment (at least {settings.min_agree} must agree on where they are) and at no "
                       f"neighbouring moment's agreed place")
            continue
        active = activity_cells(events, int(t_us[i]), width, height, settings.window_us) \
            if "region" in settings.checks and events is not None and events.size else None
        s, w = check_detection(kp[i], in_view[i], active, cell, settings)
        status.append(s)
        why.append(w)
    return status, why


#: The statuses of an accepted detection: a whole or partial view as detected, or a close-up kept as its upper body.
ACCEPTED = ("ok", CLOSE_UP)
#: What changes each check (the setting a refusal names).
CHECK_SETTINGS = {"outside": "stages.detect.min_in_view", "parts": "stages.detect.checks",
                  "agree": "stages.detect.min_agree / stages.detect.agree_ratio",
                  "region": "stages.detect.region_ratio / stages.detect.edge_ratio",
                  "scale": "stages.detect.head_ratio / stages.detect.shoulder_ratio"}


def found_message(status: list[str], what: str, enough: bool = True) -> str:
    """What the detect stage says about its images: ``a person in 197 of 202 images (rejected: region 3, scale 2)``,
    or when there are not ``enough``, the cause first: ``no person in 199 of 202 images: a person in 3``."""
    n = len(status)
    counts = Counter(status)
    close = counts.pop(CLOSE_UP, 0)
    ok = counts.pop("ok", 0) + close
    none = counts.pop("no_person", 0)
    rejected = ", ".join(f"{k} {c}" for c, k in sorted(((c, k) for k, c in counts.items()), reverse=True))
    n_rej = sum(counts.values())
    close_note = f"{close} of them close-ups: the head and shoulders kept, the lower body unobserved" if close else ""
    if not enough:
        return (f"{what}: no person in {none} of {n} images" + (f", {n_rej} rejected ({rejected})" if n_rej else "")
                + (f": a person in {ok}" if ok else "") + (f" ({close_note})" if close else ""))
    extra = "; ".join(([close_note] if close else []) + ([f"rejected: {rejected}"] if n_rej else [])
                      + ([f"no person in {none}"] if none else []))
    return f"{what}: a person in {ok} of {n} images" + (f" ({extra})" if extra else "")


def refusal_hint(status: list[str], why: list[str], event_images: bool) -> str:
    """What to look at and which setting would change a refusal for too few detections: the checks when they
    rejected more images than the detector missed (naming the most frequent check, its first reason and its
    setting), else the detector's images."""
    counts = Counter(s for s in status if s not in (*ACCEPTED, "no_person"))
    missed = status.count("no_person")
    if counts and sum(counts.values()) >= missed:
        check, c = counts.most_common(1)[0]
        first = next(w for s, w in zip(status, why) if s == check)
        return (f"the detector found a person in {c} images that check {check} rejected (first: {first}): look at "
                f"them in `eventcap preview FILE --t SECONDS`; if a person shows there, the check is wrong for this "
                f"recording: {CHECK_SETTINGS.get(check, 'stages.detect.checks')} (or stages.detect.checks without "
                f"{check}) changes it")
    images = ("the images made from the events (stages.detect.event_images) showed the network no person"
              + (f" (and in {counts['agree']} more, too few of them agreed on one: check agree, "
                 f"{CHECK_SETTINGS['agree']})" if counts.get("agree") else "") + ": "
              if event_images else "the network saw no person in its images: ")
    return (images + "look at the recording in `eventcap preview FILE` (a person in view there means the images "
            "were too poor for it; none means there is nobody to capture); stages.detect.min_found solves the "
            "images it found")


def longest_gap(status: list[str]) -> int:
    """The longest run of consecutive images without an accepted detection."""
    best = run = 0
    for s in status:
        run = 0 if s in ACCEPTED else run + 1
        best = max(best, run)
    return best


def longest_stretch(status: list[str]) -> tuple[int, int]:
    """(first, last) image of the longest run of accepted detections that at most one image interrupts; (0, -1)
    when there is none."""
    best, start, gap = (0, -1), None, 0
    for i, s in enumerate([*status, "end", "end"]):
        if s in ACCEPTED:
            start, gap = (i if start is None else start), 0
            last = i
            if last - start > best[1] - best[0]:
                best = (start, last)
        elif start is not None:
            gap += 1
            if gap > 1:
                start, gap = None, 0
    return best
