"""Uploading an iPhone recording (POST /api/recordings) to a real server on loopback: converted
into the page's replay form, readable only with its token, refused clearly when it is too large,
not a recording, or broken, and nothing left behind then."""

from __future__ import annotations

import asyncio
import io
import json
import logging
import os
import socket
import struct
import time
import zipfile
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest

from server.client import server_process
from server.datasets import open_dataset
from tests.conftest import Stream, auth
from tests.support.iphone_recordings import (
    jpeg_declaring,
    lzfse_declaring,
    png_declaring,
    room_recording,
    write_r3d,
    write_stray,
    zip_folder,
)
from tests.support.paths import SHARED_DATA

ROOM = SHARED_DATA / "synthetic_room0"
pytestmark = pytest.mark.skipif(not ROOM.is_dir(), reason=f"shared data not found at {ROOM}")

FRAMES = 6


@pytest.fixture(scope="module")
def room():
    return room_recording(ROOM, list(range(FRAMES)))


@pytest.fixture(scope="module")
def r3d(room, tmp_path_factory) -> Path:
    return write_r3d(room, tmp_path_factory.mktemp("r3d") / "room_scan.r3d")


@pytest.fixture(scope="module")
def stray_zip(room, tmp_path_factory) -> Path:
    folder = write_stray(room, tmp_path_factory.mktemp("stray") / "scan", video_size=(1280, 960))
    return zip_folder(folder, folder.parent / "scan.zip", inside="scan")


def upload(server, data: bytes, name: str = "upload.r3d", **headers) -> httpx.Response:
    return httpx.post(
        f"{server.url}/api/recordings",
        params={"name": name},
        content=data,
        headers=headers,
        timeout=60,
    )


def leftovers(server) -> list[str]:
    """What the recordings folder holds besides finished recordings."""
    root = server.settings.data_dir / "recordings"
    found = [p for p in root.rglob("*") if p.is_file()] if root.is_dir() else []
    return [str(p.relative_to(root)) for p in found if p.relative_to(root).parts[0].startswith(".")]


@pytest.mark.parametrize("which", ["record3d", "stray zip"])
def test_an_upload_is_converted_and_read_back_with_its_token(live_server, r3d, stray_zip, which):
    server = live_server()
    path = r3d if which == "record3d" else stray_zip
    r = upload(server, path.read_bytes(), name=f"C:\\phone\\{path.name}")
    assert r.status_code == 201, r.text
    body = r.json()
    assert body["frames"] == FRAMES and body["index"] == f"/api/recordings/{body['id']}"
    assert body["name"] == ("room_scan" if which == "record3d" else "scan")

    index = httpx.get(server.url + body["index"], headers=auth(body["token"])).json()
    assert index["colour_size"] == [640, 480] and index["depth_scale"] == 1000.0
    np.testing.assert_allclose(index["intrinsics"], [525.0, 525.0, 319.5, 239.5], atol=1e-6)
    # The phone's poses, per frame, as the loader reads them.
    ds = open_dataset(r3d)
    for i, frame in enumerate(index["frames"]):
        pose = np.array(frame["T_device_camera"]).reshape(4, 4)
        np.testing.assert_allclose(pose, ds.device_poses.poses[i], atol=1e-6)
    # ARKit's world is y up: gravity in the first camera is -y of the world in camera axes.
    assert np.linalg.norm(index["gravity"]) == pytest.approx(1.0)

    frame = index["frames"][2]
    colour = httpx.get(server.url + frame["colour"], headers=auth(body["token"]))
    depth = httpx.get(server.url + frame["depth"], headers=auth(body["token"]))
    assert colour.headers["content-type"] == "image/jpeg"
    image = cv2.imdecode(np.frombuffer(colour.content, np.uint8), cv2.IMREAD_COLOR)
    mm = cv2.imdecode(np.frombuffer(depth.content, np.uint8), cv2.IMREAD_UNCHANGED)
    assert image.shape == (480, 640, 3) and mm.dtype == np.uint16 and mm.shape == (480, 640)
    np.testing.assert_allclose(mm / 1000.0, ds[2].depth, atol=0.0006)

    # Only its token opens it; a stranger cannot tell a wrong token from an unknown id.
    assert httpx.get(server.url + body["index"]).status_code == 401
    wrong = httpx.get(server.url + body["index"], headers=auth("not-the-token"))
    unknown = httpx.get(f"{server.url}/api/recordings/0123456789abcdef", headers=auth("x"))
    assert wrong.status_code == unknown.status_code == 404
    assert wrong.json() == unknown.json()
    assert httpx.get(server.url + frame["colour"], headers=auth("nope")).status_code == 404
    escape = f"{server.url}/api/recordings/{body['id']}/files/rgb/../index.json"
    assert httpx.get(escape, headers=auth(body["token"])).status_code == 404
    assert leftovers(server) == []

    gone = httpx.delete(server.url + body["index"], headers=auth(body["token"]))
    assert gone.status_code == 204
    assert httpx.get(server.url + body["index"], headers=auth(body["token"])).status_code == 404


def broken_r3d(r3d: Path) -> bytes:
    """The Record3D file with its metadata cut short."""
    with zipfile.ZipFile(r3d) as z:
        return r3d_with(r3d, metadata=z.read("metadata")[:20])


def other_zip() -> bytes:
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as z:
        z.writestr("holiday/photo.jpg", b"\xff\xd8\xff")
    return out.getvalue()


def test_bad_uploads_get_clear_errors_and_leave_nothing_behind(live_server, r3d, tmp_path):
    server = live_server(max_upload_mb=r3d.stat().st_size / 1e6 * 1.5)
    cases = {
        "broken metadata": (broken_r3d(r3d), {}, 422, "bad_recording"),
        "not a zip": (b"GIF89a" + bytes(2000), {}, 415, "unsupported_recording"),
        "a zip of something else": (other_zip(), {}, 415, "unsupported_recording"),
        "empty": (b"", {}, 415, "unsupported_recording"),
        "a multipart form": (
            r3d.read_bytes(),
            {"content-type": "multipart/form-data; boundary=x"},
            415,
            "unsupported_recording",
        ),
        "too large": (r3d.read_bytes() * 2, {}, 413, "upload_too_large"),
    }
    for name, (data, headers, status, code) in cases.items():
        r = upload(server, data, **headers)
        assert r.status_code == status, (name, r.text)
        assert r.json()["error"]["code"] == code, name
        assert r.json()["error"]["message"], name
    # Too large without a Content-Length up front: refused while it streams in.
    chunks = iter([r3d.read_bytes(), r3d.read_bytes()])
    r = httpx.post(f"{server.url}/api/recordings", content=chunks, timeout=60)
    assert r.status_code == 413 and r.json()["error"]["code"] == "upload_too_large"
    root = server.settings.data_dir / "recordings"
    assert leftovers(server) == []
    assert not [p for p in root.iterdir() if not p.name.startswith(".")]
    # The server still takes a good one.
    assert upload(server, r3d.read_bytes()).status_code == 201


def r3d_with(
    r3d: Path, metadata: bytes | None = None, depth: bytes | None = None, jpeg: bytes | None = None
) -> bytes:
    """The Record3D file with its metadata (and every depth, or colour, member) replaced,
    compressed."""
    out = io.BytesIO()
    with zipfile.ZipFile(r3d) as src, zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as dst:
        for item in src.namelist():
            data = src.read(item)
            if item == "metadata" and metadata is not None:
                data = metadata
            elif item.endswith(".depth") and depth is not None:
                data = depth
            elif item.endswith(".jpg") and jpeg is not None:
                data = jpeg
            dst.writestr(item, data)
    return out.getvalue()


def metadata_of(r3d: Path) -> dict:
    with zipfile.ZipFile(r3d) as z:
        return json.loads(z.read("metadata"))


def rss_mb() -> float:
    """This process's resident memory (the live server runs in it), MB."""
    return server_process.rss_mb(os.getpid())


def test_a_file_that_inflates_far_costs_its_conversion_process_not_the_server(
    live_server, r3d, shared_data
):
    """A 1 MB .r3d whose metadata inflates to 1 GB of JSON whitespace, with the limit on what
    metadata may declare raised past it (the memory ceiling is the defence behind the declared
    sizes, for a stream that lies about them): converted in a process of its own under
    server.upload_memory_mb, it is refused (422, naming the limit) while the web process stays
    small, answers /healthz and keeps a live session streaming."""
    server = live_server(upload_memory_mb=256, upload_max_metadata_mb=2000)
    spaces = b" " * (1 << 30)
    bomb = r3d_with(r3d, metadata=b'{"w": 640' + spaces + b"}")
    assert len(bomb) < 3 * 2**20, len(bomb)
    del spaces
    sid, token = server.create_session()
    ds = open_dataset(shared_data / "synthetic_room0")
    stream = Stream(server.ws_url, sid, token, ds)

    async def streaming_while_uploading():
        await stream.open()
        answer = asyncio.create_task(asyncio.to_thread(upload, server, bomb))
        seq = 0
        while not answer.done():
            await stream.send(seq)
            seq += 1
        await stream.send(seq)  # and after it
        await stream.close()
        return await answer

    before = rss_mb()
    r = asyncio.run(streaming_while_uploading())
    grown = rss_mb() - before
    assert r.status_code == 422, r.text
    assert r.json()["error"]["code"] == "bad_recording"
    assert "server.upload_memory_mb" in r.json()["error"]["message"]
    assert grown < 100, f"the web process grew by {grown:.0f} MB"
    assert len(stream.poses) >= 2 and all(p["state"] != "lost" for p in stream.poses)
    assert httpx.get(f"{server.url}/healthz").status_code == 200
    assert leftovers(server) == []
    assert upload(server, r3d.read_bytes()).status_code == 201  # and a good one still converts


def stray_with(room, tmp_path: Path, member: str, data: bytes) -> bytes:
    """A Stray export of the room, zipped (deflated), with ``member`` written as ``data``."""
    folder = write_stray(room, tmp_path / "scan", video_size=(1280, 960))
    (folder / member).write_bytes(data)
    archive = zip_folder(folder, tmp_path / "scan.zip", "scan", zipfile.ZIP_DEFLATED)
    return archive.read_bytes()


@pytest.mark.parametrize(
    "bomb",
    [
        "metadata of 1 GB",
        "depth of 2 GB",
        "depth of 64 MB in a small stream",
        "colour of 30000x20000",
        "metadata of 16384x16384",
        "more frames than allowed",
        "depth png of 60000x45000",
        "second depth png of 24000x18000",
        "stray members declaring 40 MB",
    ],
)
def test_what_an_upload_declares_is_refused_before_it_is_decoded(
    live_server, r3d, room, tmp_path, bomb
):
    """Each small file that would expand to gigabytes is refused by the size it declares (a zip
    member's, an LZFSE stream's block headers, a JPEG's frame header, a PNG's IHDR, the
    metadata's), with a 422 that names the limit, before any of it is inflated: the memory
    ceiling (server.upload_memory_mb, set low here) is never what stops it."""
    frames = FRAMES - 1 if bomb == "more frames than allowed" else FRAMES
    server = live_server(upload_memory_mb=256, upload_max_frames=frames, max_upload_mb=5)
    meta = metadata_of(r3d)
    with zipfile.ZipFile(r3d) as z:
        first_jpeg = z.read("rgbd/0.jpg")
    data, name, says = {
        "metadata of 1 GB": lambda: (
            r3d_with(r3d, metadata=b'{"w": 640' + b" " * (1 << 30) + b"}"),
            "upload.r3d",
            "server.upload_max_metadata_mb",
        ),
        "depth of 2 GB": lambda: (
            r3d_with(r3d, depth=lzfse_declaring(2 << 30)),
            "upload.r3d",
            "rgbd/0.depth unpacks to 1.3 MB, more than the 0.3 MB allowed",
        ),
        "depth of 64 MB in a small stream": lambda: (
            r3d_with(r3d, depth=lzfse_declaring(64 << 20)),
            "upload.r3d",
            "rgbd/0.depth holds 67108864 bytes, expected 196608",
        ),
        "colour of 30000x20000": lambda: (
            r3d_with(r3d, jpeg=jpeg_declaring(first_jpeg, 30000, 20000)),
            "upload.r3d",
            "is 30000x20000 but the intrinsics say 640x480",
        ),
        "metadata of 16384x16384": lambda: (
            r3d_with(r3d, metadata=json.dumps({**meta, "w": 16384, "h": 16384}).encode()),
            "upload.r3d",
            "server.upload_max_megapixels",
        ),
        "more frames than allowed": lambda: (
            r3d.read_bytes(),
            "upload.r3d",
            "server.upload_max_frames",
        ),
        "depth png of 60000x45000": lambda: (
            stray_with(room, tmp_path, "depth/000000.png", png_declaring(60000, 45000)),
            "scan.zip",
            "server.upload_max_megapixels",
        ),
        "second depth png of 24000x18000": lambda: (
            stray_with(room, tmp_path, "depth/000001.png", png_declaring(24000, 18000)),
            "scan.zip",
            "not the recording's depth size",
        ),
        "stray members declaring 40 MB": lambda: (
            stray_with(room, tmp_path, "depth/000099.png", bytes(40 << 20)),
            "scan.zip",
            "more than the 20 MB allowed (a multiple of server.max_upload_mb)",
        ),
    }[bomb]()
    assert len(data) < 3 * 2**20, len(data)
    r = upload(server, data, name=name)
    assert r.status_code == 422 and r.json()["error"]["code"] == "bad_recording", r.text
    message = r.json()["error"]["message"]
    assert says in message, message
    assert "server.upload_memory_mb" not in message
    assert str(server.settings.data_dir) not in message and ".incoming" not in message, message
    assert leftovers(server) == []


@pytest.mark.parametrize(
    "change",
    [
        {"w": 1e999},  # int(inf)
        {"dw": -256, "dh": -192},  # a positive product, then a reshape that cannot be
        {"fps": 0},
        {"fps": float("nan")},
        {"poses": "not poses"},
    ],
    ids=["infinite width", "negative depth size", "zero fps", "nan fps", "poses not a list"],
)
def test_malformed_metadata_is_a_422_never_a_500(live_server, r3d, change):
    server = live_server()
    metadata = {**metadata_of(r3d), **change}
    r = upload(server, r3d_with(r3d, metadata=json.dumps(metadata).encode()))
    assert r.status_code in (201, 422), (change, r.status_code, r.text)
    if r.status_code == 422:
        assert r.json()["error"]["code"] == "bad_recording"
        assert str(server.settings.data_dir) not in r.json()["error"]["message"]
    else:  # accepted: then its index must be readable (no NaN stored)
        index = httpx.get(
            f"{server.url}{r.json()['index']}", headers=auth(r.json()["token"]), timeout=30
        )
        assert index.status_code == 200, (change, index.text)
    assert leftovers(server) == []


def deflate_corrupted(r3d: Path, member: str) -> bytes:
    """The Record3D file deflated, with bytes in the middle of ``member``'s compressed data
    overwritten (its zlib stream, or its CRC, then fails)."""
    data = bytearray(r3d_with(r3d))
    with zipfile.ZipFile(io.BytesIO(bytes(data))) as z:
        info = z.getinfo(member)
    name_len, extra_len = struct.unpack_from("<HH", data, info.header_offset + 26)
    start = info.header_offset + 30 + name_len + extra_len
    middle = start + info.compress_size // 2
    data[middle : middle + 16] = bytes(range(200, 216))
    return bytes(data)


@pytest.mark.parametrize("how", ["not lzfse", "corrupt deflate"])
def test_a_corrupt_depth_member_is_a_422(live_server, r3d, how):
    server = live_server()
    if how == "not lzfse":
        data = r3d_with(r3d, depth=b"not lzfse at all" * 10)
    else:
        data = deflate_corrupted(r3d, "rgbd/3.depth")
    r = upload(server, data)
    assert r.status_code == 422 and r.json()["error"]["code"] == "bad_recording", r.text
    assert "rgbd/" in r.json()["error"]["message"] or "Error" in r.json()["error"]["message"]
    assert leftovers(server) == []


@pytest.mark.parametrize("bad", ["nan", "inf"])
def test_a_stray_export_with_odometry_that_is_not_finite_is_refused(
    live_server, room, tmp_path, bad
):
    """NaN or infinite odometry (a timestamp and a position) would be stored and break the
    recording's index later: refused at upload, 422."""
    folder = write_stray(room, tmp_path / "scan", video_size=(1280, 960))
    lines = (folder / "odometry.csv").read_text().splitlines()
    cells = lines[2].split(",")
    cells[0], cells[2] = bad, bad
    lines[2] = ",".join(cells)
    (folder / "odometry.csv").write_text("\n".join(lines) + "\n")
    archive = zip_folder(folder, tmp_path / "scan.zip", inside="scan")
    server = live_server()
    r = upload(server, archive.read_bytes(), name="scan.zip")
    assert r.status_code == 422 and r.json()["error"]["code"] == "bad_recording", r.text
    assert "not finite" in r.json()["error"]["message"]
    assert str(server.settings.data_dir) not in r.json()["error"]["message"]
    assert leftovers(server) == []


def test_an_upload_the_client_aborts_is_one_log_line_and_leaves_nothing(live_server, r3d):
    """A client that hangs up mid-upload: the part received is removed, the server logs one
    line (no traceback: nothing on the server failed) and takes the next upload."""
    server = live_server()
    records: list[logging.LogRecord] = []
    handler = logging.Handler()
    handler.emit = records.append  # type: ignore[method-assign]
    watched = [logging.getLogger(n) for n in ("uvicorn.error", "server.transport")]
    for logger in watched:
        logger.addHandler(handler)
    old_level = watched[1].level
    watched[1].setLevel(logging.INFO)
    try:
        with socket.create_connection(("127.0.0.1", server.port)) as s:
            s.sendall(
                b"POST /api/recordings?name=cut.r3d HTTP/1.1\r\nHost: test\r\n"
                b"Content-Type: application/octet-stream\r\nContent-Length: 5000000\r\n\r\n"
                + r3d.read_bytes()[:200_000]
            )
            deadline = time.time() + 10
            while not any((server.settings.data_dir / "recordings" / ".incoming").glob("*")):
                assert time.time() < deadline, "the upload never arrived"
                time.sleep(0.05)
        deadline = time.time() + 10
        while not any("aborted" in r.getMessage() for r in records) and time.time() < deadline:
            time.sleep(0.05)
    finally:
        for logger in watched:
            logger.removeHandler(handler)
        watched[1].setLevel(old_level)
    aborted = [r for r in records if "aborted" in r.getMessage()]
    assert len(aborted) == 1 and aborted[0].levelno == logging.INFO, records
    assert not [r for r in records if r.exc_info or r.levelno >= logging.ERROR], [
        r.getMessage() for r in records
    ]
    assert leftovers(server) == []
    assert upload(server, r3d.read_bytes()).status_code == 201
