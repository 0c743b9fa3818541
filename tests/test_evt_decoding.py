"""EVT 2.0 / 3.0 and DAT times never quietly moved (issue 57 item 3): every event at the time the file gives it, a
time going backwards reported (index, size) and handled by the time checks every format shares, duplicates only
events equal in t, x, y, p as the file holds them. The oracle is tests/helpers/evt_reference.py (files written word
by word in the order given, and a spec-literal decoder); the data are simulated."""

from __future__ import annotations

import re

import numpy as np
import pytest

from helpers.bad_inputs import events
from helpers.evt_reference import header, held_events, write_in_file_order
from helpers.fuzz_readers import unaccounted

from eventcap.events import EVENT_DTYPE
from eventcap.io import read_recording, write_events
from eventcap.io.evt import DecoderState, decode_words
from eventcap.io.prophesee import read_header

T0 = 1_633_000_000_000_000
W, H = 240, 180


@pytest.fixture(scope="module")
def ev():
    e = events(n=20_000, span_us=550_000)
    e["t"] -= e["t"][0]
    return e


def _read(path):
    r = read_recording(path)
    got = r.events.copy()
    got["t"] += r.t_offset_us
    return r, got


def _cases(ev):
    late = ev.copy()
    late["t"][10_000] += 5_000_000
    yield "late_event", late
    yield "moved_block", np.concatenate([ev[:5000], ev[15000:15500], ev[5000:15000], ev[15500:]])
    yield "swapped_blocks", np.concatenate([ev[:5000], ev[9000:10000], ev[6000:9000], ev[5000:6000], ev[10000:]])
    yield "duplicated_block", np.concatenate([ev[:8000], ev[7000:8000], ev[8000:]])


@pytest.mark.parametrize("version", ["evt3", "evt2"])
def test_the_issues_damage_changes_nothing_beyond_what_a_note_says(tmp_path, ev, version):
    """One event 5 s late, 500 events moved earlier, blocks swapped, a block duplicated: every event read is one the
    file holds, at its time; what is gone is named with its count."""
    for name, damaged in _cases(ev):
        path = write_in_file_order(tmp_path / f"{name}.raw", damaged, version, W, H, T0)
        held = held_events(path, version)
        r, got = _read(path)
        assert unaccounted(got, held, r.repairs) == [], (name, r.repairs)
        assert int(r.events["t"][-1]) < 600_000, name  # never stretched to 5 s
        if name == "late_event":
            assert len(got) == len(ev) - 1
            assert any(re.search(r"dropped 1 event\(s\) with wild times.*event index 10000 .*between a jump of 5 s "
                                 r"and one back", s) for s in r.repairs), r.repairs
        elif name == "duplicated_block":  # the file holds 1000 events twice: those, and only those, are duplicates
            assert len(got) == len(ev)
            assert any("dropped 1000 duplicated event(s)" in s for s in r.repairs)
        else:
            assert len(got) == len(ev)
            assert any(re.search(r"sorted events by time: time went backwards at \d place\(s\) \(first at event index "
                                 r"\d+: .*largest step back \d+ µs\)", s) for s in r.repairs), r.repairs
            assert not any("duplicated" in s for s in r.repairs)


def test_a_flipped_bit_of_an_evt3_time_word_is_read_as_the_file_says_with_a_note(tmp_path, ev):
    path = write_events(tmp_path / "a.raw", ev, width=W, height=H, format="evt3", t_offset_us=T0)
    data = bytearray(path.read_bytes())
    hl = read_header(path)[1]
    words = np.frombuffer(bytes(data[hl:]), "<u2")
    lows = np.flatnonzero((words >> 12 == 0x6) & (words >> 9 & 1 == 0))
    k = int(lows[len(lows) // 2])  # bit 9 of a TIME_LOW set: its events 512 µs late, as the file now says
    data[hl + 2 * k + 1] ^= 1 << 1
    path.write_bytes(bytes(data))
    held = held_events(path, "evt3")
    r, got = _read(path)
    assert unaccounted(got, held, r.repairs) == []
    assert any("sorted events by time: time went backwards" in s for s in r.repairs), r.repairs


def test_our_decoder_equals_the_spec_literal_one_on_every_word_type(tmp_path):
    """Random streams of every EVT3 word type (vectors, base x, rows, time words, triggers, others, undefined) and
    of EVT2 words: the same events, in file order, as the plain decoder; state carried across blocks."""
    rng = np.random.default_rng(4)
    for version in ("evt3", "evt2"):
        for trial in range(5):
            if version == "evt3":
                kinds = rng.choice([0x0, 0x2, 0x3, 0x4, 0x5, 0x6, 0x8, 0xA, 0xE, 0x9], 4000,
                                   p=[.1, .2, .1, .15, .1, .15, .1, .03, .03, .04])
                values = rng.integers(0, 1 << 12, 4000)
                values[kinds == 0x0] %= H
                values[kinds == 0x2] = (values[kinds == 0x2] & 0x800) | (values[kinds == 0x2] % W)
                values[kinds == 0x3] = (values[kinds == 0x3] & 0x800) | (values[kinds == 0x3] % (W - 40))
                words = ((kinds << 12) | values).astype("<u2")
            else:
                kinds = rng.choice([0x0, 0x1, 0x8, 0xA, 0x3], 4000, p=[.4, .4, .12, .04, .04])
                values = rng.integers(0, 1 << 28, 4000)
                cd = kinds <= 1
                values[cd] = (values[cd] & (0x3F << 22)) | ((values[cd] >> 11 & 0x7FF) % W << 11) | (values[cd] % H)
                words = ((kinds.astype(np.uint64) << 28) | values.astype(np.uint64)).astype("<u4")
            path = tmp_path / f"{version}_{trial}.raw"
            path.write_bytes(header(version, 4096, 4096, T0) + words.tobytes())
            held = held_events(path, version)
            state = DecoderState(version)
            parts = [decode_words(block, state) for block in np.array_split(words, 7)]
            t, x, y, p = (np.concatenate([q[i] for q in parts]) for i in range(4))
            np.testing.assert_array_equal(t + T0, held["t"])
            np.testing.assert_array_equal(x, held["x"])
            np.testing.assert_array_equal(y, held["y"])
            np.testing.assert_array_equal(np.where(p > 0, 1, -1), held["p"])
            assert state.undefined == int(np.sum(kinds == (0x9 if version == "evt3" else 0x3)))


def test_an_undefined_word_and_events_without_a_time_are_named(tmp_path, ev):
    path = write_events(tmp_path / "b.raw", ev[:3000], width=W, height=H, format="evt2", t_offset_us=T0)
    data = path.read_bytes()
    hl = read_header(path)[1]
    words = np.frombuffer(data[hl:], "<u4").copy()
    words[100] = 0x30000000  # a type EVT2 does not define
    cd = np.array([(1 << 28) | (5 << 11) | 7], "<u4")  # a CD event before any time word
    path.write_bytes(data[:hl] + cd.tobytes() + words.tobytes())
    r, got = _read(path)
    assert f"skipped 1 word(s) of a type EVT2 does not define (first at byte {hl + 4 * 101})" in " ".join(r.repairs)
    assert f"dropped 1 event(s) before the first time word (first at byte {hl})" in " ".join(r.repairs)
    assert unaccounted(got, held_events(path, "evt2"), r.repairs) == []


def test_evt3_counter_wraps_as_a_sensor_writes_them(tmp_path):
    """A sensor writes EVT_TIME_HIGH at every 4096-µs step: 40 s of sparse events cross two 2^24-µs wraps."""
    t = np.arange(0, 40_000_000, 50_000)
    words = []
    for tick in range(0, 40_000_000 >> 12):
        words.append(0x8000 | (tick & 0xFFF))
        for tt in t[(t >> 12) == tick]:
            words += [0x6000 | (int(tt) & 0xFFF), 0x0000 | 5, 0x2000 | 0x800 | 9]
    path = tmp_path / "w.raw"
    path.write_bytes(header("evt3", W, H, T0) + np.array(words, "<u2").tobytes())
    r, got = _read(path)
    np.testing.assert_array_equal(got["t"], t + T0)
    assert r.repairs == ()


def test_a_dat_time_going_back_is_kept_and_sorted_with_a_note(tmp_path, ev):
    path = write_events(tmp_path / "c.dat", ev[:2000], width=W, height=H, format="dat", t_offset_us=T0)
    data = bytearray(path.read_bytes())
    first = read_header(path)[1] + 2  # the header, then the type and size bytes
    k = 1500  # this event's time set 20 ms back: faery kept it at its neighbour's time
    old = int.from_bytes(data[first + 8 * k:first + 8 * k + 4], "little")
    data[first + 8 * k:first + 8 * k + 4] = (old - 20_000).to_bytes(4, "little")
    path.write_bytes(bytes(data))
    r, got = _read(path)
    assert any("time went backwards at 1 place(s) (first at event index 1500" in s and "largest step back" in s
               for s in r.repairs), r.repairs
    assert int(ev["t"][1500]) - 20_000 + T0 in got["t"] and len(got) == 2000


def test_one_event_per_pixel_and_time_is_not_a_duplicate_when_the_polarities_differ(tmp_path):
    e = np.zeros(200, EVENT_DTYPE)
    e["t"] = np.repeat(np.arange(100) * 1000, 2)
    e["x"], e["y"] = 3, 4
    e["p"] = np.tile([1, -1], 100)
    path = write_in_file_order(tmp_path / "d.raw", e, "evt3", W, H, T0)
    r, got = _read(path)
    assert len(got) == 200 and not any("duplicated" in s for s in r.repairs)
