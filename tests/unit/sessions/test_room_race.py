"""A room's race standings (server/sessions/web/room_race.py) from its pilots' course messages."""

from __future__ import annotations

import numpy as np

from server.sessions.web.live import LiveSession
from server.sessions.web.room_race import Race, ranks


class _Worker:
    dropped = 0


def _pilot(sid: str, course: dict | None, at: float = 5.0) -> LiveSession:
    session = LiveSession(sid, "hash", 0.0, lambda _: _Worker())
    session.latest_course = None if course is None else (at, course)
    return session


def _course(state: str, gates: list[str], elapsed: float) -> dict:
    return {"type": "course", "state": state, "gate_states": gates, "elapsed_s": elapsed}


def test_ranks_go_to_those_who_finished_fastest_first():
    assert ranks([True, False, True], [9.0, 1.0, 7.5]) == [2, 0, 1]
    assert ranks([False, False], [1.0, 2.0]) == [0, 0]


def test_standings_count_down_then_follow_each_pilots_course_since_the_start():
    race = Race(1, np.zeros((3, 7)), "easy", 7, False, starts_at=4.0)
    before = _course("finished", ["passed"] * 3, 3.0)  # a course of its own, before the race
    pilots = [_pilot("a", before, at=1.0), _pilot("b", None)]
    counting = race.standings(pilots, now=3.0)
    assert counting["race"] == "countdown" and counting["starts_in_s"] == 1.0
    assert counting["passed"] == [0, 0] and counting["rank"] == [0, 0]
    assert race.due(4.0) and not race.due(3.9)
    race.started_at, race.pilots = 4.0, ["a", "b"]
    pilots = [
        _pilot("a", _course("running", ["passed", "pending", "pending"], 2.0)),
        _pilot("b", _course("finished", ["passed", "missed", "passed"], 6.5)),
    ]
    running = race.standings(pilots, now=6.0)
    assert running["race"] == "running" and running["passed"] == [1, 2]
    assert running["missed"] == [0, 1] and running["rank"] == [0, 1]
    pilots[0].latest_course = (7.0, _course("finished", ["passed"] * 3, 5.0))
    done = race.standings(pilots, now=8.0)
    assert done["race"] == "finished" and done["rank"] == [1, 2] and done["finished"] == [True] * 2
