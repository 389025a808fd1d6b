"""The worker's pipe: message framing, large calls both ways, errors, deaths, cancelled calls,
and a stop that waits for the worker's open calls."""

from __future__ import annotations

import asyncio
import os
import time
from pathlib import Path

import pytest

from service.worker_pipe import WorkerDied, WorkerPipe, frame_bytes, split_frames
from service.worker_process import worker_context


class NoFactory:
    """Nothing to warm up."""


def reverse(data: bytes) -> bytes:
    return data[::-1]


def pause(seconds: float) -> int:
    time.sleep(seconds)
    return os.getpid()


def refuse(message: str) -> None:
    raise ValueError(message)


def die() -> None:
    os._exit(3)


def test_messages_are_split_only_when_complete() -> None:
    short, long_form = frame_bytes(b"abc"), b"\xff\xff\xff\xff" + (2).to_bytes(8, "big") + b"xy"
    buffer = bytearray(short + long_form + frame_bytes(b"tail")[:5])
    assert split_frames(buffer) == [b"abc", b"xy"]
    assert bytes(buffer) == frame_bytes(b"tail")[:5]  # the incomplete one waits
    buffer += frame_bytes(b"tail")[5:]
    assert split_frames(buffer) == [b"tail"] and not buffer


async def _with_worker(test, on_exit=None) -> None:
    exits: list[WorkerPipe] = []
    worker = WorkerPipe(worker_context(), NoFactory(), on_exit or exits.append)
    try:
        assert await asyncio.wait_for(worker.ready, 120) == worker.pid
        await test(worker, exits)
    finally:
        await worker.stop(10.0)
    assert not Path(f"/proc/{worker.pid}").exists()  # gone and reaped


def test_large_calls_and_answers_go_through_in_order_and_errors_come_back() -> None:
    async def test(worker: WorkerPipe, exits: list) -> None:
        big = os.urandom(3 << 20)  # far more than a pipe holds: written as the worker reads
        calls = [worker.call(reverse, big), worker.call(reverse, b"ab"),
                 worker.call(refuse, "no such rig")]
        assert await calls[0] == big[::-1]
        assert await calls[1] == b"ba"
        with pytest.raises(ValueError, match="no such rig"):
            await calls[2]
        assert worker.open_calls == 0 and not exits

    asyncio.run(_with_worker(test))


def test_a_death_fails_every_open_call_and_runs_their_clean_up() -> None:
    async def test(worker: WorkerPipe, exits: list) -> None:
        over: list[str] = []
        dying = worker.call(die, over=lambda: over.append("dying"))
        queued = worker.call(reverse, b"x", over=lambda: over.append("queued"))
        for call in (dying, queued):
            with pytest.raises(WorkerDied):
                await asyncio.wait_for(call, 60)
        assert sorted(over) == ["dying", "queued"] and exits == [worker]
        assert not worker.alive
        with pytest.raises(WorkerDied):
            worker.call(reverse, b"y")

    asyncio.run(_with_worker(test))


def test_a_cancelled_call_is_over_only_when_the_worker_is_done_and_stop_waits_for_it() -> None:
    async def test(worker: WorkerPipe, exits: list) -> None:
        over: list[float] = []
        slow = worker.call(pause, 0.5, over=lambda: over.append(time.monotonic()))
        slow.cancel()  # the caller stopped waiting; the worker still runs it
        await asyncio.sleep(0.1)
        assert not over  # a shared image slot must not be reused yet
        assert await worker.call(reverse, b"ab") == b"ba"  # answered after the slow one
        assert len(over) == 1
        worker.call(pause, 0.3, over=lambda: over.append(time.monotonic()))
        started = time.monotonic()
        await worker.stop(10.0)  # drains the open call before closing the pipe
        assert len(over) == 2 and over[1] >= started
        assert exits == [worker] and not worker.alive

    asyncio.run(_with_worker(test))


def test_a_stop_kills_a_worker_stuck_in_a_call_nobody_waits_for() -> None:
    async def test(worker: WorkerPipe, exits: list) -> None:
        stuck = worker.call(pause, 3600.0)
        stuck.cancel()
        started = time.monotonic()
        await worker.stop(1.0)
        assert time.monotonic() - started < 30 and exits == [worker] and not worker.alive

    asyncio.run(_with_worker(test))


def test_frames_reach_a_worker_without_any_thread_of_the_server(tmp_path: Path) -> None:
    """No process pool: its manager and call-queue feeder threads woke on every frame."""
    import threading
    from concurrent.futures.process import _ExecutorManagerThread

    from fastapi.testclient import TestClient
    from test_service_units import ProcessFactory, new_session, send, settings_for

    from service.app import create_app

    settings = settings_for(tmp_path, executor="process", workers=2)
    with TestClient(create_app(settings, ProcessFactory())) as c:
        session = new_session(c)
        assert send(c, session, 10).status_code == 200
        assert send(c, session, 20).status_code == 200
        pool_threads = [t.name for t in threading.enumerate()
                        if isinstance(t, _ExecutorManagerThread) or t.name == "QueueFeederThread"]
    assert pool_threads == []
