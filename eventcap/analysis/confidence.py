"""What of an estimated motion the camera saw: which joints are in view. The uncertainty in millimetres and the
confidence derived from it are :mod:`eventcap.analysis.uncertainty`'s.

**In view.** The estimated joint projects into the image, in front of the camera, with the body around it: at least
its depth inside the template's body (:func:`joint_radii`, projected) inside every edge (a joint outside the image
was not seen, whatever the solve made of it; one whose body the edge cuts was at best half seen, and a detector's
landmark there is extrapolated), and with its uncertainty around it when one is given (a joint the solve puts just
inside the edge, known only to within centimetres, may well be outside it).

Below :data:`OBSERVED` a joint's confidence says it is unobserved or not trusted (what the outputs mark as such).
"""

from __future__ import annotations

import numpy as np

from eventcap.body.kinematics import joint_positions
from eventcap.body.skeleton import NUM_JOINTS
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


def joints_in_view(template, camera: Camera, poses: np.ndarray, margin_m: np.ndarray | None = None) -> np.ndarray:
    """(T, 24) bool: each joint of the estimate (poses (T, 33); NaN rows: gaps, False) is in view (module doc):
    with the ball of its body's depth around it, or of ``margin_m`` (T, 24) metres when that is larger (its
    uncertainty: a joint known only to within it is not claimed in view at the edge), inside every image edge."""
    P = np.asarray(poses, dtype=np.float64)
    est = np.isfinite(P).all(axis=1)
    out = np.zeros((P.shape[0], NUM_JOINTS), dtype=bool)
    if est.any():
        r = np.broadcast_to(joint_radii(template), (int(est.sum()), NUM_JOINTS))
        if margin_m is not None:
            r = np.fmax(r, np.asarray(margin_m, dtype=np.float64)[est])
        out[est] = in_image(camera, joint_positions(P[est], template), r)
    return out


__all__ = ["OBSERVED", "in_image", "joint_radii", "joints_in_view"]
