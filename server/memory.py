"""The server process's memory: which malloc it runs on.

Two causes made a long-running server grow (``benchmarks/soak.py``: +488 MB/min with 2 phones and
a new session every minute, although every session was closed on time):

- A closed session's objects (its threads' targets, the drone's callbacks, the simulator) refer to
  one another, so reference counting never frees them. Sessions now run in worker processes of their
  own (``server/sessions/processes/session_process.py``): a closed session's memory leaves with its
  process, whatever cycles it held.
- Each session's tracking, mapping and flight threads free tens of MB of images, point clouds and
  TSDF blocks a second, and glibc's malloc keeps a fragmented per-thread arena's pages: with the
  collection alone, the level RSS fell back to after each generation of sessions still rose
  (624, 778, 991 MB); on jemalloc it stayed put (429, 522, 460, 518 MB). So ``serve`` restarts
  itself on jemalloc (``LD_PRELOAD``) when Debian's ``libjemalloc2`` is installed: the allocator
  must be chosen before the interpreter starts. Without it, glibc's ``malloc_trim`` after each
  close gives back what it can.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import logging
import os
import sys
from pathlib import Path

log = logging.getLogger(__name__)

# Where Debian and Docker's python images install libjemalloc2.
_JEMALLOC_CANDIDATES = (
    "/usr/lib/x86_64-linux-gnu/libjemalloc.so.2",
    "/usr/lib/aarch64-linux-gnu/libjemalloc.so.2",
    "/usr/lib/libjemalloc.so.2",
)


def find_jemalloc() -> str | None:
    """The jemalloc shared library on this machine (a path, or a name the dynamic loader finds
    in its own folders), or None."""
    for candidate in _JEMALLOC_CANDIDATES:
        if Path(candidate).is_file():
            return candidate
    return ctypes.util.find_library("jemalloc")


def loaded_allocator(pid: int | str = "self") -> str:
    """``"jemalloc"`` when a process has jemalloc mapped, else ``"glibc"`` (Linux /proc)."""
    try:
        maps = Path(f"/proc/{pid}/maps").read_text()
    except OSError:
        return "unknown"
    return "jemalloc" if "libjemalloc" in maps else "glibc"


def restart_on_jemalloc() -> None:
    """Replace this process with the same command preloading jemalloc, when it is installed and
    not loaded yet; return when it cannot (then the process goes on with glibc's malloc).

    Call it first thing in a long-running command, before any thread starts: ``execve`` keeps the
    pid, the arguments and the environment, so supervisors and signals see the same process."""
    if loaded_allocator() == "jemalloc":
        return
    library = find_jemalloc()
    if library is None:
        log.warning(
            "jemalloc is not installed (Debian: libjemalloc2): running on glibc's malloc, "
            "whose memory can grow with many sessions over hours"
        )
        return
    preload = os.environ.get("LD_PRELOAD", "")
    if library in preload.split():
        return  # asked for already but not loaded (e.g. refused by the loader): don't loop
    env = {**os.environ, "LD_PRELOAD": f"{library} {preload}".strip()}
    argv = list(getattr(sys, "orig_argv", sys.argv))
    sys.stdout.flush()
    sys.stderr.flush()
    os.execve(sys.executable, [sys.executable, *argv[1:]], env)


@functools.cache
def this_process_allocator() -> str:
    """:func:`loaded_allocator` of this process, which cannot change once it runs."""
    return loaded_allocator()
