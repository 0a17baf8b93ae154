"""Measure the bytes per frame message at 640x480 and 320x240 on real RGB-D frames.

Encodes 30 frames spread evenly over each sequence with the protocol codec (colour JPEG q=80,
depth re-quantised to millimetres, depth_scale 1000, as PNG and as zlib) and prints a markdown
table of medians, with the bit rate at 15 and 30 frames per second. 320x240 is made with
INTER_AREA for colour and INTER_NEAREST for depth (no mixing across depth edges and holes); a
third setting keeps colour at 640x480 with depth at 320x240, as phone depth sensors deliver.

    python3 -m shared.measure_bandwidth [DATA_DIR]    # from the repo root; default ../shared/data
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import cv2
import numpy as np

from server.protocol import encode, make_frame

DATA = Path("..") / "shared" / "data"  # beside the checkout, run from its root (above)
SEQUENCES = {"synthetic_room0": 5000.0, "7scenes_a": 1000.0}  # folder -> depth scale of its PNGs
FRAMES = 30
# (colour size, depth size): both 640x480, both 320x240, and phone-like depth at half size.
SIZES = [((640, 480), (640, 480)), ((320, 240), (320, 240)), ((640, 480), (320, 240))]


def load_frames(folder: Path, depth_scale: float, n: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """n (colour RGB uint8, depth float32 metres) pairs spread evenly over associations.txt."""
    lines = [ln.split() for ln in (folder / "associations.txt").read_text().splitlines()]
    lines = [ln for ln in lines if ln and not ln[0].startswith("#")]
    frames = []
    for i in np.linspace(0, len(lines) - 1, n).round().astype(int):
        _, rgb_name, _, depth_name = lines[i]
        colour = cv2.cvtColor(cv2.imread(str(folder / rgb_name)), cv2.COLOR_BGR2RGB)
        depth = cv2.imread(str(folder / depth_name), cv2.IMREAD_UNCHANGED)
        frames.append((colour, depth.astype(np.float32) / depth_scale))
    return frames


def resize(colour: np.ndarray, depth: np.ndarray, sizes: tuple) -> tuple:
    """Colour with INTER_AREA, depth with INTER_NEAREST, to (width, height) sizes."""
    colour_size, depth_size = sizes
    if colour.shape[1::-1] != colour_size:
        colour = cv2.resize(colour, colour_size, interpolation=cv2.INTER_AREA)
    if depth.shape[::-1] != depth_size:
        depth = cv2.resize(depth, depth_size, interpolation=cv2.INTER_NEAREST)
    return colour, depth


def measure(frames: list, sizes: tuple, depth_format: str) -> dict[str, float]:
    """Median colour bytes, depth bytes, whole message bytes and encode time (ms)."""
    rows = []
    for seq, (colour, depth) in enumerate(frames):
        colour, depth = resize(colour, depth, sizes)
        t0 = time.perf_counter()
        msg = make_frame(seq, seq / 30.0, colour, depth, depth_format, 80, 1000.0)
        data = encode(msg)
        ms = 1000 * (time.perf_counter() - t0)
        rows.append((len(msg["colour"]), len(msg["depth"]), len(data), ms))
    colour_b, depth_b, total_b, ms = np.median(np.array(rows), axis=0)
    return {"colour": colour_b, "depth": depth_b, "total": total_b, "ms": ms}


def main() -> None:
    data = Path(sys.argv[1]) if len(sys.argv) > 1 else DATA
    print(f"Median over {FRAMES} frames; JPEG q=80, depth in mm (scale 1000); bytes of the whole")
    print("msgpack frame message; encode time on this machine, one CPU thread.\n")
    print(
        "| sequence | colour / depth size | depth | colour JPEG B | depth B | message B "
        "| Mbit/s @15 fps | Mbit/s @30 fps | encode ms |"
    )
    print("|---|---|---|--:|--:|--:|--:|--:|--:|")
    for name, scale in SEQUENCES.items():
        frames = load_frames(data / name, scale, FRAMES)
        for sizes in SIZES:
            (cw, ch), (dw, dh) = sizes
            label = f"{cw}x{ch}" if sizes[0] == sizes[1] else f"{cw}x{ch} / {dw}x{dh}"
            for fmt in ("png", "zlib"):
                m = measure(frames, sizes, fmt)
                print(
                    f"| {name} | {label} | {fmt} | {m['colour']:,.0f} | "
                    f"{m['depth']:,.0f} | {m['total']:,.0f} | {m['total'] * 8 * 15 / 1e6:.1f} | "
                    f"{m['total'] * 8 * 30 / 1e6:.1f} | {m['ms']:.1f} |"
                )


if __name__ == "__main__":
    cv2.setNumThreads(1)
    main()
