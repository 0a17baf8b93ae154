"""A live session's loop closure: a thread of the worker process that looks each new keyframe up
among the older ones, and on a verified loop optimises the pose graph and hands the session a
corrected world (``Correction``).

The numerical work is ``server/registration/loops.py``'s ``LoopCloser``, in a process of its own
when the session has one (``server/sessions/processes/loop_process.py``: in the tracking process it
would share the tracker's GIL), else in this thread; this module only feeds it from a queue (every
keyframe, none dropped), at a priority below the mapping's (when cores are short the loops fall
behind the map, never the poses), and keeps the sequence of corrected worlds (``Worlds``), so that a
pose tracked in one world can be carried into a later one exactly as the tracker was.

Not for a session continuing in a saved room: the room's keyframes would have to stay fixed
nodes of the graph (their poses are the room's world, shared with the map on disk and with
other sessions), and Open3D's optimiser fixes only one node; such a session runs without loop
closure (``Session`` does not start one).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from server.geometry import Intrinsics, invert, orthonormalize, rotation_angle_deg
from server.registration.config import RegistrationConfig
from server.registration.loops import LoopCloser
from server.registration.place import PlaceFeatures
from server.sessions.processes.loop_process import LoopCloserClient
from server.sessions.processes.priority import LOOPS_NICE, lower_this_threads_priority

log = logging.getLogger(__name__)


@dataclass
class LoopKeyframe:
    """A keyframe for the loop closer, from the mapping thread once its room file is written.

    T_world_keyframe: 4x4, metres, in world ``world`` (the corrections the tracker had applied
    when it made the keyframe: 0 = none); depth: (H, W) metres, cleaned."""

    kf_id: int
    seq: int
    T_world_keyframe: np.ndarray
    world: int
    features: PlaceFeatures
    depth: np.ndarray


@dataclass(frozen=True)
class Correction:
    """A corrected world, number ``world`` (1, 2, ...), from a pose-graph optimisation.

    keyframes: corrected T_world_keyframe (4x4, metres) per keyframe id the graph held, with
    ``seqs`` their frames' seq; T_correction: old world (``world`` - 1) to this one, for every
    pose not in ``keyframes`` (the tracker's newer keyframes, its last pose, the drone):
    T_new = T_correction @ T_old. It is the newest graph keyframe's corrected pose times the
    inverse of its pose in the old world."""

    world: int
    keyframes: dict[int, np.ndarray]
    seqs: dict[int, int]
    T_correction: np.ndarray
    loops: int  # verified loops so far
    refused: int  # keyframes whose loop candidates were refused so far
    optimise_ms: float


class Worlds:
    """The corrections so far, in order; thread-safe. World 0 is the tracker's own."""

    def __init__(self) -> None:
        self._corrections: list[Correction] = []
        self._lock = threading.Lock()

    @property
    def latest(self) -> int:
        with self._lock:
            return len(self._corrections)

    def add(self, correction: Correction) -> None:
        with self._lock:
            if correction.world != len(self._corrections) + 1:
                raise ValueError(f"correction {correction.world} after {len(self._corrections)}")
            self._corrections.append(correction)

    def carry(
        self, kf_id: int | None, T: np.ndarray, world: int, to: int | None = None
    ) -> np.ndarray:
        """Pose ``T`` (4x4, of keyframe ``kf_id`` or of anything else when None) from world
        ``world`` into world ``to`` (the latest when None), as the tracker carried it: a
        keyframe a correction names takes its corrected pose, everything else moves by the
        correction's T_correction."""
        with self._lock:
            steps = self._corrections[world : len(self._corrections) if to is None else to]
        T = np.asarray(T, dtype=np.float64)
        for c in steps:
            known = None if kf_id is None else c.keyframes.get(kf_id)
            T = known if known is not None else c.T_correction @ T
        return T.copy()

    def delta(self, world: int, to: int) -> np.ndarray:
        """What moves a pose that no correction names from world ``world`` into ``to``."""
        return self.carry(None, np.eye(4), world, to)


def pose_move_m(T_a: np.ndarray, T_b: np.ndarray, reach_m: float = 2.0) -> float:
    """How far a correction from camera pose T_a to T_b (4x4 T_world_camera, metres) moves what
    the camera saw: its centre's shift plus its turn (radians) times ``reach_m``, a bound on
    how far a point ``reach_m`` in front of it moves."""
    shift = float(np.linalg.norm(T_b[:3, 3] - T_a[:3, 3]))
    return shift + np.radians(rotation_angle_deg(invert(T_a) @ T_b)) * reach_m


@dataclass
class LoopStats:
    """What the loop closer did so far (the session's status ``loops``)."""

    keyframes: int = 0
    found: int = 0
    refused: int = 0
    corrections: int = 0
    last_optimise_ms: float | None = None
    last_optimise_cpu_ms: float | None = None
    # per keyframe: its cloud, odometry edge, look-up, verification (this thread's CPU and, with
    # a loop process, that process's)
    lookup_cpu_s: float = 0.0
    optimise_ms: list[float] = field(default_factory=list)


class LoopClosing:
    """The loop thread of one session. ``submit`` keyframes in order (any thread; never
    blocks); ``on_correction(Correction)`` is called from the loop thread after each verified
    loop's optimisation, and ``on_failure(exc)`` when a keyframe fails (it is left out of the
    graph; the thread goes on). ``conn``: a pipe to the session's loop process
    (``loop_process.loops_main``), which then does the work; None: this thread does it."""

    def __init__(
        self,
        K: Intrinsics,
        cfg: RegistrationConfig,
        on_correction: Callable[[Correction], None],
        on_failure: Callable[[BaseException], None],
        name: str = "loops",
        conn=None,
    ) -> None:
        self.closer: LoopCloser | LoopCloserClient = (
            LoopCloser(K, cfg) if conn is None else LoopCloserClient(conn, K, cfg)
        )
        self.worlds = Worlds()
        self.stats = LoopStats()
        self.on_correction = on_correction
        self.on_failure = on_failure
        # Unbounded: every keyframe is kept (a few per second at most, each a cloud of ~20k
        # points once in the graph); the thread drains it at its own pace.
        self._queue: queue.SimpleQueue[LoopKeyframe | None] = queue.SimpleQueue()
        self._given: dict[int, tuple[int, np.ndarray, int]] = {}  # id -> seq, T, world
        self._last: LoopKeyframe | None = None
        self._lock = threading.Lock()  # guards stats and _given for readers on other threads
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self) -> None:
        self._thread.start()

    def submit(self, keyframe: LoopKeyframe) -> None:
        self._queue.put(keyframe)

    def stop(self, timeout_s: float = 60.0) -> None:
        """Process the keyframes queued so far, then end the thread (and the loop process)."""
        if self._thread.is_alive():
            self._queue.put(None)
            self._thread.join(timeout_s)
        if isinstance(self.closer, LoopCloserClient) and not self._thread.is_alive():
            self.closer.close()

    def figures(self) -> dict:
        """For the status: counts, the latest optimisation's wall time, mean CPU per keyframe."""
        with self._lock:
            s = self.stats
            return {
                "keyframes": s.keyframes,
                "queued": self._queue.qsize(),
                "found": s.found,
                "refused": s.refused,
                "corrections": s.corrections,
                "last_optimise_ms": s.last_optimise_ms,
                "last_optimise_cpu_ms": s.last_optimise_cpu_ms,
                "lookup_cpu_ms": (
                    None if s.keyframes == 0 else round(1e3 * s.lookup_cpu_s / s.keyframes, 2)
                ),
            }

    def poses(self) -> dict[int, np.ndarray]:
        """Every keyframe given so far at its pose in the latest world."""
        with self._lock:
            given = dict(self._given)
        return {i: self.worlds.carry(i, T, w) for i, (_, T, w) in given.items()}

    # ---- the thread ------------------------------------------------------------------------
    def _run(self) -> None:
        lower_this_threads_priority(LOOPS_NICE)
        while True:
            keyframe = self._queue.get()
            if keyframe is None:
                return
            try:
                self._add(keyframe)
            except Exception as exc:  # this keyframe is left out; the next ones go on
                self.on_failure(exc)

    def _cpu_s(self) -> float:
        """CPU seconds spent on loop closure so far: this thread's and the loop process's."""
        remote = self.closer.cpu_s if isinstance(self.closer, LoopCloserClient) else 0.0
        return time.thread_time() + remote

    def _add(self, kf: LoopKeyframe) -> None:
        cpu0 = self._cpu_s()
        prev = self._last
        # The odometry edge joins the two keyframes in one world: the previous one carried
        # into this one's (the tracker may have been corrected between them).
        T_prev = (
            None
            if prev is None
            else self.worlds.carry(prev.kf_id, prev.T_world_keyframe, prev.world, kf.world)
        )
        loop = self.closer.add_keyframe(
            kf.kf_id, kf.T_world_keyframe, kf.features, kf.depth, T_world_previous=T_prev
        )
        self._last = kf
        with self._lock:
            self._given[kf.kf_id] = (kf.seq, kf.T_world_keyframe.copy(), kf.world)
            self.stats.keyframes += 1
            self.stats.found = len(self.closer.loops)
            self.stats.refused = self.closer.refused
            self.stats.lookup_cpu_s += self._cpu_s() - cpu0
        if loop is None:
            return
        t0, cpu0 = time.perf_counter(), self._cpu_s()
        corrected = self.closer.optimise()
        ms, cpu_ms = (time.perf_counter() - t0) * 1e3, (self._cpu_s() - cpu0) * 1e3
        latest = self.worlds.latest
        T_old = self.worlds.carry(kf.kf_id, kf.T_world_keyframe, kf.world, latest)
        with self._lock:
            seqs = {i: self._given[i][0] for i in corrected}
        correction = Correction(
            latest + 1,
            corrected,
            seqs,
            orthonormalize(corrected[kf.kf_id] @ invert(T_old)),
            len(self.closer.loops),
            self.closer.refused,
            ms,
        )
        self.worlds.add(correction)
        with self._lock:
            self.stats.corrections += 1
            self.stats.last_optimise_ms = round(ms, 2)
            self.stats.last_optimise_cpu_ms = round(cpu_ms, 2)
            self.stats.optimise_ms.append(ms)
        log.info(
            "loop %d-%d: world %d over %d keyframes in %.0f ms",
            loop.old,
            loop.new,
            correction.world,
            len(corrected),
            ms,
        )
        self.on_correction(correction)
