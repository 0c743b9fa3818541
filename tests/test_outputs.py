"""Run outputs (eventcap/apps/outputs.py): motion.bvh, motion.npz and overlay.mp4 written by the core after a run from the
committed per-batch poses, the ``outputs:`` config, and runs that cannot have them."""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path

import numpy as np
import pytest

from eventcap.body.kinematics import joint_positions
from eventcap.body.motions import motion_poses
from eventcap.export.bvh import read_motion_npz
from eventcap.apps.outputs import OutputsConfig, check_outputs_config, video_frame_indices
from eventcap.core.runner import Runner
from helpers.runs import known_poses_config, run_with_outputs

TESTS = Path(__file__).resolve().parent
ROOT = TESTS.parent


pytestmark = pytest.mark.usefixtures("known_poses")  # conftest: tests/output_stages.py registered


def test_bvh_npz_and_video_of_a_tiny_run(tmp_path):
    import cv2
    from helpers.bvh_reference import positions_via_bvh_package, stacked

    run_dir = tmp_path / "run"
    runner, result, summary = run_with_outputs(known_poses_config(tmp_path / "cache", video_every_ms=4, video_png_frames=3), run_dir)
    assert result.ok and summary["problems"] == [] and \
        set(summary["written"]) == {"bvh", "npz", "video", "plausibility"}
    assert json.loads((run_dir / "plausibility.json").read_text())["findings"] == []  # the true jumping jack
    tpl = runner.load_output(result, "template.template")[None]
    parts = runner.load_output(result, "solve.poses")
    assert sorted(parts) == [0, 1]
    # npz: the joined motion (the shared boundary frame once), joints = FK of the poses on the template
    m = read_motion_npz(run_dir / "motion.npz")
    t0, t1 = parts[0].t_us[0], parts[1].t_us[-1]
    assert np.array_equal(m["t_us"], np.arange(t0, t1 + 1, 1000))
    assert np.allclose(m["poses"], motion_poses("jumping_jack", m["t_us"] * 1e-6), atol=1e-12)
    assert np.abs(m["joints"] - joint_positions(m["poses"], tpl)).max() < 1e-9
    # bvh: read back by an independent parser, 1000 fps, the same joints within 1e-6 m
    text = (run_dir / "motion.bvh").read_text()
    assert f"Frames: {m['t_us'].size}\nFrame Time: 0.001\n" in text
    got = stacked(positions_via_bvh_package(run_dir / "motion.bvh"))
    assert np.abs(got - joint_positions(m["poses"], tpl.rest_joints)).max() < 1e-6
    # video: readable, the expected frame count and size, PNGs of some frames
    n = video_frame_indices(m["t_us"], 4, 500).size
    assert n == m["t_us"].size // 4 + 1
    cap = cv2.VideoCapture(str(run_dir / "overlay.mp4"))
    assert cap.isOpened()
    frames = 0
    while True:
        ok, img = cap.read()
        if not ok:
            break
        frames += 1
        assert img.shape == (180 * 2, 240 * 2 + 180 * 2, 3)
    cap.release()
    assert frames == n
    assert video_codec(run_dir / "overlay.mp4") == ("h264", "yuv420p", n)  # plays in a browser
    assert len(list((run_dir / "overlay_frames").glob("*.png"))) == 3
    assert not list(run_dir.glob("*.partial*"))
    assert json.loads((run_dir / "run.json").read_text())["outputs"]["written"]["bvh"].endswith("motion.bvh")


def video_codec(path) -> tuple[str, str, int]:
    """(codec, pixel format, decoded frames) of a video's first stream, as FFmpeg (through PyAV) reads it."""
    import av

    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        frames = sum(1 for _ in container.decode(stream))
        return stream.codec_context.name, stream.codec_context.pix_fmt, frames


def test_overlay_falls_back_to_opencv_without_pyav_and_says_so(tmp_path, caplog, monkeypatch):
    """Without PyAV the video is OpenCV's MPEG-4 Part 2, and the log says which codec and why."""
    import builtins

    real_import = builtins.__import__

    def no_av(name, *args, **kwargs):
        if name == "av":
            raise ImportError("No module named 'av'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_av)
    with caplog.at_level(logging.INFO, logger="eventcap.apps.outputs"):
        _, result, summary = run_with_outputs(known_poses_config(tmp_path / "cache", bvh=False, npz=False, video_every_ms=10,
                                        video_png_frames=0), tmp_path / "run")
    monkeypatch.setattr(builtins, "__import__", real_import)
    assert summary["problems"] == [] and set(summary["written"]) == {"video", "plausibility"}
    assert "codec MPEG-4 Part 2 (OpenCV mp4v; browsers do not play it: H.264 needs PyAV, pip install av; " \
           "ImportError: No module named 'av')" in caplog.text
    codec, _, frames = video_codec(tmp_path / "run" / "overlay.mp4")
    assert codec == "mpeg4" and frames == 9


def test_outputs_are_skipped_with_a_log_line_when_the_poses_node_failed(tmp_path, caplog):
    cfg = known_poses_config(tmp_path / "cache")
    cfg["stages"]["solve"]["fail_batches"] = [-1]
    with caplog.at_level(logging.INFO, logger="eventcap.apps.outputs"):  # INFO: the run's summary reports the cause
        _, result, summary = run_with_outputs(cfg, tmp_path / "run")
    assert not result.ok and summary["written"] == {} and summary["problems"] == []
    assert result.committed("solve") == {}
    assert "node 'solve' committed no poses (failed batches: 0, 1)" in caplog.text
    assert "outputs: skipped (bvh, npz, video)" in caplog.text
    assert not any((tmp_path / "run").glob("motion.*")) and not (tmp_path / "run" / "overlay.mp4").exists()


def test_a_failed_batch_leaves_a_gap_that_no_output_fills(tmp_path, caplog):
    """Batch 1 of 3 fails: motion.npz keeps its frames as a gap (NaN, estimated false, in gaps_us); BVH cannot mark
    one, so it is cut into one file per stretch, each exact; nothing is interpolated."""
    from helpers.bvh_reference import positions_via_bvh_package, stacked

    cfg = known_poses_config(tmp_path / "cache", video=False)
    cfg["source"]["duration_s"] = 0.13  # 4 intensity frames: 3 batches
    cfg["stages"]["solve"]["fail_batches"] = [1]
    with caplog.at_level(logging.WARNING, logger="eventcap.apps.outputs"):
        runner, result, summary = run_with_outputs(cfg, tmp_path / "run")
    assert set(summary["written"]) == {"bvh", "npz", "plausibility"}
    parts = runner.load_output(result, "solve.poses")
    assert sorted(parts) == [0, 2]
    m = read_motion_npz(tmp_path / "run" / "motion.npz")
    est = m["estimated"]
    assert np.array_equal(m["t_us"][est], np.concatenate([parts[0].t_us, parts[2].t_us]))
    assert np.isnan(m["poses"][~est]).all() and (~est).sum() == 39 and m["gaps_us"].shape == (1, 2)
    assert np.array_equal(m["t_us"], np.arange(m["t_us"][0], m["t_us"][-1] + 1, 1000))
    assert "committed 2 batch(es); 1 failed" in caplog.text and "no motion.bvh" in caplog.text
    assert not (tmp_path / "run" / "motion.bvh").exists()
    for n, part in ((1, parts[0]), (2, parts[2])):  # each stretch exact, no frame of the gap
        got = stacked(positions_via_bvh_package(tmp_path / "run" / f"motion_part{n:02d}.bvh"))
        assert got.shape[0] == part.t_us.size
        k = np.searchsorted(m["t_us"], part.t_us)
        assert np.abs(got - m["joints"][k]).max() < 1e-6


def test_recording_without_ground_truth_still_gets_every_output(tmp_path):
    """A real recording (the project's zarr format, no ground truth) through source=recording."""
    import zarr

    runner, result, _ = run_with_outputs(known_poses_config(tmp_path / "cache", bvh=False, npz=False, video=False), tmp_path / "sim")
    rec = runner.load_output(result, "source.recording")[None]
    real = dataclasses.replace(rec, ground_truth=None, name="real")
    path = tmp_path / "real.zarr"
    real.to_zarr(zarr.open_group(str(path), mode="w"))
    cfg = known_poses_config(tmp_path / "cache", video_every_ms=10)
    cfg["source"] = {"stage": "recording", "path": str(path)}
    runner, result, summary = run_with_outputs(cfg, tmp_path / "run")
    assert result.ok and summary["problems"] == [] and \
        set(summary["written"]) == {"bvh", "npz", "video", "plausibility"}
    assert runner.load_output(result, "source.recording")[None].ground_truth is None


def test_outputs_config_is_checked():
    with pytest.raises(ValueError, match=r"outputs\.vidoe: no config key named 'vidoe' in outputs; did you mean 'video'\? Available: poses, join, bvh"):
        OutputsConfig.from_mapping({"vidoe": True})
    with pytest.raises(ValueError, match=r"outputs\.video_every_ms: expected a finite number > 0, got 0"):
        OutputsConfig.from_mapping({"video_every_ms": 0})
    with pytest.raises(ValueError, match=r"outputs\.bvh: expected true or false, got 'maybe'"):
        OutputsConfig.from_mapping({"bvh": "maybe"})
    with pytest.raises(ValueError, match=r"outputs\.poses: expected '<node>\.<port>'"):
        OutputsConfig.from_mapping({"poses": "solve"})
    assert OutputsConfig.from_mapping(None) == OutputsConfig()


def test_outputs_config_is_checked_against_the_pipeline(tmp_path, caplog):
    with pytest.raises(ValueError, match=r"outputs\.poses: 'solve\.pose': node 'solve' \(stage 'known_poses'\) has "
                                         r"no output 'pose' \(outputs: poses\)"):
        check_outputs_config(Runner(known_poses_config(tmp_path, poses="solve.pose")))
    with pytest.raises(ValueError, match=r"'source\.recording' is a Recording, expected PoseSequence"):
        check_outputs_config(Runner(known_poses_config(tmp_path, poses="source.recording")))
    with caplog.at_level(logging.WARNING, logger="eventcap.apps.outputs"):
        assert check_outputs_config(Runner(known_poses_config(tmp_path, poses="refine.poses"))).poses is None
    assert "this pipeline has no node 'refine'" in caplog.text


def test_unknown_outputs_key_is_refused_by_eventcap_run(tmp_path):
    import subprocess
    import sys

    p = subprocess.run([sys.executable, "-m", "eventcap.apps.cli", "run", "+outputs.colour=red", "hydra.run.dir=x"],
                       cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert p.returncode == 1
    assert "outputs.colour: no config key named 'colour' in outputs" in p.stdout + p.stderr


def test_video_frame_indices():
    t = np.arange(0, 1_001_000, 1000, dtype=np.int64)  # 1 s at 1 kHz
    assert np.array_equal(video_frame_indices(t, 2, 1000), np.arange(0, 1001, 2))
    idx = video_frame_indices(t, 2, 500)  # 501 frames wanted: the step widens to cover the whole second
    assert idx.size <= 500 and idx[0] == 0 and idx[-1] >= 990
    gap = np.concatenate([t[:100], t[500:]])  # a gap: frames after it are still found
    assert np.all(np.diff(gap[video_frame_indices(gap, 10, 500)]) >= 10_000)


def test_label_stays_inside_its_box_and_is_readable():
    import cv2

    from eventcap.imaging.viz import label

    img = np.full((40, 300, 3), 200, np.uint8)
    text = "batch 2: 30 tracks, 9643 events"
    label(img, text, (6, 18), 0.5)
    (w, h), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.5, 1)
    changed = np.argwhere(np.any(img != 200, axis=-1))
    # Every changed pixel is in the darkened box around the text (no outline copy drifting along the line).
    assert changed[:, 1].max() <= 6 + w + 3 and changed[:, 0].min() >= 18 - h - 3
    box = img[18 - h - 3:18 + base + 1, 3:6 + w + 3]
    assert (box <= 66).mean() > 0.5 and box.max() >= 200  # dark box, white glyphs
