"""A per-session TSDF map fused from registered RGB-D frames (Open3D tensor VoxelBlockGrid, CPU).

"World" is the frame of the poses given to ``integrate`` (``T_world_camera``, 4x4, metres; camera
x right, y down, z forward); everything returned is in the world frame, in metres. Per voxel the
grid holds a TSDF value (signed distance / truncation, -1..1), a weight (observations) and an RGB
colour (0..255 in the grid, 0..1 where returned), all float32 (saved smaller: ``save``). Open3D
allocates blocks only near surfaces; with ``carve_free_space`` the space sparse camera rays cross
before them is recorded as seen in a coarser grid beside it (server/mapping/free_space.py),
which ``occupancy`` needs to tell free space from unknown space. ``occupancy_update`` returns
only the part of that grid the frames fused since its last call can have changed. Which pixels
of a frame are fused: server/mapping/frame_input.py.
"""

from __future__ import annotations

import logging
import threading
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import open3d as o3d
import open3d.core as o3c
from numpy.typing import ArrayLike

from server.atomic import atomic_write
from server.errors import ConfigError, DroneSimError
from server.geometry import Intrinsics
from server.geometry.arrays import BoolArray, FloatArray, GreyImage, Int64Array, RealArray
from server.mapping.change_readers import ChangeReaders
from server.mapping.config import TSDFConfig
from server.mapping.frame_input import fusion_frame, open3d_projection
from server.mapping.free_space import FreeSpace
from server.mapping.occupancy import (
    Cells,
    OccupancyBox,
    block_cells,
    camera_cells,
    check_cell,
    grid_in,
    pack_keys,
    seen_cells,
    unpack_keys,
    voxel_cells,
)
from server.mapping.settled_blocks import SettledBlocks
from server.mapping.tsdf_files import StoredTSDF, read_tsdf, write_tsdf
from server.mapping.voxel_blocks import (
    BYTES_PER_VOXEL,
    HOST,
    active_keys,
    grid_from_blocks,
    has_surface,
    new_grid,
    read_all,
    read_blocks,
    reblocked,
)

log = logging.getLogger(__name__)


class MapError(DroneSimError):
    """A frame or a file given to the TSDF map is malformed."""


def _open3d_write(path: str | Path, writer: Callable[..., bool], geometry: object) -> None:
    """Write ``geometry`` with the Open3D ``writer`` (binary PLY), atomically, readable by all."""

    def write(tmp: str) -> None:
        if writer(tmp, geometry) is False:
            raise MapError(f"Open3D could not write {path}")

    atomic_write(path, write, suffix=".ply", mode=0o644)


class TSDFMap:
    """The fused map of one session. All methods may be called from different threads."""

    def __init__(
        self,
        config: TSDFConfig | None = None,
        grid: o3d.t.geometry.VoxelBlockGrid | None = None,
        camera_positions: ArrayLike | None = None,
        free: FreeSpace | None = None,
    ) -> None:
        """config: None for ``TSDFConfig()``. grid: an existing ``open3d.t.geometry.VoxelBlockGrid``
        and camera_positions (N, 3) (world, metres) of the frames fused in it, free the free
        space seen with them, if any (used by ``load``)."""
        self.config = config = config or TSDFConfig()
        self._device = o3c.Device(config.device)
        if grid is None:
            grid = new_grid(config, config.block_count)
        self._grid = grid
        if free is None and config.carve_free_space:
            free = FreeSpace(config)
        self._free = free if config.carve_free_space else None
        self._lock = threading.Lock()
        # Where each fused frame's camera was: known free space, even just behind the camera.
        self._cameras: list[FloatArray] = list(
            np.reshape([] if camera_positions is None else camera_positions, (-1, 3))
        )
        self._dirty = np.sort(
            pack_keys(active_keys(self._grid))
        )  # blocks touched since the last preview
        # Blocks touched, and cameras added, since each reader's last occupancy_update (a new
        # reader's first update is the whole grid).
        self._readers = ChangeReaders()
        self._sent = np.empty(0, np.int64)  # voxel keys of the points already previewed
        self._settled = SettledBlocks(config.settle_after, config.settled_every)
        self._integrations = 0  # frames with depth integrated by this object (for carve_every)
        self._rng = np.random.default_rng(0)

    # --- fusion ------------------------------------------------------------------------------
    def integrate(
        self,
        colour_rgb_uint8: GreyImage,
        depth_m: RealArray,
        K: Intrinsics,
        T_world_camera: RealArray,
    ) -> int:
        """Fuse one frame and return the number of newly allocated blocks.

        colour_rgb_uint8: (Hc, Wc, 3) RGB uint8, registered to the depth image; resized (area
        interpolation) to the depth image's size when they differ. depth_m: (H, W) metres along
        the optical axis; NaN, inf, zero and negative values mean no measurement. K: intrinsics
        of the camera at K.width x K.height, rescaled to the depth image's size when it differs
        (same aspect ratio required). T_world_camera: 4x4 pose of the camera in the world, metres.
        """
        cfg = self.config
        depth = np.asarray(depth_m, dtype=np.float32)
        colour = np.asarray(colour_rgb_uint8)
        if depth.ndim != 2 or colour.ndim != 3 or colour.shape[2] != 3 or colour.dtype != np.uint8:
            raise MapError(
                f"need depth (H, W) and colour (H, W, 3) uint8, got depth "
                f"{depth.shape} and colour {colour.shape} {colour.dtype}"
            )
        T = np.asarray(T_world_camera, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise MapError(f"T_world_camera must be a finite 4x4 matrix, got shape {T.shape}")
        try:
            frame = fusion_frame(colour, depth, K, cfg)
        except ValueError as exc:
            raise MapError(str(exc)) from exc
        units = frame.depth_units
        intrinsic = o3c.Tensor(open3d_projection(frame.K), o3c.float64, HOST)
        # T_camera_world, as Open3D wants.
        extrinsic = o3c.Tensor(np.linalg.inv(T), o3c.float64, HOST)
        depth_img = self._image(frame.depth_uint16, o3c.uint16)
        colour_img = self._image(frame.colour_uint8, o3c.uint8)
        search_img = self._image(frame.search_uint16, o3c.uint16)
        search_intrinsic = o3c.Tensor(frame.search_K.matrix, o3c.float64, HOST)

        with self._lock:
            self._cameras.append(T[:3, 3].copy())
            if not np.any(frame.depth_uint16):
                return 0
            blocks = self._grid.compute_unique_block_coordinates(
                search_img,
                search_intrinsic,
                extrinsic,
                units,
                cfg.depth_max_m,
                frame.search_band_voxels,
            )
            keys = self._settled.to_fuse(np.unique(pack_keys(blocks.cpu().numpy())))
            if self._free is not None and self._integrations % cfg.carve_every == 0:
                self._free.carve(depth_img, frame, T)
            self._integrations += 1
            if keys.size == 0:
                return 0
            hashmap = self._grid.hashmap()
            before = hashmap.size()
            coords = o3c.Tensor(unpack_keys(keys).astype(np.int32), o3c.int32, HOST).to(
                self._device
            )
            self._grid.integrate(
                coords,
                depth_img,
                colour_img,
                intrinsic,
                extrinsic,
                units,
                cfg.depth_max_m,
                cfg.trunc_voxels,
            )
            self._dirty = np.union1d(self._dirty, keys)
            self._readers.fused(keys)
            return hashmap.size() - before

    def _image(self, array: np.ndarray, dtype: o3c.Dtype) -> o3d.t.geometry.Image:
        return o3d.t.geometry.Image(o3c.Tensor(array, dtype, HOST)).to(self._device)

    # --- extraction --------------------------------------------------------------------------
    def _extract(self) -> tuple[FloatArray, FloatArray]:
        empty = np.empty((0, 3)), np.empty((0, 3))
        if self._grid.hashmap().size() == 0:  # Open3D raises on an empty grid
            return empty
        pcd = self._grid.extract_point_cloud(self.config.min_weight).cpu()
        if "positions" not in pcd.point or len(pcd.point.positions) == 0:
            return empty
        points = pcd.point.positions.numpy().astype(np.float64)
        colours = np.clip(pcd.point.colors.numpy().astype(np.float64), 0.0, 1.0)
        return points, colours

    def point_cloud(self) -> tuple[FloatArray, FloatArray]:
        """Surface points of the TSDF: (points (N, 3) float64 metres in the world frame,
        colours (N, 3) float64 RGB in 0..1)."""
        with self._lock:
            return self._extract()

    def take_preview(self, max_points: int = 4000) -> tuple[FloatArray, FloatArray]:
        """Surface points (as in ``point_cloud``, at most one per voxel) of the blocks touched
        since the last call and not returned before: at most ``max_points``, a random subset when
        there are more (the rest stays pending for the next call)."""
        with self._lock:
            if self._dirty.size == 0:
                return np.empty((0, 3)), np.empty((0, 3))
            points, colours = self._extract()
            voxels = pack_keys(np.floor(points / self.config.voxel_m))
            blocks = pack_keys(np.floor(points / self.config.block_m))
            fresh = np.isin(blocks, self._dirty) & ~np.isin(voxels, self._sent)
            _, first = np.unique(voxels[fresh], return_index=True)
            idx = np.flatnonzero(fresh)[first]
            self._dirty = np.empty(0, np.int64)
            if idx.size > max_points:
                pick = self._rng.choice(idx.size, size=max_points, replace=False)
                rest = np.setdiff1d(np.arange(idx.size), pick)
                self._dirty = np.unique(blocks[idx[rest]])
                idx = np.sort(idx[pick])
            self._sent = np.union1d(self._sent, voxels[idx])
            return points[idx], colours[idx]

    def mesh(self) -> o3d.geometry.TriangleMesh:
        """Marching-cubes surface (legacy mesh, world frame, metres, vertex colours 0..1)."""
        with self._lock:
            if self._grid.hashmap().size() == 0:
                return o3d.geometry.TriangleMesh()
            return self._grid.extract_triangle_mesh(self.config.min_weight).cpu().to_legacy()

    def has_surface(self) -> bool:
        """Whether ``mesh()`` and the surface points would be other than empty (voxel_blocks)."""
        with self._lock:
            return has_surface(self._grid, self.config.min_weight)

    # --- occupancy for the drone ---------------------------------------------------------------
    def occupancy(
        self, voxel_m: float = 0.05, R_grid_world: RealArray | None = None
    ) -> tuple[FloatArray, BoolArray, BoolArray]:
        """A coarse occupancy grid derived from the TSDF, for the drone simulator.

        R_grid_world: rotation (3x3) from the world frame into the frame whose axes the grid
        follows (a gravity-aligned flight frame); None for the world's own axes.
        Returns (origin (3,) metres in the grid frame, occupied, observed), both bool arrays of
        the same shape indexed [i, j, k] <-> grid-frame x, y, z: cell (i, j, k) spans
        origin + [i, i + 1) * voxel_m along x, and likewise for y (j) and z (k); the origin is a
        whole number of cells from the grid frame's origin. A cell is observed when one of its
        TSDF voxels was seen (weight > 0) or a fused frame's camera was in it, and occupied when a
        seen TSDF voxel in it has a TSDF distance under half the cell's diagonal (at least one
        TSDF voxel, at most the truncation). Free = observed & ~occupied; unobserved cells should
        be treated as unknown (not safe to fly).
        """
        check_cell(voxel_m)
        with self._lock:
            keys, tsdf, weight = read_blocks(self._grid)
            free = None if self._free is None else self._free.read()
            cameras = np.array(self._cameras).reshape(-1, 3)
        seen, surface = voxel_cells(keys, tsdf, weight, voxel_m, R_grid_world, self.config)
        free_seen = self._free_cells(free, voxel_m, R_grid_world)
        at_camera = camera_cells(cameras, voxel_m, R_grid_world)
        box = OccupancyBox.around([seen, free_seen, surface, at_camera])
        grid = grid_in(box, voxel_m, [seen, free_seen, at_camera], surface)
        if grid is None:
            return np.zeros(3), np.zeros((0, 0, 0), bool), np.zeros((0, 0, 0), bool)
        return grid

    def occupancy_update(
        self, voxel_m: float = 0.05, R_grid_world: RealArray | None = None, reader: str = ""
    ) -> tuple[FloatArray, BoolArray, BoolArray] | None:
        """The part of ``occupancy(voxel_m, R_grid_world)`` that what was fused since the last
        call can have changed, or None when nothing can have.

        Returns (origin, occupied, observed) as ``occupancy`` does, for a sub-box of its grid:
        every cell that a voxel of a block integrated since the last call can fall in (the
        blocks' extent in the grid frame, one cell wider each side) and every new camera's
        cell, cropped to the cells observed in it. Inside that box the values are exactly a
        full ``occupancy``'s (the voxels of untouched blocks that fall in the box are read too).
        The origin sits on the same lattice as every ``occupancy`` grid, so boxes merge into one
        grid (``FlightMap.update_region``). Outside the box nothing changed: observed never
        turns false, except, when voxel_m is 2.5 TSDF voxels or more (the seen voxels are then
        sampled, ``occupancy.seen_cells``), a cell seen only through surface voxels that have
        left the surface band (unobserved now, where it was occupied: blocked either way).

        A reader's first call returns the whole grid. Each call restarts what that reader's
        next one covers: ``reader`` names a drone reading the map (each phone sharing it has
        one), which passes the same voxel_m and R_grid_world every time; ``occupancy``
        restarts nothing.
        """
        check_cell(voxel_m)
        cfg = self.config
        with self._lock:
            free = self._free
            if free is not None:
                self._readers.carved(free.take_dirty())
            none = np.empty(0, np.int64)
            cameras = np.array(self._cameras).reshape(-1, 3)
            blocks, unread_free, first_camera = self._readers.take(
                reader,
                len(cameras),
                lambda: np.sort(pack_keys(active_keys(self._grid))),
                lambda: none if free is None else free.all_keys(),
            )
            dirty, free_dirty = unpack_keys(blocks), unpack_keys(unread_free)
            new_cameras = cameras[first_camera:]
            if len(dirty) == 0 and len(free_dirty) == 0 and len(new_cameras) == 0:
                return None
            reach = [block_cells(dirty, voxel_m, R_grid_world, cfg)]
            if free is not None:
                reach.append(block_cells(free_dirty, voxel_m, R_grid_world, free.config))
            if len(new_cameras):
                at = np.stack(camera_cells(new_cameras, voxel_m, R_grid_world), axis=1)
                reach.append((at, at))
            box_lo = np.min([lo.min(axis=0) for lo, _ in reach if len(lo)], axis=0)
            box_hi = np.max([hi.max(axis=0) for _, hi in reach if len(hi)], axis=0) + 1

            def overlapping(grid: TSDFConfig) -> Callable[[Int64Array], BoolArray]:
                def hits(keys: Int64Array) -> BoolArray:  # blocks with a voxel in the box
                    lo, hi = block_cells(keys, voxel_m, R_grid_world, grid)
                    hit: BoolArray = np.all((lo < box_hi) & (hi >= box_lo), axis=1)
                    return hit

                return hits

            keys, tsdf, weight = read_blocks(self._grid, overlapping(cfg))
            free_blocks = None if free is None else free.read(overlapping(free.config))
        seen, surface = voxel_cells(keys, tsdf, weight, voxel_m, R_grid_world, cfg)
        free_seen = self._free_cells(free_blocks, voxel_m, R_grid_world)
        at_camera = camera_cells(cameras, voxel_m, R_grid_world)
        # Cropped to what is observed: the rest of the box was unobserved before too.
        return grid_in(OccupancyBox(box_lo, box_hi), voxel_m, [seen, free_seen, at_camera], surface)

    def _free_cells(
        self,
        free: tuple[Int64Array, np.ndarray] | None,
        voxel_m: float,
        R_grid_world: RealArray | None,
    ) -> Cells:
        """Cells of the free-space grid's seen voxels among ``free`` = (keys, weights)."""
        if free is None or self._free is None:
            none = np.empty(0, np.int64)
            return none, none, none
        return seen_cells(*free, voxel_m, R_grid_world, self._free.config)

    # --- files -------------------------------------------------------------------------------
    def write_point_cloud_ply(self, path: str | Path) -> None:
        """Binary PLY of ``point_cloud()`` with per-point colours, written atomically."""
        points, colours = self.point_cloud()
        if len(points) == 0:
            raise MapError(f"the map has no surface to write to {path} yet")
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        cloud.colors = o3d.utility.Vector3dVector(colours)
        _open3d_write(path, o3d.io.write_point_cloud, cloud)

    def write_mesh_ply(self, path: str | Path) -> None:
        """Binary PLY of ``mesh()`` with vertex colours, written atomically."""
        mesh = self.mesh()
        if not mesh.has_triangles():
            raise MapError(f"the map has no surface to write to {path} yet")
        _open3d_write(path, o3d.io.write_triangle_mesh, mesh)

    def save(self, path: str | Path, compress: bool = True) -> None:
        """Persist the whole grid and the camera positions, written atomically (the format:
        server/mapping/tsdf_files.py; ``compress``: deflated). Gathered with numpy rather than
        Open3D's own save, which is ~20x slower at it, under the lock that fusion waits for."""
        with self._lock:
            keys, values = read_all(self._grid)
            free = None if self._free is None else self._free.blocks()
            cameras = np.array(self._cameras).reshape(-1, 3)
        cfg = self.config
        stored = StoredTSDF(cfg.voxel_m, cfg.block_resolution, cameras, keys, values)
        if free is not None and self._free is not None:
            stored.free_voxel_m = self._free.config.voxel_m
            stored.free_keys, stored.free_values = free
        write_tsdf(path, stored, compress)
        log.info("saved TSDF map (%d blocks) to %s", len(keys), path)

    @classmethod
    def load(cls, path: str | Path, config: TSDFConfig | None = None) -> TSDFMap:
        """Restore a map written by ``save`` (or by an earlier version's, in the layout of
        Open3D's ``VoxelBlockGrid.save``). ``config`` must match the file's voxel size; blocks of
        another resolution (one a multiple of the other) are re-blocked to its. None takes voxel
        size and block resolution from the file (other settings at their defaults)."""
        path = Path(path)
        if not path.is_file():
            raise MapError(f"no TSDF map file at {path}")
        try:
            stored = read_tsdf(path)
            voxel_m, resolution = stored.voxel_m, stored.block_resolution
            if config is None:
                free_voxels = round(stored.free_voxel_m / voxel_m) if stored.free_voxel_m else 2
                config = TSDFConfig(
                    voxel_m=round(voxel_m, 9),
                    block_resolution=resolution,
                    carve_voxels=max(1, free_voxels),
                )
            elif not np.isclose(config.voxel_m, voxel_m):
                raise ConfigError(
                    f"{path} holds {voxel_m} m voxels, config asks for {config.voxel_m} m"
                )
            if stored.keys is not None and stored.values is not None:
                keys, values = stored.keys, stored.values
            else:  # Open3D's own layout
                keys, values = read_all(o3d.t.geometry.VoxelBlockGrid.load(str(path)))
            if resolution != config.block_resolution:
                keys, values = reblocked(keys, values, config.block_resolution)
            grid = grid_from_blocks(config, keys, values)
            free = None
            if config.carve_free_space and stored.free_keys is not None and stored.free_values:
                free = FreeSpace.from_blocks(
                    config, stored.free_voxel_m, stored.free_keys, stored.free_values
                )
        except (OSError, RuntimeError, KeyError, ValueError, zipfile.BadZipFile) as exc:
            raise MapError(f"cannot load a TSDF map from {path}: {exc}") from exc
        return cls(
            config,
            grid=grid.to(o3c.Device(config.device)),
            camera_positions=stored.camera_positions,
            free=free,
        )

    def stats(self) -> dict[str, int | float]:
        """frames_integrated, active_blocks, capacity_blocks (the TSDF's), voxel_m, memory_bytes
        (approximate: the allocated block buffers, which Open3D sizes to the capacity, of the
        TSDF and the free-space grid)."""
        with self._lock:
            hashmap = self._grid.hashmap()
            active, capacity = hashmap.size(), hashmap.capacity()
            frames = len(self._cameras)
            free_bytes = 0 if self._free is None else self._free.memory_bytes()
        per_block = self.config.block_resolution**3 * BYTES_PER_VOXEL + 3 * 4
        return {
            "frames_integrated": frames,
            "active_blocks": active,
            "capacity_blocks": capacity,
            "voxel_m": self.config.voxel_m,
            "memory_bytes": capacity * per_block + free_bytes,
        }
