"""Tests of `eventcap convert` / eventcap.io.convert: streamed conversion into the project's recording format."""

import os
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import zarr

import eventcap.artifact as base
from eventcap.artifacts import ArtifactError
from eventcap.artifact import ArrayAppender
from eventcap.artifacts.recording import Recording
from eventcap.apps.cli import main
from eventcap.events import EVENT_DTYPE
from eventcap.io import RawRecording, RecordingError, Roi, read_recording, write_events, write_recording
from eventcap.io.convert import (
    _StreamCheck,
    convert_recording,
    recording_from_raw,
    roi_from_corners,
    window_from_seconds,
)
from eventcap.core.testing import StageConformance

from helpers.fuzz_readers import synthetic_recording

ROOT = Path(__file__).resolve().parents[1]
REAL = Path(__file__).resolve().parent / "data" / "real" / "davis346_lab_aps.aedat4"  # shipped (tests/data/real/SOURCE.md)


@pytest.fixture(scope="module")
def synth() -> RawRecording:
    return synthetic_recording()  # 64 x 48, ~1500 events over 90 ms, 3 frames, a calibration


@pytest.fixture
def small_chunks(monkeypatch):
    """Zarr chunks of 1 KiB instead of 4 MiB, so small files exercise multi-chunk appends (both in the converter and
    in Artifact.to_zarr, which share the chunking rule)."""
    monkeypatch.setattr(base, "_CHUNK_BYTES", 1024)


def _read_back(path) -> Recording:
    return Recording.from_zarr(zarr.open_group(str(path), mode="r"), where=str(path))


def _layout(group, prefix=""):
    """Every node's stored metadata: group attributes, array shape/chunks/dtype/codecs/attributes."""
    out = {prefix or "/": dict(group.attrs)}
    for name, node in group.members():
        if isinstance(node, zarr.Group):
            out.update(_layout(node, f"{prefix}/{name}"))
        else:
            out[f"{prefix}/{name}"] = node.metadata.to_dict()
    return out


def _write(fmt, tmp_path, rec: RawRecording) -> tuple[Path, dict]:
    """``rec`` written in ``fmt``; returns the path and the size arguments the format needs to be read."""
    if fmt in ("hdf5", "npz", "rpg"):
        return write_recording(tmp_path / f"in_{fmt}", rec, format=fmt), {}
    if fmt == "npy":
        path = tmp_path / "in.npy"
        arr = rec.events.copy()
        arr["t"] += rec.t_offset_us
        np.save(path, arr)
        return path, {"width": rec.width, "height": rec.height}
    return write_events(tmp_path / f"in_{fmt}", rec.events, width=rec.width, height=rec.height, format=fmt,
                        t_offset_us=rec.t_offset_us), {}


# ---------------------------------------------------------------------------------------------------- round trips
@pytest.mark.parametrize("fmt", ["aedat4", "evt2", "evt3", "dat", "npy", "hdf5", "npz", "rpg"])
def test_round_trip_each_format(synth, tmp_path, small_chunks, fmt):
    path, size = _write(fmt, tmp_path, synth)
    out = tmp_path / "out.zarr"
    stats = convert_recording(path, out, chunk_events=100, format=fmt, **size)
    back = _read_back(out)
    raw = read_recording(path, format=fmt, **size)
    np.testing.assert_array_equal(back.events.events, raw.events)
    np.testing.assert_array_equal(back.events.events, synth.events)
    assert (back.width, back.height) == (64, 48)
    assert stats["events"] == stats["events_read"] == len(synth.events) and stats["t_offset_us"] == synth.t_offset_us
    if fmt in ("hdf5", "npz", "rpg"):  # formats with frames and a calibration
        np.testing.assert_array_equal(back.frames.images, synth.frames.images)
        np.testing.assert_array_equal(back.frames.t_us, [2_000, 42_000, 82_000])
        exposure = [0, 0, 0] if fmt == "rpg" else [4_000] * 3  # rpg does not record exposures
        np.testing.assert_array_equal(back.frames.exposure_us, exposure)
        assert (back.camera.fx, back.camera.fy, back.camera.cx, back.camera.cy) == (60.0, 61.0, 31.5, 23.5)
        assert "calibration from the file" in back.source and stats["frames"] == 3
    else:
        assert back.frames is None and "UNCALIBRATED" in back.source and stats["frames"] == 0
    # Everything (camera, source text with t_offset and repairs) equals the in-memory path.
    assert back.equals(recording_from_raw(raw))
    # ... and so does the stored layout, chunk for chunk (events here span several 1 KiB chunks).
    ref = zarr.open_group(str(tmp_path / "ref.zarr"), mode="w")
    recording_from_raw(raw).to_zarr(ref)
    got = _layout(zarr.open_group(str(out), mode="r"))
    assert got == _layout(ref)
    assert got["/events/events/t"]["chunk_grid"]["configuration"]["chunk_shape"] == (128,)
    assert sorted(p.name for p in tmp_path.iterdir() if ".partial" in p.name) == []


def test_real_davis346(tmp_path):
    stats = convert_recording(REAL, tmp_path / "real.zarr", chunk_events=20_000)
    rec = _read_back(tmp_path / "real.zarr")
    assert (rec.width, rec.height) == (346, 260)
    assert rec.events.events.size == 117_667 and stats["events"] == 117_667
    assert rec.frames.images.shape == (3, 260, 346) and stats["frames"] == 3
    np.testing.assert_array_equal(rec.frames.t_us, [2954, 42954, 82954])
    np.testing.assert_array_equal(rec.frames.exposure_us, [4773, 4773, 4773])
    assert rec.events.events["t"][-1] == 129_999 and stats["t_offset_us"] == 1_633_953_690_975_950
    assert rec.equals(recording_from_raw(read_recording(REAL)))
    assert rec.name == "davis346_lab_aps" and "repairs: none" in rec.source


def test_array_appender_matches_whole_array_layout(tmp_path, small_chunks):
    rng = np.random.default_rng(1)
    for n in (0, 1, 127, 128, 129, 1000):
        data = rng.normal(size=(n, 3)).astype(np.float32)  # rows of 12 bytes: 85 per 1 KiB chunk
        whole = zarr.open_group(str(tmp_path / f"whole{n}"), mode="w")
        base._write_array(whole, "a", data, "m")
        parts = zarr.open_group(str(tmp_path / f"parts{n}"), mode="w")
        app = ArrayAppender(parts, "a", np.float32, (3,), units="m")
        for a in range(0, n, 37):
            app.append(data[a:a + 37])
        assert app.close() == n
        assert parts["a"].metadata.to_dict() == whole["a"].metadata.to_dict()
        np.testing.assert_array_equal(parts["a"][...], data)
    with pytest.raises(ValueError, match=r"expected rows of dtype float32 and shape \(3,\), got float64"):
        ArrayAppender(parts, "b", np.float32, (3,)).append(np.zeros((2, 3)))


# --------------------------------------------------------------------------------------- window, ROI, calibration
def test_window_roi_and_calibration_match_the_stage_path(synth, tmp_path):
    path = write_recording(tmp_path / "s.h5", synth, format="hdf5")
    calib = tmp_path / "calib.txt"
    calib.write_text("100 101 32.5 24.5 -0.1 0.01 0 0 0\n")
    roi = roi_from_corners([10, 5, 40, 35])
    assert roi == Roi(10, 5, 30, 30)
    window = window_from_seconds(0.03, 0.06)
    assert window == (30_000, 60_000)
    stats = convert_recording(path, tmp_path / "w.zarr", chunk_events=64, time_window_us=window, roi=roi,
                              calibration=calib)
    rec = _read_back(tmp_path / "w.zarr")
    ref = recording_from_raw(read_recording(path, time_window_us=window, roi=roi), calibration=calib, roi=roi)
    assert rec.equals(ref)
    ev = rec.events.events
    assert (rec.width, rec.height) == (30, 30) and ev["t"].min() >= 30_000 and ev["t"].max() < 60_000
    assert ev["x"].max() < 30 and ev["y"].max() < 30 and 0 < len(ev) < len(synth.events) / 3
    np.testing.assert_array_equal(rec.frames.t_us, [42_000])  # the one frame whose exposure centre is inside
    assert rec.frames.images.shape == (1, 30, 30)
    np.testing.assert_array_equal(rec.frames.images[0], synth.frames.images[1, 5:35, 10:40])
    # The full sensor's principal point, moved by the ROI's corner.
    assert (rec.camera.fx, rec.camera.cx, rec.camera.cy) == (100.0, 22.5, 19.5)
    assert f"calibration {calib}" in rec.source
    # The file declares its size, so decoding stopped after the window: fewer events read than the file holds.
    assert stats["stopped_at_window_end"] and stats["events_read"] < len(synth.events)


def test_recording_stage_reads_roi_corners_like_convert(synth, tmp_path):
    path = write_recording(tmp_path / "s.npz", synth, format="npz")

    class RecordingStage(StageConformance):
        stage_name = "recording"

        def make_inputs(self):
            return {}

    staged = RecordingStage().run_once(path=str(path), roi=[10, 5, 40, 35], t_start_s=0.01)["recording"]
    convert_recording(path, tmp_path / "c.zarr", roi=[10, 5, 30, 30], time_window_us=window_from_seconds(0.01, 0))
    assert (staged.width, staged.height) == (30, 30)
    # the stage also puts the camera into a y-up world (a file has no extrinsics: a level camera is assumed)
    import dataclasses

    from eventcap.camera import level_rotation

    back = _read_back(tmp_path / "c.zarr")
    assert np.array_equal(staged.camera.R, level_rotation()) and np.array_equal(back.camera.R, np.eye(3))
    assert staged.equals(dataclasses.replace(back, camera=back.camera.with_pose(level_rotation(), np.zeros(3)),
                                                     world="assumed_level"))


def test_size_inferred_when_the_file_has_none(synth, tmp_path):
    path = write_events(tmp_path / "ev_rpg", synth.events, width=64, height=48, format="rpg")  # no frames: no size
    convert_recording(path, tmp_path / "r.zarr", chunk_events=200)
    rec = _read_back(tmp_path / "r.zarr")
    raw = read_recording(path)
    assert (rec.width, rec.height) == (raw.width, raw.height) == (int(synth.events["x"].max()) + 1,
                                                                   int(synth.events["y"].max()) + 1)
    assert "inferred" in rec.source and rec.equals(recording_from_raw(raw))


def test_bad_options(synth, tmp_path):
    path, _ = _write("evt3", tmp_path, synth)
    with pytest.raises(ValueError, match=r"roi Roi\(x=60, y=0, width=10, height=10\) does not lie inside the 64 × 48"):
        convert_recording(path, tmp_path / "o.zarr", roi=(60, 0, 10, 10))
    with pytest.raises(RecordingError, match=r"no events in the time window \[200000, 300000\) µs: .* 0\.\.\d+ µs"):
        convert_recording(path, tmp_path / "o.zarr", time_window_us=(200_000, 300_000))
    with pytest.raises(ValueError, match="expected start < end"):
        convert_recording(path, tmp_path / "o.zarr", time_window_us=(5, 5))
    with pytest.raises(ValueError, match=r"expected 0 <= x0 < x1 and 0 <= y0 < y1 .* got \[5, 0, 5, 10\]"):
        roi_from_corners([5, 0, 5, 10])
    with pytest.raises(ValueError, match="expected 0 <= t_start_s < t_end_s"):
        window_from_seconds(0.5, 0.2)
    with pytest.raises(ValueError, match="chunk_events must be ≥ 1, got 0"):
        convert_recording(path, tmp_path / "o.zarr", chunk_events=0)
    assert window_from_seconds(0, 0) is None and window_from_seconds(0.5, 0)[0] == 500_000
    assert not (tmp_path / "o.zarr").exists()


def test_stream_check_names_the_row():
    check = _StreamCheck(64, 48)
    ev = np.zeros(3, EVENT_DTYPE)
    ev["t"], ev["p"] = [10, 20, 30], 1
    check(ev)
    later = ev.copy()
    later["t"] = [29, 40, 50]
    with pytest.raises(ArtifactError, match=r"not sorted at row 3 \(30 > 29 us\)"):
        check(later)
    wide = ev.copy()
    wide["t"], wide["x"] = [30, 31, 32], [0, 64, 0]
    with pytest.raises(ArtifactError, match="x=64 at row 4 outside the sensor"):
        check(wide)
    badp = ev.copy()
    badp["t"], badp["p"] = [30, 31, 32], [1, 0, 1]
    with pytest.raises(ArtifactError, match="polarity 0 at row 4"):
        check(badp)


# ------------------------------------------------------------------------------------------- errors leave nothing
def _leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("out.zarr"))


@pytest.mark.parametrize("corruption", ["time_back", "polarity", "garbage"])
def test_corrupted_input_leaves_nothing(synth, tmp_path, corruption):
    path = write_events(tmp_path / "c.h5", synth.events, width=64, height=48, t_offset_us=synth.t_offset_us)
    if corruption == "garbage":
        path = tmp_path / "c.aedat4"
        path.write_bytes(b"#!AER-DAT4.0\r\n" + np.random.default_rng(0).bytes(3001))
    else:
        with h5py.File(path, "r+") as f:  # event 1200: far back in time, or a polarity of 7
            if corruption == "time_back":
                f["events/t"][1200] = synth.t_offset_us
            else:
                f["events/p"][1200] = 7
    with pytest.raises(RecordingError) as err:
        convert_recording(path, tmp_path / "out.zarr", chunk_events=100)
    if corruption == "time_back":
        assert "cannot sort in bounded memory" in str(err.value) and "event index 1200" in str(err.value)
    elif corruption == "polarity":
        assert "polarity 7 is not one of the encodings" in str(err.value)
    else:
        assert "c.aedat4: file header:" in str(err.value)
    assert _leftovers(tmp_path) == []


def test_interrupted_conversion_leaves_nothing(synth, tmp_path):
    path, _ = _write("evt2", tmp_path, synth)

    def interrupt(written, read, seconds):
        if read >= 500:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        convert_recording(path, tmp_path / "out.zarr", chunk_events=100, progress=interrupt)
    assert _leftovers(tmp_path) == []


def test_killed_conversions_folder_is_removed_next_time(synth, tmp_path):
    path, _ = _write("evt3", tmp_path, synth)
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    stale = tmp_path / f"out.zarr.partial-{int(dead.stdout)}"
    (stale / "events").mkdir(parents=True)
    convert_recording(path, tmp_path / "out.zarr")
    assert _leftovers(tmp_path) == ["out.zarr"]


def test_refuses_to_overwrite(synth, tmp_path):
    path, _ = _write("dat", tmp_path, synth)
    out = tmp_path / "out.zarr"
    convert_recording(path, out)
    before = _read_back(out)
    with pytest.raises(FileExistsError, match="out.zarr exists: pass overwrite=True"):
        convert_recording(path, out, roi=(0, 0, 10, 10))
    assert _read_back(out).equals(before)
    convert_recording(path, out, roi=(0, 0, 10, 10), overwrite=True)
    assert _read_back(out).width == 10 and _leftovers(tmp_path) == ["out.zarr"]
    folder = tmp_path / "notes"
    folder.mkdir()
    (folder / "keep.txt").write_text("mine")
    with pytest.raises(ValueError, match="is not a recording in the project's format: refusing to replace it"):
        convert_recording(path, folder, overwrite=True)
    assert (folder / "keep.txt").read_text() == "mine"
    with pytest.raises(ValueError, match="overlaps the input"):
        convert_recording(path, path, overwrite=True)
    with pytest.raises(ValueError, match="already a recording in the project's format"):
        convert_recording(out, tmp_path / "again.zarr")


# ---------------------------------------------------------------------------------------------------------- CLI
def test_cli_convert(synth, tmp_path, capsys):
    path = write_recording(tmp_path / "s.npz", synth, format="npz")
    out = tmp_path / "out.zarr"
    assert main(["convert", str(path), str(out), "--t-start", "0.01", "--roi", "0", "0", "32", "24",
                 "--chunk-events", "500"]) == 0
    text = capsys.readouterr().out
    rec = _read_back(out)
    assert f"wrote {out}: {len(rec.events.events):,} events" in text and "32x24 (width x height), from npz" in text
    assert "calibration from the file" in text and "0 repair(s)" in text
    assert rec.events.events["t"].min() >= 10_000
    assert main(["convert", str(path), str(out)]) == 2
    assert capsys.readouterr().err.strip() == f"eventcap convert: {out} exists: pass overwrite=True (--overwrite) " \
                                              f"to replace it"
    assert main(["convert", str(path), str(out), "--overwrite"]) == 0
    assert _read_back(out).width == 64
    capsys.readouterr()
    assert main(["convert", str(path), str(tmp_path / "b.zarr"), "--width", "64"]) == 2
    assert "eventcap convert: give both --width and --height or neither" in capsys.readouterr().err
    assert main(["convert", str(path), str(tmp_path / "b.zarr"), "--roi", "0", "0", "100", "10"]) == 2
    assert "eventcap convert: roi Roi(x=0, y=0, width=100, height=10) does not lie inside" in capsys.readouterr().err
    assert main(["convert", str(tmp_path / "missing.raw"), str(tmp_path / "b.zarr")]) == 2
    assert capsys.readouterr().err.strip() == f"eventcap convert: {tmp_path / 'missing.raw'}: no such file or folder"
    assert not (tmp_path / "b.zarr").exists()


def test_cli_subprocess_exit_codes(synth, tmp_path):
    path, _ = _write("evt3", tmp_path, synth)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    cmd = [sys.executable, "-m", "eventcap.apps.cli", "convert", str(path), str(tmp_path / "o.zarr")]
    ok = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT)
    assert ok.returncode == 0, ok.stderr
    assert f"{len(synth.events):,} events" in ok.stdout and "UNCALIBRATED" in ok.stdout
    again = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT)
    assert again.returncode == 2 and again.stderr.startswith("eventcap convert: ") and "exists" in again.stderr
