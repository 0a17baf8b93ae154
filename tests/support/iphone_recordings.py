"""iPhone LiDAR recordings made here from synthetic_room0, in each app's export layout.

What an iPhone would record: 256x192 LiDAR depth, a confidence map, and the camera's odometry
in ARKit's axes (camera x right, y up, z back) in a y-up world. The Stray video is MPEG-4 Part 2
(mp4v), which OpenCV writes everywhere; the app writes HEVC, which the loader decodes through the
same FFmpeg path. Everything is written into the caller's (temporary) folder.
"""

from __future__ import annotations

import json
import struct
import zipfile
import zlib
from pathlib import Path

import cv2
import lzfse
import numpy as np

from server.datasets import open_dataset
from server.datasets.bounds import lzfse_size
from server.geometry import Intrinsics, quaternion_from_pose
from server.pipeline import ground_truth_pose_at
from server.registration.preprocess import resample_depth

LIDAR_SIZE = (256, 192)  # width, height
ROOM_K = Intrinsics(525.0, 525.0, 319.5, 239.5, 640, 480)
# The phone's world is y up: the room's z-up world turned -90 degrees about x (y <- z, z <- -y).
ROOM_TO_PHONE_WORLD = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0], [0, -1.0, 0, 0], [0, 0, 0, 1.0]])
# ARKit's camera axes written out independently of the loader's constant.
CAMERA_TO_ARKIT = np.diag([1.0, -1.0, -1.0, 1.0])


def lidar_confidence(frame: int) -> np.ndarray:
    """A confidence map (192, 256): high, with a low strip at the left and a medium band at the
    bottom, moving with the frame so that each frame masks different pixels."""
    w, h = LIDAR_SIZE
    conf = np.full((h, w), 2, dtype=np.uint8)
    conf[:, frame % 200 : frame % 200 + 30] = 0
    conf[150:, :] = 1
    return conf


def room_recording(room_path: Path, indices: list[int]) -> dict:
    """Frames ``indices`` of synthetic_room0 as a phone records them: colour, LiDAR-sized depth
    (metres, NaN holes), confidence, T_world_camera in this project's axes and the phone's world
    (``poses``) and in the room's (``ground_truth``), and ARKit-clock timestamps (seconds)."""
    ds = open_dataset(room_path)
    assert ds.intrinsics == ROOM_K
    frames = [ds[i] for i in indices]
    gt = np.array([ground_truth_pose_at(ds, f.timestamp) for f in frames])
    lidar = [resample_depth(f.depth, *LIDAR_SIZE) for f in frames]
    for d in lidar:
        d[5:9, 100:104] = np.nan  # ARKit leaves holes; Record3D stores them as NaN
    return {
        "colour": [f.colour for f in frames],
        "lidar": lidar,
        "confidence": [lidar_confidence(i) for i in range(len(frames))],
        "poses": ROOM_TO_PHONE_WORLD @ gt,
        "ground_truth": gt,
        "timestamps": np.array([f.timestamp for f in frames]) - frames[0].timestamp + 5021.25,
    }


def arkit_rows(poses: np.ndarray):
    """(t, q_xyzw) of each pose after turning it to ARKit's camera axes."""
    for T in poses @ CAMERA_TO_ARKIT:
        yield T[:3, 3], quaternion_from_pose(T)


def write_stray(
    room: dict, folder: Path, video_size: tuple[int, int] = (640, 480), matrix_size=None
) -> Path:
    """A Stray Scanner export of ``room`` in ``folder`` (created). The video is written at
    ``video_size`` (width, height, px) and camera_matrix.csv for ``matrix_size`` (default: the
    video's), as the app writes the matrix for the camera's full resolution."""
    folder.mkdir(parents=True)
    (folder / "depth").mkdir()
    (folder / "confidence").mkdir()
    video = cv2.VideoWriter(
        str(folder / "rgb.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 30.0, video_size
    )
    assert video.isOpened(), "OpenCV cannot write mp4v here"
    for i, colour in enumerate(room["colour"]):
        bgr = cv2.cvtColor(colour, cv2.COLOR_RGB2BGR)
        if video_size != (640, 480):
            bgr = cv2.resize(bgr, video_size, interpolation=cv2.INTER_AREA)
        video.write(bgr)
        mm = np.rint(np.nan_to_num(room["lidar"][i]) * 1000.0).astype(np.uint16)
        cv2.imwrite(str(folder / "depth" / f"{i:06d}.png"), mm)
        cv2.imwrite(str(folder / "confidence" / f"{i:06d}.png"), room["confidence"][i])
    video.release()
    mw, mh = matrix_size or video_size
    K = ROOM_K.matrix.copy()
    # The room's camera scaled to the matrix's size (pixel centres at integers).
    K[0, 0] *= mw / 640
    K[1, 1] *= mh / 480
    K[0, 2] = (K[0, 2] + 0.5) * mw / 640 - 0.5
    K[1, 2] = (K[1, 2] + 0.5) * mh / 480 - 0.5
    (folder / "camera_matrix.csv").write_text("\n".join(",".join(f"{v}" for v in r) for r in K))
    rows = ["timestamp, frame, x, y, z, qx, qy, qz, qw"]
    for i, (t, q) in enumerate(arkit_rows(room["poses"])):
        values = [*t, *q]
        rows.append(f"{room['timestamps'][i]:.6f}, {i}, " + ", ".join(f"{v:.12f}" for v in values))
    (folder / "odometry.csv").write_text("\n".join(rows) + "\n")
    return folder


def write_r3d(room: dict, path: Path) -> Path:
    """A Record3D ``.r3d`` file of ``room`` at ``path``."""
    K = ROOM_K.matrix
    metadata = {
        "w": 640,
        "h": 480,
        "K": K.T.reshape(-1).tolist(),  # column-major
        "dw": LIDAR_SIZE[0],
        "dh": LIDAR_SIZE[1],
        "fps": 30,
        "poses": [[*q, *t] for t, q in arkit_rows(room["poses"])],
        "initPose": [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0],
        "cameraType": 1,
    }
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("metadata", json.dumps(metadata))
        for i, colour in enumerate(room["colour"]):
            ok, jpg = cv2.imencode(".jpg", cv2.cvtColor(colour, cv2.COLOR_RGB2BGR))
            assert ok
            z.writestr(f"rgbd/{i}.jpg", jpg.tobytes())
            depth = room["lidar"][i].astype(np.float32)
            z.writestr(f"rgbd/{i}.depth", lzfse.compress(depth.tobytes()))
            z.writestr(f"rgbd/{i}.conf", lzfse.compress(room["confidence"][i].tobytes()))
    return path


def zip_folder(
    folder: Path, path: Path, inside: str | None = None, compression: int = zipfile.ZIP_STORED
) -> Path:
    """``folder``'s files zipped into ``path``, under ``inside/`` (default: at the top)."""
    with zipfile.ZipFile(path, "w", compression) as z:
        for item in sorted(folder.rglob("*")):
            if item.is_file():
                name = item.relative_to(folder).as_posix()
                z.write(item, f"{inside}/{name}" if inside else name)
    return path


# ---- files that declare more than they hold: upload bombs, built small (tests and benchmarks)


def png_declaring(width: int, height: int) -> bytes:
    """A 16-bit greyscale PNG whose header declares ``width`` x ``height`` and whose pixel data
    is a little zlib stream of zeros (a decoder would allocate the header's size first)."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
        )

    header = struct.pack(">IIBBBBB", width, height, 16, 0, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(bytes(1 << 20), 9))
        + chunk(b"IEND", b"")
    )


def jpeg_declaring(jpeg: bytes, width: int, height: int) -> bytes:
    """``jpeg`` with the size in its baseline frame header (SOF0) changed."""
    at = jpeg.index(b"\xff\xc0")
    return jpeg[: at + 5] + struct.pack(">HH", height, width) + jpeg[at + 9 :]


def lzfse_declaring(raw_bytes: int) -> bytes:
    """An LZFSE stream of ``raw_bytes`` zeros (a whole number of 8 MiB blocks), made from one
    compressed block repeated: ~1 MB of stream per GB, never held decompressed here."""
    block = lzfse.compress(bytes(8 << 20))
    assert block.endswith(b"bvx$") and lzfse_size(block) == 8 << 20
    return block[:-4] * (raw_bytes // (8 << 20)) + b"bvx$"
