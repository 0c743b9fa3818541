"""Run function of the sharpen stage (EDI, paper Sec. 3.1, Eq. 2; imported when the stage runs)."""

from __future__ import annotations

import numpy as np

from eventcap.artifacts.tracking import LatentFrames


def run_edi(inputs, config, ctx):
    from eventcap.imaging import edi

    rec = inputs["recording"]
    frames = rec.require_frames("edi")
    events = rec.events.events
    estimated = config.contrast <= 0
    if estimated:
        est = edi.estimate_contrast(frames.images, frames.t_us, frames.exposure_us, events,
                                    c_range=(config.c_min, config.c_max), eps=config.eps)
        c = float(est.c)
        ctx.log.info("EDI contrast threshold estimated at C = %.4f (%d pixel residuals)", c, est.n_pixels)
        ctx.stats.update({"contrast": c, "contrast_at_range_edge": est.at_range_edge})
        if est.at_range_edge:
            ctx.log.warning("EDI contrast threshold C = %.4f is at the edge of its search range [%g, %g]: the best C "
                            "may lie outside it (widen stages.sharpen.c_min / c_max, or set stages.sharpen.contrast)",
                            c, config.c_min, config.c_max)
    else:
        c = float(config.contrast)
    logs = edi.sharpen_frames(frames.images, frames.t_us, frames.exposure_us, events, c, config.eps)
    return {"latent": LatentFrames(log_images=logs.astype(np.float32, copy=False), t_us=frames.t_us.copy(), contrast=c,
                                   eps=config.eps, contrast_estimated=estimated, height=rec.height, width=rec.width)}
