"""Uploading an iPhone recording (POST /api/recordings) to a real server on loopback: converted
into the page's replay form, readable only with its token, refused clearly when it is too large,
not a recording, or broken, and nothing left behind then."""

from __future__ import annotations

import asyncio
import io
import json
import zipfile
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest
from conftest import Stream, auth
from iphone_recordings import room_recording, write_r3d, write_stray, zip_folder

from server.datasets import open_dataset

REPO = Path(__file__).resolve().parents[1]
ROOM = REPO.parent / "shared" / "data" / "synthetic_room0"
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
    out = io.BytesIO()
    with zipfile.ZipFile(r3d) as src, zipfile.ZipFile(out, "w") as dst:
        for item in src.namelist():
            dst.writestr(item, src.read(item)[:20] if item == "metadata" else src.read(item))
    return out.getvalue()


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


def r3d_with(r3d: Path, metadata: bytes | None = None, depth: bytes | None = None) -> bytes:
    """The Record3D file with its metadata (and every depth member) replaced, compressed."""
    out = io.BytesIO()
    with zipfile.ZipFile(r3d) as src, zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as dst:
        for item in src.namelist():
            data = src.read(item)
            if item == "metadata" and metadata is not None:
                data = metadata
            elif item.endswith(".depth") and depth is not None:
                data = depth
            dst.writestr(item, data)
    return out.getvalue()


def metadata_of(r3d: Path) -> dict:
    with zipfile.ZipFile(r3d) as z:
        return json.loads(z.read("metadata"))


def rss_mb() -> float:
    """This process's resident memory (the live server runs in it), MB."""
    for line in open("/proc/self/status"):
        if line.startswith("VmRSS"):
            return int(line.split()[1]) / 1024
    return 0.0


def test_a_file_that_inflates_far_costs_its_conversion_process_not_the_server(
    live_server, r3d, shared_data
):
    """A 1 MB .r3d whose metadata inflates to 1 GB of JSON whitespace: converted in a process of
    its own under server.upload_memory_mb, it is refused (422, naming the limit) while the web
    process stays small, answers /healthz and keeps a live session streaming."""
    server = live_server(upload_memory_mb=256)
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


def test_a_corrupt_depth_member_is_a_422(live_server, r3d):
    server = live_server()
    r = upload(server, r3d_with(r3d, depth=b"not lzfse at all" * 10))
    assert r.status_code == 422 and r.json()["error"]["code"] == "bad_recording", r.text
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
