"""Map changes waiting for the flight thread: the mapping thread hands them over here and the
flight thread takes them all at its next step, so mapping never waits for physics.

Grids are occupancy in the flight frame (``TSDFMap.occupancy(voxel_m,
R_grid_world=R_flight_world)``): ``origin`` (3,) metres, ``occupied`` and ``observed`` (X, Y, Z)
bool. What is pending is a whole grid, then the sub-boxes that came after it merged into one
(``flight_map.Region``), or a grid rebuilt in a corrected world with the move into it.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from server.simulation.map_regions import Region

Grid = tuple[np.ndarray, np.ndarray, np.ndarray]  # origin, occupied, observed


@dataclass(frozen=True)
class MapChanges:
    """What was pending: ``grid`` a whole new grid, ``region`` the sub-boxes since, ``frames``
    the fused frames the flight map holds once these are applied, ``world`` a grid rebuilt in
    a corrected world and the move into it (4x4, world frame, metres: old world to new)."""

    grid: Grid | None = None
    region: Region | None = None
    frames: int | None = None
    world: tuple[Grid, np.ndarray] | None = None

    @property
    def map_changed(self) -> bool:
        return self.grid is not None or self.region is not None or self.world is not None


class PendingMap:
    """The map changes not yet applied. Thread-safe: its own lock, taking no other under it."""

    def __init__(self, voxel_m: float) -> None:
        self.voxel_m = voxel_m  # the flight map's lattice, for merging sub-boxes
        self._lock = threading.Lock()
        self._pending = MapChanges()

    def grid(self, origin: np.ndarray, occupied: np.ndarray, observed: np.ndarray) -> None:
        """A whole new grid: it replaces whatever is pending but a corrected world's."""
        with self._lock:
            p = self._pending
            self._pending = MapChanges((origin, occupied, observed), None, p.frames, p.world)

    def replaced(
        self,
        grid: Grid,
        T_correction: np.ndarray,
        frames: int | None = None,
    ) -> None:
        """The map rebuilt in a corrected world, and the move into it; what was pending for the
        old map is dropped, and two rebuilds before a step compose their moves."""
        T_move = np.asarray(T_correction, dtype=np.float64)
        with self._lock:
            p = self._pending
            if p.world is not None:
                T_move = T_move @ p.world[1]
            self._pending = MapChanges(
                None, None, p.frames if frames is None else frames, (grid, T_move)
            )

    def region(self, region: Region, frames: int | None = None) -> None:
        """New occupancy for a sub-box: merged with the boxes pending (the newer wins where
        they overlap)."""
        with self._lock:
            p = self._pending
            merged = region if p.region is None else p.region.merged(region, self.voxel_m)
            self._pending = MapChanges(
                p.grid, merged, p.frames if frames is None else frames, p.world
            )

    def frames(self, frames: int) -> None:
        """The flight map holds ``frames`` fused frames once what is pending is applied."""
        with self._lock:
            p = self._pending
            self._pending = MapChanges(p.grid, p.region, frames, p.world)

    def take(self) -> MapChanges:
        """Everything pending, which is then nothing."""
        with self._lock:
            taken, self._pending = self._pending, MapChanges()
            return taken
