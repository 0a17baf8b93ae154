"""A shared room's races in the Flights dialog, in a real browser: the room's best list and the
races this session flew in, and "Replay together", which flies every pilot's recorded flights
again over the map on the race's clock, each drone in its pilot's colour at the pixel where its
recorded pose projects, and stops by itself at the end.

A real race takes about 40 s to fly (tests/server/test_shared_rooms_server.py flies one); here
two pilots' sessions are saved on disk by the project's own writers, as a server leaves them:
their flights through the flight store's recorder (server/sessions/flight_store.py), fed drone
states on a wall clock of the test's, and two finished races with the room's best list through
server/sessions/race_results.py, from the standings and records the room itself makes
(server/sessions/web/room_race.py). A server started on that data dir loads them as saved
sessions; the page opens one of them as its own (its id and token where a page keeps them).
"""

from __future__ import annotations

import json
import time
from types import SimpleNamespace

import cv2
import httpx
import numpy as np

from server.sessions.flight_store import FlightLog, read_flight, read_index
from server.sessions.race_results import keep_race, room_best_with
from server.sessions.store import SessionStore, hash_token
from server.sessions.web.room_race import Race, race_record
from server.simulation import flight_recording
from tests.conftest import auth
from tests.support.browser import DESKTOP, count_near

ALICE, BOB = "0123456789abc0a1", "0123456789abc0b2"  # alice owns the room
TOKENS = {ALICE: "alice-token-for-the-race-replay-test", BOB: "bob-token-for-the-race-replay-test"}
HZ = 20.0
T0 = float(int(time.time()) - 3600)  # race 2's start, Unix s (an hour ago)
END_S = 5.3  # race 2 ends this long after its start: the last pilot finished
# Three gates along world x (y points down: heights are -y), centre, unit normal, ring radius.
GATES = [
    [-1.0, -1.0, 1.9, 1, 0, 0, 0.4],
    [0.0, -1.2, 1.9, 1, 0, 0, 0.4],
    [1.0, -1.0, 1.9, 1, 0, 0, 0.4],
]
# Level, nose along world +x, body z up (world -y): T_world_drone's rotation.
R_LEVEL = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])
# Each flight: (seconds from race 2's start, position) waypoints, straight lines between them;
# it opens in the air at its first and closes landed at its last. The sessions' simulation
# clocks differ: alice's time 0 was 30 s before the race, bob's 100 s.
FLIGHTS = {
    ALICE: (
        30.0,
        [[(-2.0, (-2.0, 0.0, 2.1)), (-0.5, (-2.0, -1.0, 2.1)), (0.0, (-2.0, -1.0, 2.1)),
          (4.2, (2.0, -1.0, 2.1)), (5.5, (2.0, 0.0, 2.1))]],
    ),
    BOB: (
        100.0,
        [[(-60.0, (0.0, 0.0, 0.5)), (-58.0, (0.0, -0.5, 0.5)), (-56.0, (0.0, 0.0, 0.5))],  # before
         [(-1.5, (-2.0, 0.0, 1.6)), (-0.5, (-2.0, -1.0, 1.6)), (2.0, (-0.5, -1.0, 1.6)),
          (2.5, (-0.5, 0.0, 1.6))],  # down at 2.5 s; on again past the last gate passed
         [(3.0, (0.3, 0.0, 1.6)), (3.5, (0.3, -1.0, 1.6)), (5.1, (2.0, -1.0, 1.6)),
          (6.0, (2.0, 0.0, 1.6))]],
    ),
}  # fmt: skip
COLOURS = [0x00C8FF, 0xFF9A00]  # room_pilots.js: pilot 0 sky blue, pilot 1 orange
REPLAY = "window.dronesim.snapshot().raceReplay"


def _record_flights(store: SessionStore, sid: str, monkeypatch) -> None:
    """The session's flights as its worker records them: drone states at HZ into a FlightLog,
    the recorder's wall clock (a flight's started_at) running with the simulation's."""
    spawn, flights = FLIGHTS[sid]
    wall = [0.0]
    with monkeypatch.context() as m:
        m.setattr(flight_recording, "time", SimpleNamespace(time=lambda: wall[0]))
        log = FlightLog(store, sid, state_hz=HZ, max_flight_s=120.0, flights_kept=20)
        for waypoints in flights:
            times = [w[0] for w in waypoints]
            n = int(round((times[-1] - times[0]) * HZ))
            for k in range(n + 1):
                t_race = times[0] + k / HZ
                T = np.eye(4)
                T[:3, :3] = R_LEVEL
                T[:3, 3] = [
                    np.interp(t_race, times, [w[1][i] for w in waypoints]) for i in range(3)
                ]
                wall[0] = T0 + t_race
                mode = "landed" if k == n else "manual"  # the landing closes the flight
                log.recorder.state(t_race + spawn, T, np.zeros(3), mode)


def _finish_race(folders: dict, number: int, start: float, length: float, results: dict) -> None:
    """A finished race as the room keeps it (SharedRooms._keep_race): the standings of each
    pilot's last course message, the record, the room's best list with it, into each folder."""
    race = Race(number, np.array(GATES), "easy", 7, False, 0.0, 0.0, start, [ALICE, BOB])
    members = []
    for sid, (name, time_s, missed, crashes) in results.items():
        states = ["passed"] * (len(GATES) - missed) + ["missed"] * missed
        course = dict(gate_states=states, elapsed_s=time_s, state="finished", crashes=crashes)
        members.append(SimpleNamespace(id=sid, client_name=name, latest_course=(1.0, course)))
    record = race_record(race, ALICE, members, race.standings(members, 1.0), start + length)
    best = room_best_with(folders[ALICE], record)
    for folder in folders.values():
        keep_race(folder, record, best)


def _saved_room(data_dir, monkeypatch) -> SessionStore:
    store = SessionStore(data_dir)
    folders = {sid: store.folder(sid) for sid in (ALICE, BOB)}
    for sid, folder in folders.items():
        folder.mkdir(parents=True)
        meta = {"id": sid, "token_sha256": hash_token(TOKENS[sid]), "created_at": T0 - 200}
        store.write_meta(sid, meta | {"closed": True, "status": {"id": sid, "closed": True}})
        _record_flights(store, sid, monkeypatch)
    # Race 1, ten minutes earlier (no flight recorded then): alice missed a gate, so bob's
    # slower time ranks above hers in the best list; race 2: both fly all gates.
    _finish_race(folders, 1, T0 - 600, 7.0, {ALICE: ("alice", 6.0, 1, 0), BOB: ("bob", 6.5, 0, 0)})
    _finish_race(folders, 2, T0, END_S, {ALICE: ("alice", 4.2, 0, 0), BOB: ("bob", 5.1, 0, 1)})
    return store


def _expected(store: SessionStore, sid: str, wall: float) -> np.ndarray:
    """Where the pilot's recorded flights put its drone at wall clock ``wall`` (Unix s): in the
    latest flight opened by then (a row's wall clock: started_at + t - start_time_s), its
    position interpolated between rows, held at the ends; computed here, from the files."""
    flights = [read_flight(store, sid, f["id"]) for f in read_index(store, sid)]
    opened = [f for f in flights if f["started_at"] <= wall] or flights[:1]
    flight = max(opened, key=lambda f: f["started_at"])
    rows = np.array([r[:4] for r in flight["states"]], float)
    t = flight["start_time_s"] + wall - flight["started_at"]
    return np.array([np.interp(t, rows[:, 0], rows[:, i]) for i in (1, 2, 3)])


def _pixel(camera: dict, p: np.ndarray) -> tuple[float, float]:
    """A world point's place on the page (CSS px) through the map's camera: its projection and
    view matrices (three.js's, column-major) onto its canvas."""
    P = np.array(camera["projection"]).reshape(4, 4).T
    V = np.array(camera["view"]).reshape(4, 4).T
    clip = P @ V @ np.append(p, 1.0)
    assert clip[3] > 0, "behind the map's camera"
    x, y = clip[:2] / clip[3]
    c = camera["canvas"]
    return c["left"] + (x + 1) / 2 * c["width"], c["top"] + (1 - y) / 2 * c["height"]


def _paint(rgb: np.ndarray, colour: int) -> np.ndarray:
    """Pixels near a drone paint's hue, lit or in shade (room_pilots.js's colours)."""
    want = np.array([[[(colour >> 16) & 255, (colour >> 8) & 255, colour & 255]]], np.uint8)
    hue = int(cv2.cvtColor(want, cv2.COLOR_RGB2HSV)[0, 0, 0])
    hsv = cv2.cvtColor(rgb, cv2.COLOR_RGB2HSV).astype(int)
    dh = np.minimum(abs(hsv[..., 0] - hue), 180 - abs(hsv[..., 0] - hue))
    return (dh <= 8) & (hsv[..., 1] > 150) & (hsv[..., 2] > 90)


def test_the_flights_dialog_lists_the_rooms_races_and_replays_one_with_every_pilot(
    live_server, open_page, tmp_path, monkeypatch
):
    store = _saved_room(tmp_path / "data", monkeypatch)
    server = live_server(tmp_path / "data")
    r = httpx.get(f"{server.url}/api/sessions/{ALICE}/races/2/flights", headers=auth(TOKENS[ALICE]))
    assert r.status_code == 200, r.text
    assert [len(p["flights"]) for p in r.json()["pilots"]] == [1, 2]  # bob's early flight: not

    # The page of alice's saved session: its id and token where the page keeps them.
    saved = json.dumps({"id": ALICE, "token": TOKENS[ALICE]})
    keep = f"sessionStorage.setItem('dronesim.session', {json.dumps(saved)})"
    page = open_page(server, "/?view=map", init=lambda c: c.add_init_script(keep), **DESKTOP)
    page.page.click("#btn-flights")
    page.wait("document.querySelectorAll('#race-list li').length === 2", 10, "the races")
    races = page.snapshot()["races"]
    assert races["shown"] and page.page.is_visible("#races")
    assert races["listed"] == [
        "Race 2 (easy, 3 gates): #1 alice 4.2 s · #2 bob 5.1 s (1 crash)",
        "Race 1 (easy, 3 gates): #1 alice 6.0 s (1 missed) · #2 bob 6.5 s",
    ], races["listed"]
    # The best list: fewest gates missed first, then the fastest.
    assert races["bestListed"] == [
        "1. alice · 4.2 s · 0 missed · 0 crashes · easy · race 2",
        "2. bob · 5.1 s · 0 missed · 1 crash · easy · race 2",
        "3. bob · 6.5 s · 0 missed · 0 crashes · easy · race 1",
        "4. alice · 6.0 s · 1 missed · 0 crashes · easy · race 1",
    ], races["bestListed"]
    colours = page.page.eval_on_selector_all(
        "#race-list li[data-race='2'] .race-pilot",
        "(els) => els.map((e) => [e.dataset.pilot, getComputedStyle(e).color])",
    )
    assert colours == [["0", "rgb(0, 200, 255)"], ["1", "rgb(255, 154, 0)"]], colours
    page.screenshot("race-list.png")

    # Replay together: both drones on the race's clock, from a second before its start.
    page.page.click("#race-list li[data-race='2'] button:text('Replay together')")
    page.wait(f"{REPLAY}.playing && {REPLAY}.raceTime > 0.3", 10, "the replay")
    first = page.snapshot()["raceReplay"]
    assert first["race"] == 2 and first["gates"] == len(GATES)
    assert not page.page.is_visible("#flights")  # the dialog closed for the map
    assert np.isclose(first["from"], T0 - 1) and np.isclose(first["to"], T0 + END_S + 1)
    assert first["label"].startswith("race 2 replay ") and page.page.is_visible("#race-replay")
    page.wait(f"{REPLAY}.raceTime > {first['raceTime']} + 1.0", 15, "the replay's clock")
    later = page.snapshot()["raceReplay"]
    for s in (first, later):
        for sid, drone in zip((ALICE, BOB), s["drones"], strict=True):
            assert drone["visible"], drone
            want = _expected(store, sid, s["clock"])
            assert np.allclose(drone["position"], want, atol=2e-3), (s["clock"], drone, want)
    for a, b in zip(first["drones"], later["drones"], strict=True):
        assert np.linalg.norm(np.subtract(b["position"], a["position"])) > 0.3, (a, b)

    # Held: each drone in its pilot's colour where its recorded pose projects on the map.
    page.page.click("[data-race-replay=pause]")
    page.wait(f"{REPLAY}.paused && {REPLAY}.drawnAt > {REPLAY}.pausedAt", 10, "a held draw")
    s = page.snapshot()["raceReplay"]
    assert s["label"].endswith("(paused)"), s["label"]
    rgb = page.screenshot("race-replay.png")
    for sid, drone, colour in zip((ALICE, BOB), s["drones"], COLOURS, strict=True):
        expected = _expected(store, sid, s["clock"])
        assert np.allclose(drone["position"], expected, atol=2e-3), (drone, expected)
        xy = _pixel(s["camera"], expected)
        c = s["camera"]["canvas"]
        assert (
            c["left"] < xy[0] < c["left"] + c["width"] and c["top"] < xy[1] < c["top"] + c["height"]
        )
        near, around = (count_near(_paint(rgb, colour), xy, r) for r in (12, 40))
        assert near > 50 and near >= 0.9 * around, (drone, xy, near, around)  # centred there
    xy_alice = _pixel(s["camera"], _expected(store, ALICE, s["clock"]))
    assert count_near(_paint(rgb, COLOURS[1]), xy_alice, 6) == 0  # not bob's drone there

    # It runs on to the end and stops by itself: the drones and the clock gone.
    page.page.click("[data-race-replay=pause]")
    page.wait(f"!{REPLAY}.playing && {REPLAY}.ended", END_S + 15, "the replay's end")
    s = page.snapshot()["raceReplay"]
    assert not any(d["visible"] for d in s["drones"]) and s["gates"] == 0 and s["label"] is None
    assert not page.page.is_visible("#race-replay")
    assert not page.errors, page.errors
