"""One live session's hold on its lease: taken or renewed before a frame, given up at the end.

Replicas on one PostgreSQL database share sessions through leases (:mod:`service.lease`); on
SQLite, or with leases off, holding one is a no-op. A new fencing token means another replica
may have written the session meanwhile, so the caller gets the stored record back to compare
its counters with.
"""

from __future__ import annotations

import asyncio
import time
from concurrent.futures import ThreadPoolExecutor

from service.lease import Held, LeaseBook, LeaseHeld
from service.sessions.frames import FrameRejected, SessionGone
from service.storage import Fence, SessionRecord, Store


class SessionLease:
    """This replica's lease on one session, when it has one."""

    def __init__(
        self, book: LeaseBook | None, session_id: str, store: Store, io_pool: ThreadPoolExecutor
    ) -> None:
        self.book = book
        self.session_id = session_id
        self.store = store
        self.io_pool = io_pool
        self.held: Held | None = None

    @property
    def fence(self) -> Fence | None:
        """The fencing token a write must carry (None without a lease)."""
        return self.held.fence if self.held is not None else None

    def drop(self) -> None:
        """Forget the lease (lost, or its database is away): the next frame takes it again."""
        self.held = None

    def renewed(self) -> None:
        """A stored write renewed the lease: its renewal time moves on."""
        if self.held is not None and self.book is not None:
            self.held = self.book.held(self.held.fence)

    async def hold(self) -> SessionRecord | None:
        """Own the session before processing: take or renew its lease (PostgreSQL only).

        Returns the stored session when the fencing token is new (another replica may have
        written meanwhile: the caller reads its counters again), else None. A lease given up
        and taken back by this replica keeps its token, and the caller its pipeline.
        """
        if self.book is None or not self.book.enabled:
            return None
        if self.held is not None and time.monotonic() < self.held.renew_after:
            return None
        try:
            fence = await self._acquire(self.book)
        except LeaseHeld as error:
            self.held = None
            raise FrameRejected(503, str(error), "lease_held", error.retry_after_s) from error
        assert fence is not None
        record = None
        if self.held is None or self.held.fence.token != fence.token:
            loop = asyncio.get_running_loop()
            record = await loop.run_in_executor(self.io_pool, self.store.get_session,
                                                self.session_id)
            if record is None:
                raise SessionGone()
        self.held = self.book.held(fence)
        return record

    async def _acquire(self, book: LeaseBook) -> Fence | None:
        """Take the lease; one that expires within a lease's time is waited for here, once.

        Its holder may be dead (a failover): refusing would cost the robot a reconnect and a
        resend before the frame is computed. A holder that keeps streaming renews it meanwhile,
        and the frame is refused after all (LeaseHeld).
        """
        loop = asyncio.get_running_loop()
        try:
            return await loop.run_in_executor(self.io_pool, book.acquire, self.session_id)
        except LeaseHeld as error:
            if error.retry_after_s > book.ttl_s:
                raise
            await asyncio.sleep(error.retry_after_s)
        return await loop.run_in_executor(self.io_pool, book.acquire, self.session_id)

    def release(self) -> None:
        """Give the lease up (blocking I/O): the session's streams have all ended."""
        held, self.held = self.held, None
        if self.book is not None and held is not None:
            self.book.release(self.session_id, held.fence)
