"""The server's memory over many sessions: a closed session is freed as it closes, and ``serve``
runs on jemalloc, which returns freed pages (the soak, ``benchmarks/soak.py``, is the long
check)."""

from __future__ import annotations

import asyncio
import gc
import os
import time
import weakref
from pathlib import Path

import httpx
import pytest

from server.client.replay import replay
from server.client.server_process import ServerProcess
from server.datasets import open_dataset
from server.memory import find_jemalloc, loaded_allocator
from tests.conftest import missing, process_running, session_status


@pytest.fixture
def no_automatic_gc():
    """Python's own cyclic collections run at random moments; off, only the server's count."""
    gc.collect()
    gc.disable()
    yield
    gc.enable()


def test_a_session_closed_after_its_ttl_is_freed_at_once(live_server, shared_data, no_automatic_gc):
    """Its worker process ends (all its memory goes back with it), and the web process's handle
    on it is freed at once, not at Python's next full collection."""
    server = live_server(session_ttl_s=1.0)
    sid, token = server.create_session()
    session = weakref.ref(server.app.state.manager._live[sid])
    room = open_dataset(shared_data / "synthetic_room0")
    stats = asyncio.run(
        replay(
            f"{server.ws_url}/ws/sessions/{sid}",
            token,
            room,
            fps=30,
            max_frames=20,
            drop_when_busy=False,
        )
    )
    # Sent at 30 fps without waiting: a frame may lose to a newer one (newest wins); what this
    # test is about is the memory after the close.
    assert len(stats.poses) >= 15
    pid = session_status(server.url, sid, token)["worker"]["pid"]
    assert pid != os.getpid() and Path(f"/proc/{pid}").exists()
    assert session() is not None and session().worker is not None  # threads, pipe: cycles
    deadline = time.monotonic() + 30
    while httpx.get(f"{server.url}/healthz").json()["live_sessions"]:
        assert time.monotonic() < deadline, "the session was not closed after its TTL"
        time.sleep(0.1)
    deadline = time.monotonic() + 5  # the reaper thread returns after the close
    while (session() is not None or process_running(pid)) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not process_running(pid), "the closed session's worker process is still there"
    assert session() is None, "a closed session stays in memory until Python's next full GC"


def test_serve_runs_on_jemalloc_when_installed_and_on_glibc_when_told(tmp_path):
    if find_jemalloc() is None:
        missing("libjemalloc2 is not installed (scripts/setup.sh installs it)")
    with ServerProcess(tmp_path / "a", log=tmp_path / "a.log") as jemalloc:
        assert jemalloc.health()["allocator"] == "jemalloc"
        assert loaded_allocator(jemalloc.pid) == "jemalloc"  # the same pid: exec, not a child
    env = {"DRONESIM_ALLOCATOR": "system"}
    with ServerProcess(tmp_path / "b", env, log=tmp_path / "b.log") as system:
        assert system.health()["allocator"] == "glibc"
