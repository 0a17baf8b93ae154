"""A drone holding still costs no physics: steps are skipped while its state is a fixed point.

A drone hovering on a held position (mode ``hover``, or ``manual`` with nothing to fly: stale
sticks, or position mode with the sticks centred) runs a step that reads nothing but its own
state, the quadrotor's and the setpoint's: not the time, not the map, not a route. Once that
state is a fixed point of the step (a step leaves it the same, to the bit), every later step
does too, until something from outside changes it: a command, the sticks, a map change that
moves the drone, a corrected world. So ``Stillness.skip`` lets the time pass as the steps would
(``time_s += dt`` once a step, the same additions) and runs none of them, and it checks on
every ``advance`` that nothing changed: its ``key`` (every value a step reads or writes, to the
bit) must still be the one it saw at the fixed point. There is no wake-up call to forget: any
change of the state ends the skipping at the next advance. Contact checks are not needed while
skipping: a drone that does not move cannot touch the map (contact.first_contact counts a touch
only when the distance shrinks), whatever the map does.

Holding still by stepping, the drone never quite reaches its fixed point: after a flight its
state creeps towards it in the last bits for minutes (the position ~1e-10 m from the setpoint,
the body rates ~1e-14 rad/s, below what turns the attitude). Once every part of it is within
``SETTLED`` of the setpoint's hover (position, velocity, tilt, heading, body rates, motor
thrusts; SI units), it is **settled** onto it: put exactly at the setpoint, level, at rest, the
motors at hover thrust. That moves it by less than ``SETTLED`` (1e-9: a nanometre), what stepping
itself leaves in the last bits, and only while nothing is commanded. The settled state is then
tried: a step must leave it unchanged, else it is put back as it was, unsettled, and stepping
goes on as before.

``DroneSimulator(skip_still=False)`` steps every step, as before this module (benchmarks and
tests compare the two).
"""

from __future__ import annotations

import math
import struct

from server.simulation.commands import CENTRED
from server.simulation.control import Setpoint
from server.simulation.drone_types import DroneMode
from server.simulation.flight_map import FlightMap
from server.simulation.modes import DroneModes
from server.simulation.pilot_modes import FlightMode

SETTLED = 1e-9  # settled onto the fixed point within this (m, m/s, rad, rad/s, N)

_FLOATS = struct.Struct("<17d11d5d")  # quadrotor, setpoint's numbers, sticks and their time
_SP_FLOATS = Setpoint.__slots__[:11]  # x .. yaw_rate; hold_xy and hold_z are the flags


class Stillness:
    """Skips the physics steps of one drone (``DroneModes``) while it holds a fixed point."""

    def __init__(self, modes: DroneModes, flight_map: FlightMap, enabled: bool = True) -> None:
        self.modes = modes
        self.flight_map = flight_map
        self.enabled = enabled
        self._still: tuple[object, ...] | None = None  # the key at the fixed point
        self.skipped = 0  # steps skipped so far (for benchmarks and tests)

    @property
    def still(self) -> bool:
        """Whether the last advance found the drone at its fixed point."""
        return self._still is not None

    def key(self) -> tuple[object, ...] | None:
        """Every value a step reads or writes, to the bit (floats packed: -0.0 is not 0.0),
        when the step depends on nothing else; None in a mode whose step does (a route, the
        time of the sticks, a descent, a fall)."""
        m = self.modes
        mode = m.mode
        manual = m.manual
        if mode == DroneMode.MANUAL:
            fresh = m.time_s - manual.read_at_s <= manual.timeout_s
            # Fresh sticks in angle or acro fly the attitude controller; fresh non-centred
            # ones in position mode turn into a stop when they go stale: both hang on time.
            if fresh and (manual.flight_mode != FlightMode.POSITION or manual.sticks != CENTRED):
                return None
        elif mode != DroneMode.HOVER:
            return None
        sp = m.sp
        floats = _FLOATS.pack(
            *m.quad.state(),
            *(getattr(sp, name) for name in _SP_FLOATS),
            *manual.sticks,
            manual.read_at_s,
        )
        return (floats, sp.hold_xy, sp.hold_z, mode, manual.flight_mode, manual.pilot.engaged)

    def skip(self, n: int) -> int:
        """Of the ``n`` physics steps due, skip those the drone holds still through (time passes
        as they would pass it); returns how many are left to run (all of them when it does not
        hold still)."""
        if not self.enabled or n <= 0:
            self._still = None
            return n
        key = self.key()
        if key is None:
            self._still = None
            return n
        if key != self._still:
            self._still = None
            if not self._settle(key):
                return n
            n -= 1  # the step that tried the settled state
        m = self.modes
        dt = m.quad.dt
        t = m.time_s
        for _ in range(n):  # the same additions the steps would make
            t += dt
        m.time_s = t
        self.skipped += n
        return 0

    def _settle(self, key: tuple[object, ...]) -> bool:
        """Whether the drone holds a fixed point, as it is or settled onto its setpoint's hover
        (module docstring); if so it is there, one step later, and ``_still`` is its key. Else
        it is put back as it was."""
        m = self.modes
        q, sp = m.quad, m.sp
        if not (sp.hold_xy and sp.hold_z) or m.manual.pilot.engaged:
            return False
        hover = q.params.hover_thrust_n
        off = max(
            abs(q.px - sp.x),
            abs(q.py - sp.y),
            abs(q.pz - sp.z),
            abs(q.vx),
            abs(q.vy),
            abs(q.vz),
            abs(q.qx),
            abs(q.qy),
            abs(math.remainder(q.yaw_rad - sp.yaw, math.tau)),
            abs(q.wx),
            abs(q.wy),
            abs(q.wz),
            abs(q.f0 - hover),
            abs(q.f1 - hover),
            abs(q.f2 - hover),
            abs(q.f3 - hover),
            abs(sp.vx),
            abs(sp.vy),
            abs(sp.vz),
            abs(sp.ax),
            abs(sp.ay),
            abs(sp.az),
            abs(sp.yaw_rate),
        )
        if not off <= SETTLED:
            return False
        # Far enough from the map that settling and the trial step cannot touch it (as
        # contact.run_checked's chunks: clearance beyond the radius and a cell).
        config = m.config
        if self.flight_map.distance_at(q.px, q.py, q.pz) <= config.radius_m + config.voxel_m:
            return False
        saved = m.save()
        m.step()  # a fixed point as it is (after a spawn, say): nothing to settle
        if self.key() == key:
            self._still = key
            return True
        m.restore(saved)
        qw, qx, qy, qz = q.qw, q.qx, q.qy, q.qz
        q.reset((sp.x, sp.y, sp.z), sp.yaw, hovering=True)
        if qw * q.qw + qx * q.qx + qy * q.qy + qz * q.qz < 0.0:  # the same rotation, kept
            q.qw, q.qx, q.qy, q.qz = -q.qw, -q.qx, -q.qy, -q.qz  # continuous with the old one
        settled = self.key()
        m.step()
        after = self.key()
        if after is None or after != settled:
            m.restore(saved)
            return False
        self._still = after
        return True
