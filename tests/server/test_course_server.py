"""A course through the real server: stream the small demo room (server/datasets/demo.py, the
page's demo), start a course with the autopilot over the WebSocket, see its gates passed and
the run finish, then find it in the session's best list over REST, before and after a restart
of the server."""

from __future__ import annotations

import asyncio

import httpx
import numpy as np

from server import protocol as proto
from server.datasets import open_dataset
from server.datasets.demo import demo_sequence_path
from server.simulation.config import SimulationConfig
from server.transport.schemas import CourseBest
from tests.conftest import auth
from tests.server.test_drone_server import drone_position, flight_map_caught_up, piloting


async def fly_a_course(server, dataset) -> dict:
    sid, token = server.create_session()
    async with piloting(server, sid, token, dataset, "course-test") as pilot:
        # The whole walk (every other frame: half the time, the same room seen).
        for i in range(0, len(dataset), 2):
            frame = dataset[i]
            await pilot.send(proto.make_frame(i, frame.timestamp, frame.colour, frame.depth))
            await pilot.wait_for("pose", seq=i)
        await pilot.wait_for("drone_event", event="spawned")
        await flight_map_caught_up(server, sid, token)
        # The easy preset with a few seeds: the map the server fused differs a little from run
        # to run (which frames it fused), and a course must fit in what it holds.
        for command_id, options in enumerate([{"difficulty": "easy", "seed": s} for s in range(4)]):
            await pilot.send(
                proto.make_command(command_id, "course_start", autopilot=True, **options)
            )
            while not (
                pilot.of("course", command_id=command_id)
                or pilot.of("error", command_id=command_id)
            ):
                await asyncio.sleep(0.05)
            if pilot.of("course", command_id=command_id):
                break
        try:
            finished = await pilot.wait_for(
                "course", timeout=60.0, state="finished", command_id=command_id
            )
        except AssertionError:
            events = [(e["event"], e["message"]) for e in pilot.of("drone_event")]
            raise AssertionError(f"the course did not finish; drone events: {events}") from None
        await asyncio.sleep(0.5)  # the drone flies on out of the last ring
        out = {
            "sid": sid,
            "token": token,
            "refusals": pilot.of("error"),
            "laid": pilot.of("course", command_id=command_id)[0],
            "finished": finished,
            "events": pilot.of("drone_event"),
            "states": pilot.of("drone_state"),
        }
    return out


def best(server, sid: str, token: str) -> CourseBest:
    r = httpx.get(f"{server.url}/api/sessions/{sid}/course/best", headers=auth(token))
    assert r.status_code == 200, r.text
    return CourseBest.model_validate(r.json())


def test_an_autopilot_course_over_the_wire_and_its_best_list_after_a_restart(live_server, tmp_path):
    from server.transport.routes_client import DEMO_PRESETS

    dataset = open_dataset(demo_sequence_path(DEMO_PRESETS["small"], progress=False), "tum")
    data_dir = tmp_path / "data"
    server = live_server(data_dir)
    out = asyncio.run(fly_a_course(server, dataset))
    for refusal in out["refusals"]:  # a refusal is a clear bad_command, naming the course
        assert refusal["name"] == "bad_command" and "course" in refusal["message"], refusal

    laid, finished = out["laid"], out["finished"]
    n = len(laid["gates"]) // 7
    assert laid["state"] == "running" and laid["autopilot"] and n >= 2
    gates = np.array(laid["gates"]).reshape(n, 7)
    np.testing.assert_allclose(np.linalg.norm(gates[:, 3:6], axis=1), 1.0, atol=1e-9)
    events = out["events"]
    passed = [e for e in events if e["event"] == "gate_passed"]
    assert len(passed) == n and not [e for e in events if e["event"] == "gate_missed"]
    assert not [e for e in events if e["event"] in ("collision", "crash")]
    # Each pass was reported where the drone went through that ring (world frame).
    for k, event in enumerate(passed):
        centre, radius = gates[k, :3], gates[k, 6]
        assert np.linalg.norm(np.array(event["position"]) - centre) <= radius + 1e-6
    (done,) = [e for e in events if e["event"] == "course_finished"]
    assert f"score {finished['score']}" in done["message"]
    assert finished["gate_states"] == ["passed"] * n and finished["rank"] == 1
    assert finished["score"] >= 140 * n  # all gates, about par
    radius = SimulationConfig().radius_m
    assert min(s["clearance"] for s in out["states"]) >= radius
    # The drone flew the route the course message drew: out through the last ring's plane.
    last = drone_position(out["states"][-1]) - gates[-1, :3]
    assert last @ gates[-1, 3:6] > 0

    listed = best(server, out["sid"], out["token"])
    assert len(listed.results) == 1
    result = listed.results[0]
    assert result.score == finished["score"] and result.passed == n and result.autopilot
    assert (
        result.time_s == round(finished["elapsed_s"], 3)
        or abs(result.time_s - finished["elapsed_s"]) < 1e-3
    )

    # The flight recording holds the course and its result: the finished course ended it.
    flights = f"{server.url}/api/sessions/{out['sid']}/flights"
    listed_flights = httpx.get(flights, headers=auth(out["token"])).json()["flights"]
    (flown,) = [f for f in listed_flights if f["end"] == "course_finished"]
    recording = httpx.get(f"{flights}/{flown['id']}.json", headers=auth(out["token"])).json()
    assert recording["course"]["gates"] == laid["gates"]
    assert recording["course"]["seed"] == laid["seed"]
    assert recording["result"]["score"] == finished["score"] == flown["result"]["score"]
    assert recording["result"]["gates_passed"] == n and recording["result"]["gates_missed"] == 0

    # A restart: the server stops (saving the session), a new one reads the same folder.
    server.stop()
    again = live_server(data_dir)
    assert best(again, out["sid"], out["token"]).results == listed.results
    r = httpx.get(f"{again.url}/api/sessions/{out['sid']}/course/best", headers=auth("x" * 43))
    assert r.status_code == 404  # the token still guards it

    # The session left a room; a return visit to it has the room's best list to beat.
    r = httpx.post(
        f"{again.url}/api/sessions", json={"room": out["sid"]}, headers=auth(out["token"])
    )
    assert r.status_code == 201, r.text
    visit = r.json()
    assert best(again, visit["id"], visit["token"]).results == listed.results
