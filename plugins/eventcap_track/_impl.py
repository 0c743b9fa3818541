"""Run functions of the tracking stages (eklt, klt_latent, oracle) and of slicing (bspline), paper Sec. 3.1; imported
when a stage runs."""

from __future__ import annotations

import numpy as np

from eventcap.artifacts.tracking import LatentFrames, SlicedTracks, Tracks


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


def actor_mask(inputs, config, t_us: int, height: int, width: int, log) -> np.ndarray | None:
    """Feature-detection region at t_us: the bounding box of the confident 2D keypoints of the detection at that
    frame grown by ``roi_margin_px`` (None = the whole image: roi=image, no detections wired, or none usable)."""
    if config.roi not in ("actor", "image"):
        raise ValueError(f"stages.track.roi: expected actor | image, got {config.roi!r}")
    det = inputs.get("detections")
    if config.roi == "image" or det is None:
        return None
    k = int(np.searchsorted(det.t_us, t_us))
    if k >= det.t_us.size or det.t_us[k] != t_us:
        log.warning("no detection at t = %d us: features detected on the whole image", t_us)
        return None
    ok = det.confidence_2d[k] > 0.1
    if ok.sum() < 3:
        log.warning("fewer than 3 confident keypoints at t = %d us: features detected on the whole image", t_us)
        return None
    kp = det.keypoints_2d[k][ok]
    m = float(config.roi_margin_px)
    x0, y0 = np.floor(kp.min(axis=0) - m).astype(int)
    x1, y1 = np.ceil(kp.max(axis=0) + m).astype(int)
    mask = np.zeros((height, width), bool)
    mask[max(y0, 0):max(min(y1 + 1, height), 0), max(x0, 0):max(min(x1 + 1, width), 0)] = True
    return mask if mask.any() else None


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
                          lag_gain=config.lag_gain, relocate_radius_px=config.relocate_radius_px,
                          contrast_threshold=latent.contrast)
    h, w = L0.shape
    m0 = actor_mask(inputs, config, b.t0_us, h, w, ctx.log)
    m1 = actor_mask(inputs, config, b.t1_us, h, w, ctx.log)
    if config.direction == "both":
        ft = eklt.track_bidirectional(L0, L1, events, b.t0_us, b.t1_us, stitch_px=config.stitch_px, config=cfg,
                                      mask_0=m0, mask_1=m1)
    elif config.direction in ("forward", "backward"):
        d = +1 if config.direction == "forward" else -1
        ft = eklt.track(L0 if d > 0 else L1, events, b.t0_us, b.t1_us, direction=d, config=cfg,
                        mask=m0 if d > 0 else m1)
    else:
        raise ValueError(f"stages.track.direction: expected both | forward | backward, got {config.direction!r}")
    return {"tracks": to_tracks(ft)}


def run_klt_latent(inputs, config, ctx):
    from eventcap.imaging import edi

    from . import eklt, klt

    rec, latent, b = inputs["recording"], inputs["latent"], ctx.batch
    L0 = latent.log_images[_frame_index(latent, b.t0_us)]
    events = rec.events.window(b.t0_us, b.t1_us + 1)
    times = np.arange(b.t0_us, b.t1_us + 1, config.step_us, dtype=np.int64)
    if times[-1] != b.t1_us:
        times = np.append(times, b.t1_us)
    latents = edi.latent_log_sequence(L0, b.t0_us, times, events, latent.contrast)
    det = eklt.EkltConfig(max_features=config.max_features, min_distance_px=config.min_distance_px,
                          quality_level=config.quality_level)
    features = eklt.detect_features(L0, actor_mask(inputs, config, b.t0_us, *L0.shape, ctx.log), det)

    def at(t_us: int) -> np.ndarray:
        return latents[int(np.searchsorted(times, t_us))]

    ft = klt.klt_latent(at, b.t0_us, b.t1_us, step_us=config.step_us, direction=+1,
                        config=klt.KltConfig(window_px=config.window_px, max_level=config.max_level),
                        features=features)
    return {"tracks": to_tracks(ft)}


def run_oracle(inputs, config, ctx):
    """Tracks of the synthetic capture's ground-truth surface points (GroundTruth.track_px) over the batch: each
    point's longest run of visible 1 kHz samples inside [t0, t1] (>= 2 samples), plus optional Gaussian noise."""
    rec, b = inputs["recording"], ctx.batch
    gt = rec.ground_truth
    name = rec.name or rec.source or "(unnamed)"
    if gt is None or gt.track_px is None or gt.track_visible is None:
        raise ValueError(f"stage 'oracle' needs ground-truth surface tracks (a synthetic recording), but recording "
                         f"{name!r} has none: use a real tracker (stages/track=eklt)")
    if config.max_tracks < 1 or config.noise_px < 0:
        raise ValueError(f"stages.track: max_tracks must be >= 1 and noise_px >= 0, got {config.max_tracks}, "
                         f"{config.noise_px}")
    sel = (gt.t_us >= b.t0_us) & (gt.t_us <= b.t1_us)
    t = np.asarray(gt.t_us[sel], np.int64)
    px = np.asarray(gt.track_px[sel][:, : config.max_tracks], np.float64)
    vis = np.asarray(gt.track_visible[sel][:, : config.max_tracks], bool)
    ids, times, xy, survived = [], [], [], []
    for h in range(vis.shape[1]):
        run = _longest_run(vis[:, h])
        if run is None:
            continue
        a, e = run
        ids.append(np.full(e - a, len(survived), np.int32))
        times.append(t[a:e])
        xy.append(px[a:e, h])
        survived.append(e == t.size)
    if not ids:
        return {"tracks": Tracks(track_id=np.zeros(0, np.int32), t_us=np.zeros(0, np.int64),
                                 xy=np.zeros((0, 2), np.float32), cost=np.zeros(0, np.float32),
                                 kind=np.zeros(0, np.int8), survived=np.zeros(0, bool))}
    xy = np.concatenate(xy)
    if config.noise_px > 0:
        xy = xy + ctx.rng(config.seed).normal(0.0, config.noise_px, xy.shape)
    ctx.log.info("oracle tracks (simulated, exact ground truth%s): %d tracks, %d samples",
                 f" + {config.noise_px} px noise" if config.noise_px else "", len(survived), xy.shape[0])
    return {"tracks": Tracks(track_id=np.concatenate(ids), t_us=np.concatenate(times), xy=xy.astype(np.float32),
                             cost=np.zeros(xy.shape[0], np.float32), kind=np.full(len(survived), 3, np.int8),
                             survived=np.asarray(survived, bool))}


def _longest_run(mask: np.ndarray) -> tuple[int, int] | None:
    """[start, end) of the longest run of True (at least 2 long), or None."""
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
    if starts.size == 0:
        return None
    k = int(np.argmax(ends - starts))
    return (int(starts[k]), int(ends[k])) if ends[k] - starts[k] >= 2 else None
