"""Measures against ground truth: where a tracked image feature truly is over time, and track errors."""

from __future__ import annotations

import numpy as np

from eventcap.body.kinematics import skin
from eventcap.render import Render, pick_surface_points, rasterize


def pose_at(gt, t_us: np.ndarray) -> np.ndarray:
    """Ground-truth poses (T, 33) at arbitrary times, linearly interpolated from the 1 kHz ground truth."""
    t = np.asarray(t_us, dtype=np.float64)
    return np.stack([np.interp(t, gt.t_us, gt.poses[:, k]) for k in range(gt.poses.shape[1])], axis=-1)


def feature_ground_truth(rec, t_ref_us: int, xy_ref: np.ndarray, times_us: np.ndarray,
                         ) -> tuple[np.ndarray, np.ndarray]:
    """True image positions over ``times_us`` of the scene points seen at ``xy_ref`` (H, 2) at ``t_ref_us``.

    A point on the actor is the surface point under the pixel at t_ref (triangle + barycentrics of the posed
    template), moved by the ground-truth motion and projected; a point on the static background stays where it is.
    Returns positions (T, H, 2) and on_actor (H,) bool.
    """
    gt, tpl, cam = rec.ground_truth, rec.template, rec.camera
    if gt is None or tpl is None:
        raise ValueError("feature_ground_truth needs a recording with ground truth and its template (synthetic)")
    xy_ref = np.asarray(xy_ref, dtype=np.float64).reshape(-1, 2)
    times_us = np.asarray(times_us, dtype=np.int64)
    verts = skin(pose_at(gt, np.array([t_ref_us]))[0], tpl)
    depth, tri_id, bary = rasterize(cam, verts, tpl.faces)
    tri, b = pick_surface_points(cam, verts, tpl.faces, Render(depth, depth, tri_id, bary), xy_ref)
    on = tri >= 0
    out = np.repeat(xy_ref[None], times_us.size, axis=0)
    if on.any():
        V = skin(pose_at(gt, times_us), tpl)  # (T, V, 3)
        corners = V[:, tpl.faces[tri[on]]]  # (T, P, 3, 3)
        world = np.einsum("pk,tpkd->tpd", b[on], corners)
        out[:, on] = cam.project(world)
    return out, on


def track_errors(rec, track_id: np.ndarray, t_us: np.ndarray, xy: np.ndarray, t_ref_us: np.ndarray,
                 xy_ref: np.ndarray, grid_us: int = 500) -> tuple[np.ndarray, np.ndarray]:
    """Per-sample error (px) of asynchronous tracks against the truth.

    Track k follows the scene point seen at ``xy_ref[k]`` at time ``t_ref_us[k]`` (its detection). The truth is
    computed on a ``grid_us`` time grid and interpolated linearly at each sample time (the motion is smooth at this
    scale). Returns error (S,) and on_actor (K,) bool.
    """
    track_id = np.asarray(track_id)
    t_us = np.asarray(t_us, np.int64)
    K = int(np.asarray(t_ref_us).shape[0])
    err = np.full(track_id.size, np.nan)
    on_actor = np.zeros(K, bool)
    if track_id.size == 0:
        return err, on_actor
    grid = np.arange(t_us.min() - grid_us, t_us.max() + 2 * grid_us, grid_us, dtype=np.int64)
    for t_ref in np.unique(t_ref_us):
        ks = np.flatnonzero(t_ref_us == t_ref)
        truth, on = feature_ground_truth(rec, int(t_ref), xy_ref[ks], grid)  # (G, n, 2)
        on_actor[ks] = on
        for j, k in enumerate(ks):
            m = track_id == k
            tx = np.interp(t_us[m], grid, truth[:, j, 0])
            ty = np.interp(t_us[m], grid, truth[:, j, 1])
            err[m] = np.hypot(tx - xy[m, 0], ty - xy[m, 1])
    return err, on_actor


def procrustes_align(pred: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """pred (..., J, 3) rigidly aligned (rotation + translation, no scale) to truth per leading index (Kabsch)."""
    pred = np.asarray(pred, dtype=np.float64)
    truth = np.asarray(truth, dtype=np.float64)
    if pred.shape != truth.shape or pred.shape[-1] != 3:
        raise ValueError(f"procrustes_align: expected two (..., J, 3) arrays of one shape, got {pred.shape}, "
                         f"{truth.shape}")
    mp, mt = pred.mean(axis=-2, keepdims=True), truth.mean(axis=-2, keepdims=True)
    A, B = pred - mp, truth - mt
    U, _, Vt = np.linalg.svd(np.swapaxes(A, -1, -2) @ B)
    d = np.sign(np.linalg.det(U @ Vt))
    D = np.zeros(U.shape)
    D[..., 0, 0] = D[..., 1, 1] = 1.0
    D[..., 2, 2] = d
    R = U @ D @ Vt  # applied on the right: A @ R ≈ B
    return A @ R + mt


def mean_joint_error(pred_joints: np.ndarray, true_joints: np.ndarray, align: bool = True) -> np.ndarray:
    """Per-frame mean per-joint 3D error in metres (paper's AE), after Procrustes alignment per frame by default.

    pred_joints, true_joints: (T, 24, 3) metres. Returns (T,).
    """
    pred = procrustes_align(pred_joints, true_joints) if align else np.asarray(pred_joints, dtype=np.float64)
    return np.linalg.norm(pred - np.asarray(true_joints, dtype=np.float64), axis=-1).mean(axis=-1)
