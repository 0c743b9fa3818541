"""Tests of the event feature trackers (plugins/eventcap_track/eklt.py, klt.py) against exact ground truth.

The scenes are simulated (``tests/helpers/tracking_scenes.py``, also used by ``benchmarks/accuracy/bench_tracking.py``): textured patterns at 240x180 moving fast with known
motion, turned into events by ``eventcap.sim.events``; every texture point's true position is known at any time.
Thresholds are conservative versions of the benchmark's numbers (see the module docstring of eklt.py).
"""

from __future__ import annotations


import numpy as np
import pytest

from eventcap.events import EVENT_DTYPE, make_events
from eventcap_track import eklt, klt
from eventcap_track.eklt import (
    KIND_BACKWARD,
    KIND_FORWARD,
    KIND_STITCHED,
    EkltConfig,
    FeatureTracks,
    detect_features,
    relocate,
    stitch,
    track,
    track_bidirectional,
)
from helpers import tracking_scenes as bt

T0, T1 = bt.T0_US, bt.T1_US


@pytest.fixture(scope="module")
def scenes():
    """Simulated scenes and their events, made once per module (each takes 0.1-0.4 s)."""
    cache = {}

    def get(name):
        if name not in cache:
            scene = bt.make_scene(name)
            cache[name] = (scene, bt.simulate_events(scene))
        return cache[name]

    return get


def _starts(tracks: FeatureTracks) -> np.ndarray:
    o = tracks.offsets
    return np.c_[tracks.x[o[:-1]], tracks.y[o[:-1]]]


def _tracks(k, t, x, y, kind, survived=None, height=180, width=240) -> FeatureTracks:
    """Hand-made FeatureTracks (samples given per track in time order)."""
    k = np.asarray(k, np.int32)
    return FeatureTracks(np.asarray(t, np.int64), np.asarray(x, float), np.asarray(y, float), k,
                         np.zeros(k.size, np.float32), np.asarray(kind, np.int8),
                         np.ones(len(kind), bool) if survived is None else np.asarray(survived, bool), height, width)


# ------------------------------------------------------------------------------------------- layout, detection
def test_smoke_layout_of_forward_tracks(scenes):
    scene, events = scenes("translate_1500")
    log0 = bt.log_image(scene, T0)
    tr = track(log0, events, T0, 10_000, +1)
    assert tr.n_tracks >= 20 and (tr.height, tr.width) == (180, 240)
    assert tr.t_us.dtype == np.int64 and tr.x.dtype == np.float64 and tr.track_id.dtype == np.int32
    assert tr.kind.dtype == np.int8 and np.all(tr.kind == KIND_FORWARD) and tr.survived.dtype == bool
    # Every track starts with its detection, exactly, at t_start; samples stay in the interval and increase.
    np.testing.assert_array_equal(_starts(tr), detect_features(log0))
    first, last = tr.span_us()
    assert np.all(first == T0) and np.all(last <= 10_000) and np.all(last > 5_000)
    o = tr.offsets
    assert o[0] == 0 and o[-1] == tr.t_us.size and np.all(np.diff(o) >= 1)
    for k in range(tr.n_tracks):
        t, _, _ = tr.track(k)
        assert np.all(np.diff(t) > 0)
    # positions_at: the detection at t0, NaN after a track's last sample.
    pos = tr.positions_at([T0, 10_000 + 1])
    np.testing.assert_allclose(pos[:, 0], _starts(tr))
    assert np.all(np.isnan(pos[:, 1]))


def test_detect_features_respects_mask_border_and_spacing(scenes):
    scene, _ = scenes("disc_2000")
    log0 = bt.log_image(scene, T0)
    mask = scene.mask(T0)
    cfg = EkltConfig(max_features=50)
    f = detect_features(log0, mask, cfg)
    assert 10 <= f.shape[0] <= 50 and f.shape[1] == 2
    assert np.all(mask[np.rint(f[:, 1]).astype(int), np.rint(f[:, 0]).astype(int)])
    h = cfg.half_px
    assert np.all((f[:, 0] >= h) & (f[:, 0] <= 239 - h) & (f[:, 1] >= h) & (f[:, 1] <= 179 - h))
    d = np.hypot(f[:, None, 0] - f[None, :, 0], f[:, None, 1] - f[None, :, 1]) + np.eye(len(f)) * 1e9
    assert d.min() >= cfg.min_distance_px - 2.0  # sub-pixel refinement moves corners by a fraction of a pixel
    assert detect_features(log0, np.zeros_like(mask)).shape == (0, 2)


# ---------------------------------------------------------------------------------------- accuracy, EKLT
def test_forward_tracking_of_fast_translation_is_subpixel(scenes):
    scene, events = scenes("translate_1500")
    tr = track(bt.log_image(scene, T0), events, T0, T1, +1)
    score = bt.evaluate(tr, scene)
    # Benchmark: median 0.31 px, p90 0.71 px, 2 % lost away from the border; the rest leave the view.
    assert score.n_tracks >= 30
    assert score.median_px < 0.6 and score.p90_px < 1.5
    assert score.lost_inside <= 0.1
    # Tracks whose texture point stays well inside the image all the way survive.
    stays = np.all(np.abs(scene.truth(_starts(tr), T0, T1) - [120, 90]) < [105, 75], axis=1)
    assert stays.sum() >= 10 and np.mean(tr.survived[stays]) >= 0.9


def test_backward_tracking_of_rotation_is_subpixel(scenes):
    scene, events = scenes("rotate")
    log1 = bt.log_image(scene, T1)
    tr = track(log1, events, T0, T1, -1)
    assert np.all(tr.kind == KIND_BACKWARD)
    first, last = tr.span_us()
    assert np.all(last == T1) and np.median(first) < T0 + 5_000  # tracked back to near the start
    o = tr.offsets
    np.testing.assert_array_equal(np.c_[tr.x[o[1:] - 1], tr.y[o[1:] - 1]], detect_features(log1))
    score = bt.evaluate(tr, scene)
    # Benchmark: median 0.28 px, p90 0.73 px, survival 0.94 at up to ~2200 px/s.
    assert score.median_px < 0.6 and score.p90_px < 1.8 and score.survival >= 0.8


def test_backward_is_forward_tracking_of_the_time_reversed_stream(scenes):
    """Backward tracking = forward tracking of the events mirrored in time with flipped polarity."""
    scene, events = scenes("translate_500")
    ev = events[(events["t"] >= T0) & (events["t"] <= 20_000)]
    mirrored = make_events(T0 + 20_000 - ev["t"][::-1], ev["x"][::-1], ev["y"][::-1], -ev["p"][::-1])
    log1 = bt.log_image(scene, 20_000)
    cfg = EkltConfig(lag_gain=0.0)  # the hysteresis correction follows sensor time, so it differs by design
    back = track(log1, ev, T0, 20_000, -1, cfg)
    fwd = track(log1, mirrored, T0, 20_000, +1, cfg)
    assert back.n_tracks == fwd.n_tracks and back.t_us.size == fwd.t_us.size
    for k in range(back.n_tracks):
        tb, xb, yb = back.track(k)
        tf, xf, yf = fwd.track(k)
        np.testing.assert_array_equal(tb, (T0 + 20_000 - tf)[::-1])
        np.testing.assert_allclose(xb, xf[::-1], atol=1e-9)
        np.testing.assert_allclose(yb, yf[::-1], atol=1e-9)


def test_hysteresis_compensation_removes_the_trailing_bias(scenes):
    """Without compensation, tracks trail the true position along the motion (pixels fire after a full C)."""
    scene, events = scenes("translate_1500")
    log0 = bt.log_image(scene, T0)
    direction = np.array([np.cos(0.5), np.sin(0.5)])  # the scene's motion direction

    def mean_along(cfg):
        tr = track(log0, events, T0, T1, +1, cfg)
        err = tr.positions_at(np.arange(5_000, T1, 1000)) - np.stack(
            [scene.truth(_starts(tr), T0, t) for t in range(5_000, T1, 1000)], axis=1)
        return np.nanmean(err @ direction)

    assert mean_along(EkltConfig(lag_gain=0.0)) < -0.4  # measured -0.7 px
    assert abs(mean_along(EkltConfig())) < 0.2


# ----------------------------------------------------------------------------------------------- stitching
def test_stitch_associates_within_threshold_one_to_one():
    # Forward tracks 0, 1, 2 at x = 10, 20, 50 at t_mid = 500; backward at x = 11, 20.5, 60.
    f = _tracks([0, 0, 1, 1, 2, 2], [0, 1000] * 3, [10, 10, 20, 20, 50, 50], [5] * 6, [KIND_FORWARD] * 3)
    b = _tracks([0, 0, 1, 1, 2, 2], [0, 1000] * 3, [11, 11, 20.5, 20.5, 60, 60], [5] * 6, [KIND_BACKWARD] * 3)
    s = stitch(f, b, 0, 1000, stitch_px=4.0, mode="split")
    assert list(s.kind) == [KIND_STITCHED, KIND_STITCHED, KIND_FORWARD, KIND_BACKWARD]
    # Split: forward samples up to t_mid, backward after it.
    t, x, _ = s.track(0)
    np.testing.assert_array_equal(t, [0, 1000])
    np.testing.assert_allclose(x, [10, 11])
    # Unmatched tracks are kept as they were.
    np.testing.assert_allclose(s.track(2)[1], [50, 50])
    np.testing.assert_allclose(s.track(3)[1], [60, 60])
    cat = FeatureTracks.concatenate([f, b])
    assert cat.n_tracks == 6 and list(cat.kind) == [KIND_FORWARD] * 3 + [KIND_BACKWARD] * 3
    np.testing.assert_allclose(cat.track(4)[1], [20.5, 20.5])
    # Two forward tracks near one backward track: only the closer one gets it.
    f2 = _tracks([0, 0, 1, 1], [0, 1000] * 2, [10, 10, 12, 12], [5] * 4, [KIND_FORWARD] * 2)
    b2 = _tracks([0, 0], [0, 1000], [11.5, 11.5], [5, 5], [KIND_BACKWARD])
    s2 = stitch(f2, b2, 0, 1000)
    assert list(s2.kind) == [KIND_STITCHED, KIND_FORWARD]
    assert s2.track(0)[1][0] == 12  # the stitched one is forward track 1 (0.5 px away, not 1.5 px)


def test_stitch_blend_is_continuous_and_trusts_each_side_at_its_end():
    # Forward covers [0, 800] at y = 0; backward covers [200, 1000] at y = 2: overlap [200, 800].
    tf = np.arange(0, 801, 100)
    tb = np.arange(200, 1001, 100)
    f = _tracks(np.zeros(tf.size), tf, np.full(tf.size, 30.0), np.zeros(tf.size), [KIND_FORWARD])
    b = _tracks(np.zeros(tb.size), tb, np.full(tb.size, 30.0), np.full(tb.size, 2.0), [KIND_BACKWARD])
    s = stitch(f, b, 0, 1000, mode="blend")
    t, x, y = s.track(0)
    np.testing.assert_array_equal(t, np.arange(0, 1001, 100))
    np.testing.assert_allclose(y, [0, 0, 0, 1 / 3, 2 / 3, 1, 4 / 3, 5 / 3, 2, 2, 2], atol=1e-12)
    assert s.survived[0] and s.kind[0] == KIND_STITCHED


def test_relocate_finds_forward_points_on_the_end_image(scenes):
    scene, events = scenes("rotate")
    log0, log1 = bt.log_image(scene, T0), bt.log_image(scene, T1)
    fwd, warps = eklt._track(log0, events, T0, T1, +1, EkltConfig(), None, None)
    found = relocate(log0, log1, fwd, T1, warps)
    ok = np.all(np.isfinite(found), axis=1)
    assert ok.sum() >= 0.6 * fwd.n_tracks
    err = np.hypot(*(found[ok] - scene.truth(_starts(fwd)[ok], T0, T1)).T)
    assert np.median(err) < 0.1 and np.mean(err < 0.5) >= 0.9  # measured: median 0.02 px


def test_bidirectional_stitching_covers_the_batch_and_lowers_error(scenes):
    scene, events = scenes("affine")
    log0, log1 = bt.log_image(scene, T0), bt.log_image(scene, T1)
    both = track_bidirectional(log0, log1, events, T0, T1)
    fwd = track(log0, events, T0, T1, +1)
    stitched = np.flatnonzero(both.kind == KIND_STITCHED)
    assert stitched.size >= 15
    err_s = bt.track_errors(both, scene)[stitched]
    # The same texture points tracked forward only (stitched tracks start with a forward detection).
    starts = _starts(both)[stitched]
    same = [int(np.argmin(np.hypot(*(_starts(fwd) - p).T))) for p in starts]
    err_f = bt.track_errors(fwd, scene)[same]
    # Stitched tracks cover the whole batch; one-directional ones stop when dropped (survivors hold to the end).
    assert np.mean(np.isfinite(err_s)) > 0.99 and np.mean(np.isfinite(err_s)) >= np.mean(np.isfinite(err_f))
    # Measured: median 0.38 vs 0.49 px, p90 0.83 vs 1.16 px.
    assert np.nanpercentile(err_s, 90) < np.nanpercentile(err_f, 90)
    assert np.nanmedian(err_s) < np.nanmedian(err_f)
    # The paper's independent detection on the end image stitches different points together: worse.
    paper = track_bidirectional(log0, log1, events, T0, T1, backward_start="detect")
    assert bt.evaluate(both, scene).p90_px < bt.evaluate(paper, scene).p90_px


# ------------------------------------------------------------------------------------- the KLT baseline
def test_eklt_beats_klt_on_event_integrated_latents(scenes):
    scene, events = scenes("translate_1500")
    log0 = bt.log_image(scene, T0)
    fwd = track(log0, events, T0, T1, +1)
    feats = _starts(fwd)
    latents = bt.event_latents(log0, events, T0, T1)
    assert latents.shape == (41, 180, 240)
    k_ev = klt.klt_latent(latents, T0, T1, features=feats)
    np.testing.assert_array_equal(_starts(k_ev), feats)
    e_eklt, e_klt = bt.evaluate(fwd, scene), bt.evaluate(k_ev, scene)
    # Measured: 0.31 px vs 11.9 px median. Accumulated threshold mismatch and C-quantisation smear the latents.
    assert e_klt.median_px > 3 * e_eklt.median_px and e_klt.median_px > 1.5
    # The baseline itself is sound: on the true 1 ms images (a 1000 fps camera, not available) it is exact.
    k_true = klt.klt_latent(bt.true_latents(scene), T0, T1, features=feats)
    assert bt.evaluate(k_true, scene).median_px < 0.1


def test_klt_latent_callable_array_and_backward(scenes):
    scene, _ = scenes("translate_500")
    stack = bt.true_latents(scene, T0, 10_000)
    a = klt.klt_latent(stack, T0, 10_000)
    b = klt.klt_latent(lambda t: bt.log_image(scene, t), T0, 10_000)
    np.testing.assert_array_equal(a.t_us, b.t_us)
    np.testing.assert_allclose(a.x, b.x)
    assert np.all(a.kind == KIND_FORWARD) and np.all(np.isin(a.t_us, np.arange(T0, 10_001, 1000)))
    back = klt.klt_latent(stack, T0, 10_000, direction=-1)
    assert np.all(back.kind == KIND_BACKWARD) and np.all(back.span_us()[1] == 10_000)
    assert bt.evaluate(back, scene, T0, 10_000).median_px < 0.1


# ------------------------------------------------------------------------------------------------- errors
def test_exceptions(scenes):
    scene, events = scenes("translate_500")
    log0 = bt.log_image(scene, T0)
    with pytest.raises(ValueError, match="EVENT_DTYPE"):
        track(log0, np.zeros(5), T0, T1)
    with pytest.raises(ValueError, match="sorted ascending, row 1"):
        track(log0, make_events([5, 3], [1, 1], [1, 1], [1, 1]), T0, T1)
    with pytest.raises(ValueError, match="x < 240"):
        track(log0, make_events([5], [240], [1], [1]), T0, T1)
    with pytest.raises(ValueError, match="direction"):
        track(log0, events, T0, T1, direction=0)
    with pytest.raises(ValueError, match="t_end_us > t_start_us"):
        track(log0, events, T1, T0)
    with pytest.raises(ValueError, match="height, width"):
        track(log0[None], events, T0, T1)
    with pytest.raises(ValueError, match=r"\(K, 2\)"):
        track(log0, events, T0, T1, features=np.zeros(3))
    with pytest.raises(ValueError, match="inside the 240x180 image"):
        track(log0, events, T0, T1, features=[[300.0, 10.0]])
    with pytest.raises(ValueError, match=r"mask: expected shape \(height, width\) = \(180, 240\)"):
        detect_features(log0, np.ones((10, 10), bool))
    with pytest.raises(ValueError, match="patch_px: expected an odd integer"):
        EkltConfig(patch_px=24)
    with pytest.raises(ValueError, match="warp: expected one of"):
        EkltConfig(warp="homography")
    with pytest.raises(ValueError, match="n_events_min <= n_events_max"):
        EkltConfig(n_events_min=500)
    with pytest.raises(ValueError, match="backward_start"):
        track_bidirectional(log0, log0, events, T0, T1, backward_start="guess")
    empty = _tracks([0], [0], [1.0], [1.0], [KIND_FORWARD])
    with pytest.raises(ValueError, match="mode: expected 'blend' or 'split'"):
        stitch(empty, empty, 0, 1000, mode="average")
    with pytest.raises(ValueError, match="at least 41 frames"):
        klt.klt_latent(np.zeros((5, 180, 240), np.float32), T0, T1)
    with pytest.raises(ValueError, match="sorted by track_id"):
        _tracks([1, 0], [0, 0], [1.0, 1.0], [1.0, 1.0], [KIND_FORWARD] * 2)
    assert EVENT_DTYPE == events.dtype


def test_empty_event_stream_holds_detections_to_the_end(scenes):
    scene, _ = scenes("translate_500")
    tr = track(bt.log_image(scene, T0), np.empty(0, EVENT_DTYPE), T0, T1)
    # No events: nothing moved; each track is its detection at T0 held to T1.
    assert tr.t_us.size == 2 * tr.n_tracks and np.all(tr.survived)
    assert np.array_equal(tr.t_us, np.tile([T0, T1], tr.n_tracks))
    assert np.array_equal(tr.x[0::2], tr.x[1::2]) and np.array_equal(tr.y[0::2], tr.y[1::2])


@pytest.mark.parametrize("warp", ["translation", "affine"])
def test_other_warp_models_track_translation(scenes, warp):
    scene, events = scenes("translate_1500")
    tr = track(bt.log_image(scene, T0), events, T0, 20_000, +1, EkltConfig(warp=warp))
    score = bt.evaluate(tr, scene, T0, 20_000)
    # Measured over 40 ms: median 0.26 / 0.40 px, p90 0.62 / 1.05 px (translation / affine).
    assert score.median_px < 0.6 and score.p90_px < 1.5
