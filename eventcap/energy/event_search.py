"""Closest event search of the pose refinement (paper Sec. 3.3, Eq. 12-13).

For a boundary pixel s_b of the rendered estimate at tracking frame f (time t_f), the target is the event
e = (u, t, ρ) minimising

    D(s_b, e) = λ_dist ((t_f - t) / (t_N - t_0))² + ‖s_b - u‖²                                        (Eq. 12)

over the events within a local patch around s_b and within the batch-duration window centred at t_f (Eq. 13);
polarity plays no part. u is the event's pixel (integer pixel centre, origin top-left), times are µs.

Patch. "8×8 centred at s_b" cannot be centred on a pixel with an even side; an asymmetric 8×8 block would make
targets on one side reachable 4 px away and on the other only 3 px, a systematic pull in one direction. The patch
here is the square of side ``patch_px`` centred on the pixel centre of s_b: events whose pixel centre lies within
``patch_px / 2`` in x and y, i.e. offsets -4..4 (9×9 pixels) for ``patch_px = 8``. Window: |t - t_f| <= T/2 with
T = t_N - t_0, both ends included.

How (no event is scanned per boundary pixel). Within one pixel the spatial term of D is the same for every event,
so the best event of a pixel is the one nearest in time to t_f. :class:`EventIndex` sorts the events of the batch
span once by (pixel, time) — a CSR layout over the sensor's pixels — and, for every tracking frame and every pixel
that has events, finds that nearest event in one merge-like pass over the pixel's sorted times (compiled, numba).
The result is a per-frame table of time offsets (F, H·W). A query then reads the patch's (2h+1)² entries of that
table for each boundary pixel and keeps the minimum of D (a compiled loop: no (B, (2h+1)²) temporaries). The index
is built once per batch and serves every ICP iteration (the events do not change; the boundary does).

Noise (not in the paper). A DAVIS fires background-activity events everywhere (the synthetic sensor: 0.2 Hz per
pixel, ~350 in a 40 ms batch at 240×180), so ~65% of the 9×9 patches of a silhouette that does not move contain one,
and Eq. 13 makes it a target that pulls an exact start off (docs/results/implementation.md). With ``support_us`` > 0
the index keeps only events that have another event in their 3×3 pixel neighbourhood within ±support_us — the usual
background-activity filter: moving edges fire neighbouring pixels within milliseconds, isolated noise does not (at
0.2 Hz per pixel, one of the 9 pixels fires within ±5 ms by chance with probability ~2%). The stage's default is
5 ms; 0 searches all events (the paper).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._sil_kernels import nearest_in_time, patch_search, supported_events

#: Default of the event support filter (µs; ``support_us``): events without another event in their 3×3 pixel
#: neighbourhood within ± this are dropped as noise (module doc).
DENOISE_US = 5000
#: Marks "no event of this pixel within the frame's window" in the time-offset table.
_NONE = np.iinfo(np.int32).min
_TIME_BITS = 40  # key = pixel << 40 | (t - t_lo): windows up to 2^40 µs (12 days)


@dataclass(frozen=True)
class EventMatches:
    """Result of :meth:`EventIndex.closest` for B boundary pixels."""

    found: np.ndarray  #: (B,) bool: an event lies in the pixel's patch and window
    target_px: np.ndarray  #: (B, 2) float64, u_b: pixel of the closest event (x, y); NaN where not found
    dt_us: np.ndarray  #: (B,) int64, t - t_f of that event; 0 where not found
    cost: np.ndarray  #: (B,) float64, D(s_b, e_b) of Eq. 12 (px²); inf where not found


def check_patch(patch_px) -> int:
    """The patch's half-width patch_px // 2; ValueError unless patch_px is an integer >= 0 (pixels)."""
    if isinstance(patch_px, bool) or int(patch_px) != patch_px or patch_px < 0:
        raise ValueError(f"patch_px: expected an integer >= 0 (pixels), got {patch_px!r}")
    return int(patch_px) // 2


class EventIndex:
    """The events of one batch, indexed for the closest-event queries of its tracking frames (module doc).

    events: EVENT_DTYPE array (t µs, x, y, p), sorted by time or not. width, height: sensor size. frame_t_us (F,):
    the tracking frame times t_f. window_us: T = t_N - t_0, the length of the window centred at each t_f.
    support_us: drop events without another event in their 3×3 neighbourhood within ±support_us (0: keep all).
    """

    def __init__(self, events: np.ndarray, width: int, height: int, frame_t_us: np.ndarray, window_us: int,
                 support_us: int = 0):
        t_f = np.asarray(frame_t_us, dtype=np.int64)
        if t_f.ndim != 1 or t_f.size < 1:
            raise ValueError(f"frame_t_us: expected a non-empty 1-D array of times (µs), got shape {t_f.shape}")
        if isinstance(window_us, bool) or int(window_us) != window_us or window_us < 0:
            raise ValueError(f"window_us: expected an integer >= 0 (µs), got {window_us!r}")
        if isinstance(support_us, bool) or int(support_us) != support_us or support_us < 0:
            raise ValueError(f"support_us: expected an integer >= 0 (µs), got {support_us!r}")
        self.width, self.height = int(width), int(height)
        self.frame_t_us = t_f
        self.window_us = int(window_us)
        # Events of the span of all windows: 2 |t - t_f| <= T for some f (integers, no rounding of T / 2); for the
        # support filter also those up to support_us beyond, which may support events inside.
        lo_t, hi_t = int(t_f.min()), int(t_f.max())
        margin = 2 * int(support_us)
        t = np.asarray(events["t"], dtype=np.int64)
        ev = events[(2 * (lo_t - t) <= self.window_us + margin) & (2 * (t - hi_t) <= self.window_us + margin)]
        x, y = ev["x"].astype(np.int64), ev["y"].astype(np.int64)
        if ev.size and (x.max() >= self.width or y.max() >= self.height):
            raise ValueError(f"events: pixel outside the {self.width}x{self.height} sensor "
                             f"(max x {x.max()}, max y {y.max()})")
        self.t_lo = lo_t - self.window_us // 2 - int(support_us) - 1  # every kept event has t - t_lo >= 0
        t_rel = ev["t"].astype(np.int64) - self.t_lo
        keys = np.sort(((y * self.width + x) << _TIME_BITS) | t_rel)
        t_rel = keys & ((1 << _TIME_BITS) - 1)
        inside = ((2 * (lo_t - self.t_lo - t_rel) <= self.window_us)
                  & (2 * (t_rel - (hi_t - self.t_lo)) <= self.window_us))
        self.n_events = int(inside.sum())  # in the span of the windows, before the support filter
        self.n_unsupported = 0
        if support_us and keys.size:
            pix_start = np.searchsorted(keys >> _TIME_BITS, np.arange(self.width * self.height + 1))
            supported = np.empty(keys.size, dtype=np.bool_)
            supported_events(keys, pix_start, self.width, self.height, int(support_us), supported)
            self.n_unsupported = int(np.sum(inside & ~supported))
            inside &= supported
        keys = keys[inside]
        pix_of = keys >> _TIME_BITS
        pixels, start = np.unique(pix_of, return_index=True)  # CSR: the occupied pixels and where each starts
        end = np.append(start[1:], keys.size)
        # dt[f, pixel]: t - t_f of the pixel's event nearest in time to t_f within the window (_NONE: none).
        self.dt = np.full((t_f.size, self.height * self.width), _NONE, dtype=np.int32)
        if pixels.size:
            order = np.argsort(t_f, kind="stable")
            table = np.empty((t_f.size, pixels.size), dtype=np.int32)
            nearest_in_time(keys, start.astype(np.int64), end.astype(np.int64), (t_f[order] - self.t_lo),
                            np.int64(self.window_us // 2), np.int32(_NONE), table)  # 2|dt| <= T for integers
            self.dt[np.ix_(order, pixels)] = table

    def closest(self, frame: np.ndarray, pixel: np.ndarray, lambda_dist: float, patch_px: int) -> EventMatches:
        """e_b of Eq. 13 for boundary pixels ``pixel`` (B, 2) int (x, y) at tracking frames ``frame`` (B,) int
        (indices into frame_t_us). Among equal D the first patch offset in row-major order wins."""
        frame = np.asarray(frame, dtype=np.int64)
        pixel = np.asarray(pixel, dtype=np.int64)
        if pixel.ndim != 2 or pixel.shape[1] != 2 or frame.shape != (pixel.shape[0],):
            raise ValueError(f"closest: expected frame (B,) and pixel (B, 2), got {frame.shape}, {pixel.shape}")
        if frame.size and (frame.min() < 0 or frame.max() >= self.frame_t_us.size):
            raise ValueError(f"closest: frame indices must lie in [0, {self.frame_t_us.size}), got "
                             f"[{frame.min()}, {frame.max()}]")
        if not (np.isfinite(lambda_dist) and lambda_dist >= 0):
            raise ValueError(f"lambda_dist: expected a finite number >= 0, got {lambda_dist!r}")
        h = check_patch(patch_px)
        B = pixel.shape[0]
        found = np.zeros(B, dtype=np.bool_)
        tx, ty = np.zeros(B, np.int64), np.zeros(B, np.int64)
        dt, cost = np.zeros(B, np.int64), np.zeros(B, np.float64)
        patch_search(self.dt, frame, np.ascontiguousarray(pixel[:, 0]), np.ascontiguousarray(pixel[:, 1]),
                     self.width, self.height, h, float(lambda_dist), float(max(self.window_us, 1)),
                     np.int32(_NONE), found, tx, ty, dt, cost)
        target = np.stack([tx, ty], axis=1).astype(np.float64)
        target[~found] = np.nan
        return EventMatches(found=found, target_px=target, dt_us=np.where(found, dt, 0), cost=cost)
