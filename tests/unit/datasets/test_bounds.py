"""The sizes a recording's pieces declare (server.datasets.bounds), read without decoding them,
against what the real encoders write: LZFSE streams of one block and of many, baseline and
progressive JPEGs, PNGs; anything else is a DatasetError, never a wrong size."""

from __future__ import annotations

import cv2
import lzfse
import numpy as np
import pytest

from server.datasets.bounds import DecodeLimits, jpeg_size, lzfse_size, png_size
from server.errors import DatasetError


@pytest.mark.parametrize("size", [1, 3000, 196_608, 5_000_000, 20_000_000])
@pytest.mark.parametrize("content", ["noise", "zeros", "depth"])
def test_lzfse_streams_declare_what_they_decompress_to(size, content):
    rng = np.random.default_rng(size)
    raw = {
        "noise": lambda: rng.integers(0, 256, size, dtype=np.uint8).tobytes(),
        "zeros": lambda: bytes(size),
        "depth": lambda: (
            (1.5 + np.sin(np.arange(size // 4 + 1) / 40.0)).astype(np.float32).tobytes()[:size]
        ),
    }[content]()
    stream = lzfse.compress(raw)
    assert lzfse_size(stream) == len(raw) == len(lzfse.decompress(stream))


@pytest.mark.parametrize(
    "stream",
    [b"", b"bvx", b"not lzfse", b"bvx2" + bytes(10), b"bvx-\xff\xff\xff\x7f" + bytes(8)],
    ids=["empty", "short", "garbage", "truncated header", "raw block past the end"],
)
def test_a_stream_whose_blocks_do_not_parse_is_refused(stream):
    with pytest.raises(DatasetError):
        lzfse_size(stream)


@pytest.mark.parametrize("progressive", [0, 1])
def test_jpeg_and_png_sizes_come_from_their_headers(progressive):
    image = np.random.default_rng(1).integers(0, 256, (123, 457, 3), dtype=np.uint8)
    flags = [cv2.IMWRITE_JPEG_PROGRESSIVE, progressive]
    jpeg = cv2.imencode(".jpg", image, flags)[1].tobytes()
    assert jpeg_size(jpeg) == (457, 123)
    png = cv2.imencode(".png", image[..., 0].astype(np.uint16))[1].tobytes()
    assert png_size(png[:24]) == (457, 123)
    for bad in (b"", jpeg[:2], b"\xff\xd8\xff\xda" + bytes(20), png[:3]):
        with pytest.raises(DatasetError):
            jpeg_size(bad) if bad[:2] == b"\xff\xd8" or not bad else png_size(bad)


def test_limits_name_the_setting_that_refused():
    limits = DecodeLimits(max_pixels=100, max_frames=2, max_metadata_bytes=10)
    limits.check_pixels("it", 10, 10)
    for check, args, setting in [
        (limits.check_pixels, ("it", 11, 10), "upload_max_megapixels"),
        (limits.check_pixels, ("it", -256, -192), "declares a size"),
        (limits.check_frames, ("it", 3), "upload_max_frames"),
        (limits.check_text, ("it", 11), "metadata"),
    ]:
        with pytest.raises(DatasetError, match=setting):
            check(*args)
