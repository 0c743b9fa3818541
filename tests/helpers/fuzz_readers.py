"""Fuzz the recording readers: mutate small valid files of every format and read each in its own process.

Run by ``python3 benchmarks/robustness/fuzz_readers.py --n 2000 [--seed 0] [--workers 2] [--timeout 20]`` and, small, by
tests/test_readers_fuzz.py.

Corpus: small synthetic recordings written by :mod:`eventcap.io` (aedat4, evt2, evt3, dat, hdf5 with frames and
calibration, npz with frames, npy, a (4, N) Fortran-order npy, a csv with a header of column names, an rpg folder
with PNG frames, AEDAT 2.0 (DAVIS240C, with special events) and AEDAT 3.1 with frames and invalid events, the last
two written by the tool's own test writers) plus the real DAVIS346 AEDAT4 file. Each
mutation (bit flips, truncation, byte insertion or deletion, garbage in the header) is applied to one file of
one corpus entry; a forked child reads it with ``read_recording`` (and, when that succeeds, streams it with
``iter_event_chunks``) and reports one outcome:

- ``loaded``: the same events and frames as the original;
- ``repaired``: loaded with at least one repair listed in ``repairs``;
- ``changed_undetected``: loaded without a repair note but different from the original, with every invariant
  holding — a change the format cannot reveal (a flipped bit in an EVT word, a cut at an EVT word boundary);
- ``rejected``: a ``RecordingError`` whose message names the mutated file;
- ``unclear_error``: any other exception, or a ``RecordingError`` not naming the file (must be 0);
- ``silently_wrong`` (must be 0): loaded events that break an invariant (unsorted, first event not at 0,
  outside the sensor, polarity not ±1, duplicates, frames not finite in [0, 1] or mis-shaped, frame times not
  increasing, negative exposure), a truncated file giving events that are not a prefix of the original's, or
  streaming giving other events than ``read_recording``;
- ``crashed`` (must be 0): the child died (signal, abort, non-zero exit) without reporting;
- ``hung`` (must be 0): the child took longer than the timeout.

Two children run at a time; the parent is single-threaded (fork + ``multiprocessing.connection.wait``).
"""

from __future__ import annotations

import collections
import logging
import multiprocessing
import multiprocessing.connection
import os
import random
import shutil
import tempfile
import time
import traceback
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from eventcap.events import EVENT_DTYPE
from eventcap.io import RecordingError, iter_event_chunks, read_recording, write_events, write_recording
from eventcap.io.recording import Frames, RawRecording

from .paths import REAL_DAVIS346

REAL_AEDAT4 = REAL_DAVIS346
OUTCOMES = ("loaded", "repaired", "changed_undetected", "rejected", "unclear_error", "silently_wrong", "crashed",
            "hung")
MUST_BE_ZERO = ("unclear_error", "silently_wrong", "crashed", "hung")
KINDS = ("bitflip", "truncate", "insert", "delete", "header")


@dataclass(frozen=True)
class Entry:
    """One valid corpus item: a file or folder, the files in it worth mutating, and its decoded reference."""

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


def make_corpus(folder: Path, include_real: bool = True) -> list[Entry]:
    """Write the corpus into ``folder``."""
    rec = synthetic_recording()
    ev, w, h, off = rec.events, rec.width, rec.height, rec.t_offset_us
    entries = []
    for fmt, name in (("aedat4", "small.aedat4"), ("evt2", "small_evt2.raw"), ("evt3", "small_evt3.raw"),
                      ("dat", "small.dat")):
        write_events(folder / name, ev, width=w, height=h, format=fmt, t_offset_us=off)
        entries.append(Entry(fmt, folder / name, ("",), (1.0,)))
    write_recording(folder / "small.h5", rec, format="hdf5")
    entries.append(Entry("hdf5", folder / "small.h5", ("",), (1.0,)))
    write_recording(folder / "small.npz", rec, format="npz")
    entries.append(Entry("npz", folder / "small.npz", ("",), (1.0,)))
    structured = np.empty(len(ev), [("t", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "i1")])
    structured["t"], structured["x"], structured["y"], structured["p"] = ev["t"] + off, ev["x"], ev["y"], ev["p"]
    np.save(folder / "small.npy", structured)
    entries.append(Entry("npy", folder / "small.npy", ("",), (1.0,)))
    cols = np.stack([ev["x"].astype(np.int64), ev["y"].astype(np.int64), ev["t"] + off, (ev["p"] > 0).astype(np.int64)])
    np.save(folder / "small_4n.npy", np.asfortranarray(cols))
    entries.append(Entry("npy_4n", folder / "small_4n.npy", ("",), (1.0,)))
    (folder / "small.csv").write_text("x,y,t,p\n" + "".join(f"{x},{y},{t // 10**6}.{t % 10**6:06d},{p}\n"
                                                             for x, y, t, p in cols.T))  # text times in seconds
    entries.append(Entry("csv", folder / "small.csv", ("",), (1.0,)))
    from eventcap.io.aedat_legacy import write_aedat2, write_aedat31

    file_ev = ev.copy()
    file_ev["t"] = (ev["t"] + off) % 2**32  # jAER's 32-bit µs counter
    write_aedat2(folder / "small2.aedat", file_ev, specials_every=9)
    entries.append(Entry("aedat2", folder / "small2.aedat", ("",), (1.0,)))
    yy, xx = np.mgrid[0:180, 0:240]
    aps = np.stack([(512 + 400 * np.sin(xx / 9.0 + k) * np.cos(yy / 7.0)).astype(np.int64) for k in range(2)])
    t_aps = (file_ev["t"][0] + np.array([10_000, 50_000])) % 2**32
    write_aedat2(folder / "small2_aps.aedat", file_ev, frames=(aps, t_aps, t_aps + 4_000))
    entries.append(Entry("aedat2_aps", folder / "small2_aps.aedat", ("",), (1.0,)))
    file_ev["t"] = ev["t"] + off
    f = rec.frames
    images = np.rint(np.asarray(f.images) * 65535).astype(np.uint16)
    begin = f.t_us + off - f.exposure_us // 2
    write_aedat31(folder / "small3.aedat", file_ev, source="Test64x48", packet_events=400,
                  frames=(images, begin, begin + f.exposure_us), invalid_every=11)
    entries.append(Entry("aedat3", folder / "small3.aedat", ("",), (1.0,)))
    write_recording(folder / "rpg", rec, format="rpg")
    entries.append(Entry("rpg", folder / "rpg", ("events.txt", "images.txt", "calib.txt", "images/frame_00000001.png"),
                         (0.55, 0.15, 0.15, 0.15)))
    if include_real and REAL_AEDAT4.is_file():
        shutil.copy(REAL_AEDAT4, folder / "real.aedat4")
        entries.append(Entry("aedat4_real", folder / "real.aedat4", ("",), (1.0,)))
    return entries


def mutate(data: bytes, kind: str, rng: random.Random) -> bytes:
    """One mutation of ``data`` (deterministic given ``rng``)."""
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


def _same_frames(a: Frames | None, b: Frames | None) -> bool:
    if a is None or b is None:
        return a is b
    return (a.images.shape == b.images.shape and np.array_equal(a.images, b.images)
            and np.array_equal(a.t_us, b.t_us))


def _is_prefix(small: np.ndarray, big: np.ndarray) -> bool:
    return len(small) <= len(big) and np.array_equal(small, big[:len(small)])


def classify(target: Path, kind: str, reference: RawRecording, chunk_events: int = 257) -> tuple[str, str]:
    """Read ``target`` and judge the outcome against the unmutated ``reference`` (see the module docstring)."""
    try:
        r = read_recording(target)
    except RecordingError as exc:
        root = str(target)
        if root in str(exc) or str(target.parent) in str(exc):
            return "rejected", str(exc)[:300]
        return "unclear_error", f"RecordingError not naming the file: {exc}"[:300]
    except Exception as exc:  # noqa: BLE001 - classifying is the point
        return "unclear_error", "".join(traceback.format_exception_only(exc)).strip()[-300:]
    bad = invariant_violations(r)
    ev = _abs_events(r)
    ref = _abs_events(reference)
    if not bad and kind == "truncate" and not _is_prefix(ev, ref):
        bad.append("a truncated file gave events that are not a prefix of the original's")
    if not bad:
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
                return "unclear_error", f"streaming: {type(exc).__name__}: {exc}"[:300]
        except Exception as exc:  # noqa: BLE001
            return "unclear_error", f"streaming: {type(exc).__name__}: {exc}"[:300]
    if bad:
        return "silently_wrong", "; ".join(bad)
    same = (np.array_equal(ev, ref) and (r.width, r.height) == (reference.width, reference.height)
            and _same_frames(r.frames, reference.frames))
    if r.repairs:
        return "repaired", r.repairs[0][:300]
    return ("loaded", "") if same else ("changed_undetected", f"{len(ev)} events vs {len(ref)}")


# -------------------------------------------------------------------------------------------------- execution
_CORPUS: list[Entry] = []
_REFERENCES: dict[str, RawRecording] = {}


def _plan(seed: int, i: int) -> tuple[Entry, str, str]:
    rng = random.Random(f"{seed}:{i}")
    entry = _CORPUS[i % len(_CORPUS)]
    rel = rng.choices(entry.files, entry.weights)[0]
    kind = rng.choices(KINDS, (0.3, 0.2, 0.15, 0.15, 0.2))[0]
    return entry, rel, kind


def _child(seed: int, i: int, workdir: str, conn) -> None:
    # Runs in a forked process: build the mutated copy, read it, send (outcome, detail).
    logging.disable(logging.CRITICAL)
    # Rust panics print a backtrace to stderr before they become exceptions: keep the report readable.
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 2)
    entry, rel, kind = _plan(seed, i)
    rng = random.Random(f"{seed}:{i}:bytes")
    base = Path(workdir) / f"case{i}"
    if entry.path.is_dir():
        shutil.copytree(entry.path, base)
        target = base
        victim = base / rel
    else:
        base.mkdir()
        target = victim = base / entry.path.name
        shutil.copy(entry.path, victim)
    victim.write_bytes(mutate(victim.read_bytes(), kind, rng))
    outcome, detail = classify(target, kind, _REFERENCES[entry.name])
    conn.send((outcome, detail))
    conn.close()


def run_fuzz(n: int, seed: int = 0, workers: int = 2, timeout_s: float = 20.0, include_real: bool = True,
             only: str | None = None, log=None) -> dict:
    """Run ``n`` mutations (of the corpus entries whose name contains ``only``, if given).

    Returns {"counts", "by_format", "examples", "seconds"}.
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
        for e in _CORPUS:
            _REFERENCES[e.name] = read_recording(e.path)
        import aedat  # noqa: F401 - imported before forking, not in each child
        import faery  # noqa: F401
        import h5py  # noqa: F401

        counts = collections.Counter({k: 0 for k in OUTCOMES})
        by_format: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
        examples: dict[str, list[str]] = collections.defaultdict(list)
        running: dict = {}  # sentinel -> (i, process, conn, start)
        next_i = 0

        def record(i: int, outcome: str, detail: str) -> None:
            entry, rel, kind = _plan(seed, i)
            counts[outcome] += 1
            by_format[entry.name][outcome] += 1
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
                        record(i, "crashed", f"exit code {p.exitcode}")
                    else:
                        record(i, *result)
                elif now - start > timeout_s:
                    p.kill()
                    p.join()
                    record(i, "hung", f"> {timeout_s} s")
                else:
                    continue
                recv.close()
                del running[sentinel]
                case = work / f"case{i}"
                shutil.rmtree(case, ignore_errors=True)
    return {"counts": dict(counts), "by_format": {k: dict(v) for k, v in by_format.items()},
            "examples": dict(examples), "seconds": time.perf_counter() - t0}
