"""How much of an estimated motion was seen: a confidence per frame and joint, in [0, 1], from measurable support.

No ground truth enters; only what the run observed. For every joint j at every frame t of the motion:

1. **In view.** The estimated joint projects into the image, in front of the camera, with the body around it: at
   least its depth inside the template's body (:func:`joint_radii`, projected) inside every edge; else 0 (a joint
   outside the image was not seen, whatever the solve made of it; one whose body the edge cuts was at best half seen,
   and a detector's landmark there is extrapolated).
2. **Detections, at the intensity frames.** A landmark the detector marks as an observation (``in_view``, confidence
   > 0, its image accepted) supports the joint it follows as much as the estimate agrees with it:
   ``c_det · exp(-(r / r0)²)``, r the reprojection residual of the estimated landmark (px), r0 = ``detection_frac``
   of the person's height in the image (the in-view landmarks' extent), so the scale follows resolution and
   distance. A joint with several landmarks takes the best; a joint without a landmark of its own (the spine, the
   collars, the hands and feet) the mean of its skeleton neighbours' supports (through the neighbours that have
   one: spine2 takes spine1's and spine3's). A landmark not observed gives 0.
3. **Between two intensity frames**, the support of the two frames, interpolated in time, is only as good as what
   happened in between is known: a joint whose estimated image position moves less than ``still_frac`` of the body
   height over the interval was still, and keeps it; one that moved must be confirmed by the events: the events
   around its bones where the estimate puts them (:func:`eventcap.energy.silence.measure_silence`, above the
   background) confirm it, silence there does not. Away from the frames the support then decays with
   ``m(τ) = 4τ(1 - τ)`` (0 at a frame, 1 half way): ``c = interp · (1 - m (1 - e))``, e in [0, 1] the event support
   (1 - stillness) of the joint's bones in the knot bin holding t.
4. **Gaps** (frames with no estimate, NaN poses) are 0.

Below 0.5 a joint is unobserved or not trusted (what the outputs mark as such).
"""

from __future__ import annotations

import numpy as np

from eventcap.body.kinematics import joint_positions, landmark_positions
from eventcap.body.skeleton import NUM_JOINTS, PARENTS
from eventcap.camera import Camera

#: A joint below this confidence is unobserved or not trusted.
OBSERVED = 0.5


def in_image(camera: Camera, points: np.ndarray, radius_m=None) -> np.ndarray:
    """(...,) bool: the points (..., 3) project into the image (pixel centres' extent) and lie in front of it; with
    ``radius_m`` (broadcast to the points' shape (...)), the ball of that radius around each point does too: the
    point is at least its radius's projection (f r / z px) inside every edge."""
    P = np.asarray(points, dtype=np.float64)
    flat = P.reshape(-1, 3)
    r = np.zeros(flat.shape[0]) if radius_m is None else \
        np.broadcast_to(np.asarray(radius_m, dtype=np.float64), P.shape[:-1]).reshape(-1)
    ok = np.isfinite(flat).all(axis=1)
    out = np.zeros(flat.shape[0], dtype=bool)
    if ok.any():
        z = camera.depth(flat[ok])
        front = z > 0.05
        px = np.full((int(ok.sum()), 2), np.nan)
        if front.any():
            px[front] = camera.project(flat[ok][front])
        m = max(camera.fx, camera.fy) * r[ok] / np.maximum(z, 0.05)
        inside = front & (px[:, 0] >= m - 0.5) & (px[:, 0] <= camera.width - 0.5 - m) & (px[:, 1] >= m - 0.5) \
            & (px[:, 1] <= camera.height - 0.5 - m)
        out[np.flatnonzero(ok)] = inside
    return out.reshape(P.shape[:-1])


def joint_radii(template) -> np.ndarray:
    """(24,) how deep each joint of the template lies inside its body: the distance from the rest pose's joint to the
    nearest point of the template's surface (m). A joint closer to an image edge than this (projected) has part of the
    body around it out of the image: a detector's landmark there is extrapolated, not seen."""
    import trimesh

    mesh = trimesh.Trimesh(np.asarray(template.vertices), np.asarray(template.faces), process=False)
    _, dist, _ = trimesh.proximity.closest_point(mesh, np.asarray(template.rest_joints, dtype=np.float64))
    return np.asarray(dist, dtype=np.float64)


def _joint_neighbours() -> list[np.ndarray]:
    """Each joint's skeleton neighbours (parent and children)."""
    out = []
    for j in range(NUM_JOINTS):
        nb = list(np.flatnonzero(PARENTS == j))
        if PARENTS[j] >= 0:
            nb.append(int(PARENTS[j]))
        out.append(np.array(sorted(nb), dtype=np.int64))
    return out


_NEIGHBOURS = _joint_neighbours()


def detection_support(template, camera: Camera, poses: np.ndarray, keypoints: np.ndarray, observed: np.ndarray,
                      confidence_2d: np.ndarray, detection_frac: float) -> np.ndarray:
    """(D, 24) support of each joint at D detection frames (module doc, 2): poses (D, 33) the estimate there,
    keypoints (D, L, 2) px, observed (D, L) bool, confidence_2d (D, L)."""
    D = poses.shape[0]
    est = camera.project(landmark_positions(poses, template).reshape(-1, 3)).reshape(D, -1, 2)
    obs = observed & (confidence_2d > 0) & np.isfinite(keypoints).all(-1) & np.isfinite(est).all(-1)
    lo = np.where(obs[..., None], keypoints, np.inf).min(axis=1)
    hi = np.where(obs[..., None], keypoints, -np.inf).max(axis=1)
    height = np.where(obs.sum(1) >= 2, np.max(hi - lo, axis=1), np.nan)  # the person's extent in the image
    r0 = np.maximum(detection_frac * height, 1.0)[:, None]
    r = np.linalg.norm(np.where(obs[..., None], est - keypoints, 0.0), axis=-1)
    s_lm = np.where(obs, confidence_2d * np.exp(-(r / r0) ** 2), 0.0)
    s_lm = np.where(np.isfinite(s_lm), s_lm, 0.0)
    lj = np.asarray(template.landmark_joint)
    s = np.zeros((D, NUM_JOINTS))
    has = np.zeros(NUM_JOINTS, dtype=bool)
    for k, j in enumerate(lj):
        s[:, j] = np.maximum(s[:, j], s_lm[:, k])
        has[j] = True
    todo = set(np.flatnonzero(~has).tolist())
    while todo:  # no landmark of its own: the mean of its neighbours' that have a support (spine2: via spine1, 3)
        ready = {j: [n for n in _NEIGHBOURS[j] if has[n]] for j in todo}
        ready = {j: nb for j, nb in ready.items() if nb}
        if not ready:
            break
        for j, nb in ready.items():
            s[:, j] = s[:, nb].mean(axis=1)
        for j in ready:
            has[j] = True
            todo.discard(j)
    return s


def interval_support(t_us: np.ndarray, t_det: np.ndarray, s_det: np.ndarray, moved: np.ndarray,
                     events: np.ndarray) -> np.ndarray:
    """(T, 24) support at the motion's times t_us (module doc, 3): the detection frames' support s_det (D, 24) at
    t_det (D,) interpolated, decaying between frames unless the joint was still over its interval (moved: (D - 1,
    24) bool, it moved) or the events confirm it (events: (T, 24) in [0, 1])."""
    t = np.asarray(t_us, dtype=np.float64)
    td = np.asarray(t_det, dtype=np.float64)
    out = np.zeros((t.size, NUM_JOINTS))
    if td.size == 0:
        return out
    k = np.clip(np.searchsorted(td, t, side="right") - 1, 0, max(td.size - 2, 0))
    if td.size == 1:
        near = np.abs(t - td[0]) < 1.0
        out[near] = s_det[0]
        return out
    a, b = td[k], td[k + 1]
    tau = np.clip((t - a) / np.maximum(b - a, 1.0), 0.0, 1.0)[:, None]
    interp = (1.0 - tau) * s_det[k] + tau * s_det[k + 1]
    m = 4.0 * tau * (1.0 - tau)
    confirm = np.where(moved[k], events, 1.0)
    out = interp * (1.0 - m * (1.0 - confirm))
    outside = (t < td[0] - 0.5) | (t > td[-1] + 0.5)  # beyond the first/last detection frame: only the events
    out[outside] = 0.0
    return out


def motion_confidence(template, camera: Camera, t_us: np.ndarray, poses: np.ndarray, t_det: np.ndarray,
                      keypoints: np.ndarray, observed: np.ndarray, confidence_2d: np.ndarray,
                      event_support: np.ndarray, detection_frac: float, still_frac: float) -> np.ndarray:
    """(T, 24) confidence of the motion (t_us (T,), poses (T, 33); NaN rows: gaps) from the detections at t_det
    (D,) (keypoints (D, L, 2), observed (D, L), confidence_2d (D, L)) and the event support (T, 24) in [0, 1]
    (module doc). Detection frames outside the motion's estimated frames give no support."""
    t_us = np.asarray(t_us, dtype=np.int64)
    poses = np.asarray(poses, dtype=np.float64)
    est = np.isfinite(poses).all(axis=1)
    out = np.zeros((t_us.size, NUM_JOINTS))
    if not est.any():
        return out
    # the estimate at the detection frames (exact tracking frames when they are among the motion's times)
    t_det = np.asarray(t_det, dtype=np.int64)
    idx = np.searchsorted(t_us, t_det)
    hit = (idx < t_us.size) & (t_us[np.minimum(idx, t_us.size - 1)] == t_det)
    hit[hit] &= est[idx[hit]]
    t_d, P_d = t_det[hit], poses[idx[hit]]
    s_det = detection_support(template, camera, P_d, keypoints[hit], observed[hit], confidence_2d[hit],
                              detection_frac) if t_d.size else np.zeros((0, NUM_JOINTS))
    # moved over each interval between detection frames: the estimate's image displacement against the body height
    J_d = joint_positions(P_d, template) if t_d.size else np.zeros((0, NUM_JOINTS, 3))
    px_d = camera.project(J_d.reshape(-1, 3)).reshape(-1, NUM_JOINTS, 2) if t_d.size else np.zeros((0, NUM_JOINTS, 2))
    body = np.nanmax(np.ptp(px_d, axis=1), axis=1) if t_d.size else np.zeros(0)  # (D,) the skeleton's extent
    if t_d.size > 1:
        step = np.linalg.norm(px_d[1:] - px_d[:-1], axis=-1)
        moved = ~(step <= still_frac * np.minimum(body[1:], body[:-1])[:, None])
    else:
        moved = np.zeros((0, NUM_JOINTS), dtype=bool)
    out = interval_support(t_us, t_d, s_det, moved, np.asarray(event_support, dtype=np.float64))
    seen = in_image(camera, joint_positions(np.where(est[:, None], poses, 0.0), template), joint_radii(template))
    out = np.where(seen & est[:, None], out, 0.0)
    return np.clip(out, 0.0, 1.0)


__all__ = ["OBSERVED", "detection_support", "in_image", "interval_support", "joint_radii", "motion_confidence"]
