"""REST API for sessions: create, status, delete, and download map, mesh and trajectory."""

from __future__ import annotations

import asyncio
import tempfile
from pathlib import Path

from fastapi import APIRouter, Depends, Request, Response, status

from server.mapping.tsdf import MapError, TSDFMap
from server.sessions import LiveSession
from server.transport.deps import ManagerDep, SessionDep, creation_allowed
from server.transport.websocket import end_connection

router = APIRouter(prefix="/api/sessions", tags=["sessions"])

PLY = "application/octet-stream"


@router.post("", status_code=status.HTTP_201_CREATED, dependencies=[Depends(creation_allowed)])
def create_session(request: Request, manager: ManagerDep) -> dict:
    """Create a live session. The token is shown only here: keep it, every other call needs it
    (``Authorization: Bearer <token>``, or ``?token=`` on the WebSocket). A client creating
    sessions too fast gets 429 with Retry-After; a full server 503."""
    session, token = manager.create()
    scheme = "wss" if request.url.scheme == "https" else "ws"
    return {
        "id": session.id,
        "token": token,
        "websocket": f"{scheme}://{request.url.netloc}/ws/sessions/{session.id}",
    }


@router.get("/{session_id}")
def session_status(session: SessionDep) -> dict:
    """Statistics of a live or closed session. ``tracking_lost``: the latest frame was lost (the
    pose holds the last good one and the map takes no frames until tracking recovers)."""
    if not isinstance(session, LiveSession):
        return session["status"] | {"closed": True, "tracking_lost": False}
    return session.status()


@router.delete("/{session_id}", status_code=status.HTTP_204_NO_CONTENT)
async def delete_session(
    request: Request, session_id: str, session: SessionDep, manager: ManagerDep
) -> Response:
    """Stop the session and delete its map and trajectory; its open WebSocket, if any, is told
    (``unauthorized``) and closed."""
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


@router.get("/{session_id}/map.ply")
def download_map(session_id: str, session: SessionDep, manager: ManagerDep) -> Response:
    """The fused map's surface points with colours, binary PLY, world frame, metres."""
    if isinstance(session, LiveSession):
        data = session.download("map.ply")
    else:
        data = _saved(manager.store.file(session_id, "map.ply"))
    return _download(data, f"{session_id}-map.ply", PLY)


@router.get("/{session_id}/mesh.ply")
def download_mesh(session_id: str, session: SessionDep, manager: ManagerDep) -> Response:
    """The TSDF surface as a triangle mesh with vertex colours, binary PLY."""
    if isinstance(session, LiveSession):
        data = session.download("mesh.ply")
    else:
        _saved(manager.store.file(session_id, "map.npz"), read=False)
        data = _mesh_bytes(TSDFMap.load(manager.store.file(session_id, "map.npz")))
    return _download(data, f"{session_id}-mesh.ply", PLY)


@router.get("/{session_id}/trajectory.tum")
def download_trajectory(session_id: str, session: SessionDep, manager: ManagerDep) -> Response:
    """Camera poses T_world_camera, one line per processed frame: ``t tx ty tz qx qy qz qw``."""
    if isinstance(session, LiveSession):
        data = session.download("trajectory.tum")
    else:
        data = manager.store.file(session_id, "trajectory.tum").read_bytes()
    return _download(data, f"{session_id}-trajectory.tum", "text/plain")
