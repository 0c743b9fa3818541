"""The `recording` source: read a file into a Recording (the readers in eventcap.io do the decoding)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from eventcap.artifacts import BatchPlan
from eventcap.artifacts.recording import EventStream, FrameStack, Recording
from eventcap.camera import Camera, read_rpg_calibration
from eventcap.stage import StageFailed


def is_project_recording(path: Path) -> bool:
    """A directory holding a zarr group written from a Recording artifact."""
    meta = path / "zarr.json"
    return path.is_dir() and meta.is_file() and '"Recording"' in meta.read_text()


def _window_us(config) -> tuple[int, int] | None:
    if config.t_start_s == 0.0 and config.t_end_s == 0.0:
        return None
    if config.t_start_s < 0 or (config.t_end_s and config.t_end_s <= config.t_start_s):
        raise ValueError(f"source.t_start_s/t_end_s: expected 0 <= start < end, got {config.t_start_s}, "
                         f"{config.t_end_s}")
    end = int(round(config.t_end_s * 1e6)) if config.t_end_s else np.iinfo(np.int64).max // 2
    return int(round(config.t_start_s * 1e6)), end


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


def _nominal_camera(width: int, height: int) -> Camera:
    # Without a calibration the intrinsics are a guess (about 65 degrees horizontal field of view); say so.
    f = 0.78 * width
    return Camera(width, height, f, f, (width - 1) / 2, (height - 1) / 2)


def _read_external(path: Path, config, ctx) -> Recording:
    from eventcap.io import read_recording

    win = _window_us(config)
    raw = read_recording(path, format=config.format or None, time_window_us=win,
                         roi=tuple(config.roi) if config.roi else None,
                         width=config.width or None, height=config.height or None)
    for r in raw.repairs:
        ctx.log.warning("%s: repaired: %s", path, r)
    if config.calibration:
        cam = read_rpg_calibration(config.calibration, raw.width, raw.height)
        cal_note = f"calibration {config.calibration}"
    elif raw.calibration is not None:
        cam, cal_note = raw.calibration, "calibration from the file"
    else:
        cam = _nominal_camera(raw.width, raw.height)
        cal_note = "UNCALIBRATED: nominal pinhole intrinsics (give source.calibration)"
        ctx.log.warning("%s has no calibration; using a nominal pinhole camera (set source.calibration)", path)
    frames = None
    if raw.frames is not None:
        exp = raw.frames.exposure_us if raw.frames.exposure_us is not None else np.zeros(len(raw.frames), np.int64)
        frames = FrameStack(images=np.clip(raw.frames.images, 0.0, 1.0).astype(np.float32),
                            t_us=np.asarray(raw.frames.t_us, np.int64), exposure_us=np.asarray(exp, np.int64),
                            height=raw.height, width=raw.width)
    return Recording(events=EventStream(events=np.asarray(raw.events).copy(), width=raw.width, height=raw.height),
                     camera=cam, frames=frames, name=path.stem,
                     source=f"{raw.format}: {path} (t_offset_us={raw.t_offset_us}; {cal_note}; "
                            f"repairs: {'; '.join(raw.repairs) or 'none'})")


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
    if inputs.get("template") is not None and rec.template is None:
        rec = dataclasses.replace(rec, template=inputs["template"])
    t = rec.frames.t_us if rec.frames is not None else np.zeros(0, np.int64)
    if t.size < 2:
        ctx.log.warning("%s has %d intensity frames: no batches (stages that need frames will say so)", path, t.size)
    plan = BatchPlan.between_frames(t) if t.size >= 2 else BatchPlan(
        t0_us=np.zeros(0, np.int64), t1_us=np.zeros(0, np.int64), frame0=np.zeros(0, np.int64))
    return {"recording": rec, "batches": plan}
