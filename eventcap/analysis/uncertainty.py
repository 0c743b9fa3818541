"""An uncertainty per joint and frame in millimetres, and how to judge one: does it rank the error, does it cover it.

The uncertainty u (mm) of joint j at frame t says how far from the truth the joint is likely to be, after the
evaluation's per-frame rigid alignment (``stages.evaluate.align=procrustes``: the error the paper reports, and the
one every figure of this module measures): the true 3D distance lies within 2 u about 90-97 % of the time
(calibrated per detector kind on tuning captures: :func:`calibration`, docs/results/uncertainty.md). It is made of
(:func:`joint_uncertainty`):

1. **The solve's own curvature**: σ_L, the Laplace approximation of the solve (:mod:`eventcap.energy.laplace`), times
   a ``scale``: the energy is a negative log-likelihood of the noise the detector states, but the detector's errors
   are not that independent Gaussian noise (they err together, lean, flip), so the scale is calibrated per detector
   kind.
2. **Where the cues disagree**, each a distance in mm that the curvature cannot see (it measures how tightly the
   terms hold the solution, not whether they agree), added as variances:

   - the detections against the solution at the intensity frames (:func:`detection_residuals`): a landmark's
     reprojection residual, carried to the joint's depth (r_px · z / f), and the 3D detection's residual after the
     best translation (E_3D's t'), interpolated in time between the frames;
   - the events along the bones between the frames: a joint that moved while no events outline its bones where the
     solve puts it (1 - the event support of :mod:`eventcap.analysis.confidence`, growing away from the frames as
     4τ(1 - τ)), times the joint's image displacement carried to its depth;

   - the motion between the frames: the joint's displacement over its interval between two intensity frames
     (relative to the joints' mean, what the rigid alignment leaves; mm), times 4τ(1 - τ) (``motion``: far from a
     detection in time and fast), and as it is (``speed``: fast, at the frames too, where it blurs the image);
     ``between_mm`` the least added half way between two frames, 4τ(1 - τ) · between_mm, however still the joint
     (:func:`motion_mm`);

   - the body: a body estimated from the detections (the body stage) is known only to within its posterior
     (``Template.rest_spread``: independent one-sigma deviations of its rest joints); each carried to the posed
     joints at every frame, less their mean (what the rigid alignment takes away), added as variances
     (:func:`body_mm`), times the ``body`` weight;

3. **Out of view**: a joint outside the image has more than ``unseen_mm`` (its own uncertainty and unseen_mm added as
   variances): nobody saw it. Its place is only known to
   within its uncertainty, so a joint counts as in view only when the ball of its body's depth around it, and of
   ``view_margin`` times its uncertainty, projects inside every edge (:func:`eventcap.analysis.confidence.joints_in_view`):
   a joint the solve puts just inside the edge, where the detector extrapolates a landmark, is not claimed.

The confidence in [0, 1] follows from it (:func:`confidence_of`): 1 / (1 + (u / trusted_mm)²): 0.5 at u =
``trusted_mm``, below it a joint is not trusted (what the outputs mark as such).

Judging an uncertainty (Ilg et al., ECCV 2018, for optical flow): :func:`spearman` (rank correlation of u and the
error), :func:`sparsification` (drop the most uncertain first: the mean error left, against the oracle that drops the
largest errors first; the area between the two curves, AUSE, against a random ranking's), :func:`coverage` (the share
of errors within k u).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from eventcap.body.kinematics import joint_positions, landmark_positions
from eventcap.body.skeleton import NUM_JOINTS, PARENTS
from eventcap.camera import Camera


# --------------------------------------------------------------------------------------------- judging
def _pairs(u, e) -> tuple[np.ndarray, np.ndarray]:
    u, e = np.asarray(u, dtype=np.float64).ravel(), np.asarray(e, dtype=np.float64).ravel()
    if u.shape != e.shape:
        raise ValueError(f"uncertainty and error differ in size: {u.size} and {e.size}")
    ok = np.isfinite(u) & np.isfinite(e)
    return u[ok], e[ok]


def spearman(u, e) -> float:
    """Spearman's rank correlation of the uncertainty and the error over their finite pairs (NaN for fewer than 3)."""
    from scipy.stats import spearmanr

    u, e = _pairs(u, e)
    return float(spearmanr(u, e).statistic) if u.size >= 3 else float("nan")


def sparsification(u, e, steps: int = 50) -> dict:
    """The sparsification curves of an uncertainty: at each fraction f in [0, 1) (``steps`` of them), the mean error
    of what is left after dropping the f most uncertain (``curve``; pairs of equal uncertainty in a fixed random
    order), the f largest errors (``oracle``), or a random f (``random``: the mean error, in
    expectation). ``ause``: the area between curve and oracle; ``ause_random``:
    between random and oracle; ``ratio``: their quotient (1: no better than random, 0: the oracle's order)."""
    u, e = _pairs(u, e)
    n = e.size
    f = np.arange(steps) / steps
    if n == 0:
        nan = np.full(steps, np.nan)
        return {"fraction": f, "curve": nan, "oracle": nan, "random": nan, "ause": np.nan, "ause_random": np.nan,
                "ratio": np.nan}
    keep = np.maximum(n - np.floor(f * n).astype(np.int64), 1)

    def left(order):  # mean of the first `keep` after sorting by order (ascending: the kept ones first)
        c = np.cumsum(e[order])
        return c[keep - 1] / keep

    # ties in u (a floor, a constant) are broken in a fixed random order: neither the oracle's credit nor its
    # opposite, what a random ranking of the tied pairs would give
    curve = left(np.lexsort((np.random.default_rng(0).permutation(n), u)))
    oracle = left(np.argsort(e, kind="stable"))
    random = np.full(steps, e.mean())
    ause, ause_r = float(np.mean(curve - oracle)), float(np.mean(random - oracle))
    return {"fraction": f, "curve": curve, "oracle": oracle, "random": random, "ause": ause,
            "ause_random": ause_r, "ratio": ause / ause_r if ause_r > 0 else float("nan")}


def coverage(u, e, k: float = 2.0) -> float:
    """The share of finite (uncertainty, error) pairs whose error lies within k uncertainties."""
    u, e = _pairs(u, e)
    return float(np.mean(e <= k * u)) if u.size else float("nan")


# --------------------------------------------------------------------------------------------- cues
def _joint_neighbours() -> list[np.ndarray]:
    out = []
    for j in range(NUM_JOINTS):
        nb = list(np.flatnonzero(PARENTS == j))
        if PARENTS[j] >= 0:
            nb.append(int(PARENTS[j]))
        out.append(np.array(sorted(nb), dtype=np.int64))
    return out


_NEIGHBOURS = _joint_neighbours()


def fill_from_neighbours(values: np.ndarray, has: np.ndarray) -> np.ndarray:
    """(D, 24): the joints without a value of their own (``has`` (24,) False) take the mean of their skeleton
    neighbours' (through the neighbours that have one, as spine2 through spine1 and spine3); NaN stays NaN."""
    v = np.array(values, dtype=np.float64)
    has = np.array(has, dtype=bool)
    todo = set(np.flatnonzero(~has).tolist())
    while todo:
        ready = {j: [n for n in _NEIGHBOURS[j] if has[n]] for j in todo}
        ready = {j: nb for j, nb in ready.items() if nb}
        if not ready:
            break
        for j, nb in ready.items():
            x = v[:, nb]
            n = np.isfinite(x).sum(axis=1)
            v[:, j] = np.where(n > 0, np.nansum(x, axis=1) / np.maximum(n, 1), np.nan)
        for j in ready:
            has[j] = True
            todo.discard(j)
    return v


def detection_residuals(template, camera: Camera, poses: np.ndarray, keypoints: np.ndarray, observed: np.ndarray,
                        joints_3d: np.ndarray, confidence_3d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(r2, r3), each (D, 24) mm: how far the detections at D frames are from the estimate there (poses (D, 33)).

    r2: each observed landmark's reprojection residual (keypoints (D, L, 2) px, observed (D, L)) carried to the
    depth of its joint, r_px · z / f (the largest of a joint's landmarks); a joint without a landmark of its own takes
    its neighbours' (:func:`fill_from_neighbours`). r3: the 3D detection (joints_3d (D, 24, 3) root-relative,
    confidence_3d (D, 24)) against the estimate's joints after the best translation (the detected joints' weighted
    mean offset: E_3D's t'). NaN where there is nothing to compare (not detected, no estimate)."""
    P = np.asarray(poses, dtype=np.float64)
    D = P.shape[0]
    r2 = np.full((D, NUM_JOINTS), np.nan)
    r3 = np.full((D, NUM_JOINTS), np.nan)
    est = np.isfinite(P).all(axis=1)
    if not est.any():
        return r2, r3
    Pe = P[est]
    L = landmark_positions(Pe, template)  # (De, L, 3)
    De, nL = L.shape[:2]
    px = camera.project(L.reshape(-1, 3)).reshape(De, nL, 2)
    z = camera.depth(L.reshape(-1, 3)).reshape(De, nL)
    f = 0.5 * (camera.fx + camera.fy)
    kp = np.asarray(keypoints, dtype=np.float64)[est]
    obs = np.asarray(observed, dtype=bool)[est] & np.isfinite(kp).all(-1) & np.isfinite(px).all(-1) & (z > 0.05)
    r_mm = np.where(obs, np.linalg.norm(np.where(obs[..., None], px - kp, 0.0), axis=-1) * z / f * 1000.0, np.nan)
    lj = np.asarray(template.landmark_joint)
    own = np.full((De, NUM_JOINTS), np.nan)
    for k, j in enumerate(lj):
        own[:, j] = np.fmax(own[:, j], r_mm[:, k])
    has = np.zeros(NUM_JOINTS, dtype=bool)
    has[lj] = True
    r2[est] = fill_from_neighbours(own, has)
    J = joint_positions(Pe, template)
    rel = J - J[:, :1]
    j3 = np.asarray(joints_3d, dtype=np.float64)[est]
    c3 = np.asarray(confidence_3d, dtype=np.float64)[est]
    c3 = np.where(np.isfinite(j3).all(-1), c3, 0.0)
    w = c3.sum(axis=1, keepdims=True)
    diff = rel - np.where(c3[..., None] > 0, j3, 0.0)
    t = np.where(w > 0, (c3[..., None] * diff).sum(axis=1) / np.maximum(w, 1e-12), 0.0)  # (De, 3)
    res = np.linalg.norm(diff - t[:, None, :], axis=-1) * 1000.0
    r3[est] = np.where(c3 > 0, res, np.nan)
    return r2, r3


def at_times(t_us: np.ndarray, t_det: np.ndarray, values: np.ndarray) -> np.ndarray:
    """(T, 24) values (D, 24) given at the detection frames t_det (D,), linearly interpolated at t_us (T,) between
    the nearest frames on either side that have one (NaN: none; held beyond the first and last)."""
    t = np.asarray(t_us, dtype=np.float64)
    td = np.asarray(t_det, dtype=np.float64)
    V = np.asarray(values, dtype=np.float64)
    out = np.full((t.size, V.shape[1]), np.nan)
    for j in range(V.shape[1]):
        ok = np.isfinite(V[:, j])
        if ok.any():
            out[:, j] = np.interp(t, td[ok], V[ok, j])
    return out


def between_frames(t_us: np.ndarray, t_det: np.ndarray) -> np.ndarray:
    """(T,) 4τ(1 - τ): 0 at an intensity frame, 1 half way between two (τ the fraction of the interval); 1 beyond
    the first and last frame."""
    t = np.asarray(t_us, dtype=np.float64)
    td = np.asarray(t_det, dtype=np.float64)
    if td.size < 2:
        return np.where(np.isin(t, td), 0.0, 1.0)
    k = np.clip(np.searchsorted(td, t, side="right") - 1, 0, td.size - 2)
    tau = np.clip((t - td[k]) / np.maximum(td[k + 1] - td[k], 1.0), 0.0, 1.0)
    m = 4.0 * tau * (1.0 - tau)
    return np.where((t < td[0]) | (t > td[-1]), 1.0, m)


def event_gap_mm(template, camera: Camera, t_us: np.ndarray, poses: np.ndarray, t_det: np.ndarray,
                 event_support: np.ndarray) -> np.ndarray:
    """(T, 24) mm: how far the events leave each joint unconfirmed between two intensity frames: (1 - e) · 4τ(1 - τ)
    · d, e the event support of its bones (T, 24) in [0, 1], τ the fraction of the interval, d the joint's image
    displacement over the interval in the estimate (between its two frames) carried to its depth (px · z / f, mm).
    0 at the frames; NaN where the motion has no estimate."""
    t = np.asarray(t_us, dtype=np.int64)
    P = np.asarray(poses, dtype=np.float64)
    est = np.isfinite(P).all(axis=1)
    out = np.full((t.size, NUM_JOINTS), np.nan)
    if not est.any():
        return out
    J = joint_positions(np.where(est[:, None], P, 0.0), template)
    z = camera.depth(J.reshape(-1, 3)).reshape(t.size, NUM_JOINTS)
    px = np.full((t.size, NUM_JOINTS, 2), np.nan)
    front = (z > 0.05) & est[:, None]
    px[front] = camera.project(J[front])
    td = np.asarray(t_det, dtype=np.int64)
    td = td[(td >= t[0]) & (td <= t[-1])]
    k = np.searchsorted(t, td)
    d = np.zeros((t.size, NUM_JOINTS))
    if td.size >= 2:
        step = np.linalg.norm(px[k[1:]] - px[k[:-1]], axis=-1)  # (D - 1, 24) px over each interval
        seg = np.clip(np.searchsorted(td, t, side="right") - 1, 0, td.size - 2)
        d = np.nan_to_num(step[seg]) * np.where(z > 0.05, z, np.nan) / (0.5 * (camera.fx + camera.fy)) * 1000.0
    m = between_frames(t, td)[:, None]
    gap = (1.0 - np.clip(np.asarray(event_support, dtype=np.float64), 0.0, 1.0)) * m * np.nan_to_num(d)
    out[est] = gap[est]
    return out


def motion_mm(template, t_us: np.ndarray, poses: np.ndarray, t_det: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(between (T,), step (T, 24) mm): 4τ(1 - τ) at each time (:func:`between_frames`), and each joint's 3D
    displacement over its interval between the two intensity frames around t (t_det; the first or last interval
    beyond them), relative to the joints' mean (the rigid alignment's translation takes the rest away), in the
    estimate; NaN where the motion has no estimate at t or at either frame of its interval."""
    t = np.asarray(t_us, dtype=np.int64)
    P = np.asarray(poses, dtype=np.float64)
    est = np.isfinite(P).all(axis=1)
    step = np.full((t.size, NUM_JOINTS), np.nan)
    td = np.asarray(t_det, dtype=np.int64)
    td = td[(td >= t[0]) & (td <= t[-1])] if t.size else td[:0]
    m = between_frames(t, td)
    k = np.searchsorted(t, td)
    ok = (k < t.size) & (t[np.minimum(k, max(t.size - 1, 0))] == td) if t.size else np.zeros(0, bool)
    k, td = k[ok], td[ok]
    if td.size < 2 or not est.any():
        return m, step
    J = np.full((t.size, NUM_JOINTS, 3), np.nan)
    J[est] = joint_positions(P[est], template)
    rel = J - J.mean(axis=1, keepdims=True)
    d = np.linalg.norm(rel[k[1:]] - rel[k[:-1]], axis=-1) * 1000.0  # (D - 1, 24) mm over each interval
    seg = np.clip(np.searchsorted(td, t, side="right") - 1, 0, td.size - 2)
    step = np.where(est[:, None], d[seg], np.nan)
    return m, step


def body_mm(template, poses: np.ndarray) -> np.ndarray | None:
    """(T, 24) mm: how far each posed joint may lie from where the template's body puts it, given how uncertain the
    body is (``template.rest_spread`` (K, 24, 3): K independent one-sigma deviations of the rest joints): per frame
    (poses (T, 33)) the root-norm over K of each deviation carried through the pose (joint positions are linear in
    the rest joints at given angles), less its mean over the joints (the rigid alignment's translation). None when
    the body is exact (no spread); NaN where a frame has no estimate."""
    spread = getattr(template, "rest_spread", None)
    if spread is None or np.asarray(spread).shape[0] == 0:
        return None
    P = np.asarray(poses, dtype=np.float64)
    est = np.isfinite(P).all(axis=1)
    out = np.full((P.shape[0], NUM_JOINTS), np.nan)
    if not est.any():
        return out
    Pe = P[est]
    rest = np.asarray(template.rest_joints, dtype=np.float64)
    base = joint_positions(Pe, rest)
    var = np.zeros(base.shape[:2])
    for D in np.asarray(spread, dtype=np.float64):
        d = joint_positions(Pe, rest + D) - base
        d = d - d.mean(axis=1, keepdims=True)
        var += np.sum(d * d, axis=-1)
    out[est] = np.sqrt(var) * 1000.0
    return out


def joined_sigma(parts, t_us: np.ndarray) -> np.ndarray | None:
    """(T, 24) the per-batch pose sequences' ``sigma_mm`` at the joined motion's times t_us (a time two batches hold:
    the later batch's, as :func:`eventcap.analysis.motion.join_batches` with ``later``); NaN where a batch has none;
    None when no batch has one."""
    if all(getattr(p, "sigma_mm", None) is None for p in parts):
        return None
    t_all = np.asarray(t_us, dtype=np.int64)
    out = np.full((t_all.size, NUM_JOINTS), np.nan)
    for p in sorted((p for p in parts if np.asarray(p.t_us).size), key=lambda p: int(p.t_us[0])):
        k = np.searchsorted(t_all, np.asarray(p.t_us, dtype=np.int64))
        out[k] = np.nan if p.sigma_mm is None else np.asarray(p.sigma_mm, dtype=np.float64)
    return out


# --------------------------------------------------------------------------------------------- the uncertainty
@dataclass(frozen=True)
class UncertaintyModel:
    """How the uncertainty is made (module doc): ``scale`` of the solve's σ_L; the weights of the detections' 2D and
    3D residuals and of the events' missing support; ``unseen_mm`` the least uncertainty of a joint out of view;
    ``floor_mm`` the least of any joint; ``fallback_mm`` σ_L's stand-in where the solve gives none; ``body`` the
    weight of the body's own uncertainty (:func:`body_mm`); ``motion`` and ``speed`` the weights of the joint's
    displacement between the frames, away from them and everywhere, ``between_mm`` what is added half way between two
    frames (:func:`motion_mm`)."""

    scale: float
    detection_2d: float
    detection_3d: float
    events: float
    unseen_mm: float
    floor_mm: float
    fallback_mm: float
    body: float = 1.0
    motion: float = 0.0
    speed: float = 0.0
    between_mm: float = 0.0


#: the settings a calibration states (per detector kind), besides where it comes from
CALIBRATED = ("scale", "detection_2d", "detection_3d", "events", "motion", "speed", "between_mm", "floor_mm",
              "trusted_mm", "unseen_mm")


def detector_kind(detector: str) -> str:
    """The kind of detector a Detections artifact's ``detector`` text names: the word before its first colon
    (``simulated``, ``blazepose``, ``file``); '' when it names none."""
    head, sep, _ = str(detector or "").partition(":")
    return head.strip().lower() if sep else ""


def calibration(table: dict, kind: str) -> tuple[str, dict]:
    """(the entry used, its settings) of a calibration table (``{"detectors": {kind: {setting: value, ...,
    "source": text}}, "default": kind}``) for a detector kind: the kind's own entry, else the table's ``default``
    (a detector nobody calibrated, e.g. detections from a file). ValueError naming the entry and the setting when
    one is missing or not a number >= 0."""
    dets = table.get("detectors") or {}
    name = kind if kind in dets else str(table.get("default", ""))
    if name not in dets:
        raise ValueError(f"the uncertainty's calibration table has no entry for detector kind {kind!r} and no "
                         f"default entry (its entries: {', '.join(sorted(dets)) or 'none'})")
    entry = dets[name]
    out = {}
    for key in CALIBRATED:
        v = entry.get(key)
        if not isinstance(v, (int, float)) or isinstance(v, bool) or not np.isfinite(v) or v < 0:
            raise ValueError(f"the uncertainty's calibration for detector kind {name!r}: {key} must be a number >= 0, "
                             f"got {v!r}")
        out[key] = float(v)
    if out["scale"] <= 0 or out["trusted_mm"] <= 0:
        raise ValueError(f"the uncertainty's calibration for detector kind {name!r}: scale and trusted_mm must be > 0")
    by_fps = entry.get("factor_by_fps", {})
    points = []
    if not isinstance(by_fps, dict):
        raise ValueError(f"the uncertainty's calibration for detector kind {name!r}: factor_by_fps must be an object "
                         f"{{frames per second: factor}}, got {by_fps!r}")
    for k, v in by_fps.items():
        try:
            fps = float(k)
        except ValueError:
            fps = float("nan")
        if not (np.isfinite(fps) and fps > 0 and _positive(v)):
            raise ValueError(f"the uncertainty's calibration for detector kind {name!r}: factor_by_fps expects frame "
                             f"rates > 0 as keys and factors > 0, got {k!r}: {v!r}")
        points.append((fps, float(v)))
    out["factor_by_fps"] = sorted(points)
    by_view = entry.get("factor_by_view", {})
    for k, v in by_view.items() if isinstance(by_view, dict) else [(by_view, None)]:
        if k not in VIEWS or not _positive(v):
            raise ValueError(f"the uncertainty's calibration for detector kind {name!r}: factor_by_view expects a "
                             f"view ({', '.join(VIEWS)}) as key and a factor > 0, got {k!r}")
    out["factor_by_view"] = {k: float(v) for k, v in by_view.items()}
    return name, out


def _positive(v) -> bool:
    """Whether a table's value is a finite number > 0 (not a bool)."""
    return isinstance(v, (int, float)) and not isinstance(v, bool) and bool(np.isfinite(v)) and v > 0


#: the calibrated settings a frame rate's factor multiplies (the uncertainty's parts; not where it is trusted)
RATE_SCALED = ("scale", "detection_2d", "detection_3d", "events", "motion", "speed", "between_mm", "floor_mm")


def rate_factor(points: list[tuple[float, float]], fps: float | None) -> float:
    """The calibration's factor at a capture's frame rate: linear in log(fps) between the rates it was calibrated
    at (``factor_by_fps``), the nearest one's beyond them; 1 when it states none or the capture has no intensity
    frames (fps None: the kind's pooled calibration)."""
    if not points or fps is None or not np.isfinite(fps) or fps <= 0:
        return 1.0
    x = np.log([p[0] for p in points])
    return float(np.interp(np.log(fps), x, [p[1] for p in points]))


#: the views the uncertainty is calibrated apart for (:func:`view_of`): with intensity frames and most of the body in
#: the image, a close-up (much of the body out of the image), a camera without intensity frames
VIEWS = ("whole_frames", "close_up", "event_only")
#: below this share of the joints in the image (over the estimated frames) a capture with frames is a close-up
CLOSE_UP_SHARE = 0.8


def view_of(fps: float | None, in_image_share: float) -> str:
    """The view a capture's uncertainty is calibrated for (:data:`VIEWS`), from what the method sees: no intensity
    frames (fps None) is ``event_only``; with frames, less than :data:`CLOSE_UP_SHARE` of the joints inside the
    image over the estimated frames is a ``close_up``; else ``whole_frames``."""
    if fps is None or not np.isfinite(fps) or fps <= 0:
        return "event_only"
    return "close_up" if in_image_share < CLOSE_UP_SHARE else "whole_frames"


def frame_rate(t_us) -> float | None:
    """Intensity frames per second from their times (the median interval); None for fewer than 2 frames."""
    t = np.asarray(t_us, dtype=np.int64)
    if t.size < 2:
        return None
    d = float(np.median(np.diff(np.sort(t))))
    return 1e6 / d if d > 0 else None


def joint_uncertainty(model: UncertaintyModel, sigma_mm: np.ndarray | None, r2_mm: np.ndarray, r3_mm: np.ndarray,
                      event_gap_mm: np.ndarray, estimated: np.ndarray, body_mm: np.ndarray | None = None,
                      between: np.ndarray | None = None, step_mm: np.ndarray | None = None) -> np.ndarray:
    """(T, 24) the uncertainty (mm; module doc, 1-2) from σ_L (T, 24; None or NaN: ``fallback_mm``), the detections'
    residuals at the frames interpolated in time (T, 24, mm; NaN: none), the events' missing support carried to mm
    (T, 24), whether each frame has an estimate (T,): NaN where not, the body's own uncertainty (T, 24, mm;
    None: an exact body), and the motion between the frames (:func:`motion_mm`: 4τ(1 - τ) (T,) and the joints'
    displacement over the interval (T, 24) mm; None: left out). Out of view: :func:`out_of_view`."""
    T = np.asarray(estimated).shape[0]
    sig = np.full((T, NUM_JOINTS), np.nan) if sigma_mm is None else np.asarray(sigma_mm, dtype=np.float64)
    var = np.where(np.isfinite(sig), model.scale * sig, model.fallback_mm) ** 2
    var = var + (model.detection_2d * np.nan_to_num(r2_mm)) ** 2 + (model.detection_3d * np.nan_to_num(r3_mm)) ** 2
    var = var + (model.events * np.nan_to_num(event_gap_mm)) ** 2 + model.floor_mm ** 2
    if body_mm is not None:
        var = var + (model.body * np.nan_to_num(np.asarray(body_mm, dtype=np.float64))) ** 2
    if between is not None:
        m = np.asarray(between, dtype=np.float64)[:, None]
        var = var + (model.between_mm * m) ** 2
        if step_mm is not None:
            d = np.nan_to_num(np.asarray(step_mm, dtype=np.float64))
            var = var + (model.motion * m * d) ** 2 + (model.speed * d) ** 2
    return np.where(np.asarray(estimated, dtype=bool)[:, None], np.sqrt(var), np.nan)


def out_of_view(u_mm: np.ndarray, in_view: np.ndarray, unseen_mm: float) -> np.ndarray:
    """The uncertainty (T, 24) with every joint out of view (in_view (T, 24) False) raised above unseen_mm: its own
    uncertainty and unseen_mm added as variances, so that joints out of view still rank among themselves by their
    own (module doc, 3; a floor made them all alike); NaN stays NaN."""
    u = np.asarray(u_mm, dtype=np.float64)
    return np.where(np.asarray(in_view, dtype=bool) | ~np.isfinite(u), u, np.hypot(u, unseen_mm))


def confidence_of(u_mm: np.ndarray, trusted_mm: float) -> np.ndarray:
    """Confidence in [0, 1] from the uncertainty (module doc): 1 / (1 + (u / trusted_mm)²); 0 where u is NaN (a
    gap)."""
    u = np.asarray(u_mm, dtype=np.float64)
    return np.where(np.isfinite(u), 1.0 / (1.0 + (np.nan_to_num(u) / trusted_mm) ** 2), 0.0)


__all__ = ["CALIBRATED", "CLOSE_UP_SHARE", "UncertaintyModel", "VIEWS", "at_times", "between_frames", "body_mm",
           "calibration", "confidence_of", "coverage", "detection_residuals", "detector_kind", "event_gap_mm",
           "fill_from_neighbours", "frame_rate", "joined_sigma", "joint_uncertainty", "motion_mm", "out_of_view",
           "rate_factor", "sparsification", "spearman", "view_of"]
