"""run.json has one definition (eventcap/core/runrecord.py): what the runner writes reads back, bad files are refused with
the file and key named, and the outputs step adds its section."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from eventcap.core.runrecord import NodeReport, RunRecord, RunRecordError, find_cache_dir, note_outputs


def _record() -> RunRecord:
    return RunRecord(False, "/abs/cache", {
        "source": NodeReport("source", "synthetic", False, ["k0"], ["k0"], 0, 1, elapsed_s=1.23456),
        "track": NodeReport("track", "eklt", True, ["a", "b"], ["b"], 1, 1,
                            [{"batch": 1, "key": "b", "status": "x", "error": "E: boom"}], 1,
                            [{"batch": 2, "cause": "upstream failed: source: E"}], 2.0)})


def test_round_trip_and_the_file_layout(tmp_path):
    rec = _record()
    rec.write(tmp_path)
    doc = json.loads((tmp_path / "run.json").read_text())
    assert list(doc) == ["ok", "cache_dir", "nodes"] and doc["nodes"]["source"]["elapsed_s"] == 1.235
    assert list(doc["nodes"]["track"]) == ["stage", "per_batch", "cached", "computed", "skipped", "skip_causes",
                                           "failed", "elapsed_s", "keys", "computed_keys"]
    back = RunRecord.read(tmp_path)
    assert back.nodes["track"] == rec.nodes["track"] and back.ok is False and back.cache_dir == "/abs/cache"
    assert back.nodes["source"].elapsed_s == 1.235 and back.outputs is None


def test_a_run_writes_what_the_record_reads(toy_cfg, tmp_path):
    from eventcap.core.runner import Runner

    result = Runner(toy_cfg()).run(tmp_path / "run")
    rec = RunRecord.read(tmp_path / "run")
    assert rec.ok and set(rec.nodes) == set(result.nodes)
    assert all(rec.nodes[n].keys == result.nodes[n].keys for n in rec.nodes)


def test_bad_files_are_refused_naming_file_and_key(tmp_path):
    with pytest.raises(RunRecordError, match=r"run.json: no such file \(`eventcap run` writes it"):
        RunRecord.read(tmp_path)
    (tmp_path / "run.json").write_text("{not json")
    with pytest.raises(RunRecordError, match=r"run.json: cannot read it"):
        RunRecord.read(tmp_path)
    (tmp_path / "run.json").write_text(json.dumps({"nodes": {}}))
    with pytest.raises(RunRecordError, match=r"run.json: missing 'ok'"):
        RunRecord.read(tmp_path)
    (tmp_path / "run.json").write_text(json.dumps({"ok": True, "nodes": {"track": {"stage": "eklt"}}}))
    with pytest.raises(RunRecordError, match=r"run.json: nodes.track: missing 'per_batch'"):
        RunRecord.read(tmp_path)
    (tmp_path / "run.json").write_text(json.dumps({"ok": True, "nodes": {"track": {"stage": "eklt", "per_batch": 1,
                                                                                    "cached": "many"}}}))
    with pytest.raises(RunRecordError, match=r"nodes.track: invalid literal for int\(\) with base 10: 'many'"):
        RunRecord.read(tmp_path)


def test_outputs_are_noted_and_merged(tmp_path):
    note_outputs(tmp_path, {"written": {"bvh": "a.bvh"}, "skipped": {}, "problems": []})  # no run.json: nothing
    assert not (tmp_path / "run.json").exists()
    _record().write(tmp_path)
    note_outputs(tmp_path, {"written": {"bvh": "a.bvh"}, "skipped": {"video": "off"}, "problems": ["p1"]})
    note_outputs(tmp_path, {"written": {"rerun": "c.rrd"}, "skipped": {}, "problems": ["p2"]}, merge=True)
    out = RunRecord.read(tmp_path).outputs
    assert out == {"written": {"bvh": "a.bvh", "rerun": "c.rrd"}, "skipped": {"video": "off"}, "problems": ["p1", "p2"]}
    note_outputs(tmp_path, {"written": {}, "skipped": {}, "problems": []})  # without merge: replaced
    assert RunRecord.read(tmp_path).outputs == {"written": {}, "skipped": {}, "problems": []}
    assert RunRecord.read(tmp_path).nodes["track"].skipped == 1  # the rest of the record is kept


def test_the_cache_is_found_from_the_run_folder(tmp_path, monkeypatch):
    (tmp_path / "runs" / "cache" / "entries").mkdir(parents=True)
    run_dir = tmp_path / "runs" / "default" / "2026-01-01_00-00-00"
    run_dir.mkdir(parents=True)
    monkeypatch.chdir(run_dir)  # runs/cache is not below the current folder
    assert find_cache_dir(run_dir, "runs/cache") == tmp_path / "runs" / "cache"
    assert find_cache_dir(run_dir, "/elsewhere/cache") == Path("/elsewhere/cache")  # absolute: as given
