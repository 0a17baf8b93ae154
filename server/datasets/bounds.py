"""Sizes an uploaded recording declares, read before anything is decoded or allocated.

A recording is untrusted input: a 2 MB file may hold a zip member, an LZFSE stream or a PNG
that expands to gigabytes. Each reader asks this module what a piece will expand to (the size a
zip member declares, the raw bytes an LZFSE stream's block headers declare, the pixels in a PNG's
IHDR or a JPEG's frame header) and refuses it with a DatasetError naming the limit before it
decodes a byte. The decoders then cannot produce more than was declared: zipfile stops at a
member's declared size, OpenCV allocates the header's pixels.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from server.errors import DatasetError


@dataclass(frozen=True)
class DecodeLimits:
    """What one recording may expand to. max_pixels: pixels in any one image (colour, depth,
    confidence or a video frame); max_frames: frames in the recording; max_metadata_bytes: a
    metadata or odometry text, bytes. ``server.upload_*`` sets them for uploads."""

    max_pixels: int = 4096 * 4096
    max_frames: int = 100_000
    max_metadata_bytes: int = 64 * 2**20

    def check_pixels(self, what: str, width: int, height: int) -> None:
        """DatasetError unless an image of ``width`` x ``height`` is within ``max_pixels``."""
        if width <= 0 or height <= 0:
            raise DatasetError(f"{what} declares a size of {width}x{height}")
        if width * height > self.max_pixels:
            raise DatasetError(
                f"{what} is {width}x{height} pixels, more than the {self.max_pixels / 1e6:.1f} "
                "megapixels allowed (server.upload_max_megapixels)"
            )

    def check_frames(self, what: str, count: int) -> None:
        if count > self.max_frames:
            raise DatasetError(
                f"{what} lists {count} frames, more than the {self.max_frames} allowed "
                "(server.upload_max_frames)"
            )

    def check_text(self, what: str, size: int) -> None:
        if size > self.max_metadata_bytes:
            raise DatasetError(
                f"{what} is {size / 1e6:.0f} MB, more than the {self.max_metadata_bytes / 1e6:.0f}"
                " MB a recording's metadata may take (server.upload_max_metadata_mb)"
            )


DEFAULT_LIMITS = DecodeLimits()

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def png_size(head: bytes) -> tuple[int, int]:
    """(width, height) from a PNG's first 24 bytes (its IHDR chunk); DatasetError if it is no
    PNG."""
    if len(head) < 24 or head[:8] != _PNG_SIGNATURE or head[12:16] != b"IHDR":
        raise DatasetError("not a PNG file")
    width, height = struct.unpack(">II", head[16:24])
    return width, height


# Start-of-frame markers, which carry the image's size: C0-CF except DHT (C4), JPG (C8), DAC (CC).
_SOF_MARKERS = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def jpeg_size(data: bytes) -> tuple[int, int]:
    """(width, height) from a JPEG's frame header, found by walking its marker segments (no
    pixel is decoded); DatasetError if there is none before the image data."""
    if data[:2] != b"\xff\xd8":
        raise DatasetError("not a JPEG file")
    at = 2
    while at + 4 <= len(data):
        if data[at] != 0xFF:
            break
        marker = data[at + 1]
        if marker == 0xFF:  # fill byte
            at += 1
            continue
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:  # segments without a length
            at += 2
            continue
        (length,) = struct.unpack(">H", data[at + 2 : at + 4])
        if marker in _SOF_MARKERS:
            if at + 9 > len(data):
                break
            height, width = struct.unpack(">HH", data[at + 5 : at + 9])
            return width, height
        if marker in (0xD9, 0xDA) or length < 2:  # end of image, or the scan: no header came
            break
        at += 2 + length
    raise DatasetError("a JPEG without a frame header")


# LZFSE block magics (little-endian 'bvx?') and the fixed part of each block's header.
_BVX_END, _BVX_RAW, _BVX_V1, _BVX_V2, _BVX_LZVN = (
    int.from_bytes(m, "little") for m in (b"bvx$", b"bvx-", b"bvx1", b"bvx2", b"bvxn")
)


def lzfse_size(stream: bytes) -> int:
    """The bytes an LZFSE stream decompresses to, summed from its block headers (each block
    declares its raw size, and its own length, so none is decoded); DatasetError for a stream
    whose blocks do not parse."""
    at, total = 0, 0
    while True:
        if at + 4 > len(stream):
            raise DatasetError("an LZFSE stream that ends without its end-of-stream block")
        (magic,) = struct.unpack_from("<I", stream, at)
        if magic == _BVX_END:
            return total
        if at + 8 > len(stream):
            break
        (raw,) = struct.unpack_from("<I", stream, at + 4)
        if magic == _BVX_RAW:  # magic, raw size, the bytes themselves
            length = 8 + raw
        elif magic == _BVX_LZVN:  # magic, raw size, payload size, payload
            if at + 12 > len(stream):
                break
            length = 12 + struct.unpack_from("<I", stream, at + 8)[0]
        elif magic == _BVX_V2:
            # Three packed 64-bit fields follow; the header's own length is the low 32 bits of
            # the third, the literal payload bits 20-39 of the first, the L/M/D payload bits
            # 40-59 of the second.
            if at + 32 > len(stream):
                break
            fields = struct.unpack_from("<QQQ", stream, at + 8)
            literal_bytes = (fields[0] >> 20) & 0xFFFFF
            lmd_bytes = (fields[1] >> 40) & 0xFFFFF
            length = (fields[2] & 0xFFFFFFFF) + literal_bytes + lmd_bytes
        elif magic == _BVX_V1:
            raise DatasetError("an LZFSE stream with version-1 blocks, which no recorder writes")
        else:
            raise DatasetError("not an LZFSE stream (unknown block)")
        if length <= 0:
            break
        total += raw
        at += length
    raise DatasetError("a truncated LZFSE stream")
