"""What goes into a session (a decoded frame) and what it hands its client (poses, map
preview, drone states and events, refusals, its failure): plain data, no threads, no web code."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from server.registration.results import TrackingState
from server.simulation.drone_types import DroneEventKind


@dataclass
class DroneUpdate:
    """The drone's state for the client, in the world frame (metres, seconds)."""

    timestamp: float  # simulation time
    T_world_drone: np.ndarray
    T_camera_drone: np.ndarray | None  # for the latest processed frame's camera
    camera_seq: int | None
    velocity: np.ndarray  # (3,) world frame, m/s
    mode: str
    clearance: float
    target: np.ndarray | None
    route: np.ndarray | None  # (N, 3) remaining route, world frame
    command_id: int | None
    flight_mode: str = "position"  # how sticks fly the drone: position, angle or acro
    attitude: np.ndarray | None = None  # (3,) roll, pitch, yaw in degrees, flight frame
    damage: float = 0.0  # bump damage points since spawn


@dataclass
class DroneNotice:
    """Something that happened to the drone (collision, arrival, ...), world frame."""

    event: DroneEventKind
    timestamp: float
    position: np.ndarray
    message: str
    command_id: int | None


@dataclass
class FrameData:
    """A decoded frame: colour (H, W, 3) RGB uint8; depth (h, w) float32 metres, 0 = none, may be
    smaller than colour (resampled here)."""

    seq: int
    timestamp: float
    colour: np.ndarray
    depth: np.ndarray
    # When the frame arrived at the server (time.monotonic, which on Linux is one clock for every
    # process of the machine): the web process stamps it as it receives the message, and a
    # Ray actor, whose front-end may run on another machine, as the frame reaches the actor.
    # The pose's server_total is measured from it.
    received_at: float = field(default_factory=time.monotonic)
    decode_ms: float = 0.0
    # The device's own camera pose in its world (4x4, metres), when the frame carried one.
    T_device_camera: np.ndarray | None = None
    device_world: int = 0  # which of the device's worlds it is in (protocol: device_world)


@dataclass
class PoseUpdate:
    """The outcome of one processed frame, for the client."""

    seq: int
    timestamp: float
    T_world_camera: np.ndarray  # 4x4, metres
    state: TrackingState
    inliers: int
    keyframe: bool
    timings_ms: dict[str, float]
    dropped: int  # frames dropped so far in this session
    processed: int
    failures: dict[str, int] = field(default_factory=dict)  # Failures, counted so far
    recovery: str | None = None  # TrackResult.recovery: relocalised, segment, merged or None


@dataclass
class RoomUpdate:
    """The phones of a shared room and their drones, in the room's world frame, as one of its
    sessions is told (``you``: that session's index). Per pilot, in ``names``' order (the owner
    first): placed, the drone's mode ("none": no drone yet), and (N, 7) drone and camera poses
    (centre in metres and quaternion x, y, z, w; zeros where there is none)."""

    names: list[str]
    you: int
    placed: list[bool]
    modes: list[str]
    drones: np.ndarray
    cameras: np.ndarray
    race: dict | None = None  # the room's race standings (server/sessions/web/room_race.py)
    routes: list[np.ndarray | None] | None = None  # per pilot its route ahead, (K, 3) or None


@dataclass
class MapUpdate:
    """New map preview points, sent as they are fused (after the frame's pose). ``reset``: the
    map was rebuilt (loop closure): the preview restarts with these points (a map_chunk with
    reset true, even when there are none). ``surface``: the map has a surface (its mesh and
    surface points can be downloaded); an update without points says that it now has, or
    reset."""

    seq: int
    points: np.ndarray  # (N, 3) float32 world metres
    colours: np.ndarray  # (N, 3) uint8 RGB
    total_points: int
    reset: bool = False
    surface: bool = False


@dataclass
class MapCorrected:
    """A loop closure corrected the world (the protocol's map_corrected): poses of frames from
    ``from_seq`` on are in the new world; ``T_correction`` (4x4, metres) maps the old world into
    the new one for the current view; ``keyframes`` are (id, seq, T_world_keyframe 4x4) at
    their corrected poses. The rebuilt map's preview follows as a MapUpdate with reset."""

    loops: int
    from_seq: int
    T_correction: np.ndarray
    keyframes: list[tuple[int, int, np.ndarray]]
    refused: int


@dataclass
class FrameRefused:
    """A frame that got no pose: unusable (corrupt image, size mismatch, bad depth) or one the
    server failed on (internal_error). The client gets the error with the frame's seq; the
    session goes on."""

    seq: int | None
    code: str
    message: str
    counted: bool = True  # toward max_consecutive_errors (ProtocolError.counted)


@dataclass
class SessionFailed:
    """The session cannot go on: its map is gone (the mapping process or thread died), or, on
    the web side, its whole worker died. The client is told and its socket closed
    (session_failed, 4010). ``saved``: the session is being stopped and saved (its trajectory
    whole, its map as far as it was kept); else it is kept as of its last snapshot."""

    message: str
    saved: bool = False


# What a session hands its client, from its worker threads; a dict is a protocol message built
# already (a course's, server/sessions/runtime/course_control.py), sent as it is.
Update = (
    PoseUpdate
    | MapUpdate
    | MapCorrected
    | DroneUpdate
    | DroneNotice
    | FrameRefused
    | SessionFailed
    | dict
)
