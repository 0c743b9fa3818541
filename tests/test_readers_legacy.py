"""AEDAT 2.0 (jAER) and AEDAT 3.1 (cAER / DV legacy) readers: addresses decoded by the specification (x mirror and
bottom-up y of jAER undone, polarity bits, special / IMU / APS / invalid events left out, 3.1 timestamp overflow),
checked against files built here byte by byte with ``struct`` (an encoding independent of the reader), against our
own writers for round trips, and against a real public DAVIS240C file when one is given (see
``test_public_davis240c_file_matches_an_independent_decode``)."""

from __future__ import annotations

import os
import re
import struct
from pathlib import Path

import numpy as np
import pytest

from eventcap.events import make_events
from eventcap.io import RecordingError, detect_format, iter_event_chunks, read_recording
from eventcap.io.aedat_legacy import sensor_of, write_aedat2, write_aedat31

DAVIS240 = b"# AEChip: eu.seebetter.ini.chips.davis.DAVIS240C\r\n"


def aedat2_bytes(records, chip: bytes = DAVIS240) -> bytes:
    head = b"#!AER-DAT2.0\r\n# This is a raw AE data file - do not edit\r\n" + chip
    return head + b"".join(struct.pack(">II", a, t) for a, t in records)


def davis_address(x_addr: int, y_addr: int, on: bool) -> int:
    return (y_addr << 22) | (x_addr << 12) | (int(on) << 11)


def random_events(n=3000, width=240, height=180, t0=1_000, seed=0):
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(t0, t0 + 500_000, n))
    ev = make_events(t, rng.integers(0, width, n), rng.integers(0, height, n), rng.choice([-1, 1], n))
    key = (ev["t"] << 20) | (ev["x"].astype(np.int64) << 10) | ev["y"]
    return ev[np.unique(key, return_index=True)[1]]


# ------------------------------------------------------------------------------------------------------- AEDAT 2.0
def test_aedat2_davis_addresses_follow_jaer(tmp_path):
    """jAER stores DAVIS x mirrored and y from the bottom; bit 11 is ON; bit 10 marks special events, bit 31 APS or
    IMU samples (both left out)."""
    p = tmp_path / "davis.aedat"
    p.write_bytes(aedat2_bytes([
        (davis_address(239, 179, True), 100),    # top-left pixel of the image, ON
        (davis_address(0, 0, False), 150),       # bottom-right, OFF
        (1 << 10, 160),                          # external input (special) event
        ((1 << 31) | (5 << 12) | (1 << 10), 170),  # APS sample (signal read)
        ((1 << 31) | (3 << 10), 180),            # IMU sample
        (davis_address(10, 170, True), 200),     # x = 229, y = 9
    ]))
    assert detect_format(p) == "aedat2"
    r = read_recording(p)
    assert (r.format, r.width, r.height, r.t_offset_us) == ("aedat2", 240, 180, 100)
    assert r.events.tolist() == [(0, 0, 0, 1), (50, 239, 179, -1), (100, 229, 9, 1)]
    assert r.frames is None
    assert r.repairs == ("1 APS samples are not in complete global-shutter frames (rolling shutter, a region of "
                         "interest, or a frame cut short): left out",)


def aps_frame_records(image_10bit: np.ndarray, t_reset: int, t_signal: int) -> list[tuple[int, int]]:
    """A global-shutter APS frame as jAER stores it: reset reads (1023) of every pixel, then signal reads
    (1023 - value); APS x addresses are not mirrored, y counts from the bottom."""
    h, w = image_10bit.shape
    out = []
    for kind, t in ((0, t_reset), (1, t_signal)):
        for row in range(h):
            for col in range(w):
                adc = 1023 if kind == 0 else 1023 - int(image_10bit[row, col])
                out.append(((1 << 31) | ((h - 1 - row) << 22) | (col << 12) | (kind << 10) | adc, t))
    return out


def test_aedat2_global_shutter_aps_frames(tmp_path):
    rng = np.random.default_rng(8)
    frames = rng.integers(0, 1024, (2, 180, 240))
    recs = [(davis_address(239, 179, True), 1_000)]
    recs += aps_frame_records(frames[0], 2_000, 7_000)
    recs += [(davis_address(0, 0, False), 20_000)]
    recs += aps_frame_records(frames[1], 42_000, 47_000)
    recs += aps_frame_records(frames[1], 82_000, 87_000)[:1000]  # cut short by the end of the file
    p = tmp_path / "aps.aedat"
    p.write_bytes(aedat2_bytes(recs))
    r = read_recording(p)
    assert r.events.tolist() == [(0, 0, 0, 1), (19_000, 239, 179, -1)]
    np.testing.assert_array_equal(r.frames.images, (frames / 1023).astype(np.float32))
    np.testing.assert_array_equal(r.frames.t_us, [3_500, 43_500])  # mid-exposure, on the events' clock
    np.testing.assert_array_equal(r.frames.exposure_us, [5_000, 5_000])
    assert r.repairs == ("1000 APS samples are not in complete global-shutter frames (rolling shutter, a region "
                         "of interest, or a frame cut short): left out",)


AEDAT4_REAL = Path(__file__).resolve().parent / "data" / "real" / "davis346_lab_aps.aedat4"  # shipped (tests/data/real/SOURCE.md)
CONVERTED = os.environ.get("EVENTCAP_AEDAT2_OF_DAVIS346", "")


@pytest.mark.skipif(not (Path(CONVERTED).is_file() and AEDAT4_REAL.is_file()),
                    reason="set EVENTCAP_AEDAT2_OF_DAVIS346 to the real DAVIS346 AEDAT4 file converted by iniVation's "
                           "aedat4to2 (github.com/SensorsINI/aedat4to2: aedat4to2.py --no_imu davis346_lab_aps.aedat4)")
def test_real_davis346_recording_through_inivations_aedat4to2_converter():
    """The same real recording decoded from AEDAT4 (by the aedat library) and from the AEDAT 2.0 that iniVation's
    converter writes: times, y and polarity agree exactly; the converter stores DVS x unmirrored while jAER's
    extractor (which this reader follows) mirrors it, and it stores APS x mirrored, so both events and frames come
    out mirrored, consistently with each other; frames hold the 8-bit values in the 10-bit field."""
    a4, a2 = read_recording(AEDAT4_REAL), read_recording(CONVERTED)
    e4, e2 = a4.events, a2.events
    assert len(e2) == len(e4) == 117_667
    np.testing.assert_array_equal(e2["t"], e4["t"])
    np.testing.assert_array_equal(e2["y"], e4["y"])
    np.testing.assert_array_equal(e2["p"], e4["p"])
    np.testing.assert_array_equal(e2["x"], 345 - e4["x"].astype(np.int64))
    np.testing.assert_array_equal(np.rint(a2.frames.images * 1023), np.rint(a4.frames.images * 255)[:, :, ::-1])
    np.testing.assert_array_equal(a2.frames.t_us, a4.frames.t_us)
    assert a2.frames.exposure_us is None and a2.repairs == (
        "the APS samples of each frame carry a single time stamp: exposure times not recorded",)


def test_aedat2_dvs128_polarity_bit_zero_is_on(tmp_path):
    p = tmp_path / "dvs128.aedat"
    chip = b"# AEChip: ch.unizh.ini.jaer.chip.retina.DVS128\r\n"
    x_addr, y_addr = 100, 20
    p.write_bytes(aedat2_bytes([((y_addr << 8) | (x_addr << 1) | 0, 10), ((y_addr << 8) | (x_addr << 1) | 1, 20),
                                (1 << 15, 30)], chip))
    r = read_recording(p)
    assert (r.width, r.height) == (128, 128)
    assert r.events.tolist() == [(0, 27, 107, 1), (10, 27, 107, -1)]


def test_aedat2_round_trip_with_specials_wrap_and_streaming(tmp_path):
    ev = random_events()
    ev["t"] += 2**32 - 200_000  # the 32-bit µs counter wraps inside the recording
    p = tmp_path / "w.aedat"
    file_ev = ev.copy()
    file_ev["t"] %= 2**32
    write_aedat2(p, file_ev, specials_every=7)
    r = read_recording(p)
    expect = ev.copy()
    expect["t"] -= expect["t"][0]
    np.testing.assert_array_equal(r.events, expect)
    assert r.t_offset_us == int(ev["t"][0]) and any("unwrapped 1 wrap-around" in s for s in r.repairs)
    chunks = iter_event_chunks(p, chunk_events=333)
    np.testing.assert_array_equal(np.concatenate(list(chunks)), r.events)


def test_aedat2_dhp19_multi_camera_reads_one_camera_and_counts_the_others(tmp_path):
    p = tmp_path / "mov1.aedat"
    chip = b"# AEChip: ch.unizh.ini.jaer.chip.multicamera.MultiDavis346BCameraChip\r\n"
    recs = [(davis_address(345 - 10, 259 - 20, True) | 2, 10), (davis_address(0, 0, True) | 0, 20),
            (davis_address(345 - 11, 259 - 21, False) | 2, 30), (davis_address(5, 5, True) | 3, 40)]
    p.write_bytes(aedat2_bytes(recs, chip))
    r = read_recording(p)
    assert (r.width, r.height) == (346, 260)
    assert r.events.tolist() == [(0, 10, 20, 1), (20, 11, 21, -1)]  # camera 2, the first one in the file
    assert r.repairs == ("ch.unizh.ini.jaer.chip.multicamera.MultiDavis346BCameraChip records several cameras: "
                         "read camera 2; left out 2 events of camera(s) 0, 3",)


def test_aedat2_truncated_and_refused_files(tmp_path):
    ev = random_events(200)
    p = tmp_path / "t.aedat"
    write_aedat2(p, ev)
    p.write_bytes(p.read_bytes()[:-3])
    r = read_recording(p)
    assert len(r.events) == 199 and "partial 8-byte event (5 byte(s)" in r.repairs[0]
    bad = tmp_path / "bad.aedat"
    bad.write_bytes(aedat2_bytes([(davis_address(300, 5, True), 1)]))
    with pytest.raises(RecordingError, match=r"record 0 of the data: event address x=300, y=5 lies outside the "
                                             r"eu.seebetter.ini.chips.davis.DAVIS240C sensor \(240 × 180\)"):
        read_recording(bad)


def test_sensor_names():
    assert sensor_of("DAVIS346B") == ("davis", 346, 260)
    assert sensor_of("eu.seebetter.ini.chips.davis.Davis346red"[len("eu.seebetter.ini.chips.davis."):]) == \
        ("davis", 346, 260)
    assert sensor_of("DVS128") == ("dvs128", 128, 128) and sensor_of("DAVIS240C") == ("davis", 240, 180)
    assert sensor_of("Cochlea") is None


# ------------------------------------------------------------------------------------------------------- AEDAT 3.1
def packet(kind: int, source: int, size: int, ts_offset: int, overflow: int, body: bytes, number: int) -> bytes:
    return struct.pack("<hhiiiiii", kind, source, size, ts_offset, overflow, number, number, number) + body


def polarity31(x: int, y: int, on: bool, t: int, valid: bool = True) -> bytes:
    return struct.pack("<Ii", (x << 17) | (y << 2) | (int(on) << 1) | int(valid), t)


def test_aedat31_polarity_overflow_invalid_and_other_sources(tmp_path):
    head = b"#!AER-DAT3.1\r\n#Format: RAW\r\n#Source 1: DAVIS346B\r\n#Source 2: DVS128\r\n#!END-HEADER\r\n"
    first = packet(1, 1, 8, 4, 0, polarity31(3, 4, True, 2**31 - 10) + polarity31(5, 6, False, 2**31 - 5, False), 2)
    special = packet(0, 1, 8, 4, 1, struct.pack("<Ii", 1, 0), 1)  # a timestamp-wrap special event
    other = packet(1, 2, 8, 4, 1, polarity31(1, 1, True, 3), 1)  # another source: not read
    second = packet(1, 1, 8, 4, 1, polarity31(345, 259, False, 7), 1)
    p = tmp_path / "d.aedat"
    p.write_bytes(head + first + special + other + second)
    assert detect_format(p) == "aedat3"
    r = read_recording(p)
    assert (r.format, r.width, r.height) == ("aedat3", 346, 260)
    assert r.t_offset_us == 2**31 - 10
    assert r.events.tolist() == [(0, 3, 4, 1), (17, 345, 259, -1)]  # overflow 1: 2^31 + 7
    assert r.repairs == ()


def test_aedat31_round_trip_with_frames_and_streaming(tmp_path):
    ev = random_events(5000, 346, 260, t0=2**31 - 250_000, seed=3)
    rng = np.random.default_rng(4)
    images = rng.integers(0, 65536, (3, 260, 346)).astype(np.uint16)
    begin = np.array([2**31 - 240_000, 2**31 - 100_000, 2**31 + 40_000], np.int64)
    end = begin + 5_000
    p = tmp_path / "f.aedat"
    write_aedat31(p, ev, frames=(images, begin, end), invalid_every=10, packet_events=700)
    r = read_recording(p)
    keep = np.ones(len(ev), bool)
    keep[9::10] = False
    expect = ev[keep]
    assert r.t_offset_us == int(expect["t"][0])
    expect["t"] -= expect["t"][0]
    np.testing.assert_array_equal(r.events, expect)
    np.testing.assert_array_equal(r.frames.images, images.astype(np.float32) / np.float32(65535))
    np.testing.assert_array_equal(r.frames.t_us + r.t_offset_us, begin + 2_500)
    np.testing.assert_array_equal(r.frames.exposure_us, [5_000] * 3)
    chunks = iter_event_chunks(p, chunk_events=777)
    np.testing.assert_array_equal(np.concatenate(list(chunks)), r.events)


def test_aedat31_truncated_and_corrupted(tmp_path):
    ev = random_events(3000, 346, 260, seed=5)
    p = tmp_path / "c.aedat"
    write_aedat31(p, ev, packet_events=1000)
    data = p.read_bytes()
    p.write_bytes(data[:-100])
    r = read_recording(p)
    assert len(r.events) == 2000
    assert len(r.repairs) == 1
    assert re.fullmatch(r"the file ends inside packet 2 \(truncated, or a corrupted packet size\): it declares 1,000 "
                        r"events of 8 bytes at byte \d+, 7,9\d\d bytes follow; kept the 2 complete packets before it",
                        r.repairs[0]), r.repairs
    header_end = data.index(b"#!END-HEADER\r\n") + 14
    bad = bytearray(data)
    bad[header_end + 4:header_end + 8] = struct.pack("<i", -8)  # event size of packet 0
    p.write_bytes(bytes(bad))
    with pytest.raises(RecordingError, match=rf"packet 0 \(byte {header_end}\): corrupted packet header: type 1, "
                                             r"event size -8"):
        read_recording(p)


# ----------------------------------------------------------------------------------------- a real public file
PUBLIC = os.environ.get("EVENTCAP_PUBLIC_AEDAT2", "")


@pytest.mark.skipif(not Path(PUBLIC).is_file(), reason="set EVENTCAP_PUBLIC_AEDAT2 to a jAER DAVIS240C file, e.g. "
                    "IMU_translBoxes.aedat of github.com/believeinlain/PyAedatTools (no licence: not shipped)")
def test_public_davis240c_file_matches_an_independent_decode():
    """Decode the file record by record with ``struct`` (DVS events: bit 31 and bit 10 clear) and compare."""
    data = Path(PUBLIC).read_bytes()
    pos = 0
    while data[pos:pos + 1] == b"#":
        pos = data.index(b"\n", pos) + 1
    dvs = []
    for a, t in struct.iter_unpack(">II", data[pos:pos + (len(data) - pos) // 8 * 8]):
        if not a >> 31 and not (a >> 10) & 1:
            dvs.append((t, 239 - ((a >> 12) & 0x3FF), 179 - ((a >> 22) & 0x1FF), 1 if (a >> 11) & 1 else -1))
    ref = np.array(dvs, dtype=[("t", "i8"), ("x", "i8"), ("y", "i8"), ("p", "i8")])
    r = read_recording(PUBLIC)
    assert (r.width, r.height, len(r.events)) == (240, 180, len(ref))
    assert r.t_offset_us == ref["t"][0] and r.events["t"][-1] == ref["t"][-1] - ref["t"][0]
    for k in ("x", "y", "p"):
        np.testing.assert_array_equal(r.events[k], ref[k])  # file order is time order here (no repair)
    assert not any("sorted" in s for s in r.repairs)
