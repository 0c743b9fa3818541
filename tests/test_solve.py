"""The batch pose optimisation (paper Sec. 3.2, Eq. 3-8): derivatives, accuracy against ground truth, failures."""

from __future__ import annotations


import numpy as np
import pytest

from eventcap.artifacts import Batch
from eventcap.body.kinematics import joint_positions
from eventcap.body.skeleton import NUM_JOINTS, pose_bounds
from eventcap.core.stage import StageContext, StageFailed
from eventcap.core.testing import StageConformance
from eventcap.energy.cor import EventCorrespondences
from eventcap.energy.correspondences import find_correspondences, temporal_indicator
from eventcap.energy.errors import EnergyError, SolveFailed
from eventcap.energy.window import Estimate, Tracks, WindowInputs
from eventcap.energy.kernels import project_derivatives
from eventcap_solve.batch import BatchProblem, interpolate_poses, select_detections, solve_batch
from eventcap_solve.spec import BatchSolveConfig
from helpers.batch_scene import EXACT, N, T0, joint_error_mm, problem, scene, stage_inputs
from helpers.poses import detect


# ------------------------------------------------------------------------------------------------ derivatives
def test_projection_derivatives_match_finite_differences():
    rec = scene()[0]
    rng = np.random.default_rng(0)
    pts = np.array([0.0, 1.0, 0.0]) + rng.uniform(-0.8, 0.8, (20, 3))
    uv, J, H = project_derivatives(rec.camera, pts, 2)
    np.testing.assert_allclose(uv, rec.camera.project(pts), atol=1e-9)
    h = 1e-6
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        up, Jp = project_derivatives(rec.camera, pts + e, 1)
        um, Jm = project_derivatives(rec.camera, pts - e, 1)
        np.testing.assert_allclose(J[:, :, k], (up - um) / (2 * h), rtol=1e-6, atol=1e-4)
        np.testing.assert_allclose(H[:, :, :, k], (Jp - Jm) / (2 * h), rtol=1e-5, atol=1e-1)
    assert np.abs(J).max() > 50  # px per metre at 3 m: the check is not vacuous


def test_correspondences_reproject_exactly_where_found():
    """A correspondence's point, posed with the pose it was found at, lies under its pixel (module doc)."""
    rec, det, t_us, S, xy, valid = scene()
    corr = find_correspondences(rec.template, rec.camera, S, xy, valid, edge_margin_px=0.0)
    cor = EventCorrespondences(EventCorrespondences.Config(weight=1.0), rec.template, rec.camera, N + 1)
    inputs = WindowInputs(int(t_us[0]), int(t_us[-1]), tracks=Tracks(t_us, xy, valid, 0.0))
    cor.collect(inputs)
    rows = {int(t): i for i, t in enumerate(t_us)}
    est = Estimate(lambda t, d=0: S[[rows[int(v)] for v in np.asarray(t).ravel()]], 0, inputs, rec.template,
                   rec.camera)
    cor.relinearize(est)
    assert cor.corr.n == corr.n and np.array_equal(cor.corr.frame, corr.frame)  # the estimate's correspondences
    e_cor = cor.value(S)
    # Ground-truth tracks and ground-truth poses: E_cor vanishes (up to float32 pixel storage).
    assert e_cor / corr.n < (0.01 / np.sqrt(rec.camera.fx * rec.camera.fy)) ** 2
    assert set(np.unique(corr.frame - corr.source)) == {-1, 1}


def test_temporal_indicator_holds_parts_without_correspondences():
    rec, det, t_us, S, xy, valid = scene()
    corr = find_correspondences(rec.template, rec.camera, S, xy, valid)
    phi = temporal_indicator(corr, N + 1)
    assert phi.shape == (N, NUM_JOINTS)
    assert not phi[:, 0].any()  # the root is observed by every correspondence
    none = temporal_indicator(corr.__class__.empty(), N + 1)
    assert none.all()  # nothing observed: every joint held


# ------------------------------------------------------------------------------------------------ accuracy
def test_batch_beats_linear_on_fast_motion_with_exact_data():
    rec, det, t_us, S, xy, valid = scene()
    ends = select_detections(det, t_us[[0, N]])
    # Exact tracks: no need to keep away from silhouette edges (on a 240x180 image that drops most limb points).
    err = {m: joint_error_mm(rec, solve_batch(problem(mode=m, **{"tracks.edge_margin_px": 0.0}), t_us, xy, valid, ends).poses, S)
           for m in ("linear", "per_frame", "batch")}
    # Exact detections: linear interpolation's error is the motion's non-linearity between the frames.
    assert err["linear"].mean() > 3.0
    assert err["linear"][[0, N]].max() < 1.0
    assert err["batch"].mean() < 0.5 * err["linear"].mean(), {k: v.mean() for k, v in err.items()}
    # w/o_batch: each frame is pulled towards its neighbours' points as found on the interpolation, so it stays
    # near the interpolation (measured: within 2% of linear here); the joint solve is what integrates the tracks.
    assert err["batch"].mean() < 0.6 * err["per_frame"].mean() < 0.6 * 1.1 * err["linear"].mean()


def test_linear_mode_is_the_interpolated_end_fits():
    rec, det, t_us, S, xy, valid = scene()
    res = solve_batch(problem(mode="linear"), t_us, xy, valid, select_detections(det, t_us[[0, N]]))
    np.testing.assert_allclose(res.poses, interpolate_poses(res.poses[0], res.poses[-1], t_us), atol=1e-12)
    assert res.energies["n_correspondences"] == 0 and res.status == "Solve_Succeeded"  # mode linear: no search


def test_all_mode_fits_every_frame():
    rec, det, t_us, S, xy, valid = scene()
    with pytest.raises(EnergyError, match="needs detections at all 41"):
        solve_batch(problem(mode="all"), t_us, xy, valid, select_detections(det, t_us[[0, N]]))
    every = detect("simulated", rec, at="tracking", **EXACT)  # as if detected on latent images every 1 ms
    assert np.array_equal(every.t_us, np.arange(rec.frames.t_us[0], rec.frames.t_us[-1] + 1, 1000))
    res = solve_batch(problem(mode="all"), t_us, xy, valid, select_detections(every, t_us))
    assert joint_error_mm(rec, res.poses, S).max() < 1.0  # exact detections at every frame: exact poses
    assert len(res.solves) == N + 1


def test_solves_are_bit_identical():
    rec, det, t_us, S, xy, valid = scene()
    ends = select_detections(det, t_us[[0, N]])
    a = solve_batch(problem(icp_rounds=1), t_us, xy, valid, ends)
    b = solve_batch(problem(icp_rounds=1), t_us, xy, valid, ends)
    assert np.array_equal(a.poses, b.poses) and a.iterations == b.iterations


def test_joint_bounds_hold():
    rec, det, t_us, S, xy, valid = scene()
    lo, hi = pose_bounds()
    res = solve_batch(problem(), t_us, xy, valid, select_detections(det, t_us[[0, N]]))
    assert np.all(res.poses >= lo - 1e-9) and np.all(res.poses <= hi + 1e-9)


# ------------------------------------------------------------------------------------------------ failures
def test_nan_in_valid_track_fails_before_the_solver():
    rec, det, t_us, S, xy, valid = scene()
    bad = xy.copy()
    h = int(np.flatnonzero(valid[7])[0])
    bad[7, h] = np.nan
    with pytest.raises(EnergyError, match=f"track {h} has a non-finite position at tracking frame 7") as exc:
        solve_batch(problem(), t_us, bad, valid, select_detections(det, t_us[[0, N]]))
    assert exc.value.status == "invalid_input"


def test_nan_detection_with_confidence_fails():
    rec, det, t_us, S, xy, valid = scene()
    ends = select_detections(det, t_us[[0, N]])
    kp = ends.keypoints_2d.copy()
    kp[1, 4] = np.nan
    bad = ends.__class__(kp, ends.confidence_2d, ends.joints_3d, ends.confidence_3d)
    with pytest.raises(EnergyError, match="keypoints_2d is not finite at detection frame 1, entry 4") as exc:
        solve_batch(problem(), t_us, xy, valid, bad)
    assert exc.value.status == "invalid_input"


def test_impossible_bound_is_refused_with_the_parameter_named():
    rec = scene()[0]
    with pytest.raises(EnergyError, match=r"stages.solve.limits: lower bound above upper bound for pose parameter 1 "
                                          r"\(l_hip_abd\): 1.1 > 1.0") as exc:
        BatchProblem(rec.template, rec.camera, N + 1, BatchSolveConfig(limits={"l_hip_abd": [1.1, 1.0]}))
    assert exc.value.status == "invalid_bounds"


def test_iteration_cap_gives_a_failure_with_ipopts_status():
    rec, det, t_us, S, xy, valid = scene()
    with pytest.raises(SolveFailed, match="status Maximum_Iterations_Exceeded") as exc:
        solve_batch(problem(**{"ipopt.max_iter": 2}), t_us, xy, valid, select_detections(det, t_us[[0, N]]))
    assert exc.value.status == "Maximum_Iterations_Exceeded"


# ------------------------------------------------------------------------------------------------ the stage


class TestBatchStageConformance(StageConformance):
    stage_name = "batch"
    config_overrides = {"icp_rounds": 1, "tracks.max_tracks": 60}
    sensitive = ("terms.cor.weight", 10.0)
    insensitive = ("ipopt.max_iter", 50)

    def make_inputs(self):
        return stage_inputs()


def test_stage_records_solver_statistics():
    from eventcap.core.config import build_config
    from eventcap.core.registry import load_registry

    spec = load_registry().get("batch")
    ctx = StageContext(node="solve", stage="batch", batch=Batch(0, T0, T0 + 1000 * N, 0))
    out = spec.load_run()(stage_inputs(), build_config(spec, {"icp_rounds": 1}, "stages.solve"), ctx)["poses"]
    assert out.poses.shape == (N + 1, 33) and out.status == "Solve_Succeeded"
    assert out.iterations == ctx.stats["iterations"] > 0
    assert ctx.stats["n_correspondences"] > 0 and ctx.stats["solve_s"] > 0
    assert {"cor", "landmarks_2d", "joints_3d", "temp", "total"} <= set(out.energies)


# ------------------------------------------------------------------------------------------------ in the pipeline
@pytest.mark.slow  # about a minute; the default pipeline's (spline) is tests/test_spline_resume.py, in the default run
def test_failed_batches_are_recorded_and_only_they_are_recomputed(tmp_path):
    """An iteration cap of 2 fails the solve with IPOPT's status; raising it recomputes only the failed batch."""
    import json
    import subprocess
    import sys

    def run(name, *overrides):
        p = subprocess.run([sys.executable, "-m", "eventcap.apps.cli", "run", "pipeline=paper", "experiment=quick",
                            "source.duration_s=0.09", "template=procedural", "template.target_faces=3000",
                            "source.n_track_points=60", f"hydra.run.dir=runs/{name}",
                            *overrides], cwd=tmp_path, capture_output=True, text=True, timeout=600)
        return p, json.loads((tmp_path / "runs" / name / "run.json").read_text())["nodes"]["solve"]

    p, a = run("a", "batches=0:1")
    assert p.returncode == 0, p.stderr[-3000:]
    assert (a["computed"], a["cached"]) == (1, 0)
    p, b = run("b", "batches=0:2", "stages.solve.ipopt.max_iter=2")
    assert p.returncode == 1
    assert b["cached"] == 1 and b["computed"] == 0  # batch 0: the cap is not part of the key
    assert [(f["batch"], f["status"]) for f in b["failed"]] == [(1, "Maximum_Iterations_Exceeded")]
    log = p.stdout + p.stderr
    assert "solve batch 1" in log and "Maximum_Iterations_Exceeded" in log
    p, c = run("c", "batches=0:2")
    assert p.returncode == 0, p.stderr[-3000:]
    assert (c["cached"], c["computed"], c["failed"]) == (1, 1, [])
    # Solver statistics are kept in the cache manifest of each batch.
    from eventcap.core.cache import Cache

    stats = Cache(str(tmp_path / "runs" / "cache")).lookup("batch", c["keys"][1]).manifest["stats"]
    assert stats["iterations"] > 2 and stats["solve_s"] > 0 and stats["n_correspondences"] > 0


def test_neighbouring_batches_agree_on_their_shared_frame():
    """boundary=fixed: S_N of a batch is the fit of its second intensity frame, which is exactly S_0 of the next
    batch (same detections, same deterministic fit); free: the solve moves it."""
    rec, det, t_us, S, xy, valid = scene()
    prob = problem()
    ends = select_detections(det, t_us[[0, N]])
    res = solve_batch(prob, t_us, xy, valid, ends)
    next_start, _, _ = prob.fit_frame(select_detections(det, t_us[[N]]), 0)  # batch k+1's S_0
    np.testing.assert_array_equal(joint_positions(res.poses[-1], rec.template), joint_positions(next_start, rec.template))
    free = solve_batch(problem(boundary="free"), t_us, xy, valid, ends)
    assert np.abs(free.poses[-1] - res.poses[-1]).max() > 1e-6
    with pytest.raises(ValueError, match=r"stages.solve.boundary: expected one of fixed \| free, got 'loose'"):
        problem(boundary="loose")


def test_stage_joint_limit_overrides_are_applied_and_checked():
    from eventcap.core.config import build_config
    from eventcap.core.registry import load_registry
    from eventcap.energy.ipopt import PARAM_NAMES

    spec = load_registry().get("batch")
    run = spec.load_run()

    def solve(limits):
        cfg = build_config(spec, {"icp_rounds": 1, "tracks": {"max_tracks": 60}, "limits": limits}, "stages.solve")
        return run(stage_inputs(), cfg, StageContext(node="solve", stage="batch", batch=Batch(0, T0, T0 + 1000 * N, 0)))

    k = PARAM_NAMES.index("l_knee_flex")
    out = solve({"l_knee_flex": [0.0, 0.05]})["poses"]
    assert out.poses[:, k].max() <= 0.05 + 1e-9
    with pytest.raises(StageFailed, match=r"lower bound above upper bound for pose parameter 9 \(l_knee_flex\): 1.0 > -1.0") as exc:
        solve({"l_knee_flex": [1.0, -1.0]})
    assert exc.value.status == "invalid_bounds"
    with pytest.raises(StageFailed, match="no pose parameter named 'l_knee_flx'.*did you mean 'l_knee_flex'"):
        solve({"l_knee_flx": [0.0, 1.0]})


def test_edge_distance_marks_silhouette_and_self_occlusion_edges():
    from eventcap.energy.correspondences import edge_distance

    depth = np.full((40, 60), np.inf, np.float32)
    tri = np.full((40, 60), -1, np.int32)
    depth[5:35, 5:55], tri[5:35, 5:55] = 3.0, 1  # a body...
    depth[10:30, 30:40], tri[10:30, 30:40] = 2.5, 2  # ...with a nearer part in front of it
    d = edge_distance(depth, tri)
    assert d[0, 0] == 0 and d[5, 20] <= 1.0 and d[20, 15] >= 9.0  # outside / on the silhouette / deep inside
    assert d[20, 28] <= 1.0  # the farther surface next to the occluding part is an edge
    assert d[20, 35] >= 4.0  # the nearer part keeps its pixels (its own silhouette is 5 px away)
