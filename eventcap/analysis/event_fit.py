"""How well a motion explains what a real camera recorded, without ground truth (issue 53).

On a recording of a real person there is no truth to compare with; what the motion can be held against is what the
camera gave:

- :func:`outline_event_share`: the share of the projected silhouette's outline (the template posed at time t,
  rasterised in the camera, its boundary pixels) that lies within ``tol_px`` of an event of that millisecond
  (``window_us`` around t). A moving person fires events along their outline; an outline where nothing fired is
  drawn where the person is not (or where they held still: a person who stands still fires nothing, so the share
  is judged on moments with events).
- :func:`reprojection_error`: the distance in pixels between the motion's landmarks projected into the camera and
  the detector's accepted 2D landmarks at the detection times (median and 90th percentile over the landmarks in
  view).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class OutlineShare:
    """``share``: outline pixels within tol_px of an event of their millisecond, over all sampled moments;
    ``frames``: moments sampled (estimated, with events); ``per_frame``: the share per sampled moment."""

    share: float
    frames: int
    outline_px: int
    per_frame: np.ndarray


def outline_mask(camera, template, pose: np.ndarray) -> np.ndarray:
    """(H, W) bool: the boundary pixels of the template's silhouette at ``pose`` (33,) in ``camera``."""
    from scipy import ndimage

    from eventcap.body.kinematics import skin
    from eventcap.imaging.render import rasterize

    _, tri_id, _ = rasterize(camera, skin(np.asarray(pose, np.float64), template), template.faces)
    mask = tri_id >= 0
    return mask & ~ndimage.binary_erosion(mask, border_value=0)


def outline_event_share(camera, template, t_us: np.ndarray, poses: np.ndarray, events: np.ndarray,
                        tol_px: float = 2.0, window_us: int = 1000, every_us: int = 20000,
                        min_events: int = 1) -> OutlineShare:
    """The share of outline pixels within ``tol_px`` of an event within ``window_us`` around their moment, sampled
    every ``every_us`` over the estimated frames (finite poses) of ``t_us`` (T,), ``poses`` (T, 33). Moments with
    fewer than ``min_events`` events in the window (nobody moved) are left out: a still person fires nothing. A
    sparse sensor bounds the share: an outline of n pixels needs n events in the window to be all covered."""
    from scipy import ndimage

    t = np.asarray(t_us, np.int64)
    poses = np.asarray(poses, np.float64)
    est = np.isfinite(poses).all(axis=1)
    if not est.any():
        return OutlineShare(float("nan"), 0, 0, np.zeros(0))
    step = max(1, int(round(every_us / max(int(np.median(np.diff(t))) if t.size > 1 else every_us, 1))))
    h, w = camera.height, camera.width
    ev_t = events["t"]
    near_total, total, per = 0, 0, []
    for i in np.flatnonzero(est)[::step]:
        a, b = np.searchsorted(ev_t, [t[i] - window_us // 2, t[i] + window_us // 2], side="left")
        if b - a < min_events:
            continue
        fired = np.zeros((h, w), bool)
        fired[events["y"][a:b].astype(np.intp), events["x"][a:b].astype(np.intp)] = True
        outline = outline_mask(camera, template, poses[i])
        n = int(outline.sum())
        if n == 0:
            continue
        dist = ndimage.distance_transform_edt(~fired)
        k = int((dist[outline] <= tol_px).sum())
        near_total += k
        total += n
        per.append(k / n)
    share = near_total / total if total else float("nan")
    return OutlineShare(float(share), len(per), int(total), np.asarray(per))


def reprojection_error(camera, template, t_us: np.ndarray, poses: np.ndarray, detections) -> dict:
    """Pixels between the motion's projected landmarks and the detections' accepted 2D landmarks (in view, confidence
    > 0) at the detection times the motion estimates: ``median_px``, ``p90_px``, ``points``, ``images``."""
    from eventcap.body.kinematics import landmark_positions

    t = np.asarray(t_us, np.int64)
    poses = np.asarray(poses, np.float64)
    det_t = np.asarray(detections.t_us, np.int64)
    idx = np.searchsorted(t, det_t)
    ok = (idx < t.size)
    idx = np.clip(idx, 0, t.size - 1)
    ok &= np.abs(t[idx] - det_t) <= 500
    ok &= np.isfinite(poses[idx]).all(axis=1)
    seen = np.asarray(detections.confidence_2d) > 0
    if detections.in_view is not None:
        seen &= np.asarray(detections.in_view, bool)
    errs, images = [], 0
    for k in np.flatnonzero(ok & seen.any(axis=1)):
        L = landmark_positions(poses[idx[k]][None], template)[0]
        uv = camera.project(L)
        d = np.linalg.norm(uv[seen[k]] - np.asarray(detections.keypoints_2d[k], np.float64)[seen[k]], axis=1)
        errs.append(d)
        images += 1
    if not errs:
        return {"median_px": None, "p90_px": None, "points": 0, "images": 0}
    e = np.concatenate(errs)
    return {"median_px": float(np.median(e)), "p90_px": float(np.percentile(e, 90)), "points": int(e.size),
            "images": images}
