"""Readers register themselves (issue 56 item 4): one place says each format's name, files, signature, time counters
and what it reads; detection, opening, the time checks, `eventcap formats` and the fuzz corpus ask it. The worked
example, tests/fixtures/readers/nmnist.py, is a new reader in one module, tried through EVENTCAP_READERS: this test
is the only other file it needs."""

from __future__ import annotations

import logging
import subprocess
import sys

import numpy as np
import pytest

from helpers import fuzz_readers
from helpers.paths import TESTS

from eventcap.io import RecordingError, detect_format, read_recording, readers
from eventcap.io.registry import ENV_VAR, ReaderSpec, forget_readers

NMNIST = f"{TESTS / 'fixtures' / 'readers' / 'nmnist.py'}:READERS"


@pytest.fixture
def with_nmnist(monkeypatch):
    monkeypatch.setenv(ENV_VAR, NMNIST)
    forget_readers()
    yield readers()
    monkeypatch.delenv(ENV_VAR)
    forget_readers()


def test_the_builtin_readers_state_their_formats_once():
    r = readers()
    assert r.names() == ["aedat4", "aedat2", "aedat3", "hdf5", "rpg", "evt2", "evt3", "dat", "npy", "npz"]
    assert r.wraps_us("evt3") == (2**24,) and r.wraps_us("evt2") == (2**34,) and r.wraps_us("aedat3") == (2**31, 2**32)
    assert r.wraps_us("npy") == () and set(r.column_formats()) == {"hdf5", "rpg", "npy", "npz"}
    assert [s.name for s in r.by_extension(".raw")] == ["evt2", "evt3"]
    assert r.get("hdf5").magic == (b"\x89HDF\r\n\x1a\n",)
    with pytest.raises(ValueError, match="no format named 'evt4' in the recording readers; did you mean"):
        r.get("evt4")
    # every reader is in the fuzz corpus
    assert set(r.names()) <= set(fuzz_readers.entry_names())


def test_a_spec_is_checked_when_it_is_made():
    with pytest.raises(ValueError, match=r"reader 'My Format': name 'My Format': lower-case letters.*; source 'x': "
                                         r"expected 'module:callable'.*; extensions \('bin',\): lower case, each "
                                         r"starting with '.'; magic_name: required with magic"):
        ReaderSpec(name="My Format", description="d", source="x", extensions=("bin",), magic=(b"AB",))


def test_a_new_reader_in_one_module(with_nmnist, tmp_path):
    """The worked example: registered from its module alone, it is detected by its extension, read with the shared
    checks (a wild time dropped, a time going backwards sorted, each with a note) and its own (shifted bytes
    refused), listed by `eventcap formats`, and fuzzed from its own sample."""
    registry = with_nmnist
    spec = registry.get("nmnist")
    assert spec.origin.startswith(f"{ENV_VAR} ") and registry.wraps_us("nmnist") == ()
    rec = fuzz_readers.synthetic_recording()
    path = spec.load("sample")(tmp_path, rec)
    assert detect_format(path) == "nmnist"
    r = read_recording(path)
    np.testing.assert_array_equal(r.events, rec.events)
    assert (r.width, r.height) == (64, 48) and "inferred 64 × 48" in r.repairs[0]
    # bytes inserted: every later 5-byte event shifted, refused by the reader's own check, naming where
    data = path.read_bytes()
    (tmp_path / "shifted.bin").write_bytes(data[:3000] + b"\x07" + data[3000:])
    with pytest.raises(RecordingError, match=r"time goes back at \d+ of the 16 steps from event index 5\d\d: not "
                                             r"events in time order"):
        read_recording(tmp_path / "shifted.bin")
    # a high time byte flipped: one event 4.2 s late, dropped by the shared time checks with a note
    flipped = bytearray(data)
    flipped[5 * 300 + 2] ^= 0x40
    (tmp_path / "late.bin").write_bytes(bytes(flipped))
    late = read_recording(tmp_path / "late.bin")
    assert len(late.events) == len(rec.events) - 1
    assert any("dropped 1 event(s) with wild times" in s and "event index 300" in s for s in late.repairs)
    # damaged: one event's time bits say 3 ms earlier, as the file now holds it
    data = bytearray(path.read_bytes())
    k = 700
    t = (data[5 * k + 2] & 0x7F) << 16 | data[5 * k + 3] << 8 | data[5 * k + 4]
    t -= 3000
    data[5 * k + 2] = (data[5 * k + 2] & 0x80) | (t >> 16)
    data[5 * k + 3], data[5 * k + 4] = (t >> 8) & 0xFF, t & 0xFF
    path.write_bytes(bytes(data))
    assert any("sorted events by time: time went backwards at 1 place(s) (first at event index 700" in s
               for s in read_recording(path).repairs)
    path.write_bytes(b"")
    with pytest.raises(RecordingError, match="the file is empty"):
        read_recording(path)


def test_the_new_reader_is_fuzzed_and_listed(with_nmnist):
    assert "nmnist" in fuzz_readers.entry_names()
    res = fuzz_readers.run_fuzz(n=40, seed=2, workers=2, timeout_s=30.0, include_real=False, only="nmnist")
    assert sum(res["counts"].values()) == 40 and set(res["by_format"]) == {"nmnist"}
    for outcome in fuzz_readers.MUST_BE_ZERO:
        assert res["counts"][outcome] == 0, res["examples"].get(outcome)
    out = subprocess.run([sys.executable, "-m", "eventcap.apps.cli", "formats"], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0
    assert "nmnist   N-MNIST / N-Caltech101 .bin (ATIS): 5 bytes per event, a 23-bit µs time" in out.stdout
    assert "from: EVENTCAP_READERS" in out.stdout


def test_a_broken_plugin_is_skipped_with_a_warning(monkeypatch, caplog, tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text("READERS = ['not a spec']\n")
    monkeypatch.setenv(ENV_VAR, f"{bad}:READERS")
    forget_readers()
    with caplog.at_level(logging.WARNING):
        names = readers().names()
    forget_readers()
    assert "aedat4" in names and f"{ENV_VAR} entry {bad}:READERS skipped: {ENV_VAR} {bad}:READERS: expected " \
        f"ReaderSpec(s), got str" in caplog.text
