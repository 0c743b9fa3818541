"""Sensor size and damaged files (issue 38): a file that does not declare its size gets one only when its events fit
a plausible sensor; width/height given by the user override the inference and are checked against the events; a
random file named .aedat4 is called not an AEDAT4 file; an EVT3 file cut on a word boundary is noticed where the
format shows it; a picture of an enormous sensor is refused before it is allocated."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from eventcap.io import RecordingError, read_recording
from eventcap.io.convert import convert_recording
from eventcap.io.prophesee import write_prophesee

N = 100_000


def npy(path: Path, x, y) -> Path:
    """An unnamed (N, 4) t, x, y, p array: the kind of file that declares no sensor size."""
    t = np.arange(len(x), dtype=np.int64) * 10
    np.save(path, np.stack([t, x, y, np.arange(len(x)) % 2], axis=1).astype(np.int64))
    return path


@pytest.fixture
def coords():
    rng = np.random.default_rng(0)
    return rng.integers(0, 346, N), rng.integers(0, 260, N), rng


def test_a_plausible_recording_gets_its_size(tmp_path, coords):
    x, y, _ = coords
    rec = read_recording(npy(tmp_path / "ok.npy", x, y), columns="t,x,y,p")
    assert (rec.width, rec.height) == (346, 260) and len(rec.events) == N


def test_a_fifth_of_the_events_far_out_is_refused_with_the_count(tmp_path, coords):
    x, y, rng = coords
    x = x.copy()
    far = rng.random(N) < 0.2
    x[far] = 65_531
    path = npy(tmp_path / "far.npy", x, y)
    with pytest.raises(RecordingError) as err:
        read_recording(path, columns="t,x,y,p")
    msg = str(err.value)
    assert f"{int(far.sum()):,} of 100,000 events (20 %) lie outside every known event sensor (the largest: " \
           f"1280 × 960 px; x up to 65531, y up to 259)" in msg
    assert "65532 × 260 is not a plausible sensor" in msg and "pass width= and height=" in msg
    # the user's size overrides the inference and is checked against the events
    with pytest.raises(RecordingError, match=r"x = 65531 is outside the sensor \(width 346\)"):
        read_recording(path, columns="t,x,y,p", width=346, height=260)
    rec = read_recording(path, columns="t,x,y,p", width=65_532, height=260)  # the user says it is that big
    assert rec.width == 65_532 and len(rec.events) == N
    with pytest.raises(RecordingError, match=rf"{int(far.sum()):,} of 100,000 events .* pass --width and --height, or "
                                             rf"crop with --roi"):
        convert_recording(path, tmp_path / "far.zarr", columns="t,x,y,p")
    assert not (tmp_path / "far.zarr").exists()


def test_a_few_events_outside_every_known_sensor_are_dropped_and_noted(tmp_path, coords):
    x, y, rng = coords
    x = x.copy()
    idx = rng.choice(N, 50, replace=False)  # 0.05 %, spread from 400 to 4000: no gap rule catches them
    x[idx] = np.linspace(400, 4000, 50).astype(int)
    rec = read_recording(npy(tmp_path / "few.npy", x, y), columns="t,x,y,p")
    # those beyond every known sensor, and those beyond the DAVIS346's edge that the others fill (issue 48: not a
    # 1,200-pixel-wide sensor)
    assert len(rec.events) == N - 50 and (rec.width, rec.height) == (346, 260)
    assert any("inferred 346 × 260" in r and "dropped 50 outlier event(s)" in r for r in rec.repairs)


def test_all_zero_events_are_not_a_one_pixel_sensor(tmp_path):
    path = npy(tmp_path / "zero.npy", np.zeros(1000, int), np.zeros(1000, int))
    with pytest.raises(RecordingError, match=r"the 1,000 events span only x <= 0 and y <= 0, a 1 × 1 sensor: not a "
                                             r"camera's"):
        read_recording(path, columns="t,x,y,p")
    rec = read_recording(path, columns="t,x,y,p", width=240, height=180)  # a size from the user: fine
    assert (rec.width, rec.height) == (240, 180)


def test_a_random_file_named_aedat4_is_not_an_aedat4_file(tmp_path):
    path = tmp_path / "rec.aedat4"
    path.write_bytes(np.random.default_rng(1).bytes(4096))
    with pytest.raises(RecordingError, match=r"not an AEDAT4 file: a \.aedat4 file starts with b'#!AER-DAT4\.0', "
                                             r"this one with b'"):
        read_recording(path)


def _evt(tmp_path: Path, fmt: str) -> bytes:
    n = 2000
    ev = np.zeros(n, np.dtype([("t", "<u8"), ("x", "<u2"), ("y", "<u2"), ("on", "?")]))
    ev["t"], ev["x"], ev["y"], ev["on"] = np.arange(n) * 10, np.arange(n) % 300, (np.arange(n) * 7) % 200, True
    path = tmp_path / f"full.{fmt}.raw"
    write_prophesee(path, iter([ev]), fmt, 320, 240)
    return path.read_bytes()


def test_an_evt3_file_cut_inside_an_event_group_is_noted(tmp_path):
    data = _evt(tmp_path, "evt3")
    words = np.frombuffer(data[-40:], "<u2")
    # cut after the last EVT_ADDR_Y word (type 0x0): the ADDR_X after it, the event itself, is gone
    last_y = len(words) - 1 - int(np.argmax((words[::-1] >> 12) == 0x0))
    cut = tmp_path / "cut.raw"
    cut.write_bytes(data[:len(data) - 40 + 2 * (last_y + 1)])
    rec = read_recording(cut)
    assert len(rec.events) == 1999
    assert any("the file ends inside an EVT3 event group: an EVT_ADDR_Y (the row of the events that follow it) is "
               "followed by no event (only 0 time word(s))" in r for r in rec.repairs)
    # issue 48: a time word after the ADDR_Y (as faery writes ADDR_Y, TIME_LOW, ADDR_X when time moves on)
    time_low = next(int(w) for w in words[::-1] if w >> 12 == 0x6)
    cut.write_bytes(data[:len(data) - 40 + 2 * (last_y + 1)] + np.array([time_low], "<u2").tobytes())
    rec = read_recording(cut)
    assert len(rec.events) == 1999 and any("is followed by no event (only 1 time word(s))" in r for r in rec.repairs)
    whole = tmp_path / "whole.raw"
    whole.write_bytes(data)
    assert not any("truncated" in r for r in read_recording(whole).repairs)


def test_an_evt2_file_cut_between_words_cannot_be_told(tmp_path):
    """Documented in eventcap/io/prophesee.py: EVT2 words stand alone, the file stores no length."""
    data = _evt(tmp_path, "evt2")
    cut = tmp_path / "cut.raw"
    cut.write_bytes(data[:-8])
    rec = read_recording(cut)
    assert len(rec.events) == 1998 and not any("truncated" in r for r in rec.repairs)


def test_a_picture_of_an_enormous_sensor_is_refused_before_allocating():
    from eventcap.imaging.viz import check_picture_size

    check_picture_size(1280, 720, 2)
    with pytest.raises(ValueError, match=r"a 65532 × 260 sensor at scale 2 makes 131064 × 520 panels \(0\.2 GiB "
                                         r"each\): larger than any event camera's"):
        check_picture_size(65_532, 260, 2)
    with pytest.raises(ValueError, match=r"65535 × 65535 sensor at scale 2 .*\(48\.0 GiB each\)"):
        check_picture_size(65_535, 65_535, 2)


def test_the_project_format_with_a_random_name(tmp_path):
    """Not an extension problem: a random .npz is called what it is not."""
    path = tmp_path / "rec.npz"
    path.write_bytes(os.urandom(512))
    with pytest.raises(RecordingError, match=r"not a NumPy \.npz \(zip\) file"):
        read_recording(path)
