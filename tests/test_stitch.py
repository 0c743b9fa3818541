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
