"""The pieces a Ray actor's session runs on, without Ray: a process in a fresh interpreter
(server/sessions/processes/fresh.py), which ``ProcessWorker`` uses under an actor, and the
actor's stream (server/sessions/processes/actor_stream.py), frames in and updates out past
Ray, on the loopback."""

from __future__ import annotations

import os
import signal
import threading
import time
from multiprocessing import AuthenticationError

import pytest

from server.sessions.processes.actor_stream import StreamListener, hang_up, open_stream
from server.sessions.processes.fresh import FreshContext


def echo_pid(conn, offset: int) -> None:
    """A fresh process's target: answer each number with itself plus ``offset``, then its
    pid and its parent's, until the pipe closes."""
    while True:
        try:
            n = conn.recv()
        except EOFError:
            return
        conn.send((n + offset, os.getpid(), os.getppid()))


def test_a_fresh_process_runs_its_target_with_its_pipe_and_ends_with_it():
    here, there = FreshContext.Pipe()
    process = FreshContext.Process(target=echo_pid, args=(there, 100), name="echo")
    process.start()
    there.close()  # the child's now
    assert process.is_alive() and process.exitcode is None
    here.send(1)
    value, pid, ppid = here.recv()
    assert value == 101 and pid == process.pid and ppid == os.getpid()
    with open(f"/proc/{pid}/cmdline", "rb") as f:  # what it runs, for ps
        assert b"echo_pid" in f.read()
    here.close()  # its pipe closes: it ends on its own
    process.join(30)
    assert not process.is_alive() and process.exitcode == 0


def test_a_fresh_process_killed_reports_the_signal():
    here, there = FreshContext.Pipe()
    process = FreshContext.Process(target=echo_pid, args=(there, 0), name="victim")
    process.start()
    there.close()
    here.send(0)
    here.recv()  # up
    process.kill()
    process.join(30)
    assert process.exitcode == -signal.SIGKILL
    with pytest.raises(EOFError):
        here.recv()


class Frames:
    def __init__(self) -> None:
        self.got: list[tuple[str, int, tuple]] = []
        self.connected = threading.Event()

    def frame(self, owner: str, number: int, args: tuple) -> None:
        self.got.append((owner, number, args))

    def wait(self, n: int) -> None:
        deadline = time.monotonic() + 10
        while len(self.got) < n:
            assert time.monotonic() < deadline, self.got
            time.sleep(0.01)


@pytest.fixture
def stream():
    """An actor's stream listener on the loopback, and the frames it handed on."""
    frames = Frames()
    listener = StreamListener("127.0.0.1", frames.frame, frames.connected.set)
    yield listener, frames
    listener.close()


def test_the_stream_carries_numbered_frames_in_and_updates_out(stream):
    listener, frames = stream
    host, _ = listener.address
    assert host == "127.0.0.1"
    conn = open_stream(listener.address, listener.authkey, "front-a")
    assert frames.connected.wait(10)
    for number in (3, 4, 5):
        conn.send((number, (b"frame %d" % number, 1.5)))
    frames.wait(3)
    assert frames.got == [("front-a", n, (b"frame %d" % n, 1.5)) for n in (3, 4, 5)]
    # Updates go to that front-end's connection.
    mine = listener.connection("front-a")
    assert mine is not None and listener.connection("front-b") is None
    mine.send(["pose 3", "pose 4"])
    assert conn.recv() == ["pose 3", "pose 4"]
    # The front-end hangs up: its updates go by the poll again.
    hang_up(conn)
    deadline = time.monotonic() + 10
    while listener.connection("front-a") is not None:
        assert time.monotonic() < deadline
        time.sleep(0.01)


def test_the_stream_refuses_a_caller_without_the_key(stream):
    listener, frames = stream
    with pytest.raises(AuthenticationError):
        open_stream(listener.address, b"not the key" * 3, "intruder")
    assert listener.connection("intruder") is None and frames.got == []
    # The listener goes on: the holder of the key still connects.
    conn = open_stream(listener.address, listener.authkey, "front-a")
    conn.send((0, (b"x", 0.0)))
    frames.wait(1)
    hang_up(conn)


def test_hanging_up_wakes_a_thread_blocked_reading(stream):
    listener, _ = stream
    conn = open_stream(listener.address, listener.authkey, "front-a")
    ended = threading.Event()

    def read() -> None:
        try:
            conn.recv()
        except (EOFError, OSError, TypeError):
            ended.set()

    threading.Thread(target=read, daemon=True).start()
    time.sleep(0.2)  # blocked in recv
    hang_up(conn)
    assert ended.wait(5), "a reader blocked on the stream was not woken"
