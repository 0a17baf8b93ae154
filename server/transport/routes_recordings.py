"""REST API for iPhone recordings uploaded from the page: a Record3D ``.r3d`` file or a Stray
Scanner export zipped, converted on the server into the form the page's replay reads.

Safari on an iPhone has no WebXR: its user records with Stray Scanner or Record3D, uploads the
file here, and the page replays it like the demo, sending the phone's own pose with every frame
(``frame.T_device_camera``). The store is ``server.transport.recordings``.
"""

from __future__ import annotations

import asyncio
import logging
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Request, Response, status
from fastapi.responses import FileResponse, JSONResponse
from starlette.requests import ClientDisconnect

from server.transport.deps import bearer_token, creation_allowed
from server.transport.recordings import RecordingError, RecordingStore, recording_name
from server.transport.schemas import RecordingCreated, RecordingIndex, error_response

log = logging.getLogger(__name__)
router = APIRouter(prefix="/api/recordings", tags=["recordings"])
TokenDep = Annotated[str | None, Depends(bearer_token)]


_TOKEN_ERRORS: dict[int | str, dict[str, Any]] = {
    401: error_response("no `Authorization: Bearer <token>` header"),
    404: error_response("unknown recording id, or a token that does not open it (the same answer)"),
}
MEDIA_TYPES = {".jpg": "image/jpeg", ".png": "image/png"}


def _store(request: Request) -> RecordingStore:
    store: RecordingStore = request.app.state.recordings
    return store


def _urls(recording_id: str, index: dict) -> dict:
    """The stored index with file names turned into this server's URLs."""
    files = f"/api/recordings/{recording_id}/files"
    frames = [
        {**f, "colour": f"{files}/{f['colour']}", "depth": f"{files}/{f['depth']}"}
        for f in index["frames"]
    ]
    return {**index, "id": recording_id, "frames": frames}


@router.post(
    "",
    status_code=status.HTTP_201_CREATED,
    dependencies=[Depends(creation_allowed)],
    response_model=RecordingCreated,
    responses={
        413: error_response("`upload_too_large`: the body is larger than server.max_upload_mb"),
        415: error_response(
            "`unsupported_recording`: the body is not a zip of a Record3D or Stray Scanner "
            "recording (or a multipart form: send the file's bytes themselves)"
        ),
        422: error_response(
            "`bad_recording`: a recording's layout, but unreadable (its message says)"
        ),
        429: error_response("`rate_limited`: too many uploads and sessions from this address"),
    },
    openapi_extra={
        "requestBody": {
            "required": True,
            "description": "the file's bytes: a Record3D .r3d, or a Stray Scanner export "
            "folder zipped (its files at the top or in one folder)",
            "content": {
                "application/octet-stream": {"schema": {"type": "string", "format": "binary"}}
            },
        }
    },
)
async def upload_recording(request: Request, name: str | None = None) -> Response:
    """Upload an iPhone recording and convert it for the page's replay: **201** with `{id,
    token, index, name, frames}`. The token is shown only here: `GET index` with
    `Authorization: Bearer <token>` gives the replay's index (camera, sizes, per-frame file
    URLs and the phone's own pose `T_device_camera`). The answer comes when the conversion is
    done (about a second per 30 frames). A failed upload leaves nothing on the server.
    `name`: the file's name, shown by the page (its folders and suffix are dropped)."""
    store = _store(request)
    if request.headers.get("content-type", "").startswith("multipart/"):
        raise RecordingError(
            "unsupported_recording",
            "send the file's bytes as the request body, not a multipart form",
            415,
        )
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > store.max_upload_bytes:
        raise store.too_large(int(declared))
    try:
        upload = await store.receive(request.stream())
    except ClientDisconnect:
        # The client went away mid-upload: receive() removed the part written. One line, no
        # traceback: nothing on the server went wrong, and no one is left to answer.
        client = request.client.host if request.client else "?"
        log.info("upload from %s aborted by the client; nothing kept", client)
        return Response(status_code=status.HTTP_400_BAD_REQUEST)
    recording_id, token, index = await asyncio.to_thread(
        store.convert, upload, recording_name(name)
    )
    body = {
        "id": recording_id,
        "token": token,
        "index": f"/api/recordings/{recording_id}",
        "name": index["name"],
        "frames": len(index["frames"]),
    }
    return JSONResponse(body, status_code=status.HTTP_201_CREATED)


@router.get("/{recording_id}", response_model=RecordingIndex, responses=_TOKEN_ERRORS)
def recording_index(recording_id: str, request: Request, token: TokenDep) -> JSONResponse:
    """The replay's index of an uploaded recording, as `/api/demo` gives the demo's, plus each
    frame's `T_device_camera`; its file URLs need the same token."""
    store = _store(request)
    return JSONResponse(_urls(recording_id, store.index(store.folder(recording_id, token))))


@router.get(
    "/{recording_id}/files/{path:path}",
    responses={
        **_TOKEN_ERRORS,
        200: {
            "description": "a colour JPEG (rgb/NNNNNN.jpg) or a 16-bit depth PNG in "
            "millimetres (depth/NNNNNN.png)",
            "content": {"image/jpeg": {}, "image/png": {}},
        },
    },
)
def recording_file(recording_id: str, path: str, request: Request, token: TokenDep) -> FileResponse:
    """One frame file of an uploaded recording."""
    folder = _store(request).folder(recording_id, token)
    parts = path.split("/")
    if len(parts) != 2 or parts[0] not in ("rgb", "depth") or not (folder / path).is_file():
        raise RecordingError("not_found", "no such file in this recording", 404)
    return FileResponse(
        folder / path,
        media_type=MEDIA_TYPES.get((folder / path).suffix),
        headers={"Cache-Control": "private, max-age=3600"},
    )


@router.delete(
    "/{recording_id}",
    status_code=status.HTTP_204_NO_CONTENT,
    response_class=Response,
    responses=_TOKEN_ERRORS,
)
def delete_recording(recording_id: str, request: Request, token: TokenDep) -> Response:
    """Delete an uploaded recording and its files: **204**."""
    store = _store(request)
    store.delete(store.folder(recording_id, token))
    return Response(status_code=status.HTTP_204_NO_CONTENT)
