"""Run folders that belong to exactly one run: a fresh folder per run, claimed for as long as the run lives.

Two runs started in the same second used to share ``runs/<name>/<timestamp>/`` and mix their files. Now:

* the default folder name has microseconds (``runs/<name>/2026-11-23_21-05-53.481516``: readable, sorts by start
  time), and a run whose folder comes from the default pattern creates it with an exclusive ``mkdir``; should it exist
  already (another run, another host, the same microsecond), the run takes ``<folder>-1``, ``<folder>-2``, ...;
* every run (and every sweep, and ``eventcap benchmark``) holds an exclusive ``flock`` on ``<folder>/.eventcap.lock``
  while it runs. A second run given the same folder (``hydra.run.dir=...``) is refused with the holder's pid, host
  and command, before it writes anything there. The kernel drops the lock when its holder dies, even by ``kill -9``,
  so a killed run never leaves a folder claimed; a finished run's folder can be run into again, as before.

The claim happens in a Hydra callback (``hydra.callbacks.run_folder`` in conf/config.yaml), at the start of a run or
of a sweep: before Hydra writes ``.hydra/`` and opens the log file in the folder.
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


def claim(path: str | Path, what: str = "run", fresh: bool = False) -> Path:
    """Hold ``path`` for this process until :func:`release` or the process ends; return the folder claimed.

    ``fresh``: the folder must be new (see :func:`fresh_folder`); otherwise an existing folder that no live process
    holds is taken over. Raises :class:`RunFolderBusy` naming the holder when another live process holds it.
    """
    path = fresh_folder(path) if fresh else Path(path)
    path.mkdir(parents=True, exist_ok=True)
    real = path.resolve()
    if real in _HELD:
        return path
    fd = os.open(real / LOCK_NAME, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        try:
            holder = os.pread(fd, 4096, 0).decode(errors="replace").strip() or "holder unknown"
        finally:
            os.close(fd)
        raise RunFolderBusy(
            f"the {what} folder {path} is in use by another eventcap process ({holder}). Two runs writing into one folder "
            f"would mix their config, metrics and log: give this one another folder (e.g. leave hydra.run.dir / "
            f"hydra.sweep.dir at their defaults, which are unique per run), or wait until that one has finished."
        ) from None
    os.ftruncate(fd, 0)
    os.pwrite(fd, _holder_text().encode(), 0)
    _HELD[real] = fd
    return path


def release(path: str | Path) -> None:
    """Give up the claim on ``path`` (the lock file stays, naming its last holder)."""
    fd = _HELD.pop(Path(path).resolve(), None)
    if fd is not None:
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

    def _claim(self, config: Any, mode: str) -> None:
        from omegaconf import open_dict, read_write

        key = f"hydra.{mode}.dir"
        section = config.hydra[mode]
        wanted = str(section.dir)
        try:
            got = claim(wanted, what="sweep" if mode == "sweep" else "run",
                        fresh=not _given_on_command_line(config, key))
        except (RunFolderBusy, OSError) as exc:
            print(f"eventcap run: {exc}", file=sys.stderr, flush=True)
            raise SystemExit(2) from None
        self._claimed = got
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
        self._release()
