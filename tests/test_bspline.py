"""Tests of trajectory slicing (eventcap_track.bspline): accuracy on known motions, smoothness, span masks,
degenerate tracks, input layout and bad input."""

from __future__ import annotations


import numpy as np
import pytest

from eventcap_track import bspline


def motion(kind: str, t_us: np.ndarray) -> np.ndarray:
    """Smooth 2D motions in px at times t_us (µs) (a limb-like speed of several hundred px/s)."""
    t = np.asarray(t_us, np.float64) * 1e-6
    if kind == "linear":
        x, y = 30.0 + 700.0 * t, 90.0 - 250.0 * t
    elif kind == "accelerating":
        x, y = 40.0 + 200.0 * t + 2e4 * t**2, 120.0 - 5e3 * t**2
    elif kind == "wobble":  # 30 Hz, 3 px oscillation on a drift
        x, y = 50.0 + 800.0 * t + 3.0 * np.sin(2 * np.pi * 30.0 * t), 60.0 - 400.0 * t + 5e3 * t**2
    elif kind == "circle":  # 25 px radius, 4 rev/s: 630 px/s
        x, y = 120.0 + 25.0 * np.cos(2 * np.pi * 4.0 * t), 90.0 + 25.0 * np.sin(2 * np.pi * 4.0 * t)
    else:
        raise KeyError(kind)
    return np.stack(np.broadcast_arrays(x, y), axis=-1)


KINDS = ("linear", "accelerating", "wobble", "circle")


def asynchronous_tracks(rng, n_per_kind=5, mean_step_us=400):
    """Tracks of every motion kind, each with its own span inside [0, 40 ms] and jittered sample times."""
    tracks, kinds = [], []
    for kind in KINDS:
        for _ in range(n_per_kind):
            a, b = int(rng.integers(0, 8_000)), int(rng.integers(32_000, 40_001))
            t = np.unique(np.concatenate([[a, b], rng.integers(a, b + 1, (b - a) // mean_step_us)]))
            tracks.append((t, motion(kind, t)))
            kinds.append(kind)
    return tracks, kinds


def truth_grid(out, kinds):
    return np.stack([motion(k, out.t_us) for k in kinds], axis=1)


def test_smoke_shapes_and_layout():
    rng = np.random.default_rng(0)
    tracks, _ = asynchronous_tracks(rng, n_per_kind=2)
    ids, t_us, xy = bspline.concat_tracks(tracks)
    out = bspline.slice_trajectories(ids, t_us, xy, 0, 40_000)
    assert out.t_us.tolist() == list(range(0, 40_001, 1000))
    assert out.xy.shape == (41, len(tracks), 2) and out.xy.dtype == np.float32
    assert out.valid.shape == (41, len(tracks)) and out.valid.dtype == bool
    assert out.track_id.tolist() == list(range(len(tracks)))
    assert np.isnan(out.xy[~out.valid]).all() and np.isfinite(out.xy[out.valid]).all()

    # samples in any order, any integer ids: same result, columns in sorted id order
    perm = rng.permutation(ids.size)
    new_ids = np.array([7, -3, 100, 4, 55, 12, 9, 0])[ids]
    shuffled = bspline.slice_trajectories(new_ids[perm], t_us[perm], xy[perm], 0, 40_000)
    order = np.argsort([7, -3, 100, 4, 55, 12, 9, 0])
    assert shuffled.track_id.tolist() == sorted([7, -3, 100, 4, 55, 12, 9, 0])
    np.testing.assert_allclose(shuffled.xy, out.xy[:, order], atol=1e-4)
    np.testing.assert_array_equal(shuffled.valid, out.valid[:, order])


def test_noise_free_samples_are_reproduced():
    """Smooth motions sampled asynchronously (~every 0.4 ms) without noise: well under 0.1 px everywhere."""
    rng = np.random.default_rng(1)
    tracks, kinds = asynchronous_tracks(rng)
    ids, t_us, xy = bspline.concat_tracks(tracks)
    out = bspline.slice_trajectories(ids, t_us, xy, 0, 40_000, sigma_px=0.01)
    err = np.linalg.norm(out.xy - truth_grid(out, kinds), axis=2)[out.valid]
    assert err.max() < 0.03, err.max()
    assert np.sqrt(np.mean(err**2)) < 0.005
    # at the sample times themselves too (not only on the 1 ms grid), with the default smoothing
    fitted = bspline.fit_trajectories(ids, t_us, xy)
    at_samples = fitted.evaluate(ids, t_us)
    assert np.abs(at_samples - xy).max() < 0.1


def test_noisy_samples_are_smoothed():
    """0.2 px sample noise: the sliced trajectory is closer to the truth than the samples, and smooth."""
    rng = np.random.default_rng(2)
    tracks, kinds = asynchronous_tracks(rng)
    ids, t_us, xy = bspline.concat_tracks(tracks)
    noisy = xy + rng.normal(0.0, 0.2, xy.shape)
    out = bspline.slice_trajectories(ids, t_us, noisy, 0, 40_000, sigma_px=0.2)
    truth = truth_grid(out, kinds)
    err = np.abs(out.xy - truth)[out.valid]  # per coordinate, like the 0.2 px noise
    assert np.sqrt(np.mean(err**2)) < 0.1
    assert err.max() < 0.5
    # smooth: second differences at 1 ms stay near the true motion's (max 0.11 px for the wobble)
    d2 = np.abs(np.diff(out.xy, 2, axis=0))
    d2_true = np.abs(np.diff(truth, 2, axis=0))
    assert np.nanmax(d2) < d2_true.max() + 0.15
    # whereas linear interpolation of the noisy samples is as rough as the noise
    rough = np.stack([np.interp(out.t_us, t, noisy[ids == h, 0]) for h, (t, _) in enumerate(tracks)], axis=1)
    assert np.nanmax(np.abs(np.diff(np.where(out.valid, rough, np.nan), 2, axis=0))) > 3 * np.nanmax(d2[..., 0])


def test_mask_at_span_ends():
    spans = [(3_400, 27_000), (0, 40_000), (1_000, 1_999), (12_000, 12_000), (40_001, 45_000), (-5_000, 100)]
    tracks = []
    for a, b in spans:
        t = np.unique(np.linspace(a, b, 25).astype(np.int64))
        tracks.append((t, motion("circle", t)))
    ids, t_us, xy = bspline.concat_tracks(tracks)
    out = bspline.slice_trajectories(ids, t_us, xy, 0, 40_000)
    expected = np.stack([(out.t_us >= a) & (out.t_us <= b) for a, b in spans], axis=1)
    np.testing.assert_array_equal(out.valid, expected)
    assert out.valid[:, 0].nonzero()[0][[0, -1]].tolist() == [4, 27]  # 4 ms .. 27 ms (the last sample's time)
    assert out.valid[:, 2].sum() == 1  # 1 ms only: 2 ms is after the last sample at 1999 µs
    assert out.valid[:, 4].sum() == 0  # starts after the batch's last tracking frame
    # the single-sample track sits exactly at its sample
    np.testing.assert_allclose(out.xy[12, 3], motion("circle", np.array([12_000]))[0], atol=1e-4)
    # inside the spans the positions follow the motion
    err = np.linalg.norm(out.xy - motion("circle", out.t_us)[:, None, :], axis=2)[out.valid]
    assert err.max() < 0.1


def test_degenerate_tracks():
    # two samples: the straight line between them
    fit = bspline.fit_trajectory(np.array([0, 10_000]), np.array([[0.0, 0.0], [10.0, -5.0]]))
    np.testing.assert_allclose(fit(0, [0, 2_500, 10_000]), [[0, 0], [2.5, -1.25], [10, -5]], atol=1e-9)
    # repeated times are merged into their mean
    t = np.array([0, 5_000, 5_000, 10_000])
    xy = np.array([[0.0, 0.0], [4.0, 1.0], [6.0, -1.0], [10.0, 0.0]])
    fit = bspline.fit_trajectory(t, xy, sigma_px=0.001)
    np.testing.assert_allclose(fit(0, [5_000]), [[5.0, 0.0]], atol=1e-6)
    # one sample: constant
    fit = bspline.fit_trajectory(np.array([7]), np.array([[3.0, 4.0]]))
    np.testing.assert_allclose(fit(0, [7]), [[3.0, 4.0]])
    # samples far apart (40 s): still the straight line, no ill-conditioned solve
    fit = bspline.fit_trajectory(np.array([0, 40_000_000]), np.array([[100.0, 200.0], [110.0, 210.0]]))
    np.testing.assert_allclose(fit(0, [10_000_000]), [[102.5, 202.5]], atol=0.01)
    # no tracks at all
    out = bspline.slice_trajectories(np.empty(0, np.int64), np.empty(0, np.int64), np.empty((0, 2)), 0, 40_000)
    assert out.xy.shape == (41, 0, 2) and out.valid.shape == (41, 0)


def test_slice_times():
    assert bspline.slice_times_us(0, 40_000).tolist() == list(range(0, 40_001, 1000))
    # both ends (the batch's intensity frames), and the recording's 1 ms grid between them
    assert bspline.slice_times_us(5, 40_004).tolist() == [5, *range(1000, 40_001, 1000), 40_004]
    assert bspline.slice_times_us(0, 10_000, 300.0).tolist() == [0, 3333, 6667, 10_000]
    assert bspline.slice_times_us(0, 999).tolist() == [0, 999]
    assert bspline.slice_times_us(7, 7).tolist() == [7]


def test_slice_times_of_a_frame_clock_off_the_tracking_grid():
    """15 fps frames are 66 666.7 us apart: each batch ends on its second frame, and every batch's tracking frames
    between its frames lie on one 1 ms grid, so joined batches and overlapping windows sample the same times."""
    frames = 15_000 + np.round(np.arange(4) * 1e6 / 15).astype(np.int64)  # 15000, 81667, 148333, 215000
    parts = [bspline.slice_times_us(a, b) for a, b in zip(frames[:-1], frames[1:])]
    assert parts[0][[0, 1, -2, -1]].tolist() == [15_000, 16_000, 81_000, 81_667]
    assert parts[1][[0, 1, -2, -1]].tolist() == [81_667, 82_000, 148_000, 148_333]
    for a, b, p in zip(frames[:-1], frames[1:], parts):
        assert p[0] == a and p[-1] == b and np.all(np.diff(p) > 0)
        assert np.all(p[1:-1] % 1000 == 0) and np.all(np.diff(p[1:-1]) == 1000)
    joined = np.unique(np.concatenate(parts))
    assert np.array_equal(joined[joined % 1000 == 0], np.arange(15_000, 215_001, 1000))


def test_exception():
    t = np.array([0, 1000, 2000])
    xy = np.zeros((3, 2))
    ids = np.zeros(3, np.int64)
    with pytest.raises(ValueError, match=r"xy: expected \(3, 2\)"):
        bspline.slice_trajectories(ids, t, np.zeros((3, 3)), 0, 2000)
    with pytest.raises(ValueError, match=r"t_us: expected \(3,\) integer"):
        bspline.slice_trajectories(ids, t.astype(float), xy, 0, 2000)
    with pytest.raises(ValueError, match="track_id: expected a 1-D integer"):
        bspline.slice_trajectories(ids.astype(float), t, xy, 0, 2000)
    with pytest.raises(ValueError, match=r"finite pixel positions, got \[nan, 0.0\] at row 1"):
        bspline.slice_trajectories(ids, t, np.array([[0, 0], [np.nan, 0], [0, 0]]), 0, 2000)
    with pytest.raises(ValueError, match="t1_us >= t0_us"):
        bspline.slice_trajectories(ids, t, xy, 2000, 0)
    with pytest.raises(ValueError, match="sigma_px: expected a finite number > 0"):
        bspline.slice_trajectories(ids, t, xy, 0, 2000, sigma_px=0.0)
    with pytest.raises(ValueError, match="rate_hz: expected a finite number > 0"):
        bspline.slice_trajectories(ids, t, xy, 0, 2000, rate_hz=-1.0)
    with pytest.raises(ValueError, match=r"track 0: expected t_us \(K,\) and xy \(K, 2\)"):
        bspline.concat_tracks([(t, np.zeros((2, 2)))])
