"""The event-silence term (eventcap.energy.silence): which pose parameters the events call still, the background
rate, the window's quadratic form, and the errors."""

from __future__ import annotations

import numpy as np
import pytest

from eventcap.body.skeleton import JOINT_INDEX, NUM_JOINTS
from eventcap.energy.silence import measure_silence
from eventcap.events import EVENT_DTYPE

H, W = 180, 240
EDGES = np.arange(0, 50_001, 10_000, dtype=np.int64)  # 5 bins of 10 ms
#: the measurement's settings (the spline stage's config states their defaults; these are the values tested)
SETTINGS = {"radius_px": 6, "rate_hz": 2.0, "hold_bins": 0, "sweep_bins": 0}


def skeleton_px() -> np.ndarray:
    """(24, 2) a front-facing stick figure in the image: pelvis at (120, 100), arms out to the sides."""
    pts = {"pelvis": (120, 100), "l_hip": (128, 104), "r_hip": (112, 104), "spine1": (120, 92),
           "l_knee": (130, 130), "r_knee": (110, 130), "spine2": (120, 82), "l_ankle": (131, 158),
           "r_ankle": (109, 158), "spine3": (120, 72), "l_foot": (133, 165), "r_foot": (107, 165),
           "neck": (120, 62), "l_collar": (126, 64), "r_collar": (114, 64), "head": (120, 50),
           "l_shoulder": (134, 65), "r_shoulder": (106, 65), "l_elbow": (156, 66), "r_elbow": (84, 66),
           "l_wrist": (176, 67), "r_wrist": (64, 67), "l_hand": (184, 67), "r_hand": (56, 67)}
    return np.array([pts[n] for n in sorted(pts, key=JOINT_INDEX.get)], dtype=np.float64)


def events_of(t, x, y) -> np.ndarray:
    ev = np.zeros(len(t), dtype=EVENT_DTYPE)
    ev["t"], ev["x"], ev["y"], ev["p"] = t, x, y, 1
    order = np.argsort(ev["t"], kind="stable")
    return ev[order]


def noise(rate_hz: float, seed: int = 0) -> np.ndarray:
    """Background activity: every pixel a Poisson process of rate_hz over the 50 ms."""
    rng = np.random.default_rng(seed)
    n = rng.poisson(rate_hz * H * W * 0.05)
    return events_of(rng.integers(0, 50_000, n), rng.integers(0, W, n), rng.integers(0, H, n))


def edge_sweep(a, b, t0_us: int, t1_us: int, per_px: int = 3) -> np.ndarray:
    """Events of an edge along the segment a -> b (pixels) seen every 1 ms between t0 and t1 (a moving limb)."""
    s = np.linspace(0, 1, int(np.hypot(*(np.subtract(b, a)))) + 1)
    pts = np.rint(np.asarray(a) + s[:, None] * np.subtract(b, a)).astype(int)
    ts = np.arange(t0_us, t1_us, 1000)
    t = np.repeat(ts, len(pts) * per_px)
    xy = np.tile(np.repeat(pts, per_px, axis=0), (len(ts), 1))
    return events_of(t, xy[:, 0], xy[:, 1])


def test_a_moving_forearm_leaves_the_legs_and_the_other_arm_still():
    J = np.broadcast_to(skeleton_px(), (5, NUM_JOINTS, 2))
    # the right forearm moves during bins 1-2 (10-30 ms); background activity 0.5 Hz everywhere
    ev = np.concatenate([noise(0.5), edge_sweep(J[0, JOINT_INDEX["r_elbow"]], J[0, JOINT_INDEX["r_wrist"]],
                                                10_000, 30_000)])
    ev = ev[np.argsort(ev["t"], kind="stable")]
    sil = measure_silence(ev, EDGES, J, H, W, **SETTINGS)
    assert sil.stillness.shape == sil.activity_hz.shape == (5, NUM_JOINTS)
    assert sil.background_hz == pytest.approx(0.5, rel=0.15)
    s = sil.stillness
    wrist = JOINT_INDEX["r_wrist"]  # the end of the moving bone
    rest = [JOINT_INDEX[n] for n in ("pelvis", "l_knee", "r_ankle", "l_wrist", "head", "spine3")]
    # while it moves: the forearm is not still, the rest is; the elbow (the end of the silent upper arm) is in
    # between: the boxes near it overlap the forearm's first pixels
    assert s[1:3, wrist].max() < 0.01, s[1:3, wrist]
    assert s[1:3][:, rest].min() > 0.9, s[1:3][:, rest]
    assert 0.1 < s[1:3, JOINT_INDEX["r_elbow"]].min() < 0.9
    # before and after: all still (noise only)
    assert s[[0, 3, 4]].min() > 0.5 and np.median(s[[0, 3, 4]]) > 0.9
    # the forearm's activity: 3 events per px of its length every 1 ms, in 13 px boxes -> ~ 3 * 13 / 169 / 1 ms
    assert 100 < sil.activity_hz[1, wrist] < 400
    # holding: still only as much as in the least still bin within ± 1 bin; the bins next to the motion lose it
    held = measure_silence(ev, EDGES, J, H, W, **{**SETTINGS, "hold_bins": 1}).stillness
    assert held[[0, 1, 2, 3], wrist].max() < 0.01 and held[4, wrist] == s[4, wrist] > 0.5
    np.testing.assert_array_equal(held, np.array([s[max(k - 1, 0):k + 2].min(axis=0) for k in range(5)]))


def test_background_rate_is_subtracted_and_a_bone_out_of_view_counts_as_moving():
    J = np.broadcast_to(skeleton_px(), (5, NUM_JOINTS, 2)).copy()
    busy = measure_silence(noise(20.0, seed=1), EDGES, J, H, W, **SETTINGS)  # flicker: 20 events/px/s everywhere
    assert busy.background_hz == pytest.approx(20.0, rel=0.05)
    assert np.median(busy.stillness) > 0.3  # the background is not motion
    J[:, JOINT_INDEX["l_hand"]] = np.nan  # behind the camera
    sil = measure_silence(noise(0.2), EDGES, J, H, W, **SETTINGS)
    hand = JOINT_INDEX["l_hand"]
    assert np.isinf(sil.activity_hz[:, hand]).all() and np.all(sil.stillness[:, hand] == 0.0)
    assert sil.stillness[:, JOINT_INDEX["r_hand"]].min() > 0.5


def test_the_pelvis_is_as_active_as_the_most_active_of_its_bones():
    J = np.broadcast_to(skeleton_px(), (5, NUM_JOINTS, 2))
    hip = JOINT_INDEX["r_hip"]
    ev = edge_sweep(J[0, 0], J[0, hip], 0, 50_000)  # the short bone pelvis -> right hip moves
    sil = measure_silence(ev, EDGES, J, H, W, **SETTINGS)
    assert np.all(sil.activity_hz[:, 0] == sil.activity_hz[:, [JOINT_INDEX[n] for n in ("l_hip", "r_hip",
                                                                                         "spine1")]].max(1))
    assert sil.stillness[:, 0].max() < 0.01 and sil.stillness[:, JOINT_INDEX["l_ankle"]].min() > 0.99


def test_bad_input_is_named():
    J = np.broadcast_to(skeleton_px(), (5, NUM_JOINTS, 2))
    with pytest.raises(ValueError, match=r"joints_px: expected shape \(5, 24, 2\)"):
        measure_silence(noise(0.1), EDGES, J[:4], H, W, **SETTINGS)
    with pytest.raises(ValueError, match="increasing bin edges"):
        measure_silence(noise(0.1), EDGES[::-1], J, H, W, **SETTINGS)
    with pytest.raises(ValueError, match="rate_hz > 0"):
        measure_silence(noise(0.1), EDGES, J, H, W, **{**SETTINGS, "rate_hz": 0.0})
    with pytest.raises(ValueError, match="radius_px: expected an integer >= 0, got 2.5"):
        measure_silence(noise(0.1), EDGES, J, H, W, **{**SETTINGS, "radius_px": 2.5})
    with pytest.raises(ValueError, match="hold_bins: expected an integer >= 0, got -1"):
        measure_silence(noise(0.1), EDGES, J, H, W, **{**SETTINGS, "hold_bins": -1})
    with pytest.raises(ValueError, match="rate_hz > 0"):
        measure_silence(noise(0.1), EDGES, J, H, W, **{**SETTINGS, "rate_hz": float("nan")})


def test_sweep_finds_a_limb_the_estimate_has_at_the_right_place_at_the_wrong_time():
    """The right forearm moves along its resting line during bin 1 only, but the estimate has it there only in bin
    3 (in bins 0-2 it puts the forearm 40 px lower, where nothing happens). Without a sweep bin 1 calls the wrist
    still; with a sweep of 2 bins the wrist's bones of bin 3 are looked at with bin 1's events and it is not; the
    other arm stays still either way, and the activity is the largest over the places looked at."""
    J = np.broadcast_to(skeleton_px(), (5, NUM_JOINTS, 2)).copy()
    arm = [JOINT_INDEX[n] for n in ("r_elbow", "r_wrist", "r_hand")]
    J[:3, arm, 1] += 40.0
    ev = np.concatenate([noise(0.5), edge_sweep(J[3, JOINT_INDEX["r_elbow"]], J[3, JOINT_INDEX["r_wrist"]],
                                                10_000, 20_000)])
    ev = ev[np.argsort(ev["t"], kind="stable")]
    wrist, other = JOINT_INDEX["r_wrist"], JOINT_INDEX["l_wrist"]
    plain = measure_silence(ev, EDGES, J, H, W, **SETTINGS)
    swept = measure_silence(ev, EDGES, J, H, W, **{**SETTINGS, "sweep_bins": 2})
    assert plain.stillness[1, wrist] > 0.9 and swept.stillness[1, wrist] < 0.01
    assert swept.stillness[:, other].min() > 0.5
    assert np.all(swept.activity_hz >= plain.activity_hz - 1e-9)
    one = measure_silence(ev, EDGES, J, H, W, **{**SETTINGS, "sweep_bins": 1})  # bin 3 is 2 bins from bin 1: not reached
    assert one.stillness[1, wrist] > 0.9
    with pytest.raises(ValueError, match=r"sweep_bins: expected an integer >= 0, got -1"):
        measure_silence(ev, EDGES, J, H, W, **{**SETTINGS, "sweep_bins": -1})
