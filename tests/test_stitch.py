"""The stages after the spline solve (plugins/eventcap_spline/stitch.py): ``stitch`` blends every batch's window into
one motion, ``cut`` gives each batch its frames of it. Conformance, and what they compute on windows of a known
motion (the spline solve itself: tests/test_spline.py)."""

from __future__ import annotations

import numpy as np
import pytest

from eventcap.artifacts import BatchPlan
from eventcap.artifacts.pose import PoseSequence
from eventcap.body.motions import motion_poses
from eventcap.core.config import build_config
from eventcap.core.registry import load_registry
from eventcap.core.stage import StageContext
from eventcap.core.testing import StageConformance
from helpers.spline_scene import BatchSeq

FRAMES_US = 5_000 + 40_000 * np.arange(5, dtype=np.int64)  # 25 fps: 4 batches of 40 ms
PLAN = BatchPlan.between_frames(FRAMES_US)


def truth(t_us: np.ndarray) -> np.ndarray:
    return motion_poses("jumping_jack", t_us * 1e-6, speed=1.0)


def windows(offsets=(0.0, 0.0, 0.0, 0.0)) -> BatchSeq:
    """What the spline solve gives (half_window 1): batch k's window spans batches k-1..k+1 (inside the recording), at
    every 1 ms, the true motion plus ``offsets[k]`` on every pose parameter."""
    out = []
    for k in range(len(PLAN)):
        a, b = PLAN.batch(max(k - 1, 0)), PLAN.batch(min(k + 1, len(PLAN) - 1))
        t = np.arange(a.t0_us, b.t1_us + 1, 1_000, dtype=np.int64)
        out.append(PoseSequence(t_us=t, poses=truth(t) + offsets[k], status="Solve_Succeeded", iterations=4))
    return BatchSeq(out, PLAN.batches())


def run(stage: str, inputs, batch=None, **config):
    spec = load_registry().get(stage)
    return spec.load_run()(inputs, build_config(spec, config, f"stages.{stage}"),
                           StageContext(node=stage, stage=stage, batch=batch))


class TestStitchConformance(StageConformance):
    stage_name = "stitch"
    sensitive = ("taper", 0.25)

    def make_inputs(self):
        return {"windows": windows((0.0, 0.01, -0.01, 0.02))}


class TestCutConformance(StageConformance):
    stage_name = "cut"

    def make_inputs(self):
        t = np.arange(FRAMES_US[0], FRAMES_US[-1] + 1, 1_000, dtype=np.int64)
        return {"motion": PoseSequence(t_us=t, poses=truth(t), status="stitched"), "batches": PLAN}


def test_windows_that_agree_stitch_to_the_motion_itself_over_the_whole_recording():
    motion = run("stitch", {"windows": windows()})["motion"]
    t = np.arange(FRAMES_US[0], FRAMES_US[-1] + 1, 1_000, dtype=np.int64)
    assert np.array_equal(motion.t_us, t)
    np.testing.assert_allclose(motion.poses, truth(t), atol=1e-12)


def test_windows_that_disagree_blend_between_them_without_a_step():
    """Offsets 0, 0.02, -0.02, 0.04 rad on every parameter: the blend stays within the offsets of the windows that
    cover a frame, each batch's middle leans to its own window's offset, and no 1 ms step exceeds the motion's own
    steps by more than the offsets' spread spread over a window's taper."""
    offsets = (0.0, 0.02, -0.02, 0.04)
    motion = run("stitch", {"windows": windows(offsets)})["motion"]
    t = np.asarray(motion.t_us)
    blend = (motion.poses - truth(t))[:, 0]  # the same on every parameter
    np.testing.assert_allclose(motion.poses - truth(t), np.repeat(blend[:, None], 33, axis=1), atol=1e-12)
    assert blend.min() >= min(offsets) - 1e-12 and blend.max() <= max(offsets) + 1e-12
    for k in range(len(PLAN)):
        b = PLAN.batch(k)
        middle = blend[np.searchsorted(t, (b.t0_us + b.t1_us) // 2)]
        others = [offsets[j] for j in (k - 1, k + 1) if 0 <= j < len(PLAN)]
        assert abs(middle - offsets[k]) < min(abs(o - offsets[k]) for o in others), (k, middle)
    assert np.abs(np.diff(blend)).max() < 0.06 / 40  # 0.06 rad of spread over the 40 ms a taper rises in, at most


def test_two_chunks_windows_hand_over_across_their_whole_overlap():
    """Two 1.16 s windows that overlap by 160 ms (two chunks' windows across their margins) and disagree by 1 rad:
    the later window takes over across the whole 160 ms (weights summing to 1 there, the blend's steepest slope that
    of the quintic smoothstep, 1.875 rad over 160 ms), not within a few tens of ms in its middle as bumps over each
    whole window would (the 2 s seam of a real recording: a 0.5 rad disagreement became a 55 rad/s turn)."""
    from eventcap_spline.stitch import blend, ramps_us, window_weights

    t1 = np.arange(920_000, 2_080_001, 1000, dtype=np.int64)
    t2 = np.arange(1_920_000, 3_080_001, 1000, dtype=np.int64)
    ws = [(t1, np.zeros((t1.size, 33))), (t2, np.ones((t2.size, 33)))]
    assert ramps_us([(920_000, 2_080_000), (1_920_000, 3_080_000)], 0.5) == [(None, 160_000), (160_000, None)]
    t, P = blend(ws, 0.5)
    x = P[:, 27]
    rate = np.abs(np.diff(x)) / 1e-3  # rad/s
    assert rate.max() == pytest.approx(1.875 / 0.16, rel=0.01)
    assert np.all(x[t <= 1_920_000] == 0.0) and np.all(x[t >= 2_080_000] == 1.0)
    assert x[np.searchsorted(t, 2_000_000)] == pytest.approx(0.5, abs=1e-9)
    total = np.zeros(t.size)
    for idx, w in window_weights(ws, 0.5, t):
        total[idx] += w
    inside = (t >= 1_920_000) & (t <= 2_080_000)
    np.testing.assert_allclose(total[inside], 1.0, atol=1e-12)


def test_cut_gives_each_batch_its_own_frames_ends_included():
    t = np.arange(FRAMES_US[0], FRAMES_US[-1] + 1, 1_000, dtype=np.int64)
    motion = PoseSequence(t_us=t, poses=truth(t), status="stitched")
    for k in range(len(PLAN)):
        b = PLAN.batch(k)
        poses = run("cut", {"motion": motion, "batches": PLAN}, batch=b)["poses"]
        assert poses.t_us[0] == b.t0_us and poses.t_us[-1] == b.t1_us and poses.t_us.size == 41
        np.testing.assert_array_equal(poses.poses, truth(poses.t_us))
        assert poses.status == "stitched"
    from eventcap.core.stage import StageFailed

    short = PoseSequence(t_us=t[:50], poses=truth(t[:50]), status="stitched")
    with pytest.raises(StageFailed, match=r"cut: the stitched motion has no frames spanning batch 2 \[85000, 125000\]"):
        run("cut", {"motion": short, "batches": PLAN}, batch=PLAN.batch(2))


def test_windows_that_disagree_raise_the_sigma_by_their_spread_where_they_overlap():
    """Given the body, each joint's σ where windows overlap is the mixture's: its blended σ and the windows' spread
    about the blend added as variances (each window's joints relative to their mean over the joints). Windows that
    agree keep the blended σ; a frame one window alone holds keeps its σ; the spread of two windows at the frame
    where their weights are equal is half their (translation-free) distance."""
    from eventcap.body.kinematics import joint_positions
    from helpers.poses import small_template

    tpl = small_template()
    seq = windows((0.0, 0.0, 0.3, 0.0))  # batch 2's window turns every joint by 0.3 rad more
    seq = BatchSeq([PoseSequence(t_us=p.t_us, poses=p.poses, sigma_mm=np.full((p.t_us.size, 24), 10.0, np.float32),
                                 status=p.status, iterations=p.iterations) for p in seq], seq.batches)
    alone = run("stitch", {"windows": seq})["motion"]
    both = run("stitch", {"windows": seq, "template": tpl})["motion"]
    np.testing.assert_allclose(alone.sigma_mm, 10.0, rtol=1e-6)  # without the body: the σ blended alone
    np.testing.assert_allclose(both.poses, alone.poses)  # the motion itself does not change
    extra = np.sqrt(np.maximum(both.sigma_mm.astype(float) ** 2 - 100.0, 0.0))
    t = np.asarray(both.t_us)
    only_first = t < PLAN.batch(1).t0_us  # window 0 (batches 0..1) and window 1 (0..2) agree there: no spread
    assert np.all(extra[only_first] < 1e-3)
    assert extra.max() > 50.0  # 0.3 rad over the limbs' lengths
    # at a frame windows 1, 2 and 3 all hold: the weighted RMS of their joints about their weighted mean
    from eventcap_spline.stitch import window_weights

    k = int(np.searchsorted(t, PLAN.batch(2).t0_us + 20_000))
    ws = [(np.asarray(p.t_us), np.asarray(p.poses)) for p in seq]
    weights = [float(w[idx == k][0]) if np.any(idx == k) else 0.0 for idx, w in window_weights(ws, 0.5, t)]
    J = [joint_positions(truth(t[k:k + 1]) + off, tpl)[0] * 1000.0 for off in (0.0, 0.0, 0.3, 0.0)]
    J = np.stack([j - j.mean(axis=0) for j in J])
    a = np.asarray(weights) / np.sum(weights)
    mean = np.tensordot(a, J, axes=1)
    expect = np.sqrt(np.tensordot(a, np.sum((J - mean) ** 2, axis=-1), axes=1))
    assert sum(w > 0 for w in weights) == 3
    np.testing.assert_allclose(extra[k], expect, rtol=1e-3, atol=1e-2)


def test_windows_that_agree_keep_their_sigma_given_the_body():
    from helpers.poses import small_template

    seq = windows()
    seq = BatchSeq([PoseSequence(t_us=p.t_us, poses=p.poses, sigma_mm=np.full((p.t_us.size, 24), 12.0, np.float32),
                                 status=p.status, iterations=p.iterations) for p in seq], seq.batches)
    motion = run("stitch", {"windows": seq, "template": small_template()})["motion"]
    np.testing.assert_allclose(motion.sigma_mm, 12.0, atol=1e-3)


def test_windows_apart_in_place_or_pose_are_named_as_seams_given_the_body(caplog):
    """Given the body, each seam's disagreement in the middle of the overlap is measured (pose: the joints' RMS
    distance with each body's mean removed; place: between the means) and a seam beyond 50 mm in pose or 100 mm in
    place is named in a warning: a root moved 0.3 m by one window is 300 mm in place, 0 in pose; windows that agree
    are not named."""
    import logging

    from helpers.poses import small_template

    tpl = small_template()
    spec = load_registry().get("stitch")
    for shift, apart in ((0.0, 0), (0.3, 2)):
        seq = windows()
        moved = [np.array(p.poses) for p in seq]
        moved[2][:, 30] += shift  # batch 2's window puts the body 0.3 m along x
        seq = BatchSeq([PoseSequence(t_us=p.t_us, poses=m, status=p.status, iterations=p.iterations)
                        for p, m in zip(seq, moved)], seq.batches)
        ctx = StageContext(node="stitch", stage="stitch")
        caplog.clear()
        with caplog.at_level(logging.WARNING):
            spec.load_run()({"windows": seq, "template": tpl}, build_config(spec, {}, "stages.stitch"), ctx)
        assert ctx.stats["seam_shift_mm_max"] == pytest.approx(1000.0 * shift, abs=0.5)
        assert ctx.stats["seam_pose_mm_max"] < 0.5
        assert ctx.stats["seams_apart"] == apart and ctx.stats["seams"] == 3  # apart: windows 1-2 and 2-3
        named = [r.getMessage() for r in caplog.records if "solved their shared stretch differently" in r.getMessage()]
        assert len(named) == (1 if apart else 0)
        if apart:
            assert "300 mm in place" in named[0] and "2 of 3 seams" in named[0]
