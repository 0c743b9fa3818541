"""The evaluate stage (paper Sec. 4, Table 1): Procrustes alignment, AE / STD / AE.raw / AE.nonRaw against values
worked out by hand, the join of per-batch pose sequences at their shared boundary frames, the data rate, and bad
input."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from eventcap.artifacts import BatchPlan
from eventcap.artifacts.pose import JointErrors, PoseSequence
from eventcap.artifacts.recording import Recording
from eventcap.body.skeleton import DOF_INDEX, JOINT_INDEX, JOINT_NAMES
from eventcap.export.bvh import matrix_from_euler
from eventcap.analysis.metrics import mean_joint_error, procrustes_align
from eventcap.core.stage import Port, StageFailed, StageSpec, param
from eventcap.core.testing import StageConformance

from eventcap.analysis.motion import MotionError, join_batches  # noqa: E402  (moved to the core; the plugin imports it from there)
from helpers.evaluate_scene import STAGES, T0_US, batch_sequences, evaluate, odd_rest, recording


@pytest.fixture(autouse=True)
def evaluate_stage(monkeypatch):
    from eventcap.core.runner import reset_process_caches

    monkeypatch.setenv("EVENTCAP_STAGES", STAGES)
    reset_process_caches()
    yield
    reset_process_caches()


# -- inputs -----------------------------------------------------------------------------------------------------


# -- Procrustes and AE -------------------------------------------------------------------------------------------------
def test_procrustes_recovers_a_rigid_motion_exactly():
    rng = np.random.default_rng(1)
    truth = rng.normal(0.0, 0.3, (5, 24, 3))
    R = matrix_from_euler(rng.uniform(-np.pi, np.pi, (5, 3)), "ZXY")
    moved = np.einsum("fij,fkj->fki", R, truth) + rng.uniform(-2, 2, (5, 1, 3))
    assert np.abs(procrustes_align(moved, truth) - truth).max() < 1e-12
    assert np.abs(mean_joint_error(moved, truth)).max() < 1e-12
    assert mean_joint_error(moved, truth, align=False).min() > 0.05
    # a mirror image is not a rigid motion: alignment may not reflect
    mirrored = truth * np.array([-1.0, 1.0, 1.0])
    aligned = procrustes_align(mirrored, truth)
    assert mean_joint_error(mirrored, truth).min() > 0.01
    d = np.linalg.norm(aligned[:, :, None] - aligned[:, None], axis=-1)
    assert np.allclose(d, np.linalg.norm(mirrored[:, :, None] - mirrored[:, None], axis=-1))


def test_ae_of_a_tiny_case_by_hand():
    """Six points at ±1 on the axes. Estimate: 1.1 x the truth, shifted by s = (0.5, -0.2, 0.3).
    Aligned (translation and rotation, no scale): the centroid shift goes, the rotation stays the identity (the
    cross-covariance is 2.2 I), every point is 0.1 off -> AE 0.1. Not aligned: |0.1 p + s| per point."""
    truth = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=np.float64)[None]
    est = 1.1 * truth + np.array([0.5, -0.2, 0.3])
    assert mean_joint_error(est, truth)[0] == pytest.approx(0.1, abs=1e-12)
    by_hand = (np.sqrt(0.6**2 + 0.2**2 + 0.3**2) + np.sqrt(0.4**2 + 0.2**2 + 0.3**2)
               + np.sqrt(0.5**2 + 0.1**2 + 0.3**2) + np.sqrt(0.5**2 + 0.3**2 + 0.3**2)
               + np.sqrt(0.5**2 + 0.2**2 + 0.4**2) + np.sqrt(0.5**2 + 0.2**2 + 0.2**2)) / 6
    assert mean_joint_error(est, truth, align=False)[0] == pytest.approx(by_hand, abs=1e-12)


# -- joining batches ---------------------------------------------------------------------------------------------------
def _seq(t, yaw, fill):
    S = np.full((len(t), 33), float(fill))
    S[:, 27] = yaw
    return PoseSequence(t_us=np.asarray(t, np.int64), poses=S)


def test_join_keeps_one_pose_per_shared_boundary_frame():
    a = _seq([0, 1000, 2000], 0.0, 1.0)
    b = _seq([2000, 3000, 4000], 0.0, 3.0)
    c = _seq([4000, 5000], 0.0, 5.0)
    t, S, shared = join_batches([a, c, b], "later")  # order of the batches does not matter
    assert np.array_equal(t, [0, 1000, 2000, 3000, 4000, 5000]) and shared == 2
    assert np.array_equal(S[:, 0], [1, 1, 3, 3, 5, 5])
    t, S, shared = join_batches([a, b, c], "mean")
    assert np.array_equal(S[:, 0], [1, 1, 2, 3, 4, 5]) and shared == 2
    # root angles average modulo 2π: π - 0.1 and -π + 0.1 are 0.2 apart, their mean is π, not 0
    p = _seq([0, 1000], [0.0, np.pi - 0.1], 0.0)
    q = _seq([1000, 2000], [-np.pi + 0.1, -np.pi + 0.2], 0.0)
    _, S, _ = join_batches([p, q], "mean")
    assert abs(abs(S[1, 27]) - np.pi) < 1e-12
    # batches that share no frame (intensity frames not on the 1 ms grid) and empty batches
    t, S, shared = join_batches([_seq([0, 1000], 0, 1), _seq([], 0, 0), _seq([1333, 2333], 0, 2)], "later")
    assert np.array_equal(t, [0, 1000, 1333, 2333]) and shared == 0


def test_join_errors():
    # the library's own error; the runner records its status as a stage's (test_join_failure_is_recorded_by_the_runner)
    with pytest.raises(MotionError, match=r"batch 1: tracking frame times must increase; frame 1") as e:
        join_batches([_seq([0, 1000], 0, 0), _seq([2000, 2000], 0, 0)])
    assert e.value.status == "bad_poses"
    with pytest.raises(MotionError, match=r"no poses to join: 2 batch\(es\)") as e:
        join_batches([_seq([], 0, 0), _seq([], 0, 0)])
    assert e.value.status == "no_poses"
    with pytest.raises(ValueError, match=r"join: expected one of later, mean, got 'first'"):
        join_batches([_seq([0], 0, 0)], "first")


# -- the stage ---------------------------------------------------------------------------------------------------------
def test_ground_truth_poses_give_zero_error():
    rec = recording()
    values, errors = evaluate(rec, batch_sequences(rec))
    # 3 batches of 41 frames sharing 2 boundaries: 121 tracking frames 5..125 ms
    assert values["n_tracking_frames"] == 121 and values["n_shared_frames"] == 2 and values["n_batches"] == 3
    assert values["n_frames"] == 13 and values["n_raw"] == 4 and values["n_nonRaw"] == 9
    for key in ("AE_mm", "STD_mm", "AE_raw_mm", "AE_nonRaw_mm"):
        assert abs(values[key]) < 1e-9, key
    assert set(values["per_joint_mm"]) == set(JOINT_NAMES)
    assert values["solver_status"] == {"Solve_Succeeded": 3} and values["align"] == "procrustes"
    assert isinstance(errors, JointErrors) and errors.error_m.shape == (13, 24)
    assert np.array_equal(errors.t_us[errors.raw], rec.frames.t_us)


def test_known_perturbations():
    rec = recording()
    # a rigid shift of the whole body is removed by the alignment, and is the whole error without it
    shift = lambda t, S: S + np.r_[np.zeros(30), 0.1, 0.0, 0.0]  # noqa: E731
    aligned, _ = evaluate(rec, batch_sequences(rec, shift))
    raw, _ = evaluate(rec, batch_sequences(rec, shift), align="none")
    assert aligned["AE_mm"] < 1e-9 and raw["AE_mm"] == pytest.approx(100.0, abs=1e-9)
    assert raw["STD_mm"] < 1e-9 and raw["AE_raw_mm"] == pytest.approx(100.0, abs=1e-9)
    # a shift growing by 1 mm per ms: frame i is i mm off; AE and STD over i = 0, 10, ..., 120; raw at 0, 40, 80, 120
    drift = lambda t, S: S + np.outer((t - T0_US) * 1e-6, np.r_[np.zeros(30), 1.0, 0.0, 0.0])  # noqa: E731
    v, _ = evaluate(rec, batch_sequences(rec, drift), align="none")
    i = np.arange(0, 121, 10)
    assert v["AE_mm"] == pytest.approx(i.mean(), abs=1e-9) and v["STD_mm"] == pytest.approx(i.std(), abs=1e-9)
    assert v["AE_raw_mm"] == pytest.approx(60.0, abs=1e-9)
    assert v["AE_nonRaw_mm"] == pytest.approx(np.mean([10, 20, 30, 50, 60, 70, 90, 100, 110]), abs=1e-9)
    v5, _ = evaluate(rec, batch_sequences(rec, drift), align="none", every=5)
    assert v5["n_frames"] == 25 and v5["AE_mm"] == pytest.approx(60.0, abs=1e-9)


def test_bent_elbow_moves_wrist_and_hand_by_the_chord():
    """Elbow flexion + δ rotates the wrist and hand about the elbow's flexion axis (y in the elbow's frame): each
    moves by the chord 2 sin(δ/2) times its distance from that axis, whatever the pose; the other 22 joints stay."""
    rec = recording()
    delta = 0.2
    k = DOF_INDEX["l_elbow_flex"]

    def bend(t, S):
        S[:, k] += delta
        return S

    v, errors = evaluate(rec, batch_sequences(rec, bend), align="none")
    rest = odd_rest()
    e, w, h = (JOINT_INDEX[n] for n in ("l_elbow", "l_wrist", "l_hand"))
    chord = 2 * np.sin(delta / 2)
    off_axis = [np.hypot(*(rest[j] - rest[e])[[0, 2]]) for j in (w, h)]
    per_joint = v["per_joint_mm"]
    assert per_joint["l_wrist"] == pytest.approx(1000 * chord * off_axis[0], rel=1e-9)
    assert per_joint["l_hand"] == pytest.approx(1000 * chord * off_axis[1], rel=1e-9)
    assert all(per_joint[n] < 1e-9 for n in JOINT_NAMES if n not in ("l_wrist", "l_hand"))
    assert v["AE_mm"] == pytest.approx(1000 * chord * sum(off_axis) / 24, rel=1e-9)
    # the alignment minimises the sum of squared distances (not the AE, which it may raise by spreading the error)
    _, aligned = evaluate(rec, batch_sequences(rec, bend))
    assert np.all((aligned.error_m**2).sum(axis=1) < (errors.error_m**2).sum(axis=1))
    assert np.all(aligned.error_m[:, JOINT_INDEX["pelvis"]] > 0)


def test_data_rate():
    rec = recording()
    v, _ = evaluate(rec, batch_sequences(rec))
    r = v["data_rate"]
    ev = rec.events.events["t"]
    n_events = int(np.count_nonzero((ev >= 5_000) & (ev <= 125_000)))
    assert r["n_events"] == n_events and r["n_intensity_frames"] == 4 and r["duration_s"] == pytest.approx(0.12)
    assert r["bytes_per_event"] == 13 and r["bytes_per_frame"] == 240 * 180
    assert r["events_MBps"] == pytest.approx(n_events * 13 / 1e6 / 0.12)
    assert r["frames_MBps"] == pytest.approx(4 * 240 * 180 / 1e6 / 0.12)
    assert r["highspeed_fps"] == pytest.approx(1000.0) and r["highspeed_MBps"] == pytest.approx(43.2)
    assert r["reduction"] == pytest.approx(43.2 / r["total_MBps"])


def test_frames_outside_the_ground_truth_are_not_evaluated():
    rec = recording(gt_end_us=60_000)
    full = recording()
    v, errors = evaluate(rec, batch_sequences(full))
    assert v["n_outside_ground_truth"] == 65 and errors.t_us.max() <= 60_000
    assert v["n_frames"] == 6 and v["AE_mm"] < 1e-9


def test_bad_input():
    rec = recording()
    # A real recording (no ground truth): the data rate only, and it says why; the run does not fail.
    v, errors = evaluate(recording(ground_truth=False), batch_sequences(rec))
    assert v["evaluated"] is False and "has no ground truth" in v["reason"]
    assert v["data_rate"]["total_MBps"] > 0 and errors.t_us.size == 0
    with pytest.raises(StageFailed, match=r"recording 'tiny-eval' has no actor template") as e:
        evaluate(recording(template=False), batch_sequences(rec))
    assert e.value.status == "no_template"
    with pytest.raises(StageFailed, match=r"no estimated tracking frame \(200000..240000 us\) lies within") as e:
        late = [PoseSequence(t_us=s.t_us + 200_000 - 5_000, poses=s.poses) for s in batch_sequences(rec)[:1]]
        evaluate(rec, late)
    assert e.value.status == "no_overlap"
    with pytest.raises(ValueError, match=r"stages.evaluate.every: expected an integer >= 1, got 0"):
        evaluate(rec, batch_sequences(rec), every=0)
    with pytest.raises(ValueError, match=r"stages.evaluate.align: expected one of procrustes, none, got 'scale'"):
        evaluate(rec, batch_sequences(rec), align="scale")
    with pytest.raises(ValueError, match=r"stages.evaluate.join: expected one of later, mean, got 'x'"):
        evaluate(rec, batch_sequences(rec), join="x")


class TestEvaluateConformance(StageConformance):
    stage_name = "evaluate"
    sensitive = ("every", 5)

    def make_inputs(self):
        rec = recording()
        return {"recording": rec, "poses": batch_sequences(rec, lambda t, S: S + 0.01)}


# -- through the runner: per-batch poses handed over as a BatchSequence, metrics collected into metrics.json ------------
@dataclass
class _NoConfig:
    pass


@dataclass
class _OffsetConfig:
    offset_m: float = param(0.0, help="shift of the root along x, metres")
    wobble_rad: float = param(0.0, help="amplitude of a 7 ms sine added to every joint angle, radians")


def run_test_source(inputs, config, ctx):
    rec = recording()
    return {"recording": rec, "batches": BatchPlan.between_frames(rec.frames.t_us)}


def run_test_solve(inputs, config, ctx):
    rec, b = inputs["recording"], ctx.batch
    t = np.arange(b.t0_us, b.t1_us + 1, 1_000, dtype=np.int64)
    S = rec.ground_truth.poses[np.searchsorted(rec.ground_truth.t_us, t)].copy()
    S[:, 30] += config.offset_m
    S[:, :27] += config.wobble_rad * np.sin(2 * np.pi * t / 7_000)[:, None]
    return {"poses": PoseSequence(t_us=t, poses=S, status="Solve_Succeeded")}


def run_test_join(inputs, config, ctx):
    seq = inputs["poses"]
    assert seq.batches[0] is not None  # a per-batch upstream: its batches are named
    t, S, _ = join_batches([seq[i] for i in range(len(seq))])
    return {"motion": PoseSequence(t_us=t, poses=S, status="joined")}


RUNNER_SPECS = [
    StageSpec(name="eval_test_join", kind="fuse", version=1, description="every batch's poses as one motion",
              config=_NoConfig, inputs={"poses": Port(PoseSequence, all_batches=True)},
              outputs={"motion": Port(PoseSequence)}, run="test_evaluate:run_test_join"),
    StageSpec(name="eval_test_source", kind="source", version=1, description="the tiny recording of test_evaluate",
              config=_NoConfig, inputs={}, outputs={"recording": Port(Recording), "batches": Port(BatchPlan)},
              run="test_evaluate:run_test_source"),
    StageSpec(name="eval_test_solve", kind="solve", version=1, description="ground-truth poses per batch",
              config=_OffsetConfig, inputs={"recording": Port(Recording), "batches": Port(BatchPlan)},
              outputs={"poses": Port(PoseSequence)}, run="test_evaluate:run_test_solve", per_batch=True),
]


def test_runner_hands_all_batches_and_collects_metrics(tmp_path, monkeypatch):
    import json

    from eventcap.core.runner import Runner, reset_process_caches

    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parent))
    monkeypatch.setenv("EVENTCAP_STAGES", f"{STAGES},test_evaluate:RUNNER_SPECS")
    reset_process_caches()
    cfg = {"pipeline": {"nodes": {
        "source": {},
        "solve": {"inputs": {"recording": "source.recording", "batches": "source.batches"}},
        "evaluate": {"inputs": {"recording": "source.recording", "poses": "solve.poses"}}}},
        "stages": {"source": {"stage": "eval_test_source"}, "solve": {"stage": "eval_test_solve", "offset_m": 0.05},
                   "evaluate": {"stage": "evaluate", "align": "none"}},
        "cache_dir": str(tmp_path / "cache")}
    result = Runner(cfg).run(tmp_path / "run")
    assert result.ok
    m = json.loads((tmp_path / "run" / "metrics.json").read_text())["evaluate.metrics"]
    assert m["AE_mm"] == pytest.approx(50.0, abs=1e-9) and m["n_batches"] == 3 and m["n_shared_frames"] == 2


def test_a_whole_recording_motion_is_measured_as_its_batches(tmp_path, monkeypatch):
    """evaluate reads a whole-recording node's poses (a post-processing node's): the same motion handed as one
    PoseSequence or cut into its batches gives the same metrics, the peak speeds per intensity-frame interval."""
    import json

    from eventcap.core.runner import Runner, reset_process_caches

    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parent))
    monkeypatch.setenv("EVENTCAP_STAGES", f"{STAGES},test_evaluate:RUNNER_SPECS")
    reset_process_caches()
    nodes = {"source": {},
             "solve": {"inputs": {"recording": "source.recording", "batches": "source.batches"}},
             "join": {"inputs": {"poses": "solve.poses"}},
             "whole": {"config": "stages.evaluate", "inputs": {"recording": "source.recording", "poses": "join.motion"}},
             "batches": {"config": "stages.evaluate",
                         "inputs": {"recording": "source.recording", "poses": "solve.poses"}}}
    cfg = {"pipeline": {"nodes": nodes},
           "stages": {"source": {"stage": "eval_test_source"},
                      "solve": {"stage": "eval_test_solve", "offset_m": 0.02, "wobble_rad": 0.05},
                      "join": {"stage": "eval_test_join"}, "evaluate": {"stage": "evaluate", "every": 3, "align": "none"}},
           "cache_dir": str(tmp_path / "cache")}
    result = Runner(cfg).run(tmp_path / "run")
    assert result.ok
    m = json.loads((tmp_path / "run" / "metrics.json").read_text())
    whole, cut = m["whole.metrics"], m["batches.metrics"]
    assert whole["n_batches"] == 1 and cut["n_batches"] == 3 and whole["n_frames"] == cut["n_frames"] > 30
    assert whole["AE_mm"] > 20.0 and whole["MPJVE_mm_s"] > 100.0 and whole["n_peak_pairs"] > 0
    for key in ("AE_mm", "STD_mm", "AE_raw_mm", "MPJVE_mm_s", "accel_err_m_s2", "peak_speed_err", "depth_mm"):
        assert whole[key] == pytest.approx(cut[key], rel=1e-12), key
    assert whole["peak_speed_errors"] == cut["peak_speed_errors"]  # per intensity-frame interval: the batches
    assert len(whole["peak_speed_errors"]) == 3
