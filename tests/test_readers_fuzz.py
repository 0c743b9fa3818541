"""A small fuzz run of the recording readers (the full one is ``benchmarks/robustness/fuzz_readers.py --n 2000``).

Damaged files of every format (bytes, and events re-written after a change) are read in forked children; each must
be refused naming the file, repaired with a named warning, read exactly, or read with a change the format cannot
show while every promise of the checks holds: never silently wrong, never a hang, never a traceback (issue 48).
"""

import random

import numpy as np
from helpers import fuzz_readers

from eventcap.io import read_recording


def test_fuzz_small_run_has_no_silent_error_hang_or_traceback():
    res = fuzz_readers.run_fuzz(n=150, seed=7, workers=2, timeout_s=30.0)
    counts = res["counts"]
    assert sum(counts.values()) == 150
    for outcome in fuzz_readers.MUST_BE_ZERO:
        assert counts[outcome] == 0, (outcome, res["examples"].get(outcome))
    # The damage bites: most are refused with a clear error, many are repaired, a few read exactly.
    assert counts["refused"] >= 60 and counts["repaired"] >= 20 and counts["exact"] >= 1
    names = set(fuzz_readers.ENTRY_NAMES) | ({"aedat4_real"} if fuzz_readers.REAL_AEDAT4.is_file() else set())
    assert set(res["by_format"]) == names
    assert {"wild_time", "time_jump"} <= set(res["by_kind"])  # event-level damage ran too
    # no wild time passed unnoticed: each was refused or repaired (or read exactly: a jump of 2^32 µs vanishes in
    # a 32-bit time counter, the file holds the original times)
    for kind in ("wild_time", "time_jump"):
        assert res["by_kind"][kind].get("undetectable", 0) == 0, (kind, res["by_kind"][kind])
    assert 0 < res["peak_mb"] < 2000


def test_event_damage_is_caught_in_every_format(tmp_path):
    """Each event-level damage written in each format it applies to, read in-process: refused or repaired."""
    rec = fuzz_readers.synthetic_recording()
    for name in fuzz_readers.ENTRY_NAMES:
        if name == "zarr":
            continue
        kinds = ["wild_time", "time_jump"] + (["x_outliers"] if name in fuzz_readers.SIZELESS else []) \
            + (["unit"] if name == "csv" else [])
        (tmp_path / f"{name}_ref").mkdir()
        ref = read_recording(fuzz_readers.write_entry(name, tmp_path / f"{name}_ref", rec))
        for k, kind in enumerate(kinds):
            folder = tmp_path / f"{name}_{kind}"
            folder.mkdir()
            damaged = fuzz_readers.damage_events(rec, kind, random.Random(k)) if kind != "unit" else rec
            try:
                target = fuzz_readers.write_entry(name, folder, damaged, time_as_int_us=kind == "unit")
            except ValueError:  # EVT and DAT cannot hold a gap beyond their counters: nothing to read
                continue
            outcome, detail = fuzz_readers.classify(target, kind, ref)
            assert outcome in ("refused", "repaired", "exact"), (name, kind, outcome, detail)


def test_events_out_of_order_and_word_damage_change_nothing_beyond_the_notes(tmp_path):
    """Issue 57's damage, our own fuzz case for each: events left out of time order in the formats that keep file
    order, and word-level damage of the EVT files (a time bit, blocks of words swapped or written twice). Each read
    holds only events the file holds (EVT: decoded again word by word by the spec-literal decoder) and names the count
    of every event gone; nothing is classified silently wrong."""
    from eventcap.io.prophesee import read_header

    rec = fuzz_readers.synthetic_recording()
    seen = {}
    for name in fuzz_readers.FILE_ORDER:
        (tmp_path / f"{name}_ref").mkdir()
        ref = read_recording(fuzz_readers.write_entry(name, tmp_path / f"{name}_ref", rec),
                             **({"width": 64, "height": 48} if name.startswith("npy") else {}))
        kinds = fuzz_readers.ORDER_KINDS + (fuzz_readers.WORD_KINDS if name in fuzz_readers.EVT else ())
        for k, kind in enumerate(kinds):
            for trial in range(3):
                folder = tmp_path / f"{name}_{kind}_{trial}"
                folder.mkdir()
                rng = random.Random(f"{k}:{trial}")
                order = None
                if kind in fuzz_readers.ORDER_KINDS:
                    order = fuzz_readers.damage_order(rec.events, kind, rng)
                    target = fuzz_readers.write_in_order(name, folder, rec, order)
                else:
                    source = tmp_path / f"{name}_ref" / next(p.name for p in (tmp_path / f"{name}_ref").iterdir())
                    target = folder / source.name
                    target.write_bytes(fuzz_readers.damage_words(source.read_bytes(), read_header(source)[1], name,
                                                                 kind, rng))
                held = fuzz_readers.held_by_file(target, name, order, rec.t_offset_us)
                outcome, detail = fuzz_readers.classify(target, kind, ref, held=held)
                assert outcome in ("refused", "repaired", "exact", "undetectable"), (name, kind, outcome, detail)
                seen[outcome] = seen.get(outcome, 0) + 1
    assert seen.get("repaired", 0) >= 40  # the damage bites, and is named


def test_declared_sizes_larger_than_the_bytes_are_refused_before_anything_is_allocated(tmp_path):
    """Issue 57 item 4, our fuzz case: a zarr array's shape or chunk shape, HDF5 event datasets resized to 2^31-1e15
    rows, an AEDAT4 packet's size, an AEDAT 3.1 packet's capacity made larger than the bytes behind them. Each read
    (in a child limited to 2 GB of address space beyond what it has) is refused naming the file, or keeps the
    complete packets with a note: never a MemoryError, never silently wrong."""
    import multiprocessing
    import shutil

    (tmp_path / "corpus").mkdir()
    corpus = {e.name: e for e in fuzz_readers.make_corpus(tmp_path / "corpus", include_real=False)}
    outcomes = []
    ctx = multiprocessing.get_context("fork")
    for name in ("zarr", "hdf5", "aedat4", "aedat3"):
        entry = corpus[name]
        ref = fuzz_readers._read_zarr(entry.path) if name == "zarr" else read_recording(entry.path)
        for trial in range(4):
            target = tmp_path / f"{name}{trial}" / entry.path.name
            target.parent.mkdir()
            (shutil.copytree if entry.path.is_dir() else shutil.copy)(entry.path, target)
            fuzz_readers.declare_larger(target, name, random.Random(trial))
            recv, send = ctx.Pipe(duplex=False)
            p = ctx.Process(target=_classify_limited, args=(target, ref, send))
            p.start()
            p.join(60)
            outcome, detail = recv.recv()
            assert outcome in ("refused", "repaired", "exact"), (name, trial, outcome, detail)
            assert "MemoryError" not in detail
            outcomes.append(outcome)
    assert outcomes.count("refused") >= 8


def _classify_limited(target, ref, conn):
    import os
    import resource

    with open("/proc/self/statm") as f:  # address space in use, in pages
        used = int(f.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")
    resource.setrlimit(resource.RLIMIT_AS, (used + (2 << 30), resource.RLIM_INFINITY))
    try:
        conn.send(fuzz_readers.classify(target, "declared_size", ref))
    except MemoryError as exc:
        conn.send(("TRACEBACK", f"MemoryError {exc}"))


def test_unaccounted_changes_are_caught():
    """The accounting itself can fail: an event moved, or one gone without a note."""
    ev = fuzz_readers.synthetic_recording().events[:50].copy()
    moved = ev.copy()
    moved["t"][7] += 300
    assert fuzz_readers.unaccounted(moved, ev, ()) == ["1 event(s) at times (or places) the file does not hold",
                                                       "1 of the file's events gone, the notes name 0"]
    assert fuzz_readers.unaccounted(ev[:-2], ev, ()) == ["2 of the file's events gone, the notes name 0"]
    assert fuzz_readers.unaccounted(ev[:-2], ev, ("dropped 2 duplicated event(s) (same t, x, y, p ...)",)) == []


def test_corpus_reads_back_exactly(tmp_path):
    corpus = fuzz_readers.make_corpus(tmp_path, include_real=False)
    ref = fuzz_readers.synthetic_recording()
    for entry in corpus:
        if entry.name == "zarr":
            r = fuzz_readers._read_zarr(entry.path)
        else:
            r = read_recording(entry.path, **({"width": 64, "height": 48} if entry.name.startswith("npy") else {}))
        assert fuzz_readers.invariant_violations(r) == [], entry.name
        np.testing.assert_array_equal(r.events, ref.events if entry.name != "aedat3" else ref.events[
            np.arange(len(ref.events)) % 11 != 10], err_msg=entry.name)  # aedat3: every 11th event marked invalid
        # AEDAT 2.0 stores jAER's 32-bit µs counter
        if entry.name != "zarr":  # the project's zarr keeps the recording's clock, its file time in `source`
            assert r.t_offset_us == ref.t_offset_us % (2**32 if entry.name.startswith("aedat2") else 2**62), \
                entry.name
        if entry.name == "aedat3":
            np.testing.assert_array_equal(r.frames.images, ref.frames.images)
            np.testing.assert_array_equal(r.frames.t_us, ref.frames.t_us)


def test_mutations_are_deterministic():
    data = bytes(range(256)) * 4
    for kind in fuzz_readers.BYTE_KINDS:
        a = fuzz_readers.mutate(data, kind, random.Random(3))
        b = fuzz_readers.mutate(data, kind, random.Random(3))
        assert a == b and a != data, kind
