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

import signal
import threading
import time

import numpy as np

from server.errors import DroneSimError
from server.geometry import Intrinsics
from server.geometry.arrays import Float32Array, FloatArray
from server.registration.config import RegistrationConfig
from server.registration.loops import LoopCloser, LoopEdge
from server.registration.place import PlaceFeatures
from server.sessions.processes.priority import LOOPS_NICE, lower_this_threads_priority


class LoopProcessError(DroneSimError):
    """A call failed inside the loop process (the keyframe is left out; the process goes on),
    or the process is gone (every later call fails the same way)."""


def loops_main(conn) -> None:
    """Entry point of a session's loop process: ``("start", (K, cfg))`` makes its LoopCloser,
    then ``("add_keyframe", args)`` and ``("optimise", ())`` are answered with ``(ok, value,
    cpu_s)`` (value: the call's result, or the error's text) until the pipe closes."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the session's worker decides when it ends
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    import cv2
    import open3d as o3d

    # One native thread each: the loops must never crowd out tracking on a small machine.
    cv2.setNumThreads(1)
    o3d.utility.set_max_threads(1)
    lower_this_threads_priority(LOOPS_NICE)
    closer: LoopCloser | None = None
    while True:
        try:
            method, args = conn.recv()
        except (EOFError, OSError):
            return
        cpu0 = time.process_time()
        value: object
        reply: tuple[bool, object, float]
        try:
            if method == "start":
                closer, value = LoopCloser(*args), None
            elif closer is None:
                raise LoopProcessError(f"{method} before start")
            elif method == "add_keyframe":
                loop = closer.add_keyframe(*args)
                value = (loop, closer.refused)
            elif method == "optimise":
                value = closer.optimise()
            else:
                raise LoopProcessError(f"unknown call {method!r}")
            reply = (True, value, time.process_time() - cpu0)
        except Exception as exc:
            reply = (False, f"{type(exc).__name__}: {exc}", time.process_time() - cpu0)
        try:
            conn.send(reply)
        except (OSError, ValueError):
            return


class LoopCloserClient:
    """A ``LoopCloser`` in the loop process at the other end of ``conn``: the same calls, and
    the counts the session reads (``loops``: the verified loops so far, ``refused``), plus
    ``cpu_s``, what the process spent on the calls so far (seconds)."""

    def __init__(self, conn, K: Intrinsics, cfg: RegistrationConfig) -> None:
        self._conn = conn
        self._lock = threading.Lock()
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
        with self._lock:
            self._conn.close()

    def _call(self, method: str, *args):
        with self._lock:
            if self._start is not None:
                self._exchange("start", self._start)
                self._start = None
            return self._exchange(method, args)

    def _exchange(self, method: str, args: tuple):
        """One call and its answer (under the lock)."""
        try:
            self._conn.send((method, args))
            ok, value, cpu_s = self._conn.recv()
        except (EOFError, OSError, ValueError) as exc:
            raise LoopProcessError(f"the session's loop process is gone ({exc})") from None
        self.cpu_s += cpu_s
        if not ok:
            raise LoopProcessError(f"loop process: {method} failed: {value}")
        return value
