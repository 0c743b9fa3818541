"""Is a motion humanly possible? Warnings for speeds beyond human limits, joints behind the camera, sudden flips.

A motion fitted to what a camera did not see can be smooth and still impossible: a skeleton fitted into a face
lies along the line of sight with its head behind the camera; one fitted onto a hand moves its pelvis at 7-18 m/s
(issue 35). :func:`check_motion` looks for what no person does and returns each kind of finding once, with the
frames where it happens (as index and time ranges); :func:`log_findings` logs one line per kind and
:func:`write_plausibility` writes them to ``plausibility.json``. They are warnings: the motion is not changed.

Checks and the figures behind their limits (speeds by central differences over ``window_us``, 10 ms by default,
as the velocity metrics, so that millimetre jitter at 1 kHz does not count):

- ``speed``: a joint faster than the fastest people move that body part (:data:`SPEED_LIMITS_MPS`):
  the pelvis 12.5 m/s (Usain Bolt's fastest 20 m averaged 12.14 m/s, Čoh et al., Kinesiology 50(2), 2018);
  head, spine, hips and shoulders 15 m/s (a sprint plus the trunk's turn); elbows and knees 25 m/s; wrists and
  hands 40 m/s (a pitched ball leaves the fingers at 37.4 ± 0.8 m/s in fast collegiate pitchers, Kageyama et al.,
  JSSM 13, 2014; boxers' fists reach 9.3 ± 2.1 m/s, Piorkowski, Lees and Barton, Sports Biomechanics 10, 2011);
  ankles and feet 30 m/s (the foot reaches about 20-25 m/s in maximal soccer kicks, Lees and Nolan, J Sports Sci
  16, 1998).
- ``root_flip``: the pelvis's orientation (from the hips and the spine, so any skeleton parameterisation gives the
  same) turning faster than 40 rad/s: figure skaters spin 4.5-6 turns per second in quadruple jumps (about 28-38
  rad/s), and nothing a person does turns the whole body faster.
- ``behind_camera``: joints less than ``near_m`` (5 cm) in front of the camera, or behind it.
- ``head_below_pelvis``: for an upright capture in a y-up world, the head lower than the pelvis (a handstand, a
  deep bend or a fall do this; a motion fitted upside down does it all the time).
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from eventcap.body.skeleton import JOINT_INDEX, JOINT_NAMES, NUM_JOINTS
from eventcap.analysis.metrics import central_derivative, half_window_steps

log = logging.getLogger("eventcap.analysis.plausibility")

#: Fastest speed of each joint a person reaches, m/s (see the module docstring for the figures).
SPEED_LIMITS_MPS: dict[str, float] = {
    "pelvis": 12.5,
    **{j: 15.0 for j in ("l_hip", "r_hip", "spine1", "spine2", "spine3", "neck", "head", "l_collar", "r_collar",
                          "l_shoulder", "r_shoulder")},
    **{j: 25.0 for j in ("l_elbow", "r_elbow", "l_knee", "r_knee")},
    **{j: 40.0 for j in ("l_wrist", "r_wrist", "l_hand", "r_hand")},
    **{j: 30.0 for j in ("l_ankle", "r_ankle", "l_foot", "r_foot")},
}
#: Fastest turn of the whole body, rad/s (about 6 turns per second: figure skaters' quadruple jumps).
ROOT_TURN_LIMIT_RAD_S = 40.0
#: Nearer to the camera than this (or behind it) is "behind the camera", metres.
NEAR_M = 0.05
#: At most this many ranges are named in a log line (all are in the JSON).
_LOGGED_RANGES = 3


@dataclass(frozen=True)
class Finding:
    """One kind of implausibility: where (frame index ranges, inclusive, and their times), how bad (``peak`` in
    ``unit`` against ``limit``), which joints, and a one-line ``message``."""

    kind: str
    frames: tuple[tuple[int, int], ...]
    times_us: tuple[tuple[int, int], ...]
    count: int
    total: int
    peak: float
    limit: float
    unit: str
    joints: tuple[str, ...]
    message: str

    def to_dict(self) -> dict:
        return {k: (list(map(list, v)) if k in ("frames", "times_us") else v) for k, v in asdict(self).items()}


def _ranges(mask: np.ndarray) -> list[tuple[int, int]]:
    """Inclusive (first, last) index ranges of the runs of True in ``mask``."""
    m = np.concatenate([[False], np.asarray(mask, bool), [False]])
    d = np.diff(m.astype(np.int8))
    return [(int(a), int(b) - 1) for a, b in zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1))]


def _where(ranges, t_us) -> str:
    shown = [f"{t_us[a] / 1e6:.3f}-{t_us[b] / 1e6:.3f} s" if a != b else f"{t_us[a] / 1e6:.3f} s"
             for a, b in ranges[:_LOGGED_RANGES]]
    return ", ".join(shown) + (f" and {len(ranges) - _LOGGED_RANGES} more" if len(ranges) > _LOGGED_RANGES else "")


def _finding(kind, mask, t_us, peak, limit, unit, joints, what) -> Finding | None:
    if not mask.any():
        return None
    ranges = _ranges(mask)
    n, total = int(mask.sum()), int(mask.size)
    message = f"{what} in {n} of {total} frames ({_where(ranges, t_us)})"
    return Finding(kind, tuple(ranges), tuple((int(t_us[a]), int(t_us[b])) for a, b in ranges), n, total,
                   float(peak), float(limit), unit, tuple(joints), message)


def _speed(t_us, joints, window_us) -> Finding | None:
    v, valid = central_derivative(joints, t_us, window_us)
    speed = np.linalg.norm(v, axis=-1)  # (T, 24), NaN where not valid
    limits = np.array([SPEED_LIMITS_MPS[n] for n in JOINT_NAMES])
    ratio = np.where(valid[:, None], speed / limits, 0.0)
    over = ratio > 1.0
    if not over.any():
        return None
    bad = [j for j in range(NUM_JOINTS) if over[:, j].any()]
    worst = sorted(bad, key=lambda j: -np.nanmax(ratio[:, j]))
    parts = [f"{JOINT_NAMES[j]} up to {np.nanmax(speed[over[:, j], j]):.3g} m/s (limit {limits[j]:g})"
             for j in worst[:3]]
    more = f" and {len(worst) - 3} more joints" if len(worst) > 3 else ""
    j0 = worst[0]
    return _finding("speed", over.any(axis=1), t_us, np.nanmax(speed[:, j0]), limits[j0], "m/s",
                    [JOINT_NAMES[j] for j in worst], f"speed beyond human limits: {', '.join(parts)}{more}")


def pelvis_frames(joints: np.ndarray) -> np.ndarray:
    """(T, 3, 3) orientation of the pelvis from the joints (columns: left hip - right hip, up the spine, forward)."""
    x = joints[:, JOINT_INDEX["l_hip"]] - joints[:, JOINT_INDEX["r_hip"]]
    up = joints[:, JOINT_INDEX["spine1"]] - joints[:, JOINT_INDEX["pelvis"]]
    x = x / np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), 1e-9)
    y = up - (up * x).sum(-1, keepdims=True) * x
    y = y / np.maximum(np.linalg.norm(y, axis=-1, keepdims=True), 1e-9)
    return np.stack([x, y, np.cross(x, y)], axis=-1)


def _root_flip(t_us, joints, window_us) -> Finding | None:
    R = pelvis_frames(joints)
    t = np.asarray(t_us, np.int64)
    k, step = half_window_steps(t, window_us)
    h = k * step
    hi, lo = np.searchsorted(t, t + h), np.searchsorted(t, t - h)
    ok = (hi < t.size) & (t[np.minimum(hi, t.size - 1)] == t + h) & (t[lo] == t - h)
    rate = np.zeros(t.size)
    i = np.flatnonzero(ok)
    rel = np.einsum("nji,njk->nik", R[lo[i]], R[hi[i]])  # R_lo^T R_hi
    cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    rate[i] = np.arccos(cos) / (2 * h * 1e-6)
    over = rate > ROOT_TURN_LIMIT_RAD_S
    return _finding("root_flip", over, t_us, rate.max(), ROOT_TURN_LIMIT_RAD_S, "rad/s", ["pelvis"],
                    f"sudden flips of the body: the pelvis turns at up to {rate.max():.0f} rad/s "
                    f"({math.degrees(rate.max()):.0f} deg/s; limit {ROOT_TURN_LIMIT_RAD_S:g} rad/s)")


def _behind_camera(t_us, joints, camera, near_m) -> Finding | None:
    depth = camera.depth(joints)  # (T, 24)
    bad = depth < near_m
    if not bad.any():
        return None
    names = [JOINT_NAMES[j] for j in range(NUM_JOINTS) if bad[:, j].any()]
    nearest = float(depth.min())
    how = f"up to {-nearest:.2f} m behind it" if nearest < 0 else f"within {near_m * 100:.0f} cm of it"
    return _finding("behind_camera", bad.any(axis=1), t_us, nearest, near_m, "m (depth)", names,
                    f"joints behind the camera ({', '.join(names[:4])}{' ...' if len(names) > 4 else ''}; {how})")


def _head_below_pelvis(t_us, joints) -> Finding | None:
    drop = joints[:, JOINT_INDEX["pelvis"], 1] - joints[:, JOINT_INDEX["head"], 1]
    return _finding("head_below_pelvis", drop > 0, t_us, drop.max(), 0.0, "m", ["head", "pelvis"],
                    f"the head below the pelvis (by up to {drop.max():.2f} m; y is up: a handstand, a deep bend "
                    f"or a fall, else a motion upside down)")


def check_motion(t_us, joints, camera=None, *, upright: bool = True, window_us: float = 10_000,
                 near_m: float = NEAR_M) -> list[Finding]:
    """Findings of a motion: ``t_us`` (T,) increasing µs, ``joints`` (T, 24, 3) world metres (y up), ``camera`` an
    :class:`eventcap.camera.Camera` (None: the behind-camera check is left out); ``upright``: the person is
    expected upright (the head-below-pelvis check). Speeds need at least 3 frames ``window_us`` apart."""
    t = np.asarray(t_us, np.int64)
    J = np.asarray(joints, np.float64)
    if J.ndim != 3 or J.shape[1:] != (NUM_JOINTS, 3) or J.shape[0] != t.size:
        raise ValueError(f"check_motion: expected joints ({t.size}, {NUM_JOINTS}, 3) at {t.size} times, got "
                         f"{J.shape}")
    found: list[Finding | None] = []
    if t.size >= 3:
        found += [_speed(t, J, window_us), _root_flip(t, J, window_us)]
    if camera is not None:
        found.append(_behind_camera(t, J, camera, near_m))
    if upright:
        found.append(_head_below_pelvis(t, J))
    return [f for f in found if f is not None]


def log_findings(findings: list[Finding], logger: logging.Logger = log) -> None:
    """One warning line per kind of finding (or one info line saying none was found)."""
    if not findings:
        logger.info("plausibility: no speed beyond human limits, no joint behind the camera, no sudden flip")
    for f in findings:
        logger.warning("plausibility: %s", f.message)


def write_plausibility(path, t_us, joints, camera=None, *, upright: bool = True) -> Path:
    """Check a motion (:func:`check_motion`), log the findings and write them to ``path`` (JSON: the checks' limits
    and every finding with all its frame ranges)."""
    findings = check_motion(t_us, joints, camera, upright=upright)
    log_findings(findings)
    path = Path(path)
    doc = {"frames": int(np.asarray(t_us).size), "limits": {"speed_mps": SPEED_LIMITS_MPS,
                                                            "root_turn_rad_s": ROOT_TURN_LIMIT_RAD_S,
                                                            "near_m": NEAR_M},
           "camera_checked": camera is not None, "upright": upright,
           "findings": [f.to_dict() for f in findings]}
    tmp = path.with_name(path.name + ".partial")
    tmp.write_text(json.dumps(doc, indent=1))
    tmp.replace(path)
    return path
