"""A shared room's race: the owner lays one course (its drone's session plans it, not started),
and after a countdown every phone of the room flies those same gates, each from where its drone
is, each judged by its own session as any course is (server/sessions/runtime/course_control.py).
The room's standings follow each pilot's course messages: gates passed and missed, time, and a
rank for each pilot who finished, the fastest first.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from server.sessions.web.live import LiveSession

COUNTDOWNS_S = (0.0, 30.0)  # the countdown an owner may ask for, seconds


@dataclass
class Race:
    """One race of a room. gates: (N, 7) world frame rows (centre, unit normal, ring radius;
    metres); starts_at: when the countdown ends (monotonic clock); pilots: the sessions it was
    started for, and refused: those whose course could not be laid, with why."""

    number: int
    gates: np.ndarray
    difficulty: str
    seed: int
    autopilot: bool
    starts_at: float
    started_at: float | None = None
    started_at_unix: float | None = None  # the same moment, Unix seconds (the server's clock)
    pilots: list[str] = field(default_factory=list)
    refused: dict[str, str] = field(default_factory=dict)
    recorded: bool = False  # its record was written once it finished (race_results.py)

    def due(self, now: float) -> bool:
        """The countdown is over and the race not started yet."""
        return self.started_at is None and now >= self.starts_at

    def standings(self, members: list[LiveSession], now: float) -> dict:
        """The room message's race fields for ``members``, in the message's order: each
        pilot's course as its latest course message since the start says."""
        n = len(members)
        passed, missed, finished = [0] * n, [0] * n, [False] * n
        time_s, ended = [0.0] * n, [False] * n
        for i, member in enumerate(members):
            course = member.latest_course
            if self.started_at is None or course is None or course[0] < self.started_at:
                ended[i] = member.id not in self.pilots or member.id in self.refused
                continue
            message = course[1]
            passed[i] = message["gate_states"].count("passed")
            missed[i] = message["gate_states"].count("missed")
            time_s[i] = float(message["elapsed_s"])
            finished[i] = message["state"] == "finished"
            ended[i] = message["state"] != "running"
        if self.started_at is None:
            state = "countdown"
        else:
            state = "finished" if all(ended) else "running"
        return {
            "race": state,
            "number": self.number,
            "starts_in_s": max(0.0, self.starts_at - now),
            "gates": len(self.gates),
            "passed": passed,
            "missed": missed,
            "time_s": time_s,
            "finished": finished,
            "rank": ranks(finished, time_s),
        }


def ranks(finished: list[bool], time_s: list[float]) -> list[int]:
    """1 for the fastest pilot who finished, 2 for the next, ...; 0 for those who did not."""
    order = sorted((t, i) for i, (done, t) in enumerate(zip(finished, time_s, strict=True)) if done)
    rank = [0] * len(finished)
    for place, (_, i) in enumerate(order, start=1):
        rank[i] = place
    return rank


def race_record(
    race: Race, owner_id: str, members: list[LiveSession], standings: dict, ended_at: float
) -> dict:
    """The record of a finished race (server/sessions/race_results.py), from its standings
    over ``members`` (in the standings' order); ``ended_at``: Unix seconds."""
    pilots = []
    for i, member in enumerate(members):
        course = member.latest_course
        crashes = 0
        if race.started_at is not None and course is not None and course[0] >= race.started_at:
            crashes = course[1]["crashes"]
        pilots.append(
            {
                "session": member.id,
                "name": member.client_name,
                "passed": standings["passed"][i],
                "missed": standings["missed"][i],
                "time_s": round(standings["time_s"][i], 3),
                "crashes": int(crashes),
                "finished": standings["finished"][i],
                "rank": standings["rank"][i],
            }
        )
    return {
        "number": race.number,
        "difficulty": race.difficulty,
        "seed": race.seed,
        "gates": [round(float(v), 4) for v in race.gates.ravel()],
        "started_at": race.started_at_unix,
        "ended_at": ended_at,
        "owner": owner_id,
        "pilots": pilots,
    }
