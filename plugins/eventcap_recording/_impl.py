"""The `recording` source: read a file into a Recording (the readers in eventcap.io do the decoding)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from eventcap.artifacts import BatchPlan
from eventcap.artifacts.recording import EventStream, FrameStack, Recording
from eventcap.io.checks import timing_note
from eventcap.io.convert import is_project_recording, recording_from_raw, roi_from_corners, window_from_seconds
from eventcap.core.stage import StageFailed


def _window_us(config) -> tuple[int, int] | None:
    try:
        return window_from_seconds(config.t_start_s, config.t_end_s)
    except ValueError as exc:
        raise ValueError(f"source.t_start_s/t_end_s: {exc}") from None


def _read_project(path: Path, config) -> Recording:
    import zarr

    if config.roi:
        raise ValueError("source.roi applies to external formats; crop a recording in the project's format "
                         "when converting it instead")
    rec = Recording.from_zarr(zarr.open_group(str(path), mode="r"), where=str(path))
    win = _window_us(config)
    if win is None:
        return rec
    t0, t1 = win
    ev = rec.events.window(t0, t1)
    frames = rec.frames
    if frames is not None:
        keep = (frames.t_us - frames.exposure_us // 2 >= t0) & (frames.t_us + frames.exposure_us // 2 < t1)
        frames = FrameStack(images=frames.images[keep], t_us=frames.t_us[keep], exposure_us=frames.exposure_us[keep],
                            height=frames.height, width=frames.width)
    # Ground truth is kept whole: it is indexed by time, and the window only narrows what the pipeline sees.
    return dataclasses.replace(rec, events=EventStream(events=ev.copy(), width=rec.width, height=rec.height),
                               frames=frames, source=f"{rec.source} [window {t0}-{t1} us]")


def _read_external(path: Path, config, ctx) -> Recording:
    from eventcap.io import read_recording

    win = _window_us(config)
    try:
        roi = roi_from_corners(config.roi) if config.roi else None
    except ValueError as exc:
        raise ValueError(f"source.{exc}") from None
    raw = read_recording(path, format=config.format or None, time_window_us=win, roi=roi,
                         width=config.width or None, height=config.height or None,
                         time_unit=config.time_unit or None, columns=list(config.columns) or None, y_up=config.y_up,
                         max_gap_s=config.max_gap_s or None)
    for r in raw.repairs:
        ctx.log.warning("%s: repaired: %s", path, r)
    grid = timing_note(raw.events["t"])
    if grid:
        ctx.log.warning("%s: %s", path, grid)
    if not config.calibration and raw.calibration is None:
        ctx.log.warning("%s has no calibration; using a nominal pinhole camera (set source.calibration)", path)
    return recording_from_raw(raw, calibration=config.calibration or None, roi=roi, name=path.stem,
                              hint="give source.calibration")


def _world_frame(rec: Recording, config, ctx) -> Recording:
    """A y-up world for a recording whose camera has no extrinsics (identity rotation, zero translation: every format
    but a synthetic capture's): the camera at the world's origin looking along -z, tilted by
    ``source.camera_pitch_deg`` / ``camera_roll_deg`` when given (kept: ``Recording.world`` 'level'), else assumed
    level until the detect stage measures the person's vertical and turns the world to it (``source.up=person``, the
    default: 'assumed_level'; ``source.up=level`` keeps it level: 'level'). ``source.up=camera`` keeps the camera's
    axes. The log states which."""
    from eventcap.camera import level_rotation

    cam = rec.camera
    if not (np.array_equal(cam.R, np.eye(3)) and not cam.t.any()):
        ctx.log.info("world frame: from the recording's camera extrinsics")
        return rec
    if config.up == "camera":
        ctx.log.warning("world frame: the camera's own axes (source.up=camera: y points DOWN, the head's y is below "
                        "the pelvis's)")
        return dataclasses.replace(rec, world="camera")
    if config.up not in ("person", "level"):
        raise ValueError(f"source.up: expected person, level or camera, got {config.up!r}")
    try:
        R = level_rotation(config.camera_pitch_deg, config.camera_roll_deg)
    except ValueError as exc:
        raise ValueError(f"source.camera_pitch_deg / camera_roll_deg: {exc}") from None
    given = bool(config.camera_pitch_deg or config.camera_roll_deg)
    if given:
        how = f"tilted as given: pitch {config.camera_pitch_deg:g} deg, roll {config.camera_roll_deg:g} deg"
    elif config.up == "level":
        how = "assumed level (source.up=level: kept; the detect stage compares it with the person's vertical)"
    else:
        how = ("assumed level until the detect stage measures the person's vertical and turns the world to it "
               "(source.up=person; source.up=level or camera_pitch_deg / camera_roll_deg keep a camera pose)")
    ctx.log.info("world frame: y up, the camera at the origin looking along -z, %s (the recording has no extrinsics)",
                 how)
    world = "assumed_level" if config.up == "person" and not given else "level"
    return dataclasses.replace(rec, camera=cam.with_pose(R, np.zeros(3)), world=world)


def run_recording(inputs, config, ctx):
    if not config.path:
        raise StageFailed("source=recording needs source.path=<file or folder>", status="missing_file")
    path = Path(config.path)
    if not path.exists():
        raise FileNotFoundError(f"source.path: {path} does not exist")
    if config.format == "eventcap" or (not config.format and is_project_recording(path)):
        rec = _read_project(path, config)
    else:
        rec = _read_external(path, config, ctx)
    rec = _world_frame(rec, config, ctx)
    if inputs.get("template") is not None and rec.template is None:
        rec = dataclasses.replace(rec, template=inputs["template"])
    if not config.frames and rec.frames is not None:
        ctx.log.info("source.frames=false: %d intensity frames of %s left out (an event-only recording)",
                     rec.frames.t_us.size, path)
        rec = dataclasses.replace(rec, frames=None, source=f"{rec.source} [frames left out]")
    t = rec.frames.t_us if rec.frames is not None else np.zeros(0, np.int64)
    if t.size >= 2:
        return {"recording": rec, "batches": BatchPlan.between_frames(t)}
    ev = rec.events.events["t"]
    if config.batch_rate_hz <= 0:
        raise ValueError(f"source.batch_rate_hz: expected a rate > 0 Hz to cut {path} (it has {t.size} intensity "
                         f"frames) into batches, got {config.batch_rate_hz}")
    plan = BatchPlan.at_rate(int(ev[0]), int(ev[-1]), config.batch_rate_hz) if ev.size else BatchPlan.between_frames(t)
    ctx.log.info("%s has %d intensity frames: %d batches of %.1f ms from the events (source.batch_rate_hz=%g); "
                 "images reconstructed from the events stand in for frames with pipeline=events_only", path, t.size,
                 len(plan), 1e3 / config.batch_rate_hz, config.batch_rate_hz)
    return {"recording": rec, "batches": plan}
