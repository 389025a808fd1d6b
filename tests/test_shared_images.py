"""A frame's images through shared-memory slots: reuse, release, fallback, no leak."""

from __future__ import annotations

from multiprocessing import shared_memory
from pathlib import Path

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient
from test_service_units import (
    HEIGHT,
    KEY_A,
    WIDTH,
    DescribingFactory,
    new_session,
    png,
    send,
    settings_for,
)

from estimator.types import StereoFrame
from service.app import create_app
from service.images import ImageLimits, decode_image, decode_pair, image_size
from service.shared_images import ImageSlots, read_pair

LIMITS = ImageLimits(4096, 4096, 4096 * 4096)


def test_slots_are_reused_most_recent_first_and_refused_when_full_or_too_small() -> None:
    slots = ImageSlots(2, 64)
    try:
        first = slots.put(b"a" * 10, b"b" * 20)
        second = slots.put(b"c", b"d")
        assert first is not None and second is not None
        assert (first.slot, second.slot) == (0, 1)
        assert slots.put(b"e", b"f") is None  # all taken: the caller pickles instead
        assert [bytes(v) for v in read_pair(first)] == [b"a" * 10, b"b" * 20]
        slots.release(first)
        slots.release(first)  # a second release changes nothing
        assert slots.free == 1
        third = slots.put(b"g" * 3, b"h" * 4)
        assert third is not None and third.slot == 0
        assert [bytes(v) for v in read_pair(third)] == [b"ggg", b"hhhh"]
        assert slots.put(b"x" * 40, b"y" * 40) is None  # larger than a slot
        slots.release(second)
        slots.release(third)
        assert slots.free == 2
    finally:
        slots.close()


def test_closing_unlinks_the_segment() -> None:
    slots = ImageSlots(1, 1024)
    name = slots.name
    slots.close()
    slots.close()  # twice is harmless
    with pytest.raises(FileNotFoundError):
        shared_memory.SharedMemory(name=name)
    assert slots.put(b"a", b"b") is None


def test_a_png_pair_decodes_from_the_views_as_from_bytes() -> None:
    left, right = png(value=1), png(value=7)
    slots = ImageSlots(1, len(left) + len(right))
    try:
        pair = slots.put(left, right)
        assert pair is not None
        size = image_size(left, "left")
        expected = decode_pair(left, right, LIMITS, size)
        views = read_pair(pair)
        assert image_size(views[0], "left") == size
        got = decode_pair(*views, LIMITS, size)
        for a, b in zip(expected, got, strict=True):
            np.testing.assert_array_equal(a, b)
    finally:
        slots.close()


def _pixel_sums(frame: StereoFrame, message: str) -> str:
    """The pixel sums the worker was given, so the test sees what reached it."""
    return f"{int(frame.left.sum())},{int(frame.right.sum())};{message}"


def _noise_png(seed: int) -> bytes:
    """Incompressible pixels: a few KB per image, more than the small slot of the test."""
    image = np.random.default_rng(seed).integers(0, 256, (HEIGHT, WIDTH), dtype=np.uint8)
    ok, data = cv2.imencode(".png", image)
    assert ok and len(data) > 1024
    return data.tobytes()


def _sums(answer) -> tuple[int, int]:
    left, right = answer.json()["message"].split(";", 1)[0].split(",")
    return int(left), int(right)


@pytest.mark.parametrize("slot_bytes", [1 << 20, 1024])  # shared slots / too small: the pipe
def test_frames_reach_the_worker_intact_and_every_slot_comes_back(
    tmp_path: Path, slot_bytes: int
) -> None:
    settings = settings_for(tmp_path, executor="process", workers=1, image_slots=2,
                            image_slot_bytes=slot_bytes)
    with TestClient(create_app(settings, DescribingFactory(_pixel_sums))) as c:
        runner = c.app.state.swarmvo.manager.runner
        assert runner.images is not None
        name = runner.images.name
        session = new_session(c)
        for t, value in ((10, 1), (20, 5), (30, 9)):
            left, right = _noise_png(value), _noise_png(value + 100)
            answer = send(c, session, t, left=left, right=right)
            assert answer.status_code == 200, answer.text
            want = (int(decode_image(left, "l", LIMITS).sum()),
                    int(decode_image(right, "r", LIMITS).sum()))
            assert _sums(answer) == want
        assert runner.images.free == 2
        assert runner.images.handed == (3 if slot_bytes > 1024 else 0)
        died = send(c, session, 666)  # the worker dies holding a slot
        assert died.status_code == 503
        assert runner.images.free == 2
        again = send(c, session, 700)
        assert again.status_code == 200, again.text
        assert runner.images.free == 2
    with pytest.raises(FileNotFoundError):  # shut down: the segment is gone
        shared_memory.SharedMemory(name=name)


def test_no_slots_means_the_pipe(tmp_path: Path) -> None:
    settings = settings_for(tmp_path, executor="process", workers=1, image_slots=0)
    with TestClient(create_app(settings, DescribingFactory(_pixel_sums))) as c:
        assert c.app.state.swarmvo.manager.runner.images is None
        session = new_session(c)
        assert send(c, session, 10).status_code == 200


def test_raw8_pixels_over_the_websocket_reach_the_worker_through_a_slot(tmp_path: Path) -> None:
    settings = settings_for(tmp_path, executor="process", workers=1, image_slots=1)
    left = np.random.default_rng(1).integers(0, 256, WIDTH * HEIGHT, dtype=np.uint8)
    right = (left // 2).astype(np.uint8)
    header = {"type": "frame", "timestamp_ns": 10, "encoding": "raw8", "width": WIDTH,
              "height": HEIGHT, "left_bytes": left.size, "right_bytes": right.size}
    with TestClient(create_app(settings, DescribingFactory(_pixel_sums))) as c:
        runner = c.app.state.swarmvo.manager.runner
        session = new_session(c)
        with c.websocket_connect(f"/v1/sessions/{session}/stream",
                                 headers={"Authorization": f"Bearer {KEY_A}"}) as ws:
            ws.receive_json()
            ws.send_json(header)
            ws.send_bytes(left.tobytes() + right.tobytes())
            pose = ws.receive_json()
        assert pose["type"] == "pose", pose
        assert pose["message"].split(";")[0] == f"{int(left.sum())},{int(right.sum())}"
        assert (runner.images.handed, runner.images.free) == (1, 1)


@pytest.mark.parametrize("slots", [0, 1])  # no slots / a slot too small: the pipe
def test_stream_images_reach_the_worker_through_the_pipe_when_no_slot_takes_them(
    tmp_path: Path, slots: int
) -> None:
    """The stream hands on views of the received message; the pipe needs bytes."""
    settings = settings_for(tmp_path, executor="process", workers=1, image_slots=slots,
                            image_slot_bytes=1024)
    left, right = _noise_png(3), _noise_png(103)
    header = {"type": "frame", "timestamp_ns": 10, "left_bytes": len(left),
              "right_bytes": len(right)}
    with TestClient(create_app(settings, DescribingFactory(_pixel_sums))) as c:
        session = new_session(c)
        with c.websocket_connect(f"/v1/sessions/{session}/stream",
                                 headers={"Authorization": f"Bearer {KEY_A}"}) as ws:
            ws.receive_json()
            ws.send_json(header)
            ws.send_bytes(left + right)
            pose = ws.receive_json()
        assert pose["type"] == "pose", pose
        want = (int(decode_image(left, "l", LIMITS).sum()),
                int(decode_image(right, "r", LIMITS).sum()))
        assert pose["message"].split(";")[0] == f"{want[0]},{want[1]}"
