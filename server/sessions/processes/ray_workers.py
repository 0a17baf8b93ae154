"""Sessions as Ray actors: ``serve --ray ADDRESS`` runs each live session on a Ray cluster instead
of in a local worker process, so that one server scales past one machine.

Only imported when ``--ray`` is given (Ray is the optional extra ``[ray]``).

- Each session is a **detached, named actor** (``session-<id>`` in the ``dronesim`` namespace):
  it outlives the front-end that created it, and any front-end finds it by name
  (``RayWorkers.find``), so several front-ends behind a load balancer serve the same sessions
  and a restarted front-end finds its live sessions again. Actors are spread over the nodes
  (``SPREAD``); each reserves ``SESSION_CPUS`` logical CPU (its worker and mapper processes
  keep about one core busy at 15 fps), so a node with N CPUs hosts N sessions; a session that
  finds no free CPU within ``START_TIMEOUT_S`` is refused with ``server_full``.
- **The session runs in processes of the actor's** (actor_host.py): a worker process tracking
  and flying, a mapper process fusing, as the web process runs a local session, the actor's
  children (on its node, ending with it), the actor only relaying: tracking never shares a GIL
  with Ray's threads, nor with Open3D's integrate.
- **A shared room runs on one node, with one map**, as under the process workers: the owner's
  mapper listens for the room's phones on an abstract Unix socket, which exists on its machine
  only (``RayWorker.room_map``, a ``NodeRoom`` naming the owner's node); a joining phone's actor
  is placed on that node (``NodeAffinitySchedulingStrategy``, not soft), starts no mapper and
  fuses into the room's (affinity, not a placement group: nothing is reserved for phones that
  may never join). No free CPU there within ``START_TIMEOUT_S``: ``room_full``. Once one joined
  (``room_shared``), the owner's end leaves its actor up, its CPU reserved, while its mapper
  serves the phones on; it ends itself after the mapper, which ends after the last phone
  (``release``, ``linger``).
- **Order**: the hello, frames, commands and the stop go through one ``ordered`` entry point,
  sent by one thread per session with a running number per front-end (frames on the actor's
  stream, past Ray: actor_stream.py); the actor runs them strictly by that number, whatever way
  and order they came. Queries run in a concurrency group of their own, beside them.
- **Newest wins**: while a frame waits to be sent, a newer one replaces it (``dropped``).
- **Updates** (poses, map chunks, drone states and events, refused frames) go to the front-end
  that sent the latest hello (the *owner*), on its stream; its poll thread long-polls
  ``updates`` (``POLL_S``) for the rest: ownership (an earlier owner's LiveSession ends its
  socket with ``session_taken_over``), the end, a worker lost. Frames from a front-end that is
  no longer the owner are ignored (their numbering would clash with the new owner's).
- **Ends**: an actor or its worker that dies on its own -> ``on_lost``; one stopped or deleted
  by another front-end is let go quietly (the meta on the shared data dir says how it ended).
- **Snapshots** are written by the actor under the data_dir it was given, on the actor's node: on
  a real cluster data_dir must be shared storage (NFS, a ReadWriteMany volume), or each session's
  files stay on the node that ran it.
"""

from __future__ import annotations

import logging
import os
import re
import threading
import time
import uuid
import weakref
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout
from dataclasses import replace

import ray
from ray.exceptions import GetTimeoutError, RayActorError
from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

from server.sessions.errors import SessionError
from server.sessions.processes.actor_client import MAX_FRAMES_IN_FLIGHT, ActorClient
from server.sessions.processes.actor_host import ActorHost
from server.sessions.processes.room_map import RoomAddress
from server.sessions.processes.session_process import WorkerLost
from server.sessions.web.live import SessionTakenOver

log = logging.getLogger(__name__)

NAMESPACE = "dronesim"
# Ray's logical CPUs reserved per session actor (its mapper process included): the cluster's
# admission control
SESSION_CPUS = 1
# Native threads (OpenCV, Open3D, BLAS) of a session's worker: one per CPU it reserved.
SESSION_THREADS = SESSION_CPUS
POLL_S = 1.0  # an updates long-poll's longest wait (also how soon a takeover or death is seen)
START_TIMEOUT_S = 60.0
RELEASE_TIMEOUT_S = 60.0  # a shared room's owner ending its session, its map left serving
_ORDERED = {"configure", "frame", "command", "stop"}
_ID = re.compile(r"[0-9A-Za-z_-]{1,64}")


def actor_name(session_id: str) -> str:
    return f"session-{session_id}"


# ---- the actor (on a cluster node) -----------------------------------------------------------


# Ray's typing of remote() with options lists the task options only, not the actor's
# concurrency_groups.
@ray.remote(  # type: ignore[call-overload]
    concurrency_groups={"ordered": MAX_FRAMES_IN_FLIGHT + 2, "query": 2, "poll": 8, "end": 2}
)
class SessionActor:
    """The Ray actor of one session: each entry point in its concurrency group, the work done
    by an ActorHost (server/sessions/processes/actor_host.py)."""

    def __init__(self, args, owner: str) -> None:
        node_id = ray.get_runtime_context().get_node_id()
        node_ip = ray.util.get_node_ip_address()
        self.core = ActorHost(args, owner, node_id, node_ip)
        self.core.info |= {
            "node_id": node_id,
            "node_ip": node_ip,
            "actor": actor_name(args.session_id),
            "cpus": SESSION_CPUS,
        }

    @ray.method(concurrency_group="query")
    def identity(self) -> dict:
        return self.core.identity()

    @ray.method(concurrency_group="ordered")
    def ordered(self, owner: str, number: int, method: str, args: tuple):
        return self.core.ordered(owner, number, method, args)

    @ray.method(concurrency_group="query")
    def query(self, method: str, args: tuple):
        return self.core.query(method, args)

    @ray.method(concurrency_group="poll")
    def updates(self, owner: str, timeout_s: float) -> dict:
        return self.core.updates(owner, timeout_s)

    @ray.method(concurrency_group="end")
    def release(self) -> bool:
        """A shared room's owner's end: the session ends (if still live, unsaved) and, while
        its mapper still serves the room's phones, this actor lingers (True) and ends after it."""
        serving = self.core.release()
        if serving:
            ray.get_runtime_context().current_actor.linger.remote()
        return serving

    @ray.method(concurrency_group="end")
    def linger(self) -> None:
        """Wait for the room's map to end after its last phone (its process reaped), then end
        this actor, freeing its CPU."""
        self.core.wait_for_map()
        ray.actor.exit_actor()


# ---- the front-end's side --------------------------------------------------------------------


class RayWorker(ActorClient):
    """A front-end's handle on one session actor: the surface of ``ProcessWorker`` (``call``,
    ``post``, ``stop``, ``kill``, ``describe``, ``alive``, ``dropped``), plus ``last_active``
    (this process's monotonic time of the session's latest hello or frame from any front-end).
    Built as ``ActorClient`` is (server/sessions/processes/actor_client.py: the ordered calls'
    queue and send thread, the updates handed on, the ends); here the calls that need Ray."""

    kind = "ray"
    backend: RayWorkers
    # The room's map runs on the actor's node, a child of the actor, which reaps it itself:
    # nothing for SharedRooms to reap here.
    mapper_process = None

    def __init__(self, backend, actor, session_id, identity, on_update, on_lost, owner) -> None:
        super().__init__(backend, actor, session_id, identity, on_update, on_lost, owner)
        # Where the phones that join its room reach its map (on its node); None for a phone
        # that joined a room.
        self.room_map: RoomAddress | None = identity.get("room_map")
        self._room_shared = bool(identity.get("room_shared"))
        self._sharing = None  # the call that told the actor so, awaited before a stop

    @property
    def room_shared(self) -> bool:
        """Phones joined the session's room: its map serves them past the session's end."""
        return self._room_shared

    @room_shared.setter
    def room_shared(self, shared: bool) -> None:  # SharedRooms.joined, under its lock: no wait
        if shared and not self._room_shared:
            self._room_shared = True
            self._sharing = self.actor.query.remote("share_map", ())

    @property
    def alive(self) -> bool:
        return self._lost is None

    def describe(self) -> dict:
        return {"kind": self.kind, **self.info}

    def call(self, method: str, *args, timeout_s: float = 60.0):
        if method == "set_threads":
            return None  # an actor's threads follow its CPU reservation, not this front-end
        if method in _ORDERED:
            future: Future = Future()
            self._enqueue(method, args, future)
            try:
                ref = future.result(timeout_s)
            except FutureTimeout:
                raise WorkerLost(
                    f"the session's actor did not take {method} within {timeout_s:.0f} s"
                ) from None
        else:
            if self._lost is not None:
                raise WorkerLost(self._lost)
            ref = self.actor.query.remote(method, args)
        return self._get(ref, timeout_s, method)

    def _get(self, ref, timeout_s: float, method: str):
        from server.sessions.processes.ipc import result

        try:
            ok, value = ray.get(ref, timeout=timeout_s)
        except GetTimeoutError:
            raise WorkerLost(
                f"the session's actor did not answer {method} within {timeout_s:.0f} s"
            ) from None
        except RayActorError as exc:
            raise WorkerLost(self._lost or _death(exc)) from None
        return result(ok, value, "the session's Ray actor")

    def _poll_loop(self) -> None:
        owner = self.backend.owner
        while not self._closing:
            try:
                reply = ray.get(self.actor.updates.remote(owner, POLL_S), timeout=POLL_S + 30)
            except GetTimeoutError:
                log.warning(
                    "session %s: its actor did not answer a poll in %.0f s",
                    self.session_id,
                    POLL_S + 30,
                )
                continue
            except RayActorError as exc:
                reason = _death(exc)
                if _killed(exc):
                    return self._end_elsewhere("the session was ended by another front-end")
                return self._end(reason)
            except SystemExit:  # this process's Ray driver shut down
                return
            except Exception as exc:  # Ray itself went away (shut down)
                if not self._closing:
                    log.warning("session %s: polling its actor failed: %s", self.session_id, exc)
                    time.sleep(POLL_S)
                continue
            if reply.get("lost") and not self._stopped:  # its worker process died
                self._end(f"{reply['lost']} (on its Ray actor)")
                return self.kill()  # the actor (or, a shared room's, its wait for the map)
            self.last_active = time.monotonic() - reply["idle_s"]
            for item in reply["items"]:
                self._deliver(item)
            if reply["owner"]:
                self._owner = True
            elif self._owner:
                self._owner = False
                self._deliver(
                    SessionTakenOver(
                        "a newer connection, on another front-end, took the session over"
                    )
                )
            if reply["ended"] is not None and not self._stopped:
                return self._end_elsewhere("the session was closed by another front-end")

    # ------------------------------------------------------------------ the end
    def stop(self, save: bool, timeout_s: float = 120.0) -> dict:
        """Stop the session (its final snapshot when ``save``) and end the actor. A front-end
        that is going away (``RayWorkers.detach``) only lets go: the session lives on."""
        if self.backend.detached or self._ended_elsewhere:
            self._closing = True
            self._let_go("the front-end let go of the session")
            return self._meta_on_disk()
        self._stopped = True
        if self._sharing is not None:  # its stop then leaves the room's map serving
            ray.wait([self._sharing], timeout=30)
        try:
            meta = self.call("stop", save, timeout_s=timeout_s)
        except WorkerLost:
            raise
        except Exception:
            self._stopped = False
            raise
        self.kill()
        return meta

    def kill(self) -> None:
        """End the actor at once (a session deleted, or one that stopped answering). A shared
        room's owner whose map still serves joined phones ends its session and lingers instead
        (``SessionActor.release``), unless it does not answer."""
        self._stopped = True
        self._closing = True
        self._let_go("the session's actor was ended")
        if self._room_shared and self._release():
            return
        try:
            ray.kill(self.actor, no_restart=True)
        except Exception as exc:  # already gone
            log.debug("session %s: kill: %s", self.session_id, exc)

    def _release(self) -> bool:
        try:
            return bool(ray.get(self.actor.release.remote(), timeout=RELEASE_TIMEOUT_S))
        except (GetTimeoutError, RayActorError) as exc:
            log.warning("session %s: its room's map could not be kept: %s", self.session_id, exc)
            return False


def _killed(exc: RayActorError) -> bool:
    """Whether the actor was ended with ray.kill (a stop or a delete), not by a crash."""
    return "ray.kill" in str(exc)


def _death(exc: RayActorError) -> str:
    text = str(exc).strip().splitlines()
    detail = " ".join(line.strip() for line in text[:4])[:400]
    return f"the session's Ray actor died ({detail})"


# ---- the back-end ----------------------------------------------------------------------------

_RAY_LOCK = threading.Lock()
_RAY_USERS = 0
_RAY_OURS = False  # this process started Ray (and shuts it down with its last user)


def _connect(address: str) -> bool:
    """Join the cluster at ``address`` (``auto``, ``ray://host:10001``, ``host:6379``) or start
    a local instance (``local``, its traffic on 127.0.0.1). Returns whether it is local."""
    global _RAY_USERS, _RAY_OURS
    local = address == "local"
    with _RAY_LOCK:
        _RAY_USERS += 1
        if ray.is_initialized():
            return local
        include_dashboard = None  # Ray's default
        system_config = None  # a cluster's own (set where its nodes start)
        if local:
            # One machine: Ray on the loopback only (its node address, and what it listens on).
            os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"
            from ray._private import ray_constants

            ray_constants.ENABLE_RAY_CLUSTER = False
            include_dashboard = False
            # Ray starts its workers at nice 15 (its default worker_niceness), below this
            # front-end and anything else on the machine: a session's tracking then waits for
            # them. The process workers run at the server's own priority; so do these.
            system_config = {"worker_niceness": 0}
        ray.init(
            address=address,
            namespace=NAMESPACE,
            logging_level=logging.WARNING,
            log_to_driver=False,
            include_dashboard=include_dashboard,
            _system_config=system_config,
        )
        _RAY_OURS = True
        return local


class RayWorkers:
    """The Ray back-end of SessionManager: ``start``, ``find``, ``detach``, ``close``."""

    kind = "ray"

    def __init__(self, address: str) -> None:
        self.address = address
        self.owner = uuid.uuid4().hex  # this front-end, as the actors know it
        self.local = _connect(address)
        self.detached = False
        self._workers: set[RayWorker] = set()
        # Every worker whose threads may still run, let go of or not (a worker's running threads
        # keep it here): close joins them all before Ray shuts down, as a poll still in
        # ``ray.get`` then would end the whole process (Ray's core worker exits).
        self._with_threads: weakref.WeakSet[RayWorker] = weakref.WeakSet()
        self._closed = False

    def start(self, args, session) -> RayWorker:
        args = replace(args, threads=SESSION_THREADS)
        # A phone joining a room runs on the node of the room's map (its socket is that
        # machine's), or nowhere: not soft.
        room_node = getattr(args.room_map, "node_id", "")
        strategy = (
            NodeAffinitySchedulingStrategy(node_id=room_node, soft=False) if room_node else "SPREAD"
        )
        # mypy keeps the class a decorator returns as the plain class; it is Ray's ActorClass.
        actor = SessionActor.options(  # type: ignore[attr-defined]
            name=actor_name(args.session_id),
            namespace=NAMESPACE,
            lifetime="detached",
            num_cpus=SESSION_CPUS,
            scheduling_strategy=strategy,
            max_restarts=0,
        ).remote(args, self.owner)
        try:
            identity = ray.get(actor.identity.remote(), timeout=START_TIMEOUT_S)
        except GetTimeoutError:
            ray.kill(actor, no_restart=True)
            if room_node:
                raise SessionError(
                    "room_full",
                    f"the room's node (its owner's, where the room's map runs) had no free CPU "
                    f"for another phone within {START_TIMEOUT_S:.0f} s; try again later",
                ) from None
            raise SessionError(
                "server_full",
                f"the Ray cluster did not start the session within "
                f"{START_TIMEOUT_S:.0f} s (no free CPU for another one?); "
                "try again later",
            ) from None
        except RayActorError as exc:
            raise WorkerLost(_death(exc)) from None
        return RayWorker(
            self, actor, args.session_id, identity, session.deliver, session.lost, owner=True
        )

    def find(self, session_id: str):
        """The live session ``session_id`` on the cluster (any front-end's), or None."""
        from server.sessions.web.manager import FoundSession

        if not _ID.fullmatch(session_id):
            return None
        try:
            actor = ray.get_actor(actor_name(session_id), namespace=NAMESPACE)
            identity = ray.get(actor.identity.remote(), timeout=10)
        except (ValueError, RayActorError, GetTimeoutError):
            return None
        if identity["ended"] is not None:
            return None

        def attach(session) -> RayWorker:
            return RayWorker(
                self, actor, session_id, identity, session.deliver, session.lost, owner=False
            )

        return FoundSession(identity["token_hash"], identity["created_at"], attach)

    def detach(self) -> None:
        """The front-end is going away: its sessions live on in the cluster, to be found by the
        other front-ends or by this one restarted; a stop now only lets go. A local instance
        ends with this process, so its sessions are stopped and saved as usual."""
        if not self.local:
            self.detached = True

    def close(self) -> None:
        global _RAY_USERS, _RAY_OURS
        if self._closed:
            return
        self._closed = True
        workers = list(self._with_threads)  # the held ones too: they are among them
        for worker in workers:
            worker.detach_threads()
        for worker in workers:
            worker.join_threads(POLL_S + 5)
        with _RAY_LOCK:
            _RAY_USERS -= 1
            if _RAY_USERS <= 0 and _RAY_OURS:
                ray.shutdown()
                _RAY_OURS = False
