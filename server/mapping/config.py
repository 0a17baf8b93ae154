"""Every mapping parameter, with its default and units: the ``mapping`` section of the one
configuration (server/config.py). Plain frozen dataclasses, so that the map needs no settings
machinery (and this module imports no Open3D); pydantic validates them when the configuration is
loaded."""

from __future__ import annotations

from dataclasses import dataclass, field

from server.errors import ConfigError

# Most points in one map_chunk message: shared/protocol.json limits.max_map_chunk_points (a test
# holds the two equal). A bigger chunk is refused by the protocol's own encoder.
MAX_PREVIEW_POINTS = 16384


@dataclass(frozen=True)
class TSDFConfig:
    """voxel_m: voxel edge (m). block_resolution: voxels per block edge: Open3D fuses every
    voxel of each block a frame touches, so smaller blocks hug the surface band closer (8: 30 %
    less fusion CPU than 16 on 7scenes_a, benchmarks/README.md "Mapper CPU"); a saved map of
    another resolution is re-blocked when loaded. block_count: blocks allocated up front (the
    hash map doubles when full; each block costs block_resolution^3 * 20 bytes, 10 KiB at 8).
    trunc_voxels: truncation distance in voxels. depth_max_m: depth beyond this is ignored.
    min_weight: a voxel shows in extracted surfaces once observed more often than this.
    carve_free_space: also record the space rays cross before the surface as seen, in a grid
    of its own (server/mapping/free_space.py), for the drone to tell free space from unknown.
    carve_every: carve on every n-th integration only (the first included): the space a moving
    camera sees empty changes slowly. carve_voxels: the free-space grid's voxel edge, in TSDF
    voxels (2: 4 cm, the spacing at which the drone's 5 cm cells sample the TSDF).
    block_search_width_px: the blocks a frame touches are found from every n-th pixel of a depth
    image wider than this, each way (n the smallest that brings it to this width: 640x480 ->
    320x240), one voxel beyond the truncation band; every pixel is fused into them
    (server/mapping/frame_input.py). 0: found from every pixel. settle_after: frames that touch
    a block before it counts as settled (0: never); settled_every: a settled block is fused on
    every n-th frame that touches it only (server/mapping/settled_blocks.py)."""

    voxel_m: float = 0.02
    block_resolution: int = 8
    block_count: int = 1024  # 10 MiB up front (idle sessions stay cheap); a room doubles it
    trunc_voxels: float = 4.0
    depth_max_m: float = 4.0
    min_weight: float = 3.0
    carve_free_space: bool = True
    carve_every: int = 3
    carve_voxels: int = 2
    block_search_width_px: int = 320
    settle_after: int = 32
    settled_every: int = 4
    device: str = "CPU:0"

    def __post_init__(self) -> None:
        if not (self.voxel_m > 0 and self.trunc_voxels > 0 and self.depth_max_m > 0):
            raise ConfigError(f"TSDF voxel, truncation and depth range must be positive: {self}")
        if self.carve_every < 1:
            raise ConfigError(f"TSDF carve_every must be at least 1: {self}")
        if self.carve_voxels < 1:
            raise ConfigError(f"TSDF carve_voxels must be at least 1: {self}")
        if self.block_search_width_px < 0:
            raise ConfigError(f"TSDF block_search_width_px must be >= 0 (0: every pixel): {self}")
        if self.settle_after < 0 or self.settled_every < 1:
            raise ConfigError(f"TSDF settle_after must be >= 0 and settled_every >= 1: {self}")
        if self.block_resolution < 2 or self.block_count < 1:
            raise ConfigError(f"TSDF block resolution < 2 or block count < 1: {self}")

    @property
    def trunc_m(self) -> float:
        return self.trunc_voxels * self.voxel_m

    @property
    def block_m(self) -> float:
        return self.block_resolution * self.voxel_m


@dataclass(frozen=True)
class MappingConfig:
    """A live session's map: the TSDF, which frames are fused into it, and how the phone's
    preview and the drone's occupancy grid follow it."""

    tsdf: TSDFConfig = field(default_factory=TSDFConfig)
    fuse_every: int = 3  # integrate every n-th tracked frame (and every keyframe)
    preview_points: int = 4000  # most new preview points sent per fused frame (one map_chunk)
    # The drone's occupancy grid and distance field are rebuilt at most this often: a rebuild
    # costs ~0.3 s of CPU on a room (extraction + distance transform), so 1 s would take a third
    # of a core per session.
    flight_map_interval_s: float = 3.0
    # After a loop closure the map is re-fused from the keyframes
    # (server/sessions/runtime/session.py) this many at a time between two fusions (each read
    # from its files, then fused): new frames wait at most that.
    rebuild_keyframes_per_step: int = 2
    # A loop correction re-fuses the map only once it moves some keyframe by more than this
    # since the map was last fused (metres, at a point 2 m in front of the keyframe's camera:
    # translation plus rotation angle times 2 m). Smaller moves are below the map's resolution
    # (one voxel), and each re-fusion reads and fuses every keyframe so far: a third of what
    # live loop closure costs (on 7scenes_a this skips 21-30 of 28-38; benchmarks/README.md,
    # "Online, in live sessions"). 0: every correction re-fuses.
    rebuild_min_move_m: float = 0.02

    def __post_init__(self) -> None:
        # A session's voxel: below 1 mm the grid outgrows any memory, above 20 cm the map and
        # the drone's world are too coarse to fly in.
        if not 0.001 < self.tsdf.voxel_m <= 0.2:
            raise ConfigError(
                f"mapping.tsdf.voxel_m must be in (0.001, 0.2] m, got {self.tsdf.voxel_m}"
            )
        if self.fuse_every < 1:
            raise ConfigError(f"mapping.fuse_every must be >= 1, got {self.fuse_every}")
        if self.rebuild_min_move_m < 0:
            raise ConfigError(
                f"mapping.rebuild_min_move_m must be >= 0, got {self.rebuild_min_move_m}"
            )
        if not 100 <= self.preview_points <= MAX_PREVIEW_POINTS:
            raise ConfigError(
                f"mapping.preview_points must be in [100, {MAX_PREVIEW_POINTS}] (the protocol's "
                f"max_map_chunk_points), got {self.preview_points}"
            )
        if self.rebuild_keyframes_per_step < 1:
            raise ConfigError(
                "mapping.rebuild_keyframes_per_step must be >= 1, got "
                f"{self.rebuild_keyframes_per_step}"
            )
        if not self.flight_map_interval_s > 0:
            raise ConfigError(
                f"mapping.flight_map_interval_s must be > 0, got {self.flight_map_interval_s}"
            )
