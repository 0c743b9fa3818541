"""Run folders that belong to exactly one run: a fresh folder per run, claimed for as long as the run lives.

Two runs started in the same second used to share ``runs/<name>/<timestamp>/`` and mix their files. Now:

* the default folder name has microseconds (``runs/<name>/2026-11-23_21-05-53.481516``: readable, sorts by start
  time), and a run whose folder comes from the default pattern creates it with an exclusive ``mkdir``; should it exist
  already (another run, another host, the same microsecond), the run takes ``<folder>-1``, ``<folder>-2``, ...;
* every run (and every sweep, and ``eventcap benchmark``) holds an exclusive ``flock`` on ``<folder>/.eventcap.lock``
  while it runs. A second run given the same folder (``hydra.run.dir=...``) is refused with the holder's pid, host
  and command, before it writes anything there. The kernel drops the lock when its holder dies, even by ``kill -9``,
  so a killed run never leaves a folder claimed; a finished run removes the lock file, and its folder can be run
  into again, as before;
* a run writes only into a folder of its own (:func:`eventcap.core.ownership.check_run_folder`): a relative folder
  lies inside the runs root (``runs/``: ``name=../../x`` is refused), an absolute one is new or empty, an existing
  one was made by an earlier eventcap run; ``/``, system folders and files are refused, all before anything is
  written.

The claim happens in a Hydra callback (``hydra.callbacks.run_folder`` in conf/config.yaml), at the start of a run or
of a sweep: before Hydra writes ``.hydra/`` and opens the log file in the folder. A sweep prints its folder when it
ends.
"""

from __future__ import annotations

import datetime as _dt
import errno
import fcntl
import os
import socket
import sys
from pathlib import Path
from typing import Any

from eventcap.core.ownership import check_run_folder

LOCK_NAME = ".eventcap.lock"

#: folders claimed by this process: resolved path -> open file descriptor holding the flock
_HELD: dict[Path, int] = {}


class RunFolderBusy(RuntimeError):
    """Another live process holds the folder."""


def _holder_text() -> str:
    cmd = " ".join(sys.argv)[:300]
    now = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
    return f"pid {os.getpid()} on host {socket.gethostname()}, started {now}: {cmd}\n"


def fresh_folder(path: str | Path) -> Path:
    """Create ``path`` (parents too) exclusively; if it exists, the first free ``path-1``, ``path-2``, ..."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    for i in range(10_000):
        candidate = path if i == 0 else path.with_name(f"{path.name}-{i}")
        try:
            os.mkdir(candidate)
            return candidate
        except FileExistsError:
            continue
    raise OSError(errno.EEXIST, f"no free run folder name next to {path}")


class RunFolderRefused(ValueError):
    """The folder is not one a run may write into (eventcap.core.ownership.check_run_folder)."""


def claim(path: str | Path, what: str = "run", fresh: bool = False, key: str = "hydra.run.dir",
          relative: bool | None = None) -> Path:
    """Hold ``path`` for this process until :func:`release` or the process ends; return the folder claimed.

    ``fresh``: the folder must be new (see :func:`fresh_folder`); otherwise an existing folder that no live process
    holds is taken over. Raises :class:`RunFolderRefused` (naming ``key``) for a folder the run must not write into
    (:func:`eventcap.core.ownership.check_run_folder`; ``relative``: the path was given relative, by default whether
    it is), and :class:`RunFolderBusy` naming the holder when another live process holds it. Nothing is written
    before these checks.
    """
    given_relative = not Path(path).expanduser().is_absolute() if relative is None else relative
    why = check_run_folder(path, key, given_relative, fresh=fresh)
    if why:
        raise RunFolderRefused(why)
    path = fresh_folder(path) if fresh else Path(path)
    path.mkdir(parents=True, exist_ok=True)
    real = path.resolve()
    if real in _HELD:
        return path
    while True:
        fd = os.open(real / LOCK_NAME, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            try:
                holder = os.pread(fd, 4096, 0).decode(errors="replace").strip() or "holder unknown"
            finally:
                os.close(fd)
            raise RunFolderBusy(
                f"the {what} folder {path} is in use by another eventcap process ({holder}). Two runs writing into one "
                f"folder would mix their config, metrics and log: give this one another folder (e.g. leave "
                f"hydra.run.dir / hydra.sweep.dir at their defaults, which are unique per run), or wait until that one "
                f"has finished."
            ) from None
        try:
            current = os.stat(real / LOCK_NAME).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            current = False
        if current:
            break
        os.close(fd)  # its holder finished and removed the file between our open and flock: take the new one
    os.ftruncate(fd, 0)
    os.pwrite(fd, _holder_text().encode(), 0)
    _HELD[real] = fd
    return path


def release(path: str | Path) -> None:
    """Give up the claim on ``path`` and remove its lock file (while still holding it: a process that opened the file
    meanwhile sees that it is gone and takes a new one)."""
    real = Path(path).resolve()
    fd = _HELD.pop(real, None)
    if fd is not None:
        try:
            if os.stat(real / LOCK_NAME).st_ino == os.fstat(fd).st_ino:
                os.unlink(real / LOCK_NAME)
        except OSError:
            pass
        os.close(fd)  # closing the only descriptor drops the flock


def _given_on_command_line(config: Any, key: str) -> bool:
    overrides = list(config.hydra.overrides.hydra or []) + list(config.hydra.overrides.task or [])
    return any(str(o).split("=", 1)[0].lstrip("+~") == key for o in overrides)


try:
    from hydra.experimental.callback import Callback as _HydraCallback
except ImportError:  # pragma: no cover - hydra is a dependency; this keeps the module importable without it
    _HydraCallback = object


class ClaimRunFolder(_HydraCallback):
    """Hydra callback: claim ``hydra.run.dir`` (a run) or ``hydra.sweep.dir`` (a sweep) before anything is written.

    A folder from the default pattern is made fresh (never shared, even by two runs in one microsecond); a folder
    given on the command line may be an old one, but never one that another live run holds. The folder actually
    claimed is written back into the config, so Hydra, the log file and the run all use it.
    """

    def __init__(self) -> None:
        self._claimed: Path | None = None
        self._mode = "run"

    def _claim(self, config: Any, mode: str) -> None:
        from omegaconf import open_dict, read_write

        key = f"hydra.{mode}.dir"
        section = config.hydra[mode]
        wanted = str(section.dir)
        given = _given_on_command_line(config, key)
        try:
            got = claim(wanted, what="sweep" if mode == "sweep" else "run", fresh=not given,
                        key=key if given else f"{key} (from name={config.get('name')!r})",
                        relative=not Path(wanted).expanduser().is_absolute())
        except (RunFolderBusy, RunFolderRefused) as exc:
            print(f"eventcap run: {exc}", file=sys.stderr, flush=True)
            raise SystemExit(2) from None
        except OSError as exc:
            print(f"eventcap run: {key}: cannot make the {mode} folder {wanted}: {exc.strerror or exc}"
                  f"{f' ({exc.filename})' if exc.filename else ''}", file=sys.stderr, flush=True)
            raise SystemExit(2) from None
        self._claimed = got
        self._mode = mode
        with read_write(section), open_dict(section):
            section.dir = str(got)  # a literal from now on: jobs of a sweep all use this one folder

    def on_run_start(self, config: Any, **kwargs: Any) -> None:
        self._claim(config, "run")

    def on_multirun_start(self, config: Any, **kwargs: Any) -> None:
        self._claim(config, "sweep")

    def _release(self) -> None:
        if self._claimed is not None:
            release(self._claimed)
            self._claimed = None

    def on_run_end(self, config: Any, **kwargs: Any) -> None:
        self._release()

    def on_multirun_end(self, config: Any, **kwargs: Any) -> None:
        folder = self._claimed
        self._release()
        if folder is not None:
            import logging

            jobs = sorted(p.name for p in folder.iterdir() if p.is_dir() and p.name.isdigit()) if folder.is_dir() else []
            line = (f"sweep folder {shown_path(folder)}/: {len(jobs)} job folder(s); one table of them: eventcap report "
                    f"{shown_path(folder)}")
            logging.getLogger("eventcap").info("%s", line)
            print(line, file=sys.stderr, flush=True)


def shown_path(path: Path) -> str:
    """``path`` relative to the current folder when inside it (as the user typed the command), else absolute."""
    try:
        return str(Path(path).resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)
