"""Simulated fast human motions for the synthetic event-camera capture (in the spirit of the paper's dataset).

These are generated, not captured: each motion is a loop of key poses joined by minimum-jerk transitions
(quintic, so positions, velocities and accelerations are continuous: C2), plus motion-specific smooth
overlays (waving, bouncing, jumps). A seed varies the performance: segment timings (±15 %), excursions
(-15 %/+10 %), motion-specific details and the side (left/right mirrored with probability 1/2). ``speed``
scales the tempo (pose at time t = pose of the speed-1 performance at ``speed * t``) and ``amplitude`` scales
every excursion from the motion's base pose (root spins keep their full turns). Joint angles always stay inside
the skeleton's bounds (a smooth saturation acts only within a few hundredths of a radian of a bound).

The root height is not keyframed: it keeps the lowest sole point (toes, heels of the template's landmarks)
at its rest-pose height (the rest pose stands on the floor) through a smooth soft-minimum (never lower, at
most 2 mm higher), plus the jump height of the jumping motions. Root x/z stay within a few decimetres of the origin.

``MOTIONS`` lists the motions, ``motion_poses`` samples one, ``sequence_poses`` chains several with smooth
(C2) blends, and ``peak_speeds`` reports how fast the wrists and ankles move.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from eventcap.body import kinematics
from eventcap.body.skeleton import (
    DEFAULT_REST_JOINTS,
    DOF_NAMES,
    LANDMARK_INDEX,
    NUM_POSE_PARAMS,
    THETA_LOWER,
    THETA_UPPER,
    default_landmarks,
    mirror_pose,
)
from eventcap.body.template import Template

#: Motion name -> what the actor does.
MOTIONS: dict[str, str] = {
    "karate_kick": "fighting guard, fast front kick with the rear leg, then a roundhouse kick with the other leg",
    "boxing_combo": "guard with a light bounce; jab, cross, lead hook, rear uppercut",
    "javelin_throw": "javelin carried by the ear, withdrawal, plant, explosive overhead throw, follow-through",
    "dance_spin": "plié with open arms, relevé pirouette (one full turn, leg in passé), arms up, hip sway",
    "fast_wave": "one arm raised and waving fast (≈3.5 Hz), then both arms overhead waving",
    "jumping_jack": "continuous jumping jacks (≈1.1 per second), arms from the sides to overhead",
    "high_knees": "running in place with high knees and pumping arms (≈2 strides per second)",
    "ninja_strike": "low stance, overhead two-step chop and a fast turning back-fist, return to stance",
}

#: Motions that are not fast (references for tests and sensor checks).
STATIC_MOTIONS: dict[str, str] = {
    "stand": "standing still, arms relaxed at the sides (a static scene: only sensor noise fires)",
}

#: Channels that are not joint angles: root rotation/translation (no root_ty: that comes from the floor).
_ROOT_CHANNELS = ("root_yaw", "root_pitch", "root_roll", "root_tx", "root_tz")
_SOLE_LANDMARKS = ("l_big_toe", "l_small_toe", "l_heel", "r_big_toe", "r_small_toe", "r_heel")
#: Temperature of the soft minimum over sole heights (metres): soles float at most τ·log(6) ≈ 2 mm high.
_FLOOR_SOFTMIN_M = 0.001
#: Smooth saturation keeps angles this far (radians) inside the bounds; it is sharp on this scale.
_BOUND_MARGIN = 0.002
_BOUND_SHARPNESS = 0.01


# --------------------------------------------------------------------------------------------------------
# Key-pose loops


@dataclass(frozen=True)
class _Key:
    """Move (minimum jerk) to ``pose`` in ``move_s`` seconds, then hold it for ``hold_s`` seconds."""

    move_s: float
    hold_s: float
    pose: dict


@dataclass
class _Spec:
    """A motion: base pose, a loop of keys, per-loop yaw increment and an optional overlay."""

    base: dict
    keys: list
    yaw_per_loop: float = 0.0
    overlay: Callable | None = None  # (u (T,) s, channels dict, loop period s) -> None, edits channels
    params: dict = field(default_factory=dict)


def _minjerk(x: np.ndarray) -> np.ndarray:
    """Quintic 0->1 on [0, 1] with zero velocity and acceleration at both ends."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (10.0 + x * (-15.0 + 6.0 * x))


def _eval_loop(spec: _Spec, u: np.ndarray) -> dict[str, np.ndarray]:
    """Evaluate every channel of a key loop at times u (T,) seconds; returns channel -> (T,)."""
    keys = spec.keys
    moves = np.array([k.move_s for k in keys])
    holds = np.array([k.hold_s for k in keys])
    starts = np.concatenate([[0.0], np.cumsum(moves + holds)[:-1]])
    loop = float(np.sum(moves + holds))
    n_loop = np.floor(u / loop)
    r = u - n_loop * loop
    idx = np.clip(np.searchsorted(starts, r, side="right") - 1, 0, len(keys) - 1)
    q = _minjerk((r - starts[idx]) / moves[idx])
    names = set(spec.base)
    for k in keys:
        names.update(k.pose)
    out = {}
    for name in names:
        vals = np.array([k.pose.get(name, spec.base.get(name, 0.0)) for k in keys], dtype=np.float64)
        inc = spec.yaw_per_loop if name == "root_yaw" else 0.0
        prev = np.roll(vals, 1)
        prev[0] -= inc  # the loop's first move starts from the previous loop's last key
        out[name] = prev[idx] + (vals[idx] - prev[idx]) * q + n_loop * inc
    return out


def _loop_period(spec: _Spec) -> float:
    return float(sum(k.move_s + k.hold_s for k in spec.keys))


def _vary(spec: _Spec, rng: np.random.Generator) -> _Spec:
    """Seeded variation of a key loop: timing of each key ±15 %, excursion of each key -15 %/+10 %."""
    keys = []
    for k in spec.keys:
        tscale = rng.uniform(0.85, 1.15)
        ascale = rng.uniform(0.85, 1.10)
        pose = {
            n: spec.base.get(n, 0.0) + ascale * (v - spec.base.get(n, 0.0)) if n != "root_yaw" else v
            for n, v in k.pose.items()
        }
        keys.append(_Key(k.move_s * tscale, k.hold_s * tscale, pose))
    return _Spec(spec.base, keys, spec.yaw_per_loop, spec.overlay, spec.params)


def _harmonic(u: np.ndarray, period_s: float, loop_s: float) -> np.ndarray:
    """sin(2πu/p) with p adjusted so that a whole number of periods fits in a loop (keeps loops seamless)."""
    n = max(1, round(loop_s / period_s))
    return np.sin(2 * np.pi * n * u / loop_s)


def _sym(**kw) -> dict:
    """Expand ``x_…`` into both ``l_…`` and ``r_…`` (same value: DOFs are defined mirror-symmetrically)."""
    out = {}
    for k, v in kw.items():
        if k.startswith("x_"):
            out["l_" + k[2:]] = v
            out["r_" + k[2:]] = v
        else:
            out[k] = v
    return out


# Reusable poses (left-handed performances; the seed mirrors them half of the time).
_ARMS_DOWN = _sym(x_shoulder_elev=-1.35, x_shoulder_twist=0.1, x_elbow_flex=0.25, x_shoulder_flex=0.1)
_STAND = {**_ARMS_DOWN, **_sym(x_knee_flex=0.06, x_hip_flex=0.03, x_ankle_flex=0.03)}
_GUARD_ARMS = {
    "l_shoulder_flex": 1.48,
    "l_shoulder_elev": -0.92,
    "l_shoulder_twist": -1.1,
    "l_elbow_flex": 1.86,
    "r_shoulder_flex": 1.40,
    "r_shoulder_elev": -1.15,
    "r_shoulder_twist": -1.06,
    "r_elbow_flex": 2.12,
}
# Fighting stance: left foot forward, right foot back, knees soft, feet flat (ankle = knee - hip flexion).
_STANCE_LEGS = {
    "l_hip_flex": 0.32,
    "l_knee_flex": 0.42,
    "l_ankle_flex": 0.10,
    "l_hip_rot": 0.1,
    "r_hip_flex": -0.18,
    "r_knee_flex": 0.22,
    "r_ankle_flex": 0.38,
    "r_hip_rot": -0.2,
    "spine_twist": -0.15,
    "neck_twist": 0.15,
    "root_yaw": 0.0,
}
_GUARD = {**_GUARD_ARMS, **_STANCE_LEGS}


def _karate_kick(rng) -> _Spec:
    front_chamber = {
        "r_hip_flex": 1.55,
        "r_knee_flex": 2.1,
        "r_ankle_flex": -0.5,
        "r_hip_rot": 0.0,
        "l_knee_flex": 0.35,
        "l_hip_flex": 0.1,
        "l_ankle_flex": 0.25,
        "spine_flex": -0.05,
    }
    front_kick = {
        **front_chamber,
        "r_hip_flex": 1.5,
        "r_knee_flex": 0.05,
        "r_ankle_flex": -0.7,
        "spine_flex": -0.22,
        "r_shoulder_flex": 1.0,
        "r_shoulder_elev": -1.3,
        "r_elbow_flex": 1.8,
    }
    # Roundhouse with the (front) left leg: pivot on the right foot, knee up and out, snap the shank.
    round_chamber = {
        "l_hip_flex": 1.2,
        "l_hip_abd": 0.7,
        "l_hip_rot": -0.4,
        "l_knee_flex": 2.1,
        "l_ankle_flex": -0.6,
        "r_hip_flex": 0.15,
        "r_knee_flex": 0.3,
        "r_ankle_flex": 0.15,
        "r_hip_rot": 0.0,
        "spine_lat": -0.35,
        "spine_twist": -0.3,
        "root_yaw": -0.7,
        "neck_twist": 0.6,
        "neck_flex": 0.1,
    }
    round_kick = {**round_chamber, "l_knee_flex": 0.15, "l_hip_flex": 1.1, "spine_lat": -0.5}
    keys = [
        _Key(0.45, 0.35, _GUARD),
        _Key(0.24, 0.02, {**_GUARD, **front_chamber}),
        _Key(0.20, 0.05, {**_GUARD, **front_kick}),
        _Key(0.18, 0.02, {**_GUARD, **front_chamber}),
        _Key(0.35, 0.40, _GUARD),
        _Key(0.30, 0.02, {**_GUARD, **round_chamber}),
        _Key(0.20, 0.05, {**_GUARD, **round_kick}),
        _Key(0.18, 0.02, {**_GUARD, **round_chamber}),
    ]
    return _Spec(_GUARD, keys)


def _boxing_combo(rng) -> _Spec:
    jab = {
        "l_shoulder_flex": 1.43,
        "l_shoulder_elev": 0.06,
        "l_shoulder_twist": 0.12,
        "l_elbow_flex": 0.1,
        "spine_twist": -0.35,
        "neck_twist": 0.3,
    }
    cross = {
        "r_shoulder_flex": 1.25,
        "r_shoulder_elev": 0.1,
        "r_shoulder_twist": 0.6,
        "r_elbow_flex": 0.12,
        "spine_twist": 0.5,
        "neck_twist": -0.35,
        "r_hip_rot": 0.3,
        "r_ankle_flex": 0.2,
        "root_yaw": 0.25,
    }
    hook = {
        "l_shoulder_flex": 0.7,
        "l_shoulder_elev": -0.18,
        "l_shoulder_twist": -0.13,
        "l_elbow_flex": 1.8,
        "spine_twist": -0.55,
        "neck_twist": 0.4,
        "l_hip_rot": -0.3,
        "root_yaw": -0.25,
    }
    hook_load = {
        "l_shoulder_flex": 0.3,
        "l_shoulder_elev": -0.3,
        "l_shoulder_twist": -0.4,
        "l_elbow_flex": 1.7,
        "spine_twist": 0.2,
    }
    uppercut_load = {
        "r_shoulder_flex": 0.9,
        "r_shoulder_elev": -1.3,
        "r_shoulder_twist": -0.6,
        "r_elbow_flex": 1.6,
        "spine_lat": -0.2,
        "l_knee_flex": 0.7,
        "r_knee_flex": 0.5,
        "l_ankle_flex": 0.38,
        "r_ankle_flex": 0.42,
    }
    uppercut = {
        "r_shoulder_flex": 1.48,
        "r_shoulder_elev": -0.61,
        "r_shoulder_twist": -1.43,
        "r_elbow_flex": 1.69,
        "spine_twist": 0.4,
        "spine_flex": -0.1,
        "neck_twist": -0.3,
    }
    keys = [
        _Key(0.35, 0.30, _GUARD),
        _Key(0.13, 0.03, {**_GUARD, **jab}),
        _Key(0.17, 0.05, _GUARD),
        _Key(0.15, 0.03, {**_GUARD, **cross}),
        _Key(0.20, 0.02, _GUARD),
        _Key(0.14, 0.00, {**_GUARD, **hook_load}),
        _Key(0.14, 0.03, {**_GUARD, **hook}),
        _Key(0.20, 0.02, _GUARD),
        _Key(0.18, 0.02, {**_GUARD, **uppercut_load}),
        _Key(0.15, 0.04, {**_GUARD, **uppercut}),
        _Key(0.30, 0.35, _GUARD),
    ]
    bounce_amp = rng.uniform(0.04, 0.08)

    def overlay(u, ch, loop_s):
        b = bounce_amp * (0.5 + 0.5 * _harmonic(u, 0.42, loop_s))  # knees and ankles together: feet stay flat
        for side in "lr":
            ch[f"{side}_knee_flex"] = ch[f"{side}_knee_flex"] + b
            ch[f"{side}_ankle_flex"] = ch[f"{side}_ankle_flex"] + b

    return _Spec(_GUARD, keys, overlay=overlay)


def _javelin_throw(rng) -> _Spec:
    carry = {
        **_STAND,
        "r_shoulder_flex": -0.24,
        "r_shoulder_elev": 0.38,
        "r_shoulder_twist": -1.5,
        "r_elbow_flex": 1.7,
        "l_shoulder_flex": 0.9,
        "l_shoulder_elev": -0.9,
        "l_elbow_flex": 1.2,
        "spine_twist": -0.2,
    }
    withdraw = {
        **carry,
        "r_shoulder_flex": -0.64,
        "r_shoulder_elev": 0.18,
        "r_shoulder_twist": 1.2,
        "r_elbow_flex": 0.0,
        "l_shoulder_flex": 1.32,
        "l_shoulder_elev": 0.07,
        "l_shoulder_twist": -0.06,
        "l_elbow_flex": 0.1,
        "spine_twist": -0.65,
        "spine_lat": -0.15,
        "spine_flex": -0.15,
        "neck_twist": 0.6,
        "root_yaw": -0.35,
        "r_knee_flex": 0.35,
        "r_hip_flex": 0.1,
        "r_ankle_flex": 0.25,
        "l_hip_flex": 0.25,
        "l_knee_flex": 0.1,
        "l_ankle_flex": -0.15,
    }
    plant = {
        **withdraw,
        "l_hip_flex": 0.55,
        "l_knee_flex": 0.12,
        "l_ankle_flex": -0.4,
        "r_hip_flex": -0.35,
        "r_knee_flex": 0.55,
        "r_ankle_flex": 0.45,
        "root_tz": 0.08,
        "spine_flex": -0.25,
    }
    release = {
        **plant,
        "r_shoulder_flex": 0.6,
        "r_shoulder_elev": 1.25,
        "r_shoulder_twist": 0.6,
        "r_elbow_flex": 0.15,
        "l_shoulder_flex": 0.4,
        "l_shoulder_elev": -1.2,
        "l_elbow_flex": 1.0,
        "spine_twist": 0.45,
        "spine_flex": 0.3,
        "spine_lat": 0.1,
        "neck_twist": 0.0,
        "root_yaw": 0.3,
        "root_tz": 0.12,
        "r_knee_flex": 0.3,
        "r_hip_flex": -0.2,
    }
    follow = {
        **release,
        "r_shoulder_flex": 1.9,
        "r_shoulder_elev": -0.5,
        "r_shoulder_twist": 0.3,
        "r_elbow_flex": 0.2,
        "spine_flex": 0.75,
        "spine_twist": 0.6,
        "r_hip_flex": 0.6,
        "r_knee_flex": 0.9,
        "r_ankle_flex": -0.3,
        "l_knee_flex": 0.3,
        "l_hip_flex": 0.7,
        "l_ankle_flex": -0.2,
        "root_tz": 0.18,
        "neck_flex": -0.3,
    }
    keys = [
        _Key(0.8, 0.45, carry),
        _Key(0.45, 0.05, withdraw),
        _Key(0.25, 0.00, plant),
        _Key(0.34, 0.00, release),
        _Key(0.22, 0.25, follow),
        _Key(0.8, 0.10, {**carry, "root_tz": 0.06}),
    ]
    return _Spec(_STAND, keys)


def _dance_spin(rng) -> _Spec:
    open_arms = _sym(x_shoulder_elev=-0.25, x_shoulder_flex=0.45, x_elbow_flex=0.35, x_shoulder_twist=0.2)
    round_arms = _sym(x_shoulder_flex=1.13, x_shoulder_elev=-0.65, x_shoulder_twist=-0.1, x_elbow_flex=1.37)
    plie = {
        **open_arms,
        **_sym(x_hip_abd=0.25, x_hip_rot=-0.35, x_knee_flex=0.7, x_hip_flex=0.45, x_ankle_flex=0.28),
        "spine_flex": 0.05,
    }
    passe = {
        **round_arms,
        "r_hip_flex": 1.0,
        "r_hip_abd": 0.55,
        "r_hip_rot": -0.55,
        "r_knee_flex": 1.9,
        "r_ankle_flex": -0.6,
        "l_knee_flex": 0.0,
        "l_hip_flex": 0.0,
        "l_ankle_flex": -0.75,
        "l_hip_rot": -0.2,
        "neck_twist": 0.0,
    }
    turns = 1 if rng.uniform() < 0.7 else 2
    spin_yaw = 2 * np.pi * turns
    arms_up = {
        **_STAND,
        **_sym(x_shoulder_elev=1.25, x_shoulder_flex=0.5, x_elbow_flex=0.3),
        "spine_flex": -0.15,
        "neck_flex": -0.2,
    }
    sway_l = {
        **arms_up,
        "spine_lat": 0.35,
        "l_hip_abd": 0.2,
        "r_hip_abd": -0.1,
        "root_tx": 0.08,
        "l_shoulder_elev": 0.9,
        "r_shoulder_elev": 1.4,
    }
    sway_r = {
        **arms_up,
        "spine_lat": -0.35,
        "r_hip_abd": 0.2,
        "l_hip_abd": -0.1,
        "root_tx": -0.08,
        "r_shoulder_elev": 0.9,
        "l_shoulder_elev": 1.4,
    }
    keys = [
        _Key(0.55, 0.25, {**plie, "root_yaw": 0.0}),
        _Key(0.22, 0.00, {**passe, "root_yaw": 0.45}),
        _Key(0.50 * turns + 0.1, 0.00, {**passe, "root_yaw": spin_yaw - 0.2}),
        _Key(0.25, 0.10, {**arms_up, "root_yaw": spin_yaw}),
        _Key(0.30, 0.02, {**sway_l, "root_yaw": spin_yaw}),
        _Key(0.30, 0.02, {**sway_r, "root_yaw": spin_yaw}),
        _Key(0.30, 0.02, {**sway_l, "root_yaw": spin_yaw}),
        _Key(0.35, 0.00, {**arms_up, "root_yaw": spin_yaw}),
    ]
    return _Spec(_STAND, keys, yaw_per_loop=spin_yaw)


def _fast_wave(rng) -> _Spec:
    # "Hello" wave: upper arm out and up, forearm vertical; waving = elbow flexion in the frontal plane.
    raised = {
        **_STAND,
        "r_shoulder_flex": 0.16,
        "r_shoulder_elev": 0.35,
        "r_shoulder_twist": -1.41,
        "r_elbow_flex": 1.06,
        "wave_r": 1.0,
        "neck_twist": -0.25,
    }
    both = {
        **_STAND,
        **_sym(x_shoulder_flex=0.25, x_shoulder_elev=1.05, x_shoulder_twist=-0.3, x_elbow_flex=0.35),
        "wave_r": 0.0,
        "wave_both": 1.0,
        "neck_flex": -0.25,
    }
    keys = [
        _Key(0.5, 0.3, {**_STAND, "wave_r": 0.0}),
        _Key(0.3, 1.3, raised),
        _Key(0.3, 0.3, {**_STAND, "wave_r": 0.0}),
        _Key(0.35, 1.2, both),
        _Key(0.35, 0.2, _STAND),
    ]
    freq_hz = rng.uniform(3.0, 4.0)
    elbow_amp = rng.uniform(0.4, 0.55)

    def overlay(u, ch, loop_s):
        s = np.sin(2 * np.pi * freq_hz * u)  # the envelopes are zero at the loop seams, so no period matching
        ch["r_elbow_flex"] = ch["r_elbow_flex"] + elbow_amp * ch["wave_r"] * s
        ch["r_shoulder_twist"] = ch["r_shoulder_twist"] - 0.1 * ch["wave_r"] * s
        for side, sign in (("l", 1.0), ("r", -1.0)):
            ch[f"{side}_shoulder_flex"] = ch[f"{side}_shoulder_flex"] + 0.35 * ch["wave_both"] * s * sign
            ch[f"{side}_elbow_flex"] = ch[f"{side}_elbow_flex"] + 0.3 * ch["wave_both"] * (0.5 + 0.5 * s)
        ch["spine_lat"] = ch.get("spine_lat", 0.0) + 0.06 * ch["wave_both"] * s

    return _Spec({**_STAND, "wave_r": 0.0, "wave_both": 0.0}, keys, overlay=overlay)


def _periodic_spec(period_s: float, overlay) -> _Spec:
    """A motion made only of an overlay on the standing pose, looping every ``period_s``."""
    return _Spec(_STAND, [_Key(period_s, 0.0, _STAND)], overlay=overlay)


def _jumping_jack(rng) -> _Spec:
    period = rng.uniform(0.8, 1.0)
    arm_top = rng.uniform(1.15, 1.35)
    leg_open = rng.uniform(0.28, 0.36)
    height = rng.uniform(0.05, 0.08)

    def overlay(u, ch, loop_s):
        phi = 2 * np.pi * u / period
        a = 0.5 - 0.5 * np.cos(phi)  # 0 closed, 1 open
        for side in "lr":
            ch[f"{side}_shoulder_elev"] = -1.38 + (arm_top + 1.38) * a
            ch[f"{side}_shoulder_flex"] = 0.15 + 0.1 * a
            ch[f"{side}_elbow_flex"] = 0.2 + 0.15 * np.sin(phi) ** 2
            ch[f"{side}_hip_abd"] = 0.03 + leg_open * a
            ch[f"{side}_hip_rot"] = -0.2 * a
            # Knees and ankles dip at the landings (closed and open), straighten in the air.
            land = np.cos(phi) ** 2
            ch[f"{side}_knee_flex"] = 0.08 + 0.3 * land
            ch[f"{side}_hip_flex"] = 0.05 + 0.15 * land
            ch[f"{side}_ankle_flex"] = 0.03 + 0.15 * land - 0.5 * np.sin(phi) ** 4  # toes point in the air
        ch["jump"] = height * np.sin(phi) ** 4  # airborne around the switches (|sin φ| = 1)

    return _periodic_spec(period, overlay)


def _high_knees(rng) -> _Spec:
    period = rng.uniform(0.45, 0.55)  # one stride of each leg
    knee_top = rng.uniform(1.3, 1.6)
    height = rng.uniform(0.03, 0.05)
    fwd = {"shoulder_flex": 1.41, "shoulder_elev": -0.84, "shoulder_twist": -1.23, "elbow_flex": 1.64}
    back = {"shoulder_flex": -0.8, "shoulder_elev": -0.95, "shoulder_twist": 0.9, "elbow_flex": 1.3}

    def overlay(u, ch, loop_s):
        phi = 2 * np.pi * u / period
        for side, shift in (("l", 0.0), ("r", np.pi)):
            lift = (0.5 - 0.5 * np.cos(phi + shift)) ** 2  # 1 with the knee up, flat near 0 on the floor
            ch[f"{side}_hip_flex"] = 0.05 + knee_top * lift
            ch[f"{side}_knee_flex"] = 0.1 + 1.9 * lift
            ch[f"{side}_ankle_flex"] = 0.05 - 0.5 * lift
            # Arms pump opposite to the legs: the left arm is forward while the right knee is up.
            s = 0.5 - 0.5 * np.cos(phi + shift)
            other = "r" if side == "l" else "l"
            for k, front in fwd.items():
                ch[f"{other}_{k}"] = back[k] + (front - back[k]) * s
        ch["spine_flex"] = np.full_like(u, 0.12)
        ch["spine_twist"] = 0.12 * np.sin(phi)
        ch["jump"] = height * (0.5 - 0.5 * np.cos(2 * phi)) ** 3  # a short flight between strides

    return _periodic_spec(period, overlay)


def _ninja_strike(rng) -> _Spec:
    low = {
        **_GUARD,
        **_sym(x_knee_flex=1.1, x_hip_flex=0.75, x_ankle_flex=0.35, x_hip_abd=0.25, x_hip_rot=-0.15),
        "l_hip_flex": 0.95,
        "l_ankle_flex": 0.15,
        "spine_flex": 0.3,
        "neck_flex": -0.25,
    }
    chop_up = {
        **low,
        "r_shoulder_flex": 0.21,
        "r_shoulder_elev": 1.3,
        "r_shoulder_twist": -1.5,
        "r_elbow_flex": 0.68,
        "spine_flex": 0.05,
        "spine_twist": -0.3,
        "l_knee_flex": 0.8,
        "r_knee_flex": 0.8,
    }
    chop_down = {
        **low,
        "r_shoulder_flex": 1.87,
        "r_shoulder_elev": -0.22,
        "r_shoulder_twist": 0.74,
        "r_elbow_flex": 0.09,
        "spine_flex": 0.55,
        "spine_twist": 0.4,
        "neck_flex": -0.45,
    }
    # Turning back-fist with the left arm: the root turns half-way and the forearm whips out sideways.
    turn_load = {
        **low,
        "l_shoulder_flex": 1.9,
        "l_shoulder_elev": -0.2,
        "l_elbow_flex": 2.2,
        "l_shoulder_twist": 0.2,
        "root_yaw": 0.6,
        "spine_twist": 0.5,
        "neck_twist": -0.8,
    }
    backfist = {
        **low,
        "l_shoulder_flex": 0.5,
        "l_shoulder_elev": 0.1,
        "l_elbow_flex": 0.1,
        "l_shoulder_twist": 0.0,
        "root_yaw": -0.9,
        "spine_twist": -0.5,
        "neck_twist": 0.7,
        "spine_lat": -0.2,
    }
    keys = [
        _Key(0.5, 0.35, low),
        _Key(0.30, 0.05, chop_up),
        _Key(0.32, 0.10, chop_down),
        _Key(0.30, 0.10, low),
        _Key(0.25, 0.02, turn_load),
        _Key(0.28, 0.12, backfist),
        _Key(0.45, 0.10, low),
    ]
    return _Spec(_GUARD, keys)


def _stand(rng) -> _Spec:
    return _Spec(base=dict(_STAND), keys=[_Key(1.0, 0.0, {})])


_BUILDERS: dict[str, Callable[[np.random.Generator], _Spec]] = {
    "stand": _stand,
    "karate_kick": _karate_kick,
    "boxing_combo": _boxing_combo,
    "javelin_throw": _javelin_throw,
    "dance_spin": _dance_spin,
    "fast_wave": _fast_wave,
    "jumping_jack": _jumping_jack,
    "high_knees": _high_knees,
    "ninja_strike": _ninja_strike,
}
assert set(_BUILDERS) == set(MOTIONS) | set(STATIC_MOTIONS)


# --------------------------------------------------------------------------------------------------------
# Sampling


def _check_name(name: str) -> None:
    if name not in _BUILDERS:
        raise ValueError(f"unknown motion {name!r}; available: {', '.join(sorted(_BUILDERS))}")


def _check_times(t_s) -> np.ndarray:
    t = np.asarray(t_s, dtype=np.float64)
    if t.ndim != 1:
        raise ValueError(f"t_s: expected a 1-D array of times in seconds, got shape {t.shape}")
    if not np.all(np.isfinite(t)):
        raise ValueError("t_s: times must be finite")
    return t


def _check_scales(speed: float, amplitude: float) -> None:
    if not (np.isfinite(speed) and speed > 0):
        raise ValueError(f"speed: expected a positive tempo factor, got {speed!r}")
    if not (np.isfinite(amplitude) and amplitude >= 0):
        raise ValueError(f"amplitude: expected a non-negative excursion factor, got {amplitude!r}")


def _performance(name: str, seed: int, salt: int = 0) -> tuple[_Spec, bool]:
    """The seeded variant of a motion: its varied key loop and whether it is mirrored."""
    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, zlib.crc32(name.encode()), int(salt)])
    spec = _vary(_BUILDERS[name](rng), rng)
    return spec, bool(rng.uniform() < 0.5)


def _soft_clamp(x: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Smoothly saturate x into (lo, hi) shrunk by _BOUND_MARGIN; identity (to ~1e-6) 0.1 rad away from them."""
    k = 1.0 / _BOUND_SHARPNESS
    lo2, hi2 = lo + _BOUND_MARGIN, hi - _BOUND_MARGIN
    y = lo2 + np.logaddexp(0.0, k * (x - lo2)) / k
    return hi2 - np.logaddexp(0.0, k * (hi2 - y)) / k


def _raw_poses(spec: _Spec, mirrored: bool, u: np.ndarray, amplitude: float) -> tuple[np.ndarray, np.ndarray]:
    """Poses (T, 33) with root height 0 and the jump height (T,) of a performance at times u (speed 1)."""
    ch = _eval_loop(spec, u)
    if spec.overlay is not None:
        spec.overlay(u, ch, _loop_period(spec))
    scale_yaw = spec.yaw_per_loop == 0.0

    def channel(n: str) -> np.ndarray:
        b = spec.base.get(n, 0.0)
        v = np.broadcast_to(ch.get(n, b), u.shape)
        if n == "root_yaw" and not scale_yaw:
            return v
        return b + amplitude * (v - b)

    S = np.zeros((u.shape[0], NUM_POSE_PARAMS))
    for i, n in enumerate(DOF_NAMES):
        S[:, i] = channel(n)
    for n, col in zip(_ROOT_CHANNELS, (27, 28, 29, 30, 32)):
        S[:, col] = channel(n)
    S[:, :27] = _soft_clamp(S[:, :27], THETA_LOWER, THETA_UPPER)
    jump = np.maximum(channel("jump"), 0.0) if "jump" in ch else np.zeros(u.shape)
    if mirrored:
        S = mirror_pose(S)
    return S, jump


def _body(template: Template | None):
    if template is None:
        rest = DEFAULT_REST_JOINTS
        lj, lo = default_landmarks(rest)
        return rest, lj, lo
    if not isinstance(template, Template):
        raise TypeError(f"template: expected a Template or None, got {type(template).__name__}")
    return template.rest_joints, template.landmark_joint, template.landmark_offset


def _soft_min(y: np.ndarray) -> np.ndarray:
    tau = _FLOOR_SOFTMIN_M
    m = y.min(axis=-1, keepdims=True)
    return m[..., 0] - tau * np.log(np.sum(np.exp(-(y - m) / tau), axis=-1))


def _place_on_floor(S: np.ndarray, jump: np.ndarray, template: Template | None) -> np.ndarray:
    """Set the root height so that the soles touch y=0 (as in the rest pose), plus the jump height."""
    rest, lj, lo = _body(template)
    sole = [LANDMARK_INDEX[n] for n in _SOLE_LANDMARKS]
    S = S.copy()
    S[:, 31] = 0.0
    heights = kinematics.landmark_positions(S, rest, lj[sole], lo[sole])[..., 1]
    rest_heights = (rest[lj[sole]] + lo[sole])[:, 1]
    # soft-min <= min: the lowest sole never sinks below its rest height, and floats at most τ·log(6) above.
    S[:, 31] = rest_heights.min() - _soft_min(heights) + jump
    return S


def motion_poses(
    name: str, t_s, seed: int = 0, speed: float = 1.0, amplitude: float = 1.0, template: Template | None = None
) -> np.ndarray:
    """Sample a simulated motion: poses S (T, 33) (skeleton layout) at times t_s (T,) seconds.

    ``seed`` picks the performance (timing, excursions, details, side), ``speed`` scales the tempo,
    ``amplitude`` the excursions from the motion's base pose. ``template`` (default: the default skeleton)
    sets the sole points used to keep the feet on the floor. Smooth (C2) in t, joint angles within bounds.
    """
    _check_name(name)
    t = _check_times(t_s)
    _check_scales(speed, amplitude)
    spec, mirrored = _performance(name, seed)
    S, jump = _raw_poses(spec, mirrored, speed * t, amplitude)
    return _place_on_floor(S, jump, template)


def loop_duration_s(name: str, seed: int = 0, speed: float = 1.0) -> float:
    """Duration in seconds of one loop of a motion's performance (it repeats after that, spins accumulate)."""
    _check_name(name)
    _check_scales(speed, 1.0)
    spec, _ = _performance(name, seed)
    return _loop_period(spec) / speed


def sequence_poses(
    segments,
    t_s,
    seed: int = 0,
    speed: float = 1.0,
    amplitude: float = 1.0,
    template: Template | None = None,
    blend_s: float = 0.4,
) -> np.ndarray:
    """Chain motions: ``segments`` = [(name, duration_s), ...] played back to back; poses S (T, 33) at t_s.

    Consecutive motions cross-fade over ``blend_s`` seconds centred on their boundary (shorter if a segment
    is short) with a minimum-jerk weight, so the result stays C2. Each segment is its own performance
    (seeded from ``seed`` and its position); root yaw is unwrapped across boundaries (no extra turns).
    Times before 0 / after the end continue the first / last motion.
    """
    segs = list(segments)
    if not segs:
        raise ValueError("segments: expected at least one (name, duration_s) pair, got none")
    for i, seg in enumerate(segs):
        if not (isinstance(seg, (tuple, list)) and len(seg) == 2):
            raise ValueError(f"segments[{i}]: expected a (name, duration_s) pair, got {seg!r}")
        _check_name(seg[0])
        if not (np.isfinite(seg[1]) and seg[1] > 0):
            raise ValueError(f"segments[{i}]: duration must be positive seconds, got {seg[1]!r}")
    if not (np.isfinite(blend_s) and blend_s > 0):
        raise ValueError(f"blend_s: expected a positive duration in seconds, got {blend_s!r}")
    t = _check_times(t_s)
    _check_scales(speed, amplitude)

    durations = np.array([float(d) for _, d in segs])
    starts = np.concatenate([[0.0], np.cumsum(durations)[:-1]])
    perf = [_performance(name, seed, salt=i + 1) for i, (name, _) in enumerate(segs)]
    n = len(segs)
    # Half-widths of the blend windows at each inner boundary.
    half = [min(blend_s / 2, durations[i - 1] / 3, durations[i] / 3) for i in range(1, n)]

    def rising(i: int, tt: np.ndarray) -> np.ndarray:
        """Weight ramp 0 -> 1 of segment i across its starting boundary (i >= 1)."""
        b, h = starts[i], half[i - 1]
        return _minjerk((tt - (b - h)) / (2 * h))

    # Root-yaw offsets (multiples of 2π) that keep each segment's facing close to its predecessor's.
    yaw_offset = np.zeros(n)
    for i in range(1, n):
        b = np.array([starts[i]])
        prev = _raw_poses(perf[i - 1][0], perf[i - 1][1], speed * (b - starts[i - 1]), amplitude)[0][0, 27]
        cur = _raw_poses(perf[i][0], perf[i][1], speed * (b - starts[i]), amplitude)[0][0, 27]
        yaw_offset[i] = 2 * np.pi * np.round((prev + yaw_offset[i - 1] - cur) / (2 * np.pi))

    S = np.zeros((t.shape[0], NUM_POSE_PARAMS))
    jump = np.zeros(t.shape[0])
    for i in range(n):
        w = np.ones_like(t)
        if i > 0:
            w = w * rising(i, t)
        if i < n - 1:
            w = w * (1.0 - rising(i + 1, t))
        m = w > 0
        if not np.any(m):
            continue
        Si, ji = _raw_poses(perf[i][0], perf[i][1], speed * (t[m] - starts[i]), amplitude)
        Si[:, 27] += yaw_offset[i]
        S[m] += w[m, None] * Si
        jump[m] += w[m] * ji
    return _place_on_floor(S, jump, template)


def peak_speeds(
    name: str,
    seed: int = 0,
    speed: float = 1.0,
    amplitude: float = 1.0,
    duration_s: float = 8.0,
    rate_hz: float = 1000.0,
    points=("l_wrist", "r_wrist", "l_ankle", "r_ankle"),
) -> dict[str, float]:
    """Peak speed in m/s of some landmarks over ``duration_s`` of a motion (finite differences at rate_hz)."""
    t = np.arange(0.0, duration_s, 1.0 / rate_hz)
    S = motion_poses(name, t, seed=seed, speed=speed, amplitude=amplitude)
    L = kinematics.landmark_positions(S, DEFAULT_REST_JOINTS)
    idx = [LANDMARK_INDEX[p] for p in points]
    v = np.linalg.norm(np.diff(L[:, idx], axis=0), axis=-1) * rate_hz
    return {p: float(v[:, k].max()) for k, p in enumerate(points)}
