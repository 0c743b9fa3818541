"""Fusing detections through event odometry (not in the paper; plugins/eventcap_solve/fusion.py): the solve's
odometry mode, the pose graph, its estimated weight, placing batches, and pipeline=fused end to end."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from eventcap.artifacts import BatchPlan
from eventcap.artifacts.pose import PoseSequence
from eventcap.body.motions import motion_poses
from eventcap.core.config import build_config
from eventcap.core.registry import load_registry
from eventcap.core.stage import StageContext
from eventcap.core.testing import StageConformance
from eventcap_solve.batch import FrameDetections, select_detections, solve_batch
from eventcap_solve.fusion import innovation_rho, place, pose_graph
from helpers.batch_scene import N, joint_error_mm, problem, scene
from helpers.spline_scene import BatchSeq


def _objective(X, fits, steps, rho):
    return float(np.sum((X - fits) ** 2) + rho * np.sum((np.diff(X, axis=0) - steps) ** 2))


# ------------------------------------------------------------------------------------------------ odometry mode
def test_odometry_mode_follows_the_events_from_the_first_fit_and_ignores_frame_n():
    rec, det, t_us, S, xy, valid = scene()
    prob = problem(mode="odometry", **{"tracks.edge_margin_px": 0.0})
    ends = select_detections(det, t_us[[0, N]])
    res = solve_batch(prob, t_us, xy, valid, ends)
    fit0, _, _ = prob.fit_frame(ends, 0)
    np.testing.assert_array_equal(res.poses[0], fit0)  # anchored exactly at S_0's fit
    # Exact detections and exact tracks: the events alone carry the pose most of the way to the true end pose
    # (measured: 96 mm of motion, 41 mm left with 2 ICP rounds, 27 mm with 8: what 2D tracks do not show of the
    # motion in depth stays).
    moved = joint_error_mm(rec, res.poses[-1:], S[-1:])[0]
    still = joint_error_mm(rec, S[:1], S[-1:])[0]
    assert still > 50.0 and moved < 0.5 * still, (moved, still)
    # Nothing of frame N's detection enters: a different detection there gives bit-identical poses.
    kp, j3 = ends.keypoints_2d.copy(), ends.joints_3d.copy()
    kp[1] += 25.0
    j3[1] += 0.1
    other = FrameDetections(kp, ends.confidence_2d, j3, ends.confidence_3d)
    assert np.array_equal(solve_batch(prob, t_us, xy, valid, other).poses, res.poses)


# ------------------------------------------------------------------------------------------------ pose graph
def test_pose_graph_keeps_the_fits_without_odometry_weight():
    rng = np.random.default_rng(0)
    fits, steps = rng.normal(size=(7, 33)), rng.normal(size=(6, 33))
    np.testing.assert_allclose(pose_graph(fits, steps, 0.0), fits, atol=1e-12)


def test_pose_graph_with_exact_odometry_averages_the_fit_errors():
    rng = np.random.default_rng(1)
    truth = np.cumsum(rng.normal(size=(11, 33)), axis=0)
    err = rng.normal(scale=0.1, size=truth.shape)
    # exact steps tie all frames together: every frame gets the mean fit error of the frames that have a fit
    X = pose_graph(truth + err, np.diff(truth, axis=0), 1e8)
    np.testing.assert_allclose(X, truth + err.mean(axis=0), atol=1e-5)
    fits = truth + err
    fits[-1] = np.nan  # the last frame has no fit (fuse: no batch starts there): reached by odometry alone
    X = pose_graph(fits, np.diff(truth, axis=0), 1e8, fit_weights=np.r_[np.ones(10), 0.0])
    np.testing.assert_allclose(X, truth + err[:-1].mean(axis=0), atol=1e-5)


def test_pose_graph_is_the_minimum_of_its_objective():
    rng = np.random.default_rng(2)
    fits, steps, rho = rng.normal(size=(9, 4)), rng.normal(size=(8, 4)), 2.5
    X = pose_graph(fits, steps, rho)
    best = _objective(X, fits, steps, rho)
    h = 1e-6
    for i, j in [(0, 0), (4, 2), (8, 3)]:  # zero gradient, by central differences
        E = np.zeros_like(X)
        E[i, j] = h
        grad = (_objective(X + E, fits, steps, rho) - _objective(X - E, fits, steps, rho)) / (2 * h)
        assert abs(grad) < 1e-6
    for _ in range(20):  # and no random nearby point is lower
        assert _objective(X + rng.normal(scale=1e-2, size=X.shape), fits, steps, rho) > best


def test_innovation_rho_recovers_the_variance_ratio_without_ground_truth():
    rng = np.random.default_rng(3)
    truth = np.cumsum(rng.normal(scale=0.2, size=(4001, 33)), axis=0)
    for sigma_e, sigma_o in [(0.1, 0.05), (0.05, 0.1)]:
        fits = truth + rng.normal(scale=sigma_e, size=truth.shape)
        steps = np.diff(truth, axis=0) + rng.normal(scale=sigma_o, size=(4000, 33))
        expected = sigma_e ** 2 / sigma_o ** 2  # 4 and 0.25
        assert abs(innovation_rho(fits, steps) / expected - 1) < 0.1
    with pytest.raises(ValueError, match="at least 3 steps"):
        innovation_rho(truth[:3], np.diff(truth[:3], axis=0))


def test_place_anchors_both_ends_and_keeps_the_shape_when_it_fits():
    rng = np.random.default_rng(4)
    t = 1000 * np.arange(41, dtype=np.int64)
    shape = np.cumsum(rng.normal(size=(41, 33)), axis=0)
    shape -= shape[0]
    x0, x1 = rng.normal(size=33), rng.normal(size=33)
    P = place(x0, x1, shape, t)
    np.testing.assert_allclose(P[0], x0, atol=1e-12)
    np.testing.assert_allclose(P[-1], x1, atol=1e-12)
    np.testing.assert_allclose(place(x0, x0 + shape[-1], shape, t), x0 + shape, atol=1e-12)


# ------------------------------------------------------------------------------------------------ the stages
FRAMES_US = 5_000 + 40_000 * np.arange(5, dtype=np.int64)  # 4 batches of 40 ms


def odometry(start_error: float = 0.0) -> BatchSeq:
    """What the solve gives in mode odometry: each batch's 1 ms poses of a known motion, from its first frame's fit
    (off by ``start_error`` rad on every parameter, a different sign per batch) following the events exactly."""
    plan = BatchPlan.between_frames(FRAMES_US)
    out = []
    for k in range(len(plan)):
        b = plan.batch(k)
        t = np.arange(b.t0_us, b.t1_us + 1, 1_000, dtype=np.int64)
        S = motion_poses("jumping_jack", t * 1e-6) + start_error * (-1) ** k
        out.append(PoseSequence(t_us=t, poses=S, status="Solve_Succeeded", iterations=7))
    return BatchSeq(out, plan.batches())


def run_stage(stage: str, inputs, **config):
    spec = load_registry().get(stage)
    return spec.load_run()(inputs, build_config(spec, config, f"stages.{stage}"), StageContext(node=stage, stage=stage))


class TestFuseConformance(StageConformance):
    stage_name = "fuse"
    config_overrides = {"rho": 1.0}
    sensitive = ("rho", 4.0)

    def make_inputs(self):
        return {"odometry": odometry(0.01)}


class TestPlaceConformance(StageConformance):
    stage_name = "place"

    def make_inputs(self):
        odo = odometry(0.01)
        anchors = run_stage("fuse", {"odometry": odo}, rho=1.0)["anchors"]
        return {"odometry": odo[1], "anchors": anchors}


def test_fuse_and_place_average_the_fits_errors_through_exact_odometry():
    """Fits off by +-0.01 rad by turns, exact steps between them: the fused anchors lie nearer the truth than the fits
    (the errors average out through the steps), at every frame; place puts each batch's trajectory on its two
    anchors and keeps its shape."""
    odo = odometry(0.01)
    anchors = run_stage("fuse", {"odometry": odo}, rho=10.0)["anchors"]
    assert np.array_equal(anchors.t_us, FRAMES_US)
    err = np.abs(anchors.poses - motion_poses("jumping_jack", FRAMES_US * 1e-6))
    assert np.all(np.isfinite(anchors.poses)) and err.max() < 0.5 * 0.01
    for k in range(len(odo)):
        placed = run_stage("place", {"odometry": odo[k], "anchors": anchors})["poses"]
        np.testing.assert_allclose(placed.poses[[0, -1]], anchors.poses[[k, k + 1]], atol=1e-12)
        shape = odo[k].poses - odo[k].poses[0]
        drift = placed.poses - placed.poses[0] - shape  # the end mismatch, spread linearly in time
        np.testing.assert_allclose(drift, np.linspace(0, 1, 41)[:, None] * drift[-1], atol=1e-12)
        assert placed.status == odo[k].status and placed.iterations == 7


# ------------------------------------------------------------------------------------------------ pipeline
@pytest.mark.slow  # about a minute: pipeline=fused (not the default) end to end, twice
def test_fused_pipeline_runs_and_explains_too_few_batches(tmp_path):
    def run(name, *overrides):
        p = subprocess.run([sys.executable, "-m", "eventcap.apps.cli", "run", "pipeline=fused", "experiment=quick",
                            "source.duration_s=0.17", "template=procedural", "template.target_faces=3000",
                            "source.n_track_points=60",
                            "outputs.video=false", f"hydra.run.dir=runs/{name}", *overrides],
                           cwd=tmp_path, capture_output=True, text=True, timeout=900)
        return p, tmp_path / "runs" / name

    p, d = run("four")
    assert p.returncode == 0, p.stderr[-3000:]
    nodes = json.loads((d / "run.json").read_text())["nodes"]
    assert nodes["odometry"]["computed"] == 4 and nodes["fuse"]["computed"] == 1 and nodes["solve"]["computed"] == 4
    ae = json.loads((d / "metrics.json").read_text())["evaluate.metrics"]["AE_mm"]
    assert 1.0 < ae < 150.0
    motion = np.load(d / "motion.npz")
    assert motion["poses"].shape == (161, 33) and np.isfinite(motion["poses"]).all()
    # Two batches give one step between fitted frames: too few to estimate the weight, and the error says what
    # to set; the odometry batches come from the cache.
    p, d = run("two", "batches=0:2")
    assert p.returncode == 1
    assert "give stages.fuse.rho > 0" in p.stdout + p.stderr
    assert json.loads((d / "run.json").read_text())["nodes"]["odometry"]["cached"] == 2
    p, d = run("two_rho", "batches=0:2", "stages.fuse.rho=2")
    assert p.returncode == 0, p.stderr[-3000:]
