"""The one way a session's processes talk (server/sessions/processes/ipc.py): a target served
over a pipe (here in a thread), called through a Proxy."""

from __future__ import annotations

import logging
import multiprocessing
import threading

import pytest

from server.mapping.tsdf import MapError
from server.sessions.errors import SessionError
from server.sessions.processes.ipc import Proxy, serve

log = logging.getLogger(__name__)


class Lost(SessionError):
    def __init__(self, message: str) -> None:
        super().__init__("session_failed", message)


class Target:
    def add(self, a: int, b: int) -> int:
        return a + b

    def no_map(self) -> None:
        raise MapError("no map yet")

    def bug(self) -> None:
        raise ZeroDivisionError("oops")

    def stop(self) -> str:
        return "stopped"


def _served(**options):
    here, there = multiprocessing.Pipe(duplex=True)
    ended: list[bool] = []
    thread = threading.Thread(
        target=lambda: ended.append(serve(Target(), there, log, **options)), daemon=True
    )
    thread.start()
    return Proxy(here, Lost, "the test process"), thread, ended, there


def test_a_call_returns_its_value_and_an_answer_error_comes_back_as_its_class():
    proxy, thread, ended, _ = _served()
    assert proxy.call("add", 2, 3) == 5
    with pytest.raises(MapError, match="no map yet"):
        proxy.call("no_map")
    with pytest.raises(RuntimeError, match="the test process failed: ZeroDivisionError: oops"):
        proxy.call("bug")
    assert proxy.call("add", 1, 1) == 2  # a failed call leaves the loop serving
    proxy.close()
    thread.join(5)
    assert ended == [False]  # ended by the closed pipe


def test_a_successful_last_call_ends_the_loop():
    proxy, thread, ended, _ = _served(last="stop")
    assert proxy.call("stop") == "stopped"
    thread.join(5)
    assert ended == [True]


def test_a_process_gone_raises_the_callers_lost_error():
    proxy, thread, _, there = _served(last="stop")
    proxy.call("stop")
    thread.join(5)
    there.close()  # the serving end is gone
    with pytest.raises(Lost, match="the test process is gone"):
        proxy.call("add", 1, 2)


class Slow(Target):
    """A target whose ordered call ``wait`` runs until ``go`` is set."""

    def __init__(self) -> None:
        self.go = threading.Event()

    def wait(self) -> str:
        assert self.go.wait(10)
        return "waited"


def test_a_query_is_answered_while_an_ordered_call_runs():
    """With ``ordered``: a method not in it runs beside, at once, however long the ordered call
    in hand takes (a worker's status while its stop writes the final snapshot)."""
    here, there = multiprocessing.Pipe(duplex=True)
    target = Slow()
    ended: list[bool] = []
    thread = threading.Thread(
        target=lambda: ended.append(
            serve(target, there, log, ordered={"wait", "stop"}, beside=2, last="stop")
        ),
        daemon=True,
    )
    thread.start()
    here.send((1, "wait", ()))
    here.send((2, "add", (2, 3)))
    assert here.poll(10)
    assert here.recv() == ("reply", 2, True, 5)  # the query, while "wait" still runs
    target.go.set()
    assert here.poll(10)
    assert here.recv() == ("reply", 1, True, "waited")
    here.send((3, "stop", ()))
    assert here.poll(10) and here.recv() == ("reply", 3, True, "stopped")
    thread.join(5)
    assert ended == [True]


def test_a_busy_proxy_is_not_waited_for_by_call_if_idle():
    proxy, thread, _, _ = _served()
    with proxy._lock:  # another call in progress
        assert proxy.call_if_idle("add", 1, 2) == (False, None)
    assert proxy.call_if_idle("add", 1, 2) == (True, 3)
    proxy.close()
    thread.join(5)
