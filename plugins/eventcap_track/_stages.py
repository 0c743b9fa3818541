"""Run functions of the Sec. 3.1 stages (imported when a stage runs)."""

from __future__ import annotations

import numpy as np

from eventcap.artifacts.tracking import LatentFrames, SlicedTracks


def run_edi(inputs, config, ctx):
    from . import edi

    rec = inputs["recording"]
    frames = rec.require_frames("edi")
    events = rec.events.events
    estimated = config.contrast <= 0
    if estimated:
        est = edi.estimate_contrast(frames.images, frames.t_us, frames.exposure_us, events,
                                    c_range=(config.c_min, config.c_max), eps=config.eps)
        c = float(est.c)
        ctx.log.info("EDI contrast threshold estimated at C = %.4f (%d pixel residuals)", c, est.n_pixels)
    else:
        c = float(config.contrast)
    logs = edi.sharpen_frames(frames.images, frames.t_us, frames.exposure_us, events, c, config.eps)
    return {"latent": LatentFrames(log_images=logs.astype(np.float32), t_us=frames.t_us.copy(), contrast=c,
                                   eps=config.eps, contrast_estimated=estimated, height=rec.height, width=rec.width)}


def run_bspline(inputs, config, ctx):
    from . import bspline

    tr, b = inputs["tracks"], ctx.batch
    s = bspline.slice_trajectories(tr.track_id, tr.t_us, tr.xy.astype(np.float64), b.t0_us, b.t1_us,
                                   rate_hz=config.rate_hz, sigma_px=config.sigma_px,
                                   accel_px_s2=config.accel_px_s2, knot_spacing_us=config.knot_spacing_us)
    return {"sliced": SlicedTracks(t_us=np.asarray(s.t_us, np.int64), xy=np.asarray(s.xy, np.float32),
                                   valid=np.asarray(s.valid, bool), track_id=np.asarray(s.track_id, np.int32))}
