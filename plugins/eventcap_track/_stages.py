"""Run functions of the Sec. 3.1 stages (imported when a stage runs)."""

from __future__ import annotations

import numpy as np

from eventcap.artifacts.tracking import LatentFrames, SlicedTracks, Tracks


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


def _frame_index(latent: LatentFrames, t_us: int) -> int:
    i = int(np.searchsorted(latent.t_us, t_us))
    if i >= latent.t_us.size or latent.t_us[i] != t_us:
        raise ValueError(f"no sharpened frame at t = {t_us} us (the batch plan and the latent frames disagree)")
    return i


def to_tracks(ft) -> Tracks:
    """eklt.FeatureTracks -> the Tracks artifact."""
    xy = np.stack([ft.x, ft.y], axis=1).astype(np.float32) if ft.t_us.size else np.zeros((0, 2), np.float32)
    return Tracks(track_id=np.asarray(ft.track_id, np.int32), t_us=np.asarray(ft.t_us, np.int64), xy=xy,
                  cost=np.asarray(ft.cost, np.float32), kind=np.asarray(ft.kind, np.int8),
                  survived=np.asarray(ft.survived, bool))


def run_eklt(inputs, config, ctx):
    from . import eklt

    rec, latent, b = inputs["recording"], inputs["latent"], ctx.batch
    L0 = latent.log_images[_frame_index(latent, b.t0_us)]
    L1 = latent.log_images[_frame_index(latent, b.t1_us)]
    events = rec.events.window(b.t0_us, b.t1_us + 1)
    cfg = eklt.EkltConfig(patch_px=config.patch_px, max_features=config.max_features,
                          min_distance_px=config.min_distance_px, quality_level=config.quality_level,
                          warp=config.warp, update_every=config.update_every, max_cost=config.max_cost,
                          lag_gain=config.lag_gain, contrast_threshold=latent.contrast)
    if config.direction == "both":
        ft = eklt.track_bidirectional(L0, L1, events, b.t0_us, b.t1_us, stitch_px=config.stitch_px, config=cfg)
    elif config.direction in ("forward", "backward"):
        d = +1 if config.direction == "forward" else -1
        ft = eklt.track(L0 if d > 0 else L1, events, b.t0_us, b.t1_us, direction=d, config=cfg)
    else:
        raise ValueError(f"stages.track.direction: expected both | forward | backward, got {config.direction!r}")
    return {"tracks": to_tracks(ft)}


def run_klt_latent(inputs, config, ctx):
    from . import edi, eklt, klt

    rec, latent, b = inputs["recording"], inputs["latent"], ctx.batch
    L0 = latent.log_images[_frame_index(latent, b.t0_us)]
    events = rec.events.window(b.t0_us, b.t1_us + 1)
    times = np.arange(b.t0_us, b.t1_us + 1, config.step_us, dtype=np.int64)
    if times[-1] != b.t1_us:
        times = np.append(times, b.t1_us)
    latents = edi.latent_log_sequence(L0, b.t0_us, times, events, latent.contrast)
    det = eklt.EkltConfig(max_features=config.max_features, min_distance_px=config.min_distance_px,
                          quality_level=config.quality_level)
    features = eklt.detect_features(L0, None, det)

    def at(t_us: int) -> np.ndarray:
        return latents[int(np.searchsorted(times, t_us))]

    ft = klt.klt_latent(at, b.t0_us, b.t1_us, step_us=config.step_us, direction=+1,
                        config=klt.KltConfig(window_px=config.window_px, max_level=config.max_level),
                        features=features)
    return {"tracks": to_tracks(ft)}
