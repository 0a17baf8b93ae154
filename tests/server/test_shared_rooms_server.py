"""Several phones in one room, over the real server: the owner of a live session invites, a
second phone joins with the join token, is placed in the owner's room by place recognition,
tracks in the owner's world frame and fuses into the owner's map, the one map of the room,
which serves it on when the owner leaves; every wrong use is refused with its documented
code."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import httpx
import numpy as np
from websockets.exceptions import ConnectionClosed

from server import protocol as P
from server.datasets import open_dataset
from server.datasets.demo import demo_sequence_path
from server.evaluation.metrics import ate
from server.evaluation.trajectory import Trajectory
from server.geometry import invert
from server.pipeline import ground_truth_pose_at
from server.transport.schemas import RaceFlights, RaceList
from tests.conftest import Stream, auth
from tests.server.test_openapi_server import strictly
from tests.support.rest import drone_spawned, map_caught_up, wait_for_status


def _stream(server, sid: str, token: str, ds, first: int, n: int) -> Stream:
    """Frames ``first``.. of ``ds`` as seqs 0..n-1, each waiting for its pose."""

    async def run() -> Stream:
        s = await Stream(server.ws_url, sid, token, ds).open()
        await s.send_range(range(n), first_index=first)
        await s.close()
        return s

    return asyncio.run(run())


def _listen(server, sid: str, token: str, ds, seconds: float = 1.5):
    """The ``room`` messages a socket of the session gets over ``seconds`` (no frames sent),
    and the last drone pose its drone_state messages gave (T_world_drone) or None."""

    async def run():
        s = await Stream(server.ws_url, sid, token, ds).open()
        rooms, own = [], None
        deadline = time.monotonic() + seconds
        while (left := deadline - time.monotonic()) > 0:
            try:
                msg = await s.conn.receive(left)
            except asyncio.TimeoutError:
                break
            if msg["type"] == "room":
                rooms.append(msg)
            elif msg["type"] == "drone_state":
                own = P.pose_matrix(msg, "T_world_drone")
        await s.close()
        return rooms, own

    return asyncio.run(run())


def _fly_into(server, sid: str, token: str, ds, target: np.ndarray) -> dict:
    """Send the session's drone to ``target`` (world frame); its first collision or crash
    event, or the last event when none comes within 15 s."""

    async def run() -> dict:
        s = await Stream(server.ws_url, sid, token, ds).open()
        await s.conn.send(P.make_command(1, "takeoff"))
        await s.conn.send(P.make_command(2, "goto", target=target))
        last: dict = {}
        deadline = time.monotonic() + 15.0
        while (left := deadline - time.monotonic()) > 0:
            try:
                msg = await s.conn.receive(left)
            except asyncio.TimeoutError:
                break
            if msg["type"] in ("drone_event", "error"):
                last = msg
                if msg.get("event") in ("collision", "crash"):
                    break
        await s.close()
        return last

    return asyncio.run(run())


def _status(server, sid: str, token: str) -> dict:
    r = httpx.get(f"{server.url}/api/sessions/{sid}", headers=auth(token))
    assert r.status_code == 200, r.text
    return r.json()


def _error(response: httpx.Response, status: int, code: str) -> None:
    assert response.status_code == status, response.text
    assert response.json()["error"]["code"] == code, response.text


def _trajectory(ds, first: int, stream: Stream) -> tuple[Trajectory, Trajectory]:
    """(truth in the owner's frame, estimate) for the placed poses of a stream of ``ds``
    from frame ``first``: the owner's first camera (frame 0) is the room's origin."""
    T_room_gt = invert(ground_truth_pose_at(ds, ds[0].timestamp))
    placed = [k for k, p in enumerate(stream.poses) if p["state"] != "lost"]
    stamps = np.array([ds[first + k].timestamp for k in placed])
    truth = np.array([T_room_gt @ ground_truth_pose_at(ds, t) for t in stamps])
    return Trajectory(stamps, truth), Trajectory(stamps, stream.matrices()[placed])


def _joined(a: Trajectory, b: Trajectory) -> Trajectory:
    return Trajectory(
        np.concatenate([a.timestamps, b.timestamps]), np.concatenate([a.poses, b.poses])
    )


def test_a_phone_joins_a_live_room_and_is_placed_in_its_frame(live_server, shared_data, tmp_path):
    server = live_server(tmp_path / "data", max_room_phones=2, snapshot_interval_s=1.0)
    ds = open_dataset(shared_data / "7scenes_a")
    sessions = f"{server.url}/api/sessions"

    # 1. The owner maps frames 0-39 and stays live (a session outlives its socket for the TTL).
    a, token_a = server.create_session()
    s_a = _stream(server, a, token_a, ds, 0, 40)
    owner_map = wait_for_status(server.url, a, token_a, map_caught_up, "the owner's map")["map"]

    # 2. Only the owner's token invites; each call is a new join token.
    other, token_other = server.create_session()
    assert httpx.post(f"{sessions}/{a}/invites").status_code == 401
    _error(httpx.post(f"{sessions}/{a}/invites", headers=auth(token_other)), 404, "not_found")
    r = httpx.post(f"{sessions}/{a}/invites", headers=auth(token_a))
    assert r.status_code == 201, r.text
    join_token = r.json()["join_token"]
    assert r.json()["join"] == a and join_token not in (token_a, token_other)

    # 3. Joining needs that token: none is 401; the owner's own token, or another room's join
    # token, opens nothing (404, as an unknown id); `room` and `join` together are refused.
    assert httpx.post(sessions, json={"join": a}).status_code == 401
    _error(httpx.post(sessions, json={"join": a}, headers=auth(token_a)), 404, "not_found")
    empty_room = httpx.post(f"{sessions}/{other}/invites", headers=auth(token_other))
    other_join = empty_room.json()["join_token"]
    _error(httpx.post(sessions, json={"join": a}, headers=auth(other_join)), 404, "not_found")
    # A room that has mapped nothing yet cannot be joined (nothing to place a phone in).
    r = httpx.post(sessions, json={"join": other}, headers=auth(other_join))
    _error(r, 409, "room_unavailable")
    both = httpx.post(sessions, json={"join": a, "room": a}, headers=auth(join_token))
    assert both.status_code == 422

    r = httpx.post(sessions, json={"join": a}, headers=auth(join_token))
    assert r.status_code == 201, r.text
    b, token_b = r.json()["id"], r.json()["token"]
    assert r.json()["join"] == a and token_b not in (token_a, join_token)

    # 4. The room lists its phones on both sessions; the joined one is not placed yet, may not
    # invite, and the room (max_room_phones=2) is full.
    assert _status(server, a, token_a)["shared_room"] == {"owner": a, "phones": [b]}
    status_b = _status(server, b, token_b)
    assert status_b["shared_room"] == {"owner": a, "phones": [b]}
    assert "shared_room" not in _status(server, other, token_other)
    _error(httpx.post(f"{sessions}/{b}/invites", headers=auth(token_b)), 409, "room_unavailable")
    _error(httpx.post(sessions, json={"join": a}, headers=auth(join_token)), 409, "room_full")

    # 5. The second phone streams a later stretch: answered lost until a frame is recognised
    # in the room (no pose guess), then tracked in the owner's world frame.
    s_b = _stream(server, b, token_b, ds, 60, 20)
    states = [p["state"] for p in s_b.poses]
    first_ok = next(k for k, st in enumerate(states) if st != "lost")
    assert first_ok <= 5 and states.count("lost") == first_ok, states
    assert _status(server, b, token_b)["placed"] is True
    truth_b, estimate_b = _trajectory(ds, 60, s_b)
    errors = np.linalg.norm(truth_b.poses[:, :3, 3] - estimate_b.poses[:, :3, 3], axis=1)
    assert errors.max() < 0.05, errors  # in the owner's frame as it is, no alignment

    # 6. One map: the joined phone's frames went into the owner's map (both sessions report
    # that map, now holding more frames than the owner fused), and its drone flies in it.
    joined = wait_for_status(server.url, b, token_b, map_caught_up, "the joined phone's fusion")
    shared = _status(server, a, token_a)["map"]
    assert shared["frames_integrated"] == joined["map"]["frames_integrated"]
    assert shared["frames_integrated"] > owner_map["frames_integrated"], (shared, owner_map)
    assert shared["active_blocks"] >= owner_map["active_blocks"]
    wait_for_status(server.url, b, token_b, drone_spawned, "the joined phone's drone")
    wait_for_status(server.url, a, token_a, drone_spawned, "the owner's drone")
    # One copy of the room's map in the periodic snapshots (1 s here): the owner's. The joined
    # phone's hold its trajectory; its map comes with its last snapshot.
    folders = tmp_path / "data" / "sessions"
    deadline = time.monotonic() + 20
    while not ((folders / b / "trajectory.tum").is_file() and (folders / a / "map.npz").is_file()):
        assert time.monotonic() < deadline, "no periodic snapshot of both sessions"
        time.sleep(0.2)
    assert not (folders / b / "map.npz").exists()

    # 7. Everyone sees everyone: each phone's socket gets the room's state, itself named by
    # `you`, every drone where its own drone_state puts it.
    for sid, token, you in ((a, token_a, 0), (b, token_b, 1)):
        rooms, own = _listen(server, sid, token, ds)
        assert len(rooms) >= 3, rooms  # about 5 a second
        room = rooms[-1]
        assert room["you"] == you and len(room["pilots"]) == 2 and room["pilots"][you] == "test"
        assert room["placed"] == [True, True] and "none" not in room["modes"], room
        drones = np.reshape(room["drones"], (2, 7))
        assert own is not None
        assert np.allclose(drones[you, :3], own[:3, 3], atol=0.05), (drones, own)
        assert np.linalg.norm(drones[0, :3] - drones[1, :3]) > 0  # two drones, not one twice

    # 8. Drones touch each other: the joined phone's drone sent to the owner's drone's centre
    # (a route on the map alone, which the other drone is not in) bumps into it on the way.
    hit = _fly_into(server, b, token_b, ds, drones[0, :3])
    assert hit["event"] in ("collision", "crash"), hit
    assert np.linalg.norm(np.array(hit["position"]) - drones[0, :3]) < 2 * 0.12 + 0.1, hit

    # 9. Both phones in one frame: one rigid alignment over all their poses fits within 1.5x
    # of the worse of each phone's own.
    truth_a, estimate_a = _trajectory(ds, 0, s_a)
    own = max(ate(truth_a, estimate_a)["rmse"], ate(truth_b, estimate_b)["rmse"])
    together = ate(_joined(truth_a, truth_b), _joined(estimate_a, estimate_b))["rmse"]
    assert together <= 1.5 * own, (together, own)

    # 10. Once the owner's session has ended, its join tokens open nothing, and the room's map
    # serves the joined phone on: it keeps tracking and fusing. The map's process ends (and is
    # reaped) once the last joined phone has gone.
    map_pid = _status(server, a, token_a)["worker"]["mapper_pid"]
    assert httpx.delete(f"{sessions}/{a}", headers=auth(token_a)).status_code == 204
    _error(httpx.post(sessions, json={"join": a}, headers=auth(join_token)), 404, "not_found")
    before = _status(server, b, token_b)["map"]["frames_integrated"]
    s_later = _stream(server, b, token_b, ds, 80, 9)
    assert all(p["state"] != "lost" for p in s_later.poses), [p["state"] for p in s_later.poses]
    later = wait_for_status(server.url, b, token_b, map_caught_up, "the map after the owner left")
    assert later.get("failure") is None and later["map"]["frames_integrated"] > before
    assert Path(f"/proc/{map_pid}").exists()
    assert httpx.delete(f"{sessions}/{b}", headers=auth(token_b)).status_code == 204
    deadline = time.monotonic() + 30
    while Path(f"/proc/{map_pid}").exists() and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not Path(f"/proc/{map_pid}").exists(), "the room's map process outlived its phones"


def _room_until(server, sid: str, token: str, ds, done, timeout_s: float) -> list[dict]:
    """The ``room`` messages a socket of the session gets until ``done(message)`` (or the
    timeout): the last one holds. A socket that sends nothing is closed after the protocol's
    idle_timeout_s: it connects again then, as a phone does."""

    async def run() -> list[dict]:
        rooms: list[dict] = []
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            s = await Stream(server.ws_url, sid, token, ds).open()
            try:
                while (left := deadline - time.monotonic()) > 0:
                    msg = await s.conn.receive(left)
                    if msg["type"] == "room":
                        rooms.append(msg)
                        if done(msg):
                            await s.close()
                            return rooms
            except asyncio.TimeoutError:
                break
            except ConnectionClosed:
                continue
        return rooms

    return asyncio.run(run())


def test_a_race_in_a_shared_room_has_every_drone_fly_the_same_gates_and_a_winner(
    live_server, tmp_path
):
    """The owner starts a race (autopilots, easy course, 1 s countdown): the room counts down,
    both drones fly the same gates from where each is, the standings follow, and the race ends
    with both finished, ranked 1 and 2 by time, no gate missed. The bundled demo room: a
    course needs more free space than a few frames of a real room map."""
    from server.transport.routes_client import DEMO_PRESETS

    ds = open_dataset(demo_sequence_path(DEMO_PRESETS["small"], progress=False), "tum")
    server = live_server(tmp_path / "data")
    sessions = f"{server.url}/api/sessions"
    a, token_a = server.create_session()
    _stream_frames(server, a, token_a, ds, list(range(0, len(ds), 2)))
    join_token = httpx.post(f"{sessions}/{a}/invites", headers=auth(token_a)).json()["join_token"]
    created = httpx.post(sessions, json={"join": a}, headers=auth(join_token)).json()
    b, token_b = created["id"], created["token"]
    _stream_frames(server, b, token_b, ds, list(range(1, 41, 2)))
    for sid, token in ((a, token_a), (b, token_b)):
        wait_for_status(server.url, sid, token, drone_spawned, "a drone")
        wait_for_status(server.url, sid, token, map_caught_up, "a map")

    # Only the room's owner starts it; a joined phone is refused.
    body = {"difficulty": "easy", "countdown_s": 1.0, "autopilot": True}
    r = httpx.post(f"{sessions}/{b}/race", json=body | {"seed": 0}, headers=auth(token_b))
    _error(r, 409, "room_unavailable")
    for sid, token in ((a, token_a), (b, token_b)):  # the autopilot flies a flying drone
        _command(server, sid, token, ds, P.make_command(1, "takeoff"), settle_s=2.0)
    for seed in range(4):  # the map differs a little from run to run: a course must fit it
        r = httpx.post(
            f"{sessions}/{a}/race", json=body | {"seed": seed}, headers=auth(token_a), timeout=60
        )
        if r.status_code != 409:
            break
        _error(r, 409, "race_unavailable")
    assert r.status_code == 201, r.text
    started = r.json()
    assert started["gates"] == 3 and started["difficulty"] == "easy"

    rooms = _room_until(server, a, token_a, ds, lambda m: m.get("race") == "finished", 90)
    states = [m.get("race") for m in rooms]
    assert states[0] == "countdown" and "running" in states, states
    # Each drone's route ahead travels with the room, starting where the drone is.
    routed = [m for m in rooms if min(m.get("route_lengths", [0])) >= 2]
    assert routed, "no room message carried both autopilots' routes"
    m = routed[-1]
    starts = np.cumsum([0, *m["route_lengths"][:-1]])
    routes = np.reshape(m["routes"], (-1, 3))
    drones = np.reshape(m["drones"], (-1, 7))[:, :3]
    assert np.all(np.linalg.norm(routes[starts] - drones, axis=1) < 0.3), (routes[starts], drones)
    last = rooms[-1]
    assert last["race"] == "finished", last
    assert last["race_finished"] == [True, True] and last["race_missed"] == [0, 0], last
    assert last["race_passed"] == [3, 3] and sorted(last["race_rank"]) == [1, 2], last
    winner = last["race_rank"].index(1)
    assert last["race_time_s"][winner] <= last["race_time_s"][1 - winner]
    for sid, token in ((a, token_a), (b, token_b)):  # each judged by its own session
        events = _status(server, sid, token)["drone"]["events"]
        assert events.get("course_finished", 0) >= 1, events

    # Kept in each pilot's session: the race's record and the room's best list.
    for sid, token in ((a, token_a), (b, token_b)):
        listing = strictly(RaceList, _get(f"{sessions}/{sid}/races", token))
        (record,) = listing.races
        assert record.number == started["race"] and record.seed == started["seed"]
        assert [p.session for p in record.pilots] == [a, b] and record.owner == a
        assert [p.rank for p in record.pilots] == last["race_rank"]
        assert [p.time_s for p in record.pilots] == [round(t, 3) for t in last["race_time_s"]]
        assert [e.session for e in listing.best] == [
            record.pilots[winner].session,
            [a, b][1 - winner],
        ]
        assert listing.best[0].time_s <= listing.best[1].time_s
    # Replayed together: every pilot's flights of the race, each holding the race's course.
    flown = strictly(RaceFlights, _get(f"{sessions}/{b}/races/{started['race']}/flights", token_b))
    assert [p.session for p in flown.pilots] == [a, b]
    for pilot in flown.pilots:
        raced = [f for f in pilot.flights if (f.get("course") or {}).get("seed") == started["seed"]]
        assert raced and raced[-1]["result"]["gates_passed"] == 3, pilot.session
        flight = raced[-1]
        ends = flight["started_at"] + flight["end_time_s"] - flight["start_time_s"]
        assert flight["started_at"] <= record.ended_at and ends >= record.started_at
    r = httpx.get(f"{sessions}/{a}/races/99/flights", headers=auth(token_a))
    _error(r, 404, "not_found")

    # Another day: the server stops (saving both sessions and the owner's room); a session
    # continuing in that room starts with the room's best list to beat.
    best = listing.best
    server.stop()
    assert (tmp_path / "data" / "sessions" / b / "map.npz").is_file()  # the joined phone's last
    again = live_server(tmp_path / "data")
    assert strictly(RaceList, _get(f"{again.url}/api/sessions/{a}/races", token_a)).best == best
    r = httpx.post(f"{again.url}/api/sessions", json={"room": a}, headers=auth(token_a))
    assert r.status_code == 201, r.text
    visit = r.json()
    carried = strictly(
        RaceList, _get(f"{again.url}/api/sessions/{visit['id']}/races", visit["token"])
    )
    assert carried.races == [] and carried.best == best


def _get(url: str, token: str) -> dict:
    r = httpx.get(url, headers=auth(token))
    assert r.status_code == 200, r.text
    return r.json()


def _stream_frames(server, sid: str, token: str, ds, frames: list[int]) -> Stream:
    """Frames ``frames`` of ``ds`` as seqs 0.., each waiting for its pose."""

    async def run() -> Stream:
        s = await Stream(server.ws_url, sid, token, ds).open()
        for seq, index in enumerate(frames):
            await s.send(seq, index=index)
        await s.close()
        return s

    return asyncio.run(run())


def _command(server, sid: str, token: str, ds, command: dict, settle_s: float) -> None:
    """Send one command on the session's socket and keep the socket open ``settle_s``."""

    async def run() -> None:
        s = await Stream(server.ws_url, sid, token, ds).open()
        await s.conn.send(command)
        await asyncio.sleep(settle_s)
        await s.close()

    asyncio.run(run())
