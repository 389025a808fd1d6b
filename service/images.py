"""Decode and validate uploaded stereo images before they reach the odometry.

Dimensions are read from the PNG/JPEG headers first, so a small file that claims a huge image
(a decompression bomb) is refused before any pixel buffer is allocated. Truncated files are
refused structurally (PNG whose chunks end before IEND, JPEG without EOI), because decoders
would otherwise quietly fill the missing rows with grey.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
JPEG_SOI = b"\xff\xd8\xff"
# SOFn markers carrying the frame size (not DHT=C4, JPG=C8, DAC=CC).
_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


class ImageError(ValueError):
    """An upload that is not a usable image; ``status_code`` is the HTTP answer it deserves."""

    def __init__(self, message: str, status_code: int = 422) -> None:
        super().__init__(message)
        self.status_code = status_code


@dataclass(frozen=True)
class ImageLimits:
    max_width: int
    max_height: int
    max_pixels: int


def _png_size(data: bytes | memoryview, name: str) -> tuple[int, int]:
    if len(data) < 33 or data[12:16] != b"IHDR":
        raise ImageError(f"{name}: truncated PNG (no IHDR header)")
    width, height = struct.unpack(">II", data[16:24])
    if not _png_complete(data):
        raise ImageError(f"{name}: truncated PNG (no IEND chunk at the end)")
    return width, height


def _png_complete(data: bytes | memoryview) -> bool:
    """Walk the chunks (length, type, data, CRC) to IEND; bytes after it are ignored."""
    position = len(PNG_SIGNATURE)
    while position + 12 <= len(data):
        (length,) = struct.unpack(">I", data[position : position + 4])
        if data[position + 4 : position + 8] == b"IEND":
            return True
        position += 12 + length
    return False


def _jpeg_size(data: bytes, name: str) -> tuple[int, int]:
    position = 2
    while position + 4 <= len(data):
        if data[position] != 0xFF:
            raise ImageError(f"{name}: corrupt JPEG (bad marker at byte {position})")
        marker = data[position + 1]
        if marker == 0xFF:  # fill byte
            position += 1
            continue
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:  # no length field
            position += 2
            continue
        (length,) = struct.unpack(">H", data[position + 2 : position + 4])
        if marker in _JPEG_SOF:
            if position + 9 > len(data):
                break
            height, width = struct.unpack(">HH", data[position + 5 : position + 9])
            if not data.rstrip(b"\x00").endswith(b"\xff\xd9"):
                raise ImageError(f"{name}: truncated JPEG (no end-of-image marker)")
            return width, height
        if length < 2:
            raise ImageError(f"{name}: corrupt JPEG (segment length {length})")
        position += 2 + length
    raise ImageError(f"{name}: truncated or corrupt JPEG (no frame header)")


def image_size(data: bytes | memoryview, name: str) -> tuple[int, int]:
    """(width, height) from the header of a PNG or JPEG file (bytes, or a view of them)."""
    head = bytes(data[:len(PNG_SIGNATURE)])
    if head.startswith(PNG_SIGNATURE):
        return _png_size(data, name)
    if head.startswith(JPEG_SOI):
        return _jpeg_size(bytes(data), name)
    if not data:
        raise ImageError(f"{name}: empty file")
    raise ImageError(f"{name}: not a PNG or JPEG image (unrecognised file signature)")


def decode_image(data: bytes | memoryview, name: str, limits: ImageLimits) -> np.ndarray:
    """Decode one image as stored: 8/16-bit grey, or colour (BGR; alpha is dropped)."""
    width, height = image_size(data, name)
    if width == 0 or height == 0:
        raise ImageError(f"{name}: image has zero size ({width}x{height})")
    if width > limits.max_width or height > limits.max_height:
        raise ImageError(
            f"{name}: {width}x{height} exceeds the maximum image size "
            f"{limits.max_width}x{limits.max_height}",
            status_code=413,
        )
    if width * height > limits.max_pixels:
        raise ImageError(
            f"{name}: {width}x{height} = {width * height} pixels exceeds the limit of "
            f"{limits.max_pixels}",
            status_code=413,
        )
    # here: the server process validates headers only, its workers decode
    from estimator.formats.png import decode_image as decode_pixels

    image = decode_pixels(data)
    if image is None:
        raise ImageError(f"{name}: the image data could not be decoded (corrupt file)")
    if image.shape[1] != width or image.shape[0] != height:
        raise ImageError(f"{name}: decoded size differs from the header (corrupt file)")
    if image.dtype not in (np.uint8, np.uint16):
        raise ImageError(f"{name}: unsupported pixel type {image.dtype} (8 or 16 bit only)")
    if image.ndim == 3:
        channels = image.shape[2]
        if channels == 4:
            image = np.ascontiguousarray(image[:, :, :3])
        elif channels == 1:
            image = image[:, :, 0]
        elif channels != 3:
            raise ImageError(f"{name}: unsupported channel count {channels}")
    return image


def warm_up_decoder() -> None:
    """Decode one grey PNG in this process, so that the compiled row unfilter
    (estimator/formats/png.py) is loaded (or, with an empty JIT cache, compiled) before the
    first frame arrives, not inside its CPU budget."""
    import cv2

    ok, encoded = cv2.imencode(".png", np.zeros((8, 8), dtype=np.uint8))
    if ok:
        decode_image(encoded.tobytes(), "warm-up", ImageLimits(64, 64, 64 * 64))


def decode_pair(
    left: bytes | memoryview,
    right: bytes | memoryview,
    limits: ImageLimits,
    expected_size: tuple[int, int],
) -> tuple[np.ndarray, np.ndarray]:
    """Both images of a stereo pair, checked against each other and the calibration."""
    left_image = decode_image(left, "left", limits)
    right_image = decode_image(right, "right", limits)
    if left_image.shape != right_image.shape or left_image.dtype != right_image.dtype:
        raise ImageError(
            f"left and right images differ: {_describe(left_image)} vs {_describe(right_image)}"
        )
    width, height = expected_size
    if left_image.shape[1] != width or left_image.shape[0] != height:
        raise ImageError(
            f"images are {left_image.shape[1]}x{left_image.shape[0]} but the session's "
            f"calibration is for {width}x{height}"
        )
    return left_image, right_image


def decode_raw_pair(
    left: bytes | memoryview, right: bytes | memoryview, expected_size: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """A raw 8-bit grey pair (row-major, no container): nothing to decode, only sizes to check."""
    width, height = expected_size
    pixels = width * height
    for name, data in (("left", left), ("right", right)):
        if len(data) != pixels:
            raise ImageError(
                f"{name}: {len(data)} raw bytes, but the session's calibration is for "
                f"{width}x{height} = {pixels} 8-bit pixels"
            )
    shape = (height, width)
    # Copies: the estimator owns writable arrays, as it does after a PNG decode.
    return (np.frombuffer(left, dtype=np.uint8).reshape(shape).copy(),
            np.frombuffer(right, dtype=np.uint8).reshape(shape).copy())


def _describe(image: np.ndarray) -> str:
    channels = 1 if image.ndim == 2 else image.shape[2]
    return f"{image.shape[1]}x{image.shape[0]}x{channels} {image.dtype}"
