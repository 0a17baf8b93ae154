"""What the REST API returns, as pydantic models: the wire schemas of ``/docs`` (OpenAPI).

The routes return the bodies the sessions assemble (in their worker processes) unchanged; these
models describe them for clients, and the tests check every body against them. Fields are
declared with units and frames. A client must ignore fields it does not know (``extra``
allowed): later versions may add counters. Positions are in the session's world frame (the
camera frame of its first tracked frame, metres; see ``shared/PROTOCOL.md``).
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class _Body(BaseModel):
    model_config = ConfigDict(extra="allow")


class SessionCreate(_Body):
    """The optional body of ``POST /api/sessions``."""

    room: str | None = Field(
        None,
        description="continue in the room a closed session saved: that session's id. The "
        "request's `Authorization: Bearer <token>` must be that session's token. The new "
        "session relocalises its first frames in the room and tracks in its world frame; the "
        "map and the drone's map start as the room's",
        pattern="^[0-9a-f]{16}$",
    )
    loop_closure: bool | None = Field(
        None,
        description="close loops in this session: when the camera comes back to a place it "
        "saw, the keyframes are corrected, the map re-fused and `map_corrected` sent (PROTOCOL.md, "
        '"Loop closure"; costs the server ~0.1 s of CPU per keyframe and a re-fuse per loop). '
        "null: the server's setting (`registration.loops.live`). Not in a session continuing "
        "in a room",
    )


class SessionCreated(_Body):
    """``POST /api/sessions`` answers 201 with this body."""

    id: str = Field(
        description="the session's id: 16 lowercase hex digits; {id} of every session URL",
        pattern="^[0-9a-f]{16}$",
    )
    token: str = Field(
        description="the session's secret (256 bits, URL-safe base64), shown only in this "
        "answer: every other call needs it, as `Authorization: Bearer <token>` on REST and "
        "as `?token=` on the WebSocket. The server keeps only its SHA-256",
    )
    websocket: str = Field(
        description="URL of the session's WebSocket, ws:// or wss:// as the request came in "
        "(`/ws/sessions/{id}`), WITHOUT the token: append `?token=<token>` to connect",
    )
    room: str | None = Field(
        None, description="the room this session continues in (a session id), or null"
    )
    loop_closure: bool = Field(
        False, description="loop closure runs in this session (asked for, or the server's setting)"
    )


class ErrorDetail(_Body):
    code: str = Field(
        description="unauthorized (401: no token), not_found (404: unknown id or wrong token, "
        "the same answer), rate_limited (429, with a Retry-After header in seconds), "
        "server_full (503: the server holds its maximum of live sessions), map_unavailable "
        "(409: no map surface fused yet), room_unavailable (409: the session named as a room "
        "saved none, or is still live), session_failed (400: the session's worker died "
        "during the request), session_closed (409: a viewer link asked of a closed session), "
        "too_many_viewers (409: the session has max_viewers links)"
    )
    message: str = Field(description="human-readable explanation")


class ErrorBody(_Body):
    """Every REST error (4xx/5xx) carries this body."""

    error: ErrorDetail


def error_response(description: str) -> dict:
    """A route's documented error answer (FastAPI ``responses`` entry): ErrorBody, and when."""
    return {"model": ErrorBody, "description": description}


class Intrinsics(_Body):
    """The camera of the session's hello: pixels of the colour image."""

    fx: float = Field(description="focal length along x, px")
    fy: float = Field(description="focal length along y, px")
    cx: float = Field(description="principal point x, px (pixel centres at integers)")
    cy: float = Field(description="principal point y, px")
    width: int = Field(description="colour image width, px")
    height: int = Field(description="colour image height, px")


class MapStats(_Body):
    """The session's TSDF map (Open3D VoxelBlockGrid)."""

    frames_integrated: int = Field(description="frames fused into the map so far")
    active_blocks: int = Field(description="voxel blocks holding data")
    capacity_blocks: int = Field(description="voxel blocks allocated (grows on demand)")
    voxel_m: float = Field(description="TSDF voxel edge, m")
    memory_bytes: int = Field(description="approximate memory of the block buffers, bytes")


class DroneSummary(_Body):
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
        description="fused frames the drone's flight map holds; it has caught up with the map "
        "when this equals map.frames_integrated (it is updated at most every "
        "flight_map_interval_s while frames come, and once more when they stop)",
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


class LoopClosure(_Body):
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


class CourseResult(_Body):
    """One finished course run (PROTOCOL.md, "Courses")."""

    score: int = Field(description="the run's score (the course message's formula), >= 0")
    time_s: float = Field(description="simulation time from the start to the last gate, s")
    par_s: float = Field(description="the course's own route's time to its last gate, s")
    gates: int = Field(description="gates in the course")
    passed: int = Field(description="gates flown through in order")
    missed: int = Field(description="gates left out")
    bumps: int = Field(description="collision events during the run")
    crashes: int = Field(description="crash events during the run")
    difficulty: str = Field(description="easy, medium, hard, or custom")
    seed: int = Field(description="the course generator's seed")
    autopilot: bool = Field(description="the planner flew it (a demonstration), not the pilot")
    finished_at: float = Field(description="when it finished, Unix seconds (the server's clock)")


class CourseBest(_Body):
    """``GET /api/sessions/{id}/course/best``: the session's best finished runs."""

    results: list[CourseResult] = Field(
        description="at most 10, highest score first (equal scores: the faster, then the "
        "earlier); kept in the session's files, so they outlast restarts"
    )


class Failures(_Body):
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


class WorkerInfo(_Body):
    """Where a live session runs."""

    kind: str = Field(description="process (a local worker process) or ray (a Ray actor)")
    threads: int = Field(description="native threads (OpenCV, BLAS) of its thread pools")
    pid: int | None = Field(None, description="the worker's process id (on its node, for Ray)")
    mapper_pid: int | None = Field(
        None, description="process workers: the session's mapper process id"
    )
    loops_pid: int | None = Field(
        None,
        description="process workers of sessions that close loops online: the session's loop "
        "process id",
    )
    node_id: str | None = Field(None, description="Ray: the node the actor runs on")
    node_ip: str | None = Field(None, description="Ray: that node's address")


class DevicePoseUse(_Body):
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


class TrackingRecovery(_Body):
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


class SessionStatus(_Body):
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


class RecordingCreated(_Body):
    """``POST /api/recordings`` answers 201 with this body once the upload is converted."""

    id: str = Field(
        description="the recording's id: 16 lowercase hex digits", pattern="^[0-9a-f]{16}$"
    )
    token: str = Field(
        description="the recording's secret, shown only in this answer: reading the index and "
        "its files needs `Authorization: Bearer <token>`. The server keeps only its SHA-256",
    )
    index: str = Field(description="URL of the replay's index (`GET`, with the token)")
    name: str = Field(description="the recording's name (the .r3d file's or the export's folder)")
    frames: int = Field(description="frames converted")


class RecordingFrame(_Body):
    """One frame of a recording's replay index."""

    timestamp: float = Field(description="capture time, seconds (the phone's clock)")
    colour: str = Field(description="URL of the colour JPEG (needs the token)")
    depth: str = Field(description="URL of the 16-bit depth PNG, units of depth_scale")
    T_device_camera: list[float] | None = Field(
        None,
        min_length=16,
        max_length=16,
        description="the phone's own camera pose (ARKit odometry) in its world, 4x4 "
        "camera-to-world, row-major, metres, this protocol's camera axes (x right, y down, "
        "z forward): sent as frame.T_device_camera",
    )


class RecordingIndex(_Body):
    """``GET /api/recordings/{id}``: what the page's replay needs, as ``/api/demo`` gives."""

    id: str = Field(description="the recording's id")
    name: str = Field(description="the recording's name")
    intrinsics: list[float] = Field(
        min_length=4, max_length=4, description="[fx, fy, cx, cy] of the colour image, px"
    )
    colour_size: list[int] = Field(min_length=2, max_length=2, description="[width, height], px")
    depth_size: list[int] = Field(min_length=2, max_length=2, description="[width, height], px")
    depth_scale: float = Field(description="depth PNG units per metre (1000: millimetres)")
    depth_format: str = Field(description="png")
    fps: float = Field(description="frames per second as recorded")
    gravity: list[float] | None = Field(
        None,
        description="gravity in the first camera's frame (unit vector), from ARKit's y-up world",
    )
    frames: list[RecordingFrame] = Field(description="the frames in order")


class FlightSummary(_Body):
    """One recorded flight in ``GET /api/sessions/{id}/flights``."""

    id: str = Field(description="the flight's id within the session: 1, 2, ... in order")
    started_at: float = Field(description="when the flight opened, Unix seconds (server clock)")
    duration_s: float = Field(description="simulation time from its first entry to its last, s")
    finished: bool = Field(
        description="false: the flight was in progress when saved (it is saved with every "
        "snapshot and again when it ends)"
    )
    end: str | None = Field(
        description="why it ended: landed, faulted, course_finished, session_end; in_progress "
        "while it goes on"
    )
    states: int = Field(description="drone states recorded (rows of the CSV)")
    events: int = Field(description="drone events recorded")
    commands: int = Field(description="pilot commands recorded")
    has_course: bool = Field(description="a course was being flown (the JSON holds it)")
    result: dict | None = Field(
        description="the course's result as the course judge gave it (time_s, gates_passed, "
        "gates_missed, collisions, score, ...), null without one"
    )
    bytes: int = Field(description="size of the flight's JSON, bytes")


class FlightList(_Body):
    """``GET /api/sessions/{id}/flights``: the session's saved flights, oldest first."""

    flights: list[FlightSummary] = Field(description="at most the server's flights_kept, newest")


class FlightEvent(_Body):
    """A drone_event during the flight."""

    t: float = Field(description="simulation time, s")
    event: str = Field(description="drone_event.event")
    position: list[float] = Field(
        min_length=3, max_length=3, description="drone position, world frame, m"
    )
    message: str = Field(description="drone_event.message")
    command_id: int | None = Field(description="the command it concerns, if any")


class FlightCommand(_Body):
    """A pilot command the drone accepted, with the fields it was sent with (target, pixel,
    seq, sticks, speed: those given, as in the protocol's `command`)."""

    t: float = Field(description="simulation time it arrived at, s")
    name: str = Field(description="command.name")
    id: int = Field(description="command.id")


class FlightRecordingBody(_Body):
    """``GET /api/sessions/{id}/flights/{flight_id}.json``: one flight, whole."""

    format: str = Field(description="dronesim-flight/1")
    id: str = Field(description="the flight's id")
    started_at: float = Field(description="when it opened, Unix seconds (server clock)")
    start_time_s: float = Field(description="simulation time of its first entry, s")
    end_time_s: float = Field(description="simulation time of its last entry, s")
    duration_s: float = Field(description="end_time_s - start_time_s, s")
    finished: bool = Field(description="false while it was in progress when saved")
    end: str | None = Field(
        description="landed, faulted, course_finished, session_end, in_progress"
    )
    state_hz: float = Field(description="drone states per second (the server's drone_state_hz)")
    state_columns: list[str] = Field(
        description="the columns of each row of states: t (simulation time, s), x y z (drone "
        "centre, world frame, m), vx vy vz (velocity, world frame, m/s), qx qy qz qw (unit "
        "quaternion of T_world_drone's rotation, w >= 0), mode (drone_state.mode)"
    )
    states: list[list[float | str]] = Field(description="one row per drone state, in order")
    events: list[FlightEvent] = Field(description="drone events, in order")
    commands: list[FlightCommand] = Field(description="accepted pilot commands, in order")
    course: dict | None = Field(description="the course flown (as the course module gave it)")
    result: dict | None = Field(description="the course's result, when the course finished")
    truncated: bool = Field(
        description="the flight outlasted flight_max_s (or its event/command caps): later "
        "entries were not kept"
    )


class ViewerCreated(_Body):
    """``POST /api/sessions/{id}/viewers`` answers 201 with this body."""

    viewer_id: str = Field(description="names the viewer link (8 hex digits), for DELETE")
    viewer_token: str = Field(
        description="the viewer link's secret (256 bits, URL-safe base64), shown only here; "
        "the server keeps only its SHA-256. It opens the read-only socket and nothing else"
    )
    url: str = Field(
        description="the phone page opened as a viewer: `http(s)://host:port/#watch=<id>&token="
        "<viewer_token>` (in the fragment, which browsers never send to a server)"
    )
    websocket: str = Field(
        description="the viewer socket's URL without the token (`/ws/sessions/{id}/view`): "
        "append `?token=<viewer_token>`"
    )


class ViewerList(_Body):
    """``GET /api/sessions/{id}/viewers``: the session's viewer links."""

    viewers: list[str] = Field(description="viewer_id of every link not revoked")


class PhoneLinkBody(_Body):
    """``GET /api/phone-link``: how a phone on the local network opens this server (the link
    and notes ``serve`` prints)."""

    urls: list[str] = Field(
        description="the page's URLs on this machine's LAN addresses (and the hosts the "
        "operator named, `server.phone_hosts`), best first; `/api/phone-link.svg` is the first's "
        "QR code. Empty when no phone can reach the server (it listens on loopback only)"
    )
    tls: bool = Field(description="served over HTTPS (a secure origin: camera and depth work)")
    notes: list[str] = Field(description="what the phone's user must know, a sentence each")
