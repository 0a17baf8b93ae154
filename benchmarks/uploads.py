"""Uploads that cannot take the server down: what a small hostile recording costs the server.

Starts ``python -m server serve`` in its own process, waits until its process tree is idle, then
uploads (``POST /api/recordings``) each of a set of small files built here on the fly: a genuine
little Record3D recording (the baseline, converted and kept), and bombs that would expand to
gigabytes if decoded (metadata of JSON whitespace, LZFSE depth streams, a JPEG and PNGs whose
headers declare huge images). For each it
records the answer, the wall time, the CPU of the server's whole process tree (the web process,
the forkserver and the conversion process it forks: ``capacity.py``'s readers) and the web
process's peak resident memory (VmHWM) over its idle figure.

Targets (issue 32): the web process's peak within ~100 MB of idle through every bomb; at most
1 s of CPU for a rejected upload under 1 MB (all of these are under 3 MB; the worst counts).
Writes ``benchmarks/results/uploads.md``. (A zip whose members declare more than
``MAX_UNPACK_FACTOR`` times the upload limit is refused from its directory; building one that
declares gigabytes takes minutes, so ``tests/server/test_recordings.py`` covers it at a small
limit.)

    python benchmarks/uploads.py
"""

from __future__ import annotations

import argparse
import io
import json
import sys
import tempfile
import time
import zipfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # run from anywhere, installed or not

import cv2  # noqa: E402
import httpx  # noqa: E402
import lzfse  # noqa: E402
import numpy as np  # noqa: E402
from capacity import scan_tree, snapshot_tree, tree_cpu_s  # noqa: E402  (this folder)
from provenance import run_heading, utc_stamp  # noqa: E402

from server.client.server_process import ServerProcess  # noqa: E402
from tests.support.iphone_recordings import (  # noqa: E402  (the bombs the upload tests build)
    jpeg_declaring,
    lzfse_declaring,
    png_declaring,
)

RESULTS = REPO / "benchmarks" / "results" / "uploads.md"
WEB_GROWTH_TARGET_MB = 100.0
CPU_TARGET_S = 1.0  # per rejected upload (the figure is for files under 1 MB)
W, H, DW, DH, FRAMES = 640, 480, 256, 192, 8


def hwm_mb(pid: int) -> float:
    """A process's peak resident memory so far (VmHWM), MB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def r3d(metadata: bytes | None = None, depth: bytes | None = None, jpeg: bytes | None = None):
    """A little Record3D recording (FRAMES frames of a textured wall 1.5 m away), with its
    metadata, every depth member or every colour member replaced when given."""
    rng = np.random.default_rng(0)
    image = cv2.GaussianBlur(rng.integers(0, 256, (H, W, 3), dtype=np.uint8), (5, 5), 0)
    meta = {
        "w": W,
        "h": H,
        "K": [500.0, 0, 0, 0, 500.0, 0, W / 2 - 0.5, H / 2 - 0.5, 1],
        "dw": DW,
        "dh": DH,
        "fps": 30,
        "poses": [[0, 0, 0, 1, 0.01 * i, 0, 0] for i in range(FRAMES)],
    }
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("metadata", metadata if metadata is not None else json.dumps(meta))
        for i in range(FRAMES):
            colour = jpeg or cv2.imencode(".jpg", np.roll(image, 4 * i, axis=1))[1].tobytes()
            z.writestr(f"rgbd/{i}.jpg", colour)
            wall = np.full((DH, DW), 1.5, np.float32).tobytes()
            z.writestr(f"rgbd/{i}.depth", depth or lzfse.compress(wall))
            z.writestr(f"rgbd/{i}.conf", lzfse.compress(np.full((DH, DW), 2, np.uint8).tobytes()))
    return out.getvalue()


def stray_zip(folder: Path, first_depth: bytes | None = None) -> bytes:
    """A little Stray Scanner export zipped, its first depth PNG replaced when given."""
    folder.mkdir(parents=True)
    (folder / "depth").mkdir()
    video = cv2.VideoWriter(str(folder / "rgb.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 30, (W, H))
    rng = np.random.default_rng(1)
    for i in range(FRAMES):
        video.write(rng.integers(0, 256, (H, W, 3), dtype=np.uint8))
        depth = np.full((DH, DW), 1500, np.uint16)
        (folder / "depth" / f"{i:06d}.png").write_bytes(cv2.imencode(".png", depth)[1].tobytes())
    video.release()
    if first_depth is not None:
        (folder / "depth" / "000000.png").write_bytes(first_depth)
    (folder / "camera_matrix.csv").write_text(f"500,0,{W / 2 - 0.5}\n0,500,{H / 2 - 0.5}\n0,0,1\n")
    rows = ["timestamp, frame, x, y, z, qx, qy, qz, qw"]
    rows += [f"{i / 30:.4f}, {i}, {0.01 * i}, 0, 0, 0, 0, 0, 1" for i in range(FRAMES)]
    (folder / "odometry.csv").write_text("\n".join(rows) + "\n")
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as z:
        for item in sorted(folder.rglob("*")):
            if item.is_file():
                z.write(item, item.relative_to(folder).as_posix())
    return out.getvalue()


def cases(scratch: Path) -> list[tuple[str, bytes, str]]:
    """(what, the file's bytes, its name) for each upload, the genuine one first."""
    first_jpeg = cv2.imencode(".jpg", np.zeros((H, W, 3), np.uint8))[1].tobytes()
    huge_jpeg = jpeg_declaring(first_jpeg, 30000, 20000)
    meta = json.loads(zipfile.ZipFile(io.BytesIO(r3d())).read("metadata"))
    return [
        ("genuine .r3d, 8 frames (converted)", r3d(), "genuine.r3d"),
        ("metadata: 1 GB of JSON whitespace", r3d(b'{"w": 640' + b" " * (1 << 30) + b"}"), "a.r3d"),
        ("depth: LZFSE streams of 2 GB each", r3d(depth=lzfse_declaring(2 << 30)), "b.r3d"),
        ("depth: 64 MB in a 40 kB LZFSE stream", r3d(depth=lzfse_declaring(64 << 20)), "c.r3d"),
        ("colour: JPEG declaring 30000x20000", r3d(jpeg=huge_jpeg), "d.r3d"),
        (
            "metadata: 16384x16384 colour",
            r3d(json.dumps({**meta, "w": 16384, "h": 16384}).encode()),
            "e.r3d",
        ),
        (
            "stray: depth PNG declaring 60000x45000",
            stray_zip(scratch / "png", png_declaring(60000, 45000)),
            "f.zip",
        ),
    ]


def wait_idle(root: int, cores: float = 0.1, timeout_s: float = 60.0) -> None:
    """Until the server's process tree uses under ``cores`` over half a second."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        before = tree_cpu_s(scan_tree(root))
        time.sleep(0.5)
        if tree_cpu_s(scan_tree(root)) - before < 0.5 * cores:
            return


def main() -> None:
    argparse.ArgumentParser(description=__doc__.split("\n\n")[0]).parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as scratch:
        uploads = cases(Path(scratch))
        with ServerProcess(Path(scratch) / "data") as server:
            wait_idle(server.pid)
            idle_hwm = hwm_mb(server.pid)
            print(f"server up; web process peak so far {idle_hwm:.0f} MB", flush=True)
            for what, data, name in uploads:
                tree0, _ = snapshot_tree(server.pid)
                t0 = time.monotonic()
                r = httpx.post(
                    f"{server.url}/api/recordings",
                    params={"name": name},
                    content=data,
                    timeout=600,
                )
                wall = time.monotonic() - t0
                wait_idle(server.pid)
                tree1, _ = snapshot_tree(server.pid)
                cpu = tree_cpu_s(tree1) - tree_cpu_s(tree0)
                answer = r.json()
                said = answer.get("error", {}).get("message", f"{answer.get('frames')} frames")
                row = {
                    "what": what,
                    "mb": len(data) / 1e6,
                    "status": r.status_code,
                    "wall_s": wall,
                    "cpu_s": cpu,
                    "growth_mb": hwm_mb(server.pid) - idle_hwm,
                    "said": said,
                }
                rows.append(row)
                print(
                    f"{what}: {row['mb']:.2f} MB -> {r.status_code} in {wall:.2f} s, "
                    f"CPU {cpu:.2f} s, web peak +{row['growth_mb']:.0f} MB; {said[:100]}",
                    flush=True,
                )
    report(rows)


def report(rows: list[dict]) -> None:
    growth = max(r["growth_mb"] for r in rows)
    rejected = [r for r in rows if r["status"] >= 400]
    worst_cpu = max((r["cpu_s"] for r in rejected), default=float("nan"))
    largest = max((r["mb"] for r in rejected), default=float("nan"))
    lines = run_heading(utc_stamp())
    lines += [
        "| upload | size MB | answer | wall s | server CPU s | web peak over idle MB | message |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['what']} | {r['mb']:.2f} | {r['status']} | {r['wall_s']:.2f} | "
            f"{r['cpu_s']:.2f} | {r['growth_mb']:.0f} | {r['said'][:90]} |"
        )
    lines += [
        "",
        "| figure | measured | target | met |",
        "|---|---|---|---|",
        f"| web process peak over idle, all uploads | {growth:.0f} MB "
        f"| <= {WEB_GROWTH_TARGET_MB:.0f} MB "
        f"| {'yes' if growth <= WEB_GROWTH_TARGET_MB else 'NO'} |",
        f"| server CPU per rejected upload (worst of {len(rejected)}, all <= {largest:.1f} MB) "
        f"| {worst_cpu:.2f} s | <= {CPU_TARGET_S:.0f} s "
        f"| {'yes' if worst_cpu <= CPU_TARGET_S else 'NO'} |",
    ]
    print("\n".join(lines))
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    previous = RESULTS.read_text() if RESULTS.exists() else "# Uploads: what hostile files cost\n"
    RESULTS.write_text(previous.rstrip("\n") + "\n" + "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
