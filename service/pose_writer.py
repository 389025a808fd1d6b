"""Group commit of answered poses: the poses of all sessions waiting to be stored share one
transaction.

A transaction's fixed cost (begin, commit, the ORM's flush bookkeeping) is most of the server's
CPU per stored pose; at 8 robots x 20 Hz several poses are usually waiting at once, and storing
them together costs a third of storing them one by one (docs/performance.md). Every caller
still waits until its own pose is committed, so no client ever sees a pose that is not stored.
A batch that fails is retried pose by pose, so one bad pose fails only its own frame.
"""

from __future__ import annotations

import asyncio
from concurrent.futures import Executor

from service.storage import PendingPose, Store

__all__ = ["PoseWriter"]


class PoseWriter:
    """Stores poses in the I/O pool, batching those that arrive while a commit is running."""

    def __init__(self, store: Store, pool: Executor) -> None:
        self.store = store
        self.pool = pool
        self._pending: list[tuple[PendingPose, asyncio.Future[None]]] = []
        self._draining = False
        self._task: asyncio.Task[None] | None = None  # the running drain (kept: no lost task)

    async def add(self, pose: PendingPose) -> None:
        """Return once ``pose`` is committed; raise the storage error (or ``LeaseLost``)."""
        done: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self._pending.append((pose, done))
        if not self._draining:
            self._draining = True
            self._task = asyncio.get_running_loop().create_task(self._drain())
        await done

    async def drained(self) -> None:
        """Return once every pose handed in so far is committed or has failed: called at
        shutdown before the I/O pool stops, so that no pose waiting for a batch is lost even
        when the frame that handed it in no longer waits for it."""
        while self._task is not None and not self._task.done():
            await asyncio.wait({self._task})  # never raises, even for a cancelled drain

    async def _drain(self) -> None:
        loop = asyncio.get_running_loop()
        try:
            while self._pending:
                batch, self._pending = self._pending, []
                if len(batch) > 1:
                    poses = [pose for pose, _ in batch]
                    try:
                        await loop.run_in_executor(self.pool, self.store.add_poses, poses)
                    except Exception:
                        pass  # retried one by one below: only the bad pose fails
                    else:
                        for _, done in batch:
                            _settle(done, None)
                        continue
                for pose, done in batch:
                    try:
                        await loop.run_in_executor(self.pool, self.store.add_poses, [pose])
                    except Exception as error:
                        _settle(done, error)
                    else:
                        _settle(done, None)
        finally:
            self._draining = False


def _settle(done: asyncio.Future[None], error: Exception | None) -> None:
    if done.done():  # the waiting frame was cancelled (its session closed)
        return
    if error is None:
        done.set_result(None)
    else:
        done.set_exception(error)
