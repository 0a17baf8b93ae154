"""Flight recordings: the recorder's flights, and a real session's flights over REST, kept across
a restart."""

from __future__ import annotations

import asyncio
import csv
import io
import json
import time

import httpx
import numpy as np
from conftest import auth
from test_drone_server import piloting
from test_openapi import strictly

from server import protocol as proto
from server.datasets import open_dataset
from server.evaluation.trajectory import read_tum
from server.sessions.flight_store import FlightLog, read_flight, read_index
from server.sessions.store import SessionStore
from server.simulation.flight_recording import STATE_COLUMNS, FlightRecorder, states_csv
from server.transport.schemas import FlightList, FlightRecordingBody, FlightSummary

FRAMES = 24


def _pose(x: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = [x, 0.0, 1.0]
    return T


def test_a_flight_opens_in_the_air_closes_on_the_ground_and_carries_its_course(tmp_path):
    store = SessionStore(tmp_path)
    log = FlightLog(store, "0123456789abcdef", state_hz=20.0, max_flight_s=1.0, flights_kept=2)
    rec = log.recorder
    course = {"gates": [{"centre": [1.0, 0.0, 1.0], "radius_m": 0.4}], "difficulty": "easy"}
    rec.set_course(course)
    rec.state(0.0, _pose(0.0), np.zeros(3), "landed")  # on the ground: no flight
    rec.command(0.0, "sticks", 1, {"sticks": [0.1, 0, 0, 0]})  # not kept: nothing is open
    assert read_index(store, "0123456789abcdef") == []
    rec.command(0.05, "takeoff", 2, {"target": None})
    for k in range(1, 31):  # 1.5 s at 20 Hz: beyond max_flight_s, so truncated at 20 rows
        rec.state(0.05 * k, _pose(0.1 * k), np.array([2.0, 0, 0]), "hover")
    rec.event(1.5, "collision", np.array([3.0, 0, 1]), "touched", None)
    result = {"time_s": 1.5, "gates_passed": 1, "gates_missed": 0, "collisions": 1, "score": 87}
    rec.finish(result)
    rec.state(1.55, _pose(3.0), np.zeros(3), "hover")  # still flying: the next flight opens
    stale = rec.open_flight()  # a snapshot's copy, saved only after the flight ended:
    log.save_open()
    rec.state(1.6, _pose(3.0), np.zeros(3), "landed")  # and lands
    log.save(stale)  # it does not overwrite the ended flight

    index = read_index(store, "0123456789abcdef")
    assert [f["id"] for f in index] == ["1", "2"]
    first = read_flight(store, "0123456789abcdef", "1")
    assert first["end"] == "course_finished" and first["finished"]
    assert first["course"] == course and first["result"] == result
    assert index[0]["result"] == result and index[0]["has_course"]
    assert first["truncated"] and len(first["states"]) == 20
    assert [c["name"] for c in first["commands"]] == ["takeoff"]
    assert first["commands"][0] == {"t": 0.05, "name": "takeoff", "id": 2}
    assert first["events"][0]["event"] == "collision"
    assert first["states"][0][: len(STATE_COLUMNS) - 1] == [0.05, 0.1, 0, 1, 2, 0, 0, 0, 0, 0, 1]
    second = read_flight(store, "0123456789abcdef", "2")
    assert second["end"] == "landed" and second["states"][-1][-1] == "landed"
    assert second["course"] == course and second["result"] is None

    rows = list(csv.reader(io.StringIO(states_csv(first))))
    assert tuple(rows[0]) == STATE_COLUMNS and len(rows) == 21

    # flights_kept=2: a third flight drops the first; a new recorder numbers on.
    rec.state(2.0, _pose(0.0), np.zeros(3), "manual")
    rec.state(2.05, _pose(0.0), np.zeros(3), "faulted")
    assert [f["id"] for f in read_index(store, "0123456789abcdef")] == ["2", "3"]
    assert not (store.folder("0123456789abcdef") / "flights" / "1.json").exists()
    again = FlightLog(store, "0123456789abcdef", 20.0, 1.0, 2)
    again.recorder.state(0.0, _pose(0.0), np.zeros(3), "hover")
    again.close()
    assert read_index(store, "0123456789abcdef")[-1]["id"] == "4"


def test_a_flights_path_reads_back_as_a_tum_trajectory_in_the_world_frame(tmp_path):
    """states_tum: ``t x y z qx qy qz qw`` per state, T_world_drone, as read_tum and evo read
    a session's trajectory.tum."""
    from evo.tools import file_interface
    from scipy.spatial.transform import Rotation

    from server.simulation.flight_recording import states_tum

    store = SessionStore(tmp_path)
    log = FlightLog(store, "0123456789abcdef", state_hz=20.0, max_flight_s=10.0, flights_kept=2)
    poses = []
    for k in range(10):
        T = _pose(0.1 * k)
        T[:3, :3] = Rotation.from_euler("z", 9 * k, degrees=True).as_matrix()
        poses.append(T)
        log.recorder.state(0.05 * (k + 1), T, np.zeros(3), "hover" if k < 9 else "landed")
    text = states_tum(read_flight(store, "0123456789abcdef", "1"))
    assert text.startswith("# timestamp tx ty tz qx qy qz qw (T_world_drone")
    (tmp_path / "flight.tum").write_text(text)
    flight = read_tum(tmp_path / "flight.tum")
    np.testing.assert_allclose(flight.timestamps, 0.05 * np.arange(1, 11), atol=1e-9)
    np.testing.assert_allclose(flight.poses, np.array(poses), atol=1e-4)  # 4 decimals kept
    assert file_interface.read_tum_trajectory_file(tmp_path / "flight.tum").num_poses == 10


def test_a_minute_of_flight_takes_the_documented_bytes():
    """docs/SERVER.md: about 110 kB per minute of states, about 45 kB more per minute of sticks at
    10 Hz; the figures come from this flight (random poses, full-precision numbers)."""
    from server.geometry import exp_se3

    ended = []
    rec = FlightRecorder(20.0, 600.0, ended.append)
    rng = np.random.default_rng(0)
    for k in range(1200):  # 60 s at 20 Hz
        t = 3.2173 + 0.05 * k
        pose = exp_se3(np.r_[rng.normal(size=3) * 0.3, rng.normal(size=3) * 1.5])
        rec.state(t, pose, rng.normal(size=3), "manual")
        if k % 2 == 0:
            rec.command(t, "sticks", 1000 + k, {"sticks": list(rng.uniform(-1, 1, 4).round(3))})
    rec.close()
    flight = ended[0].as_dict()
    with_sticks = len(json.dumps(flight, separators=(",", ":")))
    flight["commands"] = []
    states_only = len(json.dumps(flight, separators=(",", ":")))
    assert 90e3 < states_only < 130e3, states_only
    assert 30e3 < with_sticks - states_only < 60e3, with_sticks - states_only


def test_a_recorder_without_a_flight_records_nothing():
    ended = []
    rec = FlightRecorder(20.0, 10.0, ended.append)
    rec.state(0.0, _pose(0.0), np.zeros(3), "landed")
    assert rec.finish({"score": 1}) is None and rec.close() is None and ended == []
    assert rec.open_flight() is None


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
