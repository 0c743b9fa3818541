"""A newcomer's first hour (issue 47): the default command on a real recording, simulate's shorthands in `run`,
where `preview` writes, what `run --help` shows, the metrics table and the closing line, and a CLI piped into a
reader that stops early."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys

import numpy as np
import pytest
from helpers.paths import REAL_DAVIS346, ROOT

from eventcap.apps.cli import main, preview_path, source_shorthands
from eventcap.apps.compose import groundless_detect_nodes
from eventcap.apps.jobs import metrics_table, run_folder_line


def run(tmp_path, name: str, *overrides: str) -> tuple[int, dict, list[str]]:
    """Exit code, run.json and the log's messages (the run folder's eventcap.log, without the time stamps)."""
    run_dir = tmp_path / name
    code = main(["run", f"cache_dir={tmp_path / 'cache'}", f"hydra.run.dir={run_dir}", "outputs.video=false",
                 *overrides])
    log = [line.partition("] - ")[2] for line in (run_dir / "eventcap.log").read_text().splitlines()
           if "] - " in line]
    return code, json.loads((run_dir / "run.json").read_text()), log


# -- a real recording runs with the default command ------------------------------------------------------------------
def test_the_real_davis346_file_gets_blazepose_by_itself(tmp_path):
    """No ground truth: the detector becomes BlazePose and the log says why; the file has no person in it, so the
    run stops at detect with BlazePose's own refusal (not with the simulated detector's "has no ground truth")."""
    code, summary, log = run(tmp_path, "real", "source=recording", f"source.path={REAL_DAVIS346}")
    assert code == 1
    assert f"{REAL_DAVIS346} has no ground truth (a recording from a camera, not a simulated capture): detecting " \
           f"with stages/detect=blazepose (the default detector is simulated from ground truth; give " \
           f"stages/detect=... to choose another, e.g. stages/detect=file stages.detect.path=<detections made " \
           f"elsewhere>)" in log
    detect = summary["nodes"]["detect"]
    assert detect["stage"] == "blazepose"
    [failure] = detect["failed"]
    assert failure["status"] == "no_person" and "no person in 3 of 3 images" in failure["error"]
    assert "ground truth" not in failure["error"]
    assert log[-2:] == ["run incomplete: detect failed (no_person); skipped because of it: 8 nodes (body, track, slice, "
                        "solve, stitch, cut, confidence, evaluate); the first error is above (detect); every failure "
                        "in full: run.json",
                        f"run folder {tmp_path / 'real'}/: config.yaml, eventcap.log, run.json"]  # nothing measured
    assert sum("no person in 3 of 3 images" in line for line in log) == 1  # once, where it happened


def test_a_detector_given_by_the_user_is_kept_and_its_refusal_names_blazepose(tmp_path):
    code, summary, log = run(tmp_path, "kept", "source=recording", f"source.path={REAL_DAVIS346}",
                             "stages/detect=simulated")
    assert code == 1 and not any("detecting with" in line for line in log)
    [failure] = summary["nodes"]["detect"]["failed"]
    assert "has no ground truth (a real recording?): use a real detector instead: stages/detect=blazepose " \
           "(BlazePose on the images) or detections made elsewhere, stages/detect=file stages.detect.path=<OpenPose " \
           "JSON folder, .npz or .csv>" in failure["error"]


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    """A tiny synthetic recording (0.09 s) in the project's format, with its ground truth and without."""
    import zarr

    from eventcap.artifacts.recording import Recording

    tmp = tmp_path_factory.mktemp("first_hour")
    assert main(["simulate", "duration_s=0.09", "template=procedural", "template.target_faces=2000",
                 f"cache_dir={tmp / 'cache'}", f"hydra.run.dir={tmp / 'sim'}"]) == 0
    with_truth = tmp / "sim" / "source.recording.zarr"
    rec = Recording.from_zarr(zarr.open_group(str(with_truth), mode="r"))
    assert rec.ground_truth is not None
    bare = tmp / "bare.zarr"
    dataclasses.replace(rec, ground_truth=None, name="bare").to_zarr(zarr.open_group(str(bare), mode="w"))
    return tmp, with_truth, bare


def test_a_synthetic_recording_without_ground_truth_runs_with_blazepose(simulated):
    tmp, _, bare = simulated
    code, summary, log = run(tmp, "bare", "source=recording", f"source.path={bare}", "template=procedural",
                             "template.target_faces=2000")
    assert any(line.startswith(f"{bare} has no ground truth") for line in log)
    detect = summary["nodes"]["detect"]
    assert detect["stage"] == "blazepose" and not any("ground truth" in f["error"] for f in detect["failed"])
    if code == 0:  # BlazePose found the person: the motion is written, measured by the data rate only
        assert (tmp / "bare" / "motion.npz").is_file()


def test_a_simulated_capture_read_as_a_recording_keeps_the_simulated_detector_and_says_so(simulated):
    tmp, with_truth, _ = simulated
    code, summary, log = run(tmp, "truth", "source=recording", f"source.path={with_truth}", "template=procedural",
                             "template.target_faces=2000", "batches=1")
    assert summary["nodes"]["detect"]["stage"] == "simulated"
    assert f"{with_truth} holds the ground truth of a simulated capture: detect detects from it with the simulated " \
           f"detector (stages/detect=blazepose runs a real one on its images)" in log


def test_which_sources_need_a_real_detector(simulated):
    _, with_truth, bare = simulated
    nodes = {"detect": {"inputs": {}}, "solve": {"config": "stages.spline"}}
    stages = {"detect": {"stage": "simulated"}, "spline": {"stage": "spline"}}

    def data(source, detect="simulated"):
        return {"source": source, "pipeline": {"nodes": nodes}, "stages": {**stages, "detect": {"stage": detect}}}

    assert groundless_detect_nodes(data({"stage": "recording", "path": str(bare)}))[0] == ["detect"]
    assert groundless_detect_nodes(data({"stage": "recording", "path": str(bare)}, "blazepose"))[0] == []
    assert groundless_detect_nodes(data({"stage": "recording", "path": str(with_truth)})) == ([], None)
    assert groundless_detect_nodes(data({"stage": "synthetic"})) == ([], None)
    assert groundless_detect_nodes(data({"stage": "recording", "path": str(REAL_DAVIS346)}))[0] == ["detect"]
    # a file that is not there is the source stage's to report
    assert groundless_detect_nodes(data({"stage": "recording", "path": "/nowhere.aedat4"})) == ([], None)


# -- simulate's shorthands -----------------------------------------------------------------------------------------
def test_run_and_simulate_take_the_same_shorthands():
    argv = ["duration_s=1", "motion=jumping_jack", "seed=3", "path=x.aedat4", "experiment=quick", "name=a",
            "pipeline=paper", "template.height_m=1.8", "+source.extra=1", "--cfg", "job", "unknown=1"]
    assert source_shorthands(argv) == ["source.duration_s=1", "source.motion=jumping_jack", "source.seed=3",
                                       "source.path=x.aedat4", "experiment=quick", "name=a", "pipeline=paper",
                                       "template.height_m=1.8", "+source.extra=1", "--cfg", "job", "unknown=1"]


def test_run_composes_a_shorthand_as_its_source_key(capsys):
    assert main(["run", "duration_s=0.5", "motion=jumping_jack", "--cfg", "job", "--package", "source"]) == 0
    out = capsys.readouterr().out
    assert "\nduration_s: 0.5\n" in out and "\nmotion: jumping_jack\n" in out


def test_a_shorthand_the_chosen_source_lacks_is_refused_naming_source_key(tmp_path, capsys):
    assert main(["run", "source=recording", f"source.path={REAL_DAVIS346}", "duration_s=1",
                 f"hydra.run.dir={tmp_path / 'r'}"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("eventcap run: source.duration_s: no config key named 'duration_s' in source (config "
                          "group source=recording")


# -- quiet ends ------------------------------------------------------------------------------------------------------
def test_metrics_print_as_a_short_table():
    metrics = {"evaluate.metrics": {"AE_mm": 25.882061651960786, "STD_mm": 0.5889730762245069,
                                    "AE_raw_mm": 25.955848408362286, "AE_nonRaw_mm": 25.853366802249095,
                                    "per_joint_mm": {f"j{i}": 20.0 + i for i in range(24)},
                                    "AE_rootrel_mm": 37.79706324789481, "MPJVE_mm_s": 315.520269416412,
                                    "accel_err_m_s2": 7.708903571322242, "peak_speed_err": 0.17890798408757755,
                                    "peak_speed_errors": [[None, 0.38934]] * 30, "n_frames": 25,
                                    "data_rate": {"total_MBps": 2.7194666666666665, "n_events": 26944}}}
    table = metrics_table(metrics)
    assert table.splitlines() == [
        "metrics of evaluate.metrics (every value: metrics.json)",
        "  AE (mm)          25.88    STD (mm)        0.5890",
        "  AE.raw (mm)      25.96    AE.nonRaw (mm)   25.85",
        "  AE.rootrel (mm)  37.80    MPJVE (mm/s)     315.5",
        "  Acc.err (m/s²)   7.709    peak speed err  0.1789",
        "  MB/s             2.719"]
    real = {"evaluate.metrics": {"evaluated": False, "reason": "recording 'x' has no ground truth: no joint errors "
                                                               "(data rate only)", "n_batches": 2,
                                 "data_rate": {"total_MBps": 2.126}}}
    assert metrics_table(real).splitlines() == [
        "metrics of evaluate.metrics (every value: metrics.json): recording 'x' has no ground truth: no joint "
        "errors (data rate only)", "  MB/s 2.126"]
    assert metrics_table({"other.metrics": {"n": 3, "rate": 0.5, "names": ["a"]}}).splitlines()[1] == \
        "  n         3    rate 0.5000"  # values right-aligned


def test_the_closing_line_names_the_run_folder_and_its_files(tmp_path, monkeypatch):
    run_dir = tmp_path / "runs" / "quick" / "ts"
    (run_dir / "overlay_frames").mkdir(parents=True)
    (run_dir / ".hydra").mkdir()
    for name in ("run.json", "motion.bvh", "config.yaml"):
        (run_dir / name).write_text("x")
    monkeypatch.chdir(tmp_path)
    assert run_folder_line(run_dir) == "run folder runs/quick/ts/: config.yaml, motion.bvh, overlay_frames/, run.json"
    monkeypatch.chdir(run_dir / "overlay_frames")
    assert run_folder_line(run_dir).startswith(f"run folder {run_dir}/: ")


# -- preview writes where the user is ------------------------------------------------------------------------------
def test_preview_writes_to_the_current_folder_or_out_never_beside_its_input(tmp_path, monkeypatch, capsys):
    from eventcap.events import make_events
    from eventcap.io import write_events

    data = tmp_path / "data"
    data.mkdir()
    rng = np.random.default_rng(0)
    ev = np.unique(make_events(np.sort(rng.integers(0, 100_000, 3000)), rng.integers(0, 64, 3000),
                               rng.integers(0, 48, 3000), rng.choice([-1, 1], 3000)))
    rec = data / "rec.h5"
    write_events(rec, ev, width=64, height=48, format="hdf5")
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    assert main(["preview", str(rec)]) == 0
    assert "wrote rec.preview.png (" in capsys.readouterr().out
    assert (work / "rec.preview.png").is_file() and sorted(p.name for p in data.iterdir()) == ["rec.h5"]
    out_dir = tmp_path / "pngs"
    out_dir.mkdir()
    assert main(["preview", str(rec), "--out", str(out_dir)]) == 0
    assert (out_dir / "rec.preview.png").is_file() and sorted(p.name for p in data.iterdir()) == ["rec.h5"]
    assert preview_path("runs/sim/source.recording.zarr") == preview_path("x/source.h5")  # the name: the stem
    assert str(preview_path("a/b.aedat4", "c.png")) == "c.png"


# -- run --help ----------------------------------------------------------------------------------------------------
def test_run_help_shows_groups_nodes_and_their_keys_not_the_config(capsys):
    assert main(["run", "--help"]) == 0
    text = capsys.readouterr().out
    lines = text.splitlines()
    assert len(lines) < 60 and max(map(len, lines)) <= 115
    assert "  source      where the recording comes from: recording | *synthetic" in lines
    assert any(line.split()[:4] == ["solve", "spline", "stages.solve", "stages/solve=all"] and "*spline" in line
               for line in lines)  # one vocabulary: the node solve at stages.solve, chosen with stages/solve=
    assert any(line.split()[:3] == ["detect", "simulated", "stages.detect"] and "*simulated" in line
               for line in lines)
    assert not any(line.split()[:1] == ["stage"] for line in lines)  # the stages' own defaults: an internal group
    assert "benchmark" not in text and "stages/refine" not in text and "stages/fuse" not in text  # not run here
    assert not any(line.strip() in ("nodes:", "inputs:", "defaults:") for line in lines)  # that is --cfg job
    assert main(["run", "pipeline=paper", "--help"]) == 0
    paper = capsys.readouterr().out.splitlines()
    assert any(line.split() == ["refine", "silhouette", "stages.refine", "stages/refine=*silhouette"]
               for line in paper)
    assert any(line.split()[:4] == ["solve", "batch", "stages.solve", "stages/solve=all"] for line in paper)
    assert not any(line.split()[:1] == ["stitch"] for line in paper)


def test_run_help_on_a_recording_says_what_the_run_picks_by_itself(capsys):
    assert main(["run", "source=recording", "--help"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert "On a file without ground truth the run takes stages/detect=blazepose by itself, unless stages/detect=... " \
           "is given." in lines
    assert "On a file without intensity frames it takes pipeline=events_only by itself." in lines
    assert main(["run", "source=recording", "stages/detect=file", "pipeline=paper", "--help"]) == 0
    assert "by itself" not in capsys.readouterr().out


def test_run_help_with_a_key_that_does_not_compose_says_so(capsys):
    assert main(["run", "stages.solve.nope=1", "--help"]) == 1
    assert "eventcap run: stages.solve.nope" in capsys.readouterr().err


# -- piped into a reader that stops early ----------------------------------------------------------------------------
@pytest.mark.parametrize("args", [["stages"], ["stages", "-v"], ["run", "--help"], ["run", "--cfg", "job"]])
def test_a_closed_pipe_ends_the_output_quietly(args):
    read, write = os.pipe()
    os.close(read)  # `| head` that has already gone: every write fails with EPIPE
    try:
        p = subprocess.run([sys.executable, "-m", "eventcap.apps.cli", *args], stdout=write, stderr=subprocess.PIPE,
                           text=True, cwd=ROOT, timeout=120)
    finally:
        os.close(write)
    assert p.returncode == 0 and p.stderr == ""


def test_a_setting_of_the_simulated_detector_on_a_real_file_says_what_to_choose(tmp_path, capsys):
    run_dir = tmp_path / "r"
    assert main(["run", "source=recording", f"source.path={REAL_DAVIS346}", "stages.detect.sigma_px=3",
                 f"cache_dir={tmp_path / 'cache'}", f"hydra.run.dir={run_dir}"]) == 1
    err = capsys.readouterr().err
    assert "the settings given do not fit stages/detect=blazepose, chosen for this recording: stages.detect.sigma_px: " \
           "no config key named 'sigma_px' in stages.detect (config group stages/detect=blazepose" in err
    assert err.rstrip().endswith("or choose yourself: stages/detect=...")
    assert not run_dir.exists()  # refused before the run folder was claimed
