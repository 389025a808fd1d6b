"""The grey-PNG decoder gives OpenCV's pixels, and hands every other image back to OpenCV.

PNGs are built here with every row filter (OpenCV's encoder picks its own), split over several
IDAT chunks and with ancillary chunks, so that each branch of the unfilter is exercised.
"""

from __future__ import annotations

import itertools
import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from estimator.formats.png import PNG_SIGNATURE, decode_grey8_png, decode_image

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"


def _chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def _paeth(left: int, up: int, corner: int) -> int:
    estimate = left + up - corner
    distances = (abs(estimate - left), abs(estimate - up), abs(estimate - corner))
    if distances[0] <= distances[1] and distances[0] <= distances[2]:
        return left
    return up if distances[1] <= distances[2] else corner


def _filtered(image: np.ndarray, kinds: list[int]) -> bytes:
    """The PNG row stream of a grey 8-bit image with the given filter type per row."""
    height, width = image.shape
    out = bytearray()
    for y in range(height):
        row = image[y].astype(int)
        above = image[y - 1].astype(int) if y > 0 else np.zeros(width, int)
        left = np.concatenate([[0], row[:-1]])
        corner = np.concatenate([[0], above[:-1]])
        kind = kinds[y % len(kinds)]
        if kind == 0:
            predicted = np.zeros(width, int)
        elif kind == 1:
            predicted = left
        elif kind == 2:
            predicted = above
        elif kind == 3:
            predicted = (left + above) // 2
        else:
            predicted = np.array([_paeth(*p) for p in zip(left, above, corner, strict=True)])
        out.append(kind)
        out.extend(((row - predicted) % 256).astype(np.uint8).tobytes())
    return bytes(out)


def _png(
    image: np.ndarray,
    kinds: list[int],
    idat_parts: int = 1,
    depth: int = 8,
    colour: int = 0,
    interlace: int = 0,
) -> bytes:
    height, width = image.shape[:2]
    header = struct.pack(">IIBBBBB", width, height, depth, colour, 0, 0, interlace)
    stream = zlib.compress(_filtered(image, kinds), 6)
    cuts = np.linspace(0, len(stream), idat_parts + 1).astype(int)
    idats = [_chunk(b"IDAT", stream[a:b]) for a, b in itertools.pairwise(cuts)]
    text = _chunk(b"tEXt", b"Comment\x00rendered")
    return PNG_SIGNATURE + _chunk(b"IHDR", header) + text + b"".join(idats) + _chunk(b"IEND", b"")


def _opencv(data: bytes) -> np.ndarray | None:
    return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)


@pytest.mark.parametrize("kinds", [[0], [1], [2], [3], [4], [4, 1, 3, 0, 2, 4, 4]])
@pytest.mark.parametrize("shape", [(37, 53), (1, 9), (12, 1), (96, 160)])
def test_every_row_filter_decodes_to_the_image(kinds: list[int], shape: tuple[int, int]) -> None:
    rng = np.random.default_rng(sum(kinds) * 100 + shape[0])
    # smooth structure plus noise, so that predictions are neither always right nor random
    y, x = np.mgrid[: shape[0], : shape[1]]
    image = ((x * 7 + y * 3) % 256 + rng.integers(0, 40, shape)).astype(np.uint8)
    data = _png(image, kinds, idat_parts=3)
    decoded = decode_grey8_png(data)
    assert decoded is not None and decoded.dtype == np.uint8
    np.testing.assert_array_equal(decoded, image)
    np.testing.assert_array_equal(_opencv(data), image)
    np.testing.assert_array_equal(decode_image(memoryview(data)), image)


def test_opencv_written_pngs_at_every_level() -> None:
    image = np.random.default_rng(3).integers(0, 256, (48, 64), dtype=np.uint8)
    for level in (0, 1, 6, 9):
        ok, encoded = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, level])
        assert ok
        np.testing.assert_array_equal(decode_grey8_png(encoded), image)


def test_other_images_go_to_opencv() -> None:
    rng = np.random.default_rng(5)
    grey16 = rng.integers(0, 65535, (20, 30), dtype=np.uint16)
    colour = rng.integers(0, 256, (20, 30, 3), dtype=np.uint8)
    for image in (grey16, colour):
        ok, encoded = cv2.imencode(".png", image)
        assert ok
        assert decode_grey8_png(encoded) is None
        np.testing.assert_array_equal(decode_image(encoded), image)
    ok, jpeg = cv2.imencode(".jpg", colour)
    assert decode_grey8_png(jpeg) is None
    np.testing.assert_array_equal(decode_image(jpeg), _opencv(jpeg.tobytes()))
    interlaced = _png(colour[:, :, 0], [0], interlace=1)
    assert decode_grey8_png(interlaced) is None


def test_damaged_files_get_opencvs_verdict() -> None:
    image = np.random.default_rng(7).integers(0, 256, (30, 40), dtype=np.uint8)
    good = _png(image, [4, 1], idat_parts=2)
    idat = good.index(b"IDAT")
    bad_crc = bytearray(good)
    bad_crc[idat + 10] ^= 0xFF  # a payload byte: the chunk's CRC no longer matches
    stream = bytearray(_filtered(image, [0]))
    stream[0] = 7  # the first row's filter type: there are five (0-4)
    header = struct.pack(">IIBBBBB", 40, 30, 8, 0, 0, 0, 0)
    bad_filter = (
        PNG_SIGNATURE
        + _chunk(b"IHDR", header)
        + _chunk(b"IDAT", zlib.compress(bytes(stream)))
        + _chunk(b"IEND", b"")
    )
    truncated = (good[: len(good) // 2], good[:-12], b"", b"\x89PNG")
    for damaged in (bytes(bad_crc), bad_filter, *truncated):
        assert decode_grey8_png(damaged) is None
        expected = _opencv(damaged) if damaged else None
        result = decode_image(damaged) if damaged else None
        if expected is None:
            assert result is None
        else:
            np.testing.assert_array_equal(result, expected)


def test_real_frames_match_opencv() -> None:
    folder = SHARED / "euroc_mh01_moving" / "mav0" / "cam0" / "data"
    if not folder.is_dir():
        pytest.skip(f"shared real data not found at {folder}")
    for path in sorted(folder.glob("*.png"))[:5]:
        data = path.read_bytes()
        decoded = decode_grey8_png(data)
        assert decoded is not None
        np.testing.assert_array_equal(decoded, _opencv(data))
