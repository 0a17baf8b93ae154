"""Messages: builders from numpy data, msgpack packing and unpacking (each checked against
protocol.json), and readers of the fields that carry arrays."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import msgpack
import numpy as np
from numpy.typing import ArrayLike

from server.protocol.codecs import encode_depth, encode_jpeg
from server.protocol.errors import ProtocolError, check_raw
from server.protocol.errors import floats as _floats
from server.protocol.errors import new_message as _message
from server.protocol.schema import validate
from server.protocol.spec import LIMITS, VERSION


def encode(message: dict, *, max_bytes: int | None = None) -> bytes:
    """Validate (strictly) and pack one message; raises ProtocolError."""
    validate(message, strict=True)
    data = msgpack.packb(message, use_bin_type=True)
    limit = LIMITS["max_message_bytes"] if max_bytes is None else max_bytes
    if len(data) > limit:
        raise ProtocolError("message_too_big", f"{len(data)} bytes, limit {limit}")
    return data


def decode(data: object, *, direction: str | None = None, max_bytes: int | None = None) -> dict:
    """Unpack and validate one message; the size limit is checked before unpacking. ``data`` is
    whatever the socket gave: anything but bytes (a text frame) is a malformed_message."""
    check_raw(data, max_bytes)
    try:
        message = msgpack.unpackb(data, raw=False, strict_map_key=True)
    except (ValueError, TypeError, OverflowError, msgpack.UnpackException) as exc:
        raise ProtocolError("malformed_message", f"not one msgpack object: {exc}") from exc
    try:
        return validate(message, direction)
    except ProtocolError as exc:
        # A refused command names itself when its id can be read, as the spec promises the
        # pilot (a command error carries command_id).
        if isinstance(message, dict) and message.get("type") == "command":
            command_id = message.get("id")
            if type(command_id) is int:
                exc.command_id = command_id
        raise


# ---- message builders ----------------------------------------------------------------------------


def make_hello(
    client_name: str,
    intrinsics: ArrayLike,
    colour_size: Sequence[int],
    depth_size: Sequence[int] | None = None,
    depth_scale: float = 1000.0,
    version: int = VERSION,
    gravity: ArrayLike | None = None,
    recorded: bool = False,
) -> dict:
    """intrinsics: fx, fy, cx, cy of the colour image (px); sizes (width, height) px;
    depth_size defaults to colour_size; depth_scale: depth units per metre; gravity: its
    direction in the first camera's frame (None: the server assumes +y); recorded: the frames
    come from a recording, to be queued rather than dropped (see ``queued_frames``)."""
    depth_size = colour_size if depth_size is None else depth_size
    return _message(
        "hello",
        version=int(version),
        client_name=client_name,
        intrinsics=_floats(intrinsics, 4, "intrinsics"),
        colour_size=[int(v) for v in colour_size],
        depth_size=[int(v) for v in depth_size],
        depth_scale=float(depth_scale),
        gravity=None if gravity is None else _floats(gravity, 3, "gravity"),
        recorded=True if recorded else None,
    )


def make_frame(
    seq: int,
    timestamp: float,
    colour_rgb: np.ndarray,
    depth_m: np.ndarray,
    depth_format: str = "png",
    jpeg_quality: int = 80,
    depth_scale: float = 1000.0,
    T_device_camera: ArrayLike | None = None,
    device_world: int | None = None,
) -> dict:
    """A frame message: colour (H, W, 3) uint8 RGB as JPEG, depth (h, w) metres as uint16;
    T_device_camera: the device's own 4x4 camera pose in its world (metres, this protocol's
    camera axes), or None; device_world: which of the device's worlds that is (a new number
    after its own tracking restarted), or None."""
    return _message(
        "frame",
        seq=int(seq),
        timestamp=float(timestamp),
        colour=encode_jpeg(colour_rgb, jpeg_quality),
        depth=encode_depth(depth_m, depth_format, depth_scale),
        depth_format=depth_format,
        depth_scale=float(depth_scale),
        T_device_camera=None
        if T_device_camera is None
        else _floats(T_device_camera, 16, "T_device_camera"),
        device_world=None if device_world is None else int(device_world),
    )


def make_command(
    command_id: int,
    name: str,
    target: ArrayLike | None = None,
    speed: float | None = None,
    *,
    pixel: ArrayLike | None = None,
    seq: int | None = None,
    sticks: ArrayLike | None = None,
    flight_mode: str | None = None,
    **course: str | int | float | bool | None,
) -> dict:
    """target: world [x, y, z] metres (goto); pixel: [u, v] of frame seq (goto_pixel);
    sticks: [throttle, yaw, pitch, roll] in -1..1 (sticks); flight_mode: position, angle or
    acro (flight_mode); ``course``: course_start's difficulty, seed, gates, spacing,
    ring_radius, autopilot (as the protocol names them)."""
    return _message(
        "command",
        id=int(command_id),
        name=name,
        target=None if target is None else _floats(target, 3, "target"),
        pixel=None if pixel is None else _floats(pixel, 2, "pixel"),
        seq=None if seq is None else int(seq),
        sticks=None if sticks is None else _floats(sticks, 4, "sticks"),
        speed=None if speed is None else float(speed),
        flight_mode=flight_mode,
        **course,
    )


def make_bye(reason: str | None = None) -> dict:
    return _message("bye", reason=reason)


def make_welcome(
    session_id: str,
    max_in_flight: int = LIMITS["max_in_flight"],
    max_message_bytes: int = LIMITS["max_message_bytes"],
    map_chunk_max_points: int = LIMITS["max_map_chunk_points"],
    role: str | None = None,
    queued_frames: int | None = None,
) -> dict:
    """role: None for the session's own socket, "viewer" for a viewer link's. queued_frames:
    ``queued_frames(hello)`` for the session's own socket."""
    return _message(
        "welcome",
        version=VERSION,
        session_id=session_id,
        max_in_flight=int(max_in_flight),
        max_message_bytes=int(max_message_bytes),
        map_chunk_max_points=int(map_chunk_max_points),
        role=role,
        queued_frames=None if queued_frames is None else int(queued_frames),
    )


def queued_frames(hello: dict, max_in_flight: int = LIMITS["max_in_flight"]) -> int:
    """How many of a connection's frames the server queues while it is busy: a recording's
    (hello ``recorded``) as many as it may have in flight, so a replay loses none; a live
    camera's one, the newest (an older one still waiting is dropped: latency stays bounded)."""
    return int(max_in_flight) if hello.get("recorded") else 1


def make_pose(
    seq: int,
    timestamp: float,
    T_world_camera: np.ndarray,
    state: str,
    inliers: int,
    timings_ms: Mapping[str, float],
    dropped: int,
    keyframe: bool | None = None,
    failures: Mapping[str, int] | None = None,
    recovery: str | None = None,
) -> dict:
    """T_world_camera: 4x4 (metres), sent row-major; state: ok / weak / lost (or TrackingState);
    failures: the session's failure counts so far, by name (left out when None or empty);
    recovery: relocalised / segment / merged while tracking recovers from a loss (else None,
    left out)."""
    return _message(
        "pose",
        seq=int(seq),
        timestamp=float(timestamp),
        T_world_camera=_floats(T_world_camera, 16, "T_world_camera"),
        state=str(getattr(state, "value", state)),
        inliers=int(inliers),
        timings_ms={str(k): float(v) for k, v in timings_ms.items()},
        dropped=int(dropped),
        keyframe=None if keyframe is None else bool(keyframe),
        failures={str(k): int(v) for k, v in failures.items()} if failures else None,
        recovery=recovery,
    )


def make_drone_state(
    timestamp: float,
    T_world_drone: np.ndarray,
    velocity: ArrayLike,
    mode: str,
    command_id: int | None = None,
    *,
    T_camera_drone: np.ndarray | None = None,
    camera_seq: int | None = None,
    clearance: float | None = None,
    target: ArrayLike | None = None,
    route: np.ndarray | None = None,
    flight_mode: str | None = None,
    attitude: ArrayLike | None = None,
    damage: float | None = None,
) -> dict:
    """Transforms 4x4 (metres, sent row-major); route (N, 3) world metres, at most 512 points;
    flight_mode: position, angle or acro; attitude: [roll, pitch, yaw] degrees (flight frame);
    damage: bump damage points."""
    return _message(
        "drone_state",
        timestamp=float(timestamp),
        T_world_drone=_floats(T_world_drone, 16, "T_world_drone"),
        T_camera_drone=None
        if T_camera_drone is None
        else _floats(T_camera_drone, 16, "T_camera_drone"),
        camera_seq=None if camera_seq is None else int(camera_seq),
        velocity=_floats(velocity, 3, "velocity"),
        mode=str(getattr(mode, "value", mode)),
        flight_mode=None
        if flight_mode is None
        else str(getattr(flight_mode, "value", flight_mode)),
        attitude=None if attitude is None else _floats(attitude, 3, "attitude"),
        clearance=None if clearance is None else float(clearance),
        target=None if target is None else _floats(target, 3, "target"),
        route=None if route is None else np.asarray(route, dtype=np.float64).ravel().tolist(),
        command_id=None if command_id is None else int(command_id),
        damage=None if damage is None else float(damage),
    )


def make_drone_event(
    event: str,
    timestamp: float,
    position: ArrayLike,
    message: str,
    command_id: int | None = None,
) -> dict:
    return _message(
        "drone_event",
        event=str(getattr(event, "value", event)),
        timestamp=float(timestamp),
        position=_floats(position, 3, "position"),
        message=message[:1024],
        command_id=None if command_id is None else int(command_id),
    )


def make_course(
    course_id: int,
    state: str,
    difficulty: str,
    seed: int,
    gates: ArrayLike,
    gate_states: Sequence[str],
    next_gate: int,
    elapsed_s: float,
    par_s: float,
    bumps: int,
    crashes: int,
    score: int,
    autopilot: bool,
    rank: int | None = None,
    command_id: int | None = None,
) -> dict:
    """gates: (N, 7) world frame, per gate centre, unit normal (the way through), radius (m)."""
    return _message(
        "course",
        course_id=int(course_id),
        state=str(state),
        difficulty=str(difficulty),
        seed=int(seed),
        gates=np.asarray(gates, dtype=np.float64).ravel().tolist(),
        gate_states=[str(getattr(s, "value", s)) for s in gate_states],
        next_gate=int(next_gate),
        elapsed_s=max(0.0, float(elapsed_s)),
        par_s=max(0.0, float(par_s)),
        bumps=int(bumps),
        crashes=int(crashes),
        score=int(score),
        autopilot=bool(autopilot),
        rank=None if rank is None else int(rank),
        command_id=None if command_id is None else int(command_id),
    )


def make_room(
    pilots: Sequence[str],
    you: int,
    placed: Sequence[bool],
    modes: Sequence[str],
    drones: ArrayLike,
    cameras: ArrayLike,
    race: Mapping | None = None,
    routes: Sequence[ArrayLike | None] | None = None,
) -> dict:
    """drones, cameras: (N, 7) world frame, per pilot a centre (m) and a unit quaternion
    [qx, qy, qz, qw]; zeros where there is none. race: the room's race (RaceStandings'
    fields: race, number, starts_in_s, gates, and per pilot passed, missed, time_s,
    finished, rank), or None. routes: per pilot its route ahead, (K, 3) world frame metres
    (at most ROOM_ROUTE_POINTS), or None; left out when none has one."""
    n = len(pilots)
    fields: dict = {}
    arrays = [
        np.zeros((0, 3)) if r is None else np.asarray(r, float).reshape(-1, 3) for r in routes or []
    ]
    if any(len(a) for a in arrays):
        flat = np.concatenate(arrays)
        fields["route_lengths"] = [len(a) for a in arrays]
        fields["routes"] = _floats(flat, flat.size, "routes")
    if race is not None:
        fields |= {
            "race": str(race["race"]),
            "race_number": int(race["number"]),
            "race_starts_in_s": max(0.0, float(race["starts_in_s"])),
            "race_gates": int(race["gates"]),
            "race_passed": [int(v) for v in race["passed"]],
            "race_missed": [int(v) for v in race["missed"]],
            "race_time_s": [max(0.0, float(v)) for v in race["time_s"]],
            "race_finished": [bool(v) for v in race["finished"]],
            "race_rank": [int(v) for v in race["rank"]],
        }
    return _message(
        "room",
        pilots=[str(name)[:64] for name in pilots],
        you=int(you),
        placed=[bool(p) for p in placed],
        modes=[str(m) for m in modes],
        drones=_floats(drones, 7 * n, "drones"),
        cameras=_floats(cameras, 7 * n, "cameras"),
        **fields,
    )


def make_map_chunk(
    points: np.ndarray,
    colours: np.ndarray,
    chunk: int = 0,
    total_points: int | None = None,
    reset: bool | None = None,
    surface: bool | None = None,
) -> dict:
    """points (N, 3) metres -> N*12 bytes float32 LE; colours (N, 3) uint8 RGB -> N*3 bytes."""
    pts = np.ascontiguousarray(points, dtype="<f4")
    rgb = np.ascontiguousarray(colours, dtype=np.uint8)
    if pts.ndim != 2 or pts.shape[1] != 3 or rgb.shape != pts.shape:
        raise ProtocolError(
            "invalid_field", f"need (N, 3) points and colours, got {pts.shape} and {rgb.shape}"
        )
    n = len(pts)
    return _message(
        "map_chunk",
        chunk=int(chunk),
        count=n,
        points=pts.tobytes(),
        colours=rgb.tobytes(),
        total_points=n if total_points is None else int(total_points),
        reset=reset,
        surface=surface,
    )


def make_map_corrected(
    loops: int,
    from_seq: int,
    T_correction: ArrayLike,
    keyframes: Sequence[tuple[int, int, ArrayLike]],
    refused: int,
) -> dict:
    """keyframes: (id, seq, T_world_keyframe 4x4 metres) at their corrected poses;
    T_correction: 4x4, old world to new (both sent row-major)."""
    return _message(
        "map_corrected",
        loops=int(loops),
        from_seq=max(0, int(from_seq)),
        T_correction=_floats(T_correction, 16, "T_correction"),
        keyframes=[
            {
                "id": int(i),
                "seq": int(seq),
                "T_world_keyframe": _floats(T, 16, "T_world_keyframe"),
            }
            for i, seq, T in keyframes
        ],
        refused=int(refused),
    )


# ---- message readers --------------------------------------------------------------------------


def pose_matrix(message: Mapping, key: str = "T_world_camera") -> np.ndarray:
    """The 4x4 float64 transform of a pose (or drone_state with key='T_world_drone')."""
    return np.asarray(message[key], dtype=np.float64).reshape(4, 4)


def decode_map_corrected(
    message: Mapping,
) -> tuple[np.ndarray, dict[int, tuple[int, np.ndarray]]]:
    """-> T_correction (4x4 float64) and, per keyframe id, (seq, T_world_keyframe 4x4)."""
    keyframes = {
        int(k["id"]): (int(k["seq"]), pose_matrix(k, "T_world_keyframe"))
        for k in message["keyframes"]
    }
    return pose_matrix(message, "T_correction"), keyframes


def decode_map_chunk(message: Mapping) -> tuple[np.ndarray, np.ndarray]:
    """-> points (N, 3) float32 metres, colours (N, 3) uint8 RGB."""
    points = np.frombuffer(message["points"], dtype="<f4").reshape(-1, 3).astype(np.float32)
    colours = np.frombuffer(message["colours"], dtype=np.uint8).reshape(-1, 3).copy()
    return points, colours


def depth_intrinsics(hello: Mapping) -> tuple[float, float, float, float]:
    """fx, fy, cx, cy of the depth image: the colour ones scaled to depth_size (pixel centres)."""
    fx, fy, cx, cy = hello["intrinsics"]
    (cw, ch), (dw, dh) = hello["colour_size"], hello["depth_size"]
    sx, sy = dw / cw, dh / ch
    return fx * sx, fy * sy, (cx + 0.5) * sx - 0.5, (cy + 0.5) * sy - 0.5
