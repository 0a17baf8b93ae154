"""A live session's loop closer in a process of its own, beside the session's tracking process.

Why a process: a keyframe's look-up (the place database's vote, verification, ICP) is numpy,
OpenCV and Open3D work with much Python between the calls; in a thread of the tracking process
it shares the tracker's GIL. Measured on 2 cores, 7scenes_a at 15 fps
(``benchmarks/beside_tracking.py --beside loops --keyframe-period 0.25``): tracking's p95
25-31 ms alone, 35 ms beside the loop closer in a thread, 27 ms beside it in another process;
with keyframes back to back (a scratch run) the tracker's mean went from 31 to 43-48 ms beside
the thread, and stayed at 32 ms beside the process.

``loops_main`` serves one ``LoopCloser`` over a pipe, a call at a time; ``LoopCloserClient``
is the session's handle on it (``server/sessions/runtime/loop_closing.py``'s thread calls it as it
would the ``LoopCloser`` itself). The process ends when its pipe closes.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from server.errors import DroneSimError
from server.geometry import Intrinsics
from server.geometry.arrays import Float32Array, FloatArray
from server.registration.config import RegistrationConfig
from server.registration.loops import LoopCloser, LoopEdge
from server.registration.place import PlaceFeatures
from server.sessions.failures import SessionLog
from server.sessions.processes.ipc import Proxy, prepare_child, serve
from server.sessions.processes.priority import LOOPS_NICE

log = logging.getLogger(__name__)


class LoopProcessError(DroneSimError):
    """The loop process is gone: this call and every later one fail the same way (the keyframe
    is left out; the session goes on without loop closure). A call that fails inside the process
    raises its own error (``ipc.raise_remote``)."""


class _Loops:
    """What the loop process serves: the session's LoopCloser, made by ``start``; each answer
    comes as (the value, the CPU seconds the process has spent on the calls so far)."""

    def __init__(self) -> None:
        self.closer: LoopCloser | None = None
        self._cpu0 = time.process_time()

    def start(self, K: Intrinsics, cfg: RegistrationConfig) -> float:
        self.closer = LoopCloser(K, cfg)
        return self._cpu_s()

    def add_keyframe(self, *args) -> tuple[tuple[LoopEdge | None, int], float]:
        closer = self._closer()
        loop = closer.add_keyframe(*args)
        return (loop, closer.refused), self._cpu_s()

    def optimise(self) -> tuple[dict[int, np.ndarray], float]:
        return self._closer().optimise(), self._cpu_s()

    def _closer(self) -> LoopCloser:
        if self.closer is None:
            raise RuntimeError("a loop closer call before start")
        return self.closer

    def _cpu_s(self) -> float:
        return time.process_time() - self._cpu0


def loops_main(conn, session_id: str = "") -> None:
    """Entry point of a session's loop process: serve ``start(K, cfg)`` (which makes its
    LoopCloser), then ``add_keyframe`` and ``optimise``, until the pipe closes."""
    prepare_child(LOOPS_NICE)  # the session's worker decides when it ends
    import cv2
    import open3d as o3d

    # One native thread each: the loops must never crowd out tracking on a small machine.
    cv2.setNumThreads(1)
    o3d.utility.set_max_threads(1)
    serve(_Loops(), conn, SessionLog(log, session_id))


class LoopCloserClient:
    """A ``LoopCloser`` in the loop process at the other end of ``conn``: the same calls, and
    the counts the session reads (``loops``: the verified loops so far, ``refused``), plus
    ``cpu_s``, what the process spent on the calls so far (seconds)."""

    def __init__(self, conn, K: Intrinsics, cfg: RegistrationConfig) -> None:
        self._proxy = Proxy(conn, LoopProcessError, "the session's loop process")
        # Sent with the first keyframe, not here: the session's hello (which makes this) must
        # neither wait for the loop process nor fail with it.
        self._start: tuple | None = (K, cfg)
        self.loops: list[LoopEdge] = []
        self.refused = 0
        self.cpu_s = 0.0

    def add_keyframe(
        self,
        kf_id: int,
        T_world_keyframe: FloatArray,
        features: PlaceFeatures,
        depth: Float32Array,
        T_world_previous: FloatArray | None = None,
    ) -> LoopEdge | None:
        """As ``LoopCloser.add_keyframe``."""
        loop, self.refused = self._call(
            "add_keyframe", kf_id, T_world_keyframe, features, depth, T_world_previous
        )
        if loop is not None:
            self.loops.append(loop)
        return loop

    def optimise(self) -> dict[int, np.ndarray]:
        """As ``LoopCloser.optimise``."""
        corrected: dict[int, np.ndarray] = self._call("optimise")
        return corrected

    def close(self) -> None:
        """Let the process end (it exits when its pipe closes)."""
        self._proxy.close()

    def _call(self, method: str, *args):
        """One call; the process's LoopCloser is made first, with the first keyframe. Returns
        the call's value, and counts the process's CPU."""
        if self._start is not None:
            self.cpu_s = self._proxy.call("start", *self._start)
            self._start = None
        value, self.cpu_s = self._proxy.call(method, *args)
        return value
