"""One skeletal motion from per-batch pose sequences, as the evaluation and the run outputs both need it.

Joining. A per-batch pose stage (solve, refine) gives one PoseSequence per batch; neighbouring batches share their
boundary tracking frame (the intensity frame between them). Frames are ordered by time and every time appears once:
with ``later`` a shared frame keeps the later batch's pose (the batch that starts there), with ``mean`` the average
of the batches' poses (root rotation angles averaged modulo 2π, so a spin unwrapped differently in two batches does
not average to a wrong turn). Batches missing from the sequence (failed batches, or a run on a selection of batches)
leave gaps; :func:`uniform_motion` fills them for formats that need a constant frame rate (BVH).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from eventcap.artifacts.pose import PoseSequence
from eventcap.body.skeleton import ROOT_ROTATION_SLICE
from eventcap.errors import ComputationFailed

JOIN_RULES = ("later", "mean")


class MotionError(ComputationFailed):
    """Per-batch poses that cannot be joined into one motion (status ``bad_poses`` or ``no_poses``)."""


def wrap_angle(a: np.ndarray) -> np.ndarray:
    """Angles into [-π, π)."""
    return (a + np.pi) % (2 * np.pi) - np.pi


def join_batches(parts: Sequence[PoseSequence], rule: str = "later") -> tuple[np.ndarray, np.ndarray, int]:
    """One motion from per-batch pose sequences: times (T,) int64 µs (increasing, unique), poses (T, 33) and the
    number of tracking frames that more than one batch held (resolved by ``rule``: later | mean).

    Raises MotionError (status ``bad_poses``) when a batch's times do not increase, (``no_poses``) when no batch has
    a frame, and ValueError for an unknown rule.
    """
    if rule not in JOIN_RULES:
        raise ValueError(f"join: expected one of {', '.join(JOIN_RULES)}, got {rule!r}")
    ts, Ss = [], []
    for i in range(len(parts)):
        p = parts[i]
        t = np.asarray(p.t_us, dtype=np.int64)
        if t.size == 0:
            continue
        if t.size > 1 and np.any(np.diff(t) <= 0):
            k = int(np.argmax(np.diff(t) <= 0)) + 1
            raise MotionError(f"poses of batch {i}: tracking frame times must increase; frame {k} is at {t[k]} us "
                              f"after {t[k - 1]} us", status="bad_poses")
        ts.append(t)
        Ss.append(np.asarray(p.poses, dtype=np.float64))
    if not ts:
        raise MotionError(f"no poses to join: {len(parts)} batch(es), none with a tracking frame",
                          status="no_poses")
    perm = np.argsort([t[0] for t in ts], kind="stable")  # batch order = time order; later batches last
    t = np.concatenate([ts[k] for k in perm])
    S = np.concatenate([Ss[k] for k in perm])
    times, first, inverse, counts = np.unique(t, return_index=True, return_inverse=True, return_counts=True)
    shared = int(np.count_nonzero(counts > 1))
    if rule == "later":
        last = np.zeros(times.size, dtype=np.int64)
        np.maximum.at(last, inverse, np.arange(t.size))
        return times, S[last], shared
    ref = S[first][inverse]
    adj = S.copy()
    rr = ROOT_ROTATION_SLICE
    adj[:, rr] = ref[:, rr] + wrap_angle(S[:, rr] - ref[:, rr])
    out = np.zeros((times.size, S.shape[1]))
    np.add.at(out, inverse, adj)
    return times, out / counts[:, None], shared


def tracking_times_us(t0_us: int, t1_us: int, rate_hz: float = 1000.0) -> np.ndarray:
    """The tracking-frame times (int64 µs) of a batch [t0_us, t1_us]: both ends (its intensity frames) and, between
    them, every time of the recording's tracking grid ``round(k · 1e6 / rate_hz)`` (integer k, from 0 µs).

    The grid is the same for every batch, so a motion joined from batches whose frames are not a whole number of
    tracking steps apart (15 or 30 fps at 1 kHz; any real camera's frame clock) is on one grid between its frames,
    and overlapping windows sample the same times. Where the ends are on the grid (25 or 10 fps frames at 1 kHz
    from a whole millisecond) this is ``t0_us + n · 1e6 / rate_hz``, n = 0..N."""
    t0, t1 = int(t0_us), int(t1_us)
    if t1 < t0:
        raise ValueError(f"tracking times: expected t1_us >= t0_us, got t0_us={t0}, t1_us={t1}")
    if not (np.isfinite(rate_hz) and rate_hz > 0):
        raise ValueError(f"tracking times: expected a rate > 0 Hz, got {rate_hz!r}")
    period = 1e6 / float(rate_hz)
    k = np.arange(np.floor(t0 / period) - 1, np.ceil(t1 / period) + 2)
    grid = np.round(k * period).astype(np.int64)
    inner = grid[(grid > t0) & (grid < t1)]
    return np.unique(np.concatenate([[t0], inner, [t1]]).astype(np.int64))


def frame_step_us(t_us: np.ndarray) -> int | None:
    """The motion's tracking frame step (median of the time differences, µs), None for a single frame."""
    t = np.asarray(t_us, dtype=np.int64)
    return int(np.median(np.diff(t))) if t.size > 1 else None


def on_grid(t_us: np.ndarray, step_us: int) -> np.ndarray:
    """Mask (T,) of the times on the recording's tracking grid of step_us (the multiples of step_us,
    :func:`tracking_times_us`); the others are intensity frames between two grid times."""
    return np.asarray(t_us, dtype=np.int64) % int(step_us) == 0


def uniform_motion(t_us: np.ndarray, poses: np.ndarray, step_us: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The motion on the uniform grid of the multiples of step_us (:func:`tracking_times_us`) from its first frame
    to its last: times (G,), poses (G, 33) and a mask (G,) of the grid frames that were *not* estimated (gaps), whose
    poses are interpolated linearly in time between the neighbouring estimated frames (root rotation angles along
    the shorter way round). Estimated frames off the grid (intensity frames between two grid times) are used only
    to fill gaps. A motion with no grid time between its first and last frame is refused (ValueError)."""
    t = np.asarray(t_us, dtype=np.int64)
    S = np.asarray(poses, dtype=np.float64)
    if step_us <= 0:
        raise ValueError(f"step_us: expected a positive step, got {step_us}")
    first = -(-int(t[0]) // step_us) * step_us
    if first > t[-1]:
        raise ValueError(f"uniform_motion: no multiple of {step_us} us between the motion's first ({t[0]} us) and "
                         f"last ({t[-1]} us) frame")
    grid = first + step_us * np.arange((t[-1] - first) // step_us + 1, dtype=np.int64)
    k = np.searchsorted(t, grid)
    exact = (k < t.size) & (t[np.minimum(k, t.size - 1)] == grid)
    if exact.all():
        return grid, S[k].copy(), np.zeros(grid.size, dtype=bool)
    # Unwrap the root angles along the motion first, so interpolation takes the short way between neighbours.
    U = S.copy()
    rr = ROOT_ROTATION_SLICE
    U[:, rr] = np.unwrap(S[:, rr], axis=0)
    out = np.stack([np.interp(grid.astype(np.float64), t.astype(np.float64), U[:, c]) for c in range(S.shape[1])],
                   axis=1)
    out[exact] = S[k[exact]]
    return grid, out, ~exact


def frames_every(t_us: np.ndarray, every_ms: float, max_frames: int) -> tuple[np.ndarray, int]:
    """Indices into the increasing frame times ``t_us`` of one frame every ``every_ms`` of motion time (the first
    frame at or after each step), at most ``max_frames``: when more would be needed, the step widens evenly to cover
    the whole motion. Returns (indices, the step used in µs). The overlay video and the Rerun recording thin their
    frames with it."""
    t = np.asarray(t_us, dtype=np.int64)
    every_us = max(1, int(round(every_ms * 1000)))
    span = int(t[-1] - t[0])
    n = span // every_us + 1
    if n > max_frames:
        every_us = int(math.ceil(span / max(1, max_frames - 1))) if max_frames > 1 else span + 1
    targets = t[0] + every_us * np.arange(span // every_us + 1, dtype=np.int64)
    idx = np.unique(np.clip(np.searchsorted(t, targets), 0, t.size - 1))
    return idx[:max_frames], every_us
