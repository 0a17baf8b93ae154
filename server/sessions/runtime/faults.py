"""Fault injection for tests: make a session's stages fail on chosen calls, inside whichever
process hosts the session (the faults travel to it in ``HostArgs.faults``)."""

from __future__ import annotations

import functools
from collections.abc import Collection, Mapping

from server.errors import DroneSimError


class InjectedFault(DroneSimError):
    """A failure a test asked for. None of the errors a session answers with a code of its own
    (``SessionError``, ``ProtocolError``, ``SnapshotError``, ``MapError``): each stage meets it
    as the unexpected failure it stands for."""


class InjectedThreadDeath(BaseException):
    """Escapes every ``except Exception``: what ends a worker thread outright."""


def inject(session, faults: Mapping[str, Collection[int]]) -> None:
    """Make stages of a configured ``session`` raise on the given calls (1-based). Stages:
    ``track`` (the tracker), ``fuse`` (the map), ``flight_step`` (one step of the drone's
    thread), ``mapping_thread`` (ends the mapping thread at that fusion), ``loop_keyframe``
    (the loop closer, on a keyframe), ``rebuild`` (a step of the map's rebuild after a loop)."""
    loops = session.loops
    stages = {
        "track": (session.tracker, "track", InjectedFault),
        "fuse": (session.mapper, "fuse", InjectedFault),
        "loop_keyframe": (None if loops is None else loops.closer, "add_keyframe", InjectedFault),
        "rebuild": (session.mapper, "rebuild_step", InjectedFault),
        "flight_step": (session.flight, "_tick", InjectedFault),
        "mapping_thread": (session.mapper, "fuse", InjectedThreadDeath),
    }
    for stage, calls in faults.items():
        owner, name, error = stages[stage]
        setattr(owner, name, _failing(getattr(owner, name), set(calls), error, stage))


def _failing(method, calls: set[int], error: type[BaseException], stage: str):
    count = 0

    @functools.wraps(method)
    def wrapper(*args, **kwargs):
        nonlocal count
        count += 1
        if count in calls:
            raise error(f"injected {stage} failure (call {count})")
        return method(*args, **kwargs)

    return wrapper
