"""The client's raw8 encoding: the exact pixels the server would decode, or the file as is."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from swarmvo_client.encoding import grey_png_pixels, raw8_pair

from service.images import ImageLimits, decode_pair, decode_raw_pair

LIMITS = ImageLimits(4096, 4096, 16_000_000)


def _png(image: np.ndarray) -> bytes:
    ok, data = cv2.imencode(".png", image)
    assert ok
    return data.tobytes()


@pytest.mark.euroc
def test_raw8_pixels_are_what_the_server_decodes_from_the_png(euroc_v101_micro: Path) -> None:
    folder = euroc_v101_micro / "mav0"
    name = sorted((folder / "cam0" / "data").iterdir())[3].name
    left = (folder / "cam0" / "data" / name).read_bytes()
    right = (folder / "cam1" / "data" / name).read_bytes()
    raw = raw8_pair(left, right)
    assert raw is not None
    raw_left, raw_right, width, height = raw
    assert (width, height) == (752, 480) and len(raw_left) == width * height
    from_png = decode_pair(left, right, LIMITS, (width, height))
    from_raw = decode_raw_pair(raw_left, raw_right, (width, height))
    for png_image, raw_image in zip(from_png, from_raw, strict=True):
        np.testing.assert_array_equal(png_image, raw_image)


def test_what_raw8_cannot_carry_is_sent_as_the_file() -> None:
    rng = np.random.default_rng(0)
    grey = rng.integers(0, 256, (24, 32), dtype=np.uint8)
    assert grey_png_pixels(_png(grey)) is not None
    np.testing.assert_array_equal(grey_png_pixels(_png(grey)), grey)
    colour = rng.integers(0, 256, (24, 32, 3), dtype=np.uint8)
    deep = rng.integers(0, 65536, (24, 32), dtype=np.uint16)
    ok, jpeg = cv2.imencode(".jpg", grey)
    assert ok
    assert grey_png_pixels(_png(colour)) is None
    assert grey_png_pixels(_png(deep)) is None
    assert grey_png_pixels(jpeg.tobytes()) is None  # lossy: the server's decode is the reference
    assert grey_png_pixels(b"not an image") is None
    assert raw8_pair(_png(grey), _png(colour)) is None
    assert raw8_pair(_png(grey), _png(grey[:, :16])) is None  # sizes differ
    both = raw8_pair(_png(grey), _png(grey[::-1]))
    assert both is not None and both[2:] == (32, 24) and both[1] == grey[::-1].tobytes()
