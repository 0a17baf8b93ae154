"""Flight recordings through the real server: a session's flights over REST, kept across a restart
(the recorder itself: tests/unit/simulation/test_flight_recordings.py)."""

from __future__ import annotations

import asyncio
import csv
import io
import time

import httpx
import numpy as np

from server import protocol as proto
from server.datasets import open_dataset
from server.evaluation.trajectory import read_tum
from server.simulation.flight_recording import STATE_COLUMNS
from server.transport.schemas import FlightList, FlightRecordingBody, FlightSummary
from tests.conftest import auth
from tests.server.test_drone_server import piloting
from tests.server.test_openapi_server import strictly

FRAMES = 24


async def _fly_and_land(server, dataset) -> tuple[str, str, dict]:
    """Stream FRAMES frames, fly by sticks for 2 s, land, then take off again (a second flight
    that is still in the air when the server stops)."""
    sid, token = server.create_session()
    async with piloting(server, sid, token, dataset, "rec-test") as pilot:
        for i in range(FRAMES):
            frame = dataset[i]
            await pilot.send(proto.make_frame(i, frame.timestamp, frame.colour, frame.depth))
            await pilot.wait_for("pose", seq=i)
        await pilot.wait_for("drone_event", timeout=30.0, event="spawned")
        start = time.monotonic()
        command_id = 10
        while time.monotonic() - start < 2.0:  # a gentle yaw by hand, at the page's 10 Hz
            await pilot.send(proto.make_command(command_id, "sticks", sticks=[0, 0.5, 0, 0]))
            command_id += 1
            await asyncio.sleep(0.1)
        await pilot.send(proto.make_command(1, "land"))
        await pilot.wait_for("drone_event", timeout=30.0, event="landed")
        await asyncio.sleep(0.3)  # the landed state closes the flight, which is then saved
        await pilot.send(proto.make_command(2, "takeoff"))
        await pilot.wait_for("drone_state", timeout=10.0, command_id=2)
        await asyncio.sleep(0.5)
        out = {
            "sticks_sent": command_id - 10,
            "states": pilot.of("drone_state"),
            "errors": pilot.of("error"),
        }
    return sid, token, out


def test_a_session_records_its_flights_and_serves_them_after_a_restart(
    live_server, shared_data, tmp_path
):
    dataset = open_dataset(shared_data / "synthetic_room0")
    data_dir = tmp_path / "data"
    server = live_server(data_dir)
    sid, token, out = asyncio.run(_fly_and_land(server, dataset))
    assert not out["errors"], out["errors"]
    base = f"{server.url}/api/sessions/{sid}/flights"

    body = httpx.get(base, headers=auth(token)).json()
    strictly(FlightList, body)  # the documented models hold every field of the answers
    listed = body["flights"]
    for summary in listed:
        strictly(FlightSummary, summary)
    assert listed[0]["id"] == "1" and listed[0]["end"] == "landed" and listed[0]["finished"]
    flight = httpx.get(f"{base}/1.json", headers=auth(token)).json()
    strictly(FlightRecordingBody, flight)
    assert flight["format"] == "dronesim-flight/1" and flight["state_columns"] == list(
        STATE_COLUMNS
    )
    states = np.array([row[:-1] for row in flight["states"]], dtype=float)
    # 20 Hz: simulation time advances by the state period between rows (the flight thread
    # slows the drone rather than let it jump when starved, so allow a busy machine's spread).
    steps = np.diff(states[:, 0])
    assert abs(np.median(steps) - 0.05) < 0.01, np.median(steps)
    # (Two states may share a time: a step shorter than one physics step advances nothing.)
    assert np.all(steps >= 0) and np.all(steps <= 0.25 + 1e-6)
    rate = len(states) / flight["duration_s"]
    assert 15.0 < rate < 21.0, f"{rate:.1f} states/s"
    assert flight["duration_s"] > 2.0  # the sticks, the descent
    assert np.allclose(np.linalg.norm(states[:, 7:11], axis=1), 1.0, atol=1e-3)
    # The yaw by hand turned the drone: its attitude changed over the flight.
    assert abs(abs(np.dot(states[0, 7:11], states[-1, 7:11])) - 1.0) > 1e-3
    events = [e["event"] for e in flight["events"]]
    assert events[0] == "spawned" and events[-1] == "landed"
    names = [c["name"] for c in flight["commands"]]
    assert names.count("sticks") >= 0.8 * out["sticks_sent"] and names[-1] == "land"
    sticks = next(c for c in flight["commands"] if c["name"] == "sticks")
    assert sticks["sticks"] == [0, 0.5, 0, 0] and sticks["t"] >= flight["start_time_s"]
    assert flight["states"][-1][-1] == "landed"
    # One row per drone_state sent: every state the pilot got during the flight is a row
    # (a slow client may miss some: it gets only the newest), at the same place.
    rows = {row[0]: row for row in flight["states"]}
    during = [
        s for s in out["states"] if flight["start_time_s"] <= s["timestamp"] <= flight["end_time_s"]
    ]
    assert len(during) > 0.8 * len(flight["states"])
    for s in during:
        row = rows[round(s["timestamp"], 4)]
        position = proto.pose_matrix(s, "T_world_drone")[:3, 3]
        assert np.allclose(row[1:4], position, atol=1e-4) and row[-1] == s["mode"]

    csv_text = httpx.get(f"{base}/1.csv", headers=auth(token))
    assert csv_text.headers["content-type"].startswith("text/csv")
    rows = list(csv.reader(io.StringIO(csv_text.text)))
    assert rows[0] == list(STATE_COLUMNS) and len(rows) == len(flight["states"]) + 1
    assert float(rows[1][0]) == flight["states"][0][0]
    tum = httpx.get(f"{base}/1.tum", headers=auth(token))
    assert tum.status_code == 200 and tum.headers["content-type"].startswith("text/plain")
    path = tmp_path / "flight.tum"
    path.write_bytes(tum.content)
    path_tum = read_tum(path)  # the drone's path, in the frame of the session's trajectory.tum
    np.testing.assert_allclose(path_tum.poses[:, :3, 3], states[:, 1:4], atol=1e-9)

    # Bad flight ids and strangers: 404 / 401 as every session route.
    assert httpx.get(f"{base}/99.json", headers=auth(token)).status_code == 404
    bad = httpx.get(f"{base}/..%2Fmeta.json", headers=auth(token))
    assert bad.status_code == 404
    assert httpx.get(f"{base}/0.csv", headers=auth(token)).json()["error"]["code"] == "not_found"
    assert httpx.get(base).status_code == 401
    assert httpx.get(f"{base}/1.json").status_code == 401
    assert httpx.get(base, headers=auth("x" * 43)).status_code == 404

    # A restart: the session is saved and closed with its second flight in the air, which
    # ends with it; both flights download with the token from the new server.
    server.stop()
    again = live_server(data_dir)
    base = f"{again.url}/api/sessions/{sid}/flights"
    listed = httpx.get(base, headers=auth(token)).json()["flights"]
    assert [f["id"] for f in listed] == ["1", "2"]
    assert listed[1]["end"] == "session_end"
    second = httpx.get(f"{base}/2.json", headers=auth(token)).json()
    assert second["commands"][0]["name"] == "takeoff" and len(second["states"]) > 5
    assert httpx.get(f"{base}/1.json", headers=auth(token)).json() == flight
