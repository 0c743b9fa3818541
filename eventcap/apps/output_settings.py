"""The ``outputs:`` settings of a run (the files it leaves, :mod:`eventcap.apps.outputs`), declared once.

Light to import: the Hydra plugin registers :class:`OutputsConfig` as ``/settings/outputs`` before every composition,
and ``conf/config.yaml`` starts its ``outputs`` block from it, stating only what differs.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from eventcap.params import param


@dataclass
class OutputsConfig:
    """The ``outputs:`` section of the run config (eventcap.apps.outputs says what each file holds)."""

    poses: str | None = param("solve.poses", help="node.port of the per-batch poses that make the motion files "
                                                  "(default: those the evaluate node measures); null: none of these "
                                                  "files")
    join: str = param("later", choices=("later", "mean"), help="a frame two batches share: the later batch's, or "
                                                               "the mean")
    bvh: bool = param(True, help="motion.bvh at the tracking frame rate, on the template's skeleton")
    npz: bool = param(True, help="motion.npz: times, poses, joints, confidence, gaps (docs/formats.md)")
    video: bool = param(True, help="overlay.mp4 (and overlay_frames/*.png): skeleton, silhouette and events over "
                                   "the images")
    video_every_ms: float = param(2.0, gt=0, help="motion time between video frames, ms")
    video_max_frames: int = param(500, ge=1, help="at most this many video frames (the step widens to cover the "
                                                  "whole motion)")
    video_fps: float = param(25.0, gt=0, help="video playback rate, frames per second")
    video_scale: int = param(2, ge=1, help="image pixels per sensor pixel in the video")
    video_events_ms: float = param(5.0, gt=0, help="events of the last this many ms are drawn (red +, blue -)")
    video_png_frames: int = param(4, ge=0, help="frames of the video also saved as PNG")
    c3d: bool = param(False, help="motion.c3d: joint centres and Plug-in Gait surface markers at the tracking rate")
    up_axis: str = param("y", choices=("y", "z"), help="motion.bvh / motion.c3d: the up axis (Vicon, Visual3D, "
                                                       "OpenSim: z)")
    units: str | None = param(None, choices=("m", "cm", "mm", None),
                              help="motion.bvh / motion.c3d length unit: m | cm | mm; null: BVH in m, C3D in mm")
    rerun: bool = param(False, help="capture.rrd: the whole run for the Rerun viewer (eventcap view RUN_DIR; "
                                    "rerun-sdk)")
    rerun_events_ms: float = param(1.0, gt=0, help="each event image shows the events of the last this many ms")
    rerun_every_ms: float = param(1.0, gt=0, help="motion time between event images, ms")
    rerun_outline_every_ms: float = param(5.0, gt=0, help="motion time between silhouette outlines, ms (each costs "
                                                          "a rasterization)")
    rerun_max_frames: int = param(2000, ge=1, help="at most this many event images / outlines (the step widens)")

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any] | None) -> OutputsConfig:
        """Checked config from the ``outputs`` mapping: unknown keys, wrong types and values name ``outputs.<key>``."""
        from eventcap.core.config import build_settings

        cfg = build_settings(cls, values, "outputs")
        if cfg.poses is not None and cfg.poses.count(".") != 1:
            raise ValueError(f"outputs.poses: expected '<node>.<port>' (e.g. solve.poses) or null, got {cfg.poses!r}")
        return cfg


__all__ = ["OutputsConfig"]
