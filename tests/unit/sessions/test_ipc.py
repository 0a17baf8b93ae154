"""The one way a session's processes talk (server/sessions/processes/ipc.py): a target served
over a pipe (here in a thread), called through a Proxy."""

from __future__ import annotations

import logging
import multiprocessing
import signal
import threading
import time

import pytest

from server.mapping.tsdf import MapError
from server.sessions.errors import SessionError
from server.sessions.processes.ipc import Proxy, TurnLock, serve

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


def test_callers_take_turns_a_caller_that_calls_again_at_once_does_not_starve_another():
    """The mapping thread fuses frame after frame through the mapper's Proxy; a download beside
    it must wait for the fusion in progress, not for every one after it. With a plain Lock the
    loop below got up to 37 calls in while the other waited (1.5 s) on this machine with both
    cores busy."""
    proxy, thread, _, _ = _served()
    stop = threading.Event()
    loop_calls = 0

    def call_again_and_again():
        nonlocal loop_calls
        while not stop.is_set():
            proxy.call("add", 1, 1)
            loop_calls += 1

    looper = threading.Thread(target=call_again_and_again, daemon=True)
    looper.start()
    try:
        for _ in range(50):
            before = loop_calls
            assert proxy.call("add", 2, 3) == 5
            # The call in progress when this one asked, and at most the one asked just before.
            assert loop_calls - before <= 2, loop_calls - before
    finally:
        stop.set()
        looper.join(5)
    assert loop_calls > 50
    proxy.close()
    thread.join(5)


def test_a_turn_lock_goes_to_its_waiters_in_the_order_they_asked():
    lock = TurnLock()
    order: list[int] = []
    lock.acquire()
    threads = []
    for i in range(4):
        t = threading.Thread(target=lambda i=i: (lock.acquire(), order.append(i), lock.release()))
        t.start()
        threads.append(t)
        while len(lock._waiting) < i + 1:  # this one is queued before the next asks
            time.sleep(0.001)
    assert not lock.acquire(blocking=False)
    lock.release()
    for t in threads:
        t.join(5)
    assert order == [0, 1, 2, 3]
    assert lock.acquire(blocking=False)  # free again once the last waiter released it


def test_a_wait_for_a_turn_that_a_signal_interrupts_leaves_the_lock_usable():
    """A signal handler that raises (SIGTERM in a worker's main thread) while the main thread
    waits for its turn: the lock must not be handed to a waiter that is gone."""

    class Interrupted(Exception):
        pass

    def interrupt(*_):
        raise Interrupted

    lock = TurnLock()
    held = threading.Event()
    release = threading.Event()

    def hold():
        with lock:
            held.set()
            release.wait(5)

    holder = threading.Thread(target=hold)
    holder.start()
    held.wait(5)
    previous = signal.signal(signal.SIGALRM, interrupt)
    try:
        signal.setitimer(signal.ITIMER_REAL, 0.05)
        with pytest.raises(Interrupted):
            lock.acquire()
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
    release.set()
    holder.join(5)
    assert lock.acquire(blocking=False)  # free: no one is left waiting for it
    lock.release()
