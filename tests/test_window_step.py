"""Windows that advance by several batches (stages.solve.window_step): the batches are cut into runs of window_step,
each run kept by one window solved by its middle batch; the other batches solve nothing (status in_window, no
frames: not a gap) and stitch blends the windows that exist."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from eventcap.artifacts import BatchPlan
from eventcap.artifacts.pose import PoseSequence
from eventcap.core.stage import StageFailed
from eventcap_spline._impl import kept_by, window_of, window_schedule, window_role
from helpers.spline_scene import run_stage, stage_inputs, stitch
from helpers.runs import TINY_SPLINE_RUN


def test_window_role_cuts_the_batches_into_runs_each_kept_by_its_middle_batchs_window():
    # 10 batches, windows of 5, step 3: runs 0-2, 3-5, 6-8, 9 solved by batches 1, 4, 7, 9; but batch 9's window
    # (shifted inwards: 5..9) is batch 7's, so runs 6-8 and 9 are one, kept by batch 7's window solved once
    roles = [window_role(10, k, 2, 3) for k in range(10)]
    assert [k for k, r in enumerate(roles) if r is not None] == [1, 4, 7]
    assert roles[1] == (0, 4, 0, 2) and roles[4] == (2, 6, 3, 5) and roles[7] == (5, 9, 6, 9)
    assert [kept_by(10, k, 2, 3) for k in range(10)] == [1, 1, 1, 4, 4, 4, 7, 7, 7, 7]
    assert window_schedule(24, 2, 3) == tuple((c, *window_of(24, c, 2), c - 1, c + 1) for c in range(1, 24, 3))
    # step 2: the earlier of the two middles solves; batches 0 and 2 both have the window 0..4 (one run 0-3), and so
    # have batches 8 and 10 of 11 (6..10)
    assert window_schedule(11, 2, 2) == ((0, 0, 4, 0, 3), (4, 2, 6, 4, 5), (6, 4, 8, 6, 7), (8, 6, 10, 8, 10))
    # step 1: every batch its own window, keeping itself (the plan before window_step), even where windows coincide
    assert [window_role(10, k, 2, 1) for k in range(10)] == [(*window_of(10, k, 2), k, k) for k in range(10)]


@pytest.mark.parametrize("n", [1, 2, 3, 5, 7, 10, 24, 25])
@pytest.mark.parametrize("half", [0, 1, 2, 3])
def test_every_batch_is_kept_by_exactly_one_window_that_covers_it(n, half):
    for step in range(1, max(1, 2 * half) + 1):
        keepers, windows = {}, []
        for k in range(n):
            role = window_role(n, k, half, step)
            if role is None:
                continue
            a, z, ka, kz = role
            assert ka <= k <= kz and a <= ka and kz <= z and (a, z) == window_of(n, k, half)
            windows.append((a, z))
            for j in range(ka, kz + 1):
                assert j not in keepers, (n, half, step, j)
                keepers[j] = k
        assert sorted(keepers) == list(range(n)), (n, half, step)
        assert len(windows) == (n if step == 1 else len(set(windows)))  # no window solved twice (step > 1)
        assert len(windows) <= -(-n // step)  # at most ceil(n / step) windows
        assert all(kept_by(n, j, half, step) == keepers[j] for j in range(n))


def test_window_role_refuses_a_step_that_leaves_windows_apart():
    with pytest.raises(ValueError, match=r"window step 5: expected 1 .. max\(1, 2·half_window\) = 4"):
        window_role(10, 0, 2, 5)
    with pytest.raises(ValueError, match="window step 0"):
        window_role(10, 0, 2, 0)
    assert window_role(3, 0, 0, 1) == (0, 0, 0, 0)


def test_the_stage_refuses_a_window_step_beyond_twice_the_half_window():
    inputs = stage_inputs()
    b = inputs["batches"].batch(1)
    with pytest.raises(StageFailed, match=r"stages.solve.window_step: expected at most max\(1, 2·half_window\) = 2 "
                                          r"\(neighbouring windows must overlap to be blended\), got 3") as err:
        run_stage(inputs, b, half_window=1, window_step=3)
    assert err.value.status == "invalid_config"
    with pytest.raises(ValueError, match=r"stages.solve.window_step: expected an integer >= 1, got 0"):
        run_stage(inputs, b, window_step=0)


def test_a_batch_another_window_keeps_solves_nothing_and_says_which():
    inputs = stage_inputs()  # 3 batches; half_window 1, step 2: batch 0 keeps 0-1, batch 2 keeps itself
    out, ctx = run_stage(inputs, inputs["batches"].batch(1), half_window=1, window_step=2)
    p = out["poses"]
    assert p.status == "in_window" and p.t_us.shape == (0,) and p.poses.shape == (0, 33)
    assert ctx.stats["kept_by"] == 0 and "solve_s" not in ctx.stats


def _windows(n: int, step: int, half: int, offsets: dict[int, float] | None = None, gap: int | None = None):
    """Windows of a smooth motion over n batches of 40 ms, as the spline stage gives them with window_step ``step``:
    the solving batches' windows (truth + their offset; NaN for ``gap``), the others empty (in_window)."""
    t0 = 5_000 + 40_000 * np.arange(n + 1)
    plan = BatchPlan.between_frames(t0)
    t = np.arange(t0[0], t0[-1] + 1, 1_000)
    truth = np.zeros((t.size, 33))
    truth[:, :27] = 0.3 * np.sin(2 * np.pi * 1.5 * t[:, None] * 1e-6 + np.arange(27)[None, :])
    truth[:, 30:] = [0.1, 0.9, 3.0]
    out = []
    for k in range(n):
        role = window_role(n, k, half, step)
        if role is None:
            out.append(PoseSequence(t_us=np.zeros(0, dtype=np.int64), poses=np.zeros((0, 33)), status="in_window"))
            continue
        a, z = role[:2]
        sel = (t >= plan.t0_us[a]) & (t <= plan.t1_us[z])
        p = truth[sel] + (offsets or {}).get(k, 0.0)
        if k == gap:
            p[:] = np.nan
        out.append(PoseSequence(t_us=t[sel], poses=p, status="gap" if k == gap else "Solve_Succeeded",
                                iterations=1))
    return plan, t, truth, out


def test_stitch_with_step_three_covers_every_batch_and_blends_the_windows():
    """10 batches, windows of 5 batches solved by batches 1, 4, 7 (keeping 0-2, 3-5, 6-9): the blend holds every tracking frame of the
    recording; with exact windows it is the truth; with the window of batch 4 off by 0.03 rad the motion is off by
    at most that, all of it only where that window alone has weight, and each batch's cut spans the batch."""
    plan, t, truth, windows = _windows(10, 3, 2)
    motion, cut, ctx = stitch(windows, plan)
    assert motion.t_us.tolist() == t.tolist() and np.isfinite(motion.poses).all()
    np.testing.assert_allclose(motion.poses, truth, atol=1e-12)
    assert ctx.stats["windows"] == 3 and "gap_windows" not in ctx.stats and ctx.stats["seam_rad_max"] == 0
    assert [(c.t_us[0], c.t_us[-1]) for c in cut] == list(zip(plan.t0_us.tolist(), plan.t1_us.tolist()))
    assert all(c.status == "stitched" for c in cut)
    _, _, _, off = _windows(10, 3, 2, offsets={4: 0.03})
    motion, cut, ctx = stitch(off, plan)
    err = motion.poses[:, :27] - truth[:, :27]
    assert err.min() >= -1e-12 and err.max() == pytest.approx(0.03)
    assert ctx.stats["seam_rad_max"] == pytest.approx(0.03)
    # batch 4's own interval is where its window is alone or weighs most: the error is largest there
    inner = (t >= plan.t0_us[4]) & (t <= plan.t1_us[4])
    assert err[inner].mean() > err[~inner].mean()
    assert np.abs(np.diff(err, axis=0)).max() < 0.03 / 20  # no step: blended over more than 20 ms


def test_a_gap_window_beside_skipped_batches_leaves_no_gap_where_other_windows_see():
    """Batch 4's window (batches 2..6) saw nothing (status gap): its run 3..5 is still covered by the windows of
    batches 1 (0..4) and 7 (5..9), so the motion has no gap; the skipped (in_window) batches are not gaps."""
    plan, t, truth, windows = _windows(10, 3, 2, gap=4)
    motion, cut, ctx = stitch(windows, plan)
    assert np.isfinite(motion.poses).all()
    np.testing.assert_allclose(motion.poses, truth, atol=1e-12)
    assert ctx.stats["gap_windows"] == [4] and "gap_frames" not in ctx.stats
    assert [c.status for c in cut] == ["stitched"] * 10
    # with windows of 3 batches (half 1, step 2: batches 0, 2, 4, 6, 8) a gap in batch 4's window (3..5) leaves
    # batch 4 to no one: a gap there (but at its ends, which the neighbours' windows share), never filled in; the
    # skipped batches 3 and 5 are seen by their neighbours' windows
    plan, t, truth, windows = _windows(10, 2, 1, gap=4)
    motion, cut, ctx = stitch(windows, plan)
    ok = np.isfinite(motion.poses).all(axis=1)
    assert not ok[(t > plan.t0_us[4]) & (t < plan.t1_us[4])].any()
    assert ok[t <= plan.t0_us[4] - 10_000].all() and ok[t >= plan.t1_us[4] + 10_000].all()
    assert [c.status for c in cut][3:6] == ["stitched", "stitched, with a gap", "stitched"]
    assert ctx.stats["gap_windows"] == [4] and ctx.stats["gap_frames"] == 39  # batch 4 but its two end frames


def test_stitch_refuses_a_batch_no_window_covers_and_an_in_window_batch_with_frames():
    plan, t, truth, windows = _windows(10, 3, 2)
    lost = list(windows)
    lost[7] = dataclasses.replace(lost[7], t_us=np.zeros(0, dtype=np.int64), poses=np.zeros((0, 33)),
                                  status="in_window")
    with pytest.raises(StageFailed, match=r"stitch: no window covers batch 7 \[285000, 325000\] us"):
        stitch(lost, plan)
    odd = list(windows)
    odd[0] = dataclasses.replace(windows[1], status="in_window")
    with pytest.raises(StageFailed, match=r"batch 0 says another batch's window keeps it \(status in_window\) but "
                                          r"holds 201 frames"):
        stitch(odd, plan)


def test_a_small_run_with_window_step_three_estimates_every_frame(tmp_path):
    """A 0.28 s capture (7 batches), windows of 5 batches advancing by 3 (batch 1 solves 0..4 keeping 0-2, batch 4
    solves 2..6 keeping 3-6, as batch 6's window would be the same): every tracking
    frame of the motion is estimated, and its error against the truth is in the range of the solve's."""
    from eventcap.apps.cli import main

    run_dir = tmp_path / "run"
    code = main(["run", *TINY_SPLINE_RUN, "source.duration_s=0.3", "stages.solve.half_window=2",
                 "stages.solve.window_step=3", f"cache_dir={tmp_path / 'cache'}", f"hydra.run.dir={run_dir}"])
    assert code == 0
    with np.load(run_dir / "motion.npz") as z:
        poses, t, estimated = z["poses"], z["t_us"], z["estimated"]
    assert t.size == 281 and np.isfinite(poses).all() and estimated.all()
    record = json.loads((run_dir / "run.json").read_text())
    assert record["nodes"]["solve"]["computed"] == 7
    from eventcap.core.cache import Cache

    stitched = Cache(str(tmp_path / "cache")).lookup("stitch", record["nodes"]["stitch"]["keys"][0]).manifest["stats"]
    assert stitched["windows"] == 2 and "gap_windows" not in stitched
    metrics = json.loads((run_dir / "metrics.json").read_text())["evaluate.metrics"]
    assert 5 < metrics["AE_mm"] < 60 and np.isfinite(metrics["MPJVE_mm_s"])


def test_the_geometry_digest_is_computed_once_and_follows_the_geometry():
    from helpers.poses import posed_recording

    tpl = posed_recording("high_knees", n_frames=2, speed=1.0, with_template=True).template
    d = tpl.geometry_digest()
    assert tpl.__dict__["_geometry_digest"] == d and tpl.geometry_digest() == d and len(d) == 40
    moved = dataclasses.replace(tpl, vertices=tpl.vertices + 0.01)
    assert moved.geometry_digest() != d and "_geometry_digest" not in dataclasses.replace(tpl).__dict__
