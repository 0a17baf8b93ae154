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
