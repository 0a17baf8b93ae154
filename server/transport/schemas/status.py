"""``GET /api/sessions/{id}``: a session's status and the parts it is made of."""

from __future__ import annotations

from pydantic import Field

from server.transport.schemas.common import WireModel
from server.transport.schemas.rooms import SharedRoom


class Intrinsics(WireModel):
    """The camera of the session's hello: pixels of the colour image."""

    fx: float = Field(description="focal length along x, px")
    fy: float = Field(description="focal length along y, px")
    cx: float = Field(description="principal point x, px (pixel centres at integers)")
    cy: float = Field(description="principal point y, px")
    width: int = Field(description="colour image width, px")
    height: int = Field(description="colour image height, px")


class MapStats(WireModel):
    """The session's TSDF map (Open3D VoxelBlockGrid)."""

    frames_integrated: int = Field(description="frames fused into the map so far")
    active_blocks: int = Field(description="voxel blocks holding data")
    capacity_blocks: int = Field(description="voxel blocks allocated (grows on demand)")
    voxel_m: float = Field(description="TSDF voxel edge, m")
    memory_bytes: int = Field(description="approximate memory of the block buffers, bytes")


class DroneSummary(WireModel):
    """The session's drone: ``{"spawned": false}`` until it appears (with the first map);
    the other fields only once it has."""

    spawned: bool = Field(description="the drone has appeared (drone_event 'spawned' was sent)")
    mode: str | None = Field(
        None,
        description="flight mode as drone_state.mode: landed, hover, manual, goto, landing, "
        "crashed, faulted",
    )
    position: list[float] | None = Field(
        None,
        min_length=3,
        max_length=3,
        description="[x, y, z] of the drone's centre, world frame, m",
    )
    clearance_m: float | None = Field(
        None,
        description="distance from the drone's centre to the nearest occupied or unobserved "
        "cell of the flight map, m",
    )
    damage: float | None = Field(
        None, description="damage points from bumps since the drone spawned (drone_state.damage)"
    )
    events: dict[str, int] | None = Field(
        None, description="drone_event messages sent so far, by event name"
    )
    errors: int = Field(0, description="simulation steps that failed (flight_errors)")
    map_frames: int = Field(
        0,
        description="frames this session fused that the drone's flight map holds; in a "
        "session of its own it has caught up with the map when this equals "
        "map.frames_integrated (it is updated at most every flight_map_interval_s while frames "
        "come, and once more when they stop); in a room, map.frames_integrated also counts the "
        "room's frames and the other phones'",
    )
    fault: str | None = Field(
        None,
        description="why the drone was stopped for good after failing steps (mode faulted); "
        "null while it flies",
    )
    corrections: int = Field(
        0,
        description="rebuilt maps (loop closures) whose full occupancy replaced the flight map, "
        "the drone moving with the corrected world",
    )


class LoopClosure(WireModel):
    """Online loop closure in a live session (PROTOCOL.md, "Loop closure")."""

    enabled: bool = Field(
        description="loop closure runs in this session (registration.loops.live, with rooms "
        "kept and not continuing in a saved room)"
    )
    keyframes: int = Field(description="keyframes looked up in the place database so far")
    queued: int = Field(
        0, description="keyframes waiting for the loop thread (it runs below the map's priority)"
    )
    found: int = Field(description="verified loops (edges added to the pose graph)")
    refused: int = Field(description="keyframes whose loop candidates verification refused")
    corrections: int = Field(description="pose-graph optimisations that corrected the world")
    last_optimise_ms: float | None = Field(
        None, description="wall time of the latest pose-graph optimisation, ms"
    )
    last_optimise_cpu_ms: float | None = Field(
        None, description="the loop thread's CPU time for the latest optimisation, ms"
    )
    lookup_cpu_ms: float | None = Field(
        None,
        description="CPU time per keyframe, on average: its cloud, odometry edge, place lookup "
        "and verification, ms",
    )
    rebuilds: int = Field(description="maps rebuilt from the corrected keyframes and swapped in")
    rebuild_pending: bool = Field(
        False,
        description="a correction waits for its map rebuild, or a rebuild is in progress; "
        "false once the newest correction's rebuild was swapped in (its map_chunk with reset "
        "sent), skipped (rebuilds_skipped) or failed (failures.loops_failed)",
    )
    rebuilds_skipped: int = Field(
        0,
        description="corrections that moved no keyframe by more than mapping.rebuild_min_move_m "
        "from its pose in the map, which was therefore not re-fused",
    )
    rebuilds_cpu_ms: float = Field(
        0.0, description="the mapping process's CPU time over every rebuild so far, ms"
    )
    map_behind_m: float = Field(
        0.0,
        description="the most the corrections since the map was last fused moved a keyframe "
        "(its camera's shift plus its turn times 2 m), m; 0 right after a rebuild",
    )
    last_rebuild_ms: float | None = Field(
        None, description="wall time of the latest rebuild, from its start to the swap, ms"
    )
    last_rebuild_cpu_ms: float | None = Field(
        None, description="the mapping process's CPU time for the latest rebuild's keyframes, ms"
    )
    last_rebuild_keyframes: int | None = Field(
        None, description="keyframes re-read and fused by the latest rebuild"
    )


class Failures(WireModel):
    """Failures on the server's side, counted per session (PROTOCOL.md, "Failures"); a client
    must ignore names it does not know."""

    frames_failed: int = Field(description="frames answered internal_error (decode or track)")
    fusions_failed: int = Field(description="tracked frames that failed to fuse: not in the map")
    flight_map_failed: int = Field(description="occupancy updates for the drone that failed")
    flight_errors: int = Field(description="drone simulation steps that failed")
    snapshots_failed: int = Field(description="periodic or final snapshots that failed")
    sends_failed: int = Field(description="connections ended with send_failed (close 4011)")
    room_keyframes_failed: int = Field(
        0, description="keyframes that could not be written to the session's room"
    )
    loops_failed: int = Field(
        0,
        description="keyframes the loop closer failed on, and map rebuilds that failed (the "
        "session goes on with the map it had)",
    )


class WorkerInfo(WireModel):
    """Where a live session runs."""

    kind: str = Field(description="process (a local worker process) or ray (a Ray actor)")
    threads: int = Field(description="native threads (OpenCV, BLAS) of its thread pools")
    pid: int | None = Field(
        None,
        description="the worker's process id (for Ray, on the actor's node: a child of the "
        "actor's process)",
    )
    mapper_pid: int | None = Field(
        None,
        description="the session's mapper process id (for Ray, on the actor's node: a child "
        "of the actor's process)",
    )
    loops_pid: int | None = Field(
        None,
        description="sessions that close loops online: the session's loop process id",
    )
    actor_pid: int | None = Field(
        None, description="Ray: the actor's process id, which relays to the worker"
    )
    node_id: str | None = Field(None, description="Ray: the node the actor runs on")
    node_ip: str | None = Field(None, description="Ray: that node's address")


class DevicePoseUse(WireModel):
    """How the tracker used the phone's own pose (frame.T_device_camera, PROTOCOL.md)."""

    frames: int = Field(description="processed frames that carried T_device_camera")
    guesses: int = Field(
        description="of those, frames whose initial guess came from the device pose's motion "
        "(the rest fell back to constant velocity: the first frame, a device pose that jumped, "
        "or registration.prior.enabled false)"
    )
    world_changes: int = Field(
        0,
        description="frames whose device_world differed from the frame before: the device's own "
        "tracking restarted (its prior's alignment to the map started again)",
    )


class TrackingRecovery(WireModel):
    """How tracking recovered from losses (registration.relocalise, PROTOCOL.md's pose
    ``recovery``)."""

    relocalised: int = Field(description="frames found again by place recognition")
    segments: int = Field(
        description="map segments started after a loss nothing recovered (tracked apart, weak, "
        "not fused, until they merge)"
    )
    merged: int = Field(description="segments merged into the map")
    in_segment: int = Field(description="frames tracked in a segment not merged yet")
    segment_frames_fused: int = Field(
        0,
        description="keyframes of merged segments fused into the map (and the drone's map) at "
        "their corrected poses after the merge",
    )


class SessionStatus(WireModel):
    """``GET /api/sessions/{id}``: a live session's figures now, or a closed session's as its
    final snapshot saved them."""

    id: str = Field(description="the session's id")
    created_at: float = Field(description="creation time, Unix seconds (the server's clock)")
    closed: bool = Field(
        description="true once the session was closed and saved: its final snapshot is on "
        "disk and no frame is taken any more. A `bye` does NOT close it: a session with no "
        "connection and no frame is closed after the server's session_ttl_s (300 s by "
        "default), or at server shutdown; DELETE removes it instead"
    )
    client_name: str = Field(description="hello.client_name of the latest hello; '' before one")
    frames_received: int = Field(
        description="frame messages accepted from the client(s) over all connections"
    )
    frames_processed: int = Field(description="frames tracked: each got a pose")
    frames_dropped: int = Field(
        description="frames dropped unprocessed because a newer one arrived (newest wins); "
        "as pose.dropped"
    )
    frames_failed: int = Field(
        description="frames the server failed on (each answered with internal_error)"
    )
    fusion_skipped: int = Field(
        description="tracked frames not fused into the map because the mapper was behind"
    )
    fusion_waiting: int = Field(
        0,
        description="tracked frames still on their way into the map: queued for the mapping "
        "thread or being fused (a frame counts from its pose until it is fused or known not to "
        "be). 0: the map (map.frames_integrated) holds every frame it will take of those "
        "processed so far",
    )
    frames_repeated: int = Field(
        0,
        description="frames whose colour or depth image was the very same as the frame before's: "
        "colour and depth of two moments, so held at the previous pose (moved by the device's "
        "own motion when the frame carries T_device_camera; state as before), not tracked or "
        "fused (registration.state.hold_repeated_frames)",
    )
    fusion_failed: int = Field(description="frames whose fusion into the map failed (logged)")
    tracking_states: dict[str, int] = Field(
        description="processed frames by tracking state: ok, weak, lost"
    )
    recovery: TrackingRecovery | None = Field(
        None,
        description="recovery from lost tracking (absent in the snapshots of sessions saved "
        "before it was counted)",
    )
    trajectory_poses: int = Field(description="lines of trajectory.tum: one per processed frame")
    device_pose: DevicePoseUse | None = Field(
        None,
        description="the phone's own pose as the tracker's prior (absent in the snapshots of "
        "sessions saved before it was counted)",
    )
    map: MapStats = Field(description="the TSDF map's figures")
    intrinsics: Intrinsics | None = Field(description="the hello's camera; null before a hello")
    gravity: list[float] | None = Field(
        None,
        min_length=3,
        max_length=3,
        description="the first hello's gravity: its direction (unit) in the first camera's frame "
        "(x right, y down, z forward), which is the world frame unless the session continues a "
        "room; the down of the drone and of `mesh.ply?frame=upright` and `mesh.glb`. Null when "
        "the client sent none (absent in snapshots saved before it was kept)",
    )
    drone: DroneSummary | None = Field(
        description="the drone; null before the first hello (or with the simulation off)"
    )
    snapshot_error: str | None = Field(
        description="why the latest snapshot failed (disk full, ...), null when it succeeded"
    )
    tracking_lost: bool = Field(
        False,
        description="the latest frame was lost: poses hold the last good one and the map takes "
        "no frames until tracking recovers (false for a closed session)",
    )
    worker: WorkerInfo | None = Field(
        None, description="live sessions only: where the session runs"
    )
    shared_room: SharedRoom | None = Field(
        None,
        description="live sessions only: the shared room it invited phones into, or joined; "
        "absent otherwise",
    )
    placed: bool | None = Field(
        None,
        description="a session continuing in a room (saved, or joined live): whether a frame "
        "was recognised in the room yet (until then its frames are answered `lost` and fuse "
        "nothing); absent otherwise",
    )
    failures: Failures | None = Field(
        None,
        description="the session's failure counts so far, as pose.failures (absent in the "
        "snapshots of sessions saved before the counts existed)",
    )
    loops: LoopClosure | None = Field(
        None,
        description="online loop closure (absent in the snapshots of sessions saved before it "
        "existed)",
    )
    failure: str | None = Field(
        None,
        description="why the session ended early: its worker, mapping process or mapping "
        "thread died (session_failed). Its files are those of its last snapshot; the "
        "trajectory reaches the last pose when the worker itself survived",
    )
