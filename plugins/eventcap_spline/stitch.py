"""Joining the windows of the spline solve into one motion without seams (not in the paper).

Each batch's task solves a window of several batches (:mod:`.solve`) and returns the window's whole curve.
Neighbouring windows overlap but disagree slightly (each sees its own batch's events and different detections at
its far ends). Keeping only each batch's own interval leaves a jump where two batches meet: a speed spike at every
batch boundary, the largest part of the velocity error (docs/results/implementation.md).

``stitch`` (whole recording) blends the windows instead: at every tracking frame t,

    S(t) = Σ_k w_k(t) S_k(t) / Σ_k w_k(t),

with w_k a C² bump over window k's span (the quintic smoothstep 6u⁵ - 15u⁴ + 10u³ over the first and last
``taper`` of the window, or over its overlap with its neighbour where that is shorter, 1 between; a window's end at
the start or end of the recording is not tapered, so every frame has weight; likewise a window's end at the edge of a
gap). Where windows overlap little (two chunks' windows across their margins) the later one so takes over across the
whole stretch both solved, the weights summing to 1 there: bumps over each whole window would both be near 0 there
and hand over within a few tens of ms, a quick jump wherever two chunks disagree. With ``stages.solve.window_step`` > 1 only every
few batches solve a window (each keeping a run of batches); the others return no frames (status ``in_window``: not
a gap) and the windows that exist are blended the same way. Each S_k is a C² cubic B-spline and every weight
and its first two derivatives vanish at the window's ends, so the blend is C² everywhere: no seam, and overlapping
windows average their errors. A window's estimate spans its frames that hold an observation (the spline stage leaves
NaN beyond them: never extrapolated); a window that saw nothing (status ``gap``) is left out; the times no window
covers are a gap: NaN, never interpolated. Root angles
are moved by multiples of 2π so each window continues the ones before it. ``cut`` (per batch) gives each batch its
frames of the blended motion, so everything downstream (evaluate, outputs) keeps the batch boundaries.

Each window's joint σ (the Laplace approximation of its solve, ``PoseSequence.sigma_mm``) is blended with the same
weights, as variances (:func:`blend_sigma`), and cut with the poses. Where windows overlap and disagree, the blend
is neither window's estimate: given the body they pose (the ``template`` input), each joint's spread of the windows
about the blend (after removing each window's mean over the joints, as the error is measured after a rigid
alignment) is added to its variance, the variance of a mixture (:func:`disagreement_mm`). Two chunks that solved
their shared stretch differently are marked as uncertain there as they are.
"""

from __future__ import annotations

import math

import numpy as np

from eventcap.artifacts.pose import PoseSequence
from eventcap.core.stage import StageFailed


def smootherstep(u: np.ndarray) -> np.ndarray:
    """6u⁵ - 15u⁴ + 10u³ on [0, 1] (0 below, 1 above): its first and second derivatives vanish at both ends."""
    u = np.clip(u, 0.0, 1.0)
    return u * u * u * (u * (6.0 * u - 15.0) + 10.0)


def window_weight(t_us: np.ndarray, a_us: int, b_us: int, ramp_start_us: float | None, ramp_end_us: float | None):
    """Blending weight of a window spanning [a_us, b_us] at times t_us (0 outside): the quintic smoothstep over
    ``ramp_start_us`` after its start and ``ramp_end_us`` before its end (None: that end not tapered), 1 between."""
    t = np.asarray(t_us, dtype=np.float64)
    w = np.ones_like(t)
    if ramp_start_us is not None:
        w *= smootherstep((t - a_us) / max(float(ramp_start_us), 1.0))
    if ramp_end_us is not None:
        w *= smootherstep((b_us - t) / max(float(ramp_end_us), 1.0))
    return np.where((t >= a_us) & (t <= b_us), w, 0.0)


def ramps_us(spans: list[tuple[int, int]], taper: float) -> list[tuple[float | None, float | None]]:
    """Each window's ramps (µs) at its start and end, from the windows' spans [(a, b)]: ``taper`` of its length,
    or its overlap with the windows around it where that is shorter (so that where two windows meet, as two chunks'
    windows do across their margins, the later one takes over across the whole stretch both solved: their weights
    then sum to 1 there, no quick switch in its middle); None at an end nothing overlaps (the recording's ends, the
    edges of gaps, where two windows only touch). In O(K log K): the overlap before a window's start is with the
    latest end of the windows that start before it, the overlap before its end with the earliest start of the
    windows that end after it."""
    if not spans:
        return []
    a, b = (np.asarray(x, dtype=np.float64) for x in zip(*spans))
    k = a.size
    by_a = np.argsort(a, kind="stable")
    n_before = np.searchsorted(a[by_a], a, side="left")  # windows starting strictly earlier
    latest_end = np.maximum.accumulate(b[by_a])[np.maximum(n_before - 1, 0)]
    before = np.where((n_before > 0) & (latest_end > a), np.minimum(latest_end, b) - a, 0.0)
    by_b = np.argsort(b, kind="stable")
    first_after = np.searchsorted(b[by_b], b, side="right")  # windows ending strictly later
    earliest_start = np.minimum.accumulate(a[by_b][::-1])[::-1][np.minimum(first_after, k - 1)]
    after = np.where((first_after < k) & (earliest_start < b), b - np.maximum(earliest_start, a), 0.0)
    full = taper * (b - a)
    return [(float(min(f, x)) if x > 0 else None, float(min(f, y)) if y > 0 else None)
            for f, x, y in zip(full, before, after)]


def _covered_spans(windows: list[tuple[np.ndarray, np.ndarray]]) -> list[tuple[int, int]]:
    """The time spans [a, b] µs the estimated windows (finite poses) cover together, each a union of overlapping
    windows (two windows that only touch, as beside a window that saw nothing, start a new span): outside them the
    blend is a gap."""
    spans: list[list[int]] = []
    for t, _ in sorted(windows, key=lambda w: int(w[0][0])):
        a, b = int(t[0]), int(t[-1])
        if spans and a < spans[-1][1]:
            spans[-1][1] = max(spans[-1][1], b)
        else:
            spans.append([a, b])
    return [(a, b) for a, b in spans]


def blend(windows: list[tuple[np.ndarray, np.ndarray]], taper: float,
          t_all: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Blend the estimated windows [(t_us (T_k,), poses (T_k, 33))] into one motion at the union of their times (or
    at t_all): NaN rows where no window covers a time (a gap)."""
    if t_all is None:
        t_all = np.unique(np.concatenate([np.asarray(t, dtype=np.int64) for t, _ in windows]))
    spans = _covered_spans(windows)
    num = np.zeros((t_all.size, 33))
    den = np.zeros(t_all.size)
    for (_, P), (idx, w) in zip(windows, window_weights(windows, taper, t_all)):
        P = np.asarray(P, dtype=np.float64).copy()
        have = den[idx] > 0  # the blend so far: the root branch of this window continues it
        if have.any():
            j = int(np.flatnonzero(have)[0])
            ref = num[idx[j], 27:30] / den[idx[j]]
            P[:, 27:30] -= 2.0 * np.pi * np.round((P[j, 27:30] - ref) / (2.0 * np.pi))
        num[idx] += w[:, None] * P
        den[idx] += w
    inside = np.zeros(t_all.size, dtype=bool)
    for sa, sb in spans:
        inside |= (t_all >= sa) & (t_all <= sb)
    if np.any(inside & (den <= 0)):
        k = int(np.flatnonzero(inside & (den <= 0))[0])
        raise ValueError(f"no window covers t = {int(t_all[k])} us with a positive weight")
    out = np.full((t_all.size, 33), np.nan)
    out[inside] = num[inside] / den[inside, None]
    return t_all, out


def window_weights(windows: list[tuple[np.ndarray, np.ndarray]], taper: float,
                   t_all: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Each estimated window's (rows of t_all at its times, its blending weights there) (:func:`blend`; its ramps:
    :func:`ramps_us`)."""
    ts = [np.asarray(t, dtype=np.int64) for t, _ in windows]
    ramps = ramps_us([(int(t[0]), int(t[-1])) for t in ts], taper)
    return [(np.searchsorted(t_all, t), window_weight(t, int(t[0]), int(t[-1]), *r)) for t, r in zip(ts, ramps)]


def disagreement_mm(windows: list[tuple[np.ndarray, np.ndarray]], taper: float, t_all: np.ndarray,
                    template) -> np.ndarray:
    """(T, 24) mm at t_all: the root-mean-square spread of the windows' joint positions about their blend, with the
    blend's weights, each window's and the blend's joints taken relative to their mean over the joints (the
    translation a rigid alignment removes); 0 where one window alone holds a frame."""
    from eventcap.body.kinematics import joint_positions

    ww = window_weights(windows, taper, t_all)
    count = np.zeros(t_all.size, dtype=int)
    for idx, _ in ww:
        count[idx] += 1
    shared = count > 1
    num = np.zeros((t_all.size, 24, 3))
    sq = np.zeros((t_all.size, 24))
    den = np.zeros(t_all.size)
    for (_, P), (idx, w) in zip(windows, ww):
        keep = shared[idx]
        if not keep.any():
            continue
        J = joint_positions(np.asarray(P, dtype=np.float64)[keep], template) * 1000.0
        J -= J.mean(axis=1, keepdims=True)
        i, wk = idx[keep], w[keep]
        num[i] += wk[:, None, None] * J
        sq[i] += wk[:, None] * np.sum(J * J, axis=-1)
        den[i] += wk
    out = np.zeros((t_all.size, 24))
    ok = den > 0
    mean = num[ok] / den[ok, None, None]
    out[ok] = np.sqrt(np.maximum(sq[ok] / den[ok, None] - np.sum(mean * mean, axis=-1), 0.0))
    return out


def blend_sigma(windows: list[tuple[np.ndarray, np.ndarray]], sigmas: list[np.ndarray | None], taper: float,
                t_all: np.ndarray) -> np.ndarray:
    """(T, 24) the windows' joint σ (mm; sigmas[k] (T_k, 24) at window k's times, or None) blended as variances with
    the weights the poses are blended with, σ = sqrt(Σ w_k σ_k² / Σ w_k): the windows share most of their data, so
    their errors are not independent and averaging does not shrink the variance. NaN where no window has a σ."""
    num = np.zeros((t_all.size, 24))
    den = np.zeros((t_all.size, 24))
    for (idx, w), sig in zip(window_weights(windows, taper, t_all), sigmas):
        if sig is None:
            continue
        v = np.asarray(sig, dtype=np.float64) ** 2
        ok = np.isfinite(v)
        num[idx] += np.where(ok, w[:, None] * v, 0.0)
        den[idx] += np.where(ok, w[:, None], 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, np.sqrt(num / np.where(den > 0, den, 1.0)), np.nan)


def run_stitch(inputs, config, ctx):
    seq = inputs["windows"]
    K = len(seq)
    if K < 1:
        raise StageFailed("stitch: no batches of the spline solve", status="invalid_input")
    if not (math.isfinite(config.taper) and 0.0 < config.taper <= 0.5):
        raise StageFailed(f"stages.stitch.taper: expected a fraction in (0, 0.5], got {config.taper!r}",
                          status="invalid_config")
    windows, kept, sigmas = [], [], {}
    for k in range(K):
        p = seq[k]
        windows.append((np.asarray(p.t_us, dtype=np.int64), np.asarray(p.poses)))
        sigmas[k] = None if p.sigma_mm is None else np.asarray(p.sigma_mm)
        if p.status == "in_window" and windows[-1][0].size:
            raise StageFailed(f"stitch: batch {seq.batches[k].index} says another batch's window keeps it (status "
                              f"in_window) but holds {windows[-1][0].size} frames", status="invalid_input")
        if p.status != "in_window":
            kept.append(k)
        ctx.report(k + 1, K)
    b = seq.batches
    check_cover(windows, kept, b)
    t_all = np.unique(np.concatenate([windows[k][0] for k in kept]))
    # a window's estimate spans its observed frames only (NaN beyond, never extrapolated): blend that part
    rows = {k: np.isfinite(windows[k][1]).all(axis=1) for k in kept}
    estimated = {k: (windows[k][0][rows[k]], windows[k][1][rows[k]]) for k in kept}
    gaps = [k for k in kept if estimated[k][0].size < 2]
    if len(gaps) == len(kept):
        raise StageFailed(f"stitch: none of the {len(kept)} windows estimated anything (nothing observed in any)",
                          status="gap")
    used = [k for k in kept if k not in gaps]
    try:
        t_out, poses = blend([estimated[k] for k in used], float(config.taper), t_all)
    except ValueError as exc:
        raise StageFailed(f"stitch: {exc}", status="invalid_input") from exc
    sigma = None
    if any(sigmas[k] is not None for k in used):
        sigma = blend_sigma([estimated[k] for k in used],
                            [None if sigmas[k] is None else sigmas[k][rows[k]] for k in used], float(config.taper),
                            t_out)
        if inputs.get("template") is not None and len(used) > 1:
            spread = disagreement_mm([estimated[k] for k in used], float(config.taper), t_out, inputs["template"])
            sigma = np.hypot(sigma, spread)
            ctx.log.info("stitch: the windows' disagreement where they overlap, added to the σ: median %.0f mm, "
                         "largest %.0f mm", float(np.median(spread[spread > 0])) if (spread > 0).any() else 0.0,
                         float(spread.max()))
            ctx.stats["disagreement_mm_max"] = round(float(spread.max()), 1)
        sigma[~np.isfinite(poses).all(axis=1)] = np.nan
        sigma = sigma.astype(np.float32)
    missing = int(np.sum(~np.isfinite(poses).all(axis=1)))
    named = ", ".join(str(b[k].index) for k in gaps[:10]) + (" ..." if len(gaps) > 10 else "")
    if missing:
        ctx.log.warning("stitch: %d of %d windows saw nothing (solved by batches %s); %d of %d tracking frames are a "
                        "gap (no window observed them: not estimated, NaN, never interpolated)", len(gaps), len(kept),
                        named, missing, t_out.size)
        ctx.stats["gap_frames"] = missing
    elif gaps:
        ctx.log.info("stitch: %d of %d windows saw nothing (solved by batches %s); the others observed every frame",
                     len(gaps), len(kept), named)
    if gaps:
        ctx.stats["gap_windows"] = [b[k].index for k in gaps]
    seams = window_seams(windows, kept)
    ctx.log.info("stitch: %d windows (of %d batches) blended over %d tracking frames; largest joint-angle "
                 "disagreement of two neighbouring windows in the middle of their overlap: %.3f rad", len(kept), K,
                 t_out.size, max(seams, default=0.0))
    ctx.stats.update({"windows": len(kept), "seam_rad_max": max(seams, default=0.0),
                      "seam_rad_median": float(np.median(seams or [0]))})
    if inputs.get("template") is not None:
        report_seams(seam_bodies(windows, kept, inputs["template"]), ctx)
    return {"motion": PoseSequence(t_us=t_out, poses=poses, sigma_mm=sigma, status="stitched", iterations=0,
                                   energies={})}


def check_cover(windows: list[tuple[np.ndarray, np.ndarray]], kept: list[int], batches) -> None:
    """StageFailed unless every batch lies within one of the windows ``kept`` (the batches that solved a window;
    the others, status in_window, are kept by a neighbour's: stages.solve.window_step) and each of those has frames."""
    for k in kept:
        if windows[k][0].size < 2:
            raise StageFailed(f"stitch: batch {batches[k].index}'s window has {windows[k][0].size} frame(s): is the "
                              "input the spline stage's?", status="invalid_input")
    spans = [(int(windows[k][0][0]), int(windows[k][0][-1])) for k in kept]
    for bb in batches:
        if not any(a <= bb.t0_us and bb.t1_us <= z for a, z in spans):
            raise StageFailed(f"stitch: no window covers batch {bb.index} [{bb.t0_us}, {bb.t1_us}] us: is the input "
                              "the spline stage's?", status="invalid_input")


def seam_frames(windows: list[tuple[np.ndarray, np.ndarray]], kept: list[int]):
    """For each two consecutive windows (of the batches ``kept``) that overlap: (the tracking frame nearest the middle
    of their overlap, where their blending weights are equal; with a window per batch, the boundary where the later
    batch starts, µs, the earlier window's pose there, the later one's), when both estimated it."""
    for p, q in zip(kept[:-1], kept[1:]):
        (t_p, P_p), (t_q, P_q) = windows[p], windows[q]
        common = np.intersect1d(t_p, t_q)
        if common.size == 0:
            continue
        tm = common[np.argmin(np.abs(common - 0.5 * (float(t_q[0]) + float(t_p[-1]))))]
        a, b = P_p[np.searchsorted(t_p, tm)], P_q[np.searchsorted(t_q, tm)]
        if np.isfinite(a).all() and np.isfinite(b).all():
            yield int(tm), a, b


def window_seams(windows: list[tuple[np.ndarray, np.ndarray]], kept: list[int]) -> list[float]:
    """The seams the blend removed: the largest joint-angle disagreement (rad) of each two consecutive windows at
    their :func:`seam_frames`."""
    return [float(np.abs(a[:27] - b[:27]).max()) for _, a, b in seam_frames(windows, kept)]


#: Two neighbouring windows whose bodies in the middle of their overlap differ by more than this (mm, the joints' RMS
#: distance with each body's mean over the joints removed) or whose bodies lie further apart than SEAM_SHIFT_MM (mm,
#: between the joints' means) solved their shared stretch differently: the blend hands over from one to the other
#: there. On the synthetic suite's 2 s captures (two chunks that see the same person) seams measure 3-27 mm and 0-27
#: mm; on the real recordings 52-249 mm and 49-610 mm (docs/results/real.md).
SEAM_POSE_MM = 50.0
SEAM_SHIFT_MM = 100.0


def seam_bodies(windows: list[tuple[np.ndarray, np.ndarray]], kept: list[int], template) -> list[dict]:
    """For each two consecutive windows at their :func:`seam_frames`: that time (µs), how much their bodies differ
    there in pose (``pose_mm``: the joints' RMS distance, each body's mean over the joints removed) and in place
    (``shift_mm``: between the joints' means)."""
    from eventcap.body.kinematics import joint_positions

    out = []
    for tm, a, b in seam_frames(windows, kept):
        J = joint_positions(np.stack([a, b]).astype(np.float64), template) * 1000.0
        mean = J.mean(axis=1)
        d = (J[0] - mean[0]) - (J[1] - mean[1])
        out.append({"t_us": tm, "pose_mm": float(np.sqrt(np.mean(np.sum(d * d, axis=1)))),
                    "shift_mm": float(np.linalg.norm(mean[0] - mean[1]))})
    return out


def report_seams(seams: list[dict], ctx) -> None:
    """The seams' largest disagreements in the stage's stats; a warning naming each seam beyond SEAM_POSE_MM or
    SEAM_SHIFT_MM (the motion there hands over between two solutions, its σ carrying their spread)."""
    if not seams:
        return
    ctx.stats.update({"seam_pose_mm_max": round(max(s["pose_mm"] for s in seams), 1),
                      "seam_shift_mm_max": round(max(s["shift_mm"] for s in seams), 1)})
    far = [s for s in seams if s["pose_mm"] > SEAM_POSE_MM or s["shift_mm"] > SEAM_SHIFT_MM]
    ctx.stats.update({"seams": len(seams), "seams_apart": len(far)})
    if far:
        ctx.log.warning(
            "stitch: at %d of %d seams the neighbouring windows solved their shared stretch differently (more than "
            "%g mm apart in pose or %g mm in place): %s; the motion hands over from one solution to the other across "
            "their overlap and its uncertainty there includes their spread: do not read a turn or a step into it",
            len(far), len(seams), SEAM_POSE_MM, SEAM_SHIFT_MM,
            "; ".join(f"{s['t_us'] / 1e6:.2f} s: {s['pose_mm']:.0f} mm in pose, {s['shift_mm']:.0f} mm in place"
                      for s in far[:6]) + (" ..." if len(far) > 6 else ""))


def run_cut(inputs, config, ctx):
    motion, b = inputs["motion"], ctx.batch
    if b is None:
        raise StageFailed("cut runs per batch (no batch given)", status="invalid_input")
    t = np.asarray(motion.t_us, dtype=np.int64)
    sel = (t >= b.t0_us) & (t <= b.t1_us)
    if sel.sum() < 2 or t[sel][0] != b.t0_us or t[sel][-1] != b.t1_us:
        raise StageFailed(f"cut: the stitched motion has no frames spanning batch {b.index} [{b.t0_us}, {b.t1_us}] "
                          "us", status="invalid_input")
    poses = np.asarray(motion.poses)[sel].copy()
    sigma = None if motion.sigma_mm is None else np.asarray(motion.sigma_mm)[sel].copy()
    status = "stitched" if np.isfinite(poses).all() else ("gap" if not np.isfinite(poses).all(axis=1).any()
                                                           else "stitched, with a gap")
    return {"poses": PoseSequence(t_us=t[sel].copy(), poses=poses, sigma_mm=sigma, status=status, iterations=0,
                                  energies={})}
