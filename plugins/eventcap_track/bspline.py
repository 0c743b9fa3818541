"""Trajectory slicing (paper Sec. 3.1): fit a smoothing cubic B-spline to each tracked feature's asynchronous
2D samples and sample all of a batch's trajectories at the tracking frame rate (every 1 ms by default).

Input layout (what the tracker produces): every track contributes a variable number of samples ``(t_us, x, y)``.
They are passed as three concatenated columns of equal length S, in any order:

    track_id (S,) int   which track a sample belongs to (any integers; output columns = sorted unique ids)
    t_us     (S,) int   sample time, µs
    xy       (S, 2)     sample position (x, y) in pixels, origin top-left

:func:`concat_tracks` builds these columns from a list of per-track ``(t_us (K,), xy (K, 2))`` pairs.

Fit: a penalised cubic B-spline (P-spline, Eilers & Marx) per track, ``t -> (x, y)``, with uniform knots over
the track's observed span ``[first sample, last sample]`` at most ``knot_spacing_us`` apart, minimising

    sum_i n_i |xy_i - s(t_i)|² / sigma_px²  +  sum_j |c_j - 2 c_{j+1} + c_{j+2}|² / (accel_px_s2 · h²)²

(n_i: samples merged at one time, c_j: the 2D control points, h: knot spacing in s). The first term trusts
samples to their noise ``sigma_px``; the second is a prior on acceleration (the second difference of uniform
cubic B-spline coefficients is ``h²·s''``), which smooths noise and bridges gaps between samples without the
oscillation of an interpolating spline. Why not FITPACK's ``splprep(s=...)``: an underestimated noise level made it
return a spline that blows up, and its knot choice let the fit wander between samples on noise-free data
(docs/results/implementation.md); this penalised fit is a fixed linear
least-squares problem, solved for all tracks of a batch at once (one banded Cholesky), and cannot blow up.
A track with one sample is a constant; with two distinct times a straight line (the prior's null space).
Guards for extreme input (none bites on batch-length tracks sampled every few ms): at most 4 knot intervals per
sample (+16), the prior's weight clamped to [1e-6, 1e6] of the data term's, a 1e-12 ridge. A track whose samples
leave a gap of hundreds of knot intervals is not bridged faithfully there (the ridge pulls the gap towards the
track's mean position): split such tracks.

Slicing: positions at the batch's ends and at every time ``round(k · 1e6 / rate_hz)`` of the recording's tracking
grid between them (:func:`eventcap.analysis.motion.tracking_times_us`: the same grid for every batch, whatever the frame
clock); a position is valid only inside its track's observed span (no extrapolation); invalid positions are NaN.
"""

from __future__ import annotations

import math
import operator
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.linalg import solveh_banded

from eventcap.analysis.motion import tracking_times_us

#: Default expected noise of tracked positions, px (sub-pixel accuracy of event-based feature trackers).
DEFAULT_SIGMA_PX = 0.2
#: Default acceleration scale of the prior, px/s²: a limb crossing the image at 1000 px/s reverses in ~20 ms.
DEFAULT_ACCEL_PX_S2 = 1e5
#: Default largest knot spacing, µs: 20 control intervals per 40 ms batch; motion detail faster than ~250 Hz is
#: smoothed away (the cubic's approximation error on a 30 Hz, 3 px wobble is ~1e-3 px).
DEFAULT_KNOT_SPACING_US = 2_000
# Bounds of the prior's weight relative to the data term, and a ridge on control points (see fit_trajectories).
_LAM_MIN, _LAM_MAX = 1e-6, 1e6
_RIDGE = 1e-12
# A track with K distinct sample times gets at most this many knot intervals per sample (+ 16): more control
# points than samples only add gap modes that the prior alone must pin down.
_INTERVALS_PER_SAMPLE = 4


def _as_int(what: str, value: object) -> int:
    try:
        return operator.index(value)  # type: ignore[arg-type]
    except TypeError:
        raise ValueError(f"{what}: expected an integer (µs), got {value!r}") from None


def _positive(what: str, value: float) -> float:
    v = float(value)
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{what}: expected a finite number > 0, got {value!r}")
    return v


@dataclass(frozen=True)
class Trajectories:
    """Fitted trajectories of H tracks: uniform cubic B-splines, control points concatenated per track.

    Track h's curve on its span uses control points ``ctrl[offset[h] : offset[h] + n_intervals[h] + 3]``.
    """

    track_id: np.ndarray  # (H,) int64 sorted unique track ids
    t_first_us: np.ndarray  # (H,) int64 first sample time of each track, µs
    t_last_us: np.ndarray  # (H,) int64 last sample time, µs
    knot_us: np.ndarray  # (H,) float64 knot spacing h of each track, µs (0 for a single-sample track)
    n_intervals: np.ndarray  # (H,) int64 knot intervals over the span (>= 1)
    offset: np.ndarray  # (H,) int64 first control point of each track in ctrl
    ctrl: np.ndarray  # (sum(n_intervals + 3), 2) float64 control points, px

    def __len__(self) -> int:
        return int(self.track_id.size)

    def evaluate(self, h: np.ndarray, t_us: np.ndarray) -> np.ndarray:
        """Positions (M, 2) float64 px of tracks ``h`` (M,) (column indices, not ids) at times ``t_us`` (M,).

        Times outside a track's span are clamped to the span (mask them yourself; see :func:`slice_trajectories`)."""
        h = np.asarray(h, np.int64)
        t = np.asarray(t_us, np.float64)
        knot = self.knot_us[h]
        u = np.where(knot > 0, (t - self.t_first_us[h]) / np.where(knot > 0, knot, 1.0), 0.0)
        u = np.clip(u, 0.0, self.n_intervals[h].astype(np.float64))
        j = np.minimum(np.floor(u).astype(np.int64), self.n_intervals[h] - 1)
        basis = _cubic_basis(u - j)  # (M, 4)
        idx = self.offset[h][:, None] + j[:, None] + np.arange(4)
        return np.einsum("mk,mkd->md", basis, self.ctrl[idx])

    def __call__(self, h: int, t_us: np.ndarray | Sequence[int]) -> np.ndarray:
        """Positions (M, 2) float64 px of track column ``h`` at times t_us (M,) (clamped to its span)."""
        t = np.atleast_1d(np.asarray(t_us))
        return self.evaluate(np.full(t.size, int(h)), t)


def _cubic_basis(f: np.ndarray) -> np.ndarray:
    """The four uniform cubic B-spline weights (M, 4) at fractional positions f (M,) in [0, 1]."""
    f2, f3 = f * f, f * f * f
    return np.stack([(1 - f) ** 3, 3 * f3 - 6 * f2 + 4, -3 * f3 + 3 * f2 + 3 * f + 1, f3], axis=-1) / 6.0


def concat_tracks(tracks: Sequence[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-track ``(t_us (K_h,), xy (K_h, 2))`` pairs to the concatenated ``(track_id, t_us, xy)`` columns
    (track h gets id h)."""
    ids, ts, xys = [], [], []
    for h, (t, xy) in enumerate(tracks):
        t = np.asarray(t)
        xy = np.asarray(xy, dtype=np.float64)
        if t.ndim != 1 or xy.shape != (t.size, 2):
            raise ValueError(f"track {h}: expected t_us (K,) and xy (K, 2) of equal K, got {t.shape} and {xy.shape}")
        ids.append(np.full(t.size, h, np.int64))
        ts.append(t.astype(np.int64))
        xys.append(xy)
    if not ids:
        return np.empty(0, np.int64), np.empty(0, np.int64), np.empty((0, 2))
    return np.concatenate(ids), np.concatenate(ts), np.concatenate(xys)


def fit_trajectories(
    track_id: np.ndarray,
    t_us: np.ndarray,
    xy: np.ndarray,
    *,
    sigma_px: float = DEFAULT_SIGMA_PX,
    accel_px_s2: float = DEFAULT_ACCEL_PX_S2,
    knot_spacing_us: int = DEFAULT_KNOT_SPACING_US,
) -> Trajectories:
    """Fit every track of the concatenated columns (layout in the module docstring) in one banded solve.

    sigma_px: expected noise of the samples (px); accel_px_s2: acceleration scale of the smoothness prior
    (px/s², larger = follows the samples more closely); knot_spacing_us: largest knot spacing (µs).
    """
    track_id, t_us, xy = _check_columns(track_id, t_us, xy)
    sigma = _positive("sigma_px", sigma_px)
    accel = _positive("accel_px_s2", accel_px_s2)
    spacing = _positive("knot_spacing_us", _as_int("knot_spacing_us", knot_spacing_us))
    if track_id.size == 0:
        empty = np.empty(0, np.int64)
        return Trajectories(empty, empty, empty, np.empty(0), empty, empty, np.empty((0, 2)))

    # merge samples of one track at one time (mean position, weight = count)
    keys, inverse, count = np.unique(np.stack([track_id, t_us], axis=1), axis=0, return_inverse=True,
                                     return_counts=True)  # fmt: skip
    inverse = inverse.ravel()
    pos = np.zeros((keys.shape[0], 2))
    np.add.at(pos, inverse, xy)
    pos /= count[:, None]
    sample_track, sample_t = keys[:, 0], keys[:, 1]  # sorted by (track, t)

    ids, start, n_samples = np.unique(sample_track, return_index=True, return_counts=True)
    # solve for positions relative to each track's mean: the prior ignores constants, and small numbers keep the
    # Cholesky's rounding small
    h = np.repeat(np.arange(ids.size), n_samples)
    centre = np.zeros((ids.size, 2))
    np.add.at(centre, h, pos)
    centre /= n_samples[:, None]
    pos = pos - centre[h]
    t_first = sample_t[start]
    t_last = sample_t[start + n_samples - 1]
    span = (t_last - t_first).astype(np.float64)
    n_int = np.ceil(span / spacing - 1e-9).astype(np.int64)
    n_int = np.clip(n_int, 1, _INTERVALS_PER_SAMPLE * n_samples + 16)
    knot = span / n_int
    n_ctrl = n_int + 3
    offset = np.concatenate([[0], np.cumsum(n_ctrl)[:-1]])
    total = int(n_ctrl.sum())

    # normal equations of the data term, banded (bandwidth 3): sample i touches control points j_i .. j_i + 3
    u = np.where(knot[h] > 0, (sample_t - t_first[h]) / np.where(knot[h] > 0, knot[h], 1.0), 0.0)
    j = np.minimum(np.floor(u).astype(np.int64), n_int[h] - 1)
    basis = _cubic_basis(u - j) * np.sqrt(count)[:, None]  # weight n_i: merged samples count n_i times
    first = offset[h] + j
    ab = np.zeros((4, total))  # upper banded storage: ab[3 + r - c, c] = A[r, c] for r <= c
    rhs = np.zeros((total, 2))
    for a in range(4):
        np.add.at(rhs, first + a, basis[:, a, None] * (pos * np.sqrt(count)[:, None]))
        for b in range(a, 4):
            np.add.at(ab[3 - (b - a)], first + b, basis[:, a] * basis[:, b])

    # smoothness prior, in units of the data term: lam = sigma² / (accel · h²)² per track (h in seconds)
    knot_s = np.where(knot > 0, knot, spacing) * 1e-6
    # clamped to keep the banded system well conditioned at extreme spans: on µs-long tracks (lam ~ 1e12) the
    # data would be lost to rounding; for samples seconds apart (lam ~ 1e-13) the control points between them
    # would be left almost undetermined
    lam = np.clip(sigma**2 / (accel * knot_s**2) ** 2, _LAM_MIN, _LAM_MAX)
    rows = np.concatenate([offset[k] + np.arange(n_ctrl[k] - 2) for k in range(ids.size)])
    row_lam = np.repeat(lam, n_ctrl - 2)
    d = np.array([1.0, -2.0, 1.0])
    for a in range(3):
        for b in range(a, 3):
            np.add.at(ab[3 - (b - a)], rows + b, row_lam * d[a] * d[b])

    # Last-resort ridge on the (centred) control points: the prior's weakest modes shrink like (h / gap)^4, so a
    # gap of thousands of knot intervals between samples would make the system numerically singular.
    ab[3] += _RIDGE
    # A single-sample track has no data beyond its one point: pin all its control points to it instead.
    single = np.flatnonzero(n_samples == 1)
    for k in single:
        cols = offset[k] + np.arange(n_ctrl[k])
        ab[:, cols] = 0.0
        ab[3, cols] = 1.0
        rhs[cols] = pos[start[k]]
    ctrl = solveh_banded(ab, rhs, lower=False, check_finite=False) + np.repeat(centre, n_ctrl, axis=0)
    return Trajectories(ids, t_first, t_last, knot, n_int, offset, ctrl)


def fit_trajectory(
    t_us: np.ndarray | Sequence[int],
    xy: np.ndarray,
    *,
    sigma_px: float = DEFAULT_SIGMA_PX,
    accel_px_s2: float = DEFAULT_ACCEL_PX_S2,
    knot_spacing_us: int = DEFAULT_KNOT_SPACING_US,
) -> Trajectories:
    """The smoothing cubic B-spline of one track: t_us (K,) int µs (any order), xy (K, 2) px. Evaluate with
    ``traj(0, t_us) -> (M, 2)`` on ``[traj.t_first_us[0], traj.t_last_us[0]]``. Parameters as
    :func:`fit_trajectories`."""
    t = np.asarray(t_us)
    if t.ndim != 1 or t.size == 0:
        raise ValueError(f"t_us: expected a non-empty 1-D array of integer µs, got shape {t.shape}")
    return fit_trajectories(np.zeros(t.size, np.int64), t, xy, sigma_px=sigma_px, accel_px_s2=accel_px_s2,
                            knot_spacing_us=knot_spacing_us)  # fmt: skip


def slice_times_us(t0_us: int, t1_us: int, rate_hz: float = 1000.0) -> np.ndarray:
    """The tracking-frame times int64 µs of a batch: both ends and the recording's tracking grid between them
    (:func:`eventcap.analysis.motion.tracking_times_us`)."""
    return tracking_times_us(_as_int("t0_us", t0_us), _as_int("t1_us", t1_us), _positive("rate_hz", rate_hz))


@dataclass(frozen=True)
class SlicedTrajectories:
    """All trajectories of a batch sampled at the tracking frame rate."""

    t_us: np.ndarray  # (N+1,) int64 tracking-frame times, µs
    xy: np.ndarray  # (N+1, H, 2) float32 positions (x, y) px; NaN where not valid
    valid: np.ndarray  # (N+1, H) bool: inside the track's observed time span
    track_id: np.ndarray  # (H,) int64 id of each column (sorted unique ids of the input)


def slice_fitted(trajectories: Trajectories, t0_us: int, t1_us: int, rate_hz: float = 1000.0) -> SlicedTrajectories:
    """Sample fitted trajectories every ``1/rate_hz`` over [t0_us, t1_us] (valid only inside each span)."""
    times = slice_times_us(t0_us, t1_us, rate_hz)
    n_tracks = len(trajectories)
    valid = (times[:, None] >= trajectories.t_first_us[None, :]) & (times[:, None] <= trajectories.t_last_us[None, :])
    xy = np.full((times.size, n_tracks, 2), np.nan, np.float32)
    ti, hi = np.nonzero(valid)
    xy[ti, hi] = trajectories.evaluate(hi, times[ti])
    return SlicedTrajectories(times, xy, valid, trajectories.track_id)


def slice_trajectories(
    track_id: np.ndarray,
    t_us: np.ndarray,
    xy: np.ndarray,
    t0_us: int,
    t1_us: int,
    rate_hz: float = 1000.0,
    *,
    sigma_px: float = DEFAULT_SIGMA_PX,
    accel_px_s2: float = DEFAULT_ACCEL_PX_S2,
    knot_spacing_us: int = DEFAULT_KNOT_SPACING_US,
) -> SlicedTrajectories:
    """Fit every track (column layout in the module docstring) and sample all of them every ``1/rate_hz`` over
    [t0_us, t1_us]: positions (N+1, H, 2) float32 and validity mask (N+1, H). Parameters as
    :func:`fit_trajectories`."""
    fitted = fit_trajectories(track_id, t_us, xy, sigma_px=sigma_px, accel_px_s2=accel_px_s2,
                              knot_spacing_us=knot_spacing_us)  # fmt: skip
    return slice_fitted(fitted, t0_us, t1_us, rate_hz)


def _check_columns(track_id, t_us, xy) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    track_id, t_us = np.asarray(track_id), np.asarray(t_us)
    xy = np.asarray(xy, dtype=np.float64)
    if track_id.ndim != 1 or not (track_id.size == 0 or np.issubdtype(track_id.dtype, np.integer)):
        raise ValueError(f"track_id: expected a 1-D integer array, got shape {track_id.shape} dtype {track_id.dtype}")
    s = track_id.shape[0]
    if t_us.shape != (s,) or not (s == 0 or np.issubdtype(t_us.dtype, np.integer)):
        raise ValueError(f"t_us: expected ({s},) integer µs like track_id, got shape {t_us.shape} dtype {t_us.dtype}")
    if xy.shape != (s, 2):
        raise ValueError(f"xy: expected ({s}, 2) pixel positions like track_id, got shape {xy.shape}")
    if not np.all(np.isfinite(xy)):
        i = int(np.argmax(~np.isfinite(xy).all(axis=1)))
        raise ValueError(f"xy: expected finite pixel positions, got {xy[i].tolist()} at row {i}")
    return track_id.astype(np.int64), t_us.astype(np.int64), xy
