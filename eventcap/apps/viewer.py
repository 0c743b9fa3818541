"""An interactive recording of a run for the Rerun viewer: everything the run saw and produced, on its time axis.

``capture.rrd`` (written by ``outputs.rerun=true`` after a run, or by ``eventcap view RUN_DIR`` into the view cache,
:func:`view_cache_dir`) holds, on the timeline ``t_us`` (the run's own time axis, microseconds, shown as a duration):

=====================================  ===========================================================================
entity                                 what
=====================================  ===========================================================================
``world/camera``                       the event camera's pose (world -> camera) and pinhole; its image plane is
                                       ``world/camera/image`` (2D, distorted pixel coordinates as the sensor sees)
``world/camera/image/frame``           the intensity frames (motion-blurred), at their exposure centres
``world/camera/image/latent``          the sharpened (EDI) latent images, drawn over the frames
``world/camera/image/events``          event images: the pixels with events in the last ``rerun_events_ms``, as
                                       points coloured by their net polarity (red +, blue -)
``world/camera/image/detections``      the 2D detections (BODY_25 key points), at the intensity frames
``world/camera/image/tracks``          the sliced feature tracks at every tracking frame (one colour per track)
``world/camera/image/silhouette``      the template's silhouette outline at the estimated pose (every 5 ms)
``world/camera/image/skeleton``        the estimated skeleton projected (and ``.../truth`` the ground truth)
``world/skeleton/estimate``            the 3D skeleton at every tracking frame (1 kHz), joint names on hover
``world/skeleton/truth``               the ground-truth 3D skeleton (synthetic captures)
``speed/estimate/<joint>``             end-effector speeds (m/s, central differences over +-5 ms), and
``speed/truth/<joint>``                the same of the ground truth
``error/mean_joint_error_mm``          the evaluation's per-frame mean joint error, when the run has one
``batches/plan``                       the batch index (a step at every batch boundary)
``batches/<node>``                     per batch of every per-batch node: a log line (committed, solver status,
                                       iterations; failures as errors) at the batch start; ``.../iterations``
=====================================  ===========================================================================

What would not fit is decimated and the log says so: event images (one every ``rerun_every_ms``) and silhouette
outlines (one every ``rerun_outline_every_ms``, 5 ms by default: each is a rasterization of the mesh, ~10-40 ms here;
the viewer shows the latest outline until the next) are drawn at most ``rerun_max_frames`` times each (the step widens
evenly over the run, as the overlay video's frames do); the 3D skeleton, the projected skeleton, the tracks and the
speeds are kept at every tracking frame.

This module is an app layer below :mod:`eventcap.apps.outputs`, which calls it (``outputs.rerun=true``, and
:func:`eventcap.apps.outputs.build_run_recording` for ``eventcap view``): it is handed a runner and its result, reads the
run's outputs through them (:meth:`Runner.load_output`), and imports neither the outputs, the runner nor a plugin. Rerun is an optional dependency (``rerun-sdk``, ~500 MB
with its viewer): without it, :func:`require_rerun` says what to install.
"""

from __future__ import annotations

import logging
import os
import shutil
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger("eventcap.apps.viewer")

RRD_NAME = "capture.rrd"
TIMELINE = "t_us"
#: joints whose speed is plotted (end effectors and the head)
SPEED_JOINTS = ("l_wrist", "r_wrist", "l_ankle", "r_ankle", "head")
SPEED_HALF_WINDOW_US = 5000  # central differences over +-5 ms (10 ms), as the project's velocity errors
#: OpenPose BODY_25 limbs (pairs of key point indices, the order of skeleton.LANDMARK_NAMES)
BODY25_LIMBS = ((1, 8), (1, 2), (1, 5), (2, 3), (3, 4), (5, 6), (6, 7), (8, 9), (9, 10), (10, 11), (8, 12), (12, 13),
                (13, 14), (1, 0), (0, 15), (15, 17), (0, 16), (16, 18), (14, 19), (19, 20), (14, 21), (11, 22),
                (22, 23), (11, 24))
#: annotation classes (colours and skeleton connections for key points)
CLASS_ESTIMATE, CLASS_TRUTH, CLASS_DETECTION, CLASS_POSITIVE, CLASS_NEGATIVE = 1, 2, 3, 4, 5
GREEN, GREY, ORANGE, YELLOW = (60, 200, 60), (170, 170, 170), (255, 150, 30), (255, 230, 0)

INSTALL_HINT = 'pip install rerun-sdk (or: pip install -e ".[viewer]")'


def require_rerun():
    """The ``rerun`` module, or an ImportError saying what to install."""
    try:
        import rerun
    except ImportError:
        raise ImportError(f"the Rerun viewer is not installed: {INSTALL_HINT}") from None
    return rerun


# ---------------------------------------------------------------------------------------------------------------------
# What a recording shows
# ---------------------------------------------------------------------------------------------------------------------
@dataclass
class RunContent:
    """The pieces of a finished run a recording shows (all but the motion are optional)."""

    t_us: np.ndarray | None = None  # (T,) the motion's frames
    poses: np.ndarray | None = None  # (T, 33)
    joints: np.ndarray | None = None  # (T, 24, 3) metres
    motion_from: str = ""  # node.port of the poses
    rec: Any = None  # Recording
    template: Any = None
    latent: Any = None  # LatentFrames
    detections: Any = None  # Detections
    sliced: dict[int, Any] = field(default_factory=dict)  # batch -> SlicedTracks
    plan: Any = None  # BatchPlan
    pose_nodes: dict[str, dict[int, Any]] = field(default_factory=dict)  # per-batch node -> batch -> PoseSequence
    batch_nodes: dict[str, dict[str, Any]] = field(default_factory=dict)  # per-batch node -> committed/failed batches
    errors: Any = None  # JointErrors
    confidence: np.ndarray | None = None  # (T, 24) in [0, 1] at the motion's frames (eventcap.analysis.uncertainty)
    uncertainty_mm: np.ndarray | None = None  # (T, 24) mm at the motion's frames (NaN: none)
    name: str = ""


def collect_run_content(runner, result, t_us=None, poses=None, joints=None, rec=None, template=None, latent=None,
                        motion_from: str = "") -> RunContent:
    """What a recording of this run shows: the motion and artifacts :mod:`eventcap.apps.outputs` already loaded (passed
    in), the rest found by type among the run's committed outputs."""
    from eventcap.artifacts import BatchPlan
    from eventcap.artifacts.pose import Detections, JointErrors, PoseSequence
    from eventcap.artifacts.tracking import SlicedTracks

    c = RunContent(t_us=t_us, poses=poses, joints=joints, motion_from=motion_from, rec=rec, template=template,
                   latent=latent, name=str(runner.cfg.get("name") or ""))
    for node in runner.nodes:
        rep = result.nodes.get(node.name)
        if rep is None:
            continue
        for port, p in node.spec.outputs.items():
            if node.spec.per_batch:
                if issubclass(p.type, PoseSequence):
                    c.pose_nodes[node.name] = runner.load_output(result, f"{node.name}.{port}")
                elif issubclass(p.type, SlicedTracks) and not c.sliced:
                    c.sliced = runner.load_output(result, f"{node.name}.{port}")
                continue
            want = [(BatchPlan, "plan"), (Detections, "detections"), (JointErrors, "errors")]
            for cls, attr in want:
                if issubclass(p.type, cls) and getattr(c, attr) is None:
                    got = runner.load_output(result, f"{node.name}.{port}")
                    setattr(c, attr, got.get(None))
        if node.spec.per_batch:
            c.batch_nodes[node.name] = {"stage": node.spec.name, "committed": sorted(result.committed(node.name)),
                                        "failed": {f["batch"]: f for f in rep.failed if f.get("batch") is not None},
                                        "skipped": rep.skipped}
    return c


# ---------------------------------------------------------------------------------------------------------------------
# Writing the recording
# ---------------------------------------------------------------------------------------------------------------------
def _times(rr, t_us) -> list:
    return [rr.TimeColumn(TIMELINE, duration=np.asarray(t_us, dtype=np.int64).astype("timedelta64[us]"))]


def _set_time(rec_stream, t_us: int) -> None:
    rec_stream.set_time(TIMELINE, duration=np.timedelta64(int(t_us), "us"))


def decimated(t_us: np.ndarray, every_ms: float, max_frames: int) -> np.ndarray:
    """Indices into the motion frames ``t_us``: one every ``every_ms`` of motion time, at most ``max_frames`` (the step
    widens evenly over the whole motion); the same rule as the overlay video's frames."""
    from eventcap.analysis.motion import frames_every

    return frames_every(t_us, every_ms, max_frames)[0]


def speeds(t_us: np.ndarray, joints: np.ndarray, half_window_us: int = SPEED_HALF_WINDOW_US
           ) -> tuple[np.ndarray, np.ndarray]:
    """Joint speeds (m/s) by central differences ``|J(t+h) - J(t-h)| / 2h`` at the frames whose ``t +- h`` are both
    frames of the motion (gaps and the ends drop out): (indices (K,), speeds (K, joints))."""
    t = np.asarray(t_us, dtype=np.int64)
    lo = np.searchsorted(t, t - half_window_us)
    hi = np.searchsorted(t, t + half_window_us)
    lo_c, hi_c = np.minimum(lo, t.size - 1), np.minimum(hi, t.size - 1)
    ok = (t[lo_c] == t - half_window_us) & (t[hi_c] == t + half_window_us)
    idx = np.flatnonzero(ok)
    d = joints[hi_c[idx]] - joints[lo_c[idx]]
    return idx, np.linalg.norm(d, axis=-1) / (2 * half_window_us * 1e-6)


def event_image(events: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """An event window as a sparse image: the pixels whose events do not cancel, ``(xy (K, 2) pixel centres,
    sign (K,) +1/-1 of the net polarity)``, at most one point per pixel however many events it had."""
    flat = events["y"].astype(np.int64) * width + events["x"].astype(np.int64)
    acc = np.bincount(flat, weights=events["p"].astype(np.float64), minlength=height * width)
    k = np.flatnonzero(acc)
    return np.stack([k % width, k // width], axis=1).astype(np.float32), np.sign(acc[k]).astype(np.int8)


def silhouette_outline(camera, template, S: np.ndarray) -> list[np.ndarray]:
    """The outline of the template at pose ``S`` in the camera image: closed pixel polylines (outer and inner
    contours of the rasterized silhouette)."""
    import cv2

    from eventcap.body.kinematics import skin
    from eventcap.imaging.render import rasterize

    _, tri_id, _ = rasterize(camera, skin(S, template), template.faces)
    mask = (tri_id >= 0).astype(np.uint8)
    contours, _ = cv2.findContours(mask, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_SIMPLE)
    out = []
    for c in contours:
        p = c[:, 0, :].astype(np.float32)
        if len(p) >= 2:
            out.append(np.vstack([p, p[:1]]))
    return out


def _palette(ids: np.ndarray) -> np.ndarray:
    """A stable colour per track id (golden-angle hues)."""
    import colorsys

    hues = (np.asarray(ids, dtype=np.float64) * 0.618033988749895) % 1.0
    return np.array([[int(255 * v) for v in colorsys.hsv_to_rgb(h, 0.8, 1.0)] for h in hues], np.uint8)


def _blueprint(rrb, has_speed: bool):
    top = rrb.Horizontal(rrb.Spatial2DView(origin="world/camera/image", name="camera image"),
                         rrb.Spatial3DView(origin="world", name="3D"), column_shares=[3, 2])
    bottom = [rrb.TimeSeriesView(origin="speed", name="end-effector speed (m/s)")] if has_speed else []
    bottom += [rrb.TimeSeriesView(origin="error", name="joint error (mm)"),
               rrb.TimeSeriesView(origin="uncertainty", name="joint uncertainty (mm)"),
               rrb.TextDocumentView(origin="legend", name="joint colours"),
               rrb.TextLogView(origin="batches", name="batches")]
    return rrb.Blueprint(rrb.Vertical(top, rrb.Horizontal(*bottom), row_shares=[3, 2]), collapse_panels=True)


def write_recording(path, content: RunContent, events_ms: float = 1.0, every_ms: float = 1.0,
                    max_frames: int = 2000, outline_every_ms: float = 5.0) -> dict[str, Any]:
    """Write ``content`` as a Rerun recording at ``path`` (atomically: ``<stem>.partial.rrd``, then renamed); returns
    what it holds (counts per layer, what was decimated, seconds, bytes)."""
    rr = require_rerun()
    import rerun.blueprint as rrb

    from eventcap.body.skeleton import JOINT_INDEX, JOINT_NAMES, LANDMARK_NAMES, PARENTS

    path = Path(path)
    tmp = path.with_name(path.stem + ".partial.rrd")
    tmp.unlink(missing_ok=True)
    path.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    stats: dict[str, Any] = {"counts": {}, "decimated": {}}
    counts = stats["counts"]
    rec = content.rec
    has_speed = content.joints is not None and content.t_us is not None and content.t_us.size > 2
    stream = rr.RecordingStream("eventcap", recording_id=content.name or None, send_properties=False)
    try:
        stream.save(tmp, default_blueprint=_blueprint(rrb, has_speed))
        _log_static(rr, stream, content, JOINT_NAMES, LANDMARK_NAMES, PARENTS)
        if rec is not None:
            _log_images(rr, stream, content, counts)
            if content.t_us is not None:
                _log_event_images(rr, stream, content, events_ms, every_ms, max_frames, stats)
            else:
                _log_event_images_plain(rr, stream, content, events_ms, max_frames, stats)
            _log_detections(rr, stream, content, counts)
            _log_tracks(rr, stream, content, counts)
        if content.t_us is not None and content.joints is not None:
            _log_motion(rr, stream, content, counts)
            if rec is not None and content.template is not None and content.poses is not None:
                _log_silhouettes(rr, stream, content, outline_every_ms, max_frames, stats)
            _log_speeds(rr, stream, content, JOINT_INDEX, counts)
        _log_truth(rr, stream, content, counts)
        _log_errors(rr, stream, content, counts)
        _log_batches(rr, stream, content, counts)
        stream.flush()
        stream.disconnect()
        os.replace(tmp, path)
    except BaseException:
        try:
            stream.disconnect()
        finally:
            tmp.unlink(missing_ok=True)
        raise
    stats["seconds"] = round(time.perf_counter() - t0, 3)
    stats["bytes"] = path.stat().st_size
    if content.t_us is not None and content.t_us.size > 1:
        span_s = (int(content.t_us[-1]) - int(content.t_us[0])) * 1e-6
        stats["MB_per_s_of_capture"] = round(stats["bytes"] / 1e6 / span_s, 3) if span_s > 0 else None
    log.info("viewer: wrote %s (%.1f MB in %.1f s): %s", path, stats["bytes"] / 1e6, stats["seconds"],
             ", ".join(f"{k} {v}" for k, v in counts.items()))
    return stats


def _log_static(rr, s, c: RunContent, JOINT_NAMES, LANDMARK_NAMES, PARENTS) -> None:
    bones = [(int(p), j) for j, p in enumerate(PARENTS) if p >= 0]
    joints = [rr.AnnotationInfo(id=i, label=n) for i, n in enumerate(JOINT_NAMES)]
    marks = [rr.AnnotationInfo(id=i, label=n) for i, n in enumerate(LANDMARK_NAMES)]
    s.log("/", rr.AnnotationContext([
        rr.ClassDescription(info=rr.AnnotationInfo(CLASS_ESTIMATE, "estimate", GREEN),
                            keypoint_annotations=joints, keypoint_connections=bones),
        rr.ClassDescription(info=rr.AnnotationInfo(CLASS_TRUTH, "ground truth", GREY),
                            keypoint_annotations=joints, keypoint_connections=bones),
        rr.ClassDescription(info=rr.AnnotationInfo(CLASS_DETECTION, "detection (BODY_25)", ORANGE),
                            keypoint_annotations=marks, keypoint_connections=list(BODY25_LIMBS)),
        rr.ClassDescription(info=rr.AnnotationInfo(CLASS_POSITIVE, "positive events", (235, 50, 50))),
        rr.ClassDescription(info=rr.AnnotationInfo(CLASS_NEGATIVE, "negative events", (30, 120, 235))),
    ]), static=True)
    s.log("world", rr.ViewCoordinates.RIGHT_HAND_Y_UP, static=True)  # the run's world: metres, y up
    if c.rec is not None:
        cam = c.rec.camera
        s.log("world/camera", rr.Transform3D(translation=np.asarray(cam.t), mat3x3=np.asarray(cam.R),
                                             relation=rr.TransformRelation.ChildFromParent), static=True)
        depth = 1.0  # the image plane in the 3D view: at the actor's distance, so the projections meet the skeleton
        if c.joints is not None and c.joints.size:
            depth = float(np.median(cam.depth(c.joints.reshape(-1, 3))))
        s.log("world/camera/image", rr.Pinhole(image_from_camera=np.asarray(cam.K), resolution=[cam.width, cam.height],
                                               camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=depth),
              static=True)


def _log_images(rr, s, c: RunContent, counts) -> None:
    frames = c.rec.frames
    if frames is not None and frames.t_us.size:
        for t, img in zip(frames.t_us, frames.images):
            _set_time(s, t)
            s.log("world/camera/image/frame", rr.Image(_gray8(img), draw_order=-20.0))
        counts["intensity frames"] = int(frames.t_us.size)
    lat = c.latent
    if lat is not None and lat.t_us.size:
        for t, li in zip(lat.t_us, lat.log_images):
            img = np.clip(np.exp(li.astype(np.float64)) - lat.eps, 0.0, 1.0)
            _set_time(s, t)
            s.log("world/camera/image/latent", rr.Image(_gray8(img), draw_order=-10.0))
        counts["latent images"] = int(lat.t_us.size)


def _gray8(img: np.ndarray) -> np.ndarray:
    return (np.clip(np.asarray(img, dtype=np.float64), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def _event_windows(rr, s, ev_stream, ends: np.ndarray, window_us: int, h: int, w: int) -> tuple[int, int]:
    """One sparse event image per window ending at each of ``ends``, sent as columns: (images, points)."""
    xys, classes, lengths = [], [], []
    for t in ends:
        xy, sign = event_image(ev_stream.window(int(t) - window_us, int(t) + 1), h, w)
        xys.append(xy)
        classes.append(np.where(sign > 0, CLASS_POSITIVE, CLASS_NEGATIVE).astype(np.uint16))
        lengths.append(xy.shape[0])
    if not lengths:
        return 0, 0
    xy, cls = np.concatenate(xys), np.concatenate(classes)
    rr.send_columns("world/camera/image/events", indexes=_times(rr, ends),
                    columns=[*rr.Points2D.columns(positions=xy, class_ids=cls, radii=np.full(cls.size, 0.5, np.float32),
                                                  draw_order=np.zeros(cls.size, np.float32),
                                                  show_labels=np.zeros(cls.size, bool)).partition(lengths)],
                    recording=s)
    return len(lengths), int(cls.size)


def _log_event_images(rr, s, c: RunContent, events_ms, every_ms, max_frames, stats) -> None:
    window_us = max(1, int(round(events_ms * 1000)))
    idx = decimated(c.t_us, every_ms, max_frames)
    full = decimated(c.t_us, every_ms, 10**12).size
    if idx.size < full:
        stats["decimated"]["event images"] = f"{idx.size} of {full}"
        log.info("viewer: event images decimated: %d of %d (rerun_max_frames=%d); each shows the last %g ms",
                 idx.size, full, max_frames, events_ms)
    n, k = _event_windows(rr, s, c.rec.events, c.t_us[idx], window_us, c.rec.height, c.rec.width)
    stats["counts"]["event images"], stats["counts"]["event pixels"] = n, k


def _log_event_images_plain(rr, s, c: RunContent, events_ms, max_frames, stats) -> None:
    """Without a motion (no poses): consecutive windows over the whole event stream, at most ``max_frames``."""
    ev = c.rec.events.events
    if ev.size == 0:
        return
    window_us = max(1, int(round(events_ms * 1000)))
    ends = np.arange(int(ev["t"][0]) + window_us, int(ev["t"][-1]) + window_us, window_us, dtype=np.int64)
    if ends.size > max_frames:
        stats["decimated"]["event images"] = f"{max_frames} of {ends.size}"
        log.info("viewer: event images decimated: %d of %d windows", max_frames, ends.size)
        ends = ends[np.unique(np.linspace(0, ends.size - 1, max_frames).round().astype(int))]
    n, k = _event_windows(rr, s, c.rec.events, ends, window_us, c.rec.height, c.rec.width)
    stats["counts"]["event images"], stats["counts"]["event pixels"] = n, k


def _log_detections(rr, s, c: RunContent, counts) -> None:
    d = c.detections
    if d is None or d.t_us.size == 0:
        return
    n = 0
    for t, kp, conf in zip(d.t_us, d.keypoints_2d, d.confidence_2d):
        seen = (conf > 0) & np.all(np.isfinite(kp), axis=1)
        _set_time(s, t)
        s.log("world/camera/image/detections",
              rr.Points2D(kp[seen], keypoint_ids=np.flatnonzero(seen), class_ids=CLASS_DETECTION,
                          radii=0.8 + 0.7 * conf[seen], draw_order=20.0, show_labels=False))
        n += int(seen.sum())
    counts["detection frames"] = int(d.t_us.size)
    counts["detected key points"] = n


def _log_tracks(rr, s, c: RunContent, counts) -> None:
    n_frames = n_points = 0
    for b in sorted(c.sliced):
        sl = c.sliced[b]
        valid = sl.valid & np.all(np.isfinite(sl.xy), axis=-1)
        lengths = valid.sum(axis=1)
        xy = sl.xy[valid]
        ids = np.broadcast_to(sl.track_id[None, :], valid.shape)[valid]
        rr.send_columns("world/camera/image/tracks", indexes=_times(rr, sl.t_us),
                        columns=[*rr.Points2D.columns(positions=xy, colors=_palette(ids),
                                                      radii=np.full(xy.shape[0], 1.2, np.float32)
                                                      ).partition(lengths)],
                        recording=s)
        n_frames += int(sl.t_us.size)
        n_points += int(xy.shape[0])
    if n_frames:
        counts["track frames"] = n_frames
        counts["track points"] = n_points


def _keypoint_columns(rr, cls, P: np.ndarray, class_id: int, draw_order: float | None = None,
                      uncertainty_mm: np.ndarray | None = None) -> list:
    """Columns of (T, K, dims) key points, one row of K per time; coloured by their uncertainty (T, K) mm when given
    (eventcap.imaging.viz.uncertainty_rgb; the legend: :func:`_log_legend`)."""
    from eventcap.imaging.viz import uncertainty_rgb

    T, K = P.shape[:2]
    kw = {"draw_order": np.full(T * K, draw_order, np.float32)} if draw_order is not None else {}
    if uncertainty_mm is not None:
        kw["colors"] = uncertainty_rgb(np.asarray(uncertainty_mm).reshape(-1))
    cols = cls.columns(positions=P.reshape(T * K, -1), class_ids=np.full(T * K, class_id, np.uint16),
                       keypoint_ids=np.tile(np.arange(K, dtype=np.uint16), T), show_labels=np.zeros(T * K, bool),
                       **kw)
    return [*cols.partition(np.full(T, K))]


def _log_legend(rr, s) -> None:
    """What the estimate's joint colours mean (a text panel): the uncertainty's colour stops."""
    from eventcap.imaging.viz import UNCERTAINTY_STOPS, UNKNOWN_RGB

    def swatch(rgb):
        return "#%02x%02x%02x" % tuple(rgb)

    rows = "\n".join(f"| {mm:g} mm | {swatch(rgb)} |" for mm, rgb in UNCERTAINTY_STOPS)
    text = ("## Joint colours: the uncertainty\n\nEach joint of the estimate is coloured by its uncertainty (the RMS 3D "
            "distance to the truth one expects, calibrated: within 2 of it 90-97 % of the time; `uncertainty_mm` in "
            "motion.npz), log-interpolated between these colours:\n\n| uncertainty | colour |\n|---|---|\n" + rows +
            f"\n| none (a gap) | {swatch(UNKNOWN_RGB)} |\n\nAbove trusted_mm (calibrated per detector kind: "
            "plugins/eventcap_confidence/calibration.json, or stages.confidence.trusted_mm) a joint is not trusted "
            "(confidence < 0.5).")
    s.log("legend", rr.TextDocument(text, media_type=rr.MediaType.MARKDOWN), static=True)


def _log_motion(rr, s, c: RunContent, counts) -> None:
    T = c.t_us.size
    conf, unc = c.confidence, c.uncertainty_mm
    rr.send_columns("world/skeleton/estimate", indexes=_times(rr, c.t_us),
                    columns=_keypoint_columns(rr, rr.Points3D, c.joints, CLASS_ESTIMATE, uncertainty_mm=unc),
                    recording=s)
    counts["3D skeleton frames"] = T
    if conf is not None:  # how much of the motion was seen: the share of joints observed, per frame
        rr.send_columns("confidence/observed_share", indexes=_times(rr, c.t_us),
                        columns=rr.Scalars.columns(scalars=(np.asarray(conf) >= 0.5).mean(axis=1)), recording=s)
        counts["confidence frames"] = T
    if unc is not None:  # the joints' uncertainty: its median and largest per frame, and the colours' legend
        u = np.asarray(unc, dtype=np.float64)
        ok = np.isfinite(u).any(axis=1)
        for what, f in (("median", np.nanmedian), ("largest", np.nanmax)):
            rr.send_columns(f"uncertainty/{what}_mm", indexes=_times(rr, c.t_us[ok]),
                            columns=rr.Scalars.columns(scalars=f(u[ok], axis=1)), recording=s)
        _log_legend(rr, s)
        counts["uncertainty frames"] = int(ok.sum())
    if c.rec is not None:
        px = c.rec.camera.project(c.joints.reshape(-1, 3)).reshape(T, -1, 2)
        ok = np.all(np.isfinite(px), axis=(1, 2))
        rr.send_columns("world/camera/image/skeleton", indexes=_times(rr, c.t_us[ok]),
                        columns=_keypoint_columns(rr, rr.Points2D, px[ok], CLASS_ESTIMATE, 30.0,
                                                  None if unc is None else np.asarray(unc)[ok]), recording=s)
        counts["projected skeleton frames"] = int(ok.sum())


def _truth_on(gt, t_us: np.ndarray) -> np.ndarray:
    """Ground-truth joints at the motion's frame times (linear between its samples), NaN outside its span."""
    out = np.full((t_us.size, 24, 3), np.nan)
    inside = (t_us >= gt.t_us[0]) & (t_us <= gt.t_us[-1])
    tt = t_us[inside].astype(np.float64)
    flat = gt.joints.reshape(gt.t_us.size, -1)
    out[inside] = np.stack([np.interp(tt, gt.t_us.astype(np.float64), flat[:, k]) for k in range(flat.shape[1])],
                           axis=1).reshape(-1, 24, 3)
    return out


def _log_truth(rr, s, c: RunContent, counts) -> None:
    gt = c.rec.ground_truth if c.rec is not None else None
    if gt is None or gt.t_us.size == 0:
        return
    t = gt.t_us
    if c.t_us is not None and c.t_us.size:  # the ground truth over the motion's span (it may be rendered longer)
        keep = (t >= c.t_us[0]) & (t <= c.t_us[-1])
        t, J = t[keep], gt.joints[keep]
    else:
        J = gt.joints
    if t.size == 0:
        return
    rr.send_columns("world/skeleton/truth", indexes=_times(rr, t),
                    columns=_keypoint_columns(rr, rr.Points3D, J, CLASS_TRUTH), recording=s)
    px = c.rec.camera.project(J.reshape(-1, 3)).reshape(t.size, -1, 2)
    ok = np.all(np.isfinite(px), axis=(1, 2))
    rr.send_columns("world/camera/image/truth", indexes=_times(rr, t[ok]),
                    columns=_keypoint_columns(rr, rr.Points2D, px[ok], CLASS_TRUTH, 25.0), recording=s)
    counts["ground-truth frames"] = int(t.size)
    if c.t_us is not None and c.t_us.size > 2:
        from eventcap.body.skeleton import JOINT_INDEX

        idx, v = speeds(c.t_us, _truth_on(gt, c.t_us))
        good = np.all(np.isfinite(v), axis=1)
        for name in SPEED_JOINTS:
            j = JOINT_INDEX[name]
            s.log(f"speed/truth/{name}", rr.SeriesLines(colors=GREY, names=f"{name} (truth)", widths=1.0),
                  static=True)
            rr.send_columns(f"speed/truth/{name}", indexes=_times(rr, c.t_us[idx[good]]),
                            columns=rr.Scalars.columns(scalars=v[good, j]), recording=s)


def _log_silhouettes(rr, s, c: RunContent, every_ms, max_frames, stats) -> None:
    idx = decimated(c.t_us, every_ms, max_frames)
    full = decimated(c.t_us, every_ms, 10**12).size
    if idx.size < full:
        stats["decimated"]["silhouettes"] = f"{idx.size} of {full}"
        log.info("viewer: silhouettes decimated: %d of %d (rerun_max_frames=%d)", idx.size, full, max_frames)
    cam = c.rec.camera
    for i in idx:
        strips = silhouette_outline(cam, c.template, c.poses[i])
        _set_time(s, c.t_us[i])
        s.log("world/camera/image/silhouette", rr.LineStrips2D(strips, colors=YELLOW, radii=0.4, draw_order=10.0))
    stats["counts"]["silhouettes"] = int(idx.size)


def _log_speeds(rr, s, c: RunContent, JOINT_INDEX, counts) -> None:
    idx, v = speeds(c.t_us, c.joints)
    if idx.size == 0:
        return
    colours = [(255, 80, 80), (80, 160, 255), (255, 190, 60), (120, 220, 120), (220, 120, 255)]
    for name, colour in zip(SPEED_JOINTS, colours):
        s.log(f"speed/estimate/{name}", rr.SeriesLines(colors=colour, names=name, widths=1.5), static=True)
        rr.send_columns(f"speed/estimate/{name}", indexes=_times(rr, c.t_us[idx]),
                        columns=rr.Scalars.columns(scalars=v[:, JOINT_INDEX[name]]), recording=s)
    counts["speed samples"] = int(idx.size)


def _log_errors(rr, s, c: RunContent, counts) -> None:
    e = c.errors
    if e is None or e.t_us.size == 0:
        return
    s.log("error/mean_joint_error_mm", rr.SeriesLines(colors=(240, 80, 80), names=f"mean joint error ({e.align})"),
          static=True)
    rr.send_columns("error/mean_joint_error_mm", indexes=_times(rr, e.t_us),
                    columns=rr.Scalars.columns(scalars=e.error_m.mean(axis=1) * 1000.0), recording=s)
    counts["error samples"] = int(e.t_us.size)


def _log_batches(rr, s, c: RunContent, counts) -> None:
    plan = c.plan
    if plan is not None and len(plan):
        t = np.append(plan.t0_us, plan.t1_us[-1])
        s.log("batches/plan", rr.SeriesLines(colors=(200, 200, 200), names="batch index"), static=True)
        rr.send_columns("batches/plan", indexes=_times(rr, t),
                        columns=rr.Scalars.columns(scalars=np.append(np.arange(len(plan)), len(plan) - 1.0)),
                        recording=s)
        counts["batches"] = len(plan)
    n_lines = 0
    for node, info in c.batch_nodes.items():
        poses = c.pose_nodes.get(node, {})
        its = []
        for b in sorted(set(info["committed"]) | set(info["failed"])):
            t0 = int(plan.t0_us[b]) if plan is not None and b < len(plan) else None
            if t0 is None and b in poses and poses[b].t_us.size:  # (a batch another window keeps has no frames)
                t0 = int(poses[b].t_us[0])
            if t0 is None:
                continue
            if b in info["failed"]:
                f = info["failed"][b]
                text, level = f"batch {b}: {node} FAILED ({f.get('status', '')}): {f.get('error', '')}", "ERROR"
            else:
                text, level = f"batch {b}: {node} committed", "INFO"
                if b in poses:
                    p = poses[b]
                    energies = ", ".join(f"{k} {v:.3g}" for k, v in sorted(p.energies.items())
                                         if isinstance(v, (int, float)))
                    text += f"; status {p.status or '-'}, {p.iterations} iterations" + (
                        f"; energies: {energies}" if energies else "")
                    its.append((t0, p.iterations))
            _set_time(s, t0)
            s.log(f"batches/{node}", rr.TextLog(text, level=level))
            n_lines += 1
        if its:
            its_a = np.array(its)
            rr.send_columns(f"batches/{node}/iterations", indexes=_times(rr, its_a[:, 0]),
                            columns=rr.Scalars.columns(scalars=its_a[:, 1].astype(np.float64)), recording=s)
    counts["batch log lines"] = n_lines


# ---------------------------------------------------------------------------------------------------------------------
# eventcap view
# ---------------------------------------------------------------------------------------------------------------------
class ViewError(Exception):
    """A run folder that cannot be shown (the message says why and what to do)."""


def view_cache_dir(run_dir: Path) -> Path:
    """Where ``eventcap view RUN_DIR`` keeps the recording it builds for a run folder that has none: reading a run
    folder writes nothing into it. ``$EVENTCAP_VIEW_DIR``, else ``$XDG_CACHE_HOME/eventcap/views`` (default
    ``~/.cache/eventcap/views``), one folder per run folder and its run.json (a run written again builds again),
    ending in the run folder's own name (which the recording's id carries)."""
    import hashlib

    root = os.environ.get("EVENTCAP_VIEW_DIR") or \
        Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "eventcap" / "views"
    run_dir = Path(run_dir).resolve()
    digest = hashlib.sha256(str(run_dir).encode())
    record = run_dir / "run.json"
    if record.is_file():
        digest.update(record.read_bytes())
    return Path(root) / digest.hexdigest()[:16] / run_dir.name


def has_display() -> bool:
    """Whether a native viewer window can be shown here."""
    if sys.platform in ("darwin", "win32"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def _wheel_binary() -> str | None:
    """The viewer binary inside the rerun-sdk wheel (``rerun_cli/rerun``; $RERUN_CLI_PATH overrides it, as the wheel's
    own launcher honours it), or None."""
    if os.environ.get("RERUN_CLI_PATH"):
        return os.environ["RERUN_CLI_PATH"]
    import importlib.util

    spec = importlib.util.find_spec("rerun_cli")
    if spec is None or not spec.submodule_search_locations:
        return None
    exe = Path(next(iter(spec.submodule_search_locations))) / ("rerun.exe" if sys.platform == "win32" else "rerun")
    return str(exe) if exe.is_file() else None


def _is_wheel_launcher(exe: str) -> bool:
    """Whether ``exe`` is the rerun-sdk wheel's Python launcher script (which starts the binary as a child)."""
    try:
        with open(exe, "rb") as fh:
            head = fh.read(512)
    except OSError:
        return False
    return head.startswith(b"#!") and b"rerun_cli" in head


def rerun_command() -> list[str]:
    """The ``rerun`` viewer command of this environment: the ``rerun`` on PATH (or beside this Python), except that
    the rerun-sdk wheel's launcher script is skipped for the binary it would start, so that the viewer is one
    process and nothing is left when it is stopped (:func:`run_viewer`)."""
    exe = shutil.which("rerun") or str(Path(sys.executable).with_name("rerun"))
    if not Path(exe).exists() or _is_wheel_launcher(exe):
        binary = _wheel_binary()
        if binary is not None:
            return [binary]
    return [exe] if Path(exe).exists() else [sys.executable, "-m", "rerun"]


class _Stopped(Exception):
    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


def _end_group(proc, grace_s: float = 3.0) -> None:
    """End the viewer's process group (the viewer and anything it started): SIGTERM, then SIGKILL after ``grace_s``."""
    import signal
    import subprocess

    for sig, wait_s in ((signal.SIGTERM, grace_s), (signal.SIGKILL, 5.0)):
        try:
            os.killpg(proc.pid, sig)
        except (ProcessLookupError, PermissionError):
            break  # nothing of the group is left
        try:
            proc.wait(timeout=wait_s)
        except subprocess.TimeoutExpired:
            continue
        deadline = time.monotonic() + wait_s  # the viewer is gone: give what it started the same time
        while time.monotonic() < deadline:
            try:
                os.killpg(proc.pid, 0)
            except (ProcessLookupError, PermissionError):
                return
            time.sleep(0.05)


def run_viewer(cmd: list[str]) -> int:
    """Run the viewer ``cmd`` in the foreground until it exits, and make everything it starts end with this process,
    whichever way it is stopped: it runs in its own process group, which is ended when the viewer exits and when this
    process gets SIGTERM, SIGINT (Ctrl-C) or SIGHUP; on Linux the kernel also kills the viewer when this process
    dies without a chance to clean up (``kill -9``: :func:`eventcap.core.lifeline.arm_before_exec`). Returns the
    viewer's exit code, 0 after Ctrl-C, 128 + the signal after another stop."""
    import functools
    import signal
    import subprocess

    from eventcap.core.lifeline import arm_before_exec

    def stop(signum, frame):
        raise _Stopped(signum)

    stops = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)
    old = {s: signal.signal(s, stop) for s in stops}
    proc = None
    try:
        proc = subprocess.Popen(cmd, process_group=0, preexec_fn=functools.partial(arm_before_exec, os.getpid()))
        return proc.wait()
    except _Stopped as exc:
        return 0 if exc.signum == signal.SIGINT else 128 + exc.signum
    finally:
        for s in stops:  # a second signal while the group is ended must not cut the clean-up short
            signal.signal(s, signal.SIG_IGN)
        if proc is not None:
            _end_group(proc)
        for s, handler in old.items():
            signal.signal(s, handler)


def web_viewer_url(port: int = 9090, grpc_port: int = 9876) -> str:
    """The address that opens the web viewer *with* the served recording (the bare address shows a welcome page)."""
    from urllib.parse import quote

    return f"http://127.0.0.1:{port}?url={quote(f'rerun+http://localhost:{grpc_port}/proxy', safe='')}"


def web_viewer_command(rrd: Path, port: int = 9090, grpc_port: int = 9876) -> list[str]:
    """Arguments of ``rerun`` serving the web viewer of ``rrd`` on 127.0.0.1 (HTTP ``port``, data on ``grpc_port``)."""
    return [str(rrd), "--serve-web", "--bind", "127.0.0.1", "--web-viewer-port", str(port), "--port", str(grpc_port)]


def how_to_view(rrd: Path, port: int = 9090, grpc_port: int = 9876, target: Path | str | None = None) -> str:
    """How to open ``rrd``: the native viewer, or the web viewer served by ``eventcap view TARGET --web`` (which ends
    the viewer when it is stopped; ``target``: what was given to ``eventcap view``, default ``rrd``)."""
    ports = "" if (port, grpc_port) == (9090, 9876) else f" --port {port} --grpc-port {grpc_port}"
    return (f"open it with the Rerun viewer:\n  rerun {rrd}\n"
            f"or, on a machine without a display, serve the web viewer on this machine and open it in a browser "
            f"(from elsewhere through an SSH tunnel: ssh -L {port}:localhost:{port} -L {grpc_port}:localhost:"
            f"{grpc_port} HOST):\n  eventcap view {target or rrd} --web{ports}\n"
            f"  then open {web_viewer_url(port, grpc_port)}")
