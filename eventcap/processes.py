"""What the core asks about operating-system processes and their memory (shared by the cache, the recording
converter, the readers and the artifacts).

A folder or entry named after the process that writes it (``<name>.partial-<pid>``, the cache's ``tmp/`` entries)
is a leftover once that process is gone. This module imports nothing of eventcap, so the domain library (``io``)
and the orchestration (``cache``) can both use it.
"""

from __future__ import annotations

import os


def pid_alive(pid: int) -> bool:
    """Whether a process with this pid exists on this host."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def available_memory_bytes() -> int | None:
    """MemAvailable from /proc/meminfo, or ``None`` where it cannot be read."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None
