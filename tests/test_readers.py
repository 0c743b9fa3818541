"""Tests of eventcap.io: the real AEDAT4 file, round trips per format, streaming, and each kind of bad input."""

import logging
from pathlib import Path

import h5py
import numpy as np
import pytest

from eventcap.events import EVENT_DTYPE, make_events
from eventcap.io import (
    RawRecording,
    RecordingError,
    Roi,
    detect_format,
    iter_event_chunks,
    read_recording,
    write_events,
    write_recording,
)
from eventcap.io.recording import Frames

from helpers.fuzz_readers import synthetic_recording

REAL = Path(__file__).resolve().parent / "data" / "real" / "davis346_lab_aps.aedat4"  # shipped (tests/data/real/SOURCE.md)
T0 = 1_633_000_000_000_000  # a plausible epoch-µs offset, as DV writes


@pytest.fixture(scope="module")
def real():
    return read_recording(REAL)


@pytest.fixture(scope="module")
def synth():
    return synthetic_recording()


def _events(n=200, width=64, height=48, seed=0):
    """Sorted, duplicate-free events with distinct times (so any reordering is visible)."""
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.integers(1, 500, n))
    return make_events(t, rng.integers(0, width, n), rng.integers(0, height, n), rng.choice([-1, 1], n))


def _npz(path, **arrays):
    np.savez(path, **arrays)
    return path


def _abs(r: RawRecording) -> np.ndarray:
    out = r.events.copy()
    out["t"] += r.t_offset_us
    return out


# ----------------------------------------------------------------------------------------------- the real file
def test_real_aedat4_numbers(real):
    assert (real.width, real.height) == (346, 260)
    assert len(real.events) == 117_667
    assert real.format == "aedat4" and real.repairs == ()
    assert real.t_offset_us == 1_633_953_690_975_950  # µs since the epoch of the first event
    t = real.events["t"]
    assert t[0] == 0 and t[-1] == 129_999 and np.all(np.diff(t) >= 0)  # 0.13 s
    assert set(np.unique(real.events["p"])) == {-1, 1}
    assert real.events["x"].max() == 345 and real.events["y"].max() == 259


def test_real_aedat4_frames(real):
    f = real.frames
    assert len(f) == 3 and f.images.shape == (3, 260, 346) and f.images.dtype == np.float32
    assert 0.0 <= f.images.min() and f.images.max() <= 1.0
    # Exposure from the frame packets' exposure begin/end (4.773 ms), times at the exposure centre, 40 ms apart.
    np.testing.assert_array_equal(f.exposure_us, [4773, 4773, 4773])
    np.testing.assert_array_equal(f.t_us, [2954, 42954, 82954])
    assert abs(float(f.images.mean()) * 255 - 51.2) < 0.5  # mean grey level of the APS frames


def test_real_aedat4_streams_identically(real):
    chunks = iter_event_chunks(REAL, chunk_events=10_000)
    assert (chunks.width, chunks.height, chunks.t_offset_us) == (346, 260, real.t_offset_us)
    parts = list(chunks)
    assert all(len(p) <= 10_000 + 200 for p in parts) and len(parts) >= 11
    np.testing.assert_array_equal(np.concatenate(parts), real.events)
    assert chunks.repairs == ()


# -------------------------------------------------------------------------------------------------- round trips
@pytest.mark.parametrize("fmt,name", [("aedat4", "r.aedat4"), ("evt2", "r2.raw"), ("evt3", "r3.raw"),
                                      ("dat", "r.dat"), ("hdf5", "r.h5"), ("npz", "r.npz"), ("rpg", "rpg")])
def test_round_trip_real_events(real, tmp_path, fmt, name):
    path = write_events(tmp_path / name, real.events, width=346, height=260, format=fmt, t_offset_us=real.t_offset_us)
    size = {"width": 346, "height": 260} if fmt == "rpg" else {}  # rpg keeps the size only in its frames
    back = read_recording(path, **size)
    assert back.format == fmt
    assert (back.width, back.height, back.t_offset_us) == (346, 260, real.t_offset_us)
    np.testing.assert_array_equal(back.events, real.events)
    assert back.repairs == ()
    np.testing.assert_array_equal(np.concatenate(list(iter_event_chunks(path, 5000, **size))), real.events)


@pytest.mark.parametrize("fmt,name", [("hdf5", "s.h5"), ("npz", "s.npz"), ("rpg", "srpg")])
def test_round_trip_frames_calibration_ground_truth(synth, tmp_path, fmt, name):
    gt = {"t_us": np.array([0, 500, 1000]), "pose": np.arange(21, dtype=np.float64).reshape(3, 7) / 7}
    rec = RawRecording(synth.events, synth.width, synth.height, synth.t_offset_us, synth.path, "synthetic",
                       synth.frames, synth.calibration, gt)
    back = read_recording(write_recording(tmp_path / name, rec, format=fmt))
    np.testing.assert_array_equal(back.events, rec.events)
    assert back.t_offset_us == rec.t_offset_us and back.repairs == ()
    np.testing.assert_array_equal(back.frames.images, rec.frames.images)  # k/255 levels survive 8-bit PNG too
    np.testing.assert_array_equal(back.frames.t_us, rec.frames.t_us)
    if fmt == "rpg":
        assert back.frames.exposure_us is None  # the layout does not record exposure
    else:
        np.testing.assert_array_equal(back.frames.exposure_us, rec.frames.exposure_us)
    c, d = back.calibration, rec.calibration
    assert (c.width, c.height, c.fx, c.fy, c.cx, c.cy) == (d.width, d.height, d.fx, d.fy, d.cx, d.cy)
    np.testing.assert_array_equal(c.dist, d.dist)
    np.testing.assert_array_equal(back.ground_truth["t_us"], gt["t_us"])
    np.testing.assert_allclose(back.ground_truth["pose"], gt["pose"], rtol=0, atol=1e-15)


def test_write_refuses_what_the_format_cannot_hold(synth, tmp_path):
    ev = synth.events
    with pytest.raises(ValueError, match="stores events only"):
        write_recording(tmp_path / "x.raw", synth, format="evt3")
    unsorted = ev[::-1].copy()
    with pytest.raises(ValueError, match="time goes backwards"):
        write_events(tmp_path / "u.h5", unsorted, width=64, height=48)
    with pytest.raises(ValueError, match="x outside the sensor width 32"):
        write_events(tmp_path / "o.npz", ev, width=32, height=48)
    with pytest.raises(ValueError, match="negative file time"):
        write_events(tmp_path / "n.raw", ev, width=64, height=48, t_offset_us=-10)
    # A failed write leaves neither the target nor its temporary file behind.
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_write_streams_chunks_from_a_reader(real, tmp_path):
    """A bounded-memory conversion: chunks in, chunks out, same events and clock."""
    src = iter_event_chunks(REAL, chunk_events=20_000)
    out = write_events(tmp_path / "conv.h5", src, width=src.width, height=src.height, t_offset_us=src.t_offset_us)
    back = read_recording(out)
    np.testing.assert_array_equal(back.events, real.events)
    assert back.t_offset_us == real.t_offset_us


# ---------------------------------------------------------------------------------------------- format handling
def test_detect_format_by_content_not_extension(tmp_path):
    ev = _events()
    p = write_events(tmp_path / "a.h5", ev, width=64, height=48)
    disguised = tmp_path / "events.dat"
    disguised.write_bytes(p.read_bytes())
    assert detect_format(disguised) == "hdf5"
    np.testing.assert_array_equal(read_recording(disguised).events["x"], ev["x"])


@pytest.mark.parametrize("content,match", [
    (b"", "the file is empty"),
    (b"#!AER-DAT2.0\r\n# something", "contains no events"),
    (b"#!AER-DAT3.0\r\n#!END-HEADER\r\n", "AEDAT version 3.0 is not supported"),
    (b"#!AER-DAT3.1\r\n# no end", "no '#!END-HEADER' line"),
    (b"#!AER-DAT2.0\r\n# AEChip: ch.unizh.ini.jaer.chip.cochlea.CochleaAMS1c\r\n", "unsupported chip"),
    (b"hello world", r"not an AEDAT file: a \.aedat file starts with b'#!AER-DAT', this one with b'hello world'"),
])
def test_unreadable_files_are_named(tmp_path, content, match):
    path = tmp_path / "rec.aedat"
    path.write_bytes(content)
    with pytest.raises(RecordingError, match=match) as err:
        read_recording(path)
    assert str(path) in str(err.value) and isinstance(err.value, ValueError)


def test_missing_file_and_unknown_format_argument(tmp_path):
    with pytest.raises(RecordingError, match="no such file"):
        read_recording(tmp_path / "nope.h5")
    p = write_events(tmp_path / "a.npz", _events(), width=64, height=48)
    with pytest.raises(ValueError, match="unknown format 'csv'"):
        read_recording(p, format="csv")


def test_hdf5_layouts(tmp_path):
    ev = _events()
    # DSEC-like: events/{t,x,y,p} with uint32 relative times, a t_offset and no size (→ inferred, noted).
    p = tmp_path / "dsec.h5"
    with h5py.File(p, "w") as f:
        g = f.create_group("events")
        g["t"], g["x"], g["y"], g["p"] = ev["t"].astype(np.uint32), ev["x"], ev["y"], (ev["p"] > 0).astype(np.uint8)
        f["t_offset"] = np.int64(T0)
    r = read_recording(p)
    assert r.t_offset_us == T0 + ev["t"][0]
    np.testing.assert_array_equal(r.events["t"], ev["t"] - ev["t"][0])
    np.testing.assert_array_equal(r.events["p"], ev["p"])
    assert (r.width, r.height) == (int(ev["x"].max()) + 1, int(ev["y"].max()) + 1)
    assert any("inferred" in s for s in r.repairs)
    # Compound dataset with aliases, float seconds, declared size.
    p = tmp_path / "compound.h5"
    rec = np.empty(len(ev), [("timestamp", "f8"), ("x", "u2"), ("y", "u2"), ("polarity", "i1")])
    rec["timestamp"], rec["x"], rec["y"], rec["polarity"] = ev["t"] / 1e6, ev["x"], ev["y"], ev["p"]
    with h5py.File(p, "w") as f:
        f["events"] = rec
        f.attrs["width"], f.attrs["height"] = 64, 48
    r = read_recording(p)
    np.testing.assert_array_equal(_abs(r), ev)
    assert r.repairs == () and (r.width, r.height) == (64, 48)
    # MVSEC-like (N, 4) float array, columns x, y, t, p without names: recognised by the time-ordered column.
    p = tmp_path / "mvsec.h5"
    with h5py.File(p, "w") as f:
        f["events"] = np.stack([ev["x"], ev["y"], ev["t"] / 1e6, ev["p"]], axis=1).astype(np.float64)
    r = read_recording(p, width=64, height=48)
    np.testing.assert_array_equal(_abs(r), ev)
    assert r.repairs == ("2-D event array without column names: read as (x, y, t, p) (column 2 is time-ordered)",)


def test_hdf5_missing_datasets(tmp_path):
    p = tmp_path / "none.h5"
    with h5py.File(p, "w") as f:
        f["images"] = np.zeros((2, 4, 4), np.uint8)
    with pytest.raises(RecordingError, match=r"no event data: .* found \['images'\]"):
        read_recording(p)
    p = tmp_path / "nop.h5"
    with h5py.File(p, "w") as f:
        for k in "txy":
            f[f"events/{k}"] = np.arange(5)
    with pytest.raises(RecordingError, match="no event data"):
        read_recording(p)


def test_npz_missing_keys_and_npy_layouts(tmp_path):
    with pytest.raises(RecordingError, match=r"no event data: expected arrays t, x, y, p .* found \['t', 'x'\]"):
        read_recording(_npz(tmp_path / "k.npz", t=np.arange(3), x=np.arange(3)))
    ev = _events()
    table = np.stack([ev["t"], ev["x"], ev["y"], ev["p"]], axis=1).astype(np.int64) + [T0, 0, 0, 0]
    np.save(tmp_path / "tab.npy", table)
    r = read_recording(tmp_path / "tab.npy", width=64, height=48)
    np.testing.assert_array_equal(_abs(r), make_events(ev["t"] + T0, ev["x"], ev["y"], ev["p"]))
    assert r.repairs == ("2-D event array without column names: read as (t, x, y, p) (column 0 is time-ordered)",)
    with pytest.raises(ValueError, match="declares a 64 × 48 sensor"):
        read_recording(write_events(tmp_path / "a.npz", ev, width=64, height=48), width=65, height=48)


# --------------------------------------------------------------------------------------------------- bad input
def test_unsorted_timestamps_are_sorted_and_reported(tmp_path, caplog):
    ev = _events()
    shuffled = ev.copy()
    shuffled[[10, 11]] = shuffled[[11, 10]]
    shuffled[[50, 150]] = shuffled[[150, 50]]
    p = _npz(tmp_path / "u.npz", t=shuffled["t"], x=shuffled["x"], y=shuffled["y"], p=shuffled["p"], width=64,
             height=48)
    with caplog.at_level(logging.WARNING, logger="eventcap.io"):
        r = read_recording(p)
    np.testing.assert_array_equal(_abs(r), ev)
    largest = max(ev["t"][150] - ev["t"][51], ev["t"][149] - ev["t"][50])
    assert r.repairs == ((f"sorted events by time: time went backwards at 3 place(s) (first at event index 11: "
                          f"{ev['t'][10]} µs after {ev['t'][11]} µs; largest step back {largest} µs)"),)
    assert "sorted events by time" in caplog.text and str(p) in caplog.text


def test_duplicates_are_dropped_and_reported(tmp_path):
    ev = _events()
    dup = np.insert(ev, [20, 20, 101], ev[[19, 19, 100]])
    p = write_events(tmp_path / "d.h5", dup, width=64, height=48)
    r = read_recording(p)
    np.testing.assert_array_equal(r.events["t"] + r.t_offset_us, ev["t"])
    assert r.repairs == ("dropped 3 duplicated event(s) (same t, x, y, p as an earlier one; first at event index 20)",)
    # Same time and pixel with the other polarity is not a duplicate.
    other = dup[:21].copy()
    other[20]["p"] = -other[20]["p"]
    assert len(read_recording(write_events(tmp_path / "o.npz", other, width=64, height=48)).events) == 21


def test_uint32_time_wraparound_is_unwrapped(tmp_path):
    # Two wraps of a 32-bit µs counter (every step < 2^31 µs, as in a live recording; pauses of 36 min between
    # these few events, accepted with max_gap_s).
    t_true = np.array([2**32 - 300, 2**32 - 200, 2**32 - 100, 2**32 + 50, 2**32 + 2**31, 2**33 - 10, 2**33 + 5])
    t32 = (t_true % 2**32).astype(np.uint32)
    n = len(t_true)
    p = _npz(tmp_path / "w.npz", t=t32, x=np.arange(n), y=np.zeros(n, int), p=np.ones(n, int), width=8, height=8)
    r = read_recording(p, max_gap_s=3600)
    np.testing.assert_array_equal(_abs(r)["t"], t_true)
    assert r.t_offset_us == 2**32 - 300
    assert r.repairs == (("unwrapped 2 wrap-around(s) of the 32-bit timestamp counter (+2^32 µs each; first at "
                          "event index 3)"),)
    # Streaming carries the wrap over chunk boundaries.
    stream = iter_event_chunks(p, chunk_events=2, max_gap_s=3600)
    np.testing.assert_array_equal(np.concatenate(list(stream))["t"] + stream.t_offset_us, t_true)


@pytest.mark.parametrize("fmt,name,step_us,n", [
    ("evt3", "a.raw", 2_000, 20_000),  # 40 s: two wraps of EVT3's 24-bit counter (16.8 s)
    ("dat", "c.dat", 15_000_000, 600),  # 2.5 h: two wraps of DAT's 32-bit counter (71.6 min)
    ("evt2", "b.raw", 60_000_000, 600),  # 10 h: two wraps of EVT2's 34-bit counter (4.8 h)
])
def test_format_counter_wraparound_round_trips(tmp_path, fmt, name, step_us, n):
    i = np.arange(n)
    ev = make_events(i * step_us, i % 64, i % 48, np.where(i % 2, 1, -1))
    r = read_recording(write_events(tmp_path / name, ev, width=64, height=48, format=fmt, t_offset_us=T0))
    np.testing.assert_array_equal(r.events, ev)
    assert r.t_offset_us == T0 and r.repairs == ()


def test_writer_refuses_gaps_the_counters_cannot_carry(tmp_path):
    ev = make_events([0, 15_000_000, 30_000_000], [1, 2, 3], [1, 2, 3], [1, -1, 1])
    with pytest.raises(ValueError, match="cannot write EVT3: events at 15000000 µs and 30000000 µs"):
        write_events(tmp_path / "a.raw", ev, width=4, height=4, format="evt3")
    gap = make_events([0, 2**31], [1, 2], [1, 2], [1, -1])
    with pytest.raises(ValueError, match="cannot write DAT: .* a gap of 2\\^31 µs or more"):
        write_events(tmp_path / "a.dat", gap, width=4, height=4)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("p_values,expected", [
    (np.array([0, 1, 1, 0]), [-1, 1, 1, -1]),
    (np.array([-1, 1, 1, -1]), [-1, 1, 1, -1]),
    (np.array([False, True, True, False]), [-1, 1, 1, -1]),
    (np.array([0.0, 1.0, 1.0, 0.0]), [-1, 1, 1, -1]),
    (np.array([1, 1, 1, 1], np.uint8), [1, 1, 1, 1]),
], ids=["zero-one", "minus-plus", "bool", "float", "all-on"])
def test_polarity_encodings_map_to_plus_minus_one(tmp_path, p_values, expected):
    p = _npz(tmp_path / "p.npz", t=np.arange(4), x=np.arange(4), y=np.arange(4), p=p_values, width=4, height=4)
    r = read_recording(p)
    np.testing.assert_array_equal(r.events["p"], expected)
    assert r.events["p"].dtype == np.int8 and r.repairs == ()


@pytest.mark.parametrize("p_values,match", [
    (np.array([1, 0, 2, 1]), r"event index 2: polarity 2 is not one of the encodings"),
    (np.array([1, 0, -1, 1]), r"event index 2: polarity -1 mixes encodings: earlier events \(event index 1\) used 0"),
    (np.array([1.0, 0.5, 1.0, 0.0]), r"event index 1: polarity 0.5 is not one of the encodings"),
])
def test_garbage_polarity_is_rejected_naming_the_row(tmp_path, p_values, match):
    p = _npz(tmp_path / "g.npz", t=np.arange(4), x=np.arange(4), y=np.arange(4), p=p_values, width=4, height=4)
    with pytest.raises(RecordingError, match=match):
        read_recording(p)


@pytest.mark.parametrize("column,values,match", [
    ("x", [0, 1, 70, 3], r"event index 2: x = 70 is outside the sensor \(width 64\); 1 of 4 events"),
    ("y", [0, 48, 2, 3], r"event index 1: y = 48 is outside the sensor \(height 48\)"),
    ("x", [0, -1, 2, 3], r"event index 1: x = -1 is negative"),
    ("x", [0.0, 1.5, 2.0, 3.0], r"event index 1: x = 1.5 is not an integer pixel coordinate"),
    ("t", [0.0, np.nan, 2.0, 3.0], r"event index 1: timestamp nan s is not a finite number within ±2\^62 µs"),
])
def test_bad_values_are_rejected_naming_the_row(tmp_path, column, values, match):
    cols = {"t": np.arange(4) * 10, "x": np.arange(4), "y": np.arange(4), "p": np.ones(4, int)}
    cols[column] = np.array(values)
    path = tmp_path / "bad.h5"
    with h5py.File(path, "w") as f:
        for k, v in cols.items():
            f[f"events/{k}"] = v
        f.attrs["width"], f.attrs["height"] = 64, 48
    with pytest.raises(RecordingError, match=match) as err:
        read_recording(path)
    assert str(err.value).startswith(str(path))


def test_truncated_aedat4_keeps_complete_packets(real, tmp_path):
    data = REAL.read_bytes()
    p = tmp_path / "cut.aedat4"
    p.write_bytes(data[:600_000])
    r = read_recording(p)
    # each packet's declared size is checked against the bytes that follow before the decoder reads it
    assert r.repairs == (("packet 17 at byte 543465 declares 90,083 bytes but 56,527 follow (a truncated file, or a "
                          "corrupted packet size): kept the 17 complete packets before it"),)
    assert 0 < len(r.events) < len(real.events)
    np.testing.assert_array_equal(r.events, real.events[:len(r.events)])  # a prefix, same clock
    with pytest.raises(RecordingError, match="declares .* bytes but .* follow"):
        p.write_bytes(data[:200])
        read_recording(p)


def test_truncated_npy_keeps_complete_rows(tmp_path):
    ev = _events()
    p = tmp_path / "e.npy"
    np.save(p, ev)
    p.write_bytes(p.read_bytes()[:-20])  # 13-byte rows: the last row and a bit of the one before
    r = read_recording(p, width=64, height=48)
    assert len(r.events) == 198
    assert r.repairs == (("file truncated: the header declares 200 events but only 198 complete ones are stored: "
                          "kept those"),)


def test_truncated_text_drops_the_incomplete_last_line(tmp_path):
    ev = _events()
    folder = write_recording(tmp_path / "rpg", RawRecording(ev, 64, 48, T0, Path("x"), "x"), format="rpg")
    text = (folder / "events.txt").read_text()
    (folder / "events.txt").write_text(text[:-5])  # cuts into the last line, no newline at the end
    r = read_recording(folder)
    assert len(r.events) == 199
    assert r.repairs[0].startswith("events.txt: the last line (200) is incomplete")
    # A malformed line elsewhere is an error naming its line.
    lines = text.splitlines()
    lines[6] = "0.5 12 x3 1"
    (folder / "events.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(RecordingError, match=r"events.txt line 7: field 3 is not a number: 'x3'"):
        read_recording(folder)


def test_truncated_prophesee_files_note_the_partial_word(real, tmp_path):
    for fmt, name, cut in (("evt3", "a.raw", 1), ("evt2", "b.raw", 3), ("dat", "c.dat", 5)):
        p = write_events(tmp_path / name, real.events[:5000], width=346, height=260, format=fmt,
                         t_offset_us=real.t_offset_us)
        p.write_bytes(p.read_bytes()[:-cut])
        r = read_recording(p)
        assert "truncated file?" in r.repairs[0], (fmt, r.repairs)
        np.testing.assert_array_equal(r.events, real.events[:len(r.events)])


@pytest.mark.parametrize("name,fmt", [("t.h5", "hdf5"), ("t.npz", "npz")])
def test_truncated_containers_are_rejected(synth, tmp_path, name, fmt):
    p = write_recording(tmp_path / name, synth, format=fmt)
    p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])
    with pytest.raises(RecordingError) as err:
        read_recording(p)
    assert str(p) in str(err.value)


def test_flipped_bits_in_checksummed_data_are_rejected(synth, tmp_path):
    p = write_recording(tmp_path / "f.npz", synth, format="npz")
    data = bytearray(p.read_bytes())
    data[len(data) // 3] ^= 0x10
    p.write_bytes(bytes(data))
    with pytest.raises(RecordingError, match="npz reader \\(numpy\\) failed: .*(CRC|Error)"):
        read_recording(p)
    q = write_events(tmp_path / "f.aedat4", synth.events, width=64, height=48)
    data = bytearray(q.read_bytes())
    data[-200] ^= 0x01
    q.write_bytes(bytes(data))
    # The only packet's LZ4 checksum fails: it is skipped (and said), which leaves no events.
    with pytest.raises(RecordingError, match=r"contains no events; skipped 1 corrupted compressed packet\(s\) .*"
                                             r"packet 0 \(LZ4 error: ERROR_blockChecksum_invalid\)"):
        read_recording(q)


def test_corrupted_aedat4_header_is_rejected_before_the_native_decoder(synth, tmp_path):
    """Invalid UTF-8 in the stream description aborts the Rust decoders: it must be caught in Python first."""
    # an AEDAT4 file of our writer (the real recording is not in the repository)
    data = bytearray(write_events(tmp_path / "w.aedat4", synth.events, width=64, height=48).read_bytes())
    assert data.find(b"<dv") < 200 < data.find(b"</dv>")
    data[200] = 0xD6  # inside the XML description
    p = tmp_path / "h.aedat4"
    p.write_bytes(bytes(data))
    with pytest.raises(RecordingError, match="file header: corrupted IO header: the stream description is not UTF-8"):
        read_recording(p)


def test_empty_recordings(tmp_path):
    with pytest.raises(RecordingError, match="contains no events"):
        read_recording(_npz(tmp_path / "e.npz", t=np.zeros(0, int), x=np.zeros(0, int), y=np.zeros(0, int),
                            p=np.zeros(0, int), width=4, height=4))
    (tmp_path / "rpg").mkdir()
    (tmp_path / "rpg" / "events.txt").write_text("# no events\n")
    with pytest.raises(RecordingError, match="contains no events"):
        read_recording(tmp_path / "rpg")


def test_rpg_folder_errors_name_the_file_and_line(synth, tmp_path):
    folder = write_recording(tmp_path / "rpg", synth, format="rpg")
    (folder / "images" / "frame_00000001.png").unlink()
    with pytest.raises(RecordingError, match=r"images.txt: images.txt line 2: image file 'images/frame_00000001.png' "
                                             r"does not exist"):
        read_recording(folder)
    folder = write_recording(tmp_path / "rpg2", synth, format="rpg")
    with open(folder / "events.txt", "a") as f:
        f.write("0.5 64 3 1\n")  # the frames make the sensor 64 wide
    with pytest.raises(RecordingError, match=r"events.txt: events.txt line 1501: x = 64 is outside the sensor"):
        read_recording(folder)
    folder = write_recording(tmp_path / "rpg4", synth, format="rpg")
    text = (folder / "images.txt").read_text()
    (folder / "images.txt").write_text(text.replace("1633000000.002000", "16330000002000", 1))  # a lost '.'
    with pytest.raises(RecordingError, match=r"images.txt: images.txt line 1: frame time 16330000002000.0 s is not "
                                             r"a finite number within ±2\^62 µs"):
        read_recording(folder)
    folder = write_recording(tmp_path / "rpg3", synth, format="rpg")
    (folder / "calib.txt").write_text("1 2 three 4\n")
    with pytest.raises(RecordingError, match=r"calib.txt:1: value 3 is not a number: 'three'"):
        read_recording(folder)
    with pytest.raises(RecordingError, match=r"images.txt line 1: expected 4 numbers, got 2"):
        read_recording(folder / "images.txt", format="rpg")  # a text file that is not events fails clearly


# ---------------------------------------------------------------------------------------- windows, ROI, streams
def test_time_window_and_roi(synth, tmp_path):
    path = write_recording(tmp_path / "s.h5", synth)
    r = read_recording(path, time_window_us=(30_000, 60_000), roi=Roi(10, 5, 20, 30))
    ev = synth.events
    keep = ((ev["t"] >= 30_000) & (ev["t"] < 60_000) & (ev["x"] >= 10) & (ev["x"] < 30) & (ev["y"] >= 5)
            & (ev["y"] < 35))
    np.testing.assert_array_equal(r.events["t"], ev["t"][keep])
    np.testing.assert_array_equal(r.events["x"], ev["x"][keep] - 10)
    np.testing.assert_array_equal(r.events["y"], ev["y"][keep] - 5)
    assert (r.width, r.height, r.t_offset_us) == (20, 30, synth.t_offset_us)
    np.testing.assert_array_equal(r.frames.t_us, [42_000])
    np.testing.assert_array_equal(r.frames.images[0], synth.frames.images[1, 5:35, 10:30])
    assert (r.calibration.cx, r.calibration.cy) == (synth.calibration.cx - 10, synth.calibration.cy - 5)
    with pytest.raises(RecordingError, match=r"no events in the time window \[200000, 300000\) µs"):
        read_recording(path, time_window_us=(200_000, 300_000))
    with pytest.raises(ValueError, match="does not lie inside the 64 × 48 sensor"):
        read_recording(path, roi=(60, 0, 10, 10))


def test_streaming_sorts_within_chunks_and_refuses_disorder_across_them(tmp_path):
    ev = _events(n=300)  # more than the first 101 events, which the time check holds back together
    local = ev.copy()
    local[[40, 41]] = local[[41, 40]]
    p = _npz(tmp_path / "l.npz", t=local["t"], x=local["x"], y=local["y"], p=local["p"], width=64, height=48)
    stream = iter_event_chunks(p, chunk_events=30)
    np.testing.assert_array_equal(np.concatenate(list(stream))["t"] + stream.t_offset_us, ev["t"])
    assert stream.repairs[0].startswith("sorted events by time: time went backwards at 1 place(s)")
    far = ev.copy()
    far[[5, 295]] = far[[295, 5]]
    q = _npz(tmp_path / "f.npz", t=far["t"], x=far["x"], y=far["y"], p=far["p"], width=64, height=48)
    with pytest.raises(RecordingError, match="cannot sort in bounded memory"):
        list(iter_event_chunks(q, chunk_events=30))
    np.testing.assert_array_equal(_abs(read_recording(q)), ev)  # in memory it is repaired
    np.save(tmp_path / "n.npy", ev)
    with pytest.raises(RecordingError, match="pass width= and height="):
        iter_event_chunks(tmp_path / "n.npy")


def test_dataclasses_validate_and_are_read_only(real):
    with pytest.raises(ValueError, match="expected 1-D EVENT_DTYPE"):
        RawRecording(np.zeros(3), 4, 4, 0, Path("x"), "x")
    with pytest.raises(ValueError, match="expected frames of height 260 and width 346"):
        RawRecording(real.events, 346, 260, 0, Path("x"), "x",
                     Frames(np.zeros((1, 4, 4), np.float32), np.zeros(1, np.int64)))
    with pytest.raises(ValueError, match="read-only"):
        real.events["t"][0] = 5
    assert real.calibration is None  # DV keeps calibration in separate files
    assert real.events.dtype == EVENT_DTYPE
