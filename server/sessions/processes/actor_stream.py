"""A session actor's stream: each front-end's direct connection to its actor, carrying what
comes at camera rate (frames in, updates out) past Ray, while the hello, commands, the stop,
queries and a slow poll (ownership, the end) stay Ray calls.

Why: per frame, a Ray call costs CPU in three processes (the front-end's submission, the
raylet, the actor's task loop), and the updates' long-poll as much again at 40 polls a second;
measured on one 2-core node, 2 sessions x 15 fps: the machine 85 % busy under Ray against 59 %
with the process workers for the same poses, tracking's p95 1.9x (docs/SCALING.md).

The connection is ``multiprocessing.connection`` over TCP on the actor's node address, opened
with a random key the actor gives in its identity (an HMAC challenge both ways: only a holder
of the key, who got it from Ray, connects). The front-end's first message is its id (the
*owner* in ``ActorHost``); then, front-end -> actor, ``(number, (data, arrival))`` per frame,
numbered in the same sequence as its Ray calls, so that ``ActorHost.ordered`` runs a frame
after the hello sent before it and before the stop sent after it, whichever way each came;
actor -> front-end, lists of updates, to the owner only. No Ray here."""

from __future__ import annotations

import logging
import os
import secrets
import socket
import threading
from collections.abc import Callable
from multiprocessing.connection import Client, Connection, Listener

log = logging.getLogger(__name__)


class StreamListener:
    """The actor's side: accepts the front-ends' connections on ``host`` (the node's address)
    and hands each frame to ``on_frame(owner, number, args)`` (``ActorHost.ordered``), from a
    reader thread per connection; ``on_connect()`` after a front-end connected.
    ``connection(owner)``: where that front-end's updates go."""

    def __init__(
        self,
        host: str,
        on_frame: Callable[[str, int, tuple], object],
        on_connect: Callable[[], None],
    ) -> None:
        self.authkey = secrets.token_bytes(32)
        self._listener = Listener((host, 0), family="AF_INET", authkey=self.authkey)
        self.address: tuple[str, int] = self._listener.address
        self._on_frame, self._on_connect = on_frame, on_connect
        self._lock = threading.Lock()
        self._connections: dict[str, Connection] = {}
        self._closed = False
        threading.Thread(target=self._accept, name="stream-accept", daemon=True).start()

    def _accept(self) -> None:
        while not self._closed:
            try:
                conn = self._listener.accept()  # the key's challenge, both ways
                no_delay(conn)
                owner = conn.recv()
            except Exception as exc:  # a caller without the key, or the listener closed
                if not self._closed:
                    log.warning("a stream connection was refused: %s", exc)
                continue
            with self._lock:
                earlier = self._connections.pop(owner, None)
                self._connections[owner] = conn
            if earlier is not None:
                hang_up(earlier)
            self._on_connect()
            threading.Thread(
                target=self._read, args=(owner, conn), name="stream-in", daemon=True
            ).start()

    def _read(self, owner: str, conn: Connection) -> None:
        while True:
            try:
                number, args = conn.recv()
            except (EOFError, OSError, TypeError):
                break
            self._on_frame(owner, number, args)
        self.forget(owner, conn)

    def connection(self, owner: str) -> Connection | None:
        with self._lock:
            return self._connections.get(owner)

    def forget(self, owner: str, conn: Connection) -> None:
        """That front-end's connection failed or ended: its updates go by the poll again."""
        with self._lock:
            if self._connections.get(owner) is conn:
                del self._connections[owner]
        hang_up(conn)

    def close(self) -> None:
        self._closed = True
        self._listener.close()
        with self._lock:
            connections, self._connections = list(self._connections.values()), {}
        for conn in connections:
            hang_up(conn)


def open_stream(address: tuple[str, int], authkey: bytes, owner: str) -> Connection:
    """The front-end's side: connect to an actor's stream as ``owner``."""
    conn = Client(address, family="AF_INET", authkey=authkey)
    no_delay(conn)
    conn.send(owner)
    return conn


def no_delay(conn: Connection) -> None:
    """Send each message at once: with Nagle's algorithm a small message (a pose) behind one
    not yet acknowledged waits for the peer's delayed ACK, up to 40 ms (measured: a pose's p95
    60 against 27 ms with the process workers)."""
    with socket.socket(fileno=os.dup(conn.fileno())) as sock:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)


def hang_up(conn: Connection) -> None:
    """Close a stream connection, waking a thread blocked reading it (closing its descriptor
    alone would not: the socket is shut down first)."""
    try:
        with socket.socket(fileno=os.dup(conn.fileno())) as sock:
            sock.shutdown(socket.SHUT_RDWR)
    except (OSError, ValueError, TypeError):  # closed already, or the peer has gone
        pass
    conn.close()
