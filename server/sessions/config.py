"""What one session needs of the one configuration (``server/config.py``)."""

from __future__ import annotations

from dataclasses import dataclass, replace

from server.config import Config
from server.mapping.config import MappingConfig
from server.registration.config import RegistrationConfig
from server.simulation.config import SimulationConfig


def threads_per_session(cores: int, sessions: int) -> int:
    """Native threads (OpenCV, BLAS) for each of ``sessions`` live sessions' tracking on a
    machine of ``cores``: the cores less one, shared. The one left is the sessions' other
    work's (mapping processes, drone, the web process): on 2 cores one session with a pool of
    two cost 1.5-2 ms more server CPU per 640x480 frame (7 %) than with one, for a median
    latency no lower."""
    return max(1, (cores - 1) // max(1, sessions))


@dataclass(frozen=True)
class SessionConfig:
    """What one session needs of the one configuration (server/config.py): its sections as
    they are, with no defaults of their own. Plain dataclasses, pickled to the session's worker
    process or Ray actor."""

    registration: RegistrationConfig
    mapping: MappingConfig
    simulation: SimulationConfig | None  # None: no drone
    snapshot_interval_s: float  # periodic atomic snapshot of map + trajectory
    drone_state_hz: float  # drone_state messages per second
    flight_max_s: float = 600.0  # the longest stretch of one flight recorded, s
    flights_kept: int = 20  # the newest flight recordings a session keeps on disk
    save_room: bool = True  # keep keyframes and leave a room when closed (server.save_rooms)

    def closes_loops(self, in_room: bool) -> bool:
        """Online loop closure runs in a session of this configuration: configured
        (registration.loops.live), the room's keyframes kept on disk (the rebuild reads them),
        and not continuing in a saved room (its keyframes would have to stay fixed:
        server/sessions/runtime/loop_closing.py)."""
        return self.registration.loops.live and self.save_room and not in_room

    def with_loop_closure(self, live: bool | None) -> SessionConfig:
        """This configuration with online loop closure on or off (None: as it is)."""
        if live is None or live == self.registration.loops.live:
            return self
        return replace(self, registration=self.registration.with_overrides(loops={"live": live}))

    @classmethod
    def from_config(cls, config: Config | None = None) -> SessionConfig:
        """The session's part of ``config``; of the defaults (environment unread) when None."""
        config = config or Config.defaults()
        return cls(
            registration=config.registration,
            mapping=config.mapping,
            simulation=config.simulation,
            snapshot_interval_s=config.server.snapshot_interval_s,
            drone_state_hz=config.server.drone_state_hz,
            flight_max_s=config.server.flight_max_s,
            flights_kept=config.server.flights_kept,
            save_room=config.server.save_rooms,
        )
