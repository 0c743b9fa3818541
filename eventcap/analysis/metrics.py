"""Measures against ground truth: where a tracked image feature truly is over time, track errors, joint errors and
the motion detail of a 1 kHz capture (velocity, acceleration, peak speeds). Pure functions of arrays."""

from __future__ import annotations

import numpy as np


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
    from eventcap.body.kinematics import skin  # here, not at the top: the stage specs import this module's constants
    from eventcap.imaging.render import Render, pick_surface_points, rasterize

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


def depth_split(pred_joints: np.ndarray, true_joints: np.ndarray, R_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The root-relative joint error split along the camera's axes: (depth (T, J-1), image plane (T, J-1)), metres.

    Each joint's root-relative error vector e = (P_j - P_root) - (G_j - G_root) of pred and truth (T, J, 3) in
    world coordinates is turned into the camera's axes by R_cam (3, 3, world to camera, OpenCV axes: z along the
    line of sight); depth is |e_z|, image plane ‖(e_x, e_y)‖. The root itself (0 by construction) is left out. What a
    single camera sees least is depth: this tells how much of an error lies along the line of sight."""
    P, G = root_relative(pred_joints)[..., 1:, :], root_relative(true_joints)[..., 1:, :]
    if P.shape != G.shape:
        raise ValueError(f"depth_split: pred {P.shape} and truth {G.shape} differ")
    R = np.asarray(R_cam, dtype=np.float64)
    if R.shape != (3, 3):
        raise ValueError(f"depth_split: expected a (3, 3) camera rotation, got {R.shape}")
    e = (P - G) @ R.T
    return np.abs(e[..., 2]), np.linalg.norm(e[..., :2], axis=-1)


# ---------------------------------------------------------------------------------------------------------------------
# Motion detail: velocities, accelerations and peak speeds of root-relative joints (what a 1 kHz capture is for)
# ---------------------------------------------------------------------------------------------------------------------
#: Joints whose speed shows the fast motion: feet, wrists and hands of the 24-joint skeleton.
END_EFFECTORS: tuple[str, ...] = ("l_foot", "r_foot", "l_wrist", "r_wrist", "l_hand", "r_hand")


def truth_at(gt_t_us: np.ndarray, gt_joints: np.ndarray, t_us: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth joints (n, J, 3) at the times ``t_us`` inside the truth's span (exact on its grid, linear between
    its samples), and that mask (T,)."""
    gt_t = np.asarray(gt_t_us, dtype=np.int64)
    t_us = np.asarray(t_us, dtype=np.int64)
    inside = (t_us >= gt_t[0]) & (t_us <= gt_t[-1])
    ti = t_us[inside]
    k = np.searchsorted(gt_t, ti)  # gt_t[k] >= ti
    exact = gt_t[k] == ti
    J = np.empty((ti.size, gt_joints.shape[1], 3))
    J[exact] = gt_joints[k[exact]]
    if not exact.all():
        kb = k[~exact]
        w = ((ti[~exact] - gt_t[kb - 1]) / (gt_t[kb] - gt_t[kb - 1]))[:, None, None]
        J[~exact] = (1.0 - w) * gt_joints[kb - 1] + w * gt_joints[kb]
    return J, inside


def root_relative(joints: np.ndarray, root: int = 0) -> np.ndarray:
    """Joints (..., J, 3) minus the root joint (the pelvis, index 0): the body's own motion, without its travel."""
    joints = np.asarray(joints, dtype=np.float64)
    return joints - joints[..., root:root + 1, :]


def half_window_steps(t_us: np.ndarray, window_us: float) -> tuple[int, int]:
    """(k, step_us): central differences reach k tracking steps to each side, k = round(window / 2 / step) >= 1, where
    step is the median time step. The window actually used is 2·k·step."""
    t = np.asarray(t_us, dtype=np.int64)
    if t.size < 3:
        raise ValueError(f"central differences need at least 3 frames, got {t.size}")
    if not window_us > 0:
        raise ValueError(f"window: expected a positive time window (us), got {window_us!r}")
    step = int(np.median(np.diff(t)))
    if step <= 0:
        raise ValueError("t_us: times must increase")
    return max(1, int(round(window_us / 2.0 / step))), step


def central_derivative(x: np.ndarray, t_us: np.ndarray, window_us: float, order: int = 1,
                       ) -> tuple[np.ndarray, np.ndarray]:
    """First (order=1) or second (order=2) time derivative of x (T, ...) by central differences over a window,
    per second: with h = k·step (:func:`half_window_steps`)

        order 1: (x(t + h) - x(t - h)) / 2h          order 2: (x(t + h) - 2 x(t) + x(t - h)) / h²

    Returns (T, ...) derivatives and a mask (T,) of the frames where both neighbours exist exactly h away (not near
    the ends, nor across a gap); elsewhere the values are NaN."""
    if order not in (1, 2):
        raise ValueError(f"order: expected 1 or 2, got {order!r}")
    x = np.asarray(x, dtype=np.float64)
    t = np.asarray(t_us, dtype=np.int64)
    if x.shape[0] != t.size:
        raise ValueError(f"central_derivative: x has {x.shape[0]} frames but t_us {t.size}")
    k, step = half_window_steps(t, window_us)
    out = np.full(x.shape, np.nan)
    valid = np.zeros(t.size, dtype=bool)
    h = k * step
    # the neighbours by time, not by index: an intensity frame between two grid times (tracking_times_us) is a
    # frame of its own but no grid frame's neighbour
    hi, lo = np.searchsorted(t, t + h), np.searchsorted(t, t - h)
    ok = (hi < t.size) & (t[np.minimum(hi, t.size - 1)] == t + h) & (t[lo] == t - h)
    i = np.flatnonzero(ok)
    hi, lo = hi[i], lo[i]
    hs = h * 1e-6
    if order == 1:
        out[i] = (x[hi] - x[lo]) / (2.0 * hs)
    else:
        out[i] = (x[hi] - 2.0 * x[i] + x[lo]) / (hs * hs)
    valid[i] = True
    return out, valid


def peak_speeds(t_us: np.ndarray, speed_pred: np.ndarray, speed_true: np.ndarray, valid: np.ndarray,
                intervals_us: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The peak speed of each joint in each interval (a batch: the span between two intensity frames), estimated and
    true: two (B, E) arrays (m/s) of the maxima over the valid frames with t0 <= t <= t1; NaN where an interval has
    no valid frame.

    speed_pred, speed_true: (T, E) m/s; valid (T,); intervals_us (B, 2)."""
    t = np.asarray(t_us, dtype=np.int64)
    iv = np.asarray(intervals_us, dtype=np.int64).reshape(-1, 2)
    sp, st = np.asarray(speed_pred, dtype=np.float64), np.asarray(speed_true, dtype=np.float64)
    pred, true = np.full((iv.shape[0], sp.shape[1]), np.nan), np.full((iv.shape[0], sp.shape[1]), np.nan)
    for b, (t0, t1) in enumerate(iv):
        m = valid & (t >= t0) & (t <= t1)
        if m.any():
            pred[b], true[b] = sp[m].max(axis=0), st[m].max(axis=0)
    return pred, true


def peak_speed_errors(t_us: np.ndarray, speed_pred: np.ndarray, speed_true: np.ndarray, valid: np.ndarray,
                      intervals_us: np.ndarray, min_true_mps: float = 0.0, signed: bool = False) -> np.ndarray:
    """Relative error of the peak speed of each joint in each interval (a batch) (:func:`peak_speeds`): (B, E) of
    |max pred - max true| / max true (``signed``: without the absolute value, negative where the estimate is
    slower); NaN where an interval has no valid frame or the true peak is at or below ``min_true_mps``."""
    pp, pt = peak_speeds(t_us, speed_pred, speed_true, valid, intervals_us)
    out = np.full(pp.shape, np.nan)
    ok = np.isfinite(pt) & (np.nan_to_num(pt) > max(min_true_mps, 0.0))
    d = (pp[ok] - pt[ok]) / pt[ok]
    out[ok] = d if signed else np.abs(d)
    return out


#: The true-speed bins (m/s) the signed peak-speed error is reported by: where the fast moments are lost.
SPEED_BINS_MPS: tuple[float, ...] = (0.5, 1.5, 3.0, 6.0)


def speed_bin_label(lo: float, hi: float) -> str:
    """``'0.5-1.5'``, ``'6+'``: a bin of :data:`SPEED_BINS_MPS` as the metrics name it."""
    return f"{lo:g}+" if not np.isfinite(hi) else f"{lo:g}-{hi:g}"


def signed_by_speed(true_mps: np.ndarray, signed: np.ndarray,
                    bins: tuple[float, ...] = SPEED_BINS_MPS) -> dict[str, dict[str, float | int | None]]:
    """The median signed relative peak-speed error (negative: too slow) of the (interval, end effector) pairs whose
    true peak falls in each bin (edges ``bins``, the last open-ended), with their count: {label: {median, n}}."""
    t = np.asarray(true_mps, dtype=np.float64).ravel()
    e = np.asarray(signed, dtype=np.float64).ravel()
    ok = np.isfinite(t) & np.isfinite(e)
    edges = (*bins, np.inf)
    out: dict[str, dict[str, float | int | None]] = {}
    for lo, hi in zip(edges[:-1], edges[1:]):
        m = ok & (t >= lo) & (t < hi)
        out[speed_bin_label(lo, hi)] = {"median": float(np.median(e[m])) if m.any() else None, "n": int(m.sum())}
    return out


def motion_detail(t_us: np.ndarray, pred_joints: np.ndarray, true_joints: np.ndarray, window_us: float = 10_000,
                  intervals_us: np.ndarray | None = None, end_effectors: tuple[int, ...] = (),
                  min_true_mps: float = 0.0) -> dict:
    """Velocity measures of an estimated motion against the truth, both (T, J, 3) metres at times t_us (T,).

    Joints are taken root-relative (minus the pelvis, which is then left out: 23 joints). Velocities and
    accelerations by central differences over ``window_us`` (:func:`central_derivative`), at every frame where
    they exist. Returns:

    - ``MPJVE_mm_s``: mean over frames and joints of |v_pred - v_true| (mm/s);
    - ``accel_err_m_s2``: mean over frames and joints of |a_pred - a_true| (m/s²);
    - ``peak_speed_err``: median over (interval, end effector) of the relative error of the peak speed in each
      interval (:func:`peak_speed_errors`; a fraction, 0.15 = 15%), and ``peak_speed_errors`` (B, E) itself, with
      the peaks ``peak_speed_true`` and ``peak_speed_pred`` (B, E) m/s (:func:`peak_speeds`);
    - ``window_ms``: the window actually used; ``n_velocity_frames``;
    - ``speed_pred`` / ``speed_true`` (T, E) m/s of the end effectors (NaN where no derivative) and ``valid``.
    """
    P = root_relative(pred_joints)[:, 1:]
    G = root_relative(true_joints)[:, 1:]
    if P.shape != G.shape:
        raise ValueError(f"motion_detail: pred {P.shape} and truth {G.shape} differ")
    k, step = half_window_steps(t_us, window_us)
    vp, valid = central_derivative(P, t_us, window_us, 1)
    vt, _ = central_derivative(G, t_us, window_us, 1)
    ap, _ = central_derivative(P, t_us, window_us, 2)
    at, _ = central_derivative(G, t_us, window_us, 2)
    out: dict = {"window_ms": 2 * k * step / 1000.0, "n_velocity_frames": int(valid.sum()),
                 "MPJVE_mm_s": None, "accel_err_m_s2": None, "peak_speed_err": None}
    if valid.any():
        out["MPJVE_mm_s"] = float(1000.0 * np.linalg.norm(vp[valid] - vt[valid], axis=-1).mean())
        out["accel_err_m_s2"] = float(np.linalg.norm(ap[valid] - at[valid], axis=-1).mean())
    ee = [j - 1 for j in end_effectors]  # indices into the root-relative joints without the root
    if any(j < 0 for j in ee):
        raise ValueError("end_effectors: the root (joint 0) has no root-relative speed")
    sp = np.linalg.norm(vp[:, ee], axis=-1)
    st = np.linalg.norm(vt[:, ee], axis=-1)
    out.update(speed_pred=sp, speed_true=st, valid=valid)
    if ee and intervals_us is not None and valid.any():
        pp, pt = peak_speeds(t_us, sp, st, valid, intervals_us)
        errs = peak_speed_errors(t_us, sp, st, valid, intervals_us, min_true_mps)
        out["peak_speed_errors"] = errs
        out["peak_speed_true"], out["peak_speed_pred"] = pt, pp
        fin = errs[np.isfinite(errs)]
        out["peak_speed_err"] = float(np.median(fin)) if fin.size else None
    return out
