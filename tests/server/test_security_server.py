"""Strangers: tokens, uniform refusals, the data directory's walls, rate limit, cap and CORS.

Against a real server on loopback wherever a client could try it; paths that an HTTP library
would normalise (dot segments, encoded slashes) go out on a raw socket, byte for byte. (What needs
no server, in this process: tests/unit/transport/test_security.py.)
"""

from __future__ import annotations

import asyncio
import hashlib
import json
import re
import socket
import time

import httpx
import pytest
import websockets

from server import protocol as P
from server.client.connection import Socket
from server.sessions.store import hash_token
from tests.conftest import auth

RESOURCES = [
    ("GET", ""),
    ("GET", "/map.ply"),
    ("GET", "/mesh.ply"),
    ("GET", "/mesh.ply?frame=upright"),
    ("GET", "/mesh.glb"),
    ("GET", "/trajectory.tum"),
    ("DELETE", ""),
]
UNKNOWN_ID = "0123456789abcdef"


def answer(r: httpx.Response) -> tuple[int, bytes]:
    return r.status_code, r.content


def raw_request(port: int, method: str, path: str, token: str | None = None) -> tuple[int, bytes]:
    """One HTTP/1.1 request with ``path`` sent exactly as given; -> (status, body)."""
    head = f"{method} {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nConnection: close\r\n"
    if token is not None:
        head += f"Authorization: Bearer {token}\r\n"
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        s.sendall((head + "\r\n").encode("latin-1"))
        data = b""
        while chunk := s.recv(65536):
            data += chunk
    status_line, _, rest = data.partition(b"\r\n")
    return int(status_line.split()[1]), rest.partition(b"\r\n\r\n")[2]


async def ws_refusal(url: str, token: str | None) -> tuple[dict, int | None]:
    """The error message and close code a WebSocket to ``url`` with ``token`` (None: none at
    all) gets; nothing else may come between them."""
    async with await Socket.connect(url, token) as socket:
        msg = await socket.receive(10)
        assert await socket.until_closed(10) == []
        return msg, socket.close_code


# ---- tokens ------------------------------------------------------------------------------------


def test_tokens_are_long_random_secrets_and_only_their_hashes_are_stored(live_server):
    server = live_server()
    made = [server.create_session() for _ in range(8)]
    ids, tokens = zip(*made, strict=True)
    assert len(set(ids)) == len(ids) and all(re.fullmatch(r"[0-9a-f]{16}", i) for i in ids)
    assert len(set(tokens)) == len(tokens)
    for token in tokens:  # secrets.token_urlsafe(32): 256 random bits
        assert len(token) >= 43 and re.fullmatch(r"[A-Za-z0-9_-]+", token)
    stored = b"".join(p.read_bytes() for p in server.settings.data_dir.rglob("*") if p.is_file())
    for sid, token in made:
        assert token.encode() not in stored
        meta = json.loads((server.settings.data_dir / "sessions" / sid / "meta.json").read_text())
        assert meta["token_sha256"] == hashlib.sha256(token.encode()).hexdigest()


def test_every_session_resource_refuses_a_missing_or_wrong_token_alike_for_unknown_ids(
    live_server, tmp_path
):
    """401 without a token, 404 with a wrong one: the same status and body whether the id
    exists (live or closed) or not, for status, downloads, delete and the WebSocket."""
    data_dir = tmp_path / "uniform"
    server = live_server(data_dir)
    (sid, token), (_, other_token) = server.create_session(), server.create_session()

    def check(server, sid, token) -> None:
        base = f"{server.url}/api/sessions"
        for method, path in RESOURCES:
            missing = {
                answer(httpx.request(method, f"{base}/{i}{path}")) for i in (sid, UNKNOWN_ID)
            }
            refused = {
                answer(httpx.request(method, f"{base}/{i}{path}", headers=auth(t)))
                for i, t in (
                    (sid, "wrong"),
                    (sid, other_token),
                    (UNKNOWN_ID, token),
                    (sid, token[:-1]),
                    (sid, token + "x"),
                )
            }
            refused |= {
                answer(httpx.request(method, f"{base}/{sid}{path}", headers=h))
                for h in ({"Authorization": f"Basic {token}"}, {"Authorization": "Bearer"})
            }
            assert len(missing) == 1 and next(iter(missing))[0] == 401, (method, path, missing)
            # A bad scheme counts as no token (401); every wrong token is one answer (404).
            statuses = {s for s, _ in refused}
            assert statuses <= {401, 404}
            assert len({a for a in refused if a[0] == 404}) == 1, (method, path, refused)
            # The token goes in a header, never in a REST URL (logs, history, referrers).
            assert httpx.request(method, f"{base}/{sid}{path}?token={token}").status_code == 401
        refusals = [
            asyncio.run(ws_refusal(f"{server.ws_url}/ws/sessions/{i}", t))
            for i, t in ((sid, "wrong"), (UNKNOWN_ID, token), (sid, other_token))
        ]
        assert all(code == P.CLOSE_CODES["unauthorized"] for _, code in refusals)
        assert all(msg["name"] == "unauthorized" for msg, _ in refusals)
        assert len({msg["message"] for msg, _ in refusals}) == 1
        msg, code = asyncio.run(ws_refusal(f"{server.ws_url}/ws/sessions/{sid}", None))
        assert msg["name"] == "unauthorized" and code == P.CLOSE_CODES["unauthorized"]

    check(server, sid, token)
    assert httpx.get(f"{server.url}/api/sessions/{sid}", headers=auth(token)).status_code == 200
    server.stop()  # the sessions are closed and saved: refusals must not change
    again = live_server(data_dir)
    check(again, sid, token)
    assert httpx.get(f"{again.url}/api/sessions/{sid}", headers=auth(token)).json()["closed"]


# ---- the data directory's walls --------------------------------------------------------------

TRAVERSALS = [
    "..",
    "...",
    "%2e%2e",
    "%2E%2E",
    "..%2f",
    "..%2Fevil",
    "..%2f..%2fsecret.txt",
    "%2e%2e%2fevil",
    "..%5cevil",
    "..\\evil",
    "evil",
    "notanid",
    "%00",
    f"{UNKNOWN_ID}%0a",
    f"{UNKNOWN_ID}%00",
    UNKNOWN_ID.upper(),
    f"{UNKNOWN_ID}%2f..",
    "%252e%252e%252fevil",
    "....%2f%2f",
    "~root",
    "%2fetc%2fpasswd",
    "a" * 5000,
]
SUFFIXES = [
    "",
    "/map.ply",
    "/mesh.ply",
    "/trajectory.tum",
    "/meta.json",
    "/../../secret.txt",
    "/..%2f..%2fsecret.txt",
]


def test_ids_and_file_names_never_reach_outside_the_data_directory(live_server, tmp_path):
    """A decoy session folder beside sessions/ with a known token, and secrets beside the data
    directory: no id, encoded or not, reads, lists or deletes any of them."""
    data_dir = tmp_path / "data"
    secret = "TOP SECRET canary"
    (tmp_path / "secret.txt").write_text(secret)
    (data_dir / "sessions").mkdir(parents=True)
    (data_dir / "secret.txt").write_text(secret)
    token = "decoy-token"
    meta = {"id": "evil", "token_sha256": hash_token(token), "status": {"secret": secret}}
    for folder in (
        data_dir / "evil",
        data_dir / "sessions" / "notanid",
        data_dir / "sessions" / f"{UNKNOWN_ID}\n",
    ):
        folder.mkdir()
        (folder / "meta.json").write_text(json.dumps(meta))
        (folder / "map.ply").write_text(f"ply {secret}")
        (folder / "trajectory.tum").write_text(secret)
    canaries = sorted(p for p in tmp_path.rglob("*") if p.is_file())
    server = live_server(data_dir)
    assert httpx.get(f"{server.url}/healthz").json()["saved_sessions"] == 0  # decoys not loaded

    for sid in TRAVERSALS:
        for suffix in SUFFIXES:
            for method in ("GET", "DELETE"):
                status, body = raw_request(
                    server.port, method, f"/api/sessions/{sid}{suffix}", token
                )
                assert status in (307, 400, 404, 405, 414), (method, sid, suffix, status, body)
                assert secret.encode() not in body
        try:  # a path that matches no route is refused at the handshake
            msg, code = asyncio.run(ws_refusal(f"{server.ws_url}/ws/sessions/{sid}", token))
            assert msg["name"] == "unauthorized" and code == P.CLOSE_CODES["unauthorized"]
        except websockets.InvalidStatus as refused:
            assert refused.response.status_code in (403, 404)
            assert secret.encode() not in refused.response.body
    assert all(p.is_file() for p in canaries)  # nothing deleted


# ---- rate limit and cap ------------------------------------------------------------------------


def test_session_creation_is_rate_limited_per_client_address(live_server):
    server = live_server(create_rate_per_min=60, create_burst=3)
    url = f"{server.url}/api/sessions"
    assert [httpx.post(url).status_code for _ in range(3)] == [201, 201, 201]
    refused = httpx.post(url)
    assert refused.status_code == 429
    assert refused.json()["error"]["code"] == "rate_limited"
    assert "try again" in refused.json()["error"]["message"]
    wait = int(refused.headers["Retry-After"])
    assert 1 <= wait <= 2
    assert httpx.get(f"{server.url}/healthz").json()["live_sessions"] == 3  # none made
    # Another address (loopback has all of 127/8) has a bucket of its own.
    with httpx.Client(transport=httpx.HTTPTransport(local_address="127.0.0.2")) as other:
        assert other.post(url).status_code == 201
    time.sleep(wait)
    assert httpx.post(url).status_code == 201


def test_behind_a_trusted_proxy_the_limit_counts_each_phone_and_nobody_else_can_forge_one(
    live_server,
):
    """Through a reverse proxy every phone arrives from the proxy's address; its X-Forwarded-For
    names the phone, and is believed only from the proxies in FORWARDED_ALLOW_IPS."""
    url = "/api/sessions"

    def create(server, phone: str) -> int:
        return httpx.post(f"{server.url}{url}", headers={"X-Forwarded-For": phone}).status_code

    behind_proxy = live_server(create_burst=1, create_rate_per_min=1)  # loopback is the proxy
    assert [create(behind_proxy, "203.0.113.5"), create(behind_proxy, "203.0.113.5")] == [201, 429]
    assert create(behind_proxy, "203.0.113.6") == 201  # another phone, its own bucket

    direct = live_server(create_burst=1, create_rate_per_min=1, forwarded_allow_ips="10.9.9.9")
    assert create(direct, "203.0.113.5") == 201
    assert create(direct, "198.51.100.7") == 429  # a forged header changes nothing


def test_a_full_server_says_so_with_503_until_a_session_ends(live_server):
    server = live_server(max_sessions=2)
    (sid, token), _ = server.create_session(), server.create_session()
    full = httpx.post(f"{server.url}/api/sessions")
    assert full.status_code == 503
    error = full.json()["error"]
    assert error["code"] == "server_full" and "maximum of 2 live sessions" in error["message"]
    assert httpx.delete(f"{server.url}/api/sessions/{sid}", headers=auth(token)).status_code == 204
    assert httpx.post(f"{server.url}/api/sessions").status_code == 201


# ---- CORS --------------------------------------------------------------------------------------


def preflight(server, origin: str) -> httpx.Response:
    return httpx.options(
        f"{server.url}/api/sessions",
        headers={
            "Origin": origin,
            "Access-Control-Request-Method": "POST",
            "Access-Control-Request-Headers": "authorization",
        },
    )


def test_by_default_no_other_origin_may_call_the_api(live_server):
    server = live_server()
    for origin in ("https://evil.example", "null", server.url):
        r = preflight(server, origin)
        assert r.status_code != 200 and "access-control-allow-origin" not in r.headers
        r = httpx.get(f"{server.url}/healthz", headers={"Origin": origin})
        assert "access-control-allow-origin" not in r.headers


def test_configured_origins_are_allowed_exactly_and_others_refused(live_server):
    allowed = "https://phone.example:8443"
    server = live_server(cors_origins=[allowed])
    ok = preflight(server, allowed)
    assert ok.status_code == 200
    assert ok.headers["access-control-allow-origin"] == allowed  # echoed, never "*"
    assert "POST" in ok.headers["access-control-allow-methods"]
    assert "authorization" in ok.headers["access-control-allow-headers"].lower()
    for origin in (
        "https://evil.example",
        "https://phone.example",
        "http://phone.example:8443",
        "https://phone.example:8443.evil.example",
    ):
        refused = preflight(server, origin)
        assert refused.status_code == 400 and "access-control-allow-origin" not in refused.headers
        r = httpx.get(f"{server.url}/healthz", headers={"Origin": origin})
        assert "access-control-allow-origin" not in r.headers
    r = httpx.get(f"{server.url}/healthz", headers={"Origin": allowed})
    assert r.headers["access-control-allow-origin"] == allowed


# ---- request errors ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    "method, path, kwargs, status, code",
    [
        ("post", "/api/sessions", {"content": b"{not json", "headers": {"content-type": "application/json"}}, 422, "bad_request"),  # noqa: E501
        ("post", "/api/sessions", {"json": {"loop_closure": "maybe"}}, 422, "bad_request"),
        ("post", "/api/sessions", {"json": {"room": "..%2F.."}}, 404, "not_found"),
        ("post", "/api/sessions", {"json": {"room": "a" * 10_000}}, 404, "not_found"),
        ("get", "/api/no/such/route", {}, 404, "not_found"),
        ("get", "/api/recordings/" + "x" * 40, {"headers": {"Authorization": "Bearer t"}}, 404, "not_found"),  # noqa: E501
    ],
    ids=["malformed json", "wrong type", "room id with a path", "10 kB room id", "no route",
         "malformed recording id"],
)  # fmt: skip
def test_every_request_error_has_the_documented_form(
    live_server, method, path, kwargs, status, code
):
    """Malformed bodies, ids that cannot exist and unknown paths: the documented
    ``{"error": {code, message}}`` with the documented status, not FastAPI's ``{"detail": ...}``;
    nothing of the server's own paths in the message."""
    server = live_server()
    r = getattr(httpx, method)(f"{server.url}{path}", timeout=30, **kwargs)
    assert r.status_code == status, r.text
    body = r.json()
    assert set(body) == {"error"} and body["error"]["code"] == code, body
    assert (
        body["error"]["message"] and str(server.settings.data_dir) not in body["error"]["message"]
    )
