"""Run functions of the smooth and split stages (imported when they run)."""

from __future__ import annotations

import numpy as np

from eventcap.artifacts.pose import PoseSequence
from eventcap.core.stage import StageFailed


def frame_fits(parts) -> tuple[np.ndarray, np.ndarray]:
    """The per-frame fits of per-batch pose sequences: each batch's first and last rows (its two intensity frames),
    ordered by time, a frame two batches share once (the later batch's row). Returns times (K,) and poses (K, 33)."""
    t, S = [], []
    for p in parts:
        tt = np.asarray(p.t_us, dtype=np.int64)
        if tt.size == 0:
            continue
        t += [int(tt[0]), int(tt[-1])]
        S += [p.poses[0], p.poses[-1]]
    if not t:
        return np.zeros(0, np.int64), np.zeros((0, 33))
    t_arr, S_arr = np.asarray(t, dtype=np.int64), np.stack(S)
    order = np.argsort(t_arr, kind="stable")
    t_arr, S_arr = t_arr[order], S_arr[order]
    last = np.r_[t_arr[1:] != t_arr[:-1], True]
    # in time order a shared frame appears as (batch k's last row, batch k+1's first row): keep the later one
    return t_arr[last], S_arr[last]


def run_smooth(inputs, config, ctx):
    from .smoothing import MIN_KNOTS, smooth_poses

    seq = inputs["fits"]
    parts = [seq[i] for i in range(len(seq))]
    t_knots, fits = frame_fits(parts)
    if t_knots.size < MIN_KNOTS:
        raise StageFailed(f"smooth: {t_knots.size} intensity frames with a fit ({len(parts)} batches); a smoothing "
                          f"spline needs at least {MIN_KNOTS} (a longer capture)", status="invalid_input")
    t_all = np.unique(np.concatenate([np.asarray(p.t_us, dtype=np.int64) for p in parts]))
    try:
        poses, choices = smooth_poses(t_knots, fits, t_all, config.pool, config.lam, config.criterion)
    except ValueError as exc:
        raise StageFailed(f"smooth: {exc}", status="invalid_input") from exc
    energies: dict[str, float] = {}
    for name, ch in choices.items():
        energies[f"lam_{name}"] = ch.lam
        energies[f"dof_{name}"] = ch.dof
    ctx.log.info("smooth: %d fits, %d frames; %s", t_knots.size, t_all.size,
                 ", ".join(f"{n}: lam {c.lam:.3g} s³, dof {c.dof:.1f}" for n, c in list(choices.items())[:3]))
    ctx.stats.update({"n_fits": int(t_knots.size), **{k: float(v) for k, v in energies.items()}})
    return {"motion": PoseSequence(t_us=t_all, poses=poses, status="smoothed", iterations=0, energies=energies)}


def run_split(inputs, config, ctx):
    frames, motion = inputs["frames"], inputs["motion"]
    t = np.asarray(frames.t_us, dtype=np.int64)
    tm = np.asarray(motion.t_us, dtype=np.int64)
    k = np.searchsorted(tm, t).clip(max=max(tm.size - 1, 0))
    missing = tm.size == 0 or not np.array_equal(tm[k], t)
    if missing:
        bad = t[tm[k] != t] if tm.size else t
        raise StageFailed(f"split: the motion has no frame at t = {int(bad[0])} us ({bad.size} of this batch's "
                          f"{t.size} times missing)", status="invalid_input")
    return {"poses": PoseSequence(t_us=t.copy(), poses=motion.poses[k].copy(), status=motion.status,
                                  iterations=0, energies={})}
