"""Tracking recovery in a live session (real uvicorn on loopback, a real WebSocket client): a
phone that swings away to a view the map does not have, and back, gets poses all along without a
new session; the wire says how it recovers, and the map takes no frame whose place is a guess."""

from __future__ import annotations

import asyncio
import time

from server.datasets import open_dataset
from tests.conftest import Stream, session_status

# synthetic_room0: a walk, a jump of 0.9 m and 63 degrees to a view no keyframe shares (a fast
# swing the frames did not catch), on to the end, and back over the whole path.
BEFORE = list(range(0, 40, 2))
AWAY = list(range(74, 150, 2))
BACK = list(range(147, 0, -3))


def settled_frames(server, sid, token, quiet_s: float = 4.0, timeout_s: float = 120.0) -> int:
    """The map's frames_integrated once fusion has caught up (unchanged for ``quiet_s``: the
    mapping thread runs at a lower priority and, on a loaded machine, stalls for seconds)."""
    last, since, deadline = -1, time.monotonic(), time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        now = session_status(server.url, sid, token)["map"]["frames_integrated"]
        if now != last:
            last, since = now, time.monotonic()
        elif time.monotonic() - since >= quiet_s:
            return now
        time.sleep(0.25)
    raise AssertionError("fusion did not settle")


def test_a_phone_that_swings_away_and_back_recovers_in_the_same_session(live_server, shared_data):
    server = live_server()
    ds = open_dataset(shared_data / "synthetic_room0")
    sid, token = server.create_session()
    stream = Stream(server.ws_url, sid, token, ds)

    async def conversation() -> tuple[int, int, int]:
        await stream.open()
        settled = []
        seq = 0
        for indices in (BEFORE, AWAY, BACK):
            for index in indices:
                await stream.send(seq, index=index)
                seq += 1
            settled.append(await asyncio.to_thread(settled_frames, server, sid, token))
        await stream.close()
        return settled[0], settled[1], settled[2]

    before, away, back = asyncio.run(conversation())

    poses = stream.poses
    states = [p["state"] for p in poses]
    recovery = [p.get("recovery") for p in poses]
    assert len(poses) == len(BEFORE) + len(AWAY) + len(BACK)
    assert "lost" in states  # the swing did lose track ...
    runs = "".join("l" if s == "lost" else "." for s in states).split(".")
    assert max(len(run) for run in runs) <= 3  # never lost for long
    assert states.count("lost") <= 3  # ... only for the frames before a segment starts
    first = recovery.index("segment")
    merged = recovery.index("merged")
    assert first >= len(BEFORE) and merged > first
    assert all(r == "segment" for r in recovery[first:merged])
    assert all(s == "weak" for s in states[first:merged])
    assert all(r is None for r in recovery[merged + 1 :])
    assert set(states[merged:]) <= {"ok", "weak"}

    # Nothing placed by a guess went into the map; after the merge, fusion goes on.
    assert away == before, (before, away)
    assert back > away

    status = session_status(server.url, sid, token)
    fused_later = status["recovery"].pop("segment_frames_fused")
    assert status["recovery"] == {
        "relocalised": recovery.count("relocalised"),
        "segments": 1,
        "merged": 1,
        "in_segment": merged - first,
    }
    # The segment's keyframes went into the map once it merged, at their corrected poses.
    keyframes_in_segment = sum(p.get("keyframe", False) for p in poses[first:merged])
    assert 0 < fused_later <= keyframes_in_segment
    assert status["tracking_states"]["lost"] == states.count("lost")
