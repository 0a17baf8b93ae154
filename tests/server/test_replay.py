"""The replay client says whether its run completed, and the demo logs a partial run as an
error and never its session's token."""

from __future__ import annotations

import asyncio
import logging
from types import SimpleNamespace

import httpx
import pytest

from server.client.replay import ReplayStats, replay
from server.datasets import open_dataset
from server.transport import demo
from tests.conftest import auth


def _replay(server, sid, token, ds, **kwargs) -> ReplayStats:
    url = f"{server.ws_url}/ws/sessions/{sid}"
    return asyncio.run(
        replay(url, token, ds, fps=1000, max_in_flight=1, drop_when_busy=False, **kwargs)
    )


def test_a_whole_run_is_complete(live_server, demo_clean):
    server = live_server()
    ds = open_dataset(demo_clean)
    sid, token = server.create_session()
    stats = _replay(server, sid, token, ds, max_frames=10)
    assert stats.completed, stats.failure
    assert stats.sent == stats.answered == 10 and stats.missing == 0
    assert stats.close_code == 1000 and "incomplete" not in stats.describe()


def test_a_run_cut_short_by_the_server_says_so(live_server, demo_clean):
    """The session is deleted after 3 poses: the server closes the socket; the statistics are
    partial and say so, with the close that ended them."""
    server = live_server()
    ds = open_dataset(demo_clean)
    sid, token = server.create_session()

    def delete_after_three(pose: dict) -> None:
        if pose["seq"] == 2:
            httpx.delete(f"{server.url}/api/sessions/{sid}", headers=auth(token), timeout=60)

    stats = _replay(server, sid, token, ds, max_frames=20, on_pose=delete_after_three)
    assert not stats.completed
    assert 3 <= stats.sent < 20 and len(stats.poses) >= 3
    assert "connection ended" in stats.failure and "close" in stats.failure
    assert "incomplete" in stats.describe()


def test_a_failing_pilot_ends_the_run_as_incomplete(live_server, demo_clean):
    server = live_server()
    ds = open_dataset(demo_clean)
    sid, token = server.create_session()

    def pilot(msg: dict) -> None:
        if msg["type"] == "pose" and msg["seq"] == 1:
            raise RuntimeError("pilot bug")

    stats = _replay(server, sid, token, ds, max_frames=10, pilot=pilot)
    assert not stats.completed and "pilot bug" in stats.failure


@pytest.mark.parametrize("completed", [True, False])
def test_the_demo_logs_a_partial_run_as_an_error_and_never_its_token(
    completed, demo_clean, tmp_path, monkeypatch, caplog
):
    token = "s3cr3t-t0k3n-never-logged"
    session = SimpleNamespace(id="0123456789abcdef")
    manager = SimpleNamespace(create=lambda: (session, token))
    settings = SimpleNamespace(
        tls=False, host="127.0.0.1", port=9, demo_fps=15.0, data_dir=tmp_path
    )
    app = SimpleNamespace(state=SimpleNamespace(settings=settings, manager=manager, demo=None))
    stats = ReplayStats(sent=12, missing=0 if completed else 5)
    stats.failure = None if completed else "the connection ended (close 1011 internal_error)"

    async def fake_replay(url, given_token, *args, **kwargs):
        assert given_token == token  # the token goes to the socket, not to the log
        return stats

    monkeypatch.setattr(demo, "replay", fake_replay)
    monkeypatch.setattr(demo, "demo_sequence_path", lambda: demo_clean)
    with caplog.at_level(logging.DEBUG, logger="server.transport.demo"):
        asyncio.run(demo.run_demo(app))
    assert app.state.demo == {"id": session.id, "token": token}
    assert all(token not in r.getMessage() for r in caplog.records)
    summary = [r for r in caplog.records if "12 frames sent" in r.getMessage()]
    assert len(summary) == 1
    if completed:
        assert summary[0].levelno == logging.WARNING
    else:
        assert summary[0].levelno == logging.ERROR
        assert "ended early" in summary[0].getMessage() and "5 missing" in summary[0].getMessage()
