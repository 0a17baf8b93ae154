"""A session's REST calls for tests that wait on what the server says rather than on a guess of
time: creating a session (which may take as long as the server gives a worker to start), and
its status, polled until a condition of it holds."""

from __future__ import annotations

import time
from collections.abc import Callable

import httpx

# What the server allows a create: a worker's start (ProcessWorker's start_timeout_s, Ray's
# START_TIMEOUT_S: 60 s each), then its first meta written (a worker call: 60 s). A Ray actor's
# process starting on a busy machine takes longer than httpx's default 5 s.
CREATE_TIMEOUT_S = 125.0


def auth(token: str) -> dict:
    return {"Authorization": f"Bearer {token}"}


def create_session(url: str, **body) -> tuple[str, str]:
    """POST /api/sessions (with ``body``, if any) -> (id, token)."""
    r = httpx.post(f"{url}/api/sessions", json=body or None, timeout=CREATE_TIMEOUT_S)
    r.raise_for_status()
    created = r.json()
    return created["id"], created["token"]


def status(url: str, sid: str, token: str) -> dict:
    """GET /api/sessions/{sid}: a status never waits for the session's work (its worker
    answers it beside frames and stops), so httpx's default timeout holds."""
    r = httpx.get(f"{url}/api/sessions/{sid}", headers=auth(token))
    r.raise_for_status()
    return r.json()


def wait_for_status(
    url: str,
    sid: str,
    token: str,
    condition: Callable[[dict], bool],
    what: str,
    timeout_s: float = 120.0,
) -> dict:
    """The session's status once ``condition`` holds; fails after ``timeout_s`` (a bound on a
    server that never gets there, not a guess of when it does)."""
    deadline = time.monotonic() + timeout_s
    while not condition(body := status(url, sid, token)):
        assert time.monotonic() < deadline, f"{what}: not after {timeout_s:.0f} s: {body}"
        time.sleep(0.2)
    return body


def map_caught_up(body: dict) -> bool:
    """The mapping thread has fused every frame it will of those processed so far: the map's
    figures (``map``) are final until more frames come. Fails for a session whose map died
    (it never catches up)."""
    assert body.get("failure") is None, f"the session failed: {body}"
    return body["fusion_waiting"] == 0


def drone_spawned(body: dict) -> bool:
    """The drone has spawned; fails when it never will: the mapper has caught up and the
    drone's map holds every frame fused (it spawns with the first map that reaches it), yet
    no drone (the status reads the fusion count first, then the map, then the drone, each
    figure whole)."""
    drone = body["drone"]
    if drone["spawned"]:
        return True
    fused = body["map"]["frames_integrated"]
    assert not (map_caught_up(body) and 0 < fused == drone["map_frames"]), (
        f"the drone's map holds every fused frame and no drone spawned: {body}"
    )
    return False
