"""Image codecs of the frame message: JPEG colour, 16-bit PNG or zlib depth; the size checks
read the images' headers before decoding, so a bad image is refused without decoding it."""

from __future__ import annotations

import zlib
from collections.abc import Mapping

import cv2
import numpy as np

from server.protocol.errors import ProtocolError
from server.protocol.spec import LIMITS

PNG_COMPRESSION = 3  # zlib level inside the PNG; 1-3 are near the size of 9 for depth, much faster
ZLIB_LEVEL = 6  # zlib's default, what browsers' CompressionStream("deflate") uses
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_IEND = b"\x00\x00\x00\x00IEND\xaeB`\x82"


def encode_depth(
    depth_m: np.ndarray, depth_format: str = "png", depth_scale: float = 1000.0
) -> bytes:
    """Depth (H, W) metres -> uint16 units of 1/depth_scale m, PNG or zlib bytes.

    Non-finite, non-positive and unrepresentable (> 65535 units) depths become 0 (no measurement).
    """
    depth = np.asarray(depth_m, dtype=np.float64)
    if depth.ndim != 2:
        raise ProtocolError("invalid_field", f"depth must be (H, W), got shape {depth.shape}")
    units = np.rint(np.nan_to_num(depth * depth_scale, nan=0.0, posinf=0.0, neginf=0.0))
    units[(units < 0) | (units > 65535)] = 0
    u16 = units.astype("<u2")
    if depth_format == "png":
        ok, buf = cv2.imencode(".png", u16, [cv2.IMWRITE_PNG_COMPRESSION, PNG_COMPRESSION])
        if not ok:
            raise ProtocolError("invalid_field", "depth does not encode as PNG")
        return buf.tobytes()
    if depth_format == "zlib":
        return zlib.compress(u16.tobytes(), ZLIB_LEVEL)
    raise ProtocolError("invalid_field", f"depth_format must be png or zlib, got {depth_format!r}")


def encode_jpeg(colour_rgb: np.ndarray, quality: int = 80) -> bytes:
    """(H, W, 3) uint8 RGB -> baseline JPEG bytes."""
    if colour_rgb.ndim != 3 or colour_rgb.shape[2] != 3 or colour_rgb.dtype != np.uint8:
        raise ProtocolError(
            "invalid_field", f"colour must be (H, W, 3) uint8, got {colour_rgb.shape}"
        )
    bgr = cv2.cvtColor(colour_rgb, cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ProtocolError("invalid_field", "colour does not encode as JPEG")
    return buf.tobytes()


def _jpeg_size(data: bytes) -> tuple[int, int]:
    """(width, height) from the JPEG's frame header, without decoding; raises ValueError."""
    if data[:3] != b"\xff\xd8\xff" or data.rstrip(b"\x00")[-2:] != b"\xff\xd9":
        raise ValueError("not a complete JPEG (no start or end marker)")
    i = 2
    while i + 4 <= len(data):
        if data[i] != 0xFF:
            raise ValueError(f"bad JPEG marker at byte {i}")
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
        elif marker == 0x01 or 0xD0 <= marker <= 0xD7:  # markers without a length
            i += 2
        elif 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC) and i + 9 <= len(data):
            return int.from_bytes(data[i + 7 : i + 9], "big"), int.from_bytes(
                data[i + 5 : i + 7], "big"
            )
        else:
            i += 2 + int.from_bytes(data[i + 2 : i + 4], "big")
    raise ValueError("JPEG has no frame header")


def _png_size(data: bytes) -> tuple[int, int]:
    """(width, height) of a complete 16-bit greyscale PNG, from its header; raises ValueError."""
    if data[:8] != _PNG_SIGNATURE or data[12:16] != b"IHDR" or len(data) < 33:
        raise ValueError("not a PNG")
    if data[24] != 16 or data[25] != 0:
        raise ValueError(f"depth PNG must be 16-bit greyscale, got {data[24]}-bit type {data[25]}")
    if not data.endswith(_PNG_IEND):
        raise ValueError("truncated PNG (no IEND chunk)")
    return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")


def _decode_colour(data: bytes, size: tuple[int, int], seq: int | None) -> np.ndarray:
    try:
        found = _jpeg_size(bytes(data))
    except ValueError as exc:
        raise ProtocolError("corrupt_image", f"colour: {exc}", seq=seq) from exc
    if found != size:
        raise ProtocolError("size_mismatch", f"colour is {found}, hello said {size}", seq=seq)
    # Decoded straight to RGB: the same pixels as BGR then a swap, without the swap's pass.
    rgb = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR_RGB)
    if rgb is None or rgb.shape[1::-1] != size:
        raise ProtocolError("corrupt_image", "colour JPEG does not decode", seq=seq)
    return rgb


def _decode_depth_units(
    data: bytes, fmt: str, size: tuple[int, int], seq: int | None
) -> np.ndarray:
    width, height = size
    if fmt == "png":
        try:
            found = _png_size(bytes(data))
        except ValueError as exc:
            raise ProtocolError("corrupt_image", f"depth: {exc}", seq=seq) from exc
        if found != size:
            raise ProtocolError("size_mismatch", f"depth is {found}, hello said {size}", seq=seq)
        u16 = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        if u16 is None or u16.dtype != np.uint16 or u16.shape != (height, width):
            raise ProtocolError("corrupt_image", "depth PNG does not decode", seq=seq)
        return u16
    expected = 2 * width * height  # zlib: bound the output, a small stream can inflate to GBs
    inflater = zlib.decompressobj()
    try:
        raw = inflater.decompress(data, expected + 1)
    except zlib.error as exc:
        raise ProtocolError("corrupt_image", f"depth zlib: {exc}", seq=seq) from exc
    if len(raw) > expected or inflater.unconsumed_tail:
        raise ProtocolError("size_mismatch", f"depth inflates past {width}x{height}", seq=seq)
    if not inflater.eof:
        raise ProtocolError("corrupt_image", "depth zlib stream is truncated", seq=seq)
    if len(raw) != expected:
        raise ProtocolError(
            "size_mismatch",
            f"depth has {len(raw) // 2} values, hello said {width}x{height}",
            seq=seq,
        )
    return np.frombuffer(raw, dtype="<u2").reshape(height, width)


def decode_frame_images(message: Mapping, hello: Mapping) -> tuple[np.ndarray, np.ndarray]:
    """-> colour (H, W, 3) uint8 RGB at colour_size, depth (h, w) float32 metres at depth_size.

    Raises ProtocolError: corrupt_image, size_mismatch (against the hello), or bad_depth when
    the depth in metres is non-finite, negative, above max_depth_m (a wrong depth_scale), or
    all-zero: fewer than min_valid_depth_fraction of its pixels hold a measurement (> 0).
    """
    seq = message.get("seq")
    colour = _decode_colour(message["colour"], tuple(hello["colour_size"]), seq)
    units = _decode_depth_units(
        message["depth"], message["depth_format"], tuple(hello["depth_size"]), seq
    )
    scale = message.get("depth_scale", hello["depth_scale"])
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        scale32 = np.float32(scale)
        depth = units.astype(np.float32) / scale32
    # Units are uint16 (>= 0): over a finite positive scale the depth is finite and not
    # negative, and its largest value is the largest unit's, so only other scales need the
    # passes over every pixel.
    if np.isfinite(scale32) and scale32 > 0:
        largest = np.float32(units.max()) / scale32
    else:
        if not np.isfinite(depth).all():
            raise ProtocolError("bad_depth", f"depth not finite (depth_scale {scale})", seq=seq)
        if depth.min() < 0:
            raise ProtocolError("bad_depth", f"negative depth (depth_scale {scale})", seq=seq)
        largest = depth.max()
    if largest > LIMITS["max_depth_m"]:
        raise ProtocolError(
            "bad_depth", f"depth up to {largest:.0f} m: is depth_scale {scale} right?", seq=seq
        )
    valid = np.count_nonzero(depth) / depth.size
    if valid < LIMITS["min_valid_depth_fraction"]:
        raise ProtocolError(
            "bad_depth",
            f"all-zero depth: {100 * valid:.2f}% of pixels valid, "
            f"need {100 * LIMITS['min_valid_depth_fraction']:.0f}%",
            seq=seq,
            counted=False,
        )
    return colour, depth
