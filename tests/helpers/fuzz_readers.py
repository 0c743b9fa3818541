"""Fuzz the recording readers: damage small valid files of every format and read each in its own process.

Usage: ``python3 benchmarks/robustness/fuzz_readers.py --n 2000 [--seed 0] [--workers 2] [--timeout 20]``
(``--no-table`` leaves out issue 48's table of bad inputs run through the command line, bad_inputs.py).

Corpus: small simulated recordings (random events, smooth frames; not real sensor data), one for every reader of
the registry (:mod:`eventcap.io.registry`, plugins and EVENTCAP_READERS included: a reader this module cannot write
is written by its spec's ``sample``), written by :mod:`eventcap.io`: aedat4, EVT2 and EVT3 .raw, dat, hdf5 with
frames and calibration, npz with frames, npy, a (4, N) Fortran-order npy, a csv with a header of column names, an
rpg folder with PNG frames, AEDAT 2.0 (DAVIS240C, with special events; with APS frames) and AEDAT 3.1 with frames
and invalid events, the project's own zarr recording, plus the real DAVIS346 AEDAT4 file when it is there.

Damage, one per case, to one file of one corpus entry: bytes (bit flips, truncation, bytes inserted or deleted,
garbage in the header) and events re-written in the same format after a change (``wild_time``: one event 1e12 µs
late; ``time_jump``: every event from one on 2^26..2^40 µs late; ``x_outliers``: 0.1-100 % of the events beyond
the sensor's right edge, in the formats that do not declare a size; ``unit``: a csv's times written as integer µs
under the same header); events left in place but out of time order, re-written in file order (issue 57:
``late_event``: one event 5 s late; ``moved_block``: a block of events moved earlier in the file;
``swapped_blocks``: two blocks swapped; ``duplicated_block``: a block written twice) in the formats that keep file
order (EVT2 and EVT3 written word by word by tests/helpers/evt_reference.py, npy, csv, HDF5); and, in the
EVT files, word-level damage (``time_bitflip``: one bit of one time word; ``word_swap``: two blocks of words
swapped; ``word_dup``: a block of words written twice); and ``declared_size``: a size the file declares made far
larger than the bytes behind it (a zarr array's shape or chunk shape, HDF5 event datasets resized, an AEDAT4
packet's size, an AEDAT 3.1 packet's capacity). A forked child reads the case with ``read_recording`` (and, when that succeeds, streams
it with ``iter_event_chunks``; the zarr entry is read as ``eventcap preview`` reads it) and reports one class:

- ``exact``: the same events, size and frames as the original, and no repair the original did not have;
- ``repaired``: loaded with a repair the original did not have (a named warning), every promise below kept;
- ``undetectable``: loaded without a new repair, different from the original, every promise kept: a changed
  value that is still a valid one (a flipped bit of an x, a polarity, a time within the events' pace; a file cut
  where its format cannot show a cut: docs/io-robustness.md says which);
- ``refused``: a ``RecordingError`` (or the zarr reader's ``ArtifactError``) whose message names the damaged file;
- ``SILENTLY_WRONG`` (must be 0): events the file does not hold, or events it holds gone without a note (checked
  where what the file holds is known: the EVT files, decoded again word by word by a plain spec-literal decoder,
  tests/helpers/evt_reference.py, and every file written in file order); or a promise broken: events unsorted, not
  starting at 0, outside the sensor,
  polarity not ±1, duplicated; frames not finite in [0, 1], mis-shaped, times not increasing, negative exposure;
  a truncated file giving events that are not a prefix of the original's; streaming giving other events than
  reading whole; a time span longer than the original's by more than the time checks let pass (1 s); a sensor size
  other than the original's beyond what the size checks let pass; an event rate 100 times off the original's;
- ``TRACEBACK`` (must be 0): any other exception, or an error that does not name the file; the child dying;
- ``HANG`` (must be 0): the child took longer than the timeout.

Two children run at a time; the parent is single-threaded (fork + ``multiprocessing.connection.wait``). Each child
reports its peak resident memory (``ru_maxrss``, which includes what it shares with the parent).
"""

from __future__ import annotations

import argparse
import collections
import logging
import multiprocessing
import multiprocessing.connection
import os
import random
import re
import shutil
import sys
import tempfile
import time
import traceback
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]

from eventcap.events import EVENT_DTYPE
from eventcap.io import RecordingError, iter_event_chunks, read_recording, write_events, write_recording
from eventcap.io.recording import Frames, RawRecording

REAL_AEDAT4 = ROOT / "tests" / "data" / "real" / "davis346_lab_aps.aedat4"
OUTCOMES = ("exact", "repaired", "undetectable", "refused", "SILENTLY_WRONG", "TRACEBACK", "HANG")
MUST_BE_ZERO = ("SILENTLY_WRONG", "TRACEBACK", "HANG")
BYTE_KINDS = ("bitflip", "truncate", "insert", "delete", "header")
EVENT_KINDS = ("wild_time", "time_jump", "x_outliers", "unit")
#: events out of time order, written in file order (issue 57), and word-level damage of the EVT files
ORDER_KINDS = ("late_event", "moved_block", "swapped_blocks", "duplicated_block")
WORD_KINDS = ("time_bitflip", "word_swap", "word_dup")
#: a declared size made larger than the bytes behind it (issue 57 item 4): a zarr array's shape or chunk shape, HDF5
#: event datasets resized far beyond what is stored, an AEDAT4 packet's size, an AEDAT 3.1 packet's capacity
SIZE_KINDS = ("declared_size",)
SIZE_ENTRIES = ("zarr", "hdf5", "aedat4", "aedat4_real", "aedat3")
KINDS = BYTE_KINDS + EVENT_KINDS + ORDER_KINDS + WORD_KINDS + SIZE_KINDS
_WEIGHTS = (0.21, 0.12, 0.08, 0.08, 0.12, 0.06, 0.06, 0.06, 0.03, 0.03, 0.03, 0.03, 0.02, 0.02, 0.01, 0.01, 0.03)
#: the formats whose files keep the order events are written in (ORDER_KINDS apply to them)
FILE_ORDER = ("evt2", "evt3", "npy", "npy_4n", "csv", "hdf5")
EVT = ("evt2", "evt3")
#: formats that declare no sensor size (x_outliers applies to them) and the csv (unit applies to it)
SIZELESS = ("npy", "npy_4n", "csv")
#: the time checks let a jump below this pass (eventcap.io.checks.JUMP_MIN_US): a longer span is a broken promise
SPAN_SLACK_US = 1_000_000


@dataclass(frozen=True)
class Entry:
    """One valid corpus item: a file or folder, the files in it worth damaging, and how to write it again."""

    name: str
    path: Path
    files: tuple[str, ...]  # relative to path for folders, ("",) for a single file
    weights: tuple[float, ...]


def synthetic_recording(seed: int = 0, n: int = 1500, width: int = 64, height: int = 48) -> RawRecording:
    """A small simulated recording (random events, smooth frames) for the corpus; not real sensor data."""
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, 90_000, n))
    ev = np.empty(n, EVENT_DTYPE)
    ev["t"], ev["x"], ev["y"] = t, rng.integers(0, width, n), rng.integers(0, height, n)
    ev["p"] = rng.choice(np.array([-1, 1], np.int8), n)
    key = (ev["t"] << 20) | (ev["x"].astype(np.int64) << 8) | ev["y"]
    ev = ev[np.unique(key, return_index=True)[1]]
    ev["t"] -= ev["t"][0]  # the readers' clock starts at the first event
    yy, xx = np.mgrid[0:height, 0:width]
    images = np.stack([((np.sin(xx / 7.0 + k) * np.cos(yy / 5.0) + 1) * 127).round() / 255.0
                       for k in range(3)]).astype(np.float32)
    frames = Frames(images, np.array([2_000, 42_000, 82_000], np.int64), np.array([4_000, 4_000, 4_000], np.int64))
    from eventcap.camera import Camera

    cam = Camera(width, height, 60.0, 61.0, 31.5, 23.5, np.array([-0.3, 0.1, 0.0, 0.0, 0.0]))
    return RawRecording(ev, width, height, 1_633_000_000_000_000, Path("synthetic"), "synthetic", frames, cam)


def write_entry(name: str, folder: Path, rec: RawRecording, time_as_int_us: bool = False) -> Path:
    """Write ``rec`` (events on its clock, ``t_offset_us`` the file time of t = 0) as corpus entry ``name`` in
    ``folder``; the path written. The same function writes the events of a damaged case again."""
    from eventcap.io.aedat_legacy import write_aedat2, write_aedat31

    ev, w, h, off = rec.events, rec.width, rec.height, rec.t_offset_us
    simple = {"aedat4": "small.aedat4", "evt2": "small_evt2.raw", "evt3": "small_evt3.raw", "dat": "small.dat"}
    if name in simple:
        return write_events(folder / simple[name], ev, width=w, height=h, format=name, t_offset_us=off)
    if name == "hdf5":
        return write_recording(folder / "small.h5", rec, format="hdf5")
    if name == "npz":
        return write_recording(folder / "small.npz", rec, format="npz")
    if name == "npy":
        structured = np.empty(len(ev), [("t", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "i1")])
        structured["t"], structured["x"], structured["y"], structured["p"] = ev["t"] + off, ev["x"], ev["y"], ev["p"]
        np.save(folder / "small.npy", structured)
        return folder / "small.npy"
    cols = np.stack([ev["x"].astype(np.int64), ev["y"].astype(np.int64), ev["t"] + off,
                     (ev["p"] > 0).astype(np.int64)])
    if name == "npy_4n":
        np.save(folder / "small_4n.npy", np.asfortranarray(cols))
        return folder / "small_4n.npy"
    if name == "csv":
        if time_as_int_us:  # relabelled: integer µs under the same header (read as seconds unless told)
            text = "".join(f"{x},{y},{t - off},{p}\n" for x, y, t, p in cols.T)
        else:
            text = "".join(f"{x},{y},{t // 10**6}.{t % 10**6:06d},{p}\n" for x, y, t, p in cols.T)
        (folder / "small.csv").write_text("x,y,t,p\n" + text)  # text times in seconds
        return folder / "small.csv"
    file_ev = ev.copy()
    file_ev["t"] = (ev["t"] + off) % 2**32  # jAER's 32-bit µs counter
    if name == "aedat2":
        write_aedat2(folder / "small2.aedat", file_ev, specials_every=9)
        return folder / "small2.aedat"
    if name == "aedat2_aps":
        yy, xx = np.mgrid[0:180, 0:240]
        aps = np.stack([(512 + 400 * np.sin(xx / 9.0 + k) * np.cos(yy / 7.0)).astype(np.int64) for k in range(2)])
        t_aps = (file_ev["t"][0] + np.array([10_000, 50_000])) % 2**32
        write_aedat2(folder / "small2_aps.aedat", file_ev, frames=(aps, t_aps, t_aps + 4_000))
        return folder / "small2_aps.aedat"
    if name == "aedat3":
        file_ev["t"] = ev["t"] + off
        f = rec.frames
        images = np.rint(np.asarray(f.images) * 65535).astype(np.uint16)
        begin = f.t_us + off - f.exposure_us // 2
        write_aedat31(folder / "small3.aedat", file_ev, source="Test64x48", packet_events=400,
                      frames=(images, begin, begin + f.exposure_us), invalid_every=11)
        return folder / "small3.aedat"
    if name == "rpg":
        return write_recording(folder / "rpg", rec, format="rpg")
    if name == "zarr":
        import zarr

        from eventcap.io.convert import recording_from_raw

        recording_from_raw(rec, name="small").to_zarr(zarr.open_group(str(folder / "rec.zarr"), mode="w"))
        return folder / "rec.zarr"
    from eventcap.io.registry import readers

    spec = readers().find(name)
    if spec is None:
        raise ValueError(f"unknown corpus entry {name!r}")
    if not spec.sample:
        raise ValueError(f"reader {name!r} ({spec.origin}) declares no sample writer (ReaderSpec.sample): it cannot "
                         f"be fuzzed")
    return spec.load("sample")(folder, rec)


_FOLDERS = {"rpg": (("events.txt", "images.txt", "calib.txt", "images/frame_00000001.png"), (0.55, 0.15, 0.15, 0.15)),
            "zarr": (("zarr.json", "events/events/t/c/0", "events/events/x/c/0", "events/events/t/zarr.json",
                      "events/zarr.json", "frames/images/c/0/0/0", "camera/zarr.json"),
                     (0.2, 0.25, 0.15, 0.1, 0.1, 0.1, 0.1))}
#: corpus entries beyond one per registered format: the layouts of a format worth damaging apart
VARIANTS = {"npy": ("npy", "npy_4n"), "rpg": ("rpg", "csv"), "aedat2": ("aedat2", "aedat2_aps")}
#: the project's own format (eventcap convert writes it; not a reader of the registry)
EXTRA_ENTRIES = ("zarr",)
#: the formats this module writes itself (richer than a reader's own sample: frames, special events, invalid events)
OWN_WRITERS = ("aedat4", "evt2", "evt3", "dat", "hdf5", "npz", "npy", "npy_4n", "csv", "aedat2", "aedat2_aps",
               "aedat3", "rpg", "zarr")


def entry_names() -> tuple[str, ...]:
    """The corpus: every reader of the registry (eventcap/io/registry.py, plugins and EVENTCAP_READERS included),
    its variants, and the project's zarr. A reader this module has no writer for is fuzzed from its spec's
    ``sample``."""
    from eventcap.io.registry import readers

    names = [v for n in readers().names() for v in VARIANTS.get(n, (n,))]
    return tuple(names) + EXTRA_ENTRIES


ENTRY_NAMES = entry_names()


def make_corpus(folder: Path, include_real: bool = True) -> list[Entry]:
    """Write the corpus into ``folder``."""
    rec = synthetic_recording()
    entries = []
    for name in entry_names():
        path = write_entry(name, folder, rec)
        files, weights = _FOLDERS.get(name, (("",), (1.0,)))
        entries.append(Entry(name, path, files, weights))
    if include_real and REAL_AEDAT4.is_file():
        shutil.copy(REAL_AEDAT4, folder / "real.aedat4")
        entries.append(Entry("aedat4_real", folder / "real.aedat4", ("",), (1.0,)))
    return entries


def mutate(data: bytes, kind: str, rng: random.Random) -> bytes:
    """One byte-level damage of ``data`` (deterministic given ``rng``)."""
    b = bytearray(data)
    if not b:
        return bytes(b)
    if kind == "bitflip":
        for _ in range(rng.randint(1, 8)):
            i = rng.randrange(len(b))
            b[i] ^= 1 << rng.randrange(8)
    elif kind == "truncate":
        del b[rng.randrange(len(b)):]
    elif kind == "insert":
        i = rng.randrange(len(b) + 1)
        b[i:i] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 16)))
    elif kind == "delete":
        i = rng.randrange(len(b))
        del b[i:i + rng.randint(1, 16)]
    else:  # garbage in the header region
        span = min(len(b), 512)
        for _ in range(rng.randint(1, 8)):
            b[rng.randrange(span)] = rng.randrange(256)
    return bytes(b)


def damage_events(rec: RawRecording, kind: str, rng: random.Random) -> RawRecording:
    """The recording with its events changed as ``kind`` says (see the module docstring)."""
    import dataclasses

    ev = rec.events.copy()
    n = len(ev)
    if kind == "wild_time":
        ev["t"][rng.randrange(n)] += 10**12
    elif kind == "time_jump":
        ev["t"][rng.randrange(1, n):] += 2 ** rng.randint(26, 40)
    elif kind == "x_outliers":
        share = rng.choice((0.001, 0.01, 0.1, 0.5, 1.0))
        idx = np.array(rng.sample(range(n), max(1, int(share * n))))
        ev["x"][idx] = [rng.randrange(rec.width, rec.width + 500) for _ in idx]
    ev = ev[np.argsort(ev["t"], kind="stable")]
    ev["t"] -= ev["t"][0]
    return dataclasses.replace(rec, events=ev)


def damage_order(ev: np.ndarray, kind: str, rng: random.Random) -> np.ndarray:
    """The events in file order after ``kind`` (ORDER_KINDS): times unchanged except the one late event's."""
    n = len(ev)
    ev = ev.copy()
    if kind == "late_event":
        ev["t"][rng.randrange(1, n - 1)] += 5_000_000
        return ev
    size = rng.randint(1, max(1, n // 3))
    a = rng.randrange(0, n - size)
    if kind == "moved_block":  # a block from later in the file put earlier
        b = rng.randrange(a, n - size + 1)
        block = ev[b:b + size]
        rest = np.concatenate([ev[:b], ev[b + size:]])
        return np.concatenate([rest[:a], block, rest[a:]])
    if kind == "duplicated_block":
        return np.concatenate([ev[:a + size], ev[a:a + size], ev[a + size:]])
    size = min(size, n // 2)  # swapped_blocks: two non-overlapping blocks
    a = rng.randrange(0, n - 2 * size + 1)
    b = rng.randrange(a + size, n - size + 1)
    return np.concatenate([ev[:a], ev[b:b + size], ev[a + size:b], ev[a:a + size], ev[b + size:]])


def write_in_order(name: str, folder: Path, rec: RawRecording, ev: np.ndarray) -> Path:
    """Write events (file order, on ``rec``'s clock) as corpus entry ``name`` keeping their order."""
    import dataclasses

    if name in EVT:
        from .evt_reference import write_in_file_order

        return write_in_file_order(folder / f"small_{name}.raw", ev, name, rec.width, rec.height, rec.t_offset_us)
    if name == "hdf5":
        import h5py

        with h5py.File(folder / "small.h5", "w") as f:
            g = f.create_group("events")
            g["t"], g["x"], g["y"], g["p"] = ev["t"] + rec.t_offset_us, ev["x"], ev["y"], (ev["p"] > 0).astype("u1")
        return folder / "small.h5"
    return write_entry(name, folder, dataclasses.replace(rec, events=ev))


def damage_words(data: bytes, header_bytes: int, version: str, kind: str, rng: random.Random) -> bytes:
    """One word-level damage (WORD_KINDS) of an EVT file's bytes."""
    size = 2 if version == "evt3" else 4
    dtype = "<u2" if size == 2 else "<u4"
    body = np.frombuffer(data[header_bytes:len(data) - (len(data) - header_bytes) % size], dtype).copy()
    n = len(body)
    if kind == "time_bitflip":
        shift = 12 if size == 2 else 28
        times = np.flatnonzero(np.isin(body >> shift, (0x6, 0x8) if size == 2 else (0x8,)))
        k = int(times[rng.randrange(len(times))])
        body[k] ^= 1 << rng.randrange(12 if size == 2 else 28)
        return data[:header_bytes] + body.tobytes()
    m = rng.randint(1, max(1, n // 4))
    a = rng.randrange(0, n - m)
    if kind == "word_dup":
        body = np.concatenate([body[:a + m], body[a:a + m], body[a + m:]])
    else:
        m = min(m, n // 2)
        a = rng.randrange(0, n - 2 * m + 1)
        b = rng.randrange(a + m, n - m + 1)
        body = np.concatenate([body[:a], body[b:b + m], body[a + m:b], body[a:a + m], body[b + m:]])
    return data[:header_bytes] + body.tobytes()


def declare_larger(target: Path, entry_name: str, rng: random.Random) -> None:
    """Make one declared size of the copy at ``target`` larger than the bytes behind it (SIZE_KINDS)."""
    import json

    huge = rng.choice((10**15, 2**40, 2**31 - 1, 10**9))
    if entry_name == "zarr":
        meta = target / rng.choice(("events/events/t", "events/events/x", "frames/images")) / "zarr.json"
        doc = json.loads(meta.read_text())
        if rng.random() < 0.7:
            doc["shape"][0] = huge
        else:
            doc["chunk_grid"]["configuration"]["chunk_shape"][0] = huge
        meta.write_text(json.dumps(doc))
    elif entry_name == "hdf5":
        import h5py

        with h5py.File(target, "r+") as f:
            for k in ("t", "x", "y", "p"):
                f["events"][k].resize((min(huge, 2**40),))
    elif entry_name.startswith("aedat4"):
        from eventcap.io.aedat4 import check_ioheader

        start, _ = check_ioheader(target)
        data = bytearray(target.read_bytes())
        pos, offsets = start, []
        while pos + 8 <= len(data):
            offsets.append(pos)
            pos += 8 + int.from_bytes(data[pos + 4:pos + 8], "little")
        k = offsets[rng.randrange(len(offsets))]
        data[k + 4:k + 8] = min(huge, 2**32 - 1).to_bytes(4, "little")
        target.write_bytes(bytes(data))
    else:  # aedat3: a packet's capacity (events of `size` bytes that follow its header)
        from eventcap.io.aedat_legacy import read_legacy_header

        data = bytearray(target.read_bytes())
        pos = read_legacy_header(target)[2]
        offsets = []
        while pos + 28 <= len(data):
            offsets.append(pos)
            size, capacity = (int.from_bytes(data[pos + a:pos + a + 4], "little") for a in (4, 16))
            pos += 28 + size * capacity
        k = offsets[rng.randrange(len(offsets))]
        data[k + 16:k + 20] = min(huge, 2**31 - 1).to_bytes(4, "little")
        target.write_bytes(bytes(data))


# ------------------------------------------------------------------------------------------------------- checks
_NOTED_DROPS = (re.compile(r"dropped (\d+) event\(s\) with wild times"), re.compile(r"dropped the (\d+) event\(s\)"),
                re.compile(r"dropped (\d+) duplicated event\(s\)"), re.compile(r"dropped (\d+) outlier event\(s\)"))
_NOTED_SHIFT = re.compile(r"subtracted 2\^(\d+) µs from there on")


def unaccounted(got: np.ndarray, held: np.ndarray, repairs) -> list[str]:
    """What a read changed beyond what its notes say, given the events the file holds (``held``, file time, any
    order) and those read (``got``, file time): events at times the file does not hold (a shift the notes name
    excepted), or events gone without a note (wild times, a cut, duplicates and outliers dropped are named with
    their counts). Empty when everything is accounted for."""
    def rows(a: np.ndarray) -> list[tuple]:
        return [tuple(r) for r in np.asarray(a[["t", "x", "y", "p"]]).tolist()]

    pool = collections.Counter(rows(held))
    shifts = [0] + [1 << int(m.group(1)) for r in repairs for m in _NOTED_SHIFT.finditer(r)]
    foreign = 0
    for t, x, y, p in rows(got):
        for s in shifts:
            key = (t + s, x, y, p)
            if pool[key] > 0:
                pool[key] -= 1
                break
        else:
            foreign += 1
    out = []
    if foreign:
        out.append(f"{foreign} event(s) at times (or places) the file does not hold")
    noted = sum(int(m.group(1)) for r in repairs for rx in _NOTED_DROPS for m in rx.finditer(r))
    gone = len(held) - (len(got) - foreign)
    if gone != noted:
        out.append(f"{gone} of the file's events gone, the notes name {noted}")
    return out


def held_by_file(target: Path, entry_name: str, order_events: np.ndarray | None, t_offset_us: int) -> np.ndarray | None:
    """The events the damaged file holds, when known (file time): what was written in file order, or an EVT file
    decoded word by word by the spec-literal decoder."""
    if order_events is not None:
        out = order_events.copy()
        out["t"] += t_offset_us
        return out
    if entry_name in EVT and target.is_file():
        from .evt_reference import held_events

        from eventcap.io.prophesee import header_kind, read_header

        kind = header_kind(read_header(target)[0])
        return held_events(target, kind if kind in EVT else entry_name)
    return None


# ------------------------------------------------------------------------------------------------------- checks
def _abs_events(r: RawRecording) -> np.ndarray:
    out = r.events.copy()
    out["t"] = out["t"] + r.t_offset_us
    return out


def invariant_violations(r: RawRecording) -> list[str]:
    """What is wrong with a loaded recording (empty when it keeps every promise of the readers)."""
    bad = []
    ev = r.events
    if ev.dtype != EVENT_DTYPE:
        return [f"dtype {ev.dtype}"]
    if len(ev) == 0:
        bad.append("no events")
        return bad
    t = ev["t"]
    if np.any(np.diff(t) < 0):
        bad.append("unsorted times")
    if t[0] != 0:
        bad.append(f"first event at {t[0]} µs, not 0")
    if ev["x"].max() >= r.width or ev["y"].max() >= r.height:
        bad.append("event outside the sensor")
    if not np.all((ev["p"] == 1) | (ev["p"] == -1)):
        bad.append("polarity not ±1")
    if len(np.unique(ev)) != len(ev):
        bad.append("duplicate events")
    f = r.frames
    if f is not None:
        im = f.images
        if im.dtype != np.float32 or im.shape[1:] != (r.height, r.width):
            bad.append(f"frames {im.shape} {im.dtype}")
        elif not np.all(np.isfinite(im)) or im.min() < 0 or im.max() > 1:
            bad.append("frame pixels not finite in [0, 1]")
        if len(f.t_us) > 1 and np.any(np.diff(f.t_us) <= 0):
            bad.append("frame times not increasing")
        if f.exposure_us is not None and np.any(f.exposure_us < 0):
            bad.append("negative exposure")
    return bad


def promises_broken(r: RawRecording, ref: RawRecording) -> list[str]:
    """What the time, size and rate checks promise about a damaged file that loaded, and this one breaks."""
    bad = []
    span, ref_span = int(r.events["t"][-1]), int(ref.events["t"][-1])
    if span > ref_span + SPAN_SLACK_US:
        bad.append(f"spans {span} µs, the original {ref_span} µs")
    for got, want, axis in ((r.width, ref.width, "width"), (r.height, ref.height, "height")):
        if got != want and got > max(want + 16, int(want * 1.25)):  # within the gap rule's reach: cannot be told
            bad.append(f"{axis} {got}, the original {want}")
    rate, ref_rate = len(r.events) / max(span, 1), len(ref.events) / max(ref_span, 1)
    if not ref_rate / 100 <= rate <= ref_rate * 100:
        bad.append(f"{rate * 1e6:.3g} events/s, the original {ref_rate * 1e6:.3g}")
    return bad


def _same_frames(a: Frames | None, b: Frames | None) -> bool:
    if a is None or b is None:
        return a is b
    return (a.images.shape == b.images.shape and np.array_equal(a.images, b.images)
            and np.array_equal(a.t_us, b.t_us))


def _is_prefix(small: np.ndarray, big: np.ndarray) -> bool:
    return len(small) <= len(big) and np.array_equal(small, big[:len(small)])


def _is_subset(small: np.ndarray, big: np.ndarray) -> bool:
    return bool(np.all(np.isin(small.view(np.void), big.view(np.void))))


def _read_zarr(target: Path) -> RawRecording:
    """A project recording read as ``eventcap preview`` reads it, as a RawRecording (for the same checks)."""
    from eventcap.io.convert import is_project_recording, read_project_recording

    if not is_project_recording(target):
        read_recording(target)  # the readers say what the folder is not (a damaged zarr.json named)
        raise RecordingError(target, "read as something else than a project recording")
    rec = read_project_recording(target)
    ev = np.asarray(rec.events.events).copy()
    f = rec.frames
    frames = None if f is None else Frames(np.asarray(f.images, np.float32), np.asarray(f.t_us), np.asarray(f.exposure_us))
    t0 = int(ev["t"][0]) if len(ev) else 0
    ev["t"] -= t0
    if frames is not None:
        frames = Frames(frames.images, frames.t_us - t0, frames.exposure_us)
    return RawRecording(ev, rec.width, rec.height, t0, target, "zarr", frames, None, None, ())


def classify(target: Path, kind: str, reference: RawRecording, chunk_events: int = 257,
             held: np.ndarray | None = None) -> tuple[str, str]:
    """Read ``target`` and judge the outcome against the undamaged ``reference`` and, when given, the events the
    file holds (``held``, file time; see the module docstring)."""
    from eventcap.artifacts import ArtifactError

    zarr_entry = target.name.endswith(".zarr")
    try:
        r = _read_zarr(target) if zarr_entry else read_recording(target)
    except (RecordingError, ArtifactError) as exc:
        if str(target) in str(exc) or str(target.parent) in str(exc):
            return "refused", str(exc)[:300]
        return "TRACEBACK", f"{type(exc).__name__} not naming the file: {exc}"[:300]
    except Exception as exc:  # noqa: BLE001 - classifying is the point
        return "TRACEBACK", "".join(traceback.format_exception_only(exc)).strip()[-300:]
    bad = invariant_violations(r)
    ev = _abs_events(r)
    ref = _abs_events(reference)
    if not bad and kind == "truncate" and not zarr_entry:
        dropped = any("dropped" in x for x in r.repairs if x not in reference.repairs)
        if not (_is_prefix(ev, ref) or (dropped and _is_subset(ev, ref))):
            bad.append("a truncated file gave events that are not a prefix of the original's (nor, with events "
                       "dropped and said so, a subset of them)")
    if not bad and held is not None:
        bad = unaccounted(ev, held, r.repairs)
    if not bad:
        bad = promises_broken(r, reference)
    if not bad and not zarr_entry:
        try:
            stream = iter_event_chunks(target, chunk_events=chunk_events, width=r.width, height=r.height)
            parts = list(stream)
            streamed = np.concatenate(parts) if parts else np.empty(0, EVENT_DTYPE)
            if stream.t_offset_us != r.t_offset_us or not np.array_equal(streamed, r.events):
                bad.append("streaming gave other events than read_recording")
        except RecordingError:
            pass  # e.g. disorder across chunks: refused in bounded memory, fine
        except ValueError as exc:
            if "declares" not in str(exc):
                return "TRACEBACK", f"streaming: {type(exc).__name__}: {exc}"[:300]
        except Exception as exc:  # noqa: BLE001
            return "TRACEBACK", f"streaming: {type(exc).__name__}: {exc}"[:300]
    if bad:
        return "SILENTLY_WRONG", "; ".join(bad)
    same = (np.array_equal(ev, ref) and (r.width, r.height) == (reference.width, reference.height)
            and _same_frames(r.frames, reference.frames))
    new = [x for x in r.repairs if x not in reference.repairs]
    if new:
        return "repaired", new[0][:300]
    return ("exact", "") if same else ("undetectable", f"{len(ev)} events vs {len(ref)}")


# -------------------------------------------------------------------------------------------------- execution
_CORPUS: list[Entry] = []
_REFERENCES: dict[str, RawRecording] = {}


def _plan(seed: int, i: int) -> tuple[Entry, str, str]:
    rng = random.Random(f"{seed}:{i}")
    entry = _CORPUS[i % len(_CORPUS)]
    rel = rng.choices(entry.files, entry.weights)[0]
    kind = rng.choices(KINDS, _WEIGHTS)[0]
    if (kind in ORDER_KINDS and entry.name not in FILE_ORDER) or (kind in WORD_KINDS and entry.name not in EVT) \
            or (kind in SIZE_KINDS and entry.name not in SIZE_ENTRIES):
        kind = "bitflip"
    if kind in EVENT_KINDS and (entry.name in ("aedat4_real", "zarr") or (kind == "x_outliers" and entry.name not in
                                                                         SIZELESS) or (kind == "unit" and
                                                                                       entry.name != "csv")):
        # the real file is not re-written; the project's zarr holds what the readers (and their checks) gave it,
        # so only its bytes are damaged; outliers need a format without a declared size; unit, a csv
        kind = "bitflip"
    return entry, rel, kind


def _child(seed: int, i: int, workdir: str, conn) -> None:
    # Runs in a forked process: build the damaged copy, read it, send (outcome, detail, peak RSS in MB).
    import resource

    logging.disable(logging.CRITICAL)
    # Rust panics print a backtrace to stderr before they become exceptions: keep the report readable.
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 2)
    entry, rel, kind = _plan(seed, i)
    rng = random.Random(f"{seed}:{i}:bytes")
    base = Path(workdir) / f"case{i}"
    base.mkdir()
    target = None
    order = None
    if kind in EVENT_KINDS:
        rec = _REFERENCE_RECORDINGS[entry.name]
        damaged = damage_events(rec, kind, rng) if kind != "unit" else rec
        try:
            target = write_entry(entry.name, base, damaged, time_as_int_us=kind == "unit")
        except ValueError:  # the format cannot hold the damage (EVT, DAT: a gap beyond their time counters)
            shutil.rmtree(base)
            base.mkdir()
            kind, target = "bitflip", None
        ref = _REFERENCES[entry.name]
    elif kind in ORDER_KINDS:
        rec = _REFERENCE_RECORDINGS[entry.name]
        order = damage_order(rec.events, kind, rng)
        target = write_in_order(entry.name, base, rec, order)
        ref = _REFERENCES[entry.name]
    elif kind in SIZE_KINDS:
        target = base / entry.path.name
        (shutil.copytree if entry.path.is_dir() else shutil.copy)(entry.path, target)
        declare_larger(target, entry.name, rng)
        ref = _REFERENCES[entry.name]
    elif kind in WORD_KINDS:
        from eventcap.io.prophesee import read_header

        target = base / entry.path.name
        data = entry.path.read_bytes()
        target.write_bytes(damage_words(data, read_header(entry.path)[1], entry.name, kind, rng))
        ref = _REFERENCES[entry.name]
    if target is not None:
        pass
    elif entry.path.is_dir():
        target = base / entry.path.name
        shutil.copytree(entry.path, target)
        victim = target / rel
        victim.write_bytes(mutate(victim.read_bytes(), kind, rng))
        ref = _REFERENCES[entry.name]
    else:
        target = victim = base / entry.path.name
        shutil.copy(entry.path, victim)
        victim.write_bytes(mutate(victim.read_bytes(), kind, rng))
        ref = _REFERENCES[entry.name]
    held = held_by_file(target, entry.name, order, _REFERENCE_RECORDINGS[entry.name].t_offset_us)
    outcome, detail = classify(target, kind, ref, held=held)
    conn.send((outcome, detail, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, kind))
    conn.close()


_REFERENCE_RECORDINGS: dict[str, RawRecording] = {}


def run_fuzz(n: int, seed: int = 0, workers: int = 2, timeout_s: float = 20.0, include_real: bool = True,
             only: str | None = None, log=None) -> dict:
    """Run ``n`` damaged cases (of the corpus entries whose name contains ``only``, if given).

    Returns {"counts", "by_format", "by_kind", "examples", "seconds", "peak_mb"}.
    """
    ctx = multiprocessing.get_context("fork")
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="eventcap-fuzz-") as tmp:
        corpus_dir = Path(tmp) / "corpus"
        corpus_dir.mkdir()
        work = Path(tmp) / "work"
        work.mkdir()
        _CORPUS[:] = [e for e in make_corpus(corpus_dir, include_real) if only is None or only in e.name]
        if not _CORPUS:
            raise ValueError(f"no corpus entry matches {only!r}")
        _REFERENCES.clear()
        source = synthetic_recording()
        for e in _CORPUS:
            _REFERENCES[e.name] = _read_zarr(e.path) if e.name == "zarr" else read_recording(e.path)
            _REFERENCE_RECORDINGS[e.name] = source
        import aedat  # noqa: F401 - imported before forking, not in each child
        import faery  # noqa: F401
        import h5py  # noqa: F401
        import zarr  # noqa: F401

        counts = collections.Counter({k: 0 for k in OUTCOMES})
        by_format: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
        by_kind: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
        examples: dict[str, list[str]] = collections.defaultdict(list)
        running: dict = {}  # sentinel -> (i, process, conn, start)
        next_i = 0
        peak = [0.0]

        def record(i: int, outcome: str, detail: str, rss_mb: float = 0.0, done: str | None = None) -> None:
            entry, rel, kind = _plan(seed, i)
            kind = done or kind
            counts[outcome] += 1
            by_format[entry.name][outcome] += 1
            by_kind[kind][outcome] += 1
            peak[0] = max(peak[0], rss_mb)
            if len(examples[outcome]) < 5:
                examples[outcome].append(f"#{i} {entry.name}/{rel or entry.path.name} {kind}: {detail}")
            if log and outcome in MUST_BE_ZERO:
                log(f"{outcome}: #{i} {entry.name}/{rel} {kind}: {detail}")

        while next_i < n or running:
            while next_i < n and len(running) < workers:
                recv, send = ctx.Pipe(duplex=False)
                p = ctx.Process(target=_child, args=(seed, next_i, str(work), send), daemon=True)
                p.start()
                send.close()
                running[p.sentinel] = (next_i, p, recv, time.monotonic())
                next_i += 1
            deadline = min(start + timeout_s for (_, _, _, start) in running.values())
            ready = multiprocessing.connection.wait(list(running), timeout=max(0.0, deadline - time.monotonic()))
            now = time.monotonic()
            for sentinel in list(running):
                i, p, recv, start = running[sentinel]
                if sentinel in ready:
                    p.join()
                    result = None
                    try:
                        if recv.poll():
                            result = recv.recv()
                    except (EOFError, OSError):
                        result = None
                    if result is None or p.exitcode != 0:
                        record(i, "TRACEBACK", f"the child died: exit code {p.exitcode}")
                    else:
                        record(i, *result)
                elif now - start > timeout_s:
                    p.kill()
                    p.join()
                    record(i, "HANG", f"> {timeout_s} s")
                else:
                    continue
                recv.close()
                del running[sentinel]
                shutil.rmtree(work / f"case{i}", ignore_errors=True)
    return {"counts": dict(counts), "by_format": {k: dict(v) for k, v in by_format.items()},
            "by_kind": {k: dict(v) for k, v in by_kind.items()}, "examples": dict(examples),
            "seconds": time.perf_counter() - t0, "peak_mb": peak[0]}


def print_counts(res: dict, n: int, seed: int, workers: int, file=sys.stdout) -> None:
    c = res["counts"]
    print(f"{n} damaged files, seed {seed}, {res['seconds']:.1f} s ({1000 * res['seconds'] / max(n, 1):.1f} ms per "
          f"read, {workers} workers); peak memory of a reading process {res['peak_mb']:.0f} MB (ru_maxrss, shared "
          f"pages included)", file=file)
    print("  " + "  ".join(f"{k}={c.get(k, 0)}" for k in OUTCOMES), file=file)
    for title, table in (("by format", res["by_format"]), ("by damage", res["by_kind"])):
        print(f"{title}:", file=file)
        print(f"  {'':<12} " + " ".join(f"{k[:12]:>12}" for k in OUTCOMES), file=file)
        for name, cc in sorted(table.items()):
            print(f"  {name:<12} " + " ".join(f"{cc.get(k, 0):>12}" for k in OUTCOMES), file=file)
    for k in ("repaired", "undetectable", "refused", *MUST_BE_ZERO):
        for ex in res["examples"].get(k, [])[:3]:
            print(f"  e.g. {k}: {ex}", file=file)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=2000, help="number of damaged files to read")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=2, help="children reading at the same time")
    ap.add_argument("--timeout", type=float, default=20.0, help="seconds before a read counts as hung")
    ap.add_argument("--no-real", action="store_true", help="leave the real AEDAT4 file out of the corpus")
    ap.add_argument("--only", help="fuzz only corpus entries whose name contains this (e.g. aedat4, rpg)")
    ap.add_argument("--no-table", action="store_true", help="leave out issue 48's table (bad_inputs.py)")
    ap.add_argument("--no-settings", action="store_true", help="the table without its bad settings (eventcap run)")
    args = ap.parse_args(argv)
    logging.getLogger("eventcap.io").setLevel(logging.ERROR)  # the corpus' own repair notes are expected
    failed = False
    if not args.no_table:
        from . import bad_inputs

        with tempfile.TemporaryDirectory(prefix="eventcap-bad-") as tmp:
            rows = bad_inputs.issue_table(Path(tmp), [] if args.no_settings else None)
            rows += bad_inputs.memory_rows(Path(tmp))
            own = [] if args.no_settings else bad_inputs.ownership_rows(Path(tmp))
        print("issue 48's cases, run through the command line:")
        bad_inputs.print_table(rows)
        print()
        failed = any(r["exit"] == "HANG" or r["outcome"].startswith(("TRACEBACK", "HANG")) or r["left"] for r in rows)
        if own:
            print("issue 57's settings, each in a sandbox listed before and after (and /):")
            bad_inputs.print_ownership(own)
            print()
            failed |= any(r["left"] or (r["exit"] == 0) != (r["expected"] == "accepted") for r in own)
    res = run_fuzz(args.n, args.seed, args.workers, args.timeout, not args.no_real, args.only,
                   log=lambda s: print(s, file=sys.stderr, flush=True))
    print_counts(res, args.n, args.seed, args.workers)
    return 1 if failed or any(res["counts"].get(k, 0) for k in MUST_BE_ZERO) else 0


if __name__ == "__main__":
    sys.exit(main())
