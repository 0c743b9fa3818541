"""Tests of the simulated motions (eventcap.body.motions): bounds, smoothness, seeds, tempo, floor contact."""

from __future__ import annotations

import numpy as np
import pytest

from eventcap.body import kinematics as K
from eventcap.body import motions as M
from eventcap.body import skeleton as sk
from eventcap.body.template import Template

REST = sk.DEFAULT_REST_JOINTS
SOLES = [sk.LANDMARK_INDEX[n] for n in ("l_big_toe", "l_small_toe", "l_heel", "r_big_toe", "r_small_toe", "r_heel")]
NAMES = sorted(M.MOTIONS)


def sole_min_height(S: np.ndarray, body=REST) -> np.ndarray:
    """Lowest sole landmark's height above its rest-pose height (the rest pose stands on the floor), (T,) m."""
    rest = K.landmark_positions(np.zeros(33), body)[SOLES, 1].min()
    return K.landmark_positions(S, body)[:, SOLES, 1].min(axis=1) - rest


def c2_ratio(S: np.ndarray) -> float:
    """max |Δ acceleration| at dt / the same at 10·dt, from samples at dt. ≈0.1 if C2, ≈1 if acceleration jumps."""
    a_fine = np.diff(S, 2, axis=0)  # ∝ acceleration · dt²
    coarse = S[::10]
    a_coarse = np.diff(coarse, 2, axis=0) / 100.0  # same scale as a_fine
    return float(np.abs(np.diff(a_fine, axis=0)).max() / np.abs(np.diff(a_coarse, axis=0)).max())


def test_catalogue():
    required = {"karate_kick", "boxing_combo", "javelin_throw", "dance_spin", "fast_wave", "jumping_jack"}
    assert required <= set(M.MOTIONS) and len(M.MOTIONS) >= 6
    assert all(isinstance(d, str) and len(d) > 20 for d in M.MOTIONS.values())


@pytest.mark.parametrize("name", NAMES)
def test_within_bounds_for_seeds_speeds_amplitudes(name):
    t = np.arange(-1.0, 7.0, 0.002)
    for seed in (0, 1, 7):
        for speed, amplitude in ((1.0, 1.0), (0.5, 1.5), (2.0, 0.5), (1.5, 1.2)):
            S = M.motion_poses(name, t, seed=seed, speed=speed, amplitude=amplitude)
            assert S.shape == (t.size, 33) and np.all(np.isfinite(S))
            assert np.all(S[:, :27] >= sk.THETA_LOWER) and np.all(S[:, :27] <= sk.THETA_UPPER), (seed, speed)
            assert np.abs(S[:, [30, 32]]).max() < 0.4  # stays near the origin


@pytest.mark.parametrize("name", NAMES)
def test_smooth_c2(name):
    dt = 1e-4
    t = np.arange(0.0, M.loop_duration_s(name, seed=2) + 0.5, dt)  # a whole loop plus its seam
    S = M.motion_poses(name, t, seed=2)
    assert np.abs(np.diff(S, axis=0)).max() / dt < 60.0  # rad/s or m/s: no jumps
    assert c2_ratio(S) < 0.2


@pytest.mark.parametrize("name", NAMES)
def test_fast_limbs_and_floor_contact(name):
    peaks = M.peak_speeds(name, duration_s=M.loop_duration_s(name) + 0.1)
    assert 3.0 < max(peaks.values()) < 15.0, peaks
    t = np.arange(0.0, 6.0, 0.005)
    S = M.motion_poses(name, t, seed=0)
    h = sole_min_height(S)
    assert h.min() > -1e-9  # never below the floor
    if name in ("jumping_jack", "high_knees"):
        assert h.max() > 0.025  # airborne
        assert np.quantile(h, 0.2) < 0.0025  # and landing
    else:
        assert h.max() < 0.0025  # a sole touches the floor (soft contact floats ≤ 2 mm)


def test_speed_scales_tempo_and_determinism():
    t = np.linspace(0.0, 3.0, 301)
    a = M.motion_poses("boxing_combo", t, seed=4, speed=2.0)
    b = M.motion_poses("boxing_combo", 2.0 * t, seed=4, speed=1.0)
    assert np.allclose(a, b, atol=1e-12)
    assert np.array_equal(a, M.motion_poses("boxing_combo", t, seed=4, speed=2.0))
    assert np.abs(a - M.motion_poses("boxing_combo", t, seed=5, speed=2.0)).max() > 0.05


def test_seed_varies_the_side():
    t = np.linspace(0.0, 3.5, 700)
    kicking_leg = set()
    for seed in range(10):
        S = M.motion_poses("karate_kick", t, seed=seed)
        # The front kick extends one knee fully while that hip is flexed high.
        hi_l = S[:, sk.DOF_INDEX["l_hip_flex"]].max()
        hi_r = S[:, sk.DOF_INDEX["r_hip_flex"]].max()
        kicking_leg.add("l" if hi_l > hi_r else "r")
    assert kicking_leg == {"l", "r"}


def test_amplitude_scales_excursions():
    t = np.linspace(0.0, 3.0, 600)
    ranges = []
    for amplitude in (0.0, 0.5, 1.0):
        S = M.motion_poses("jumping_jack", t, seed=0, amplitude=amplitude)
        ranges.append(np.ptp(S[:, sk.DOF_INDEX["l_shoulder_elev"]]))
    assert ranges[0] < 1e-9 and ranges[1] == pytest.approx(0.5 * ranges[2], rel=0.02)
    still = M.motion_poses("karate_kick", t, amplitude=0.0)
    assert np.ptp(still[:, :27], axis=0).max() < 1e-9


def test_dance_spin_turns_whole_turns():
    spec_s = M.loop_duration_s("dance_spin", seed=0)
    S = M.motion_poses("dance_spin", np.array([0.0, spec_s, 2 * spec_s]), seed=0)
    turns = (S[1:, 27] - S[:-1, 27]) / (2 * np.pi)
    assert np.allclose(turns, np.round(turns)) and np.all(np.abs(turns) >= 1)


def test_template_feet_on_floor():
    # A template with a longer skeleton and its own sole landmarks: its soles, not the default ones, touch y=0.
    rest = REST * 1.1
    lj, lo = sk.default_landmarks(rest)
    tpl = Template("tall", rest, rest + 0.01, np.array([[0, 1, 2]]), np.eye(24), np.zeros(24), lj, lo)
    t = np.linspace(0.0, 3.0, 300)
    S = M.motion_poses("boxing_combo", t, template=tpl)
    h = sole_min_height(S, tpl)
    assert h.min() > -1e-9 and h.max() < 0.0025
    assert np.abs(sole_min_height(S)).max() > 0.005  # the default skeleton's soles would not fit


def test_sequence_is_continuous_deterministic_and_unwraps_yaw():
    segs = [("boxing_combo", 2.0), ("dance_spin", 3.0), ("jumping_jack", 1.5), ("karate_kick", 2.5)]
    dt = 1e-4
    t = np.arange(1.6, 7.0, dt)  # covers the three transitions (at 2, 5 and 6.5 s)
    S = M.sequence_poses(segs, t, seed=3)
    assert np.all(S[:, :27] >= sk.THETA_LOWER) and np.all(S[:, :27] <= sk.THETA_UPPER)
    assert np.abs(np.diff(S, axis=0)).max() / dt < 60.0
    assert c2_ratio(S) < 0.2
    assert np.array_equal(S, M.sequence_poses(segs, t, seed=3))
    # Facing: the only turns are the dance spin's own (whole turns), none added at the boundaries.
    tt = np.array([1.0, 4.99, 5.5, 6.4, 8.5])
    Y = M.sequence_poses(segs, tt, seed=3)[:, 27] / (2 * np.pi)
    assert abs(Y[0]) < 0.1 and abs(Y[1] - np.round(Y[1])) < 0.1 and abs(Y[1]) >= 0.9
    assert np.allclose(np.round(Y[2:]), np.round(Y[1])) and np.abs(Y[2:] - Y[1]).max() < 0.2
    # Within a segment, away from transitions, the sequence plays that motion's performance.
    h = sole_min_height(M.sequence_poses(segs, np.linspace(0, 9, 400), seed=3))
    assert h.min() > -1e-9


def test_single_segment_sequence_runs_past_the_end():
    t = np.linspace(-1.0, 4.0, 200)
    S = M.sequence_poses([("fast_wave", 2.0)], t, seed=1)
    assert S.shape == (200, 33) and np.all(np.isfinite(S))


def test_errors():
    t = np.linspace(0, 1, 10)
    with pytest.raises(ValueError, match="unknown motion 'moonwalk'; available: boxing_combo, dance_spin"):
        M.motion_poses("moonwalk", t)
    with pytest.raises(ValueError, match=r"t_s: expected a 1-D array .* got shape \(2, 5\)"):
        M.motion_poses("fast_wave", t.reshape(2, 5))
    with pytest.raises(ValueError, match="speed: expected a positive tempo factor, got 0"):
        M.motion_poses("fast_wave", t, speed=0)
    with pytest.raises(ValueError, match="amplitude: expected a non-negative"):
        M.motion_poses("fast_wave", t, amplitude=-1)
    with pytest.raises(ValueError, match="at least one"):
        M.sequence_poses([], t)
    with pytest.raises(ValueError, match=r"segments\[1\]: duration must be positive seconds, got -2"):
        M.sequence_poses([("fast_wave", 1.0), ("dance_spin", -2)], t)
    with pytest.raises(ValueError, match=r"segments\[0\]: expected a \(name, duration_s\) pair"):
        M.sequence_poses(["fast_wave"], t)
