"""REST API for sessions: create, status, delete, and download map, mesh and trajectory.

Each route declares what it answers (``server.transport.schemas``, media types, error codes) so
that ``/docs`` tells a client writer everything. The JSON bodies are sent as the sessions
assemble them, unchanged: the models document them and the tests hold the bodies to them.
"""

from __future__ import annotations

import asyncio
import tempfile
from enum import Enum
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import open3d as o3d
from fastapi import APIRouter, Depends, Query, Request, Response, status
from fastapi.responses import JSONResponse

from server.mapping.mesh_files import ply_bytes, read_ply, rotated, upright_glb
from server.mapping.tsdf import MapError, TSDFMap
from server.mapping.upright import upright_frame
from server.sessions import LiveSession
from server.sessions.runtime.course_control import BEST_FILE, read_best
from server.transport.connections import end_connection
from server.transport.deps import ManagerDep, SessionDep, bearer_token, creation_allowed
from server.transport.schemas import (
    CourseBest,
    InviteCreated,
    RaceStart,
    RaceStarted,
    SessionCreate,
    SessionCreated,
    SessionStatus,
    error_response,
)

PLY = "application/octet-stream"
GLB = "model/gltf-binary"


class MeshFrame(str, Enum):
    """The axes a mesh download is in."""

    WORLD = "world"  # the session's world: its first camera's (x right, y down, z forward)
    UPRIGHT = "upright"  # z up against gravity, x the first camera's forward made level


# A route's documented answers, for the OpenAPI document: status -> FastAPI's response entry.
_Responses = dict[int | str, dict[str, Any]]


# Every call on a session: who may ask.
_TOKEN_ERRORS: _Responses = {
    401: error_response("no `Authorization: Bearer <token>` header"),
    404: error_response("unknown session id, or a token that does not open it (the same answer)"),
}
router = APIRouter(prefix="/api/sessions", tags=["sessions"])


def _file(media_type: str, description: str) -> _Responses:
    """A download's 200 answer, for the OpenAPI document."""
    return {
        200: {
            "description": description,
            "content": {media_type: {"schema": {"type": "string", "format": "binary"}}},
        }
    }


_NO_MAP: _Responses = {
    409: error_response("`map_unavailable`: the session has fused no surface yet")
}


@router.post(
    "",
    status_code=status.HTTP_201_CREATED,
    dependencies=[Depends(creation_allowed)],
    response_model=SessionCreated,
    responses={
        429: error_response(
            "`rate_limited`: too many new sessions from this address; see Retry-After"
        ),
        503: error_response("`server_full`: the server holds its maximum of live sessions"),
        401: error_response("`unauthorized`: `room` given without the room's token"),
        404: error_response("`not_found`: no closed session `room` for this token"),
        409: error_response(
            "`room_unavailable`: the session `room` saved no room, or the live room `join` has "
            "mapped nothing yet; `room_full`: the room `join` holds the server's "
            "max_room_phones, or (Ray) its node has no free CPU for another phone"
        ),
        422: error_response("`room` and `join` both given"),
    },
)
def create_session(
    request: Request,
    manager: ManagerDep,
    token: Annotated[str | None, Depends(bearer_token)],
    body: SessionCreate | None = None,
) -> JSONResponse:
    """Create a live session: **201** with `{id, token, websocket, room}`. The body is optional.

    The token is shown only here: keep it, every other call needs it (`Authorization: Bearer
    <token>`, or `?token=` on the WebSocket). `websocket` is the socket's URL without the
    token. A client creating sessions too fast gets 429 with Retry-After (seconds); a full
    server 503.

    With `{"room": "<id>"}` and that closed session's token as `Authorization: Bearer`, the new
    session continues in the room it saved (docs/OFFLINE.md, "Rooms"): its first frames are
    relocalised in the room (answered `lost` at the identity until one is recognised), then
    tracked in the room's world frame; the map and the drone's map start as the room's. The new
    session gets a token of its own.

    `{"loop_closure": true}` (or false) asks for online loop closure in this session whatever
    the server's `registration.loops.live`; the answer's `loop_closure` says whether it runs
    (never in a room's session, nor when the server keeps no rooms).

    With `{"join": "<id>"}` and a join token of that live session's room (`POST /api/sessions/
    {id}/invites`) as `Authorization: Bearer`, the new session joins the room: placed by place
    recognition in the room's keyframes as they stand now, then tracked in the room's world
    frame with a drone of its own, its frames fused into the room's one map (PROTOCOL.md, "A
    shared room"); the room's status lists it."""
    join = None if body is None else body.join
    owner = None if join is None else manager.rooms.room_to_join(join, token)
    room = None if body is None or body.room is None else manager.room_of(body.room, token)
    loops = None if body is None else body.loop_closure
    session, new_token = manager.create(room, loop_closure=loops, joining=owner)
    scheme = "wss" if request.url.scheme == "https" else "ws"
    answer = {
        "id": session.id,
        "token": new_token,
        "websocket": f"{scheme}://{request.url.netloc}/ws/sessions/{session.id}",
        "room": None if body is None else body.room,
        "loop_closure": manager.closes_loops(room, loops) and owner is None,
        "join": join,
    }
    return JSONResponse(answer, status_code=status.HTTP_201_CREATED)


@router.post(
    "/{session_id}/race",
    status_code=status.HTTP_201_CREATED,
    response_model=RaceStarted,
    responses=_TOKEN_ERRORS
    | {
        409: error_response(
            "`room_unavailable`: the session is closed, or joined another session's room; "
            "`race_unavailable`: no course fits where its drone is (no drone yet, too little "
            "mapped)"
        )
    },
)
def start_race(
    session_id: str,
    manager: ManagerDep,
    token: Annotated[str | None, Depends(bearer_token)],
    body: RaceStart | None = None,
) -> JSONResponse:
    """Start a race in this live session's room: **201** with `{race, gates, difficulty, seed,
    starts_in_s}`. The course is laid from where this session's drone is; after `countdown_s`
    every live phone of the room flies its gates, each from where its own drone is (each
    phone's course message gives the gates, the same in the room's world frame), and every
    `room` message carries the standings (PROTOCOL.md, "A shared room")."""
    body = body or RaceStart.model_validate({})
    started = manager.rooms.start_race(
        manager.authorize(session_id, token),
        body.difficulty,
        body.seed,
        body.countdown_s,
        body.autopilot,
    )
    return JSONResponse(started, status_code=status.HTTP_201_CREATED)


@router.get("/{session_id}", response_model=SessionStatus, responses=_TOKEN_ERRORS)
def session_status(session: SessionDep, manager: ManagerDep) -> JSONResponse:
    """Statistics of a live or closed session (fields in the schema below).

    `closed` stays false after a client's `bye`: the session waits for a reconnect until it
    has had no connection and no frame for the server's `session_ttl_s`, then it is closed and
    saved (`closed: true`, the snapshot final). `tracking_lost`: the latest frame was lost (the
    pose holds the last good one and the map takes no frames until tracking recovers)."""
    if not isinstance(session, LiveSession):
        return JSONResponse(session["status"] | {"closed": True, "tracking_lost": False})
    body = session.status()
    if body.get("closed"):  # answered from the final snapshot while the worker stops
        body.setdefault("tracking_lost", False)
    owner = manager.rooms.owner_of(session.id) or session.id
    phones = manager.rooms.phones(owner)
    if phones:
        body["shared_room"] = {"owner": owner, "phones": phones}
    return JSONResponse(body)


@router.post(
    "/{session_id}/invites",
    status_code=status.HTTP_201_CREATED,
    response_model=InviteCreated,
    responses=_TOKEN_ERRORS
    | {
        409: error_response(
            "`room_unavailable`: the session is closed, or joined another session's room"
        )
    },
)
def create_invite(
    session_id: str, manager: ManagerDep, token: Annotated[str | None, Depends(bearer_token)]
) -> JSONResponse:
    """Invite a phone into this live session's room: **201** with `{join_token, join}`. The
    phone opens a session of its own with `POST /api/sessions` `{"join": "<id>"}` and the join
    token as `Authorization: Bearer`; at most the server's max_room_phones phones share a
    room (this one included). Each call makes another token; all open nothing once this
    session has ended."""
    join_token = manager.rooms.invite(manager.authorize(session_id, token))
    return JSONResponse(
        {"join_token": join_token, "join": session_id}, status_code=status.HTTP_201_CREATED
    )


@router.delete(
    "/{session_id}",
    status_code=status.HTTP_204_NO_CONTENT,
    response_class=Response,
    responses=_TOKEN_ERRORS,
)
async def delete_session(
    request: Request, session_id: str, session: SessionDep, manager: ManagerDep
) -> Response:
    """Stop the session and delete its map and trajectory: **204**, no body. Its open
    WebSocket, if any, is told (error `unauthorized`) and closed with 4003."""
    await asyncio.to_thread(manager.delete, session_id)
    end_connection(request.app, session_id, "unauthorized", "this session was deleted")
    return Response(status_code=status.HTTP_204_NO_CONTENT)


def _saved(path: Path, read: bool = True) -> bytes:
    if not path.is_file():
        raise MapError("this session fused no map before it closed")
    return path.read_bytes() if read else b""


def _mesh_bytes(tsdf: TSDFMap) -> bytes:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "mesh.ply"
        tsdf.write_mesh_ply(path)
        return path.read_bytes()


def _download(data: bytes, filename: str, media_type: str) -> Response:
    return Response(
        data,
        media_type=media_type,
        headers={"Content-Disposition": f'attachment; filename="{filename}"'},
    )


@router.get(
    "/{session_id}/map.ply",
    response_class=Response,
    responses=_file(PLY, "binary little-endian PLY point cloud") | _NO_MAP | _TOKEN_ERRORS,
)
def download_map(session_id: str, session: SessionDep, manager: ManagerDep) -> Response:
    """The fused map's surface points with colours: binary little-endian PLY, one `vertex`
    element with `double x, y, z` (world frame, metres) and `uchar red, green, blue`; no
    faces. A live session's map as it is now; a closed one's as its final snapshot saved it."""
    if isinstance(session, LiveSession):
        data = session.download("map.ply")
    else:
        data = _saved(manager.store.file(session_id, "map.ply"))
    return _download(data, f"{session_id}-map.ply", PLY)


def _world_mesh(session_id: str, session: Any, manager: Any) -> o3d.geometry.TriangleMesh:
    """The session's TSDF surface in its world frame (a live one's now, a closed one's saved)."""
    if isinstance(session, LiveSession):
        mesh = read_ply(session.download("mesh.ply"))
    else:
        _saved(manager.store.file(session_id, "map.npz"), read=False)
        mesh = TSDFMap.load(manager.store.file(session_id, "map.npz")).mesh()
    if not mesh.has_triangles():
        raise MapError("the map has no surface yet")
    return mesh


def _upright(session: Any, mesh: o3d.geometry.TriangleMesh) -> o3d.geometry.TriangleMesh:
    """``mesh`` (world frame) turned upright (server/mapping/upright.py): down is the first
    hello's gravity, else found from the map's floors and table tops, else the first camera's
    +y. The world is the first camera's frame, so that camera's pose is the identity."""
    body = session.status() if isinstance(session, LiveSession) else session["status"]
    R_upright_world, _ = upright_frame(
        np.eye(4), np.asarray(mesh.vertices), np.asarray(mesh.triangles), body.get("gravity")
    )
    return rotated(mesh, R_upright_world)


@router.get(
    "/{session_id}/mesh.ply",
    response_class=Response,
    responses=_file(PLY, "binary PLY triangle mesh") | _NO_MAP | _TOKEN_ERRORS,
)
def download_mesh(
    session_id: str,
    session: SessionDep,
    manager: ManagerDep,
    frame: Annotated[
        MeshFrame,
        Query(
            description="`world` (the default): the world frame of trajectory.tum and map.ply, "
            "the first camera's axes (y down); `upright`: z up against gravity, as Blender "
            "and MeshLab show a PLY"
        ),
    ] = MeshFrame.WORLD,
) -> Response:
    """The TSDF surface as a triangle mesh with vertex colours: binary PLY (`vertex` with
    x, y, z in metres, normals and colours; `face` with vertex indices). `?frame=world` (the
    default) gives the world frame, that of trajectory.tum and map.ply; `?frame=upright` the
    same mesh rotated about the world's origin so that z is up: against the hello's
    `gravity`, else the normal of the map's floors and table tops near the first camera's
    up, else that camera's -y; x is the first camera's forward made level (the drone's
    flight frame)."""
    if frame is MeshFrame.UPRIGHT:
        data = ply_bytes(_upright(session, _world_mesh(session_id, session, manager)))
    elif isinstance(session, LiveSession):
        data = session.download("mesh.ply")
    else:
        _saved(manager.store.file(session_id, "map.npz"), read=False)
        data = _mesh_bytes(TSDFMap.load(manager.store.file(session_id, "map.npz")))
    return _download(data, f"{session_id}-mesh.ply", PLY)


@router.get(
    "/{session_id}/mesh.glb",
    response_class=Response,
    responses=_file(GLB, "binary glTF 2.0 (GLB) triangle mesh, y up") | _NO_MAP | _TOKEN_ERRORS,
)
def download_mesh_glb(session_id: str, session: SessionDep, manager: ManagerDep) -> Response:
    """The TSDF surface as binary glTF 2.0 (GLB): one mesh with float32 POSITION (metres),
    NORMAL and COLOR_0 (linear RGB), uint32 indices, a matte double-sided material. Upright
    as `mesh.ply?frame=upright`, in glTF's axes: +y up (against gravity), +z the first
    camera's forward made level, +x to its left (glTF x = upright y, y = upright z, z =
    upright x). Blender, three.js and model viewers open it standing."""
    data = upright_glb(_upright(session, _world_mesh(session_id, session, manager)))
    return _download(data, f"{session_id}-mesh.glb", GLB)


@router.get(
    "/{session_id}/trajectory.tum",
    response_class=Response,
    responses=_file("text/plain", "TUM trajectory, text") | _TOKEN_ERRORS,
)
def download_trajectory(session_id: str, session: SessionDep, manager: ManagerDep) -> Response:
    """Camera poses T_world_camera, TUM format: a `#` comment line, then one line per
    processed frame in processing order, `t tx ty tz qx qy qz qw`: `t` is the frame's
    timestamp echoed (the client's clock, seconds, 6 decimals), `tx ty tz` the camera centre
    in the world frame (metres), `qx qy qz qw` its rotation (unit quaternion, w >= 0). A lost
    frame repeats the last good pose. Empty but for the comment before the first frame."""
    if isinstance(session, LiveSession):
        data = session.download("trajectory.tum")
    else:
        data = manager.store.file(session_id, "trajectory.tum").read_bytes()
    return _download(data, f"{session_id}-trajectory.tum", "text/plain")


@router.get(
    "/{session_id}/course/best",
    response_model=CourseBest,
    responses=_TOKEN_ERRORS,
)
def course_best(session_id: str, session: SessionDep, manager: ManagerDep) -> JSONResponse:
    """The drone's best finished course runs in this session (live or closed), best first:
    score, time, gates passed and missed, bumps, crashes, the course's difficulty and seed
    (PROTOCOL.md, "Courses"). Empty before the first finished run. The session writes them
    to its files as each run finishes, so they survive a restart of the server."""
    del session  # the dependency checked the token
    return JSONResponse({"results": read_best(manager.store.file(session_id, BEST_FILE))})
