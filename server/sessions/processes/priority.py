"""The priorities of a session's threads and processes: tracking first, then the map, then loop
closing. Linux nice values are per thread, so each worker thread lowers its own."""

from __future__ import annotations

import os
import threading

MAPPING_NICE = 10  # added to the map's nice value: it yields to tracking when cores are short
# Below the mapping's priority: when the cores are short, loops fall behind the map, and the
# map behind the poses (the drone flies in the map: it must not wait for loops).
LOOPS_NICE = MAPPING_NICE + 5


def lower_this_threads_priority(nice: int) -> None:
    """Raise the calling thread's nice value by ``nice`` (Linux nice values are per thread; a
    new process's first thread speaks for the process)."""
    try:
        tid = threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, tid, os.getpriority(os.PRIO_PROCESS, tid) + nice)
    except (OSError, AttributeError):  # not Linux, or not allowed: the same priority, still right
        pass
