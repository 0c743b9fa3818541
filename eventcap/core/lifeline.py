"""Worker processes that die with the run that started them (``executor=processes``).

A ``kill -9`` of the driver gives it no chance to stop its process pool: the workers were re-parented to init and
went on computing queued batches (and kept multiprocessing's resource tracker alive) after a resumed run had
finished. Each worker therefore arms two things in its initializer:

* on Linux, ``prctl(PR_SET_PDEATHSIG, SIGKILL)``: the kernel kills the worker the moment its parent dies. (The signal
  follows the parent *thread* that created the worker; the pool's workers are started by the thread that submits,
  which is the thread running the whole pool.)
* everywhere, a daemon thread that checks ``os.getppid()`` twice a second and exits when the parent changed: the
  portable fallback (macOS has no parent-death signal), and the guard for a parent that died before the signal was
  armed.

A worker killed this way may leave a half-written ``tmp/`` entry (removed by the next run's orphan clean-up, its pid
being dead) and never a half-visible entry (commits are renames); entry locks are ``flock``s, which the kernel drops.
Why not a process group: ``killpg`` needs someone alive to send it, and a ``kill -9`` of the driver is exactly the
case where nobody is.
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys
import threading
import time

_PR_SET_PDEATHSIG = 1


def _arm_parent_death_signal() -> bool:
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def _watch_parent(parent_pid: int, poll_s: float) -> None:
    while True:
        time.sleep(poll_s)
        if os.getppid() != parent_pid:
            os._exit(1)  # no clean-up: the parent is gone, nobody waits for this process's results


def arm_before_exec(parent_pid: int) -> None:
    """For ``subprocess.Popen(preexec_fn=...)`` of a program that is not ours (the Rerun viewer): in the child, before
    it executes the program, ask the kernel to kill it when ``parent_pid`` dies (Linux; the signal survives the exec),
    and exit at once when that parent is already gone. No thread: the program replaces this process."""
    _arm_parent_death_signal()
    if os.getppid() != parent_pid:
        os._exit(1)


def die_with_parent(parent_pid: int, poll_s: float = 0.5) -> bool:
    """Make this process exit when ``parent_pid`` (its parent) dies. Returns whether the kernel signal is armed."""
    armed = _arm_parent_death_signal()
    if os.getppid() != parent_pid:  # the parent died before the signal was armed
        os._exit(1)
    threading.Thread(target=_watch_parent, args=(parent_pid, poll_s), name="eventcap-lifeline", daemon=True).start()
    return armed
