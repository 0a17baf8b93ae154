"""Strangers, in this process: tokens compared in constant time, the store's walls around session
ids, the rate limiter's bound, origins checked at start, tokens kept out of the logs (against
a real server on loopback: tests/server/test_security_server.py)."""

from __future__ import annotations

import hmac
import json
import logging
import re

import pytest
from pydantic import ValidationError

from server.config import Config, ServerConfig
from server.sessions.errors import SessionError
from server.sessions.store import SessionStore, StoreError
from server.sessions.web import manager as manager_module
from server.sessions.web.manager import SessionManager
from server.transport.app import RedactTokens
from server.transport.deps import RateLimiter

UNKNOWN_ID = "0123456789abcdef"


def test_tokens_are_compared_in_constant_time_with_the_same_work_for_unknown_ids(
    tmp_path, monkeypatch
):
    """Every outcome costs one hash and one hmac.compare_digest of two hex digests; an unknown
    id and a wrong token raise the very same error."""
    manager = SessionManager(SessionStore(tmp_path))
    live, token = manager.create()
    closed, closed_token = manager.create()
    manager.close(closed.id)
    calls = []
    real = hmac.compare_digest

    def spy(a, b):
        calls.append((a, b))
        return real(a, b)

    monkeypatch.setattr(manager_module.hmac, "compare_digest", spy)
    refusals = []
    for sid, presented in (
        (live.id, token),
        (closed.id, closed_token),
        (live.id, "wrong"),
        (closed.id, "wrong"),
        (UNKNOWN_ID, token),
        ("../../etc", token),
    ):
        calls.clear()
        try:
            manager.authorize(sid, presented)
        except SessionError as exc:
            refusals.append((exc.code, str(exc)))
        assert len(calls) == 1, (sid, calls)
        assert all(re.fullmatch(r"[0-9a-f]{64}", x) for x in calls[0])
    assert len(refusals) == 4 and len(set(refusals)) == 1
    manager.shutdown()


@pytest.mark.parametrize(
    "sid",
    [
        "",
        "..",
        "../x",
        f"{UNKNOWN_ID}\n",
        f"{UNKNOWN_ID}/..",
        f"/{UNKNOWN_ID}",
        UNKNOWN_ID.upper(),
        UNKNOWN_ID + "0",
        None,
        7,
    ],
)
def test_the_store_refuses_any_id_but_sixteen_hex_digits(tmp_path, sid):
    store = SessionStore(tmp_path)
    with pytest.raises(StoreError):
        store.folder(sid)
    assert store.folder(UNKNOWN_ID).resolve().is_relative_to(store.root.resolve())
    for name in ("../meta.json", "map.ply/../../x", "map.npz.tmp", ""):
        with pytest.raises(StoreError):
            store.file(UNKNOWN_ID, name)


def test_the_rate_limiter_forgets_clients_to_stay_bounded():
    limiter = RateLimiter(per_min=6, burst=2, max_keys=100)
    for i in range(1000):
        assert limiter.take(f"10.0.{i // 256}.{i % 256}") == 0
    assert len(limiter._buckets) <= 100
    assert limiter.take("a") == 0 and limiter.take("a") == 0
    assert 9 < limiter.take("a") <= 10  # 6 a minute: the next in 10 s
    off = RateLimiter(per_min=0, burst=1)  # 0 a minute: no limit at all
    assert [off.take("a") for _ in range(3)] == [0, 0, 0]


@pytest.mark.parametrize(
    "origins",
    [
        ["*"],
        ["https://*.example"],
        ["https://a.example/"],
        ["phone.example"],
        ["https://a.example/path"],
    ],
)
def test_a_wildcard_or_malformed_origin_stops_the_server_at_start(origins, monkeypatch):
    with pytest.raises(ValidationError, match="scheme://host"):
        ServerConfig(cors_origins=origins)
    monkeypatch.setenv("DRONESIM_CORS_ORIGINS", json.dumps(origins))
    with pytest.raises(ValidationError):
        Config()


def test_tokens_never_reach_the_logs(tmp_path):
    """uvicorn logs each WebSocket's path with its query string, which carries the token."""
    from server.transport.app import create_app

    create_app(Config(server=ServerConfig(data_dir=tmp_path)))
    logger = logging.getLogger("uvicorn.error")  # uvicorn's config stops it propagating
    assert any(isinstance(f, RedactTokens) for f in logger.filters)
    lines: list[str] = []
    handler = logging.Handler()
    handler.emit = lambda record: lines.append(record.getMessage())
    logger.addHandler(handler)
    try:
        logger.warning(
            '%s - "WebSocket %s" [accepted]',
            ("127.0.0.1", 5000),
            "/ws/sessions/0123456789abcdef?token=s3cr3t-Token_value&x=1",
        )
    finally:
        logger.removeHandler(handler)
    assert lines and "s3cr3t" not in lines[0] and "token=[redacted]&x=1" in lines[0]
