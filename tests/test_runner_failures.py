"""Failure chains through `eventcap run`: a unit whose upstream failed or was skipped is skipped and says why
("upstream failed: <node>[batch k]: <cause>"), every failure names its node, batch and cause, and run.json is
always written. Runs the framework's toy stages (tests/toy_stages.py) through the CLI's main function."""

from __future__ import annotations

import json
import logging


from eventcap.apps.cli import main
from helpers.paths import TESTS


def run_cli(tmp_path, name: str, *overrides: str, caplog=None) -> tuple[int, dict, str]:
    run_dir = tmp_path / name
    argv = ["run", f"hydra.searchpath=[file://{TESTS / 'conf'}]", "experiment=toy", f"cache_dir={tmp_path / 'cache'}",
            f"hydra.run.dir={run_dir}", "outputs.poses=null", *overrides]
    code = main(argv)
    summary = json.loads((run_dir / "run.json").read_text())
    log_text = (run_dir / "eventcap.log").read_text() if (run_dir / "eventcap.log").exists() else ""
    if caplog is not None:
        log_text += "\n" + caplog.text
    return code, summary, log_text


def test_failed_batch_skips_its_batch_downstream_and_the_whole_consumer(toy, tmp_path, caplog):
    caplog.set_level(logging.INFO)
    code, s, log_text = run_cli(tmp_path, "a", "stages.smooth.fail_batches=[2]", caplog=caplog)
    assert code == 1 and not s["ok"]
    nodes = s["nodes"]
    [fail] = nodes["smooth"]["failed"]
    assert fail["batch"] == 2 and fail["error"] == "StageFailed: injected failure in batch 2"
    assert nodes["scale"]["computed"] == 3 and nodes["scale"]["skipped"] == 1
    cause = "upstream failed: smooth[batch 2]: StageFailed: injected failure in batch 2"
    assert nodes["scale"]["skip_causes"] == [{"batch": 2, "cause": cause}]
    assert nodes["total"]["skip_causes"] == [{"batch": None, "cause": cause}]
    assert "smooth: batch 2 FAILED (Injected_Failure): StageFailed: injected failure in batch 2" in log_text
    assert log_text.count("injected failure in batch 2") == 1  # logged where it happened; run.json has the skips
    assert "skipped because of it: 2 nodes (scale (1 of 4 batches), total)" in log_text


def test_failed_whole_node_skips_per_batch_consumers_instead_of_failing_them(toy, tmp_path, caplog):
    # A whole node feeding a per-batch node (as detect feeds track): before, every batch failed with
    # "CacheCorruptError: input ... is not in the cache".
    caplog.set_level(logging.INFO)
    code, s, log_text = run_cli(tmp_path, "b", "+pipeline.nodes.noise={}", "+stages.noise={stage: toy_signal, "
                                "seed: -1}", "pipeline.nodes.smooth.inputs.series=noise.series", caplog=caplog)
    assert code == 1
    nodes = s["nodes"]
    [fail] = nodes["noise"]["failed"]
    assert fail["batch"] is None and fail["error"].startswith("ValueError")
    root = f"noise: {fail['error']}"
    for n in ("smooth", "scale", "total"):
        assert nodes[n]["failed"] == [] and nodes[n]["computed"] == 0, n
        assert nodes[n]["skip_causes"] == [{"batch": None, "cause": f"upstream failed: {root}"}], n
    assert "CacheCorruptError" not in log_text
    assert nodes["signal"]["computed"] + nodes["signal"]["cached"] == 1


def test_failed_source_still_writes_run_json(toy, tmp_path, caplog):
    # The batch-plan node itself fails: before, the run aborted while loading its plan, without run.json.
    code, s, log_text = run_cli(tmp_path, "c", "stages.signal.seed=-1", caplog=caplog)
    assert code == 1 and not s["ok"]
    [fail] = s["nodes"]["signal"]["failed"]
    root = f"signal: {fail['error']}"
    assert [s["nodes"][n]["skip_causes"][0]["cause"] for n in ("smooth", "scale", "total")] == \
        [f"upstream failed: {root}"] * 3


def test_zero_batches_is_a_named_skip_not_a_crash(toy, tmp_path, caplog):
    # Before: the whole consumer ran on 0 batches (evaluate: IndexError: tuple index out of range). An empty plan
    # (batches=2:2 was one before it was refused up front) skips every per-batch node with the cause.
    code, s, log_text = run_cli(tmp_path, "d", "stages.signal.n_batches=0", caplog=caplog)
    assert code == 1
    why = "no batches to run: the batch plan of signal is empty"
    assert s["nodes"]["smooth"]["skip_causes"] == [{"batch": None, "cause": why}]
    assert s["nodes"]["total"]["skip_causes"] == [{"batch": None, "cause": f"upstream failed: smooth: {why}"}]
    assert s["nodes"]["total"]["computed"] == 0


def test_missing_recording_is_refused_before_the_run_folder_exists(tmp_path, capsys):
    # The real pipeline: a recording path that does not exist is refused with every other setting, before the run
    # folder and the cache exist (issue 57), naming the key and the path.
    run_dir = tmp_path / "e"
    code = main(["run", "pipeline=simulate", "source=recording", f"source.path={tmp_path / 'nope.aedat4'}",
                 "template=procedural", "template.target_faces=3000", f"cache_dir={tmp_path / 'cache'}", f"hydra.run.dir={run_dir}"])
    assert code == 1
    assert f"source.path: {tmp_path / 'nope.aedat4'}: no such file or folder" in capsys.readouterr().err
    assert not run_dir.exists() and not (tmp_path / "cache").exists()


def test_a_recording_vanishing_after_the_checks_fails_the_source_node(tmp_path, monkeypatch):
    # A path checked before the run that is gone when the source is keyed: the source node fails (in the driver),
    # the rest is skipped with that cause, and the run is summarised.
    from eventcap.core import config as config_module

    monkeypatch.setattr(config_module, "check_file_settings", lambda spec, config, where: None)
    monkeypatch.setattr("eventcap.core.pipeline.check_file_settings", lambda spec, config, where: None)
    run_dir = tmp_path / "e"
    code = main(["run", "pipeline=simulate", "source=recording", f"source.path={tmp_path / 'nope.aedat4'}",
                 "template=procedural", "template.target_faces=3000", f"cache_dir={tmp_path / 'cache'}", f"hydra.run.dir={run_dir}"])
    assert code == 1
    s = json.loads((run_dir / "run.json").read_text())
    [fail] = s["nodes"]["source"]["failed"]
    assert fail["batch"] is None and fail["error"] == f"ConfigError: source.path: file not found: {tmp_path / 'nope.aedat4'}"
    assert s["nodes"]["template"]["computed"] + s["nodes"]["template"]["cached"] == 1


def test_a_library_error_is_recorded_with_its_own_status(toy, tmp_path, monkeypatch):
    # The domain library raises errors of its own (eventcap.errors.ComputationFailed subclasses such as MotionError),
    # not the framework's StageFailed; the runner records their status as it does a stage's.
    import toy_stages

    from eventcap.analysis.motion import join_batches

    real = toy_stages.run_smooth

    def run_smooth(inputs, config, ctx):
        if ctx.batch.index == 1:
            join_batches([])  # nothing to join: MotionError(status="no_poses")
        return real(inputs, config, ctx)

    monkeypatch.setattr(toy_stages, "run_smooth", run_smooth)
    code, s, _ = run_cli(tmp_path, "lib")
    assert code == 1 and not s["ok"]
    [fail] = s["nodes"]["smooth"]["failed"]
    assert fail["batch"] == 1 and fail["status"] == "no_poses"
    assert fail["error"] == "MotionError: no poses to join: 0 batch(es), none with a tracking frame"
