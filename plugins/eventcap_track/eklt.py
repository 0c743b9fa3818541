"""Asynchronous photometric feature tracking with events and a sharp start image (EKLT, Gehrig et al., IJCV 2019).

EventCap (paper Sec. 3.1) tracks sparse 2D features through each batch [t_k, t_{k+1}] between two intensity
frames with EKLT, forward from the sharpened log image L(t_k) and backward from L(t_{k+1}), and stitches the two
directions at the middle of the batch. This module implements both steps; ``klt.py`` has the frame-based baseline.

Method (our implementation of the published one, written from the paper's description)
--------------------------------------------------------------------------------------
- Features: Shi-Tomasi corners (``cv2.goodFeaturesToTrack``) on the start log image, optionally inside a mask,
  at least half a patch away from the image border, refined to sub-pixel positions (``cv2.cornerSubPix``).
- Template: the log image, lightly blurred (``blur_sigma_px``), and its Sobel derivatives up to second order.
- Event frame: every feature keeps the most recent events that fell into its ``patch_px`` square (centred on its
  current position). An update accumulates the newest N of them into a (patch_px, patch_px) frame by bilinear
  voting of their polarities. N adapts to the patch: it is the number of events the patch is expected to produce
  while moving ``displacement_px`` along the current flow direction, ``sum|grad L . v_hat| * displacement_px / C``,
  clamped to [n_events_min, n_events_max].
- Model: brightness constancy gives the increment of a moving patch as ``dL = -grad L . v dt``. The event frame is
  compared with the predicted increment ``P(u) = -grad L0(W(u)) . (cos phi, sin phi)`` after both are normalised to
  unit norm, so contrast threshold and speed cancel and only the warp W and the flow angle phi are estimated. The
  warp maps a pixel u of the current patch to the start image, ``W(u) = x0 + A (u - c)`` with the feature's start
  position x0, its current position c and A = identity (``warp="translation"``), a rotation (``"rotation"``, the
  reference's choice) or a general 2x2 matrix (``"affine"``).
- Optimisation: Levenberg-Marquardt on ``r = P/|P| - E/|E|`` (cost ``|r|^2 / 2 = 1 - cos(P, E)``, in [0, 2]) with the
  analytic Jacobian of the normalised residual, a few iterations per update, one update every ``update_every``
  new events of the patch. The flow angle is bootstrapped at the first update by linear least squares
  (``grad L . v = -E``). A track is dropped when its cost exceeds ``max_cost``, when one update moves it by more
  than half a patch, or when it leaves the image.
- Timestamp of an update: the mean time of the events in its frame (the frame shows the patch around that time).
- Hysteresis compensation (our addition; not in the reference): a DVS pixel fires only once its log intensity has
  moved by C from its last reset, so the events of a moving pattern trail it by about ``C / (2 |grad L . v_hat|)``
  px along the motion. Uncompensated, every track lagged its true position by 0.6-0.8 px at *any* speed from 500
  to 3000 px/s in the simulated scenes (a spatial, not a temporal, lag). Samples are reported moved forward along
  the flow by ``lag_gain * (C / 2) * sum|P| / sum P^2`` (forward in sensor time, so backward tracks get the
  opposite shift); this halves the median error.

Direction
---------
``direction=+1`` tracks forward from an image at ``t_start_us``. ``direction=-1`` tracks backward from an image at
``t_end_us``: the events of [t_start_us, t_end_us] are replayed in reverse time order, each with its polarity
flipped (an ON event at t means L rose through t; seen backwards, L falls), so the same forward tracker applies
unchanged -- features move with the opposite velocity in reversed time and the flow angle estimates that.

Output layout: :class:`FeatureTracks`
-------------------------------------
One object for any set of tracks (forward, backward, stitched, KLT):

- per sample (S samples, sorted by ``track_id`` then ``t_us``; times within a track strictly increase):
  ``t_us`` int64 µs, ``x``, ``y`` float64 px (origin top-left, pixel centres at integers, as events),
  ``track_id`` int32 in [0, K), ``cost`` float32 (match cost of the sample, method-specific, smaller is better;
  0 at detections);
- per track (K tracks, every track has >= 1 sample): ``kind`` int8 (``KIND_FORWARD`` = 1, ``KIND_BACKWARD`` = 2,
  ``KIND_STITCHED`` = 3) and ``survived`` bool (tracked to the end of the batch in its direction(s) without being
  dropped);
- ``height``, ``width`` of the sensor.

A forward track starts with its detection, an exact sample at t_start_us; a backward track ends with its detection
at t_end_us. Samples of track k are ``slice(offsets[k], offsets[k+1])`` (property ``offsets``).

Bidirectional tracking (:func:`track_bidirectional`)
---------------------------------------------------
Forward tracks start at corners of the start image. Backward tracks start, by default
(``backward_start="relocate"``), at the *same texture points* on the end image: every forward track that reached
the second half of the batch is extrapolated to t_end and aligned there by affine ECC between the two sharp images
(:func:`relocate`, ~0.02 px in the simulated scenes); further corners of the end image fill up to ``max_features``.
``backward_start="detect"`` is the paper's reading (independent corners on the end image). We changed the default
because independently detected corners of one texture point differ by 0.1-1.5 px between the two images under
rotation or deformation, so a stitched track switched points at mid-batch and stitching *raised* the error (median
0.47 vs 0.31 px on the rotating scene); with relocated starts it lowers it (see the benchmark).

Stitching (:func:`stitch`, paper Sec. 3.1 and Fig. 3)
----------------------------------------------------
At the middle time ``t_mid = (t0 + t1) / 2`` every forward and backward track that covers t_mid is read there
(linear interpolation between its samples). Pairs are associated greedily by increasing distance, one-to-one,
while the distance is below ``stitch_px`` (4 px in the paper). A stitched track uses, by default
(``mode="blend"``), the forward samples where only the forward track exists, the backward samples where only the
backward track exists, and on the interval where both exist the union of their sample times with a position
``(1 - w) x_fwd + w x_bwd``, w rising linearly from 0 to 1 across that interval -- each direction is trusted most
near its own image, where it has drifted least, and the result is continuous. ``mode="split"`` instead takes the
forward samples up to t_mid and the backward samples after it (the literal reading of the paper; it may jump by up
to ``stitch_px`` at t_mid). Tracks without a partner are kept for the part of the batch they cover, with their
own ``kind``; consumers that want only stitched tracks select ``kind == KIND_STITCHED``.
"""

from __future__ import annotations

import math
import operator
from collections import namedtuple
from dataclasses import dataclass

import cv2
import numba
import numpy as np

from eventcap.events import EVENT_DTYPE

KIND_FORWARD = 1
KIND_BACKWARD = 2
KIND_STITCHED = 3
_WARPS = {"translation": 0, "rotation": 1, "affine": 2}


# ----------------------------------------------------------------------------------------------- configuration
@dataclass(frozen=True)
class EkltConfig:
    """Parameters of the EKLT tracker (defaults: the public reference's where they exist, else tuned on the
    simulated scenes of ``benchmarks/accuracy/bench_tracking.py``)."""

    # Side of the square feature patch, px (odd). Reference: 25.
    patch_px: int = 25
    # Detector: at most this many Shi-Tomasi corners, this far apart, with this relative quality (reference values).
    max_features: int = 100
    min_distance_px: float = 10.0
    quality_level: float = 0.01
    # Detector block size (px) of the corner response.
    block_size: int = 3
    # Half window (px) of the sub-pixel corner refinement (cv2.cornerSubPix); 0 keeps integer corners.
    subpix_window_px: int = 3
    # Corners closer than this to the image border are not used; None = half a patch (the patch fits the image).
    border_px: int | None = None
    # Parametrisation of the patch warp: "translation", "rotation" (reference) or "affine".
    warp: str = "rotation"
    # Gaussian blur of the log image before differentiation, px; 0 = none. Events quantise the signal at pixels;
    # a light blur makes the template's derivatives smooth enough for Gauss-Newton.
    blur_sigma_px: float = 0.5
    # Displacement covered by one event frame, px; the frame holds the events expected for this much motion.
    displacement_px: float = 1.5
    # Contrast threshold C (log units; the pipeline can pass EDI's estimate). Used only to predict how many events
    # a displacement produces and for the hysteresis compensation; the fit itself is independent of C.
    contrast_threshold: float = 0.2
    # Bounds of the adaptive number of events in a frame (reference cap: 300).
    n_events_min: int = 20
    n_events_max: int = 300
    # An update after every this many new events in the patch (reference: 20-30). Our scenes give ~300 events
    # per px of motion in a patch, so 60 is still an update every ~0.2 px; 30 costs twice the time for no gain.
    update_every: int = 60
    # Levenberg-Marquardt iterations per update (reference: 10).
    max_iterations: int = 10
    # Hysteresis compensation (our addition, not in the reference): a DVS pixel fires only after its log change
    # reaches C, so the events of a moving patch trail the true pattern by ~C / (2 |grad L . v_hat|) px. Samples
    # are reported moved forward along the flow by lag_gain * (C/2) * sum|P| / sum P^2. The gain absorbs the
    # template blur; 0.45 was fitted on the simulated scenes (observed trail 0.6-0.8 px); 0 disables it.
    lag_gain: float = 0.45
    # Drop a track when its cost 1 - cos(P, E) exceeds this (reference: quality < 0.6, i.e. cost > 0.8).
    max_cost: float = 0.8
    # Half-side of the patch that relocates forward points on the end image (track_bidirectional, our addition).
    # It must stay on the object: 6 px (13 px patch) for an actor at the DAVIS240C's scale, whose limbs are ~10 px
    # wide; a 25 px patch is mostly background there and ECC aligns the background (see ``relocate``).
    relocate_radius_px: int = 6

    def __post_init__(self) -> None:
        if not (isinstance(self.patch_px, int) and self.patch_px >= 5 and self.patch_px % 2 == 1):
            raise ValueError(f"EkltConfig.patch_px: expected an odd integer >= 5, got {self.patch_px!r}")
        if self.warp not in _WARPS:
            raise ValueError(f"EkltConfig.warp: expected one of {sorted(_WARPS)}, got {self.warp!r}")
        for name in ("max_features", "block_size", "n_events_min", "n_events_max", "update_every", "max_iterations",
                     "relocate_radius_px"):
            v = getattr(self, name)
            if not (isinstance(v, int) and v >= 1):
                raise ValueError(f"EkltConfig.{name}: expected an integer >= 1, got {v!r}")
        if self.n_events_min > self.n_events_max:
            raise ValueError(
                f"EkltConfig: expected n_events_min <= n_events_max, got {self.n_events_min} > {self.n_events_max}"
            )
        for name in ("min_distance_px", "displacement_px", "contrast_threshold", "quality_level", "max_cost"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"EkltConfig.{name}: expected a finite number > 0, got {v!r}")
        if not (math.isfinite(self.lag_gain) and self.lag_gain >= 0):
            raise ValueError(f"EkltConfig.lag_gain: expected a finite number >= 0, got {self.lag_gain!r}")
        if not (math.isfinite(self.blur_sigma_px) and self.blur_sigma_px >= 0):
            raise ValueError(f"EkltConfig.blur_sigma_px: expected a finite number >= 0, got {self.blur_sigma_px!r}")
        if not (isinstance(self.subpix_window_px, int) and self.subpix_window_px >= 0):
            raise ValueError(
                f"EkltConfig.subpix_window_px: expected an integer >= 0, got {self.subpix_window_px!r}"
            )
        if self.border_px is not None and not (isinstance(self.border_px, int) and self.border_px >= 0):
            raise ValueError(f"EkltConfig.border_px: expected None or an integer >= 0, got {self.border_px!r}")

    @property
    def half_px(self) -> int:
        """Half the patch side (the patch is centre +- half_px)."""
        return (self.patch_px - 1) // 2


# ------------------------------------------------------------------------------------------------- the tracks
@dataclass(frozen=True)
class FeatureTracks:
    """Sparse 2D feature tracks of one batch; the layout is described in the module docstring."""

    t_us: np.ndarray  # (S,) int64 µs
    x: np.ndarray  # (S,) float64 px
    y: np.ndarray  # (S,) float64 px
    track_id: np.ndarray  # (S,) int32, sorted; samples of a track sorted by t_us
    cost: np.ndarray  # (S,) float32, smaller is better, 0 at detections
    kind: np.ndarray  # (K,) int8 KIND_*
    survived: np.ndarray  # (K,) bool
    height: int
    width: int

    def __post_init__(self) -> None:
        s = np.shape(self.t_us)
        for name, dtype in (("t_us", np.int64), ("x", np.float64), ("y", np.float64), ("track_id", np.int32),
                            ("cost", np.float32)):
            a = getattr(self, name)
            if not isinstance(a, np.ndarray) or a.dtype != dtype or a.ndim != 1 or a.shape != s:
                raise ValueError(
                    f"FeatureTracks.{name}: expected a 1-D {np.dtype(dtype)} array of shape {s}, got "
                    f"{getattr(a, 'dtype', type(a))} {np.shape(a)}"
                )
        k = np.shape(self.kind)
        for name, dtype in (("kind", np.int8), ("survived", np.bool_)):
            a = getattr(self, name)
            if not isinstance(a, np.ndarray) or a.dtype != dtype or a.ndim != 1 or a.shape != k:
                raise ValueError(
                    f"FeatureTracks.{name}: expected a 1-D {np.dtype(dtype)} array of shape {k}, got "
                    f"{getattr(a, 'dtype', type(a))} {np.shape(a)}"
                )
        counts = np.bincount(self.track_id, minlength=k[0]) if s[0] else np.zeros(k[0], np.int64)
        if s[0] and (self.track_id.min() < 0 or self.track_id.max() >= k[0]):
            raise ValueError(f"FeatureTracks.track_id: expected values in [0, {k[0]}), got "
                             f"[{self.track_id.min()}, {self.track_id.max()}]")
        if counts.size != k[0] or np.any(counts == 0):
            raise ValueError("FeatureTracks: expected every track to have at least one sample")
        if s[0] > 1:
            same = self.track_id[1:] == self.track_id[:-1]
            if np.any(self.track_id[1:] < self.track_id[:-1]) or np.any(same & (self.t_us[1:] <= self.t_us[:-1])):
                raise ValueError(
                    "FeatureTracks: expected samples sorted by track_id and strictly by t_us within a track"
                )
        if not np.all(np.isin(self.kind, (KIND_FORWARD, KIND_BACKWARD, KIND_STITCHED))):
            raise ValueError(f"FeatureTracks.kind: expected values in {{1, 2, 3}}, got {np.unique(self.kind)}")

    @property
    def n_tracks(self) -> int:
        return int(self.kind.shape[0])

    @property
    def offsets(self) -> np.ndarray:
        """(K+1,) int64: samples of track k are ``offsets[k]:offsets[k+1]``."""
        return np.concatenate([[0], np.cumsum(np.bincount(self.track_id, minlength=self.n_tracks))]).astype(np.int64)

    def track(self, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Samples (t_us, x, y) of track k."""
        o = self.offsets
        sl = slice(o[k], o[k + 1])
        return self.t_us[sl], self.x[sl], self.y[sl]

    def span_us(self) -> tuple[np.ndarray, np.ndarray]:
        """(K,) first and (K,) last sample time of every track, µs."""
        o = self.offsets
        return self.t_us[o[:-1]], self.t_us[o[1:] - 1]

    def positions_at(self, t_us) -> np.ndarray:
        """Positions of all tracks at the times ``t_us`` (T,) by linear interpolation -> (K, T, 2) px.

        NaN where a track does not cover the time (before its first or after its last sample).
        """
        t = np.atleast_1d(np.asarray(t_us, np.float64))
        out = np.full((self.n_tracks, t.size, 2), np.nan)
        o = self.offsets
        for k in range(self.n_tracks):
            sl = slice(o[k], o[k + 1])
            tk = self.t_us[sl].astype(np.float64)
            inside = (t >= tk[0]) & (t <= tk[-1])
            if np.any(inside):
                out[k, inside, 0] = np.interp(t[inside], tk, self.x[sl])
                out[k, inside, 1] = np.interp(t[inside], tk, self.y[sl])
        return out

    @staticmethod
    def concatenate(parts: list["FeatureTracks"]) -> "FeatureTracks":
        """All tracks of ``parts`` in one object (track ids renumbered in order)."""
        if not parts:
            raise ValueError("FeatureTracks.concatenate: expected at least one FeatureTracks, got none")
        base = 0
        ids = []
        for p in parts:
            if (p.height, p.width) != (parts[0].height, parts[0].width):
                raise ValueError("FeatureTracks.concatenate: expected one sensor size, got "
                                 f"{(parts[0].height, parts[0].width)} and {(p.height, p.width)}")
            ids.append(p.track_id + base)
            base += p.n_tracks
        cat = np.concatenate
        return FeatureTracks(
            cat([p.t_us for p in parts]), cat([p.x for p in parts]), cat([p.y for p in parts]),
            cat(ids).astype(np.int32), cat([p.cost for p in parts]), cat([p.kind for p in parts]),
            cat([p.survived for p in parts]), parts[0].height, parts[0].width,
        )


def _from_samples(k, t_us, x, y, cost, kind, survived, height, width) -> FeatureTracks:
    """FeatureTracks from unsorted samples of tracks 0..K-1 (K = len(kind)); drops duplicate times in a track."""
    order = np.lexsort((t_us, k))
    k, t_us, x, y, cost = k[order], t_us[order], x[order], y[order], cost[order]
    keep = np.ones(k.size, bool)
    keep[1:] = (k[1:] != k[:-1]) | (t_us[1:] != t_us[:-1])
    return FeatureTracks(
        t_us[keep].astype(np.int64), x[keep].astype(np.float64), y[keep].astype(np.float64),
        k[keep].astype(np.int32), cost[keep].astype(np.float32), np.asarray(kind, np.int8),
        np.asarray(survived, bool), int(height), int(width),
    )


# --------------------------------------------------------------------------------------------- input checks
def _check_log_image(name: str, img) -> np.ndarray:
    img = np.asarray(img)
    if img.ndim != 2 or img.shape[0] < 8 or img.shape[1] < 8:
        raise ValueError(f"{name}: expected a (height, width) log image of at least 8x8, got shape {img.shape}")
    if not np.issubdtype(img.dtype, np.floating) or not np.all(np.isfinite(img)):
        raise ValueError(f"{name}: expected finite floating-point log intensities, got dtype {img.dtype}"
                         + ("" if not np.issubdtype(img.dtype, np.floating) else " with non-finite values"))
    return img.astype(np.float64)


def _check_events(events, height: int, width: int) -> np.ndarray:
    if not isinstance(events, np.ndarray) or events.dtype != EVENT_DTYPE or events.ndim != 1:
        raise ValueError(f"events: expected a 1-D array of eventcap.events.EVENT_DTYPE, got "
                         f"{getattr(events, 'dtype', type(events))} {np.shape(events)}")
    if events.size:
        if np.any(np.diff(events["t"]) < 0):
            i = int(np.argmax(np.diff(events["t"]) < 0))
            raise ValueError(f"events: expected timestamps sorted ascending, row {i + 1} (t={events['t'][i + 1]}) "
                             f"is before row {i} (t={events['t'][i]})")
        if events["x"].max() >= width or events["y"].max() >= height:
            raise ValueError(f"events: expected x < {width} and y < {height} (the image size), got max x "
                             f"{events['x'].max()}, max y {events['y'].max()}")
        if not np.all(np.abs(events["p"]) == 1):
            raise ValueError("events: expected polarities in {-1, +1}")
    return events


def _check_times(t_start_us, t_end_us) -> tuple[int, int]:
    try:
        t0, t1 = operator.index(t_start_us), operator.index(t_end_us)
    except TypeError:
        raise ValueError(f"t_start_us, t_end_us: expected integers (µs), got {t_start_us!r}, {t_end_us!r}") from None
    if t1 <= t0:
        raise ValueError(f"expected t_end_us > t_start_us, got t_start_us={t0}, t_end_us={t1}")
    return t0, t1


def _check_mask(mask, height: int, width: int) -> np.ndarray | None:
    if mask is None:
        return None
    mask = np.asarray(mask)
    if mask.shape != (height, width):
        raise ValueError(f"mask: expected shape (height, width) = ({height}, {width}), got {mask.shape}")
    return mask.astype(bool)


def _check_features(features, height: int, width: int) -> np.ndarray:
    f = np.asarray(features, np.float64)
    if f.ndim != 2 or f.shape[1] != 2:
        raise ValueError(f"features: expected a (K, 2) array of (x, y) px, got shape {f.shape}")
    if f.size and (not np.all(np.isfinite(f)) or f[:, 0].min() < 0 or f[:, 1].min() < 0
                   or f[:, 0].max() > width - 1 or f[:, 1].max() > height - 1):
        raise ValueError(f"features: expected finite positions inside the {width}x{height} image")
    return f


# ------------------------------------------------------------------------------------------------- detection
def detect_features(log_image, mask=None, config: EkltConfig = EkltConfig()) -> np.ndarray:
    """Shi-Tomasi corners of a (height, width) log image -> (K, 2) float64 (x, y) px, strongest first.

    ``mask``: optional (height, width) bool, corners only where True (e.g. the actor's region). Corners closer
    than ``config.border_px`` (default half a patch) to the border are skipped.
    """
    img = _check_log_image("log_image", log_image)
    h, w = img.shape
    m = np.ones((h, w), bool) if mask is None else _check_mask(mask, h, w).copy()
    b = config.half_px if config.border_px is None else config.border_px
    if b:
        m[:b] = m[-b:] = False
        m[:, :b] = m[:, -b:] = False
    if not m.any():
        return np.zeros((0, 2))
    pts = cv2.goodFeaturesToTrack(
        img.astype(np.float32), config.max_features, config.quality_level, config.min_distance_px,
        mask=m.astype(np.uint8), blockSize=config.block_size, useHarrisDetector=False,
    )
    if pts is None:
        return np.zeros((0, 2))
    # Sub-pixel corners: the same texture point detected on the start and on the end image must give the same
    # point for forward and backward tracks to be stitched into one trajectory.
    pts = pts.reshape(-1, 2).astype(np.float64)
    if config.subpix_window_px > 0:
        refined = cv2.cornerSubPix(
            img.astype(np.float32), pts.astype(np.float32).reshape(-1, 1, 2),
            (config.subpix_window_px, config.subpix_window_px), (-1, -1),
            (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 40, 0.001),
        ).reshape(-1, 2).astype(np.float64)
        # A refinement that wanders off by more than a pixel found a different structure: keep the corner.
        moved = np.hypot(*(refined - pts).T) > 1.0
        ri = np.rint(refined).astype(int).clip(0, [w - 1, h - 1])
        bad = moved | ~m[ri[:, 1], ri[:, 0]]
        pts = np.where(bad[:, None], pts, refined)
    return pts


def _derivatives(log_image: np.ndarray, blur_sigma_px: float) -> np.ndarray:
    """(H, W, 5) float64: Lx, Ly, Lxx, Lxy, Lyy of the (blurred) log image, per px (Sobel / 8)."""
    img = log_image.astype(np.float64)
    if blur_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_sigma_px, borderType=cv2.BORDER_REPLICATE)
    def d(a, dx, dy):
        return cv2.Sobel(a, cv2.CV_64F, dx, dy, ksize=3, borderType=cv2.BORDER_REPLICATE) / 8.0
    gx, gy = d(img, 1, 0), d(img, 0, 1)
    return np.ascontiguousarray(np.stack([gx, gy, d(gx, 1, 0), d(gx, 0, 1), d(gy, 0, 1)], axis=-1))


# ------------------------------------------------------------------------------------------- numba kernels
@numba.njit(cache=True)
def _solve_spd(a, b, out):
    """Solve a x = b into ``out`` for a small symmetric positive definite a (Cholesky); False if not SPD."""
    m = b.shape[0]
    l = np.zeros((m, m))
    for i in range(m):
        for j in range(i + 1):
            s = a[i, j]
            for k in range(j):
                s -= l[i, k] * l[j, k]
            if i == j:
                if s <= 0.0:
                    return False
                l[i, i] = math.sqrt(s)
            else:
                l[i, j] = s / l[j, j]
    for i in range(m):
        s = b[i]
        for k in range(i):
            s -= l[i, k] * out[k]
        out[i] = s / l[i, i]
    for i in range(m - 1, -1, -1):
        s = out[i]
        for k in range(i + 1, m):
            s -= l[k, i] * out[k]
        out[i] = s / l[i, i]
    return True


@numba.njit(cache=True, fastmath=True)
def _build_event_frame(ring, ring_pos, nb, ev_tau, ev_x, ev_y, ev_p, ox, oy, height, width, efr, valid):
    """Vote the newest ``nb`` events of a feature's ring buffer into ``efr`` (bilinear, polarity-weighted).

    The grid pixel (i, j) sits at image position (ox + j, oy + i); ``valid`` marks grid pixels inside the image.
    ``efr`` is normalised to unit norm over the valid pixels. Returns (mean event time, events used, norm).
    """
    size = efr.shape[0]
    n_max = ring.shape[0]
    efr[:, :] = 0.0
    t_sum = 0.0
    t_cnt = 0
    for q in range(nb):
        e = ring[(ring_pos - 1 - q) % n_max]
        gx = ev_x[e] - ox
        gy = ev_y[e] - oy
        ix = int(math.floor(gx))
        iy = int(math.floor(gy))
        if ix < -1 or iy < -1 or ix >= size or iy >= size:
            continue
        fx = gx - ix
        fy = gy - iy
        pe = ev_p[e]
        for dyi in range(2):
            yy = iy + dyi
            if yy < 0 or yy >= size:
                continue
            wy = fy if dyi else 1.0 - fy
            for dxi in range(2):
                xx = ix + dxi
                if 0 <= xx < size:
                    efr[yy, xx] += pe * wy * (fx if dxi else 1.0 - fx)
        t_sum += ev_tau[e]
        t_cnt += 1
    ne = 0.0
    for a in range(size):
        uy = oy + a
        for b in range(size):
            ux = ox + b
            v = 0.0 <= ux <= width - 1 and 0.0 <= uy <= height - 1
            valid[a, b] = v
            if v:
                ne += efr[a, b] * efr[a, b]
            else:
                efr[a, b] = 0.0
    if ne > 0.0:
        ne = math.sqrt(ne)
        for a in range(size):
            for b in range(size):
                efr[a, b] /= ne
    return (t_sum / t_cnt if t_cnt else 0.0), t_cnt, ne


# The warp model is a compile-time constant of the kernels below: each takes ``mode`` (0 translation, 1 rotation,
# 2 affine) and calls ``numba.literally(mode)``, so numba compiles one specialisation per model, with the parameter
# count M a constant that unrolls the normal-equation loops (faster than a runtime M). Parameters
# p = [cx, cy, warp..., phi]: M = 3 (translation), 4 (+ rotation angle), 7 (+ 4 affine entries). Every kernel is
# a module-level function, so numba's disk cache serves later processes. (Closures over the mode, built per
# process, missed that cache: its key pickles the jitted functions a closure captures, which differ per process,
# so every process compiled the tracker again, 7-20 s, and the cache folder grew by one entry per process.)
#
# The tracker's state travels in named tuples of arrays (numba passes them as structs): _Features (per feature k:
# warp parameters params (K, M); alive, inited (flow angle bootstrapped); the ring buffer of the patch's event
# indices ring (K, n_max) with its fill ring_n and write position ring_pos; since (events since the last update);
# nbatch (events per event frame); velocity vel (px/us), vel_ok; the velocity's reference sample ref_xy, t_ref,
# ref_ok; t_prev, the time of the last update), _Workspace (scratch of one update) and _Samples (the output, grown
# by doubling).
_Features = namedtuple("_Features", "params alive inited ring ring_n ring_pos since nbatch vel vel_ok ref_xy t_ref "
                                    "ref_ok t_prev")
_Workspace = namedtuple("_Workspace", "efr valid jtj jtr jtj_n jtr_n jj jpp jpe jp lhs rhs step pn p")
_Samples = namedtuple("_Samples", "k t x y c")
#: Velocities are measured over at least this span, so that the position noise of single updates does not dominate.
_VEL_SPAN_US = 500.0


@numba.njit(inline="always")
def _n_params(mode):
    return 3 if mode == 0 else (4 if mode == 1 else 7)


@numba.njit(cache=True, fastmath=True, inline="always")
def _warp_matrix(p, mode):
    """A of the patch warp W(u) = x0 + A (u - c) as (a00, a01, a10, a11)."""
    if mode == 0:
        return 1.0, 0.0, 0.0, 1.0
    if mode == 1:
        c = math.cos(p[2])
        s = math.sin(p[2])
        return c, -s, s, c
    return 1.0 + p[2], p[3], p[4], 1.0 + p[5]


@numba.njit(cache=True, fastmath=True)
def _evaluate(p, x0, y0, der, efr, valid, ox, oy, jtj, jtr, jj, jpp, jpe, jp, mode):
    """Cost 1 - cos(P, E) at p, the LM normal equations (jtj, jtr), sum |P| and sum P^2.

    P(u) = -grad L0(W(u)) . (cos phi, sin phi) on the grid of the unit-norm event frame ``efr``. With
    n = |P|, r = P/n - E, the normalised residual's Jacobian is J = (JP - P s^T / n) / n, s = JP^T P / n;
    J^T J and J^T r then follow from sums over the patch alone, so one pass suffices.
    """
    numba.literally(mode)
    M = _n_params(mode)
    h = der.shape[0]
    w = der.shape[1]
    size = efr.shape[0]
    cx = p[0]
    cy = p[1]
    phi = p[M - 1]
    cphi = math.cos(phi)
    sphi = math.sin(phi)
    a00, a01, a10, a11 = _warp_matrix(p, mode)
    ct = math.cos(p[2]) if mode == 1 else 1.0
    st = math.sin(p[2]) if mode == 1 else 0.0
    spp = 0.0
    spe = 0.0
    sabs = 0.0
    jj[:, :] = 0.0
    jpp[:] = 0.0
    jpe[:] = 0.0
    for i in range(size):
        dy = oy + i - cy
        for j in range(size):
            if not valid[i, j]:
                continue
            dx = ox + j - cx
            wx = x0 + a00 * dx + a01 * dy
            wy = y0 + a10 * dx + a11 * dy
            e = efr[i, j]
            if not (0.0 <= wx < w - 1 and 0.0 <= wy < h - 1):
                continue  # no template there: P = 0 and no gradient
            ix = int(wx)
            iy = int(wy)
            fx = wx - ix
            fy = wy - iy
            w00 = (1.0 - fx) * (1.0 - fy)
            w01 = fx * (1.0 - fy)
            w10 = (1.0 - fx) * fy
            w11 = fx * fy
            r0 = der[iy]
            r1 = der[iy + 1]
            jx = ix + 1
            g0 = w00 * r0[ix, 0] + w01 * r0[jx, 0] + w10 * r1[ix, 0] + w11 * r1[jx, 0]
            g1 = w00 * r0[ix, 1] + w01 * r0[jx, 1] + w10 * r1[ix, 1] + w11 * r1[jx, 1]
            g2 = w00 * r0[ix, 2] + w01 * r0[jx, 2] + w10 * r1[ix, 2] + w11 * r1[jx, 2]
            g3 = w00 * r0[ix, 3] + w01 * r0[jx, 3] + w10 * r1[ix, 3] + w11 * r1[jx, 3]
            g4 = w00 * r0[ix, 4] + w01 * r0[jx, 4] + w10 * r1[ix, 4] + w11 * r1[jx, 4]
            pv = -(g0 * cphi + g1 * sphi)
            sx = -(g2 * cphi + g3 * sphi)  # dP/dw: the Hessian of L0 along the flow
            sy = -(g3 * cphi + g4 * sphi)
            jp[0] = -(sx * a00 + sy * a10)
            jp[1] = -(sx * a01 + sy * a11)
            if mode == 1:
                jp[2] = sx * (-st * dx - ct * dy) + sy * (ct * dx - st * dy)
            elif mode == 2:
                jp[2] = sx * dx
                jp[3] = sx * dy
                jp[4] = sy * dx
                jp[5] = sy * dy
            jp[M - 1] = g0 * sphi - g1 * cphi
            spp += pv * pv
            spe += pv * e
            sabs += abs(pv)
            for a in range(M):
                ja = jp[a]
                jpp[a] += ja * pv
                jpe[a] += ja * e
                for b in range(a + 1):
                    jj[a, b] += ja * jp[b]
    if spp <= 1e-20:
        return 2.0, 0.0, 0.0
    n_p = math.sqrt(spp)
    cos = spe / n_p
    for a in range(M):
        sa = jpp[a] / n_p
        jtr[a] = (sa * cos - jpe[a]) / n_p
        for b in range(a + 1):
            v = (jj[a, b] - sa * jpp[b] / n_p) / spp
            jtj[a, b] = v
            jtj[b, a] = v
    return 1.0 - cos, sabs, spp


@numba.njit(cache=True)
def _bootstrap_flow_angle(p, x0, y0, der, efr, valid, ox, oy, mode):
    """Flow angle from linear least squares grad L . v = -E at the current warp (reference's "events" bootstrap)."""
    numba.literally(mode)
    M = _n_params(mode)
    size = efr.shape[0]
    h = der.shape[0]
    w = der.shape[1]
    a00, a01, a10, a11 = _warp_matrix(p, mode)
    mxx = mxy = myy = bx = by = 0.0
    for a in range(size):
        for b in range(size):
            if not valid[a, b]:
                continue
            dx = ox + b - p[0]
            dy = oy + a - p[1]
            wx = x0 + a00 * dx + a01 * dy
            wy = y0 + a10 * dx + a11 * dy
            if not (0.0 <= wx < w - 1 and 0.0 <= wy < h - 1):
                continue
            ix = int(wx)
            iy = int(wy)
            fx = wx - ix
            fy = wy - iy
            gx = ((1 - fx) * (1 - fy) * der[iy, ix, 0] + fx * (1 - fy) * der[iy, ix + 1, 0]
                  + (1 - fx) * fy * der[iy + 1, ix, 0] + fx * fy * der[iy + 1, ix + 1, 0])
            gy = ((1 - fx) * (1 - fy) * der[iy, ix, 1] + fx * (1 - fy) * der[iy, ix + 1, 1]
                  + (1 - fx) * fy * der[iy + 1, ix, 1] + fx * fy * der[iy + 1, ix + 1, 1])
            mxx += gx * gx
            mxy += gx * gy
            myy += gy * gy
            bx += gx * efr[a, b]
            by += gy * efr[a, b]
    det = mxx * myy - mxy * mxy
    if det <= 1e-18:
        return p[M - 1]
    vx = -(myy * bx - mxy * by) / det
    vy = -(-mxy * bx + mxx * by) / det
    return math.atan2(vy, vx)


@numba.njit(cache=True)
def _levenberg_marquardt(p, x0, y0, der, ws, ox, oy, max_iter, mode):
    """Minimise the cost over p in place (Levenberg-Marquardt from p) -> (cost, sum |P|, sum P^2, evaluations)."""
    numba.literally(mode)
    M = _n_params(mode)
    efr, valid, jtj, jtr, jtj_n, jtr_n = ws.efr, ws.valid, ws.jtj, ws.jtr, ws.jtj_n, ws.jtr_n
    lhs, rhs, step, pn = ws.lhs, ws.rhs, ws.step, ws.pn
    n_evals = 1
    cost, sabs, spp = _evaluate(p, x0, y0, der, efr, valid, ox, oy, jtj, jtr, ws.jj, ws.jpp, ws.jpe, ws.jp, mode)
    lam = 1e-3
    for _ in range(max_iter):
        for a in range(M):
            for b in range(M):
                lhs[a, b] = jtj[a, b]
            lhs[a, a] += lam * jtj[a, a] + 1e-9
            rhs[a] = -jtr[a]
        if not _solve_spd(lhs, rhs, step):
            lam *= 10.0
            continue
        # A step this small moves the feature far less than one frame's noise: converged.
        small = abs(step[0]) < 2e-3 and abs(step[1]) < 2e-3
        for a in range(2, M):
            small = small and abs(step[a]) < 1e-3
        if small:
            break
        for a in range(M):
            pn[a] = p[a] + step[a]
        n_evals += 1
        cost_n, sabs_n, spp_n = _evaluate(pn, x0, y0, der, efr, valid, ox, oy, jtj_n, jtr_n, ws.jj, ws.jpp, ws.jpe,
                                          ws.jp, mode)
        if cost_n < cost:
            p[:] = pn
            cost = cost_n
            sabs = sabs_n
            spp = spp_n
            jtj[:, :] = jtj_n
            jtr[:] = jtr_n
            lam = max(lam / 3.0, 1e-7)
            # Accepted steps shrink quadratically near the minimum: after one this small, the next would be below
            # the noise.
            done = abs(step[0]) < 0.02 and abs(step[1]) < 0.02
            for a in range(2, M):
                done = done and abs(step[a]) < 2e-3
            if done:
                break
        else:
            # Below ~0.05 px the cost is not smooth (bilinear template): a rejected step that small means we are
            # at the minimum to within the frame's noise.
            tiny = abs(step[0]) < 0.05 and abs(step[1]) < 0.05
            for a in range(2, M):
                tiny = tiny and abs(step[a]) < 5e-3
            lam *= 4.0
            if tiny or lam > 1e4:
                break
    return cost, sabs, spp, n_evals


@numba.njit(cache=True)
def _new_state(feats, half, n_min, n_max, mode):
    """The tracker's state for features at ``feats`` (K, 2), the scratch of one update and an empty sample buffer."""
    numba.literally(mode)
    M = _n_params(mode)
    K = feats.shape[0]
    size = 2 * half + 1
    params = np.zeros((K, M))
    for k in range(K):
        params[k, 0] = feats[k, 0]
        params[k, 1] = feats[k, 1]
    st = _Features(params, np.ones(K, np.bool_), np.zeros(K, np.bool_), np.zeros((K, n_max), np.int64),
                   np.zeros(K, np.int64), np.zeros(K, np.int64), np.zeros(K, np.int64), np.full(K, n_min, np.int64),
                   np.zeros((K, 2)), np.zeros(K, np.bool_), np.zeros((K, 2)), np.zeros(K), np.zeros(K, np.bool_),
                   np.zeros(K))
    ws = _Workspace(np.zeros((size, size)), np.zeros((size, size), np.bool_), np.zeros((M, M)), np.zeros(M),
                    np.zeros((M, M)), np.zeros(M), np.zeros((M, M)), np.zeros(M), np.zeros(M), np.zeros(M),
                    np.zeros((M, M)), np.zeros(M), np.zeros(M), np.zeros(M), np.zeros(M))
    cap = 1024
    out = _Samples(np.zeros(cap, np.int32), np.zeros(cap, np.int64), np.zeros(cap), np.zeros(cap), np.zeros(cap))
    return st, ws, out


@numba.njit(cache=True)
def _update_feature(st, ws, k, ev_tau, ev_x, ev_y, ev_p, der, feats, half, max_cost, max_iter, mode):
    """One update of feature k from the newest events of its patch: event frame, prediction, LM fit, keep or drop.

    Returns (accepted, evaluations, mean event time, cost, sum |P|, sum P^2); the new parameters are in ws.p and
    st.params[k] when accepted, and st.alive[k] is False when the track was dropped.
    """
    numba.literally(mode)
    M = _n_params(mode)
    h = der.shape[0]
    w = der.shape[1]
    cx0 = st.params[k, 0]
    cy0 = st.params[k, 1]
    ox = cx0 - half
    oy = cy0 - half
    t_mean, t_cnt, ne = _build_event_frame(st.ring[k], st.ring_pos[k], st.nbatch[k], ev_tau, ev_x, ev_y, ev_p, ox,
                                           oy, h, w, ws.efr, ws.valid)
    if t_cnt == 0 or ne <= 0.0:
        return False, 0, t_mean, 0.0, 0.0, 0.0
    x0 = feats[k, 0]
    y0 = feats[k, 1]
    p = ws.p
    p[:] = st.params[k]
    # Constant-velocity prediction of the position at this frame's time: starts LM near the answer.
    if st.vel_ok[k]:
        p[0] += st.vel[k, 0] * (t_mean - st.t_prev[k])
        p[1] += st.vel[k, 1] * (t_mean - st.t_prev[k])
    if not st.inited[k]:
        p[M - 1] = _bootstrap_flow_angle(p, x0, y0, der, ws.efr, ws.valid, ox, oy, mode)
        st.inited[k] = True
    cost, sabs, spp, n_evals = _levenberg_marquardt(p, x0, y0, der, ws, ox, oy, max_iter, mode)
    jump = math.hypot(p[0] - cx0, p[1] - cy0)
    if cost > max_cost or jump > half or not (0.0 <= p[0] <= w - 1 and 0.0 <= p[1] <= h - 1):
        st.alive[k] = False
        return False, n_evals, t_mean, cost, sabs, spp
    p[M - 1] = math.atan2(math.sin(p[M - 1]), math.cos(p[M - 1]))
    st.params[k] = p
    if t_mean - st.t_ref[k] >= _VEL_SPAN_US:
        if st.ref_ok[k]:
            st.vel[k, 0] = (p[0] - st.ref_xy[k, 0]) / (t_mean - st.t_ref[k])
            st.vel[k, 1] = (p[1] - st.ref_xy[k, 1]) / (t_mean - st.t_ref[k])
            st.vel_ok[k] = True
        st.ref_xy[k, 0] = p[0]
        st.ref_xy[k, 1] = p[1]
        st.t_ref[k] = t_mean
        st.ref_ok[k] = True
    st.t_prev[k] = t_mean
    return True, n_evals, t_mean, cost, sabs, spp


@numba.njit(cache=True)
def _record_sample(out, ns, k, p, t_mean, cost, sabs, spp, lag_px_per_grad, mode):
    """Store sample ns of feature k (position p moved forward along the flow by the hysteresis lag); -> the buffer,
    doubled when full."""
    numba.literally(mode)
    M = _n_params(mode)
    cap = out.k.shape[0]
    if ns == cap:
        cap *= 2
        out = _Samples(_grow(out.k, cap), _grow(out.t, cap), _grow(out.x, cap), _grow(out.y, cap), _grow(out.c, cap))
    # Pixels fire only after their log change reaches C, so the events trail the true pattern by about
    # C / (2 |grad L . v_hat|) px along the motion (the pixel's hysteresis); report the position moved forward by
    # that trail, averaged over the patch with the fit's weights.
    lag = lag_px_per_grad * sabs / spp if spp > 0 else 0.0
    a00, a01, a10, a11 = _warp_matrix(p, mode)
    vx = math.cos(p[M - 1])
    vy = math.sin(p[M - 1])
    det = a00 * a11 - a01 * a10
    mx = (a11 * vx - a01 * vy) / det  # the flow direction in the current frame: A^-1 v_hat
    my = (-a10 * vx + a00 * vy) / det
    mn = math.hypot(mx, my)
    out.k[ns] = k
    out.t[ns] = int(round(t_mean))
    out.x[ns] = p[0] + lag * mx / mn
    out.y[ns] = p[1] + lag * my / mn
    out.c[ns] = cost
    return out


@numba.njit(cache=True)
def _collect_event(st, k, i, ex, ey, half, n_max, update_every):
    """Add event i at (ex, ey) to feature k's ring buffer if it falls into its patch; True when an update is due
    (every ``update_every`` new events once the buffer holds the event frame's number of events)."""
    if not st.alive[k] or abs(ex - st.params[k, 0]) > half or abs(ey - st.params[k, 1]) > half:
        return False
    st.ring[k, st.ring_pos[k]] = i
    st.ring_pos[k] = (st.ring_pos[k] + 1) % n_max
    if st.ring_n[k] < n_max:
        st.ring_n[k] += 1
    st.since[k] += 1
    nb = st.nbatch[k]
    if st.ring_n[k] < nb or st.since[k] < min(update_every, nb):
        return False
    st.since[k] = 0
    return True


@numba.njit(cache=True)
def _track_kernel(ev_tau, ev_x, ev_y, ev_p, der, feats, settings, mode):
    """Track all features through the events (in tracking-time order) -> samples, alive flags, counters."""
    numba.literally(mode)
    half, n_min, n_max, update_every, disp_over_c, max_cost, max_iter, lag_px_per_grad = settings
    K = feats.shape[0]
    st, ws, out = _new_state(feats, half, n_min, n_max, mode)
    ns = 0
    n_updates = 0
    n_evals = 0
    for i in range(ev_tau.shape[0]):
        ex = ev_x[i]
        ey = ev_y[i]
        for k in range(K):
            if not _collect_event(st, k, i, ex, ey, half, n_max, update_every):
                continue
            n_updates += 1
            ok, n_ev, t_mean, cost, sabs, spp = _update_feature(st, ws, k, ev_tau, ev_x, ev_y, ev_p, der, feats, half,
                                                                max_cost, max_iter, mode)
            n_evals += n_ev
            if not ok:
                continue
            out = _record_sample(out, ns, k, ws.p, t_mean, cost, sabs, spp, lag_px_per_grad, mode)
            ns += 1
            st.nbatch[k] = min(n_max, max(n_min, int(round(sabs * disp_over_c))))
    return out.k[:ns], out.t[:ns], out.x[:ns], out.y[:ns], out.c[:ns], st.alive, st.params, n_updates, n_evals


# One entry point per warp model, each calling the kernel with its model as a literal constant: called from Python
# with a plain int, the literal kernel would go through numba's compiler on every call.
@numba.njit(cache=True)
def _track_translation(ev_tau, ev_x, ev_y, ev_p, der, feats, settings):
    return _track_kernel(ev_tau, ev_x, ev_y, ev_p, der, feats, settings, 0)


@numba.njit(cache=True)
def _track_rotation(ev_tau, ev_x, ev_y, ev_p, der, feats, settings):
    return _track_kernel(ev_tau, ev_x, ev_y, ev_p, der, feats, settings, 1)


@numba.njit(cache=True)
def _track_affine(ev_tau, ev_x, ev_y, ev_p, der, feats, settings):
    return _track_kernel(ev_tau, ev_x, ev_y, ev_p, der, feats, settings, 2)


#: the tracking kernel of each warp model, by the index of _WARPS
_TRACK_KERNELS = (_track_translation, _track_rotation, _track_affine)


@numba.njit(cache=True)
def _grow(a, cap):
    out = np.zeros(cap, a.dtype)
    out[: a.shape[0]] = a
    return out


# ------------------------------------------------------------------------------------------------ public API
def track(
    log_image,
    events: np.ndarray,
    t_start_us: int,
    t_end_us: int,
    direction: int = +1,
    config: EkltConfig = EkltConfig(),
    *,
    features=None,
    mask=None,
    stats: dict | None = None,
) -> FeatureTracks:
    """EKLT tracks over [t_start_us, t_end_us] from one sharp log image, forward or backward in time.

    log_image: (height, width) float log intensity log(I + eps) at ``t_start_us`` (direction=+1) or at
    ``t_end_us`` (direction=-1). events: sorted ``EVENT_DTYPE`` array; only those in [t_start_us, t_end_us] are
    used. features: optional (K, 2) (x, y) px start positions on ``log_image``; default: ``detect_features`` of
    it inside ``mask``. Returns FeatureTracks with kind KIND_FORWARD / KIND_BACKWARD. If ``stats`` is a dict,
    the run's counters are stored in it (``n_events``, ``n_updates``, ``n_evaluations`` of the cost).
    """
    return _track(log_image, events, t_start_us, t_end_us, direction, config, features, mask, stats)[0]


def _track(log_image, events, t_start_us, t_end_us, direction, config, features, mask, stats=None):
    """:func:`track`, also returning each track's last warp: (K, 2, 2) A with W(u) = x0 + A (u - c)."""
    img = _check_log_image("log_image", log_image)
    height, width = img.shape
    t0, t1 = _check_times(t_start_us, t_end_us)
    if direction not in (1, -1):
        raise ValueError(f"direction: expected +1 (forward) or -1 (backward), got {direction!r}")
    ev = _check_events(events, height, width)
    if features is None:
        feats = detect_features(img, mask, config)
    else:
        feats = _check_features(features, height, width)
    ev = ev[np.searchsorted(ev["t"], t0, side="left") : np.searchsorted(ev["t"], t1, side="right")]
    if direction == 1:
        tau = ev["t"] - t0
        ex, ey, ep = ev["x"], ev["y"], ev["p"].astype(np.float64)
        t_det = t0
    else:
        ev = ev[::-1]
        tau = t1 - ev["t"]
        ex, ey, ep = ev["x"], ev["y"], -ev["p"].astype(np.float64)
        t_det = t1
    der = _derivatives(img, config.blur_sigma_px)
    settings = (config.half_px, config.n_events_min, config.n_events_max, config.update_every,
                config.displacement_px / config.contrast_threshold, config.max_cost, config.max_iterations,
                direction * config.lag_gain * 0.5 * config.contrast_threshold)
    k, ts, xs, ys, cs, alive, params, n_upd, n_ev = _TRACK_KERNELS[_WARPS[config.warp]](
        np.ascontiguousarray(tau, np.int64), np.ascontiguousarray(ex, np.float64),
        np.ascontiguousarray(ey, np.float64), np.ascontiguousarray(ep), der,
        np.ascontiguousarray(feats, np.float64), settings,
    )
    if stats is not None:
        stats.update(n_events=int(tau.size), n_updates=int(n_upd), n_evaluations=int(n_ev))
    n = feats.shape[0]
    # Every track starts with its exact detection; tracking-time tau maps back to sensor time.
    k = np.concatenate([np.arange(n, dtype=np.int32), k])
    tau_all = np.concatenate([np.zeros(n, np.int64), ts])
    t_us = t0 + tau_all if direction == 1 else t1 - tau_all
    t_us = np.clip(t_us, t0, t1)
    xs = np.concatenate([feats[:, 0], xs])
    ys = np.concatenate([feats[:, 1], ys])
    cs = np.concatenate([np.zeros(n), cs])
    # A surviving track ends with a sample at the far end of the interval holding its last estimate: no further
    # events in its patch means no motion the sensor could see, and a track must cover the batch to be stitched
    # and sliced (a static feature would otherwise be a single sample at its detection).
    last = np.full(n, -1, np.int64)
    np.maximum.at(last, k, np.arange(k.size))  # samples of a track come in tracking-time order
    ends = np.flatnonzero(np.asarray(alive, bool))
    src = np.where(last[ends] >= 0, last[ends], ends)  # tracks never updated hold their detection
    k = np.concatenate([k, ends.astype(np.int32)])
    t_us = np.concatenate([t_us, np.full(ends.size, t1 if direction == 1 else t0, np.int64)])
    xs = np.concatenate([xs, xs[src]])
    ys = np.concatenate([ys, ys[src]])
    cs = np.concatenate([cs, cs[src]])
    # A sample rounded onto the detection time would duplicate it: keep the detection.
    dup = (t_us == t_det) & (np.arange(t_us.size) >= n)
    sel = ~dup
    kind = np.full(n, KIND_FORWARD if direction == 1 else KIND_BACKWARD, np.int8)
    warps = np.tile(np.eye(2), (n, 1, 1))
    if config.warp == "rotation":
        c, s_ = np.cos(params[:, 2]), np.sin(params[:, 2])
        warps = np.stack([np.stack([c, -s_], -1), np.stack([s_, c], -1)], -2)
    elif config.warp == "affine":
        warps = params[:, 2:6].reshape(n, 2, 2) + np.eye(2)
    return _from_samples(k[sel], t_us[sel], xs[sel], ys[sel], cs[sel], kind, alive, height, width), warps


def stitch(
    forward: FeatureTracks,
    backward: FeatureTracks,
    t0_us: int,
    t1_us: int,
    stitch_px: float = 4.0,
    mode: str = "blend",
) -> FeatureTracks:
    """Join forward and backward tracks of one batch at its middle time (paper Sec. 3.1); see the module docstring.

    Returns stitched tracks first (KIND_STITCHED), then unmatched forward tracks, then unmatched backward tracks.
    """
    t0, t1 = _check_times(t0_us, t1_us)
    if mode not in ("blend", "split"):
        raise ValueError(f"mode: expected 'blend' or 'split', got {mode!r}")
    if not (math.isfinite(stitch_px) and stitch_px >= 0):
        raise ValueError(f"stitch_px: expected a finite number >= 0, got {stitch_px!r}")
    if (forward.height, forward.width) != (backward.height, backward.width):
        raise ValueError(f"stitch: expected one sensor size, got {(forward.height, forward.width)} and "
                         f"{(backward.height, backward.width)}")
    t_mid = 0.5 * (t0 + t1)
    pf = forward.positions_at([t_mid])[:, 0]
    pb = backward.positions_at([t_mid])[:, 0]
    fi = np.flatnonzero(np.all(np.isfinite(pf), axis=1))
    bi = np.flatnonzero(np.all(np.isfinite(pb), axis=1))
    pairs = []
    if fi.size and bi.size:
        d = np.hypot(pf[fi, None, 0] - pb[None, bi, 0], pf[fi, None, 1] - pb[None, bi, 1])
        order = np.argsort(d, axis=None, kind="stable")
        used_f, used_b = set(), set()
        for flat in order:
            a, b = divmod(int(flat), bi.size)
            if d[a, b] > stitch_px:
                break
            if a in used_f or b in used_b:
                continue
            used_f.add(a)
            used_b.add(b)
            pairs.append((int(fi[a]), int(bi[b])))
    pairs.sort()
    parts_k, parts_t, parts_x, parts_y, parts_c = [], [], [], [], []
    kinds, survived = [], []
    fo, bo = forward.offsets, backward.offsets

    def add(t, x, y, c, kind, surv):
        kid = len(kinds)
        parts_k.append(np.full(t.size, kid, np.int32))
        parts_t.append(t)
        parts_x.append(x)
        parts_y.append(y)
        parts_c.append(c)
        kinds.append(kind)
        survived.append(surv)

    for a, b in pairs:
        fs, bs = slice(fo[a], fo[a + 1]), slice(bo[b], bo[b + 1])
        tf, xf, yf, cf = forward.t_us[fs], forward.x[fs], forward.y[fs], forward.cost[fs]
        tb, xb, yb, cb = backward.t_us[bs], backward.x[bs], backward.y[bs], backward.cost[bs]
        if mode == "split":
            sf, sb = tf <= t_mid, tb > t_mid
            t = np.concatenate([tf[sf], tb[sb]])
            x = np.concatenate([xf[sf], xb[sb]])
            y = np.concatenate([yf[sf], yb[sb]])
            c = np.concatenate([cf[sf], cb[sb]])
        else:
            lo, hi = max(tf[0], tb[0]), min(tf[-1], tb[-1])  # both cover t_mid, so lo <= t_mid <= hi
            t = np.unique(np.concatenate([tf, tb]))
            only_f = t < lo
            only_b = t > hi
            both = ~only_f & ~only_b
            x, y, c = np.empty(t.size), np.empty(t.size), np.empty(t.size, np.float32)
            tt = t.astype(np.float64)
            for out, vf, vb in ((x, xf, xb), (y, yf, yb), (c, cf, cb)):
                at_f = np.interp(tt, tf, vf)
                at_b = np.interp(tt, tb, vb)
                wgt = np.clip((tt - lo) / (hi - lo), 0.0, 1.0) if hi > lo else np.full(t.size, 0.5)
                out[only_f] = at_f[only_f]
                out[only_b] = at_b[only_b]
                out[both] = ((1 - wgt) * at_f + wgt * at_b)[both]
            # keep only times that are real samples of the track that is used there
            keep = (only_f & np.isin(t, tf)) | (only_b & np.isin(t, tb)) | both
            t, x, y, c = t[keep], x[keep], y[keep], c[keep]
        add(t, x, y, c.astype(np.float32), KIND_STITCHED, bool(forward.survived[a] and backward.survived[b]))
    matched_f = {a for a, _ in pairs}
    matched_b = {b for _, b in pairs}
    for src, matched, o in ((forward, matched_f, fo), (backward, matched_b, bo)):
        for k in range(src.n_tracks):
            if k in matched:
                continue
            sl = slice(o[k], o[k + 1])
            add(src.t_us[sl], src.x[sl], src.y[sl], src.cost[sl], int(src.kind[k]), bool(src.survived[k]))
    if not kinds:
        return _from_samples(np.zeros(0, np.int32), np.zeros(0, np.int64), np.zeros(0), np.zeros(0),
                             np.zeros(0, np.float32), np.zeros(0, np.int8), np.zeros(0, bool),
                             forward.height, forward.width)
    cat = np.concatenate
    return _from_samples(cat(parts_k), cat(parts_t), cat(parts_x), cat(parts_y), cat(parts_c), kinds, survived,
                         forward.height, forward.width)


def log_to_uint8(log_image, lo: float, hi: float) -> np.ndarray:
    """A log image mapped linearly from [lo, hi] to 0..255 (clipped) as uint8, for OpenCV's 8-bit-only routines.

    Use one (lo, hi) for all images that are compared with each other, so that equal log intensities map to
    equal grey values.
    """
    img = np.asarray(log_image, np.float64)
    if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
        raise ValueError(f"log_to_uint8: expected finite lo < hi, got lo={lo!r}, hi={hi!r}")
    return np.clip(np.rint((img - lo) * (255.0 / (hi - lo))), 0, 255).astype(np.uint8)


def relocate(
    log_image_0,
    log_image_1,
    forward: FeatureTracks,
    t1_us: int,
    warps=None,
    max_shift_px: float = 4.0,
    radius_px: int = 6,
    min_correlation: float = 0.9,
) -> np.ndarray:
    """Where the points of forward tracks are on the end image: (K, 2) px, NaN where not found.

    Each forward track that reached the second half of the batch is extrapolated linearly to ``t1_us`` from its
    last 2 ms; the start image's (2 radius_px + 1)^2 patch around its detection is then aligned to the end image
    by ECC with an affine warp (``cv2.findTransformECC``), started from that position and from the track's last
    patch warp ``warps`` (K, 2, 2) (A of ``W(u) = x0 + A (u - c)``; identity if None). Accepted when ECC
    converges to a correlation >= ``min_correlation`` within ``max_shift_px`` of the guess.

    Why: starting the backward tracker there makes forward and backward tracks follow the *same* texture point.
    Corners detected independently on the end image differ from the forward points by a fraction of a pixel or more
    under rotation or deformation, and a stitched track would switch points at mid-batch.

    The patch must lie on the moving object: a patch that is mostly static background around a thin limb makes
    stitching worse (the radii tried: docs/results/implementation.md).
    """
    a = _check_log_image("log_image_0", log_image_0).astype(np.float32)
    b = _check_log_image("log_image_1", log_image_1).astype(np.float32)
    if a.shape != b.shape or a.shape != (forward.height, forward.width):
        raise ValueError(f"relocate: expected images of the tracks' size {(forward.height, forward.width)}, got "
                         f"{a.shape} and {b.shape}")
    n = forward.n_tracks
    if warps is None:
        warps = np.tile(np.eye(2), (n, 1, 1))
    warps = np.asarray(warps, np.float64)
    if warps.shape != (n, 2, 2):
        raise ValueError(f"relocate: expected warps of shape ({n}, 2, 2), got {warps.shape}")
    out = np.full((n, 2), np.nan)
    if n == 0:
        return out
    first, last = forward.span_us()
    o = forward.offsets
    t_mid = 0.5 * (first.min() + t1_us)
    r = int(radius_px)
    h, w = a.shape
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-4)
    for k in range(n):
        x0, y0 = forward.x[o[k]], forward.y[o[k]]
        ix, iy = int(round(x0)), int(round(y0))
        if last[k] < t_mid or ix - r < 0 or iy - r < 0 or ix + r >= w or iy + r >= h:
            continue
        sl = slice(o[k], o[k + 1])
        t = forward.t_us[sl].astype(np.float64)
        recent = t >= last[k] - 2000
        if np.count_nonzero(recent) >= 2 and np.ptp(t[recent]) > 200:
            gx = np.polyval(np.polyfit(t[recent], forward.x[sl][recent], 1), t1_us)
            gy = np.polyval(np.polyfit(t[recent], forward.y[sl][recent], 1), t1_us)
        else:
            gx, gy = forward.x[sl][-1], forward.y[sl][-1]
        template = np.ascontiguousarray(a[iy - r : iy + r + 1, ix - r : ix + r + 1])
        a_inv = np.linalg.inv(warps[k])
        # Template pixel (j, i) is start-image point (ix - r + j, iy - r + i); it maps to the end image by the
        # inverse patch warp around the guessed position.
        centre_t = np.array([x0 - (ix - r), y0 - (iy - r)])
        warp = np.zeros((2, 3), np.float32)
        warp[:, :2] = a_inv
        warp[:, 2] = np.array([gx, gy]) - a_inv @ centre_t
        try:
            cc, warp = cv2.findTransformECC(template, b, warp, cv2.MOTION_AFFINE, criteria, None, 1)
        except cv2.error:
            continue  # ECC did not converge
        p1 = warp[:, :2].astype(np.float64) @ centre_t + warp[:, 2]
        if (cc >= min_correlation and math.hypot(p1[0] - gx, p1[1] - gy) <= max_shift_px
                and 0 <= p1[0] <= w - 1 and 0 <= p1[1] <= h - 1):
            out[k] = p1
    return out


def track_bidirectional(
    log_image_0,
    log_image_1,
    events: np.ndarray,
    t0_us: int,
    t1_us: int,
    stitch_px: float = 4.0,
    config: EkltConfig = EkltConfig(),
    *,
    mask_0=None,
    mask_1=None,
    mode: str = "blend",
    backward_start: str = "relocate",
) -> FeatureTracks:
    """EKLT forward from ``log_image_0`` at t0_us and backward from ``log_image_1`` at t1_us, stitched at the middle.

    Both images are (height, width) log intensities (the EDI-sharpened latents in the pipeline); masks restrict
    detection on each image. Backward tracks start at corners of the end image: with ``backward_start="detect"``
    at independently detected ones (the paper's reading), with ``"relocate"`` (default) at the forward tracks'
    points found in the end image (:func:`relocate`) plus detected corners at least ``config.min_distance_px``
    away from those. See :func:`stitch` for the association and the output.
    """
    if backward_start not in ("detect", "relocate"):
        raise ValueError(f"backward_start: expected 'detect' or 'relocate', got {backward_start!r}")
    fwd, warps = _track(log_image_0, events, t0_us, t1_us, +1, config, None, mask_0)
    features_1 = None
    if backward_start == "relocate":
        found = relocate(log_image_0, log_image_1, fwd, t1_us, warps, stitch_px, radius_px=config.relocate_radius_px)
        found = found[np.all(np.isfinite(found), axis=1)]
        detected = detect_features(log_image_1, mask_1, config)
        if found.size and detected.size:
            d = np.hypot(detected[:, None, 0] - found[None, :, 0], detected[:, None, 1] - found[None, :, 1])
            detected = detected[d.min(axis=1) >= config.min_distance_px]
        features_1 = np.concatenate([found, detected])[: max(config.max_features, found.shape[0])]
    bwd = track(log_image_1, events, t0_us, t1_us, -1, config, features=features_1, mask=mask_1)
    return stitch(fwd, bwd, t0_us, t1_us, stitch_px, mode)
