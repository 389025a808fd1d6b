"""What handing a frame to a worker process costs: the process pool against the worker's pipe.

One spawn worker reads a V1_01 stereo pair from a shared image slot (as ``worker_frame`` does,
without the odometry; ``--pickled``: sent with the request, as when no slot is free) and
answers; the server side awaits each call from an asyncio loop (uvloop when installed, as the
service runs). Per call: CPU of the server process (all its threads:
the pool's manager and feeder threads count), CPU of the worker, wall time. Rounds alternate
between the two hand-offs; each line is one round.

    OMP_NUM_THREADS=1 python benchmarks/worker_handoff.py --calls 1000 --rounds 3
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import time
from collections.abc import Awaitable, Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path
from typing import Any

from service.frame_work import FrameRequest
from service.images import ImageLimits
from service.shared_images import ImageSlots, read_pair
from service.worker_pipe import WorkerPipe
from service.worker_process import worker_context

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "euroc_v101_micro"


class NoFactory:
    """What ``worker_serve`` gets: nothing to warm up."""


def read_frame(request: FrameRequest) -> tuple[float, int]:
    """The worker's side: the images where they lie, and this process's CPU time so far."""
    if request.shared is None:  # pickled with the request
        return time.process_time(), len(request.left) + len(request.right)
    left, right = read_pair(request.shared)
    return time.process_time(), len(left) + len(right)


def pool_init(_factory: Any) -> None:
    return None


def a_pair() -> tuple[bytes, bytes]:
    left = sorted((DATA / "mav0" / "cam0" / "data").glob("*.png"))[0]
    right = DATA / "mav0" / "cam1" / "data" / left.name
    return left.read_bytes(), right.read_bytes()


async def measure(call: Callable[[FrameRequest], Awaitable[tuple[float, int]]],
                  request: FrameRequest, slots: ImageSlots | None,
                  calls: int) -> tuple[float, ...]:
    async def one() -> tuple[float, int]:
        if slots is None:
            return await call(request)
        pair = slots.put(request.left, request.right)
        assert pair is not None
        try:
            return await call(replace(request, left=b"", right=b"", shared=pair))
        finally:
            slots.release(pair)

    worker_start, _ = await one()
    cpu, wall = time.process_time(), time.perf_counter()
    for _ in range(calls):
        worker_end, _ = await one()
    cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
    return 1e3 * cpu / calls, 1e3 * (worker_end - worker_start) / calls, 1e3 * wall / calls


async def pool_round(request: FrameRequest, slots: ImageSlots | None,
                     calls: int) -> tuple[float, ...]:
    pool = ProcessPoolExecutor(1, mp_context=worker_context(), initializer=pool_init,
                               initargs=(NoFactory(),))
    try:
        return await measure(lambda r: asyncio.wrap_future(pool.submit(read_frame, r)),
                             request, slots, calls)
    finally:
        pool.shutdown()


async def pipe_round(request: FrameRequest, slots: ImageSlots | None,
                     calls: int) -> tuple[float, ...]:
    worker = WorkerPipe(worker_context(), NoFactory(), lambda _pipe: None)
    await worker.ready
    try:
        return await measure(lambda r: worker.call(read_frame, r), request, slots, calls)
    finally:
        await worker.stop(10.0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--calls", type=int, default=1000)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--pickled", action="store_true",
                        help="the images pickled with the request (no free slot), not in a slot")
    args = parser.parse_args()
    if args.calls < 1 or args.rounds < 1:
        parser.error("--calls and --rounds must be at least 1")
    with contextlib.suppress(ImportError):
        import uvloop

        uvloop.install()
    left, right = a_pair()
    request = FrameRequest("handoff", 0, 0, left, right, ImageLimits(4096, 4096, 1 << 24),
                           (752, 480))
    slots = ImageSlots(2, 1 << 20)
    where = "pickled with the request" if args.pickled else "in a shared slot"
    print(f"load average {os.getloadavg()[0]:.2f}; {len(left) + len(right)} bytes per pair, "
          f"{where}")
    print("| hand-off | server CPU ms/call | worker CPU ms/call | wall ms/call |")
    print("|---|---:|---:|---:|")
    try:
        for _ in range(args.rounds):
            for name, run in (("process pool", pool_round), ("worker pipe", pipe_round)):
                server, worker, wall = asyncio.run(
                    run(request, None if args.pickled else slots, args.calls))
                print(f"| {name} | {server:.3f} | {worker:.3f} | {wall:.3f} |")
    finally:
        slots.close()
    print(f"load average {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
