"""Motion-detail metrics (eventcap.analysis.metrics): central differences, MPJVE, acceleration error and peak speeds per
batch against values worked out by hand on analytic trajectories, and the evaluate stage's new columns."""

from __future__ import annotations


import numpy as np
import pytest

from eventcap.analysis.metrics import (END_EFFECTORS, central_derivative, depth_split, half_window_steps, motion_detail, peak_speed_errors,
                              root_relative, truth_at)
from eventcap.analysis.motion import on_grid, tracking_times_us, uniform_motion



def still_body(T: int) -> np.ndarray:
    """(T, 24, 3): a fixed random skeleton that does not move."""
    return np.repeat(np.random.default_rng(0).normal(0.0, 0.3, (1, 24, 3)), T, axis=0)


T_US = np.arange(0, 201_000, 1_000, dtype=np.int64)  # 0..200 ms at 1 kHz
t_s = T_US * 1e-6


def test_central_differences_of_a_sinusoid_by_hand():
    """d/dt sin(wt) by (x(t+h) - x(t-h)) / 2h is cos(wt)·sin(wh)/h exactly; the second difference is
    -sin(wt)·(2 - 2cos(wh))/h²; h = 5 ms for a 10 ms window at 1 kHz."""
    w = 2 * np.pi * 7.0
    x = np.sin(w * t_s)
    v, ok = central_derivative(x, T_US, 10_000, 1)
    a, ok2 = central_derivative(x, T_US, 10_000, 2)
    h = 0.005
    assert np.array_equal(ok, ok2) and ok.sum() == T_US.size - 10 and not ok[:5].any() and not ok[-5:].any()
    assert np.allclose(v[ok], np.cos(w * t_s[ok]) * np.sin(w * h) / h, atol=1e-9)
    assert np.allclose(a[ok], -np.sin(w * t_s[ok]) * (2 - 2 * np.cos(w * h)) / h**2, atol=1e-6)
    assert np.isnan(v[~ok]).all()
    # the window snaps to whole tracking steps on each side: 9 ms at 1 ms steps -> 2·5 ms (round half to even: 4.5->4)
    assert half_window_steps(T_US, 9_000) == (4, 1000) and half_window_steps(T_US, 500) == (1, 1000)


def test_a_gap_invalidates_only_the_frames_that_reach_across_it():
    t = np.delete(T_US, 100)  # frame at 100 ms missing
    v, ok = central_derivative(2.0 * t * 1e-6, t, 4_000, 1)
    assert np.allclose(v[ok], 2.0)
    # with h = 2 ms only the frames at 98 and 102 ms need the missing one (99 and 101 ms reach 97/101 and 99/103 ms)
    bad_t = t[~ok]
    assert set(bad_t.tolist()) == {0, 1000, 98_000, 102_000, 199_000, 200_000}


def test_an_intensity_frame_between_grid_times_is_no_grid_frames_neighbour():
    """A batch boundary off the 1 ms grid (15 fps frames: 81 667 us) is a frame of the motion; the grid frames'
    differences are those of the grid alone, and the off-grid frame itself has none."""
    x = np.sin(T_US * 1e-5)[:, None]
    t = np.insert(T_US, 82, 81_667)
    xi = np.insert(x, 82, np.sin(81_667 * 1e-5))[:, None]
    for order in (1, 2):
        v, ok = central_derivative(x, T_US, 10_000, order)
        vi, oki = central_derivative(xi, t, 10_000, order)
        grid = t % 1000 == 0
        assert np.array_equal(oki[grid], ok) and np.array_equal(vi[grid], v, equal_nan=True)
        assert not oki[82] and np.isnan(vi[82]).all()


def test_a_motion_of_15_fps_batches_is_on_one_grid_between_its_frames():
    """Batches between 15 fps frames (66 666.7 us apart): the joined motion holds the frames and the whole 1 ms grid;
    the BVH's uniform motion is that grid, estimated everywhere (nothing interpolated); a motion that starts off
    the grid (a real camera's first frame) gets the grid from the next whole millisecond."""
    frames = 15_000 + np.round(np.arange(4) * 1e6 / 15).astype(np.int64)
    t = np.unique(np.concatenate([tracking_times_us(a, b) for a, b in zip(frames[:-1], frames[1:])]))
    assert set(t[~on_grid(t, 1000)].tolist()) == {81_667, 148_333}
    S = np.sin(t[:, None] * 1e-5 + np.arange(33))
    grid, U, filled = uniform_motion(t, S, 1000)
    assert np.array_equal(grid, np.arange(15_000, 215_001, 1000)) and not filled.any()
    assert np.array_equal(U, S[on_grid(t, 1000)])
    t1 = tracking_times_us(16_333, 83_000)  # a batch from a first frame at 16 333 us
    grid, U, filled = uniform_motion(t1, np.sin(t1[:, None] * 1e-5 + np.arange(33)), 1000)
    assert np.array_equal(grid, np.arange(17_000, 83_001, 1000)) and not filled.any()
    with pytest.raises(ValueError, match=r"no multiple of 1000 us between the motion's first \(1500 us\) and last"):
        uniform_motion(np.array([1500, 1900]), np.zeros((2, 33)), 1000)
    with pytest.raises(ValueError, match=r"expected t1_us >= t0_us, got t0_us=5, t1_us=4"):
        tracking_times_us(5, 4)


def test_mpjve_and_acceleration_error_by_hand():
    """Truth still; the estimate's left wrist moves at 0.3 m/s along x plus 4 m/s² along y (relative to the pelvis).
    Differences of a quadratic are exact: v_err(t) = |(0.3, 4t)|, a_err = 4, on 1 of the 23 non-root joints."""
    true = still_body(T_US.size)
    pred = true.copy()
    j = 20  # l_wrist
    pred[:, j, 0] += 0.3 * t_s
    pred[:, j, 1] += 0.5 * 4.0 * t_s**2
    d = motion_detail(T_US, pred, true, 10_000)
    ok = d["valid"]
    assert d["window_ms"] == 10.0 and d["n_velocity_frames"] == T_US.size - 10
    by_hand = 1000.0 * np.hypot(0.3, 4.0 * t_s[ok]).mean() / 23
    assert d["MPJVE_mm_s"] == pytest.approx(by_hand, rel=1e-9)
    assert d["accel_err_m_s2"] == pytest.approx(4.0 / 23, rel=1e-9)
    # moving the whole body (every joint and the pelvis alike) changes nothing: root-relative
    d2 = motion_detail(T_US, pred + np.array([1.0, 2.0, 0.0]) * t_s[:, None, None] ** 2, true, 10_000)
    assert d2["MPJVE_mm_s"] == pytest.approx(by_hand, rel=1e-9)
    assert d2["accel_err_m_s2"] == pytest.approx(4.0 / 23, rel=1e-9)


def test_peak_speed_per_batch_by_hand():
    """A wrist swings x = A sin(wt) relative to the pelvis (peak speed A·sin(wh)/h with the 10 ms window, at 50 and
    150 ms); the estimate swings with amplitude 1.5 A up to 100 ms and 0.8 A after: relative errors 50% and 20% in
    batches [0, 90] and [110, 200] ms (whose differences do not reach across 100 ms)."""
    A, w = 0.2, 2 * np.pi * 10.0  # two full periods in 200 ms: each 100 ms batch holds a peak
    true, pred = still_body(T_US.size), still_body(T_US.size)
    wrist = END_EFFECTORS.index("l_wrist")
    ee = (10, 11, 20, 21, 22, 23)
    assert ee[wrist] == 20
    true[:, 20, 0] += A * np.sin(w * t_s)
    amp = np.where(t_s <= 0.1, 1.5 * A, 0.8 * A)
    pred[:, 20, 0] += amp * np.sin(w * t_s)
    iv = np.array([[0, 90_000], [110_000, 200_000]])
    d = motion_detail(T_US, pred, true, 10_000, iv, ee)
    peak = A * np.sin(w * 0.005) / 0.005
    assert np.nanmax(d["speed_true"][:, wrist]) == pytest.approx(peak, rel=1e-9)
    errs = d["peak_speed_errors"]
    assert errs.shape == (2, 6)
    assert errs[0, wrist] == pytest.approx(0.5, abs=1e-9)
    assert errs[1, wrist] == pytest.approx(0.2, abs=1e-9)
    # the other end effectors do not move: their true peak is 0, so no relative error is defined
    assert np.isnan(np.delete(errs, wrist, axis=1)).all()
    assert d["peak_speed_err"] == pytest.approx(np.median(errs[:, wrist]))


def test_peak_speed_errors_direct_and_threshold():
    t = np.arange(6, dtype=np.int64) * 1000
    true = np.array([[1.0, 0.0], [2.0, 0.05], [1.0, 0.0], [3.0, 0.0], [4.0, 0.0], [1.0, 0.0]])
    pred = np.array([[1.0, 0.0], [3.0, 0.10], [1.0, 0.0], [1.0, 0.0], [2.0, 0.0], [1.0, 0.0]])
    valid = np.array([True, True, True, True, True, False])
    e = peak_speed_errors(t, pred, true, valid, np.array([[0, 2000], [2000, 5000]]))
    # batch 0: peaks 3 vs 2 -> 0.5, 0.10 vs 0.05 -> 1.0; batch 1 (frames 2..4; 5 invalid): 2 vs 4 -> 0.5, 0 vs 0 -> nan
    assert e[0].tolist() == [0.5, 1.0] and e[1, 0] == 0.5 and np.isnan(e[1, 1])
    e = peak_speed_errors(t, pred, true, valid, np.array([[0, 2000]]), min_true_mps=0.1)
    assert e[0, 0] == 0.5 and np.isnan(e[0, 1])


def test_fast_peaks_and_signed_error_by_true_speed():
    """detail_values keeps the fast moments apart: the same wrist swing as above at two amplitudes, one batch's true
    peak under 3 m/s and one over; peak_speed_err_fast is the error of the fast one alone, and the signed error per
    true-speed bin says which way each is wrong (negative: too slow)."""
    from eventcap_evaluate._impl import detail_values

    w = 2 * np.pi * 10.0
    true, pred = still_body(T_US.size), still_body(T_US.size)
    amp_true = np.where(t_s <= 0.1, 0.02, 0.08)  # true peaks about 1.26 and 5.0 m/s
    true[:, 20, 0] += amp_true * np.sin(w * t_s)
    pred[:, 20, 0] += np.where(t_s <= 0.1, 1.25, 0.6) * amp_true * np.sin(w * t_s)
    iv = np.array([[0, 90_000], [110_000, 200_000]])
    v = detail_values(T_US, pred, true, 10.0, END_EFFECTORS, iv, np.zeros(0, np.int64), 0.5, 3.0)
    assert v["n_peak_pairs"] == 2 and v["n_fast_pairs"] == 1
    assert v["peak_speed_err_fast"] == pytest.approx(0.4, abs=1e-9)
    assert v["peak_speed_err"] == pytest.approx(np.median([0.25, 0.4]), abs=1e-9)
    by_bin = v["peak_speed_signed_by_bin"]
    assert by_bin["0.5-1.5"]["median"] == pytest.approx(0.25, abs=1e-9) and by_bin["0.5-1.5"]["n"] == 1
    assert by_bin["3-6"]["median"] == pytest.approx(-0.4, abs=1e-9) and by_bin["3-6"]["n"] == 1
    assert by_bin["1.5-3"] == {"median": None, "n": 0} and by_bin["6+"]["n"] == 0
    wrist = END_EFFECTORS.index("l_wrist")
    assert v["peak_speed_true_mps"][1][wrist] == pytest.approx(0.08 * np.sin(w * 0.005) / 0.005, rel=1e-4)
    assert v["peak_speed_signed"][1][wrist] == pytest.approx(-0.4, abs=1e-5)
    # nothing reaches 10 m/s: no fast pair, no figure
    v = detail_values(T_US, pred, true, 10.0, END_EFFECTORS, iv, np.zeros(0, np.int64), 0.5, 10.0)
    assert v["n_fast_pairs"] == 0 and v["peak_speed_err_fast"] is None


def test_truth_at_and_root_relative():
    gt_t = np.array([0, 1000, 2000], np.int64)
    J = np.arange(3 * 2 * 3, dtype=np.float64).reshape(3, 2, 3)
    got, inside = truth_at(gt_t, J, np.array([-5, 0, 500, 2000, 2500]))
    assert inside.tolist() == [False, True, True, True, False]
    assert np.allclose(got[1], 0.5 * (J[0] + J[1])) and np.array_equal(got[2], J[2])
    rr = root_relative(J)
    assert np.all(rr[:, 0] == 0) and np.allclose(rr[:, 1], 3.0)


def test_depth_split_by_hand():
    """A joint moved 30 mm along the camera's line of sight and 40 mm across it, in a camera turned 90° about y:
    depth 30, image plane 40; a shift of the whole body (root included) is no root-relative error."""
    true = np.zeros((1, 3, 3))
    true[0, 1] = [0.0, 0.5, 0.0]
    true[0, 2] = [0.0, -0.5, 0.0]
    c, s = 0.0, 1.0  # world to camera: a rotation by 90° about y, the camera's z is the world's -x
    R = np.array([[c, 0, -s], [0, 1, 0], [s, 0, c]])
    pred = true.copy()
    pred[0, 1] += R.T @ np.array([0.0, 0.04, 0.03])  # 40 mm in the image plane, 30 mm in depth
    depth, image = depth_split(pred + 0.2, true, R)
    assert depth.shape == image.shape == (1, 2)
    assert np.allclose(depth, [[0.03, 0.0]]) and np.allclose(image, [[0.04, 0.0]])
    with pytest.raises(ValueError, match="differ"):
        depth_split(pred[:, :2], true, R)


def test_bad_input():
    with pytest.raises(ValueError, match="at least 3 frames"):
        central_derivative(np.zeros(2), np.array([0, 1000]), 10_000)
    with pytest.raises(ValueError, match="positive time window"):
        central_derivative(np.zeros(5), np.arange(5) * 1000, 0)
    with pytest.raises(ValueError, match="order: expected 1 or 2"):
        central_derivative(np.zeros(5), np.arange(5) * 1000, 2000, 3)
    with pytest.raises(ValueError, match="x has 4 frames but t_us 5"):
        central_derivative(np.zeros(4), np.arange(5) * 1000, 2000)
    with pytest.raises(ValueError, match="root"):
        motion_detail(T_US, still_body(T_US.size), still_body(T_US.size), 10_000, np.array([[0, 1000]]), (0,))


# -- the evaluate stage's columns ------------------------------------------------------------------------------------
def test_evaluate_stage_reports_motion_detail(monkeypatch):
    from helpers import evaluate_scene as te
    from eventcap.core.runner import reset_process_caches

    monkeypatch.setenv("EVENTCAP_STAGES", te.STAGES)
    reset_process_caches()
    rec = te.recording()
    values, _ = te.evaluate(rec, te.batch_sequences(rec), peak_min_speed_mps=0.0)
    assert values["MPJVE_mm_s"] == pytest.approx(0.0, abs=1e-9)
    assert values["accel_err_m_s2"] == pytest.approx(0.0, abs=1e-9)
    assert values["peak_speed_err"] == pytest.approx(0.0, abs=1e-12) and values["AE_rootrel_mm"] < 1e-9
    assert values["velocity_window_ms"] == 10.0 and values["n_velocity_frames"] == 121 - 10
    assert values["n_peak_pairs"] == 3 * 6 and set(values["peak_speed_err_per_joint"]) == set(END_EFFECTORS)
    assert np.array(values["peak_speed_errors"]).shape == (3, 6)
    # a pair counts only where the true peak exceeds peak_min_speed_mps (default 0.5 m/s: every end effector of
    # this jumping jack at double speed does, in every batch)
    values, _ = te.evaluate(rec, te.batch_sequences(rec))
    assert values["n_peak_pairs"] == 18 and values["peak_min_speed_mps"] == 0.5
    values, _ = te.evaluate(rec, te.batch_sequences(rec), peak_min_speed_mps=100.0)
    assert values["n_peak_pairs"] == 0 and values["peak_speed_err"] is None
    assert all(v is None for row in values["peak_speed_errors"] for v in row)

    # a constant shift of the root translation moves every joint: AE without alignment sees it, root-relative
    # joints do not
    def shift(t, S):
        S[:, 30:33] += [0.1, 0.0, 0.0]
        return S

    values, _ = te.evaluate(rec, te.batch_sequences(rec, shift), align="none")
    assert values["AE_mm"] == pytest.approx(100.0, rel=1e-6)
    assert values["AE_rootrel_mm"] < 1e-9 and values["MPJVE_mm_s"] < 1e-6
    assert values["depth_mm"] < 1e-9 and values["image_plane_mm"] < 1e-9

    # the estimate lags the truth by 1 ms: its velocity error is the truth's acceleration × 1 ms, on average
    def lag(t, S):
        return rec.ground_truth.poses[np.searchsorted(rec.ground_truth.t_us, np.maximum(t - 1000, 0))]

    values, _ = te.evaluate(rec, te.batch_sequences(rec, lag), velocity_window_ms=4.0)
    assert values["velocity_window_ms"] == 4.0 and values["MPJVE_mm_s"] > 1.0
    with pytest.raises(ValueError, match=r"end_effectors: 'pelvis' is not a joint other than the root"):
        te.evaluate(rec, te.batch_sequences(rec), end_effectors=["pelvis"])
    with pytest.raises(ValueError, match=r"velocity_window_ms: expected a finite number > 0, got 0"):
        te.evaluate(rec, te.batch_sequences(rec), velocity_window_ms=0.0)
    reset_process_caches()
