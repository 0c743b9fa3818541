"""Run function of the `reconstruct` stage (imported when it runs)."""

from __future__ import annotations

import dataclasses

import numpy as np

from eventcap.artifacts.recording import FrameStack
from eventcap.artifacts.tracking import LatentFrames
from eventcap.imaging.reconstruct import reconstruct, to_intensity, to_log_images
from eventcap.core.stage import StageFailed


def run_reconstruct(inputs, config, ctx):
    rec, plan = inputs["recording"], inputs["batches"]
    if config.cutoff_rad_s < 0 or config.contrast <= 0 or config.eps <= 0 or config.smooth_px < 0:
        raise ValueError(f"stages.reconstruct: expected cutoff_rad_s >= 0, contrast > 0, eps > 0 and smooth_px >= 0, "
                         f"got {config.cutoff_rad_s}, {config.contrast}, {config.eps}, {config.smooth_px}")
    if not 0 < config.base_intensity <= 1:
        raise ValueError(f"stages.reconstruct.base_intensity: expected a linear intensity in (0, 1], got "
                         f"{config.base_intensity}")
    if config.baseline not in ("median", "none"):
        raise ValueError(f"stages.reconstruct.baseline: expected median | none, got {config.baseline!r}")
    if config.exposure_us < 0:
        raise ValueError(f"stages.reconstruct.exposure_us: expected >= 0 us, got {config.exposure_us}")
    name = rec.name or rec.source or "(unnamed)"
    if len(plan) == 0:
        raise StageFailed(f"recording {name!r}: the batch plan is empty, so there is no time to reconstruct an image "
                          f"at (a recording shorter than one batch? see source.batch_rate_hz)", status="no_batches")
    times = np.unique(np.concatenate([plan.t0_us, plan.t1_us]))
    rel = reconstruct(rec.events.events, rec.height, rec.width, times, cutoff_rad_s=config.cutoff_rad_s,
                      contrast=config.contrast, baseline=config.baseline, smooth_px=config.smooth_px)
    logs = to_log_images(rel, eps=config.eps, base_intensity=config.base_intensity)
    exposure = int(config.exposure_us)
    frames = FrameStack(images=to_intensity(logs, config.eps), t_us=times, exposure_us=np.full(times.size, exposure,
                                                                                                np.int64),
                        height=rec.height, width=rec.width, origin="events")
    gt = rec.ground_truth
    if gt is not None and gt.frame_t_us is None and rec.frames is not None:
        # The ground truth's frame poses / sharp images belong to the frames replaced here: keep their times.
        gt = dataclasses.replace(gt, frame_t_us=rec.frames.t_us.copy())
    if rec.frames is not None:
        ctx.log.info("reconstruct: recording %r has %d intensity frames; the %d reconstructions replace them "
                     "downstream (an event-only run)", name, rec.frames.t_us.size, times.size)
    out = dataclasses.replace(rec, frames=frames, ground_truth=gt,
                              source=f"{rec.source} [frames reconstructed from events]")
    ctx.log.info("reconstruct: %d images from %d events (high-pass, cutoff %g rad/s, C = %g, baseline %s), declared exposure "
                 "%.1f ms; %.0f%% of pixels changed in the median image", times.size, rec.events.events.size,
                 config.cutoff_rad_s, config.contrast, config.baseline, exposure / 1e3,
                 100 * float(np.median((np.abs(rel) > 0.5 * config.contrast).mean(axis=(1, 2)))))
    latent = LatentFrames(log_images=logs, t_us=times.copy(), contrast=float(config.contrast), eps=float(config.eps),
                          contrast_estimated=False, height=rec.height, width=rec.width)
    return {"latent": latent, "recording": out}
