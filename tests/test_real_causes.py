"""Say the real cause (issue 19, item 4): each mistake a user can make, met through `eventcap` as the user meets it,
ends with a message naming the key / file / value and what was expected, at the earliest point it can be known.

Runs are kept small: the toy stages where the pipeline's content does not matter, and the real pipeline only where
the failure stops it after the template (a light one) and the source."""

from __future__ import annotations

import json
import logging
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
import zarr


from eventcap.artifacts import ArtifactError
from eventcap.artifact import read_array
from eventcap.apps.cli import main
from helpers.paths import TESTS
from helpers.toy import toy_env

TOY = [f"hydra.searchpath=[file://{TESTS / 'conf'}]", "experiment=toy", "outputs.poses=null"]
#: the real pipeline on a tiny capture with a light template (see conftest.small_capture_config)
#: (the paper's pipeline: DOWNSTREAM names its nodes)
SMALL = ["pipeline=paper", "experiment=quick", "source.duration_s=0.09", "template=procedural",
         "template.target_faces=2000", "source.n_track_points=20", "outputs.video=false"]
DOWNSTREAM = ("detect", "sharpen", "body", "track", "slice", "solve", "refine", "confidence", "evaluate")


@pytest.fixture(scope="module")
def shared_cache(tmp_path_factory):
    """One cache for the real-pipeline tests here, so the template is computed once."""
    return tmp_path_factory.mktemp("cache")


def run_main(run_dir, *argv, caplog=None, capsys=None) -> tuple[int, str]:
    code = main(["run", f"hydra.run.dir={run_dir}", *argv])
    text = (run_dir / "eventcap.log").read_text() if (run_dir / "eventcap.log").exists() else ""
    # a setting refused before the run folder is made is printed on stderr (issue 48), not logged into the folder
    err = capsys.readouterr().err if capsys is not None else ""
    return code, text + ("\n" + caplog.text if caplog is not None else "") + err


def summary(run_dir) -> dict:
    return json.loads((run_dir / "run.json").read_text())


def committed_entries(cache_dir) -> list:
    return sorted((cache_dir / "entries").glob("*/*/manifest.json"))


# --- a failed source: the cause, every later node skipped with it, run.json and config.yaml written -------------------
def test_failed_synthetic_source_is_the_cause_of_every_skip(tmp_path, shared_cache, caplog, capsys):
    caplog.set_level(logging.INFO)
    run_dir = tmp_path / "neg"
    # a value outside its declared range is refused before anything runs (issue 38), before the run folder is
    # made (issue 48): no run, no summary, no folder
    code, log_text = run_main(tmp_path / "refused", *SMALL, "source.duration_s=-1", f"cache_dir={shared_cache}",
                              caplog=caplog)
    assert code == 1 and "source.duration_s: expected a finite number in (0, 3600], got -1" in capsys.readouterr().err
    assert not (tmp_path / "refused").exists()
    # an unknown motion is refused before the run folder too (issue 57)
    code, log_text = run_main(tmp_path / "unknown", *SMALL, "source.motion=no_such_motion", f"cache_dir={shared_cache}",
                              caplog=caplog)
    assert code == 1 and "source.motion: unknown motion 'no_such_motion'" in capsys.readouterr().err
    assert not (tmp_path / "unknown").exists()
    # a source that fails while it runs (a clip file that is no BVH): every node after it is skipped with that cause
    clip = tmp_path / "no_such_motion.bvh"
    clip.write_text("not a BVH file\n")
    code, log_text = run_main(run_dir, *SMALL, f"source.motion={clip}", f"cache_dir={shared_cache}", caplog=caplog)
    assert code == 1
    assert (run_dir / "config.yaml").is_file() and "no_such_motion.bvh" in (run_dir / "config.yaml").read_text()
    s = summary(run_dir)
    [fail] = s["nodes"]["source"]["failed"]
    assert "no_such_motion" in fail["error"]
    cause = f"upstream failed: source: {fail['error']}"
    for n in DOWNSTREAM:
        assert s["nodes"][n]["skip_causes"] == [{"batch": None, "cause": cause}], n
        assert s["nodes"][n]["computed"] == 0 and s["nodes"][n]["failed"] == [], n
    assert "not in the cache" not in log_text
    # the error once, where it happened; the summary names the failure and counts the nodes skipped because of it
    assert log_text.count(fail["error"]) == 1
    assert (f"run incomplete: source failed (BvhError); skipped because of it: {len(DOWNSTREAM)} nodes "
            f"({', '.join(DOWNSTREAM)}); the first error is above (source)") in log_text


def _tiny_recording(path, n=3000):
    """A small event-only recording in the project's format, converted from an npz as a user's file would be."""
    from eventcap.io.convert import convert_recording

    rng = np.random.default_rng(0)
    src = path.with_suffix(".npz")
    np.savez(src, t=np.sort(rng.integers(0, 200_000, n)).astype(np.int64), x=rng.integers(0, 240, n).astype(np.uint16),
             y=rng.integers(0, 180, n).astype(np.uint16), p=rng.choice([-1, 1], n).astype(np.int8))
    convert_recording(src, path, width=240, height=180)
    return path


def _damage(chunk_file):
    """Flip the bytes of the Zstd frame header. (Flipped bytes inside a frame's data are not always detected: the
    chunks carry no checksum, and such a chunk can decode into wrong values, which the artifact's checks then name.)"""
    raw = bytearray(chunk_file.read_bytes())
    raw[4:8] = bytes(b ^ 0xFF for b in raw[4:8])
    chunk_file.write_bytes(bytes(raw))


def test_corrupt_chunk_of_a_recording_names_file_array_and_rows(tmp_path, shared_cache, caplog):
    caplog.set_level(logging.INFO)
    rec = _tiny_recording(tmp_path / "rec.zarr")
    chunk = rec / "events" / "events" / "x" / "c" / "0"
    _damage(chunk)
    run_dir = tmp_path / "bad"
    code, log_text = run_main(run_dir, "pipeline=paper", "source=recording", f"source.path={rec}", "template=procedural",
                              "template.target_faces=2000", "outputs.video=false", f"cache_dir={shared_cache}", caplog=caplog)
    assert code == 1 and (run_dir / "config.yaml").is_file()
    s = summary(run_dir)
    [fail] = s["nodes"]["source"]["failed"]
    assert fail["error"].startswith(f"ArtifactError: {chunk}: cannot decode chunk (0,) of array {rec}/events/events/x "
                                    f"(uint16, shape (3000,)), rows 0..2999 of 3000: RuntimeError: Zstd decompression error")
    assert "the file is damaged" in fail["error"]
    for n in DOWNSTREAM:
        assert s["nodes"][n]["skip_causes"] == [{"batch": None, "cause": f"upstream failed: source: {fail['error']}"}]
    assert "not in the cache" not in log_text


def test_damaged_or_missing_chunk_is_located(tmp_path):
    # chunks of 100 rows: the 4th is damaged, then (another array) the 7th is missing
    g = zarr.open_group(str(tmp_path / "g.zarr"), mode="w")
    a = g.create_array("t", shape=(1000,), dtype="int64", chunks=(100,), config={"write_empty_chunks": True})
    a[...] = np.arange(1000)
    b = g.create_array("u", shape=(1000, 2), dtype="float32", chunks=(100, 2), config={"write_empty_chunks": True})
    b[...] = 1.0
    np.testing.assert_array_equal(read_array(a, "rec/t"), np.arange(1000))
    _damage(tmp_path / "g.zarr" / "t" / "c" / "3")
    with pytest.raises(ArtifactError, match=r"t/c/3: cannot decode chunk \(3,\) of array rec/t \(int64, shape "
                                            r"\(1000,\)\), rows 300\.\.399 of 1000: RuntimeError: Zstd"):
        read_array(a, "rec/t")
    (tmp_path / "g.zarr" / "u" / "c" / "6" / "0").unlink()
    assert np.all(b[...][600:700] == 0)  # what zarr alone would hand back: fill values
    with pytest.raises(ArtifactError, match=r"u/c/6/0: chunk file missing: array rec/u \(float32, shape \(1000, 2\)\), "
                                            r"chunk \(6, 0\) holding rows 600\.\.699 of 1000"):
        read_array(b, "rec/u")


# --- batches= ---------------------------------------------------------------------------------------------------------
def test_reversed_or_empty_batches_are_refused_before_anything_runs(toy, tmp_path, caplog, capsys):
    for i, (value, why) in enumerate([("5:2", "batches='5:2': an empty slice (stop 2 is not after start 5)"),
                                      ("0", "batches=0: N=0 selects no batch"),
                                      ("-2:", "batches='-2:': batch indices count from 0")]):
        run_dir = tmp_path / f"r{i}"
        code, log_text = run_main(run_dir, *TOY, f"cache_dir={tmp_path / 'cache'}", f"batches={value}", caplog=caplog,
                                  capsys=capsys)
        assert code == 1
        assert why in log_text
        assert not committed_entries(tmp_path / "cache"), "nothing may run"
        assert not run_dir.exists()


def test_batches_beyond_the_plan_name_its_size(toy, tmp_path, caplog):
    caplog.set_level(logging.INFO)
    run_dir = tmp_path / "far"
    code, log_text = run_main(run_dir, *TOY, f"cache_dir={tmp_path / 'cache'}", "batches=100:200", caplog=caplog)
    assert code == 1
    cause = ("batches='100:200' is out of range: the batch plan signal.batches has 4 batches (0..3); give N <= 4 "
             "(the first N) or 'start:stop' within 0:4")
    s = summary(run_dir)
    assert s["nodes"]["signal"]["computed"] == 1
    for n in ("smooth", "scale", "total"):
        assert s["nodes"][n]["skip_causes"] == [{"batch": None, "cause": cause}], n
    assert "no poses to join" not in log_text and "selects none" not in log_text
    # 'N' asks for at most the first N: more than the plan has runs them all, and says so
    code, log_text = run_main(tmp_path / "n", *TOY, f"cache_dir={tmp_path / 'cache'}", "batches=9", caplog=caplog)
    assert code == 0 and "batches=9: the batch plan signal.batches has only 4 batches; running all of them" in log_text
    assert summary(tmp_path / "n")["nodes"]["smooth"]["cached"] + summary(tmp_path / "n")["nodes"]["smooth"]["computed"] == 4


def test_batches_beyond_the_plan_of_a_real_capture(tmp_path, shared_cache, caplog):
    # the case: accepted, then the run failed at the end with "no poses to join"
    run_dir = tmp_path / "far"
    code, log_text = run_main(run_dir, *SMALL, f"cache_dir={shared_cache}", "batches=1:5", caplog=caplog)
    assert code == 1
    s = summary(run_dir)
    cause = "batches='1:5' is out of range: the batch plan source.batches has 2 batches (0..1)"
    assert s["nodes"]["source"]["failed"] == [] and s["nodes"]["source"]["skipped"] == 0
    for n in DOWNSTREAM:
        assert s["nodes"][n]["skip_causes"][0]["cause"].startswith(cause), n
        assert s["nodes"][n]["computed"] == 0, n
    assert "no poses to join" not in log_text


# --- invalid choices and mistyped keys: refused before anything runs ------------------------------------------------
def test_invalid_choice_is_refused_before_anything_runs(tmp_path, caplog, capsys):
    run_dir = tmp_path / "side"
    code, log_text = run_main(run_dir, *SMALL, f"cache_dir={tmp_path / 'cache'}", "stages.track.direction=sideways",
                              caplog=caplog, capsys=capsys)
    assert code == 1
    assert ("node 'track': stages.track.direction: expected one of both | forward | backward, got 'sideways' "
            "(stage 'eklt')") in log_text
    assert log_text.count("sideways") == 1 + log_text.count("overrides:")  # said once, not once per batch
    assert not committed_entries(tmp_path / "cache") and not run_dir.exists()
    code, log_text = run_main(tmp_path / "loss", *SMALL, f"cache_dir={tmp_path / 'cache'}", "stages.refine.terms.sil.loss=hubber",
                              caplog=caplog, capsys=capsys)
    assert code == 1 and "expected one of l2 | huber, got 'hubber' (stage 'silhouette'); did you mean 'huber'?" \
        in log_text


def test_choices_are_checked_against_the_default_too():
    from dataclasses import dataclass

    from eventcap.artifacts import BatchPlan
    from eventcap.core.stage import Port, StageSpec, StageSpecError, param

    @dataclass
    class Bad:
        mode: str = param("sideways", help="a | b", choices=("a", "b"))

    with pytest.raises(StageSpecError, match=r"config field 'mode': default 'sideways' is not one of its choices"):
        StageSpec(name="bad", kind="x", version=1, description="", config=Bad, inputs={},
                  outputs={"batches": Port(BatchPlan)}, run="m:f")


def test_mistyped_key_gets_did_you_mean_without_a_plus(tmp_path, capsys):
    code = main(["run", *SMALL, f"cache_dir={tmp_path / 'cache'}", f"hydra.run.dir={tmp_path / 'r'}",
                 "stages.solve.icp_round=1"])
    err = capsys.readouterr().err
    assert code == 1
    assert err.startswith("eventcap run: stages.solve.icp_round: no config key named 'icp_round' in stages.solve "
                          "(config group stages/solve=batch: ")
    assert "conf/stages/solve/batch.yaml); did you mean 'icp_rounds'" in err
    assert "+stages" not in err and "not in struct" not in err
    assert not (tmp_path / "cache").exists()
    # a group name and a top-level key, each in its own file
    main(["run", *SMALL, f"hydra.run.dir={tmp_path / 'r'}", "source.duraton_s=1"])
    err = capsys.readouterr().err
    assert "source.duraton_s: no config key named 'duraton_s' in source (config group source=synthetic: " in err
    assert "did you mean 'duration_s'?" in err
    main(["run", *SMALL, f"hydra.run.dir={tmp_path / 'r'}", "cache_dirr=x"])
    err = capsys.readouterr().err
    assert "cache_dirr: no config key named 'cache_dirr' in the top-level config (" in err
    assert "conf/config.yaml); did you mean 'cache_dir'?" in err


# --- the cache directory -----------------------------------------------------------------------------------------------
def _cli(args, cwd, prefix=()):
    return subprocess.run([*prefix, sys.executable, "-m", "eventcap.apps.cli", *args], cwd=cwd, env=toy_env(),
                          capture_output=True, text=True, timeout=120)


def test_cache_commands_on_a_file_or_a_missing_path(toy, tmp_path, capsys):
    (tmp_path / "afile").write_text("not a cache")
    for action in (["ls"], ["explain", "abcd"], ["gc"]):
        assert main(["cache", *action, "--cache-dir", str(tmp_path / "afile")]) == 2
        err = capsys.readouterr().err
        assert err.strip() == (f"eventcap cache: cache_dir {tmp_path / 'afile'}: {tmp_path / 'afile'} is a file, "
                               f"not a directory; give the cache's directory")
        missing = tmp_path / "missing" / "cache"
        assert main(["cache", *action, "--cache-dir", str(missing)]) == 2
        assert f"{missing} does not exist" in capsys.readouterr().err
        assert not (tmp_path / "missing").exists()
    # a run refuses a file as its cache, before anything runs (before its run folder exists)
    code, log_text = run_main(tmp_path / "r", *TOY, f"cache_dir={tmp_path / 'afile'}")
    assert code == 1 and f"{tmp_path / 'afile'} is a file, not a directory" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()


@pytest.mark.skipif(sys.platform != "linux", reason="permissions as on Linux")
def test_unwritable_cache_dir_is_reported_as_such(tmp_path):
    prefix = ()
    if os.geteuid() == 0:  # root writes anywhere: drop the capabilities that let it
        if shutil.which("setpriv") is None:
            pytest.skip("running as root without setpriv")
        prefix = ("setpriv", "--bounding-set=-dac_override,-dac_read_search,-fowner")
    for i, layout in enumerate([(), ("entries", "tmp", "failures", "trash")]):  # a fresh directory; an existing cache
        cache = tmp_path / f"cache{i}"
        for sub in ("", *layout):
            (cache / sub).mkdir(parents=True, exist_ok=True)
        for d in [cache, *(cache / s for s in layout)]:
            d.chmod(0o555)
        p = _cli(["run", *TOY, f"cache_dir={cache}", f"hydra.run.dir={tmp_path / f'r{i}'}"], tmp_path, prefix)
        assert p.returncode == 1, p.stderr
        out = p.stdout + p.stderr
        assert f"cache_dir {cache}: not writable (permission denied: {cache}/" in out, out
        assert "cannot rename" not in out
