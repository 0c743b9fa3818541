"""What the tool may write into and delete from: a cache it marked, a run folder it made, never a system folder.

* **A cache carries a marker.** The root of every stage cache holds ``CACHEDIR.TAG`` (the Cache Directory Tagging
  Specification, https://bford.info/cachedir/, which backup tools honour), with a line naming eventcap. The cache
  writes it when it creates the root or takes an empty folder; a non-empty folder without it is refused as a cache,
  so clean-up, ``eventcap cache gc`` and every delete act only inside a folder the tool made. A cache made before the
  marker existed is recognised by its layout alone (only the cache's own folders, only names the cache writes) and
  marked then.
* **A run folder is fresh or the tool's own** (:func:`check_run_folder`): inside the project's runs root
  (``runs/`` of the current folder) when given relative, anywhere when given absolute if it is empty or absent;
  an existing folder is taken only when an earlier eventcap run made it.
* **System folders are never written** (:func:`system_folder`): ``/``, the kernel's pseudo-filesystems (``/proc``,
  ``/sys``, ``/dev``) and the operating system's own folders, nor anything that is not a folder.

Nothing here writes, except :func:`mark_cache`.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

#: The Cache Directory Tagging Specification's file name and first line.
CACHE_TAG = "CACHEDIR.TAG"
CACHE_TAG_SIGNATURE = "Signature: 8a477f597d28d172789f06886806bc55"
#: The line that says the cache is eventcap's (a CACHEDIR.TAG of another tool is not ours to clean).
CACHE_TAG_OWNER = "# eventcap stage cache"
CACHE_TAG_TEXT = (f"{CACHE_TAG_SIGNATURE}\n{CACHE_TAG_OWNER}: written by eventcap when it created this cache. Its\n"
                  "# clean-up (eventcap cache gc, orphaned temporary entries) acts only inside folders with this file.\n"
                  "# About cache directory tags: https://bford.info/cachedir/\n")

#: The sub-folders a stage cache holds (eventcap/core/cache.py).
CACHE_FOLDERS = ("entries", "tmp", "failures", "trash", "locks")
#: The sub-folders every cache made before caches were marked holds (created together with the root).
OLD_CACHE_FOLDERS = ("entries", "tmp", "failures", "trash")

#: Folders of the kernel (pseudo-filesystems): nothing is ever written under them, nor read as a setting's file.
PSEUDO_FILESYSTEMS = ("/proc", "/sys", "/dev")
#: The system's configuration and boot files (passwords, keys): never a file a setting takes, so never read.
PRIVATE_SYSTEM_FOLDERS = ("/etc", "/boot", "/private/etc")
#: The operating system's own folders: nothing is written under them either.
SYSTEM_FOLDERS = ("/bin", "/boot", "/etc", "/lib", "/lib32", "/lib64", "/libx32", "/sbin", "/usr", "/run",
                  "/var/run", "/var/lib", "/var/log", "/var/cache", "/snap", "/System", "/Library", "/private/etc",
                  "/private/var/db")
#: Folders that hold other people's things: never a run folder or a cache themselves (what is inside them may be).
SHARED_ROOTS = ("/", "/home", "/root", "/tmp", "/var", "/var/tmp", "/opt", "/mnt", "/media", "/srv", "/Users",
                "/Volumes", "/private", "/private/tmp")


def real(path: str | Path) -> Path:
    """``path`` made absolute with every symbolic link of its existing part resolved (what a write would reach)."""
    return Path(os.path.realpath(os.path.abspath(os.path.expanduser(str(path)))))


def _under(path: Path, folders) -> str | None:
    for f in folders:
        if path == Path(f) or Path(f) in path.parents:
            return f
    return None


def system_folder(path: str | Path) -> str | None:
    """Why ``path`` (resolved) is a place the tool never writes to nor deletes from, or None: ``/`` and the shared
    roots themselves (``/home``, ``/tmp``, ...), anything under the kernel's pseudo-filesystems or the operating
    system's folders."""
    p = real(path)
    shown = str(p) if os.path.abspath(os.path.expanduser(str(path))) == str(p) else f"{path} (that is {p})"
    pseudo = _under(p, PSEUDO_FILESYSTEMS)
    if pseudo:
        return f"{shown} is under {pseudo}, a folder of the kernel"
    system = _under(p, SYSTEM_FOLDERS)
    if system:
        return f"{shown} is {'' if str(p) == system else f'under {system}, '}a folder of the operating system"
    if str(p) in SHARED_ROOTS or p == p.parent:
        return f"{shown} is {'the root of the filesystem' if p == p.parent else 'a folder shared by everyone'}"
    return None


def folder_listing(path: Path, n: int = 4) -> str:
    """A few names of what ``path`` holds, for messages: ``a, b, c, ... (12 in all)``."""
    try:
        names = sorted(os.listdir(path))
    except OSError:
        return "(cannot list it)"
    shown = ", ".join(names[:n]) + (f", ... ({len(names)} in all)" if len(names) > n else "")
    return shown or "nothing"


#: the marker being written by another process (see :func:`mark_cache`): not a sign that a folder is in use
_TAG_BEING_WRITTEN = re.compile(rf"^\.{re.escape(CACHE_TAG)}\.\d+\.tmp$")


def is_empty_folder(path: Path) -> bool:
    """Whether ``path`` is a folder holding nothing (but, maybe, a cache marker another process is writing)."""
    try:
        with os.scandir(path) as it:
            return all(_TAG_BEING_WRITTEN.match(e.name) for e in it)
    except OSError:
        return False


# ------------------------------------------------------------------------------------------------------- caches
def is_marked_cache(root: str | Path) -> bool:
    """Whether ``root`` holds eventcap's ``CACHEDIR.TAG`` (a regular file with the signature and eventcap's line)."""
    tag = Path(root) / CACHE_TAG
    try:
        if not tag.is_file() or tag.is_symlink():
            return False
        with open(tag, "rb") as fh:
            head = fh.read(512).decode("utf-8", "replace")
    except OSError:
        return False
    return head.startswith(CACHE_TAG_SIGNATURE) and CACHE_TAG_OWNER in head


def mark_cache(root: str | Path) -> None:
    """Write eventcap's ``CACHEDIR.TAG`` into ``root``: complete or not at all (written aside, then linked into
    place, so two processes marking one new cache at once both succeed and neither sees half a marker)."""
    tag = Path(root) / CACHE_TAG
    if is_marked_cache(root):
        return
    tmp = tag.with_name(f".{CACHE_TAG}.{os.getpid()}.tmp")
    try:
        with open(tmp, "w") as fh:
            fh.write(CACHE_TAG_TEXT)
            fh.flush()
            os.fsync(fh.fileno())
        try:
            os.link(tmp, tag)
        except FileExistsError:
            pass  # another process marked it first
        except OSError:  # a filesystem without hard links
            os.replace(tmp, tag)
    finally:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass


KEY = r"[0-9a-f]{40}"
#: names the cache writes in each of its folders (eventcap/core/cache.py)
TMP_NAME = re.compile(rf"^(?:{KEY}|rename-probe|rename-probe-done)\.[^/]+\.\d+\.[0-9a-f]{{8}}$")
TRASH_NAME = re.compile(rf"^{KEY}\.[0-9a-f]{{8}}$")
LOCK_FILE = re.compile(rf"^{KEY}\.lock$")
FAILURE_FILE = re.compile(rf"^(?:{KEY}\.json|\.{KEY}\.json\.\d+\.[0-9a-f]{{6}}\.tmp)$")


def legacy_cache_layout(root: Path, limit: int = 200_000) -> bool:
    """Whether ``root`` is a stage cache made before caches were marked (the four folders every such cache has:
    entries, tmp, failures, trash; locks optional) or being made (a process may take an entry lock before the root is
    marked: ``locks/`` alone), nothing else at its top, and in each only names the cache writes (40-hex keys and the
    temporary names it gives them). Anything else (someone's ``tmp/`` and ``trash/``, even empty) is not a cache."""
    try:
        top = set(os.listdir(root))
    except OSError:
        return False
    if not top <= set(CACHE_FOLDERS) or not (top == {"locks"} or set(OLD_CACHE_FOLDERS) <= top):
        return False
    if any(not (root / d).is_dir() or (root / d).is_symlink() for d in top):
        return False
    checks = {"tmp": TMP_NAME, "trash": TRASH_NAME, "locks": LOCK_FILE, "failures": FAILURE_FILE}
    seen = 0
    for folder, pattern in checks.items():
        if folder not in top:
            continue
        for name in os.listdir(root / folder):
            seen += 1
            if seen > limit or not pattern.match(name):
                return False
    key = re.compile(rf"^{KEY}$")
    for stage in os.listdir(root / "entries") if "entries" in top else ():
        stage_dir = root / "entries" / stage
        if not stage_dir.is_dir() or stage_dir.is_symlink():
            return False
        for name in os.listdir(stage_dir):
            seen += 1
            if seen > limit or not key.match(name):
                return False
    return True


# ---------------------------------------------------------------------------------------------------- run folders
#: What an eventcap run, sweep or benchmark leaves in its folder first: one of these marks the folder as its own.
OWN_RUN_MARKERS = ("run.json", ".eventcap.lock", "multirun.yaml", "benchmark.json", "eventcap.log")


def is_own_run_folder(path: Path) -> bool:
    """Whether an existing folder was made by an eventcap run, sweep or benchmark (it holds what those write first:
    run.json, the run's lock file, eventcap.log beside Hydra's .hydra/, a sweep's multirun.yaml, a benchmark's
    benchmark.json)."""
    for name in OWN_RUN_MARKERS:
        if name == "eventcap.log" and not (path / ".hydra").is_dir():
            continue
        if (path / name).is_file() and not (path / name).is_symlink():
            return True
    return False


def runs_root() -> Path:
    """The project's runs root: ``runs/`` of the current folder (where relative run folders and the default cache
    go)."""
    return real(Path.cwd() / "runs")


def check_run_folder(path: str | Path, key: str, given_relative: bool, fresh: bool = False) -> str | None:
    """Why eventcap must not write its run (sweep, benchmark) into ``path``, or None. ``key`` names the setting the
    folder comes from (``hydra.run.dir``, ``name``, ``out``) for the message; ``given_relative``: the path was
    given relative to the current folder, so it must lie inside the runs root; ``fresh``: a new folder will be
    made beside it should it exist (what it holds does not matter)."""
    p = real(path)
    why = system_folder(path)
    if why:
        return f"{key}: {why}; a run writes only into a folder of its own: give another one"
    if os.path.lexists(p) and not p.is_dir():
        return f"{key}: {p} exists and is not a folder; give a folder (new, empty, or an earlier run's)"
    root = runs_root()
    if given_relative and root not in p.parents:  # the runs root itself holds the cache and other runs: not a run
        return (f"{key}: {p} lies outside the runs folder {root}: a relative run folder must be inside it (e.g. "
                f"runs/<name>/...); give an absolute path for a folder elsewhere (it must be new or empty)")
    if not fresh and p.is_dir() and not is_empty_folder(p) and not is_own_run_folder(p):
        return (f"{key}: {p} is a folder that no eventcap run made and it is not empty (it holds "
                f"{folder_listing(p)}): a run writes its config, log and results into its folder, so it takes only a "
                f"new folder, an empty one or an earlier run's. Give another folder")
    return None
