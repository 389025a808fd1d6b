"""Freed heap memory goes back to the system: the trim itself, and when workers and the
server call it."""

from __future__ import annotations

import ctypes
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from pydantic import ValidationError
from test_service_units import FakeFactory, settings_for

import service.sessions.manager as manager_module
import service.worker_process as worker_process
from service import memory
from service.app import create_app
from service.settings import ServiceSettings

needs_glibc = pytest.mark.skipif(memory._glibc() is None, reason="malloc_trim is glibc's")


def _resident_bytes() -> int:
    pages = int(Path("/proc/self/statm").read_text().split()[1])
    return pages * os.sysconf("SC_PAGE_SIZE")


@needs_glibc
def test_trim_gives_freed_pages_in_the_middle_of_the_heap_back() -> None:
    libc = memory._glibc()
    assert libc is not None
    libc.malloc.restype = ctypes.c_void_p
    libc.malloc.argtypes = [ctypes.c_size_t]
    libc.free.argtypes = [ctypes.c_void_p]
    chunk, count = 4000, 20_000  # 80 MB of small blocks, below the mmap threshold
    blocks = [libc.malloc(chunk) for _ in range(count)]
    for block in blocks:
        ctypes.memset(block, 1, chunk)  # resident now
    keep = libc.malloc(chunk)  # above the freed ones: free() alone cannot shrink the heap
    for block in blocks:
        libc.free(block)
    before = _resident_bytes()
    assert memory.trim_free_memory() is True
    after = _resident_bytes()
    libc.free(keep)
    assert before - after > 0.5 * chunk * count, (before, after)


def test_a_worker_trims_only_when_it_dropped_a_pipeline(monkeypatch) -> None:
    calls: list[bool] = []
    monkeypatch.setattr(worker_process, "trim_free_memory", lambda: calls.append(True))
    monkeypatch.setattr(worker_process, "_pipelines", {"a": object()})
    worker_process.worker_drop("unknown")
    assert calls == []
    worker_process.worker_drop("a")
    assert calls == [True] and worker_process._pipelines == {}
    assert worker_process.worker_finish("a") == []  # nothing left to flush: still trimmed
    assert calls == [True, True]


@pytest.mark.parametrize("interval_s", [0.05, 0.0])
def test_the_server_trims_on_its_interval_and_stops_at_shutdown(
    tmp_path: Path, monkeypatch, interval_s: float
) -> None:
    calls: list[float] = []
    monkeypatch.setattr(manager_module, "trim_free_memory",
                        lambda: calls.append(time.monotonic()))
    settings = settings_for(tmp_path, memory_trim_interval_s=interval_s)
    with TestClient(create_app(settings, FakeFactory())) as client:
        assert client.get("/healthz").status_code == 200
        time.sleep(0.5)
    stopped = len(calls)
    time.sleep(0.2)
    if interval_s:
        assert stopped >= 2
    else:
        assert stopped == 0
    assert len(calls) == stopped


def test_a_negative_trim_interval_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ValidationError):
        ServiceSettings(data_dir=tmp_path, api_keys="k", memory_trim_interval_s=-1)


# A fresh interpreter, as a worker is: what a worker does for an EuRoC session with IMU (read
# the rig, the IMU noise and the rate; warm up; a frame of the default pipeline) must not pull
# in scipy.spatial (with scipy.sparse and scipy.special about 25 MB per process; only the SIFT
# and KLT matchers and the ground-truth readers need it), nor the server's database layer
# (SQLAlchemy, about 28 MB).
WORKER_IMPORTS = """
import sys
from pathlib import Path
from service.estimator_adapter import (
    EstimatorFactory, euroc_calibration, euroc_frame_rate, euroc_imu_noise, synthetic_run,
)
import service.worker_pipe
import service.worker_process
mav0 = Path(sys.argv[1]) / "mav0"
cam0 = (mav0 / "cam0" / "sensor.yaml").read_bytes()
euroc_calibration(cam0, (mav0 / "cam1" / "sensor.yaml").read_bytes())
euroc_imu_noise((mav0 / "imu0" / "sensor.yaml").read_bytes())
euroc_frame_rate(cam0)
synthetic_run(EstimatorFactory())
print(sorted(m for m in sys.modules if m.startswith(("scipy.spatial", "sqlalchemy"))))
"""


def test_a_worker_imports_neither_scipy_spatial_nor_sqlalchemy(euroc_v101_micro: Path) -> None:
    done = subprocess.run(
        [sys.executable, "-c", WORKER_IMPORTS, str(euroc_v101_micro)],
        cwd=Path(__file__).resolve().parents[1], capture_output=True, text=True, timeout=600,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.strip().splitlines()[-1] == "[]"


# A fresh interpreter: splitting a 724 KB message in two, as the stream did for every frame,
# with the allocator as the server and the workers set it up.
FRAME_BUFFERS = """
import resource, sys
from service.memory import reuse_frame_buffers
assert reuse_frame_buffers()
blob = bytes(724_000)
for _ in range(20):
    left, right = blob[:362_000], blob[362_000:]
    del left, right
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(200):
    left, right = blob[:362_000], blob[362_000:]
    left[-1], right[-1]
    del left, right
print((resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / 200)
"""


@needs_glibc
def test_frame_sized_buffers_are_reused_not_faulted_in_again() -> None:
    done = subprocess.run([sys.executable, "-c", FRAME_BUFFERS],
                          cwd=Path(__file__).resolve().parents[1], capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-3000:]
    # glibc's defaults: about 145 page faults per split (fresh pages for both halves).
    assert float(done.stdout.strip()) < 5


def test_the_stream_splits_a_frame_message_into_views_not_copies() -> None:
    from service.routes.stream import _split_images

    blob = bytes(range(256)) * 10
    left, right = _split_images([blob], 1000)
    assert isinstance(left, memoryview) and left.obj is blob and right.obj is blob
    assert bytes(left) + bytes(right) == blob
    apart = _split_images([blob[:600], blob[600:]], 1000)  # a frame split across messages
    assert bytes(apart[0]) + bytes(apart[1]) == blob
