"""Manual flight: the pilot's latest sticks, how old they are, and the flight mode flying them.

Sticks ``(throttle, yaw, pitch, roll)`` in -1..1, zero where centred (commands.sticks applies
the deadband once). In position mode they become a setpoint for the cascaded controller
(control.fly_sticks: velocities, centred holds position); in angle and acro the attitude
controller (pilot_modes.PilotController) turns them into motor thrusts itself. Sticks older than
stick_timeout_s (simulation time; a lost link) count as centred: angle and acro then hand over
to position mode's braking, then holding, as a switch to position mode does.
"""

from __future__ import annotations

import math

from server.simulation.commands import CENTRED, Sticks
from server.simulation.config import SimulationConfig
from server.simulation.control import ControlGains, ControlLimits, Setpoint, fly_sticks
from server.simulation.pilot_modes import (
    FlightMode,
    PilotController,
    StickRates,
    hand_over_to_position,
)
from server.simulation.quadrotor import Quadrotor, QuadrotorParams


class ManualFlight:
    """The manual mode of one drone (module docstring)."""

    def __init__(
        self,
        config: SimulationConfig,
        params: QuadrotorParams,
        gains: ControlGains,
        limits: ControlLimits,
    ) -> None:
        self.timeout_s = config.stick_timeout_s
        self._limits = limits
        self.pilot = PilotController(params, gains, StickRates.from_config(config))
        self.flight_mode = FlightMode.POSITION
        self.sticks: Sticks = CENTRED
        self.read_at_s = -math.inf  # simulation time the sticks were read

    def set_sticks(self, sticks: Sticks, read_at_s: float) -> None:
        self.sticks, self.read_at_s = sticks, read_at_s

    def take_over(self, q: Quadrotor, sp: Setpoint) -> None:
        """Manual flight starts: hold where the drone is until the sticks say otherwise; angle
        and acro start from the drone's attitude."""
        sp.hold(q.position, q.yaw_rad)
        self.pilot.release()

    def motors(
        self, q: Quadrotor, sp: Setpoint, now_s: float
    ) -> tuple[float, float, float, float] | None:
        """Motor thrusts (N) for this step when angle or acro flies it (while the sticks are
        fresh at ``now_s``); else None, with position mode's setpoint written into ``sp`` for
        the cascaded controller."""
        fresh = now_s - self.read_at_s <= self.timeout_s
        if fresh and self.flight_mode != FlightMode.POSITION:
            return self.pilot.update(q, self.flight_mode, self.sticks)
        if self.pilot.engaged:
            self.pilot.release()
            hand_over_to_position(sp, q)
        fly_sticks(q, sp, self.sticks if fresh else CENTRED, self._limits, q.dt)
        return None
