"""Flight recordings: the recorder's flights (a real session's flights over REST, kept across a
restart: tests/server/test_flight_recordings_server.py)."""

from __future__ import annotations

import csv
import io
import json

import numpy as np

from server.evaluation.trajectory import read_tum
from server.sessions.flight_store import FlightLog, read_flight, read_index
from server.sessions.store import SessionStore
from server.simulation.flight_recording import STATE_COLUMNS, FlightRecorder, states_csv


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
