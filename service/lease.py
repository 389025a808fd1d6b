"""Session ownership across replicas: a lease in the database with a fencing token.

Replicas behind a load balancer share one PostgreSQL database; at most one of them may process
a session at any time. A replica takes a session's lease before it processes a frame: the lease
names the holder and an expiry on the database's clock, and its token rises every time the
holder changes. Every pose write carries the writer's token and is refused by the database when
the token is no longer the session's (:meth:`service.storage.Store.add_pose`), so a replica that
was paused or cut off past its lease can never write again for that session, whatever it
believes. The write also renews the lease, so a streaming session keeps its replica; a replica
that dies simply stops renewing and the next one takes over once the lease has expired.

On SQLite (one server, one file) there is nothing to share: :class:`LeaseBook` is disabled and
every write goes through unfenced, as before.
"""

from __future__ import annotations

import datetime as dt
import os
import socket
import time
import uuid
from dataclasses import dataclass

from sqlalchemy import case, func, or_, select, update

from service.storage import Fence, SessionRow, Store


class LeaseHeld(Exception):
    """Another replica holds the session's lease; ``retry_after_s`` is when it may be free."""

    def __init__(self, session_id: str, holder: str, retry_after_s: float) -> None:
        super().__init__(
            f"session {session_id} is being processed by replica {holder}; retry in "
            f"{retry_after_s:.1f} s (its lease expires unless it keeps streaming)"
        )
        self.holder = holder
        self.retry_after_s = retry_after_s


def replica_id() -> str:
    """Unique per process: a restarted replica is a new holder, never its former self."""
    return f"{socket.gethostname()[:32]}-{os.getpid()}-{uuid.uuid4().hex[:8]}"


@dataclass
class Held:
    """A lease as this replica knows it: the fence for writes, and when to check it again."""

    fence: Fence
    renew_after: float  # time.monotonic() after which the database is asked again


class LeaseBook:
    """Leases of the sessions this replica processes (no-op unless the store is PostgreSQL)."""

    def __init__(self, store: Store, holder: str, ttl_s: float, enabled: bool = True) -> None:
        self.store = store
        self.holder = holder
        self.ttl_s = ttl_s
        self.enabled = enabled and store.engine.dialect.name == "postgresql"

    def acquire(self, session_id: str) -> Fence | None:
        """Take or renew the lease (blocking I/O); None when leases are off, else LeaseHeld.

        The token stays the same while this replica keeps the lease (even past its expiry, as
        long as nobody took it meanwhile) and rises whenever the holder changes.
        """
        if not self.enabled:
            return None
        now = func.now()
        with self.store.engine.begin() as db:
            token = db.execute(
                update(SessionRow)
                .where(
                    SessionRow.id == session_id,
                    or_(
                        SessionRow.lease_holder.is_(None),
                        SessionRow.lease_holder == self.holder,
                        SessionRow.lease_expires_at <= now,
                    ),
                )
                .values(
                    lease_token=case(
                        (SessionRow.lease_holder == self.holder, SessionRow.lease_token),
                        else_=SessionRow.lease_token + 1,
                    ),
                    lease_holder=self.holder,
                    lease_expires_at=now + dt.timedelta(seconds=self.ttl_s),
                )
                .returning(SessionRow.lease_token)
            ).scalar()
            if token is not None:
                return Fence(self.holder, int(token), self.ttl_s)
            row = db.execute(
                select(
                    SessionRow.lease_holder,
                    func.extract("epoch", SessionRow.lease_expires_at - now),
                ).where(SessionRow.id == session_id)
            ).first()
        if row is None:
            raise KeyError(session_id)
        holder, remaining = row
        raise LeaseHeld(session_id, str(holder), max(float(remaining or 0.0), 0.05))

    def release(self, session_id: str, fence: Fence | None) -> None:
        """Give the lease up at once (a stream ended cleanly), so another replica need not wait."""
        if not self.enabled or fence is None:
            return
        with self.store.engine.begin() as db:
            db.execute(
                update(SessionRow)
                .where(
                    SessionRow.id == session_id,
                    SessionRow.lease_holder == fence.holder,
                    SessionRow.lease_token == fence.token,
                )
                .values(lease_holder=None, lease_expires_at=None)
            )

    def held(self, fence: Fence) -> Held:
        """Trust a fresh lease for a third of its time before asking the database again."""
        return Held(fence, time.monotonic() + self.ttl_s / 3)
