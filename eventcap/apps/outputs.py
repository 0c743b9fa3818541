"""Files a run leaves for people and other tools: the motion as BVH and npz, and an overlay video.

Written by the core after a run (stages never write files), from the committed outputs in the cache, into the run
folder, as configured by the ``outputs:`` section of ``conf/config.yaml``:

- ``motion.bvh``: the joined motion of the ``poses`` node (``node.port``, per-batch PoseSequences, e.g.
  ``solve.poses``) at its tracking frame rate (1000 fps), on the template's rest skeleton
  (:func:`eventcap.export.bvh.write_bvh`). Nothing is filled in: BVH has no way to mark a frame unestimated, so a motion
  with gaps (batches that failed or were not selected, windows that saw nothing) is cut there into
  ``motion_partNN.bvh``, one file per stretch, and the log names them.
- ``motion.npz``: ``t_us``, ``poses`` (T, 33), ``joints`` (T, 24, 3) metres (:func:`eventcap.export.bvh.write_motion_npz`),
  ``estimated`` (T,) (False: a gap, NaN poses and joints), ``gaps_us`` (the spans of the gaps), and when the
  pipeline has a confidence node ``uncertainty_mm`` (T, 24) per joint (the RMS 3D distance to the truth one expects,
  calibrated: :mod:`eventcap.analysis.uncertainty`; NaN in gaps) and ``confidence`` (T, 24) in [0, 1] derived from it
  (below 0.5 unobserved or not trusted). The BVH's first line says so (BVH cannot hold it).
- ``overlay.mp4``: every ``video_every_ms`` of the motion (at most ``video_max_frames`` frames: the step widens
  to cover the whole motion), the sharpened latent image (else the nearest intensity frame) with the events of the
  last ``video_events_ms`` (red positive, blue negative), the template's silhouette outline (yellow) and skeleton
  (green; its joints coloured by their uncertainty, with a legend, when the run has one) of the estimate projected
  into the camera, the ground-truth skeleton (grey) when the recording has one, and beside it an orthographic side
  view of the 3D skeleton. ``overlay_frames/`` keeps ``video_png_frames`` of its
  frames as PNG. The file appears atomically (written as ``overlay.partial.mp4``, then renamed).
- ``motion.c3d`` (``c3d: true``): the joint centres and the template's surface markers (Plug-in Gait) at the
  tracking rate, for mocap tools (:mod:`eventcap.export.c3d`); each point's residual is its uncertainty (a marker's:
  its joint's) in the file's unit, -1 (invalid) only in a gap.
- ``up_axis`` (y | z) and ``units`` (m | cm | mm; null: BVH in m, C3D in mm) set the frame of motion.bvh and
  motion.c3d (:mod:`eventcap.worldframe`); motion.npz stays in the internal frame (y up, metres) and says so in its
  ``world_frame`` field. Each file states the time of its first frame (``t0_us``).
- ``plausibility.json``: speeds beyond human limits, joints behind the camera, sudden flips, the head below the
  pelvis, each with its frames (:mod:`eventcap.analysis.plausibility`); also logged, one line per kind.
- ``capture.rrd`` (``rerun: true``): a Rerun recording of everything the run saw and produced (:mod:`eventcap.apps.viewer`;
  ``eventcap view RUN_DIR`` opens it, or builds it from a finished run into the view cache, outside the run folder).

A run whose poses node committed nothing (it failed or was skipped) gets none of these, with a log line saying so.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np

from eventcap.artifacts.pose import PoseSequence
from eventcap.analysis.motion import frame_step_us, frames_every, join_batches, on_grid, uniform_motion
from eventcap.analysis.plausibility import write_plausibility
from eventcap.core.runrecord import note_outputs
from eventcap.imaging.viz import label as _label
from eventcap.apps.output_settings import OutputsConfig  # noqa: F401 (this module's API)

log = logging.getLogger("eventcap.apps.outputs")

#: BGR colours of the overlay
ESTIMATE = (60, 200, 60)
TRUTH = (170, 170, 170)
OUTLINE = (0, 230, 255)
POSITIVE = np.array([50, 50, 235], np.uint8)
NEGATIVE = np.array([235, 120, 30], np.uint8)


def check_outputs_config(runner) -> OutputsConfig:
    """The run's outputs config, checked against its pipeline (before anything runs)."""
    cfg = OutputsConfig.from_mapping(runner.cfg.get("outputs"))
    import importlib.util

    for key, module, install in (("rerun", "rerun", "rerun-sdk (or: pip install -e \".[viewer]\")"),
                                 ("c3d", "c3d", "c3d")):
        if getattr(cfg, key) and importlib.util.find_spec(module) is None:  # refused before anything runs
            raise ValueError(f"outputs.{key}=true needs the {module if module != 'rerun' else 'rerun-sdk'} package: "
                             f"pip install {install}, or set outputs.{key}=false")
    if cfg.poses is None:
        return cfg
    node_name, _, port = cfg.poses.partition(".")
    node = runner.by_name.get(node_name)
    if node is None:  # e.g. pipeline=simulate: nothing to write, say so
        log.warning("outputs: no motion files: outputs.poses=%s, but this pipeline has no node %r (nodes: %s); "
                    "set outputs.poses=null to silence this", cfg.poses, node_name, ", ".join(runner.by_name))
        return dataclasses.replace(cfg, poses=None)
    if port not in node.spec.outputs:
        raise ValueError(f"outputs.poses: {cfg.poses!r}: node {node_name!r} (stage {node.spec.name!r}) has no output "
                         f"{port!r} (outputs: {', '.join(node.spec.outputs)})")
    if not issubclass(node.spec.outputs[port].type, PoseSequence):
        raise ValueError(f"outputs.poses: {cfg.poses!r} is a {node.spec.outputs[port].type.__name__}, expected "
                         f"PoseSequence")
    return cfg


# ---------------------------------------------------------------------------------------------------------------------
# After a run
# ---------------------------------------------------------------------------------------------------------------------
def _upstream(runner, node_name: str) -> list[str]:
    """The nodes ``node_name`` depends on, nearest in pipeline order first (a recording's template as the body stage
    gave it comes before the source's)."""
    seen, todo = set(), [node_name]
    while todo:
        for ref in runner.by_name[todo.pop()].inputs.values():
            if ref.node not in seen:
                seen.add(ref.node)
                todo.append(ref.node)
    return [n.name for n in reversed(runner.nodes) if n.name in seen]


def _first_output(runner, result, cls, prefer: list[str] = ()) -> Any:
    """The committed output of type ``cls`` of a whole node: the nodes in ``prefer`` first, then pipeline order."""
    nodes = [runner.by_name[n] for n in prefer if n in runner.by_name] + list(runner.nodes)
    for node in nodes:
        if node.spec.per_batch:
            continue
        for port, p in node.spec.outputs.items():
            if issubclass(p.type, cls):
                got = runner.load_output(result, f"{node.name}.{port}")
                if got:
                    return got[None]
    return None


def write_run_outputs(runner, result, run_dir: str | Path, cfg: OutputsConfig | None = None,
                      merge: bool = False) -> dict[str, Any]:
    """Write the configured outputs of a finished run into ``run_dir``; returns what was written (paths as
    strings), what was ``skipped`` and why, and ``problems`` (errors while writing). Missing inputs are logged and
    skipped, not errors. The summary is also added to the run folder's ``run.json`` under ``outputs`` (``merge``:
    added to what an earlier call recorded there)."""
    cfg = cfg or check_outputs_config(runner)
    run_dir = Path(run_dir)
    summary: dict[str, Any] = {"written": {}, "skipped": {}, "problems": []}
    try:
        _write(runner, result, run_dir, cfg, summary)
    except Exception as exc:  # noqa: BLE001 - e.g. an unreadable cache entry: reported, the run's results stay
        summary["problems"].append(f"{type(exc).__name__}: {exc}")
        log.error("outputs: %s: %s", type(exc).__name__, exc)
    note_outputs(run_dir, summary, merge)
    return summary


def _write(runner, result, run_dir: Path, cfg: OutputsConfig, summary: dict[str, Any]) -> dict[str, Any]:
    from eventcap.artifacts.recording import Recording
    from eventcap.artifacts.tracking import LatentFrames
    from eventcap.body.template import Template

    wanted = [k for k in ("bvh", "npz", "video", "c3d", "rerun") if getattr(cfg, k)]
    if cfg.poses is None or not wanted:
        return summary

    def skip(why: str, level: int = logging.WARNING) -> dict[str, Any]:
        log.log(level, "outputs: skipped (%s): %s", ", ".join(wanted), why)
        summary["skipped"] = {k: why for k in wanted}
        return summary

    node_name = cfg.poses.partition(".")[0]
    rep = result.nodes[node_name]
    parts = runner.load_output(result, cfg.poses)
    if not parts:
        failed = ", ".join(str(f["batch"]) for f in rep.failed if f.get("batch") is not None)
        why = (f"node {node_name!r} committed no poses"
               + (f" (failed batches: {failed})" if failed else " (it failed)" if rep.failed else "")
               + (" (skipped: upstream failed)" if rep.skipped and not rep.failed else ""))
        return skip(why, logging.INFO)  # a consequence of the failure the run's summary reports
    if rep.per_batch and (rep.failed or rep.skipped):
        log.warning("outputs: node %r committed %d batch(es); %d failed, %d skipped: the motion lacks their frames",
                    node_name, len(parts), len(rep.failed), rep.skipped)
    try:
        t_us, poses, _ = join_batches([parts[k] for k in parts], cfg.join)
    except Exception as exc:  # noqa: BLE001 - reported, the run's own results stay
        summary["problems"].append(f"joining {cfg.poses}: {exc}")
        log.error("outputs: cannot join the poses of %s: %s", cfg.poses, exc)
        return summary
    prefer = _upstream(runner, node_name)  # the nearest producers first: the body stage's recording and template
    from eventcap.artifacts.pose import Detections, JointConfidence
    from eventcap.worldframe import upright

    rec = _first_output(runner, result, Recording, prefer)
    if rec is not None:  # the world the motion was solved in (turned to the person's vertical by detect, or not)
        rec = upright(rec, _first_output(runner, result, Detections))
    template = rec.template if rec is not None and rec.template is not None else _first_output(runner, result,
                                                                                               Template, prefer)
    if template is None:
        return skip("no actor template in this run (the motion needs its rest skeleton)")
    from eventcap.body.kinematics import joint_positions

    t_us, poses = with_gap_frames(t_us, poses, frame_step_us(t_us) or 1000)  # failed batches: their frames, NaN
    est = np.isfinite(poses).all(axis=1)  # False: a gap (a window that saw nothing, a failed batch): never filled in
    if not est.any():
        return skip("the motion has no estimated frame: nothing was seen (every window of the solve was a gap)")
    joints = np.full((t_us.size, 24, 3), np.nan)
    joints[est] = joint_positions(poses[est], template)
    conf, unc = _confidence_on(_first_output(runner, result, JointConfidence), t_us)
    if (~est).any():
        log.warning("outputs: %d of %d frames are a gap (not estimated: nothing seen there); motion.npz marks them "
                    "(estimated false, NaN), the BVH is cut at them, the C3D marks them invalid (residual -1)",
                    int((~est).sum()), t_us.size)
    step = frame_step_us(t_us[est]) or 1000
    te, Pe, Je = t_us[est], poses[est], joints[est]
    Ue = None if unc is None else unc[est]
    jobs = []
    if cfg.bvh:
        jobs.append(("bvh", lambda: _write_bvh(run_dir / "motion.bvh", te, Pe, template, step, cfg, unc is not None)))
    if cfg.npz:
        jobs.append(("npz", lambda: _write_npz(run_dir / "motion.npz", t_us, poses, joints, est, conf, cfg, unc)))
    if cfg.video:
        if rec is None:
            summary["skipped"]["video"] = "no recording in this run (the video needs its camera)"
            log.warning("outputs: video skipped: %s", summary["skipped"]["video"])
        else:
            latent = _first_output(runner, result, LatentFrames)
            jobs.append(("video", lambda: write_overlay_video(run_dir, rec, template, te, Pe, Je, cfg,
                                                              latent=latent, uncertainty_mm=Ue)))
    if cfg.c3d:
        jobs.append(("c3d", lambda: _write_c3d(run_dir / "motion.c3d", te, Pe, Je, template, step, cfg, Ue)))
    if cfg.rerun:
        jobs.append(("rerun", lambda: _write_rerun(run_dir, runner, result, te, Pe, Je, rec, template,
                                                   cfg, summary, None if conf is None else conf[est], Ue)))
    # Plausibility warnings (eventcap/analysis/plausibility.py): logged, and written to plausibility.json; never change the motion
    jobs.append(("plausibility", lambda: write_plausibility(run_dir / "plausibility.json", te, Je,
                                                            rec.camera if rec is not None else None)))
    for name, job in jobs:
        try:
            path = job()
            summary["written"][name] = str(path)
            log.info("outputs: wrote %s", path)
        except Exception as exc:  # noqa: BLE001 - one failed file does not stop the others
            summary["problems"].append(f"{name}: {type(exc).__name__}: {exc}")
            log.error("outputs: %s failed: %s: %s", name, type(exc).__name__, exc)
    return summary


def _confidence_on(conf, t_us: np.ndarray) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The run's joint confidence and uncertainty (mm) (a JointConfidence, or None) at the motion's frames: (T, 24)
    each, confidence 0 and uncertainty NaN where it has none (gaps)."""
    if conf is None:
        return None, None
    t = np.asarray(conf.t_us, dtype=np.int64)
    k = np.searchsorted(t, t_us)
    hit = (k < t.size) & (t[np.minimum(k, max(t.size - 1, 0))] == t_us) if t.size else np.zeros(t_us.size, bool)
    c = np.zeros((t_us.size, 24))
    c[hit] = np.asarray(conf.confidence, dtype=np.float64)[k[hit]]
    u = np.full((t_us.size, 24), np.nan)
    u[hit] = np.asarray(conf.uncertainty_mm, dtype=np.float64)[k[hit]]
    return c, u


def with_gap_frames(t_us: np.ndarray, poses: np.ndarray, step_us: int) -> tuple[np.ndarray, np.ndarray]:
    """The motion with the grid frames of its time gaps (batches that failed or were not run) added as NaN rows, so
    that a gap is a gap in every output, whatever left it."""
    t = np.asarray(t_us, dtype=np.int64)
    jumps = np.flatnonzero(np.diff(t) > 1.5 * step_us)
    if not jumps.size:
        return t, poses
    extra = np.concatenate([np.arange(t[i] + step_us, t[i + 1] - step_us // 2, step_us, dtype=np.int64)
                            for i in jumps])
    t_all = np.concatenate([t, extra])
    order = np.argsort(t_all, kind="stable")
    P = np.concatenate([np.asarray(poses, dtype=np.float64), np.full((extra.size, poses.shape[1]), np.nan)])
    return t_all[order], P[order]


def motion_segments(t_us: np.ndarray, step_us: int) -> list[slice]:
    """The stretches of a motion's frames with no gap longer than a frame step (a gap is never filled in)."""
    cut = np.flatnonzero(np.diff(np.asarray(t_us, dtype=np.int64)) > 1.5 * step_us) + 1
    bounds = [0, *cut.tolist(), len(t_us)]
    return [slice(a, b) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]


#: What the BVH's first line says of the uncertainty (BVH cannot hold it).
BVH_NOTE = "each joint's uncertainty (mm) and confidence per frame: motion.npz (uncertainty_mm, confidence)"


def _write_bvh(path: Path, t_us, poses, template, step_us: int, cfg: OutputsConfig,
               with_uncertainty: bool = False) -> Path | str:
    """motion.bvh of the estimated frames; a motion with gaps (BVH has no way to mark one) is cut there into
    motion_partNN.bvh, one file per stretch, each with its own time origin (the log names them). with_uncertainty:
    the first line's comment says where the joints' uncertainty is (:data:`BVH_NOTE`)."""
    from eventcap.export.bvh import write_bvh
    from eventcap.worldframe import unit_scale

    segments = motion_segments(t_us, step_us)
    written = []
    for n, seg in enumerate(segments, start=1):
        if seg.stop - seg.start < 2:
            log.warning("outputs: a stretch of 1 frame at %d us between gaps is left out of the BVH files", t_us[seg][0])
            continue
        grid, S, _ = uniform_motion(t_us[seg], poses[seg], step_us)
        out = path if len(segments) == 1 else path.with_name(f"{path.stem}_part{n:02d}{path.suffix}")
        written.append(write_bvh(out, S, template.rest_joints, frame_time_s=step_us * 1e-6,
                                 scale=unit_scale(cfg.units or "m"), up_axis=cfg.up_axis, t0_us=int(grid[0]),
                                 note=BVH_NOTE if with_uncertainty else ""))
    if len(segments) > 1:
        spans = ", ".join(f"{t_us[s][0] / 1e3:.0f}-{t_us[s][-1] / 1e3:.0f} ms" for s in segments)
        log.warning("outputs: the motion has gaps: no motion.bvh; %d BVH files, one per stretch (%s)", len(written),
                    spans)
        return ", ".join(str(p) for p in written)
    if not written:
        raise ValueError("no stretch of the motion has 2 frames or more")
    return written[0]


def _write_npz(path: Path, t_us, poses, joints, est, conf, cfg: OutputsConfig, unc=None) -> Path:
    """motion.npz: every frame of the joined motion, gaps included (NaN, ``estimated`` false), its ``uncertainty_mm``
    and ``confidence`` per joint (NaN and 0 in gaps; when the run has a confidence node) and the time spans of its
    gaps."""
    from eventcap.export.bvh import write_motion_npz
    from eventcap.worldframe import describe

    t = np.asarray(t_us, dtype=np.int64)
    edges = np.flatnonzero(np.diff(np.concatenate([[False], ~est, [False]]).astype(int)))
    gaps = np.stack([t[edges[0::2]], t[edges[1::2] - 1]], axis=1) if edges.size else np.zeros((0, 2), np.int64)
    extra = {"source_output": np.array(cfg.poses), "t0_us": np.int64(t[0]),
             "world_frame": np.array(describe("y", "m")), "estimated": est, "gaps_us": gaps}
    if conf is not None:
        extra["confidence"] = conf.astype(np.float32)
    if unc is not None:
        extra["uncertainty_mm"] = unc.astype(np.float32)
    return write_motion_npz(path, t, poses, joints, extra=extra, estimated=est)


def _write_c3d(path: Path, t_us, poses, joints, template, step_us: int, cfg: OutputsConfig,
               unc: np.ndarray | None = None) -> Path:
    from eventcap.body.markers import plug_in_gait_markers
    from eventcap.export.c3d import write_c3d

    keep = on_grid(t_us, step_us)  # C3D has one frame rate: intensity frames between two grid times stay in motion.npz
    markers = plug_in_gait_markers(template)
    point_unc = None
    if unc is not None:  # the residual: each point's uncertainty; a marker takes its main joint's
        u = unc[keep]
        point_unc = np.concatenate([u, u[:, np.argmax(markers.weights, axis=1)]], axis=1)
    return write_c3d(path, np.asarray(t_us)[keep], np.asarray(joints)[keep],
                     markers.positions(np.asarray(poses)[keep], template), step_us, marker_names=markers.names,
                     marker_descriptions=markers.descriptions, up_axis=cfg.up_axis, units=cfg.units or "mm",
                     uncertainty_mm=point_unc)


def _write_rerun(run_dir: Path, runner, result, t_us, poses, joints, rec, template, cfg: OutputsConfig,
                 summary: dict[str, Any], conf: np.ndarray | None = None, unc: np.ndarray | None = None) -> Path:
    from eventcap.artifacts.tracking import LatentFrames
    from eventcap.apps.viewer import RRD_NAME, collect_run_content, write_recording

    content = collect_run_content(runner, result, t_us, poses, joints, rec, template,
                                  _first_output(runner, result, LatentFrames), cfg.poses)
    content.confidence = conf
    content.uncertainty_mm = unc
    content.name = f"{content.name or 'run'}/{run_dir.name}"  # the recording id: runs of one name stay apart
    stats = write_recording(run_dir / RRD_NAME, content, cfg.rerun_events_ms, cfg.rerun_every_ms,
                            cfg.rerun_max_frames, cfg.rerun_outline_every_ms)
    summary["rerun"] = stats
    return run_dir / RRD_NAME


# ---------------------------------------------------------------------------------------------------------------------
# The overlay video
# ---------------------------------------------------------------------------------------------------------------------
def video_frame_indices(t_us: np.ndarray, every_ms: float, max_frames: int) -> np.ndarray:
    """Indices of the motion frames shown: one every ``every_ms`` of motion time (the nearest estimated frame at or
    after each step), at most ``max_frames`` (the step widens evenly to cover the whole motion)."""
    idx, every_us = frames_every(t_us, every_ms, max_frames)
    wanted_us = max(1, int(round(every_ms * 1000)))
    if every_us != wanted_us:
        t = np.asarray(t_us, dtype=np.int64)
        log.info("outputs: video: %d frames at one per %g ms exceed video_max_frames=%d; one frame per %.1f ms",
                 int(t[-1] - t[0]) // wanted_us + 1, every_ms, max_frames, every_us / 1000)
    return idx


class OverlayRenderer:
    """Draws one overlay frame: image + events + silhouette outline + skeletons | side view of the 3D skeleton."""

    def __init__(self, rec, template, joints_all: np.ndarray, scale: int = 2, events_ms: float = 5.0, latent=None):
        self.rec, self.template, self.scale = rec, template, int(scale)
        self.events_us = int(round(events_ms * 1000))
        self.latent = latent
        self.h, self.w = rec.height, rec.width
        self.H, self.W = self.h * self.scale, self.w * self.scale
        self.side = self.H  # square side panel
        cam = rec.camera
        s = self.scale  # the camera of the enlarged image: pixel centres stay pixel centres
        self.cam_big = dataclasses.replace(cam, width=self.W, height=self.H, fx=cam.fx * s, fy=cam.fy * s,
                                           cx=(cam.cx + 0.5) * s - 0.5, cy=(cam.cy + 0.5) * s - 0.5)
        # Side view: camera coordinates (x right, y down, z forward), seen from the camera's right: depth z to the
        # right, y down. One fixed framing for the whole motion (the centre and extent of every joint).
        pc = cam.to_camera(joints_all.reshape(-1, 3))
        lo, hi = pc.min(axis=0), pc.max(axis=0)
        self.side_centre = 0.5 * (lo + hi)
        extent = max(float(hi[1] - lo[1]), float(hi[2] - lo[2]), 1.0) * 1.25
        self.side_px_per_m = self.side / extent
        self.gt = rec.ground_truth

    # -- pieces --------------------------------------------------------------------------------------------------
    def background(self, t_us: int) -> tuple[np.ndarray, str]:
        import cv2

        if self.latent is not None and self.latent.t_us.size:
            k = int(np.argmin(np.abs(self.latent.t_us - t_us)))
            img = np.clip(np.exp(self.latent.log_images[k].astype(np.float64)) - self.latent.eps, 0.0, 1.0)
            what = f"latent image {k}"
        elif self.rec.frames is not None and self.rec.frames.t_us.size:
            k = int(np.argmin(np.abs(self.rec.frames.t_us - t_us)))
            img = np.clip(self.rec.frames.images[k].astype(np.float64), 0.0, 1.0)
            what = f"intensity frame {k}"
        else:
            img = np.full((self.h, self.w), 0.5)
            what = "no image"
        g = (img * 0.7 * 255.0 + 0.5).astype(np.uint8)  # dimmed: the drawing stays readable
        big = cv2.resize(g, (self.W, self.H), interpolation=cv2.INTER_NEAREST)
        return np.repeat(big[..., None], 3, axis=2), what

    def draw_events(self, img: np.ndarray, t_us: int) -> int:
        ev = self.rec.events.window(t_us - self.events_us, t_us + 1)
        if ev.size == 0:
            return 0
        acc = np.zeros((self.h, self.w), np.int32)
        np.add.at(acc, (ev["y"].astype(np.intp), ev["x"].astype(np.intp)), ev["p"].astype(np.int32))
        s = self.scale
        big = np.repeat(np.repeat(np.sign(acc), s, axis=0), s, axis=1)
        img[big > 0] = POSITIVE
        img[big < 0] = NEGATIVE
        return int(ev.size)

    def draw_outline(self, img: np.ndarray, S: np.ndarray) -> None:
        """The template's silhouette at pose S (rasterized in the enlarged image), outer and inner contours."""
        import cv2

        from eventcap.body.kinematics import skin
        from eventcap.imaging.render import rasterize

        _, tri_id, _ = rasterize(self.cam_big, skin(S, self.template), self.template.faces)
        mask = (tri_id >= 0).astype(np.uint8)
        contours, _ = cv2.findContours(mask, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_SIMPLE)
        cv2.drawContours(img, contours, -1, OUTLINE, 1, cv2.LINE_AA)

    def draw_skeleton(self, img: np.ndarray, joints: np.ndarray, colour, width: int,
                      uncertainty_mm: np.ndarray | None = None) -> None:
        """Bones in ``colour``; joints too, or coloured by their uncertainty (24,) mm when given
        (:func:`eventcap.imaging.viz.uncertainty_rgb`)."""
        import cv2

        from eventcap.body.skeleton import PARENTS
        from eventcap.imaging.viz import uncertainty_rgb

        px = self.cam_big.project(joints)
        if not np.all(np.isfinite(px)):
            return
        p = np.round(px).astype(int)
        for child, parent in enumerate(PARENTS):
            if parent >= 0:
                cv2.line(img, tuple(p[parent]), tuple(p[child]), colour, width, cv2.LINE_AA)
        cols = [colour] * len(p) if uncertainty_mm is None else \
            [tuple(int(v) for v in c[::-1]) for c in uncertainty_rgb(uncertainty_mm)]
        for q, c in zip(p, cols):
            cv2.circle(img, tuple(q), width + (2 if uncertainty_mm is not None else 1), c, -1, cv2.LINE_AA)

    def side_view(self, joints: np.ndarray, truth: np.ndarray | None) -> np.ndarray:
        import cv2

        from eventcap.body.skeleton import PARENTS

        n = self.side
        panel = np.full((n, n, 3), 32, np.uint8)
        c, k = self.side_centre, self.side_px_per_m
        # floor grid: a line every 0.5 m of depth
        for z in np.arange(np.floor((c[2] - n / k / 2) * 2) / 2, c[2] + n / k / 2, 0.5):
            u = int(round((z - c[2]) * k + n / 2))
            cv2.line(panel, (u, 0), (u, n - 1), (55, 55, 55), 1)
        for J, colour, width in ((truth, TRUTH, 1), (joints, ESTIMATE, 2)):
            if J is None:
                continue
            pc = self.rec.camera.to_camera(J)
            uv = np.stack([(pc[:, 2] - c[2]) * k + n / 2, (pc[:, 1] - c[1]) * k + n / 2], axis=1)
            p = np.round(uv).astype(int)
            for child, parent in enumerate(PARENTS):
                if parent >= 0:
                    cv2.line(panel, tuple(p[parent]), tuple(p[child]), colour, width, cv2.LINE_AA)
        _label(panel, "side view (camera at left)", (6, 16))
        _label(panel, "0.5 m grid", (6, n - 8))
        return panel

    def truth_at(self, t_us: int) -> np.ndarray | None:
        gt = self.gt
        if gt is None or gt.t_us.size == 0 or not (gt.t_us[0] <= t_us <= gt.t_us[-1]):
            return None
        k = int(np.searchsorted(gt.t_us, t_us))
        if gt.t_us[k] == t_us or k == 0:
            return gt.joints[k]
        w = (t_us - gt.t_us[k - 1]) / (gt.t_us[k] - gt.t_us[k - 1])
        return (1 - w) * gt.joints[k - 1] + w * gt.joints[k]

    def frame(self, t_us: int, S: np.ndarray, joints: np.ndarray, caption: str = "",
              uncertainty_mm: np.ndarray | None = None) -> np.ndarray:
        """One frame; with the joints' uncertainty (24,) mm, the estimate's joints are coloured by it and the side
        panel shows the legend."""
        img, what = self.background(t_us)
        n_ev = self.draw_events(img, t_us)
        self.draw_outline(img, S)
        truth = self.truth_at(t_us)
        if truth is not None:
            self.draw_skeleton(img, truth, TRUTH, 1)
        self.draw_skeleton(img, joints, ESTIMATE, 2, uncertainty_mm)
        _label(img, f"t = {t_us / 1000:.1f} ms  {caption}", (6, 16))
        _label(img, f"{what}, {n_ev} events in the last {self.events_us / 1000:g} ms", (6, 34))
        _label(img, "estimate" + (" / ground truth (grey)" if truth is not None else ""), (6, self.H - 8))
        side = self.side_view(joints, truth)
        if uncertainty_mm is not None:
            from eventcap.imaging.viz import draw_uncertainty_legend

            draw_uncertainty_legend(side, (8, 40), min(150, side.shape[1] - 16))
        return np.concatenate([img, side], axis=1)


class _Encoder:
    """The overlay's video encoder: H.264 in MP4 through PyAV (FFmpeg's libx264, bundled in the ``av`` wheel), which
    browsers play; OpenCV's MPEG-4 Part 2 (FourCC ``mp4v``), which they do not, when PyAV or its encoder is missing.
    ``codec`` says which one writes."""

    def __init__(self, path: Path, fps: float, size: tuple[int, int]):
        self.path, self.size = path, size
        self._av = self._cv = None
        try:
            import av

            av.codec.Codec("libx264", "w")
        except Exception as exc:  # noqa: BLE001 - ImportError, or a PyAV built without libx264
            self._fallback(fps, f"{type(exc).__name__}: {exc}")
            return
        from fractions import Fraction

        self._av = av.open(str(path), mode="w", format="mp4", options={"movflags": "+faststart"})
        stream = self._av.add_stream("libx264", rate=Fraction(fps).limit_denominator(1001))
        # yuv420p, the pixel format browsers decode, needs even sizes: the frame is padded by a pixel if needed
        stream.width, stream.height = size[0] + size[0] % 2, size[1] + size[1] % 2
        stream.pix_fmt = "yuv420p"
        stream.options = {"crf": "20", "preset": "medium"}
        self._stream = stream
        self.codec = "H.264 (libx264 through PyAV)"

    def _fallback(self, fps: float, why: str) -> None:
        import cv2

        self._cv = cv2.VideoWriter(str(self.path), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), self.size)
        if not self._cv.isOpened():
            raise RuntimeError(f"OpenCV cannot write an 'mp4v' video to {self.path} (no encoder in this OpenCV build?)")
        self.codec = f"MPEG-4 Part 2 (OpenCV mp4v; browsers do not play it: H.264 needs PyAV, pip install av; {why})"

    def write(self, bgr: np.ndarray) -> None:
        if self._cv is not None:
            self._cv.write(bgr)
            return
        import av

        h, w = self._stream.height, self._stream.width
        if bgr.shape[:2] != (h, w):
            bgr = np.pad(bgr, ((0, h - bgr.shape[0]), (0, w - bgr.shape[1]), (0, 0)), mode="edge")
        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(bgr), format="bgr24")
        for packet in self._stream.encode(frame):
            self._av.mux(packet)

    def close(self, flush: bool = True) -> None:
        if self._cv is not None:
            self._cv.release()
        elif self._av is not None:
            try:
                if flush:
                    for packet in self._stream.encode():
                        self._av.mux(packet)
            finally:
                self._av.close()


def write_overlay_video(run_dir: str | Path, rec, template, t_us: np.ndarray, poses: np.ndarray, joints: np.ndarray,
                        cfg: OutputsConfig, latent=None, name: str = "overlay.mp4",
                        uncertainty_mm: np.ndarray | None = None) -> Path:
    """Write ``<run_dir>/overlay.mp4`` (and PNGs of a few of its frames in ``overlay_frames/``); returns its path.
    uncertainty_mm (T, 24): the joints are coloured by it, with a legend. The log names the codec
    (:class:`_Encoder`)."""
    import cv2

    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    idx = video_frame_indices(t_us, cfg.video_every_ms, cfg.video_max_frames)
    r = OverlayRenderer(rec, template, joints[idx], cfg.video_scale, cfg.video_events_ms, latent)
    size = (r.W + r.side, r.H)  # width, height
    out = run_dir / name
    tmp = run_dir / (Path(name).stem + ".partial.mp4")  # the container comes from the extension
    tmp.unlink(missing_ok=True)
    png_dir = run_dir / "overlay_frames"
    shutil.rmtree(png_dir, ignore_errors=True)
    pngs = set(np.unique(np.linspace(0, idx.size - 1, cfg.video_png_frames).round().astype(int)).tolist()) \
        if cfg.video_png_frames else set()
    writer = _Encoder(tmp, float(cfg.video_fps), size)
    t0 = time.perf_counter()
    every_log = max(1, min(100, idx.size // 5))
    log.info("outputs: rendering %d video frames (%dx%d, %g fps) to %s, codec %s", idx.size, size[0], size[1],
             cfg.video_fps, out, writer.codec)
    try:
        for n, i in enumerate(idx):
            img = r.frame(int(t_us[i]), poses[i], joints[i], f"frame {n + 1}/{idx.size}",
                          None if uncertainty_mm is None else uncertainty_mm[i])
            writer.write(img)
            if n in pngs:
                png_dir.mkdir(exist_ok=True)
                cv2.imwrite(str(png_dir / f"frame{n:04d}_t{t_us[i] / 1000:09.3f}ms.png"), img)
            if (n + 1) % every_log == 0 or n + 1 == idx.size:
                log.info("outputs: video %d/%d frames (%.1f s)", n + 1, idx.size, time.perf_counter() - t0)
        writer.close()
        os.replace(tmp, out)
    except BaseException:
        writer.close(flush=False)
        tmp.unlink(missing_ok=True)
        raise
    log.info("outputs: overlay video codec: %s", writer.codec)
    return out


# ---------------------------------------------------------------------------------------------------------------------
# eventcap view: the recording of a finished run
# ---------------------------------------------------------------------------------------------------------------------
def build_run_recording(run_dir: Path, recompute: bool = False, out_dir: Path | None = None) -> Path:
    """Write ``capture.rrd`` of a finished run (config + cache) into ``out_dir`` (default: the run's folder of the
    view cache, :func:`eventcap.apps.viewer.view_cache_dir`) through the same path as ``outputs.rerun=true``;
    ``recompute`` runs the pipeline again first (cache hits, recomputing what is gone). The run folder is only read.
    ViewError (:mod:`eventcap.apps.viewer`) when there is nothing to show; RunRecordError when the folder is not a
    finished run or its cache entries are gone."""
    import tempfile

    import yaml

    from eventcap.core.runner import Runner, load_finished_run
    from eventcap.core.runrecord import find_cache_dir
    from eventcap.apps.viewer import RRD_NAME, ViewError, view_cache_dir

    run_dir = Path(run_dir)
    out_dir = Path(out_dir) if out_dir is not None else view_cache_dir(run_dir)
    if recompute:
        cfg = yaml.safe_load((run_dir / "config.yaml").read_text()) or {}
        cfg["cache_dir"] = str(find_cache_dir(run_dir, cfg.get("cache_dir") or "runs/cache"))
        runner = Runner(cfg)
        result = runner.run(None)
    else:
        runner, result = load_finished_run(run_dir)
    cfg = check_outputs_config(runner)
    if cfg.poses is None:
        raise ViewError(f"{run_dir}: this run has no motion to show (outputs.poses is null or names no node of its "
                        f"pipeline, e.g. pipeline=simulate); `eventcap preview RECORDING.zarr` shows a recording")
    only = dataclasses.replace(cfg, bvh=False, npz=False, video=False, c3d=False, rerun=True)
    # built in a folder named as the run's (the recording's id names it), then moved into place; the run's own
    # outputs were logged by the run (the plausibility checks are made again on the way: said only if they warn)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    quiet = [logging.getLogger(n) for n in ("eventcap.apps.outputs", "eventcap.analysis.plausibility")]
    levels = [q.level for q in quiet]
    with tempfile.TemporaryDirectory(dir=out_dir.parent, prefix=".building-") as tmp:
        work = Path(tmp) / run_dir.name
        work.mkdir()
        try:
            for q in quiet:
                q.setLevel(max(q.getEffectiveLevel(), logging.WARNING))
            summary = write_run_outputs(runner, result, work, only)
        finally:
            for q, level in zip(quiet, levels):
                q.setLevel(level)
        if "rerun" not in summary["written"]:
            why = summary["skipped"].get("rerun") or "; ".join(summary["problems"]) or "nothing to show"
            raise ViewError(f"{run_dir}: no recording written: {why}")
        out_dir.mkdir(parents=True, exist_ok=True)
        (work / RRD_NAME).replace(out_dir / RRD_NAME)
    return out_dir / RRD_NAME
