"""A shared room's finished races, on disk: each race's record (``races.json``) and the room's
best list (``race_best.json``), written into the folder of every pilot's session when a race
ends (server/sessions/web/shared_rooms.py), so that each pilot's token reads them later, live
or saved.

The room's best list travels with the room as the course best list does: the owner's session
links it into its saved room (``RoomWriter.save``) and a session continuing in that room starts
from it (``drone_setup.inherit_best``), so pilots race the room's times of earlier days.

A record (``races.json``'s ``races``, oldest first)::

    {number, difficulty, seed, gates: [N x 7 floats: centre, unit normal, ring radius, world
     frame, metres], started_at, ended_at (Unix seconds, the server's clock), owner,
     pilots: [{session, name, passed, missed, time_s, crashes, finished, rank}]}

A best-list entry (one per pilot who finished a race), best first: fewest gates missed, then
the fastest, then the earlier::

    {pilot, session, race, time_s, gates, missed, crashes, difficulty, seed, finished_at}
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from server.sessions.runtime.course_control import read_best, read_records, write_records

RACES_FILE = "races.json"  # in each pilot's session folder
RACE_BEST_FILE = "race_best.json"  # in each pilot's session folder, and in a saved room
RACES_KEPT = 100  # records kept per session, the newest
BEST_KEPT = 10


def read_races(path: Path) -> list[dict[str, Any]]:
    """The race records in ``path``, oldest first; [] when there are none or it is unreadable."""
    return read_records(path, "races", "the race records")


def ranked(results: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Fewest gates missed first, then the fastest, then the earlier."""
    return sorted(results, key=lambda r: (r["missed"], r["time_s"], r["finished_at"]))


def best_entries(record: dict[str, Any]) -> list[dict[str, Any]]:
    """The best-list entries of a race record: one per pilot who finished."""
    return [
        {
            "pilot": p["name"],
            "session": p["session"],
            "race": record["number"],
            "time_s": p["time_s"],
            "gates": len(record["gates"]) // 7,
            "missed": p["missed"],
            "crashes": p["crashes"],
            "difficulty": record["difficulty"],
            "seed": record["seed"],
            "finished_at": record["ended_at"],
        }
        for p in record["pilots"]
        if p["finished"]
    ]


def keep_race(folder: Path, record: dict[str, Any], room_best: list[dict[str, Any]]) -> None:
    """Add ``record`` to the session folder's race records, and write ``room_best`` (the
    room's best list, this race's entries in it) as its best list. Raises OSError."""
    races = [*read_races(folder / RACES_FILE), record][-RACES_KEPT:]
    write_records(folder / RACES_FILE, "races", races)
    write_best(folder / RACE_BEST_FILE, room_best)


def write_best(path: Path, room_best: list[dict[str, Any]]) -> None:
    """The room's best list into ``path`` (a session's, or a saved room's). Raises OSError."""
    write_records(path, "results", room_best)


def room_best_with(folder: Path, record: dict[str, Any]) -> list[dict[str, Any]]:
    """The best list in ``folder`` (the room owner's session) with ``record``'s finishers."""
    return ranked([*read_best(folder / RACE_BEST_FILE), *best_entries(record)])[:BEST_KEPT]


def race_record_named(folder: Path, number: int) -> dict[str, Any] | None:
    """The session's latest record of race ``number``, or None."""
    matches = [r for r in read_races(folder / RACES_FILE) if r.get("number") == number]
    return matches[-1] if matches else None


def flights_in(index: list[dict[str, Any]], record: dict[str, Any]) -> list[str]:
    """The ids of the flights (a session's flight index, server/sessions/flight_store.py) that
    were open during the race: opened before it ended, and closed after it started (both on
    the server's wall clock; a flight's simulation time runs at the wall clock's pace)."""
    start, end = record["started_at"], record["ended_at"]
    return [
        f["id"]
        for f in index
        if f["started_at"] <= end and f["started_at"] + f["duration_s"] >= start
    ]
