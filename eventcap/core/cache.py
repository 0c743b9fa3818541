"""Content-addressed stage cache with atomic commits: a run killed at any moment resumes without recomputing what
it committed.

Layout under the cache root::

    entries/<stage>/<key>/manifest.json   key document, outputs, every file with size and sha256
    entries/<stage>/<key>/data/           zarr v3 group, one sub-group per output port
    CACHEDIR.TAG                          the marker: this folder is eventcap's cache (eventcap/core/ownership.py)
    tmp/<key>.<host>.<pid>.<nonce>/       an entry being written; renamed into entries/ when complete
    failures/<key>.json                   a failed computation (never a hit; removed when it later succeeds)
    locks/<key>.lock                      held (flock) by the one process computing the entry right now

A key is the sha256 of the canonical JSON of its key document (stage, version, result-affecting config, file
digests, input keys, batch). An entry exists for readers only once its directory has been renamed into place with its
manifest inside; a killed writer leaves only a ``tmp/`` orphan, removed by :meth:`Cache.clean_orphans`. Reading checks
every file against the manifest, so a missing or damaged chunk raises instead of reading back as fill values.

The cache writes and deletes only inside a root it marked (``CACHEDIR.TAG``, written when it creates the root or
takes an empty folder) and only names it writes itself: a non-empty folder without the marker is refused as a
cache (:func:`check_cache_root`), and clean-up leaves anything in ``tmp/``, ``trash/`` or ``locks/`` whose name the
cache does not give.

Concurrent runs on one cache compute each entry once: the task computing an entry holds its :class:`EntryLock` (an
exclusive ``flock``, dropped by the kernel when the holder dies, even by ``kill -9``); another run wanting the same
entry waits for it and then loads the committed entry. No deadlock is possible: a task holds one entry lock at a time
and never waits for another lock while holding it (its inputs are committed before it is started).
"""

from __future__ import annotations

import datetime as _dt
import errno
import fcntl
import hashlib
import json
import logging
import os
import shutil
import socket
import time
import uuid
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from eventcap.artifacts import Artifact
from eventcap.core.ownership import (
    CACHE_TAG,
    LOCK_FILE,
    TMP_NAME,
    TRASH_NAME,
    folder_listing,
    is_empty_folder,
    is_marked_cache,
    legacy_cache_layout,
    mark_cache,
    system_folder,
)
from eventcap.memo import ProcessCache
from eventcap.processes import pid_alive

log = logging.getLogger(__name__)

MANIFEST = "manifest.json"
FORMAT = 1
_HOST = socket.gethostname()


class CacheError(RuntimeError):
    """The cache cannot be used as asked (bad key prefix, unusable directory)."""


class CacheCorruptError(CacheError):
    """A committed entry does not match its manifest (missing or damaged file)."""


def canonical_json(doc: Any) -> str:
    return json.dumps(doc, sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False)


def make_key(doc: Mapping[str, Any]) -> str:
    return hashlib.sha256(canonical_json(doc).encode()).hexdigest()[:40]


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(1 << 22):
            h.update(block)
    return h.hexdigest()


@dataclass(frozen=True)
class Entry:
    """A committed cache entry."""

    path: Path
    manifest: dict[str, Any]

    @property
    def key(self) -> str:
        return self.manifest["key"]

    @property
    def stage(self) -> str:
        return self.manifest["stage"]

    def size_bytes(self) -> int:
        return sum(int(v[0]) for v in self.manifest["files"].values())


class Cache:
    """The cache rooted at ``root`` (a local directory; created and marked on first use). ``create=False``
    (inspecting commands) refuses a root that does not exist instead of creating it, and writes nothing. A
    non-empty folder that is not a cache is refused (:func:`check_cache_root`)."""

    def __init__(self, root: str | Path, create: bool = True):
        self.root = _local_root(root)
        self._verified: set[Path] = set()
        _check_root(root, self.root, must_exist=not create)
        if not create:
            return
        try:
            self.root.mkdir(parents=True, exist_ok=True)
            if not is_marked_cache(self.root):
                check_cache_root(root)  # again: the folder may have been filled since (or made by another run)
                if legacy_cache_layout(self.root):
                    log.info("cache: %s is a cache made before caches were marked: marked it (%s)", self.root,
                             CACHE_TAG)
                mark_cache(self.root)
            for sub in ("entries", "tmp", "failures", "trash"):
                (self.root / sub).mkdir(exist_ok=True)
        except OSError as exc:
            raise CacheError(_unusable_message(root, exc, "cannot create the cache there")) from None
        _check_atomic_rename(self.root)

    def ensure_marked(self) -> None:
        """Mark a cache made before caches were marked (see :func:`check_cache_root`) before deleting in it."""
        if not is_marked_cache(self.root):
            check_cache_root(self.root)
            mark_cache(self.root)

    # -- paths ----------------------------------------------------------------------------------------------------
    def entry_path(self, stage: str, key: str) -> Path:
        return self.root / "entries" / stage / key

    # -- lookup ---------------------------------------------------------------------------------------------------
    def lookup(self, stage: str, key: str) -> Entry | None:
        """The committed entry for ``key``, or None. A directory without a readable manifest does not exist."""
        path = self.entry_path(stage, key)
        try:
            manifest = json.loads((path / MANIFEST).read_text())
        except FileNotFoundError:
            return None
        except (OSError, json.JSONDecodeError) as exc:
            self.quarantine(path, f"unreadable manifest: {exc}")
            return None
        if manifest.get("format") != FORMAT or manifest.get("key") != key:
            self.quarantine(path, "manifest does not match its key or format")
            return None
        return Entry(path, manifest)

    def verify(self, entry: Entry) -> None:
        """Check every file of the entry against the manifest (size and sha256); raise CacheCorruptError."""
        if entry.path in self._verified:
            return
        data = entry.path
        listed = entry.manifest["files"]
        for rel, (size, digest) in listed.items():
            f = data / rel
            try:
                actual = f.stat().st_size
            except FileNotFoundError:
                raise CacheCorruptError(f"cache entry {entry.path}: file {rel} is missing (deleted or never synced)") from None
            if actual != size:
                raise CacheCorruptError(f"cache entry {entry.path}: file {rel} has {actual} bytes, manifest says {size}")
            if _sha256(f) != digest:
                raise CacheCorruptError(f"cache entry {entry.path}: file {rel} does not match its checksum")
        extra = [str(p.relative_to(data)) for p in (data / "data").rglob("*") if p.is_file()]
        extra = [p for p in extra if p not in listed]
        if extra:
            raise CacheCorruptError(f"cache entry {entry.path}: files not in the manifest: {extra[:3]}")
        self._verified.add(entry.path)

    def forget_verified(self) -> None:
        """Check every entry against its manifest again when it is next read."""
        self._verified.clear()

    def load(self, entry: Entry, port: str, cls: type[Artifact], window: tuple[int, int] | None = None,
             without: tuple[str, ...] = ()) -> Artifact:
        """Read one output port of a committed entry as ``cls`` (verified first); ``window=(t0_us, t1_us)``: only the
        rows of its time dimensions within it, ``without`` optional fields left out
        (:meth:`eventcap.artifact.Artifact.from_zarr`)."""
        import zarr

        self.verify(entry)
        outputs = entry.manifest["outputs"]
        if port not in outputs:
            raise CacheCorruptError(f"cache entry {entry.path}: no output {port!r} (has {sorted(outputs)})")
        group = zarr.open_group(str(entry.path / "data"), mode="r")
        return cls.from_zarr(group[port], where=f"{entry.path}/data/{port}", window=window,
                             without=without)

    # -- commit ---------------------------------------------------------------------------------------------------
    def commit(self, stage: str, key: str, doc: Mapping[str, Any], outputs: Mapping[str, Artifact],
               info: Mapping[str, Any] | None = None) -> Entry:
        """Write ``outputs`` atomically as the entry for ``key``; if another writer won the race, keep theirs."""
        import zarr

        tmp = self.root / "tmp" / f"{key}.{_HOST}.{os.getpid()}.{uuid.uuid4().hex[:8]}"
        tmp.mkdir(parents=True)
        try:
            group = zarr.open_group(str(tmp / "data"), mode="w")
            for port, artifact in outputs.items():
                artifact.write_zarr(group, port)
            files = {}
            for f in sorted(p for p in (tmp / "data").rglob("*") if p.is_file()):
                rel = str(f.relative_to(tmp))
                if rel.endswith(".partial"):
                    raise CacheError(f"zarr left a partial file {rel} while committing {stage}/{key}")
                files[rel] = [f.stat().st_size, _sha256(f)]
            manifest = {
                "format": FORMAT,
                "key": key,
                "stage": stage,
                "doc": doc,
                "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                "outputs": {p: {"type": a.type_name(), "schema_version": a.schema_version,
                                "schema": a.schema_signature()} for p, a in outputs.items()},
                "files": files,
                **(dict(info) if info else {}),
            }
            with open(tmp / MANIFEST, "w") as fh:
                fh.write(json.dumps(manifest, indent=1, sort_keys=True))
                fh.flush()
                os.fsync(fh.fileno())
            final = self.entry_path(stage, key)
            final.parent.mkdir(parents=True, exist_ok=True)
            try:
                os.rename(tmp, final)
            except OSError as exc:
                if exc.errno not in (errno.EEXIST, errno.ENOTEMPTY):
                    raise
                # the entry locks prevent this; seen only where flock does not work across writers
                log.warning("cache: entry %s/%s was computed twice (another writer committed it first; keeping "
                            "theirs)", stage, key[:12])
                shutil.rmtree(tmp, ignore_errors=True)
            _fsync_dir(final.parent)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        self.clear_failure(key)
        entry = self.lookup(stage, key)
        if entry is None:
            raise CacheError(f"entry {stage}/{key} vanished right after commit")
        return entry

    # -- failures -------------------------------------------------------------------------------------------------
    def record_failure(self, stage: str, key: str, doc: Mapping[str, Any], record: Mapping[str, Any]) -> Path:
        path = self.root / "failures" / f"{key}.json"
        body = {"key": key, "stage": stage, "doc": doc,
                "time": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"), **record}
        _atomic_write_text(path, json.dumps(body, indent=1, sort_keys=True, default=str))
        return path

    def failure(self, key: str) -> dict[str, Any] | None:
        try:
            return json.loads((self.root / "failures" / f"{key}.json").read_text())
        except (FileNotFoundError, json.JSONDecodeError):
            return None

    def clear_failure(self, key: str) -> None:
        (self.root / "failures" / f"{key}.json").unlink(missing_ok=True)

    # -- housekeeping ---------------------------------------------------------------------------------------------
    def quarantine(self, path: Path, why: str) -> None:
        """Move a damaged entry out of the way (so it is recomputed) and say so."""
        log.warning("cache entry %s is damaged (%s): removing it; it will be recomputed", path, why)
        dest = self.root / "trash" / f"{path.name}.{uuid.uuid4().hex[:8]}"
        try:
            os.rename(path, dest)
        except FileNotFoundError:
            return
        shutil.rmtree(dest, ignore_errors=True)
        self._verified.discard(path)

    def clean_orphans(self, max_age_s: float = 24 * 3600) -> list[Path]:
        """Remove temporary directories of writers that are gone (dead pid on this host, or older than max_age_s)."""
        removed, foreign = [], []
        now = time.time()
        if not is_marked_cache(self.root):  # made by an older version and never marked, or a foreign folder
            check_cache_root(self.root)
            mark_cache(self.root)
        subs = [self.root / "tmp", self.root / "trash"]
        for d in [d for sub in subs if sub.is_dir() for d in sub.iterdir()]:
            parts = d.name.split(".")
            dead = False
            if not (TRASH_NAME if d.parent.name == "trash" else TMP_NAME).match(d.name) or d.is_symlink():
                foreign.append(d)  # not a name the cache gives: not ours to remove
                continue
            if d.parent.name == "trash":
                dead = True
            elif len(parts) >= 4 and parts[-3] == _HOST:
                dead = not pid_alive(int(parts[-2])) if parts[-2].isdigit() else True
            else:
                try:
                    dead = now - d.stat().st_mtime > max_age_s
                except FileNotFoundError:
                    continue
            if dead:
                shutil.rmtree(d, ignore_errors=True) if d.is_dir() else d.unlink(missing_ok=True)
                removed.append(d)
        if removed:
            log.info("cache: removed %d orphaned temporary entr%s", len(removed), "y" if len(removed) == 1 else "ies")
        if foreign:
            log.warning("cache: left %d file(s) in %s that the cache did not write (e.g. %s)", len(foreign),
                        ", ".join(sorted({str(d.parent) for d in foreign})), foreign[0].name)
        clean_stale_locks(self.root)
        return removed

    def entries(self) -> list[Entry]:
        out = []
        for mf in sorted((self.root / "entries").glob(f"*/*/{MANIFEST}")):
            e = self.lookup(mf.parent.parent.name, mf.parent.name)
            if e is not None:
                out.append(e)
        return out

    def find(self, prefix: str) -> Entry:
        """The entry whose key starts with ``prefix`` (unique)."""
        if len(prefix) < 4:
            raise CacheError("give at least 4 characters of the key")
        matches = [mf.parent for mf in (self.root / "entries").glob(f"*/{prefix}*/{MANIFEST}")]
        if not matches:
            fails = list((self.root / "failures").glob(f"{prefix}*.json"))
            hint = f" (a failure is recorded for it: {fails[0]})" if fails else ""
            raise CacheError(f"no cache entry with key {prefix!r} under {self.root}{hint}")
        if len(matches) > 1:
            raise CacheError(f"key prefix {prefix!r} is ambiguous: {', '.join(m.name[:12] for m in matches[:5])}")
        entry = self.lookup(matches[0].parent.name, matches[0].name)
        if entry is None:
            raise CacheError(f"entry {matches[0]} is not readable")
        return entry

    def latest_for(self, stage: str, node: str, batch_index: int | None) -> dict[str, Any] | None:
        """The newest manifest of ``stage`` written for ``node`` (and batch), to explain why a key changed."""
        best, best_t = None, -1.0
        stage_dir = self.root / "entries" / stage
        if not stage_dir.is_dir():
            return None
        for mf in stage_dir.glob(f"*/{MANIFEST}"):
            try:
                t = mf.stat().st_mtime
                if t <= best_t:
                    continue
                m = json.loads(mf.read_text())
            except (OSError, json.JSONDecodeError):
                continue
            if m.get("node") == node and (m.get("batch") or {}).get("index") == batch_index:
                best, best_t = m, t
        return best


def explain_difference(old: Mapping[str, Any], new: Mapping[str, Any], prefix: str = "") -> list[str]:
    """Readable differences between two key documents: ``config.window: 3 -> 5``."""
    out = []
    for k in sorted(set(old) | set(new)):
        a, b = old.get(k, "<absent>"), new.get(k, "<absent>")
        if a == b:
            continue
        path = f"{prefix}{k}"
        if isinstance(a, Mapping) and isinstance(b, Mapping):
            out += explain_difference(a, b, path + ".")
        elif path.startswith("inputs."):
            out.append(f"{path} changed (upstream result differs)")
        else:
            out.append(f"{path}: {json.dumps(a)} -> {json.dumps(b)}")
    return out


def _local_root(root: str | Path) -> Path:
    """The cache directory as a local path; URLs of stores that cannot rename atomically are refused."""
    text = str(root)
    if "://" in text:
        scheme, _, rest = text.partition("://")
        if scheme != "file":
            raise CacheError(
                f"cache_dir {text}: the cache commits every entry by renaming a finished directory into place, and "
                f"{scheme}:// stores cannot rename a directory atomically (a reader could see half an entry). Put the "
                f"cache on a local disk or a shared POSIX filesystem (NFS, Lustre, BeeGFS, CephFS) mounted at the same "
                f"path on every worker, and give that path."
            )
        text = rest
    return Path(text).expanduser().resolve()


#: cache roots whose filesystem renames directories (checked once per process and root)
_RENAME_CHECKED = ProcessCache("cache.rename_checked")


#: errors that mean "you may not write here", not "this filesystem cannot do it"
_NOT_WRITABLE = (errno.EACCES, errno.EPERM, errno.EROFS)


def _check_root(given, root: Path, must_exist: bool) -> None:
    """A root that is a file, or (``must_exist``) missing, is refused with a message saying so; so is one that
    is not a cache (:func:`check_cache_root`)."""
    if must_exist and not root.exists():
        raise CacheError(f"cache_dir {given}: {root} does not exist (no cache there: a run creates it; "
                         f"the default is runs/cache relative to where you run, or $EVENTCAP_CACHE_DIR)")
    check_cache_root(given)


def check_cache_root(given) -> None:
    """Refuse, writing nothing, a ``cache_dir`` the cache must not take: a system folder (``/``, ``/proc``, ...),
    something that is not a folder, or a non-empty folder without the cache's marker (``CACHEDIR.TAG`` written by
    eventcap; a cache made before markers existed is recognised by its layout). Absent and empty folders are fine:
    the cache creates and marks them."""
    root = _local_root(given)
    why = system_folder(root)
    if why:
        raise CacheError(f"cache_dir {given}: {why}; the cache writes and deletes under its folder: give a folder "
                         f"of its own (the default is runs/cache)")
    if os.path.lexists(root) and not root.is_dir():
        raise CacheError(f"cache_dir {given}: {root} is a file, not a directory; give the cache's directory")
    if not root.is_dir() or is_marked_cache(root) or is_empty_folder(root) or legacy_cache_layout(root):
        return
    raise CacheError(f"cache_dir {given}: {root} is not an eventcap cache (it has no {CACHE_TAG} written by eventcap) "
                     f"and it is not empty (it holds {folder_listing(root)}): the cache removes what it finds in its "
                     f"tmp/ and trash/ folders, so it never takes a folder it did not make. Give a new or empty "
                     f"folder, or an eventcap cache")


def _unusable_message(given, exc: OSError, what: str) -> str:
    """The real cause of an OSError on the cache directory: not writable, a file in the way, or else as is."""
    if exc.errno in _NOT_WRITABLE:
        why = "the filesystem is mounted read-only" if exc.errno == errno.EROFS else "permission denied"
        return (f"cache_dir {given}: not writable ({why}: {exc.filename}); the cache writes its entries there. "
                f"Give a directory you can write to (cache_dir=... or $EVENTCAP_CACHE_DIR) or change its permissions")
    if exc.errno in (errno.ENOTDIR, errno.EEXIST):
        return f"cache_dir {given}: {exc.filename} is a file, not a directory ({exc.strerror}); {what}"
    return f"cache_dir {given}: {what}: {exc}"


def _rename_probe_paths(root: Path, pid: int, nonce: str) -> tuple[Path, Path]:
    """The rename probe's directory before and after its rename. Both end in ``.<host>.<pid>.<nonce>``, as the
    entries being written do, so :meth:`Cache.clean_orphans` removes what a process killed mid-probe leaves."""
    tail = f"{_HOST}.{pid}.{nonce}"
    return root / "tmp" / f"rename-probe.{tail}", root / "tmp" / f"rename-probe-done.{tail}"


def _check_atomic_rename(root: Path) -> None:
    """Refuse a filesystem that cannot rename a directory (some FUSE mounts), once per process and root."""
    _RENAME_CHECKED.get(root, lambda: _probe_atomic_rename(root))


def _probe_atomic_rename(root: Path) -> bool:
    """Rename a probe directory under ``root``: True, or CacheError saying why the cache cannot live there."""
    probe, done = _rename_probe_paths(root, os.getpid(), uuid.uuid4().hex[:8])
    try:
        (probe / "x").mkdir(parents=True)
        os.rename(probe, done)
    except OSError as exc:
        if exc.errno in _NOT_WRITABLE or exc.errno in (errno.ENOTDIR, errno.EEXIST):
            raise CacheError(_unusable_message(root, exc, "cannot write the cache there")) from None
        raise CacheError(
            f"cache_dir {root}: this filesystem cannot rename a directory ({exc}); the cache needs atomic renames "
            f"to commit entries. Use a local disk or a POSIX shared filesystem."
        ) from None
    finally:
        shutil.rmtree(probe, ignore_errors=True)
        shutil.rmtree(done, ignore_errors=True)
    return True


class EntryLock:
    """The lock of one cache entry, ``<cache>/locks/<key>.lock``, held while the entry is computed.

    An exclusive ``flock``: the kernel releases it when its holder exits or is killed, so a dead holder can never leave
    an entry stuck. The holder writes its pid/host/node into the file (for the "waiting for ..." message) and unlinks
    it on release; an acquirer that finds it locked a file already unlinked starts again on the new one.
    """

    def __init__(self, root: str | Path, key: str):
        self.path = Path(root) / "locks" / f"{key}.lock"
        self._fd: int | None = None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def acquire(self, blocking: bool = True, owner: str = "", on_wait=None, poll_s: float = 0.1) -> bool:
        """Take the lock; ``blocking=False``: return False at once when another process holds it. While waiting,
        ``on_wait(holder_text, waited_s)`` is called first after ``poll_s``, then every 30 s."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        t0, told = time.monotonic(), None
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = os.pread(fd, 1024, 0).decode(errors="replace").strip()
                os.close(fd)
                if not blocking:
                    return False
                waited = time.monotonic() - t0
                if on_wait is not None and (told is None or waited - told >= 30.0):
                    on_wait(holder or "holder unknown", waited)
                    told = waited
                time.sleep(min(0.5, poll_s * (1 + waited)))
                continue
            try:
                current = os.stat(self.path).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                current = False
            if not current:  # its holder released and unlinked it between our open and flock
                os.close(fd)
                continue
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"pid {os.getpid()} on host {_HOST}{', ' + owner if owner else ''}".encode(), 0)
            self._fd = fd
            return True

    def release(self) -> None:
        if self._fd is None:
            return
        self.path.unlink(missing_ok=True)  # while still holding it: nobody can take a file that is going away
        os.close(self._fd)
        self._fd = None


def clean_stale_locks(root: str | Path) -> int:
    """Remove lock files nobody holds (left by killed holders); return how many."""
    n = 0
    locks = Path(root) / "locks"
    if not locks.is_dir():
        return 0
    for f in locks.glob("*.lock"):
        if not LOCK_FILE.match(f.name) or f.is_symlink():
            continue  # not a lock the cache made
        lock = EntryLock(root, f.stem)
        if lock.acquire(blocking=False):
            lock.release()
            n += 1
    return n


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _atomic_write_text(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:6]}.tmp")
    with open(tmp, "w") as fh:
        fh.write(text)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)
