"""The open benchmark's generated captures (``eventcap benchmark benchmark=open``): each one drawn from its seed.

A capture is a synthetic recording whose conditions nobody chose: the motion (a shipped CMU clip from a start time
inside it, or a built-in motion from a start time inside its performance), the camera preset, the camera's distance,
height and tilt, the illuminance (which drives the photoreceptor-bandwidth model and the frames' noise), the contrast
threshold, the background and the sensor seed. The distributions are stated, one comment each, in the ``draws``
section of ``conf/benchmark/open.yaml``; this module reads them (:func:`parse_draws`) and draws (:func:`draw_capture`).

The generator: every drawn value has its own stream, ``numpy.random.default_rng([salt, seed, crc32(name)])`` (PCG64
seeded through a SeedSequence), from which exactly one double in [0, 1) is taken; every distribution is that double
transformed (a uniform range, a log-uniform range, an index into a list). Only the bit generator's stream is relied
on, which numpy keeps stable across versions and machines, and each value is rounded to a fixed number of decimals, so
the same seed gives the same capture on any machine. Adding a new drawn value does not move the others.

Seeds are split by purpose, structurally: :data:`TUNING_SEEDS` (``benchmark=open``) may be looked at while choosing
anything; :data:`CHECK_SEEDS` (``benchmark=open_check``) are only ever run to report, and a suite refuses seeds of
the other purpose.
"""

from __future__ import annotations

import functools
import math
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

#: Seeds that tuning may look at (``benchmark=open``).
TUNING_SEEDS = range(0, 20)
#: Seeds that are only ever run to report (``benchmark=open_check``): never tune on their numbers.
CHECK_SEEDS = range(100, 120)
PURPOSES: dict[str, range] = {"tuning": TUNING_SEEDS, "check": CHECK_SEEDS}
CHECK_NOTE = ("the check seeds (100-119): for reporting only. Nothing may be chosen or tuned on these numbers; "
              "tune on benchmark=open (seeds 0-19)")

_GROUP_KEYS = {"label", "cameras", "motions", "distance_factor", "height_m", "aim_m", "tilt_jitter_deg"}
_DRAW_KEYS = {"salt", "cycle", "groups", "builtin_start_s", "illuminance_lux", "contrast_threshold", "backgrounds",
              "background_seeds", "source_seeds"}
#: ``draws`` keys that may be left out (null or absent): ``body`` (without it, every capture films the template).
_OPTIONAL_DRAW_KEYS = {"body"}
_BODY_KEYS = {"height_m", "build", "muscle", "sex", "outfit_seeds", "told_error_m", "told_nothing"}


@dataclass(frozen=True)
class GroupDraws:
    """How the captures of one group are drawn (``draws.groups.<name>`` of the benchmark config)."""

    name: str
    label: str  # shown in the tables
    cameras: tuple[str, ...]  # uniform over these presets
    motions: tuple[str, ...]  # uniform over these (cmu/<trial> clips and built-in motion names)
    distance_factor: tuple[float, float]  # uniform; times the preset's distance
    height_m: tuple[float, float]  # uniform; camera height above the floor
    aim_m: float  # the camera points at this height above the actor's feet ...
    tilt_jitter_deg: tuple[float, float]  # ... plus a uniform pitch in this range (degrees, positive down)
    frames: bool  # the group's cameras record intensity frames (all of them, or none)


@dataclass(frozen=True)
class BodyDraws:
    """How the filmed person is drawn (``draws.body``) and what its user is told to type."""

    height_m: tuple[float, float]  # uniform stature
    build: tuple[float, float]  # uniform, ANNY's weight phenotype
    muscle: tuple[float, float]  # uniform
    sex: tuple[float, float]  # uniform (-1 female .. +1 male)
    outfit_seeds: int  # uniform integer in [0, n): the outfit's tones and prints
    told_error_m: tuple[float, float]  # the stature the user types: the true one plus a uniform error in this range
    told_nothing: float  # the share of captures whose user types nothing (the template's default body)


@dataclass(frozen=True)
class Draws:
    """The distributions of the generated captures (``draws`` of the benchmark config), checked."""

    salt: int
    cycle: tuple[str, ...]  # capture seed s belongs to group cycle[s % len(cycle)] (stratified)
    groups: dict[str, GroupDraws]
    builtin_start_s: tuple[float, float]  # uniform start time of a built-in motion's performance
    illuminance_lux: tuple[float, float]  # log-uniform
    contrast_threshold: tuple[float, float]  # uniform
    backgrounds: tuple[str, ...]  # uniform
    background_seeds: int  # uniform integer in [0, n)
    source_seeds: int  # uniform integer in [0, n): the sensor's noise and thresholds, a built-in performance
    body: BodyDraws | None = None  # the filmed person; None: every capture films the template


@dataclass(frozen=True)
class Capture:
    """One generated capture: everything drawn from its seed."""

    seed: int
    group: str
    motion: str
    motion_start_s: float
    camera: str
    frames: bool
    distance_m: float
    height_m: float
    tilt_deg: float
    illuminance_lux: float
    contrast_threshold: float
    background: str
    background_seed: int
    source_seed: int
    # the filmed person (source.actor) and what the run is told about it; None: the template is filmed
    actor_height_m: float | None = None
    actor_build: float | None = None
    actor_muscle: float | None = None
    actor_sex: float | None = None
    actor_seed: int | None = None
    told_height_m: float | None = None  # the stature the user types; None: nothing (also when no actor is drawn)

    @property
    def label(self) -> str:
        return f"s{self.seed}"

    def values(self) -> dict[str, Any]:
        """The drawn values by name (the ``{...}`` fields of the suite's ``sequence_overrides``)."""
        return asdict(self)

    def describe(self) -> str:
        person = "" if self.actor_height_m is None else (
            f"; a {self.actor_height_m:.2f} m person (build {self.actor_build:+.2f}, muscle {self.actor_muscle:+.2f}, "
            f"sex {self.actor_sex:+.2f}), told "
            + ("nothing" if self.told_height_m is None else f"{self.told_height_m:.2f} m"))
        return (f"{self.motion} from {self.motion_start_s:.2f} s; {self.camera} "
                f"({'frames' if self.frames else 'event-only'}) {self.distance_m:.2f} m away, "
                f"{self.height_m:.2f} m high, {self.tilt_deg:+.1f} deg; {self.illuminance_lux:g} lux; "
                f"C {self.contrast_threshold:.3f}; {self.background} background{person}")


def uniform(seed: int, salt: int, name: str) -> float:
    """The double in [0, 1) of value ``name`` of capture ``seed`` (its own stream; see the module's docstring)."""
    return float(np.random.default_rng([int(salt), int(seed), zlib.crc32(name.encode())]).random())


def _pick(seq: Sequence, u: float):
    return seq[min(int(u * len(seq)), len(seq) - 1)]


def _between(lo_hi: tuple[float, float], u: float) -> float:
    return lo_hi[0] + u * (lo_hi[1] - lo_hi[0])


@functools.lru_cache(maxsize=64)
def clip_duration_s(name: str) -> float:
    """Length of a recorded clip (``cmu/<trial>`` or a BVH path), read from its file (once per process)."""
    from eventcap.body.bvh_clip import read_bvh
    from eventcap.body.clips import clip_path

    return read_bvh(clip_path(name)).duration_s


@functools.lru_cache(maxsize=16)
def _preset(name: str):
    from eventcap.camera_presets import load_preset

    return load_preset(name)


def draw_capture(seed: int, draws: Draws, duration_s: float) -> Capture:
    """The capture of ``seed``: every value drawn from its own stream, rounded to fixed decimals."""
    from eventcap.body.clips import is_clip

    u = lambda name: uniform(seed, draws.salt, name)  # noqa: E731
    group = draws.groups[draws.cycle[seed % len(draws.cycle)]]
    camera = _pick(group.cameras, u("camera"))
    preset = _preset(camera)
    motion = _pick(group.motions, u("motion"))
    if is_clip(motion):
        room = clip_duration_s(motion) - duration_s
        if room < 0:
            raise ValueError(f"draws: clip {motion} lasts {room + duration_s:.2f} s, shorter than duration_s="
                             f"{duration_s}")
        start = u("motion_start") * room
    else:
        start = _between(draws.builtin_start_s, u("motion_start"))
    distance = preset.distance_m * _between(group.distance_factor, u("distance"))
    height = _between(group.height_m, u("height"))
    tilt = math.degrees(math.atan2(height - group.aim_m, distance)) + _between(group.tilt_jitter_deg, u("tilt"))
    lo, hi = draws.illuminance_lux
    lux = math.exp(math.log(lo) + u("illuminance") * (math.log(hi) - math.log(lo)))
    person = {}
    if draws.body is not None:
        b = draws.body
        stature = round(_between(b.height_m, u("actor_height")), 3)
        told = None if u("told_nothing") < b.told_nothing else round(stature + _between(b.told_error_m,
                                                                                        u("told_error")), 3)
        person = dict(actor_height_m=stature, actor_build=round(_between(b.build, u("actor_build")), 3),
                      actor_muscle=round(_between(b.muscle, u("actor_muscle")), 3),
                      actor_sex=round(_between(b.sex, u("actor_sex")), 3),
                      actor_seed=int(u("actor_seed") * b.outfit_seeds), told_height_m=told)
    return Capture(
        seed=int(seed), group=group.name, motion=motion, motion_start_s=round(start, 3), camera=camera,
        frames=bool(preset.frames), distance_m=round(distance, 3), height_m=round(height, 3),
        tilt_deg=round(tilt, 2), illuminance_lux=round(lux, 1),
        contrast_threshold=round(_between(draws.contrast_threshold, u("contrast_threshold")), 3),
        background=_pick(draws.backgrounds, u("background")),
        background_seed=int(u("background_seed") * draws.background_seeds),
        source_seed=int(u("source_seed") * draws.source_seeds), **person)


def suite_seeds(purpose: str, seeds: Sequence[int] | None) -> list[int]:
    """The seeds a suite of this purpose runs: all of the purpose's (``seeds`` null) or a subset of them; seeds of
    the other purpose are refused, naming the preset that runs them."""
    if purpose not in PURPOSES:
        raise ValueError(f"purpose: expected one of {', '.join(PURPOSES)}, got {purpose!r}")
    allowed = PURPOSES[purpose]
    if seeds is None:
        return list(allowed)
    out = [int(s) for s in seeds]
    bad = [s for s in out if s not in allowed]
    if bad or not out:
        other = "benchmark=open_check (for reporting only)" if any(s in CHECK_SEEDS for s in bad) else \
            "benchmark=open"
        raise ValueError(f"seeds: a {purpose} suite runs seeds {allowed.start}-{allowed.stop - 1}, got {out}"
                         + (f"; {bad} belong to {other}" if bad else ""))
    return out


# ---------------------------------------------------------------------------------------------------------------------
# Reading the distributions
# ---------------------------------------------------------------------------------------------------------------------
def _range(where: str, value: Any, low: float = -math.inf, positive: bool = False) -> tuple[float, float]:
    ok = (isinstance(value, Sequence) and not isinstance(value, str) and len(value) == 2
          and all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value))
    if not ok or not (low <= value[0] <= value[1]) or (positive and value[0] <= 0):
        bound = "> 0" if positive else (f">= {low:g}" if math.isfinite(low) else "finite")
        raise ValueError(f"draws.{where}: expected [low, high] with {bound} <= low <= high, got {value!r}")
    return float(value[0]), float(value[1])


def _names(where: str, value: Any, known: Sequence[str] | None = None) -> tuple[str, ...]:
    if not (isinstance(value, Sequence) and not isinstance(value, str) and value):
        raise ValueError(f"draws.{where}: expected a non-empty list, got {value!r}")
    out = tuple(str(v) for v in value)
    if known is not None:
        bad = [v for v in out if v not in known]
        if bad:
            raise ValueError(f"draws.{where}: unknown {bad[0]!r}; expected one of {', '.join(known)}")
    return out


def _count(where: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"draws.{where}: expected an integer >= 1, got {value!r}")
    return value


def _check_motions(where: str, motions: tuple[str, ...]) -> None:
    from eventcap.body.clips import clip_path, is_clip
    from eventcap.body.motions import MOTIONS

    for m in motions:
        if is_clip(m):
            try:
                clip_path(m)
            except FileNotFoundError as exc:
                raise ValueError(f"draws.{where}: {exc}") from None
        elif m not in MOTIONS:
            raise ValueError(f"draws.{where}: unknown motion {m!r}; built-in: {', '.join(MOTIONS)}, or cmu/<trial>")


def _parse_group(name: str, g: Any) -> GroupDraws:
    from eventcap.camera_presets import preset_names

    where = f"groups.{name}"
    if not isinstance(g, Mapping):
        raise ValueError(f"draws.{where}: expected a mapping with the keys {', '.join(sorted(_GROUP_KEYS))}")
    keys = set(g)
    if keys != _GROUP_KEYS:
        raise ValueError(f"draws.{where}: missing {sorted(_GROUP_KEYS - keys)}, unknown {sorted(keys - _GROUP_KEYS)}")
    cameras = _names(f"{where}.cameras", g["cameras"], preset_names())
    frames = {c: _preset(c).frames for c in cameras}
    if len(set(frames.values())) != 1:
        raise ValueError(f"draws.{where}.cameras: a group's cameras all record frames or none do, got "
                         + ", ".join(f"{c} ({'frames' if f else 'event-only'})" for c, f in frames.items()))
    motions = _names(f"{where}.motions", g["motions"])
    _check_motions(f"{where}.motions", motions)
    aim = g["aim_m"]
    if isinstance(aim, bool) or not isinstance(aim, (int, float)) or not math.isfinite(aim):
        raise ValueError(f"draws.{where}.aim_m: expected a height in metres, got {aim!r}")
    return GroupDraws(name=name, label=str(g["label"]), cameras=cameras, motions=motions,
                      distance_factor=_range(f"{where}.distance_factor", g["distance_factor"], positive=True),
                      height_m=_range(f"{where}.height_m", g["height_m"]), aim_m=float(aim),
                      tilt_jitter_deg=_range(f"{where}.tilt_jitter_deg", g["tilt_jitter_deg"]),
                      frames=bool(next(iter(frames.values()))))


def parse_draws(data: Any) -> Draws:
    """The ``draws`` section of a generated suite's config, checked: every key, range and name, with errors naming
    ``draws.<key>`` and what was expected."""
    if not isinstance(data, Mapping):
        raise ValueError(f"draws: expected a mapping with the keys {', '.join(sorted(_DRAW_KEYS))}, got {data!r}")
    keys = set(data)
    if not _DRAW_KEYS <= keys <= _DRAW_KEYS | _OPTIONAL_DRAW_KEYS:
        raise ValueError(f"draws: missing {sorted(_DRAW_KEYS - keys)}, unknown "
                         f"{sorted(keys - _DRAW_KEYS - _OPTIONAL_DRAW_KEYS)}")
    groups_in = data["groups"]
    if not isinstance(groups_in, Mapping) or not groups_in:
        raise ValueError(f"draws.groups: expected a mapping of group name -> its draws, got {groups_in!r}")
    groups = {str(n): _parse_group(str(n), g) for n, g in groups_in.items()}
    from eventcap.imaging.render import BACKGROUNDS

    return Draws(salt=_count("salt", data["salt"]), cycle=_names("cycle", data["cycle"], list(groups)), groups=groups,
                 builtin_start_s=_range("builtin_start_s", data["builtin_start_s"], low=0.0),
                 illuminance_lux=_range("illuminance_lux", data["illuminance_lux"], positive=True),
                 contrast_threshold=_range("contrast_threshold", data["contrast_threshold"], positive=True),
                 backgrounds=_names("backgrounds", data["backgrounds"], list(BACKGROUNDS)),
                 background_seeds=_count("background_seeds", data["background_seeds"]),
                 source_seeds=_count("source_seeds", data["source_seeds"]), body=_parse_body(data.get("body")))


def _parse_body(b: Any) -> BodyDraws | None:
    """``draws.body``, checked (None when it is null or absent)."""
    if b is None:
        return None
    if not isinstance(b, Mapping) or set(b) != _BODY_KEYS:
        got = set(b) if isinstance(b, Mapping) else set()
        raise ValueError(f"draws.body: expected a mapping with the keys {', '.join(sorted(_BODY_KEYS))}; missing "
                         f"{sorted(_BODY_KEYS - got)}, unknown {sorted(got - _BODY_KEYS)}")
    height = _range("body.height_m", b["height_m"], positive=True)
    if not (1.2 <= height[0] and height[1] <= 2.3):
        raise ValueError(f"draws.body.height_m: expected statures within the ANNY body's [1.2, 2.3] m, got {list(height)}")
    units = {k: _range(f"body.{k}", b[k], low=-1.0) for k in ("build", "muscle", "sex")}
    for k, (lo, hi) in units.items():
        if hi > 1.0:
            raise ValueError(f"draws.body.{k}: expected a range within [-1, 1], got {[lo, hi]}")
    share = b["told_nothing"]
    if isinstance(share, bool) or not isinstance(share, (int, float)) or not 0.0 <= share <= 1.0:
        raise ValueError(f"draws.body.told_nothing: expected a share in [0, 1], got {share!r}")
    return BodyDraws(height_m=height, **units, outfit_seeds=_count("body.outfit_seeds", b["outfit_seeds"]),
                     told_error_m=_range("body.told_error_m", b["told_error_m"]), told_nothing=float(share))
