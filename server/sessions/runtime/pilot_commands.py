"""The pilot's drone commands, given in the client's world, carried out by the simulator in the
flight frame; its refusals are told back in the client's world (``CommandRefused``).

The caller holds the flight's lock (server/sessions/runtime/flight.py) and has checked what a
command needs of the flight (a drone that spawned, no fault); a tapped pixel arrives as the world
point it shows (camera_frames.py).
"""

from __future__ import annotations

import numpy as np

from server.sessions.errors import CommandRefused
from server.sessions.runtime.flight_view import FlightView
from server.simulation.drone import DroneSimulator
from server.simulation.drone_types import DroneCommandError
from server.simulation.route import PlanningError

TAP_SLACK_M = 0.6  # a tapped target may move this far to the nearest reachable point, m

_REFUSALS = {  # PlanningError reasons, for the pilot
    "goal_blocked": "inside or too close to an obstacle, or in space the camera has not seen",
    "outside_map": "outside the mapped space",
    "unreachable": "no collision-free route reaches it",
    "start_blocked": "the drone has no room to move",
    "not_finite": "not three finite numbers",
}


def _xyz(p: np.ndarray) -> str:
    return "(" + ", ".join(f"{v:.2f}" for v in p) + ") m"


def carry_out(
    sim: DroneSimulator,
    view: FlightView,
    name: str,
    command_id: int,
    *,
    target=None,
    sticks=None,
    speed=None,
    flight_mode=None,
) -> None:
    """Carry out drone command ``name`` (protocol names and fields; ``target``: a world point,
    for goto_pixel the tapped one); raises CommandRefused (bad_command or
    unreachable_target)."""
    try:
        if name == "goto":
            goto(sim, view, np.asarray(target, dtype=np.float64), speed, command_id)
        elif name == "goto_pixel":
            goto_near(sim, view, target, speed, command_id)
        elif name == "sticks":
            if sim.spawned:  # sticks stream from the page before the drone exists
                sim.command_sticks(_sticks(sticks), command_id=command_id)
        elif name == "hold":
            sim.command_hold(command_id=command_id)
        elif name == "land":
            sim.command_land(command_id=command_id)
        elif name == "takeoff":
            sim.command_takeoff(command_id=command_id)
        elif name == "flight_mode":
            sim.set_flight_mode(flight_mode, command_id=command_id)
        else:
            raise CommandRefused("bad_command", f"unknown drone command {name!r}")
    except DroneCommandError as exc:
        raise CommandRefused("bad_command", str(exc)) from None


def _sticks(sticks) -> np.ndarray:
    values = np.asarray(sticks, dtype=np.float64).reshape(-1)
    if values.size != 4 or not np.all(np.isfinite(values)):
        raise CommandRefused("bad_command", "sticks must be 4 finite numbers in -1..1")
    return np.clip(values, -1.0, 1.0)


def goto(
    sim: DroneSimulator,
    view: FlightView,
    target_world: np.ndarray,
    speed: float | None,
    command_id: int,
) -> None:
    """Fly to ``target_world`` (3,), or refuse with the reason and the nearest reachable
    point, both in the client's world."""
    if not np.all(np.isfinite(target_world)):
        raise CommandRefused("bad_command", "the target must be three finite numbers")
    try:
        sim.command_goto(view.to_flight(target_world), speed=speed, command_id=command_id)
    except PlanningError as exc:
        # The planner speaks in flight-frame coordinates; the client knows the world's.
        nearest = None if exc.nearest is None else view.to_world(exc.nearest)
        code = "bad_command" if exc.reason == "not_finite" else "unreachable_target"
        why = _REFUSALS.get(exc.reason.value, str(exc))
        message = f"target {_xyz(target_world)}: {why}"
        if nearest is not None:
            message += f"; nearest reachable point {_xyz(nearest)}"
        raise CommandRefused(code, message, nearest) from None


def goto_near(
    sim: DroneSimulator,
    view: FlightView,
    target_world: np.ndarray,
    speed: float | None,
    command_id: int,
) -> None:
    """A tap means 'over there': when the exact point is too close to something, fly to the
    nearest reachable point if it is within TAP_SLACK_M."""
    try:
        goto(sim, view, target_world, speed, command_id)
    except CommandRefused as exc:
        if exc.nearest is None or np.linalg.norm(exc.nearest - target_world) > TAP_SLACK_M:
            raise
        goto(sim, view, exc.nearest, speed, command_id)
