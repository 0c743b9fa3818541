"""The sensor size of a recording whose file does not declare one, judged from its events' coordinates.

The same judgement serves :func:`eventcap.io.read_recording` (events in memory) and ``eventcap convert`` (events
streamed): both feed :class:`CoordinateStats` (histograms of x and y and a few counts; bounded memory) and ask
:meth:`CoordinateStats.judge` for the size. Coordinates far outside the dense block of the others are outliers,
never a wider sensor:

- a few events (at most 0.5 %, at most 100) beyond a gap of 25 % (and 16 px) past the others' largest coordinate
  are dropped;
- events beyond the edge of a known sensor (:data:`KNOWN_SENSORS`) that the others fill, lying there at a tenth of
  the density or less, with a sharp edge, are outliers: dropped when they are at most 0.1 % of the events (at most
  100 when fewer), refused otherwise (a wider sensor is then the user's to declare);
- events outside every known sensor: dropped when they are few (as above), refused otherwise;
- an inferred size must look like a sensor: not narrower than 8 px, no wider than 2.5 times its height (or the
  reverse; sensors range from 1:1 to 16:9), and without a margin of more than a quarter of it where no event lies
  (a block of events that starts far from (0, 0) is shifted or cropped coordinates).

A refusal is a :class:`RecordingError` that says what was seen and how to give the size (``how``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from eventcap.io.recording import RecordingError

#: Resolutions (width, height) of event sensors on the market, from their makers' datasheets.
KNOWN_SENSORS: dict[str, tuple[int, int]] = {
    "DVS128": (128, 128), "DAVIS240C": (240, 180), "DAVIS346": (346, 260), "DVXplorer": (640, 480),
    "Prophesee Gen3 VGA": (640, 480), "Prophesee EVK4 / Sony IMX636": (1280, 720), "CelePixel CeleX-V": (1280, 800),
    "Samsung DVS Gen4": (1280, 960),
}
#: No known sensor is wider or taller: an inferred size beyond it is not a plausible sensor.
PLAUSIBLE_WIDTH = max(w for w, _ in KNOWN_SENSORS.values())
PLAUSIBLE_HEIGHT = max(h for _, h in KNOWN_SENSORS.values())
#: Outliers dropped at most (events); the share below which they are dropped rather than refused.
OUTLIER_BUDGET_MAX = 100
MAX_OUTSIDE_SHARE = 0.001
#: An inferred sensor narrower or lower than this is not a camera's (e.g. all-zero coordinates).
MIN_INFERRED_SIDE = 8
#: Known sensors range from 1:1 to 16:9; an inferred size beyond this ratio of its sides is no sensor's shape.
MAX_ASPECT = 2.5
#: Events beyond a known sensor's edge at this fraction of the density inside it (or less) are not its pixels.
EDGE_DENSITY_RATIO = 0.1
#: Columns (rows) on each side of such an edge compared for its sharpness.
EDGE_BAND = 8
_SIDE = 1 << 16  # coordinates are uint16


def outlier_budget(n: int) -> int:
    """How many far events (beyond a gap) are dropped at most among ``n``: 0.5 %, at least 1, at most 100."""
    return min(OUTLIER_BUDGET_MAX, max(1, n // 200))


def few(k: int, n: int) -> bool:
    """Whether ``k`` of ``n`` events are few enough to drop as outliers (at most 0.1 %, or at most 100)."""
    return k <= max(OUTLIER_BUDGET_MAX, MAX_OUTSIDE_SHARE * n)


def size_note(width: int, height: int, dropped: int, reasons: str) -> str:
    """The repair sentence of an inferred size and the outliers dropped (``dropped`` events; ``reasons`` why)."""
    note = (f"sensor size not in the file: inferred {width} × {height} from the largest event coordinates (pass "
            f"width= and height= to set it)")
    return note + (f"; ignored and dropped {dropped} outlier event(s): {reasons}" if dropped else "")


@dataclass
class SizeDecision:
    """The judged size: ``width`` × ``height``; events with x >= ``keep_x`` or y >= ``keep_y`` are dropped
    (outliers); ``note`` is the repair sentence."""

    width: int
    height: int
    keep_x: int
    keep_y: int
    dropped: int
    note: str
    reasons: str = ""  # why the dropped events are outliers (the note's tail)


@dataclass
class CoordinateStats:
    """Histograms of the x and y coordinates of a stream of events, and how many lie outside each known sensor."""

    n: int = 0
    hx: np.ndarray = field(default_factory=lambda: np.zeros(_SIDE, np.int64))
    hy: np.ndarray = field(default_factory=lambda: np.zeros(_SIDE, np.int64))
    #: per known sensor (in KNOWN_SENSORS order): events with x >= W or y >= H
    outside: np.ndarray = field(default_factory=lambda: np.zeros(len(KNOWN_SENSORS), np.int64))
    #: per known sensor: events with x < W and y >= H (below it), and x >= W and y < H (right of it)
    below: np.ndarray = field(default_factory=lambda: np.zeros(len(KNOWN_SENSORS), np.int64))
    right: np.ndarray = field(default_factory=lambda: np.zeros(len(KNOWN_SENSORS), np.int64))
    #: events beyond every known sensor's edges (x >= PLAUSIBLE_WIDTH or y >= PLAUSIBLE_HEIGHT)
    implausible: int = 0

    def add(self, x: np.ndarray, y: np.ndarray) -> None:
        x = np.asarray(x, np.int64)
        y = np.asarray(y, np.int64)
        if not len(x):
            return
        self.n += len(x)
        self.hx += np.bincount(x, minlength=_SIDE)[:_SIDE]
        self.hy += np.bincount(y, minlength=_SIDE)[:_SIDE]
        for k, (w, h) in enumerate(KNOWN_SENSORS.values()):
            xo, yo = x >= w, y >= h
            self.outside[k] += int(np.count_nonzero(xo | yo))
            self.below[k] += int(np.count_nonzero(~xo & yo))
            self.right[k] += int(np.count_nonzero(xo & ~yo))
        self.implausible += int(np.count_nonzero((x >= PLAUSIBLE_WIDTH) | (y >= PLAUSIBLE_HEIGHT)))

    # ------------------------------------------------------------------------------------------------ judging
    def _gap_limit(self, h: np.ndarray) -> tuple[int, int, int]:
        """(limit, count above it, largest) of the gap rule on one axis: at most outlier_budget(n) events more
        than 25 % (and 16 px) beyond the largest coordinate of the others."""
        budget = outlier_budget(self.n)
        nz = np.flatnonzero(h)
        counts = h[nz]
        above = np.cumsum(counts[::-1])[::-1]  # events at or above each nonzero coordinate
        # the largest coordinate that still has more than `budget` events at or above it
        idx = int(np.flatnonzero(above > budget)[-1]) if np.any(above > budget) else 0
        bulk = int(nz[idx])
        limit = max(bulk + 16, int(bulk * 1.25))
        far = int(h[limit + 1:].sum())
        return (limit, far, int(nz[-1])) if 0 < far <= budget else (_SIDE, 0, 0)

    def judge(self, path, how: str) -> SizeDecision:
        """The size the events show, the outliers to drop, or a :class:`RecordingError` (``how``: how the user
        gives a size, in the API's or the CLI's words)."""
        n = self.n
        keep_x, keep_y = _SIDE, _SIDE
        why: list[str] = []
        for axis, h in (("x", self.hx), ("y", self.hy)):
            limit, far, top = self._gap_limit(h)
            if far:
                other = int(np.flatnonzero(h[:limit + 1])[-1])
                why.append(f"{far} event(s) with {axis} up to {top} (beyond {axis} = {other} of the others)")
                if axis == "x":
                    keep_x = limit + 1
                else:
                    keep_y = limit + 1
        max_x, max_y = self._max(self.hx, keep_x), self._max(self.hy, keep_y)
        # beyond every known sensor
        if max_x >= PLAUSIBLE_WIDTH or max_y >= PLAUSIBLE_HEIGHT:
            k_out = self._count_outside(PLAUSIBLE_WIDTH, PLAUSIBLE_HEIGHT, keep_x, keep_y)
            if not few(k_out, n) or "--" in how:
                raise RecordingError(path, f"{k_out:,} of {n:,} events ({100 * k_out / n:.2g} %) lie outside every "
                                           f"known event sensor (the largest: {PLAUSIBLE_WIDTH} × {PLAUSIBLE_HEIGHT} "
                                           f"px; x up to {max_x}, y up to {max_y}): the file does not declare its "
                                           f"size and {max_x + 1} × {max_y + 1} is not a plausible sensor (corrupt "
                                           f"events, or the wrong column order?). If the sensor is that large, {how}")
            why.append(f"{k_out} event(s) outside every known sensor ({PLAUSIBLE_WIDTH} × {PLAUSIBLE_HEIGHT} px)")
            keep_x, keep_y = min(keep_x, PLAUSIBLE_WIDTH), min(keep_y, PLAUSIBLE_HEIGHT)
            max_x, max_y = self._max(self.hx, keep_x), self._max(self.hy, keep_y)
        # beyond the edge of a known sensor the others fill
        edge = self._known_edge(max_x, max_y, keep_x, keep_y)
        if edge is not None:
            name, (w, h), k_out, ratio = edge
            where = " or ".join(s for s, beyond in ((f"x >= {w}", max_x >= w), (f"y >= {h}", max_y >= h)) if beyond)
            if not few(k_out, n):
                raise RecordingError(path, f"{k_out:,} of {n:,} events ({100 * k_out / n:.2g} %) lie at {where}, "
                                           f"outside the {w} × {h} block ({name}'s size) that the others fill, at "
                                           f"{ratio:.2g} times their density: corrupted coordinates, not a wider "
                                           f"sensor (inferred it would be {max_x + 1} × {max_y + 1}). To keep the "
                                           f"block and drop them: width={max_x + 1}, height={max_y + 1} and roi "
                                           f"0 0 {w} {h} (--width {max_x + 1} --height {max_y + 1} --roi 0 0 {w} "
                                           f"{h}); if the sensor is that large, {how}")
            why.append(f"{k_out} event(s) at {where}, outside the {w} × {h} block ({name}) the others fill, at "
                       f"{ratio:.2g} times their density")
            keep_x, keep_y = min(keep_x, w), min(keep_y, h)
            max_x, max_y = self._max(self.hx, keep_x), self._max(self.hy, keep_y)
        err = self._shape_problem(path, max_x, max_y, keep_x, keep_y, how)
        if err is not None:
            raise err
        width, height = max_x + 1, max_y + 1
        dropped = n - self._count_inside(keep_x, keep_y)
        reasons = "; ".join(why)
        return SizeDecision(width, height, keep_x, keep_y, dropped, size_note(width, height, dropped, reasons), reasons)

    @staticmethod
    def _max(h: np.ndarray, keep: int) -> int:
        nz = np.flatnonzero(h[:keep])
        return int(nz[-1]) if len(nz) else 0

    def _count_inside(self, keep_x: int, keep_y: int) -> int:
        """Events with x < keep_x and y < keep_y: exact when one of the two cuts nothing, else a bound from the
        per-sensor counts (both cuts at a known sensor's edge) or the axis histograms."""
        out_x = int(self.hx[keep_x:].sum())
        out_y = int(self.hy[keep_y:].sum())
        if out_x == 0 or out_y == 0:
            return self.n - out_x - out_y
        for k, (w, h) in enumerate(KNOWN_SENSORS.values()):
            if (w, h) == (keep_x, keep_y):
                return self.n - int(self.outside[k])
        return self.n - max(out_x, out_y)  # a lower bound of those dropped (streaming: only used for the note)

    def _count_outside(self, w: int, h: int, keep_x: int, keep_y: int) -> int:
        """Events outside every known sensor that the gap rule has not dropped already."""
        gone = int(self.hx[max(keep_x, w):].sum()) + int(self.hy[max(keep_y, h):].sum())
        return max(0, self.implausible - gone) if (keep_x < _SIDE or keep_y < _SIDE) else self.implausible

    def _known_edge(self, max_x: int, max_y: int, keep_x: int, keep_y: int):
        """The known sensor at whose edge the events' density drops (name, size, events beyond it, density ratio),
        or None: the others fill it; those beyond lie at EDGE_DENSITY_RATIO of their density or less, and the drop
        is sharp (the EDGE_BAND columns or rows just outside hold at most twice that ratio of those just inside)."""
        n = self.n
        trimmed = n - self._count_inside(keep_x, keep_y)  # already dropped: they lie beyond every sensor below
        best = None
        for k, (name, (w, h)) in enumerate(KNOWN_SENSORS.items()):
            if w > max_x + 1 or h > max_y + 1 or (w, h) == (max_x + 1, max_y + 1):
                continue
            beyond = int(self.outside[k]) - trimmed
            inside = n - int(self.outside[k])
            if beyond <= 0 or inside <= 0:
                continue
            d_in, d_out = inside / (w * h), beyond / max((max_x + 1) * (max_y + 1) - w * h, 1)
            if d_out > EDGE_DENSITY_RATIO * d_in:
                continue
            sharp = True
            for hist, edge, beyond_it in ((self.hx, w, max_x + 1 > w), (self.hy, h, max_y + 1 > h)):
                if beyond_it:
                    sharp &= bool(hist[edge:edge + EDGE_BAND].mean()
                                  <= 2 * EDGE_DENSITY_RATIO * hist[max(0, edge - EDGE_BAND):edge].mean())
            if sharp and (best is None or w * h > best[1][0] * best[1][1]):
                best = (name, (w, h), beyond, d_out / d_in)
        return best

    def _shape_problem(self, path, max_x: int, max_y: int, keep_x: int, keep_y: int, how: str):
        n = self.n
        if max_x + 1 < MIN_INFERRED_SIDE or max_y + 1 < MIN_INFERRED_SIDE:
            return RecordingError(path, f"the {n:,} events span only x <= {max_x} and y <= {max_y}, a {max_x + 1} × "
                                        f"{max_y + 1} sensor: not a camera's (all coordinates zero? a broken decode "
                                        f"or the wrong columns); the file does not declare its size: {how}")
        w, h = max_x + 1, max_y + 1
        if (w, h) in KNOWN_SENSORS.values():
            return None
        if max(w / h, h / w) > MAX_ASPECT:
            return RecordingError(path, f"the events span {w} × {h} px ({max(w / h, h / w):.2g}:1), no event sensor's "
                                        f"shape (they range from 1:1 to 16:9): corrupted coordinates mixed in, or the "
                                        f"wrong columns? The file does not declare its size: {how}")
        for axis, hist, side, keep in (("x", self.hx, w, keep_x), ("y", self.hy, h, keep_y)):
            first = int(np.flatnonzero(hist[:keep])[0])
            if first > max(16, side // 4):
                return RecordingError(path, f"no event at {axis} < {first}: the events fill {axis} = {first}..{side - 1} "
                                            f"only, so an inferred {w} × {h} sensor would be empty over a "
                                            f"{100 * first / side:.0f} % margin (shifted coordinates, or a crop that "
                                            f"kept the sensor's coordinates?). The file does not declare its size: "
                                            f"{how}")
        return None
