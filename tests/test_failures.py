"""The line an incomplete run ends with (issue 35, item 6): failures counted by cause with the first batches of
each, the nodes skipped because of them, the first error once, and advice only where it can help."""

from __future__ import annotations

import copy
import logging


from eventcap.core.failures import failure_summary
from eventcap.core.runner import NodeReport, Runner, RunResult
from helpers.toy import TOY_PIPELINE, TOY_STAGES


def _report(node, per_batch=True, computed=0, failed=(), skipped=0, skip_causes=()):
    rep = NodeReport(node, node, per_batch, computed=computed, skipped=skipped, skip_causes=list(skip_causes))
    rep.failed = [{"batch": b, "status": s, "error": f"StageFailed: batch {b}: {s} in detail", "key": ""}
                  for b, s in failed]
    return rep


def test_mixed_causes_are_counted_with_their_first_batches():
    failed = [(b, "missing_detections") for b in range(3, 183)] + \
             [(b, "Maximum_Iterations_Exceeded") for b in range(185, 192)]
    solve = _report("solve", computed=14, failed=failed)
    refine = _report("refine", computed=14, skipped=187,
                     skip_causes=[{"batch": b, "cause": f"upstream failed: solve[batch {b}]: StageFailed: x"}
                                  for b, _ in failed])
    evaluate = _report("evaluate", per_batch=False, skipped=1,
                       skip_causes=[{"batch": None, "cause": "upstream failed: solve[batch 3]: StageFailed: x"}])
    # the runner names the root failure in every skip downstream (evaluate's is solve's, through refine)
    result = RunResult({"solve": solve, "refine": refine, "evaluate": evaluate}, {})
    line = failure_summary(result)
    assert line.startswith("solve failed in 187 of 201 batches: 180 missing_detections (batches 3, 4, 5, ...), "
                           "7 Maximum_Iterations_Exceeded (batches 185, 186, 187, ...)")
    assert "skipped because of it: 2 nodes (refine (187 of 201 batches), evaluate)" in line
    assert "first error: solve[batch 3]: StageFailed: batch 3: missing_detections in detail" in line
    assert "detect node's log names the images" in line  # advice for missing detections
    assert "run the same command again" not in line  # a deterministic failure: running again cannot help
    assert len(line) < 450


def test_transient_failure_gets_the_advice_to_run_again():
    rep = _report("track", computed=3, failed=[(2, "BrokenProcessPool")])
    line = failure_summary(RunResult({"track": rep}, {}))
    assert line.startswith("track failed in 1 of 4 batches: 1 BrokenProcessPool (batch 2)")
    assert "run the same command again" in line


def test_a_skip_with_its_own_cause_names_it():
    rep = _report("smooth", skipped=1, skip_causes=[{"batch": None, "cause": "no batches to run: the batch plan of "
                                                                             "signal is empty"}])
    line = failure_summary(RunResult({"smooth": rep}, {}))
    assert line.startswith("skipped: smooth (no batches to run: the batch plan of signal is empty)")


def test_187_failed_batches_of_a_real_run_end_in_one_short_line(toy, tmp_path, caplog):
    stages = copy.deepcopy(TOY_STAGES)
    stages["signal"]["n_batches"] = 201
    stages["smooth"]["fail_batches"] = list(range(3, 190))
    result = Runner({"pipeline": TOY_PIPELINE, "stages": stages, "cache_dir": str(tmp_path / "cache")}).run(None)
    line = failure_summary(result)
    assert line == ("smooth failed in 187 of 201 batches: 187 Injected_Failure (batches 3, 4, 5, ...); skipped "
                    "because of it: 2 nodes (scale (187 of 201 batches), total); first error: smooth[batch 3]: "
                    "StageFailed: injected failure in batch 3; every failure in full: run.json")
    # before: every failed and skipped unit was listed, 3,590 characters for this run
    assert len(line) < 300


def test_the_first_error_is_never_cut():
    """The stage's advice ends its error: the summary quotes it whole (it was cut at 200 characters)."""
    advice = "use a real detector instead: stages/detect=blazepose (BlazePose on the images) or detections made " \
             "elsewhere, stages/detect=file stages.detect.path=<OpenPose JSON folder, .npz or .csv>"
    error = "ValueError: stage 'simulated' simulates a detector from ground truth, but recording 'rec' has no " \
            "ground truth (a real recording?): " + advice
    rep = NodeReport("detect", "simulated", False)
    rep.failed = [{"batch": None, "status": "ValueError", "error": error, "key": ""}]
    skipped = [_report(n, per_batch=False, skipped=1, skip_causes=[{"batch": None, "cause": f"upstream failed: "
                                                                                         f"detect: {error}"}])
               for n in ("track", "slice", "solve")]
    result = RunResult({"detect": rep, **{r.node: r for r in skipped}}, {})
    line = failure_summary(result)
    assert len(error) > 300 and f"first error: detect: {error}; every failure in full: run.json" in line
    assert line.count(advice) == 1
    assert "skipped because of it: 3 nodes (track, slice, solve)" in line
    # for the log, which showed the error where it happened: named, not quoted again
    short = failure_summary(result, first_error=False)
    assert advice not in short and "the first error is above (detect)" in short


def test_a_failure_is_logged_once_and_its_skips_counted_on_one_line(toy, tmp_path, caplog):
    """One failed node upstream of the others: its error once in the log, no line per skipped node."""
    from eventcap.apps.jobs import run_job

    stages = copy.deepcopy(TOY_STAGES)
    stages["signal"]["n_batches"] = 6
    stages["smooth"]["fail_batches"] = [1, 2, 3]
    cfg = {"pipeline": TOY_PIPELINE, "stages": stages, "cache_dir": str(tmp_path / "cache")}
    failures: list[str] = []
    with caplog.at_level(logging.INFO):
        run_job(cfg, tmp_path / "run", "{}\n", failures)
    text = caplog.text
    assert text.count("injected failure in batch 1") == 1  # where it happened, not again at every skipped unit
    assert "batch 2 FAILED (Injected_Failure, as batch 1)" in text
    assert "skipped, upstream failed" not in text
    closing = [r.getMessage() for r in caplog.records if r.getMessage().startswith("run incomplete: ")]
    assert closing == ["run incomplete: smooth failed in 3 of 6 batches: 3 Injected_Failure (batches 1, 2, 3); "
                       "skipped because of it: 2 nodes (scale (3 of 6 batches), total); the first error is above "
                       "(smooth[batch 1]); every failure in full: run.json"]
    # nothing was measured: no metrics.json (issue 56: never an empty one), run.json says why
    assert caplog.records[-1].getMessage() == "run folder " + str(tmp_path / "run") + "/: config.yaml, run.json"
    # the caller's record of the failure quotes the first error in full
    assert failures == [f"{tmp_path / 'run'}: " + failure_summary(Runner(cfg).run(None))]
