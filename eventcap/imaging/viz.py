"""Pictures of recordings for people: frames, accumulated events and the projected skeleton, side by side."""

from __future__ import annotations

import numpy as np

from eventcap.body.skeleton import PARENTS

#: BGR colours
_POS = np.array([60, 60, 230], np.uint8)  # red: positive events
_NEG = np.array([230, 120, 40], np.uint8)  # blue: negative events


def to_bgr(gray: np.ndarray) -> np.ndarray:
    """(H,W) uint8 or float in [0,1] -> (H,W,3) uint8."""
    g = gray if gray.dtype == np.uint8 else np.clip(gray * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return np.repeat(g[..., None], 3, axis=2)


def event_image(events: np.ndarray, height: int, width: int, background: np.ndarray | None = None) -> np.ndarray:
    """Accumulated events as colours (red = positive, blue = negative, by the sign of the per-pixel sum)."""
    img = np.full((height, width, 3), 255, np.uint8) if background is None else background.copy()
    if events.size:
        acc = np.zeros((height, width), np.int32)
        np.add.at(acc, (events["y"].astype(np.intp), events["x"].astype(np.intp)), events["p"].astype(np.int32))
        img[acc > 0] = _POS
        img[acc < 0] = _NEG
    return img


def draw_skeleton(img: np.ndarray, joints_px: np.ndarray, landmarks_px: np.ndarray | None = None,
                  colour=(40, 200, 40), scale: int = 1) -> np.ndarray:
    """Bones between projected joints (24,2) [and landmark dots], on a copy of a BGR image scaled by ``scale``."""
    import cv2

    out = img.copy()
    j = np.round(joints_px * scale).astype(int)
    for child, parent in enumerate(PARENTS):
        if parent >= 0:
            cv2.line(out, tuple(j[parent]), tuple(j[child]), colour, max(1, scale // 2), cv2.LINE_AA)
    for p in j:
        cv2.circle(out, tuple(p), max(1, scale), (0, 220, 255), -1, cv2.LINE_AA)
    if landmarks_px is not None:
        for p in np.round(landmarks_px * scale).astype(int):
            cv2.circle(out, tuple(p), max(1, scale // 2), (255, 0, 255), -1, cv2.LINE_AA)
    return out


def image_times(rec, rate_hz: float = 25.0, frame_index: int | None = None) -> tuple[np.ndarray, str]:
    """The times a preview shows: the intensity frames, else those of the ground truth's sharp images (an event-only
    synthetic capture), else every 1/rate_hz from the first event; and what they are. For the last kind, only the
    time of image ``frame_index`` (clipped to the recording) is returned when it is given: memory does not grow
    with the recording's time span."""
    if rec.frames is not None and rec.frames.t_us.size:
        return np.asarray(rec.frames.t_us, np.int64), "frame"
    gt = rec.ground_truth
    if gt is not None and gt.frame_t_us is not None and gt.frame_t_us.size:
        return np.asarray(gt.frame_t_us, np.int64), "image"
    t = rec.events.events["t"]
    if t.size == 0:
        raise ValueError(f"recording {rec.name or rec.source or '(unnamed)'!r} has neither intensity frames nor "
                         f"events: nothing to show")
    period = 1e6 / rate_hz
    count = int((int(t[-1]) - int(t[0])) // period) + 1
    if frame_index is not None:
        k = int(np.clip(frame_index, 0, count - 1))
        return np.array([int(t[0]) + int(round(k * period))], np.int64), "image"
    return int(t[0]) + np.round(np.arange(count) * period).astype(np.int64), "image"


#: Pixels of one enlarged panel beyond which a picture is refused (a 4096 x 4096 panel; six of them are ~300 MB).
MAX_PANEL_PIXELS = 4096 * 4096


def check_picture_size(width: int, height: int, scale: int) -> None:
    """Refuse a picture whose panels would be enormous (a declared sensor of 65,535 px would ask for gigabytes)."""
    if not (isinstance(scale, int) and scale >= 1):
        raise ValueError(f"scale: expected an integer >= 1, got {scale!r}")
    px = int(width) * int(height) * scale * scale
    if px > MAX_PANEL_PIXELS:
        raise ValueError(f"a {width} × {height} sensor at scale {scale} makes {width * scale} × {height * scale} "
                         f"panels ({px * 3 / 2**30:.1f} GiB each): larger than any event camera's; use a smaller "
                         f"scale, or check the recording's declared size")


def most_active_time(events: np.ndarray, window_us: int = 20_000) -> tuple[int, int]:
    """The centre (µs) of the ``window_us`` window holding the most events, and that count: the recording's most
    active moment (windows start every ``window_us / 8`` from the first event; the first of equal ones wins).
    ``(0, 0)`` without events. Memory and time grow with the events, not with the time they span: a best window
    can always be moved forward to start in the grid cell of its first event, so only those cells are counted,
    then the earliest start with the same count is looked for just before the best ones."""
    t = events["t"]
    if t.size == 0:
        return 0, 0
    t0, window = int(t[0]), int(window_us)
    step = max(1, window // 8)
    last_k = (max(int(t[-1]) - window, t0) - t0 + step - 1) // step  # starts t0 + k*step < max(t[-1] - w, t0) + step

    def counts(ks: np.ndarray) -> np.ndarray:
        starts = t0 + ks * step
        return np.searchsorted(t, starts + window) - np.searchsorted(t, starts)

    own = np.unique(np.minimum((t.astype(np.int64) - t0) // step, last_k))
    c = counts(own)
    best = int(c.max())
    reach = -(-window // step)  # an earlier start holds the same events only within this many steps
    near = np.unique((own[c == best][:, None] - np.arange(reach + 1)[None, :]).ravel())
    near = near[near >= 0]
    k = int(near[np.argmax(counts(near) == best)])
    return t0 + k * step + window // 2, best


def describe_recording(rec) -> str:
    """What a recording holds, in one line: sensor size, events, duration, event rate, frames, camera, source."""
    t = rec.events.events["t"]
    dur = (int(t[-1]) - int(t[0])) / 1e6 if t.size else 0.0
    rate = f", {t.size / dur / 1e6:.3g} M events/s" if dur > 0 else ""
    n_frames = 0 if rec.frames is None else int(rec.frames.t_us.size)
    frames = "no intensity frames (an event-only recording)" if not n_frames else \
        f"{n_frames} intensity frame{'s' if n_frames != 1 else ''}"
    gt = ", ground truth" if rec.ground_truth is not None else ""
    return (f"{rec.width} x {rec.height} px, {t.size:,} events over {dur:.3f} s{rate}, {frames}{gt}; "
            f"{rec.source or rec.name}")


def recording_overview(rec, frame_index: int | None = 1, scale: int = 2, window_us: int = 10_000, latent=None,
                       reconstruct: bool | None = None, rate_hz: float = 25.0, t_us: int | None = None) -> np.ndarray:
    """One picture of a Recording at an intensity frame: blurry frame | EDI-sharpened frame (if ``latent``, a
    LatentFrames, is given) | reconstruction from the events alone (``reconstruct``; default: only when the
    recording has no frames) | true sharp image (if known) | events within ±window_us of the frame | frame (or
    reconstruction) with the ground-truth skeleton projected (if known).

    Event-only recordings have no frame: image ``frame_index`` is at the ground truth's image times (synthetic
    ``source.frames=false``) or every 1/rate_hz from the first event. ``t_us`` (instead of ``frame_index``) shows
    the frame nearest that time, or for an event-only recording the image at exactly that time."""
    import cv2

    from eventcap.imaging.reconstruct import DEFAULT_BASELINE, DEFAULT_CUTOFF_RAD_S, reconstruct as events_to_images
    from eventcap.imaging.reconstruct import to_intensity, to_log_images

    check_picture_size(rec.width, rec.height, scale)
    times, what = image_times(rec, rate_hz, None if t_us is not None else (frame_index or 0))
    has_frames = what == "frame"
    if reconstruct is None:
        reconstruct = not has_frames
    if t_us is not None and not has_frames:
        times = np.array([int(t_us)], np.int64)
        frame_index = 0
    elif t_us is not None:
        frame_index = int(np.argmin(np.abs(times - int(t_us))))
    k = int(np.clip(frame_index or 0, 0, times.size - 1))
    t = int(times[k])
    h, w = rec.height, rec.width
    panels = []
    if has_frames:
        panels.append(("frame %d (t=%.3f s)" % (k, t / 1e6), to_bgr(rec.frames.images[k])))
    base = to_bgr(rec.frames.images[k]) if has_frames else None
    if latent is not None:
        lk = int(np.argmin(np.abs(latent.t_us - t)))
        lin = np.clip(np.exp(latent.log_images[lk].astype(np.float64)) - latent.eps, 0.0, 1.0)
        panels.append((f"EDI sharpened (C={latent.contrast:.3f})", to_bgr(lin)))
    if reconstruct:
        rel = events_to_images(rec.events.events, h, w, [t])
        img = to_bgr(to_intensity(to_log_images(rel))[0])
        title = f"from events only (t={t / 1e6:.3f} s)" if not has_frames else "from events only"
        panels.append((title + f", high-pass {DEFAULT_CUTOFF_RAD_S:g} rad/s - {DEFAULT_BASELINE}", img))
        base = img if base is None else base
    gt = rec.ground_truth
    gt_k = None
    if gt is not None and gt.frame_joints.shape[0]:
        gt_t = gt.frame_t_us if gt.frame_t_us is not None else (rec.frames.t_us if has_frames else None)
        if gt_t is not None and gt_t.size == gt.frame_joints.shape[0] and np.any(gt_t == t):
            gt_k = int(np.flatnonzero(gt_t == t)[0])
    if gt_k is not None and gt.sharp_images is not None:
        panels.append(("true sharp image", to_bgr(gt.sharp_images[gt_k])))
    ev = rec.events.window(t - window_us, t + window_us)
    panels.append((f"events +-{window_us / 1000:.0f} ms ({ev.size})", event_image(ev, h, w)))
    if gt is not None:
        jp = rec.camera.project(gt.frame_joints[gt_k]) if gt_k is not None else None
        lm_i = int(np.argmin(np.abs(gt.t_us - t)))
        lp = rec.camera.project(gt.landmarks[lm_i])
        if jp is None:  # joints at the nearest ground-truth sample
            jp = rec.camera.project(gt.joints[lm_i])
        big = cv2.resize(base if base is not None else event_image(ev, h, w), (w * scale, h * scale),
                         interpolation=cv2.INTER_NEAREST)
        panels.append(("ground-truth skeleton", draw_skeleton(big, jp, lp, scale=scale)))
    tiles = []
    for title, img in panels:
        if img.shape[0] != h * scale:
            img = cv2.resize(img, (w * scale, h * scale), interpolation=cv2.INTER_NEAREST)
        img = img.copy()
        label(img, title, (4, 14), 0.4)
        tiles.append(img)
    return np.concatenate(tiles, axis=1)


def tracks_overview(rec, latent, sliced, batch, scale: int = 3) -> np.ndarray:
    """Sliced feature tracks of one batch drawn over (left) the EDI-sharpened frame at the batch start and (right)
    the events accumulated over the batch; each track a colour, its 1 ms samples joined, its end dotted."""
    import cv2

    k = int(np.searchsorted(latent.t_us, batch.t0_us))
    base = to_bgr(np.clip(np.exp(latent.log_images[k].astype(np.float64)) - latent.eps, 0.0, 1.0))
    ev = rec.events.window(batch.t0_us, batch.t1_us)
    panels = [base, event_image(ev, rec.height, rec.width)]
    rng = np.random.default_rng(0)
    colours = [tuple(int(c) for c in rng.integers(40, 230, 3)) for _ in range(sliced.xy.shape[1])]
    out = []
    for img in panels:
        big = cv2.resize(img, (rec.width * scale, rec.height * scale), interpolation=cv2.INTER_NEAREST)
        for h in range(sliced.xy.shape[1]):
            ok = sliced.valid[:, h]
            if ok.sum() < 2:
                continue
            pts = np.round(sliced.xy[ok, h] * scale).astype(np.int32)
            cv2.polylines(big, [pts.reshape(-1, 1, 2)], False, colours[h], 1, cv2.LINE_AA)
            cv2.circle(big, tuple(pts[-1]), 2, colours[h], -1, cv2.LINE_AA)
        out.append(big)
    title = f"batch {batch.index}: {int(sliced.valid.any(axis=0).sum())} tracks, {ev.size} events"
    img = np.concatenate(out, axis=1)
    label(img, title, (6, 18), 0.5)
    return img


def label(img: np.ndarray, text: str, org: tuple[int, int], scale: float = 0.42) -> None:
    """White text on a darkened box, readable on any background. (A thicker black copy of the text as an outline
    does not work with OpenCV's Hershey fonts: the glyph advance grows with the thickness, so the two copies drift
    apart along the line.)"""
    import cv2

    (w, h), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    x, y = org
    box = img[max(0, y - h - 3):min(img.shape[0], y + base + 1), max(0, x - 3):min(img.shape[1], x + w + 3)]
    box //= 3
    cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1, cv2.LINE_AA)
