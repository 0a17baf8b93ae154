"""Processes in a fresh interpreter, for a parent that must not be forked or re-run: a Ray actor
(server/sessions/processes/actor_host.py) starting its session's worker, mapper and loop
process. ``FreshContext`` has the part of a multiprocessing context that ``ProcessWorker`` uses
(``Pipe``, ``Process``), so the actor runs its session exactly as the web process does, with
its processes started here instead of by the forkserver.

Why not multiprocessing's own: a fork of the actor, whose threads (Ray's among them) may hold
locks, is unsafe; ``spawn`` and the forkserver both run the parent's ``__main__`` again in the
child (preparation data), here Ray's worker script, which would import Ray into every session
process (measured for the mapper: 224 against 194 MB resident, about a second more of CPU to
start, and a resource-tracker process beside it); and multiprocessing's exit handler joins its
children, which a process ignoring SIGTERM (they all do, ``ipc.prepare_child``) would hang.

How: ``subprocess`` runs ``python -c`` with this module's ``fresh_main``; the target and its
arguments come pickled on the child's stdin, each pipe end among the arguments passed down by
descriptor (``pass_fds``) and rebuilt there. The child imports what the parent can (its
``sys.path``). A child ends on its own when its pipe closes (every session process does), and
Ray kills an actor's children when the actor's process exits.
"""

from __future__ import annotations

import multiprocessing
import os
import pickle
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import Connection

# The child's command line: its start, then (for ``ps``) what it runs and its name.
_MAIN = "from server.sessions.processes.fresh import fresh_main; fresh_main()"


@dataclass(frozen=True)
class _Descriptor:
    """A pipe end among a child's arguments: its descriptor number, the same in the child."""

    fd: int


class FreshProcess:
    """``multiprocessing.Process``'s surface that ``ProcessWorker`` uses (``start``, ``pid``,
    ``is_alive``, ``join``, ``kill``, ``exitcode``: negative for a signal), its child a fresh
    interpreter. ``daemon`` is accepted and means nothing: the child ends with its pipe."""

    def __init__(
        self, target: Callable, args: tuple = (), name: str = "", daemon: bool = True
    ) -> None:
        self.target, self.args, self.name = target, args, name
        self._popen: subprocess.Popen | None = None

    def start(self) -> None:
        args = tuple(_Descriptor(a.fileno()) if isinstance(a, Connection) else a for a in self.args)
        payload = pickle.dumps((self.target, args), protocol=pickle.HIGHEST_PROTOCOL)
        fds = tuple(a.fd for a in args if isinstance(a, _Descriptor))
        self._popen = subprocess.Popen(
            [sys.executable, "-c", _MAIN, getattr(self.target, "__name__", "?"), self.name],
            pass_fds=fds,
            stdin=subprocess.PIPE,
            env={**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)},
        )
        assert self._popen.stdin is not None
        with self._popen.stdin as stdin:
            stdin.write(payload)

    @property
    def pid(self) -> int | None:
        return None if self._popen is None else self._popen.pid

    @property
    def exitcode(self) -> int | None:
        return None if self._popen is None else self._popen.poll()

    def is_alive(self) -> bool:
        return self._popen is not None and self._popen.poll() is None

    def join(self, timeout: float | None = None) -> None:
        if self._popen is None:
            return
        try:
            self._popen.wait(timeout)
        except subprocess.TimeoutExpired:
            pass

    def kill(self) -> None:
        if self._popen is not None and self._popen.poll() is None:
            self._popen.kill()


class FreshContext:
    """What ``ProcessWorker`` asks of its multiprocessing context, with fresh processes."""

    Process = FreshProcess

    @staticmethod
    def Pipe(duplex: bool = True) -> tuple[Connection, Connection]:  # noqa: N802 (multiprocessing's name)
        return multiprocessing.Pipe(duplex)


def fresh_main() -> None:
    """A fresh process's start: its target and arguments from stdin, the pipe ends rebuilt on
    the descriptors passed down, then the target."""
    target, args = pickle.loads(sys.stdin.buffer.read())
    devnull = os.open(os.devnull, os.O_RDONLY)
    os.dup2(devnull, 0)  # nothing more comes on stdin; its pipe lets go of the parent
    os.close(devnull)
    target(*(Connection(a.fd) if isinstance(a, _Descriptor) else a for a in args))
