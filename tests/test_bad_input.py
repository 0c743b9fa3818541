"""Bad input is never silently wrong and never stuck (issue 48): each row of the issue's table, with the message
that names the file, the event index or the key, and what was done (docs/io-robustness.md)."""

from __future__ import annotations

import contextlib
import os
import re
import signal
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from helpers import bad_inputs as bi

from eventcap.apps.cli import main
from eventcap.io import RecordingError, iter_event_chunks, read_recording
from eventcap.io.convert import convert_recording


@contextlib.contextmanager
def hang_guard(seconds: int = 20):
    """Fail instead of waiting forever if a check regresses (a FIFO opened for reading blocks)."""
    def stuck(*_):
        raise TimeoutError(f"still running after {seconds} s")

    old = signal.signal(signal.SIGALRM, stuck)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


@pytest.fixture(scope="module")
def ev():
    return bi.events()


def _abs(r):
    out = r.events.copy()
    out["t"] += r.t_offset_us
    return out


# ------------------------------------------------------------------------------------------------------ time
def test_a_wild_last_timestamp_is_dropped_with_its_index(tmp_path, ev, capsys):
    wild = ev.copy()
    wild["t"][-1] = ev["t"][0] + 10**12
    path = bi.save_npy(tmp_path / "wild.npy", wild)
    r = read_recording(path)
    n = len(ev)
    np.testing.assert_array_equal(_abs(r), ev[:-1])
    assert any(f"dropped 1 event(s) with wild times, cut off from the others by jumps in time: event index {n - 1} at "
               f"{ev['t'][0] + 10**12} µs (file time), at the end of the file" in s for s in r.repairs)
    stream = iter_event_chunks(path, 1000, width=240, height=180)
    np.testing.assert_array_equal(np.concatenate(list(stream)), r.events)  # streaming decides the same
    stats = convert_recording(path, tmp_path / "w.zarr")
    assert stats["events"] == n - 1 and stats["t_last_us"] < 100_000
    assert main(["preview", str(path), "--out", str(tmp_path / "w.png")]) == 0
    assert f"{n - 1:,} events over 0.100 s" in capsys.readouterr().out


def test_a_jump_of_hours_with_events_on_both_sides_is_refused_naming_the_index(tmp_path, ev):
    jumped = ev.copy()
    k = len(ev) // 2
    jumped["t"][k:] += 2 * 3600 * 10**6
    path = bi.save_npy(tmp_path / "jump.npy", jumped)
    with pytest.raises(RecordingError) as err:
        read_recording(path)
    assert f"{path}: event index {k}: time jumps by 2 h between neighbouring events (from {jumped['t'][k - 1]} to " \
           f"{jumped['t'][k]} µs, file time), with more than 100 events on each side" in str(err.value)
    assert "max_gap_s= (source.max_gap_s, --max-gap-s)" in str(err.value)
    with pytest.raises(RecordingError, match=f"event index {k}: time jumps by 2 h"):
        convert_recording(path, tmp_path / "j.zarr")
    assert not (tmp_path / "j.zarr").exists() and not list(tmp_path.glob("j.zarr.partial-*"))
    r = read_recording(path, max_gap_s=3 * 3600, time_unit="us")  # a real pause, said so (and the unit)
    np.testing.assert_array_equal(_abs(r), jumped)


def test_a_flipped_bit_of_an_evt2_time_word_drops_its_events_with_a_note(tmp_path, ev):
    """Bit 20 of one EVT_TIME_HIGH set: its events lie 2^26 µs (67 s) late, as the file says, and time goes back at
    the next word. Our decoder keeps both (no wrap invented, no clamp): the time checks drop the late events, named."""
    path = bi.evt2_flipped(tmp_path, ev)
    r = read_recording(path)
    assert not any("2^34" in s for s in r.repairs)
    got = _abs(r)
    want = ev.copy()
    want["t"] += 1_633_000_000_000_000 - ev["t"][0]  # the file's t0 is the header's
    # the events of the damaged 64-µs slot are dropped (named); every other event is the original, at its time
    assert len(ev) - 100 < len(got) < len(ev) and np.all(np.isin(got.view(np.void), want.view(np.void)))
    assert int(r.events["t"][-1]) < 100_000
    assert any("dropped 2 event(s) with wild times" in s and "between a jump of 67.1 s and one back" in s
               for s in r.repairs)
    assert len(got) == len(ev) - 2


def test_time_standing_still_after_a_jump_cuts_the_recording(tmp_path, ev):
    stuck = ev.copy()
    k = 3000
    stuck["t"][k:] = stuck["t"][k - 1] + 300 * 10**6  # 5 min later, then time stands still (a decoder's clamp)
    path = bi.save_npy(tmp_path / "stuck.npy", stuck)
    r = read_recording(path)
    np.testing.assert_array_equal(_abs(r), ev[:k])
    assert any(f"cut the recording at event index {k}: time jumps by 5 min there" in s and
               f"dropped the {len(ev) - k} event(s) from there to the end" in s for s in r.repairs)


def test_integer_times_read_as_seconds_are_refused_naming_source_time_unit(tmp_path, ev, capsys):
    rel = ev.copy()
    rel["t"] -= rel["t"][0]
    path = bi.save_csv(tmp_path / "int_us.csv", rel)
    with pytest.raises(RecordingError) as err:
        read_recording(path)
    msg = str(err.value)
    span = int(rel["t"][-1])
    gap = int(np.median(np.diff(rel["t"][:1000])))
    assert f"{path}: the time column holds whole numbers; read as s (the default for floating-point columns) its " \
           f"first 1,000 events come {gap} s apart (the median), {1 / gap:.2g} events/s, below any event camera's " \
           f"rate" in msg
    assert f"Set it: source.time_unit=us ({1e6 / gap:.3g} events/s)" in msg
    assert main(["convert", str(path), str(tmp_path / "c.zarr")]) == 2
    assert "source.time_unit=us" in capsys.readouterr().err and not (tmp_path / "c.zarr").exists()
    r = read_recording(path, time_unit="us")
    assert int(r.events["t"][-1]) == span and len(r.events) == len(ev)


def test_more_events_per_microsecond_than_any_sensor_is_refused(tmp_path, ev):
    flat = ev.copy()
    flat["t"] = flat["t"][0]
    flat = flat[np.unique(flat[["x", "y", "p"]], return_index=True)[1]]
    path = bi.save_npy(tmp_path / "flat.npy", flat)
    with pytest.raises(RecordingError, match=re.escape(f"{len(flat):,} events within 1 µs: {len(flat):.3g} events per "
                                                       f"µs, more than any event sensor makes (at most 2,000)")):
        read_recording(path)


# ----------------------------------------------------------------------------------------------------- sizes
def test_a_few_coordinates_beyond_a_known_sensor_are_outliers(tmp_path, ev):
    bad = bi.outliers_x(ev, 0.01)
    k = int((bad["x"] >= 240).sum())
    r = read_recording(bi.save_npy(tmp_path / "o1.npy", bad))
    assert (r.width, r.height) == (240, 180) and len(r.events) == len(ev) - k
    assert any(f"dropped {k} outlier event(s): " in s and "event(s) at x >= 240, outside the 240 × 180 block "
               "(DAVIS240C) the others fill" in s for s in r.repairs)


@pytest.mark.parametrize("share", [0.1, 0.5, 0.9, 1.0])
def test_many_coordinates_beyond_the_dense_block_are_refused(tmp_path, ev, share):
    bad = bi.outliers_x(ev, share)
    for path in (bi.save_npy(tmp_path / "o.npy", bad), bi.save_csv(tmp_path / "o.csv", bad, seconds=True)):
        with pytest.raises(RecordingError) as err:
            read_recording(path)
        msg = str(err.value)
        assert msg.startswith(str(path)) and "740 × 180" in msg, msg
        if share == 0.1:
            k = int((bad["x"] >= 240).sum())
            assert f"{k:,} of {len(ev):,} events (10 %) lie at x >= 240, outside the 240 × 180 block (DAVIS240C's " \
                   f"size) that the others fill" in msg and "--width 740 --height 180 --roi 0 0 240 180" in msg
        else:
            assert "the events span 740 × 180 px (4.1:1), no event sensor's shape" in msg
    if share == 0.1:  # the advice works: the block, the outliers dropped on purpose
        r = read_recording(tmp_path / "o.npy", width=740, height=180, roi=(0, 0, 240, 180))
        assert len(r.events) == int((bad["x"] < 240).sum())


# ------------------------------------------------------------------------------------------------ truncation
def test_an_evt3_file_cut_inside_an_event_group_is_noted_and_one_cut_after_an_event_cannot_be(tmp_path, ev):
    r = read_recording(bi.evt3_cut(tmp_path, ev, inside_group=True))
    assert any("the file ends inside an EVT3 event group" in s for s in r.repairs)
    r = read_recording(bi.evt3_cut(tmp_path, ev, inside_group=False))  # docs/io-robustness.md says so
    assert r.repairs == () and len(r.events) < len(ev)


# ------------------------------------------------------------------------------------------ not regular files
def _not_regular(tmp_path) -> dict[str, tuple[Path, str]]:
    fifo = tmp_path / "fifo.raw"
    os.mkfifo(fifo)
    loop = tmp_path / "loop.aedat4"
    os.symlink(loop.name, loop)
    zero = tmp_path / "zero.npy"
    os.symlink("/dev/zero", zero)
    rnd = tmp_path / "random.raw"
    os.symlink("/dev/urandom", rnd)
    dangling = tmp_path / "gone.h5"
    os.symlink(tmp_path / "nothing-here.h5", dangling)
    folder = tmp_path / "folder"
    folder.mkdir()
    (folder / "zarr.json").write_bytes(b"\x00garbage")
    return {"fifo": (fifo, "a named pipe (FIFO), not a recording file: refused without opening it"),
            "loop": (loop, "a loop of symbolic links (the link leads back to itself): not a file"),
            "zero": (zero, "a character device (a link to /dev/zero), not a recording file"),
            "urandom": (rnd, "a character device (a link to /dev/urandom), not a recording file"),
            "dangling": (dangling, f"a symbolic link to {tmp_path / 'nothing-here.h5'}, which does not exist"),
            "zarr": (folder / "zarr.json", "not valid JSON")}


def test_files_that_are_not_regular_files_are_refused_at_once(tmp_path, capsys):
    cases = _not_regular(tmp_path)
    with hang_guard():
        for name, (path, message) in cases.items():
            target = path.parent if name == "zarr" else path
            with pytest.raises(RecordingError) as err:
                read_recording(target)
            assert str(err.value) == f"{path}: {message}" or str(err.value).startswith(f"{path}: {message}"), name
            with pytest.raises(RecordingError, match="^" + str(path)):
                convert_recording(target, tmp_path / f"{name}.zarr")
            assert main(["preview", str(target), "--out", str(tmp_path / "p.png")]) == 2
            err_lines = capsys.readouterr().err.strip().splitlines()
            assert len(err_lines) == 1 and err_lines[0].startswith(f"eventcap preview: {path}: {message}"), name
            assert main(["convert", str(target), str(tmp_path / "c.zarr")]) == 2
            assert capsys.readouterr().err.startswith(f"eventcap convert: {path}: {message}"), name
    with pytest.raises(ValueError, match="loop of symbolic links"):  # an output path that loops
        convert_recording(bi.save_npy(tmp_path / "ok.npy", bi.events(500)), cases["loop"][0])


def test_an_rpg_folder_whose_events_file_is_a_pipe_is_refused(tmp_path):
    folder = tmp_path / "rpg"
    folder.mkdir()
    os.mkfifo(folder / "events.txt")
    with hang_guard(), pytest.raises(RecordingError, match=r"events.txt: a named pipe \(FIFO\)"):
        read_recording(folder)


# ---------------------------------------------------------------------------------------------------- memory
def test_the_most_active_moment_takes_memory_for_events_not_for_time():
    from eventcap.events import EVENT_DTYPE
    from eventcap.imaging.viz import most_active_time

    ev = np.zeros(4, EVENT_DTYPE)
    ev["t"] = [0, 10, 20, 10**12]
    tracemalloc.start()
    t, count = most_active_time(ev, 20_000)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert (t, count) == (10_000, 3) and peak < 1_000_000  # the grid of 4e8 windows was 6.3 GB
    # the same answer as counting every window of the grid, on spans the grid can hold
    rng = np.random.default_rng(3)
    for _ in range(50):
        e = np.zeros(int(rng.integers(1, 400)), EVENT_DTYPE)
        e["t"] = np.sort(rng.integers(0, 300_000, len(e)))
        step = 20_000 // 8
        starts = np.arange(int(e["t"][0]), max(int(e["t"][-1]) - 20_000, int(e["t"][0])) + step, step)
        counts = np.searchsorted(e["t"], starts + 20_000) - np.searchsorted(e["t"], starts)
        assert most_active_time(e, 20_000) == (int(starts[np.argmax(counts)]) + 10_000, int(counts.max()))


def test_a_zarr_shape_of_1e15_is_refused_by_preview_without_a_traceback(tmp_path):
    """Issue 57: `eventcap preview` of a recording whose time array's zarr.json declares 1e15 rows ended in a
    MemoryError traceback; the declared size is now checked against the chunk files before anything is read."""
    import json
    import subprocess
    import sys

    from helpers import fuzz_readers

    path = fuzz_readers.write_entry("zarr", tmp_path, fuzz_readers.synthetic_recording())
    meta = path / "events" / "events" / "t" / "zarr.json"
    doc = json.loads(meta.read_text())
    doc["shape"] = [10**15]
    meta.write_text(json.dumps(doc))
    p = subprocess.run([sys.executable, "-m", "eventcap.apps.cli", "preview", str(path), "--out", str(tmp_path / "p.png")],
                       capture_output=True, text=True, timeout=120)
    out = p.stdout + p.stderr
    assert p.returncode == 2 and "Traceback" not in out and "MemoryError" not in out
    assert f"{meta}): declares shape (1000000000000000,) of int64 (8,000,000,000,000,000 bytes) in " \
           f"666,666,666,667 chunk files, and the folder holds 1" in out
    assert not (tmp_path / "p.png").exists()
