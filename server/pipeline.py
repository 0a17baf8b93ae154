"""Offline odometry over a dataset: register every frame, fuse the map, write the results.

Shared by the ``track`` command and the tests. Each frame goes through the same step as a live
session's (server/frame_step.py), so offline and live register, key and fuse frames alike.
"""

from __future__ import annotations

import json
import logging
from collections import Counter
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from server.datasets import RGBDDataset, RGBDFrame
from server.datasets.replay_export import ARKIT_GRAVITY
from server.errors import DatasetError
from server.evaluation.metrics import evaluate
from server.evaluation.plots import plot_top_view
from server.evaluation.trajectory import Trajectory, write_tum
from server.frame_step import FrameStep
from server.geometry import invert
from server.geometry.arrays import FloatArray
from server.mapping.config import MappingConfig, TSDFConfig
from server.mapping.mesh_files import write_upright
from server.mapping.pointcloud import PointCloudMap
from server.mapping.tsdf import TSDFMap
from server.mapping.upright import upright_frame
from server.overlap import Behind, read_ahead
from server.registration import Tracker, TrackResult
from server.registration.calibration import ColourToDepth
from server.registration.config import RegistrationConfig
from server.registration.loops import LoopCloser
from server.registration.preprocess import clean_depth
from server.rooms.continuation import RoomTracker
from server.rooms.room import Room
from server.rooms.room import save_room as write_room

log = logging.getLogger(__name__)


@dataclass
class OdometryRun:
    """Everything one run produced."""

    trajectory: Trajectory  # one T_world_camera per input frame, lost frames included
    results: list[TrackResult]
    map: PointCloudMap
    room: Room  # the keyframes of this run (after those of the room it continued in, if any)
    metrics: dict | None = None  # when the dataset has ground truth
    summary: dict = field(default_factory=dict)


def ground_truth_pose_at(dataset: RGBDDataset, timestamp: float, max_diff: float = 0.02):
    """The ground-truth T_world_camera nearest to ``timestamp``, or None."""
    gt = dataset.ground_truth
    if gt is None or len(gt) == 0:
        return None
    i = int(np.argmin(np.abs(gt.timestamps - timestamp)))
    return gt.poses[i] if abs(gt.timestamps[i] - timestamp) <= max_diff else None


def run_odometry(
    dataset: RGBDDataset,
    config: RegistrationConfig | None = None,
    max_frames: int | None = None,
    mapping: MappingConfig | None = None,
    progress: bool = True,
    room: Room | None = None,
    start: int = 0,
    keep_room: bool = True,
    overlap: bool = True,
) -> OdometryRun:
    """Register ``max_frames`` frames of ``dataset`` from frame ``start`` on and fuse every
    ``mapping.fuse_every``-th tracked frame (and every keyframe) into a point cloud map with
    ``mapping.tsdf.voxel_m`` voxels (offline, the map is a point cloud, not the server's TSDF).

    The first pose is the ground truth's when the dataset has one (so that estimates and ground
    truth share a frame for plots), else the identity.

    A phone's recording (``dataset.device_poses``, Stray Scanner, Record3D) gives every frame its
    device pose as the tracker's prior (``Tracker.track(..., T_device_camera=...)``), as the
    server does with a phone's frames; ``config.prior.enabled = False`` tracks without it.

    With ``room`` (a saved room, see server/rooms/), the run starts inside it: frames are
    relocalised by place recognition until one is found, and tracked from there in the room's
    world frame; the frames before have no pose and are left out of the trajectory. The room
    gains this run's keyframes (``run.room`` is the same object) and its map is cleared, to be
    re-fused from all keyframes when saved. With loop closure (``config.loops.enabled``) every
    frame moves with its keyframe's correction, and so do the points it put into the map (the
    map keeps one segment per keyframe). ``keep_room=False`` keeps no keyframes (no place
    features computed; ``run.room`` stays as it was), unless loop closure needs them.

    Frames are read ahead of the tracker, and fused, described and added to the room behind it,
    each on a thread of its own (server/overlap.py); ``overlap=False`` does it all in turn in the
    caller. Either way the results are the same.
    """
    mapping = mapping or MappingConfig()
    fuse_every, voxel_m = mapping.fuse_every, mapping.tsdf.voxel_m
    if not 0 <= start < len(dataset):
        raise DatasetError(f"start frame {start} is outside {dataset.name}'s {len(dataset)} frames")
    left = len(dataset) - start
    n = left if max_frames is None else min(max_frames, left)
    first = dataset[start]
    cfg = config or RegistrationConfig()
    if room is None:
        T_first = ground_truth_pose_at(dataset, first.timestamp)
        tracker: Tracker | RoomTracker = Tracker(dataset.intrinsics, cfg, T_first)
        room = Room(dataset.intrinsics)
    else:
        tracker = RoomTracker(room, dataset.intrinsics, cfg)
    world_map = PointCloudMap(voxel_m=voxel_m)
    step = FrameStep(
        tracker,
        dataset.intrinsics,
        # Unregistered colour (a raw RGB-D sensor's) is resampled onto depth; a phone's is not.
        ColourToDepth(dataset.intrinsics, cfg.depth, not dataset.depth_registered),
        fuse_every,
        cfg.relocalise.segment_keyframes_kept,
    )
    results, stamps = [], []
    closer = LoopCloser(dataset.intrinsics, cfg) if cfg.loops.enabled else None
    keep = keep_room or closer is not None
    use_device = cfg.prior.enabled and dataset.device_poses is not None
    with_device_pose = 0  # frames that had a device pose to give
    # The room's map grows with its keyframes behind tracking (the map a saved room holds);
    # a room continued here starts from its own keyframes again, as save_room would re-fuse it.
    # With loop closure it is fused once, when the room is saved, from the corrected keyframes
    # (Open3D's integration holds the GIL: fused behind tracking it would also slow the tracker).
    room_map = TSDFMap() if keep and closer is None else None
    behind = Behind(threaded=overlap, name="map")
    if room_map is not None:
        behind.submit(room.fuse_into, room_map, list(room.keyframes))

    def read(i: int) -> tuple[int, RGBDFrame, np.ndarray, np.ndarray]:
        frame = first if i == start else dataset[i]
        return i, frame, *step.prepare(frame.colour, frame.depth)

    frames = read_ahead(map(read, range(start, start + n)), threaded=overlap)  # a generator
    bar = tqdm(frames, total=n, desc=f"track {dataset.name}", unit="frame", disable=not progress)
    K = dataset.intrinsics
    try:
        for i, frame, colour, depth in bar:
            T_device_camera = dataset.device_pose(i) if use_device else None
            with_device_pose += T_device_camera is not None
            result = step.track(colour, depth, T_device_camera=T_device_camera)
            if result is None:  # not yet found in the room
                continue
            settled = step.settle(result, i, i, colour, depth)  # offline nothing waits
            if keep and settled.to_room:
                behind.submit(_add_keyframe, room, room_map, closer, result, colour, frame, i, cfg)
            results.append(result)
            stamps.append(frame.timestamp)
            if settled.fuse:
                T, kf_id = result.T_world_camera, result.keyframe_id
                behind.submit(world_map.fuse, colour, depth, K, T, kf_id)
            for kept, T in settled.merged:
                behind.submit(world_map.fuse, kept.colour, kept.depth, K, T, kept.keyframe_id)
            bar.set_postfix(
                state=result.state.value,
                inliers=result.inliers,
                kf=len(room.keyframes),
                refresh=False,
            )
        behind.join()
    except BaseException:
        behind.cancel()
        raise
    finally:
        frames.close()
    room.map = room_map
    trajectory = Trajectory(
        np.array(stamps).reshape(-1),
        np.array([r.T_world_camera for r in results]).reshape(-1, 4, 4),
    )
    loops = None
    if closer is not None:
        odometry = trajectory
        trajectory, moves = _close_loops(closer, room, results, trajectory)
        if moves:  # the map follows the corrected poses: each keyframe's frames move with it
            world_map = world_map.moved(moves)
        loops = {"found": len(closer.loops), "edges": [[e.old, e.new] for e in closer.loops]}
        if dataset.ground_truth is not None and len(odometry) > 1 and closer.loops:
            loops["odometry_metrics"] = evaluate(dataset.ground_truth, odometry)
    run = OdometryRun(trajectory, results, world_map, room)
    if dataset.ground_truth is not None and len(trajectory) > 1:
        run.metrics = evaluate(dataset.ground_truth, trajectory)
    times = np.array([r.timings_ms.get("total", 0.0) for r in results[1:]] or [0.0])
    run.summary = {
        "frames": n,
        # made by this run (a room's own keyframes not counted)
        "keyframes": (
            tracker.keyframe_count
            if isinstance(tracker, Tracker)
            else sum(r.new_keyframe for r in results)
        ),
        "room_keyframes": len(room.keyframes),
        "states": dict(Counter(r.state.value for r in results)),
        # frames that repeated the one before's colour or depth, held at its pose
        "repeated": dict(Counter(r.repeated for r in results if r.repeated is not None)),
        "median_ms": float(np.median(times)),
        "p90_ms": float(np.percentile(times, 90)),
        # The phone's odometry as the prior: frames that carried it, and frames whose initial
        # guess came from it (the rest fell back to constant velocity).
        "device_prior": {
            "frames": with_device_pose,
            "guesses": sum(r.prior_used for r in results),
        },
    }
    if loops is not None:
        run.summary["loops"] = loops
    if isinstance(tracker, RoomTracker):
        run.summary["relocalisation"] = _relocalisation_summary(tracker, start)
    room.sessions.append(
        {
            "dataset": str(dataset.path),
            "frames": n,
            "tracked": len(results),
            "keyframes_after": len(room.keyframes),
        }
    )
    return run


def _add_keyframe(
    room: Room,
    room_map: TSDFMap | None,
    closer: LoopCloser | None,
    result: TrackResult,
    colour: np.ndarray,
    frame: RGBDFrame,
    index: int,
    cfg: RegistrationConfig,
) -> None:
    """A new keyframe into the room (its place features computed), its map, and the loop
    closer; runs behind tracking."""
    room.add_tracked(result, colour, frame.depth, index, cfg)
    kf = room.keyframes[-1]
    kf.encoded()  # the images as the room's file holds them, ready for save_room
    if room_map is not None:
        room.fuse_into(room_map, [kf])
    if closer is not None:
        depth = clean_depth(frame.depth, cfg.depth)
        closer.add_keyframe(kf.id, kf.T_world_keyframe, kf.place, depth)


def _close_loops(
    closer: LoopCloser, room: Room, results: list[TrackResult], trajectory: Trajectory
) -> tuple[Trajectory, dict[int, FloatArray]]:
    """Optimise the pose graph and move every frame with its keyframe: each frame keeps its
    pose relative to the keyframe it was tracked against; the room's keyframes take the
    corrected poses (its map is re-fused from them when saved). Returns the trajectory and each
    moved keyframe's correction T_corrected_tracked (4x4, metres; none without loops)."""
    if not closer.loops:
        return trajectory, {}
    corrected = closer.optimise()
    moves = {
        kf.id: corrected[kf.id] @ invert(kf.T_world_keyframe)
        for kf in room.keyframes
        if kf.id in corrected
    }
    poses = trajectory.poses.copy()
    for k, r in enumerate(results):
        if r.keyframe_id in moves:
            poses[k] = moves[r.keyframe_id] @ poses[k]
    for kf in room.keyframes:
        if kf.id in corrected:
            kf.T_world_keyframe = corrected[kf.id]
    room.map = None
    return Trajectory(trajectory.timestamps.copy(), poses), moves


def _relocalisation_summary(tracker: RoomTracker, start: int) -> dict:
    """frame: the frames it took before one was recognised (0: the first); sequence_frame: that
    frame's index in the sequence; ms: its place recognition, verification and tracking."""
    found = tracker.relocalisation
    if found is None:
        return {"relocalised": False, "attempts": tracker.attempts}
    return {
        "relocalised": True,
        "frame": found.frame,
        "sequence_frame": start + found.frame,
        "keyframe": found.match.keyframe_id,
        "inliers": found.match.inliers,
        "ms": round(found.ms, 1),
        "total_ms": round(found.total_ms, 1),
    }


def write_outputs(
    run: OdometryRun,
    out_dir: Path,
    dataset: RGBDDataset,
    config: RegistrationConfig,
    mesh: bool = False,
    save_room: bool = True,
) -> dict:
    """Write trajectory.tum, map.ply, trajectory.png and summary.json into ``out_dir``, and the
    run's room, when it kept keyframes and ``save_room``, into ``out_dir/room`` (see
    server/rooms/room.py). With ``mesh``, also the surface of a TSDF fused from the keyframes,
    upright: mesh.ply (z up) and mesh.glb (y up, glTF's axes; server/mapping/mesh_files.py);
    summary.json's ``upright`` then holds R_upright_world and where up came from."""
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {
        "trajectory": out_dir / "trajectory.tum",
        "map": out_dir / "map.ply",
        "picture": out_dir / "trajectory.png",
        "summary": out_dir / "summary.json",
    }
    write_tum(paths["trajectory"], run.trajectory)
    run.map.write_ply(paths["map"])
    curves = {"estimate": run.trajectory.poses}
    gt = dataset.ground_truth
    if gt is not None:
        t0, t1 = run.trajectory.timestamps[0] - 0.02, run.trajectory.timestamps[-1] + 0.02
        within = (gt.timestamps >= t0) & (gt.timestamps <= t1)
        curves = {"ground truth": gt.poses[within], **curves}
    plot_top_view(paths["picture"], curves, run.map.points, title=f"{dataset.name}: top view")
    if run.room.keyframes and save_room:
        paths["room"] = out_dir / "room"
        run.summary["room_bytes"] = write_room(run.room, paths["room"])
    if mesh:
        paths |= _write_mesh(run, out_dir, dataset)
    summary = {
        "dataset": str(dataset.path),
        **run.summary,
        "metrics": run.metrics,
        "config": config.to_dict(),
    }
    paths["summary"].write_text(json.dumps(summary, indent=2))
    return paths


def _write_mesh(run: OdometryRun, out_dir: Path, dataset: RGBDDataset) -> dict[str, Path]:
    """mesh.ply and mesh.glb of a TSDF fused from the keyframes at their final poses, upright
    (server/mapping/upright.py): up from the phone's gravity when the recording has device
    poses, else from the map's floors and table tops, else the first camera's -y. Nothing
    (logged) when there is no surface to mesh."""
    # Each surface is seen by few keyframes (they are made as the view changes): one
    # observation is enough here, where the live map, fed every 3rd frame, asks for 3.
    tsdf = TSDFMap(replace(TSDFConfig(), min_weight=0.5))  # Open3D keeps weights above it
    run.room.fuse_into(tsdf, run.room.keyframes)
    surface = tsdf.mesh()
    if not surface.has_triangles() or len(run.trajectory) == 0:
        log.warning("%s: the keyframes hold no surface to mesh: no mesh written", dataset.name)
        return {}
    R_upright_world, source = upright_frame(
        run.trajectory.poses[0],
        np.asarray(surface.vertices),
        np.asarray(surface.triangles),
        gravity_in_world(dataset, run.trajectory),
    )
    run.summary["upright"] = {"source": source.value, "R_upright_world": R_upright_world.tolist()}
    return write_upright(out_dir, surface, R_upright_world)


def gravity_in_world(dataset: RGBDDataset, trajectory: Trajectory) -> FloatArray | None:
    """Gravity's direction (unit) in the run's world frame, from the phone's own pose at the
    first tracked frame (ARKit's world is y up); None without device poses there."""
    device = dataset.device_poses
    if device is None or len(device) == 0 or len(trajectory) == 0:
        return None
    nearest = int(np.argmin(np.abs(device.timestamps - trajectory.timestamps[0])))
    if abs(device.timestamps[nearest] - trajectory.timestamps[0]) > 0.02:
        return None
    R_world_camera = trajectory.poses[0][:3, :3]
    R_device_camera = device.poses[nearest][:3, :3]
    return R_world_camera @ (R_device_camera.T @ ARKIT_GRAVITY)
