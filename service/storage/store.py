"""The repository over the tables: every method is one short transaction."""

from __future__ import annotations

import datetime as dt
import uuid
from collections.abc import Sequence
from typing import Any

from sqlalchemy import bindparam, delete, func, insert, select, update
from sqlalchemy.engine import Connection, Engine
from sqlalchemy.orm import Session, sessionmaker

from service.answer import FrameAnswer
from service.storage.engine import make_engine, run_migrations, sqlite_folder
from service.storage.records import (
    Fence,
    LeaseLost,
    PendingPose,
    SessionRecord,
    SmoothedPose,
    answer_of,
    row_values,
    session_record,
)
from service.storage.tables import PoseRow, SessionRow, SmoothedPoseRow

# The tables as Core sees them: the pose writes skip the ORM.
_SESSIONS = SessionRow.__table__
_POSES = PoseRow.__table__
_SMOOTHED = SmoothedPoseRow.__table__
# Built once: a statement built per call costs more CPU than running it (SQLite).
_ADVANCE = (
    update(_SESSIONS)
    .where(_SESSIONS.c.id == bindparam("session"))
    .values(frame_count=bindparam("frame_count"),
            last_timestamp_ns=bindparam("last_timestamp_ns"),
            resume_state=bindparam("resume_state", type_=_SESSIONS.c.resume_state.type))
)
_UNSMOOTH = delete(_SMOOTHED).where(
    _SMOOTHED.c.session_id == bindparam("session"),
    _SMOOTHED.c.timestamp_ns.in_(bindparam("stamps", expanding=True)),
)


class Store:
    """Repository over the tables; every method is one short transaction."""

    def __init__(self, engine: Engine) -> None:
        self.engine = engine
        self._sessions = sessionmaker(engine, expire_on_commit=False)

    @classmethod
    def open(cls, url: str, sqlite_synchronous: str = "NORMAL") -> Store:
        folder = sqlite_folder(url)
        if folder is not None:
            folder.mkdir(parents=True, exist_ok=True)
        engine = make_engine(url, sqlite_synchronous)
        run_migrations(engine)
        return cls(engine)

    def close(self) -> None:
        self.engine.dispose()

    def ping(self) -> None:
        with self._sessions() as db:
            db.execute(select(1))

    # -- sessions

    def create_session(
        self,
        owner: str,
        name: str,
        calibration: dict[str, Any],
        config: dict[str, Any],
        imu_noise: dict[str, Any] | None,
        image_size: tuple[int, int],
    ) -> SessionRecord:
        row = SessionRow(
            id=uuid.uuid4().hex,
            owner=owner,
            name=name,
            created_at=dt.datetime.now(dt.UTC),
            calibration=calibration,
            config=config,
            imu_noise=imu_noise,
            image_width=image_size[0],
            image_height=image_size[1],
            frame_count=0,
            last_timestamp_ns=None,
            resume_count=0,
        )
        with self._sessions.begin() as db:
            db.add(row)
        return session_record(row)

    def count_sessions(self, owner: str) -> int:
        with self._sessions() as db:
            query = select(func.count()).select_from(SessionRow).where(SessionRow.owner == owner)
            return int(db.scalar(query) or 0)

    def get_session(self, session_id: str, owner: str | None = None) -> SessionRecord | None:
        with self._sessions() as db:
            row = db.get(SessionRow, session_id)
            if row is None or (owner is not None and row.owner != owner):
                return None
            return session_record(row)

    def list_sessions(self, owner: str) -> list[SessionRecord]:
        with self._sessions() as db:
            rows = db.scalars(
                select(SessionRow).where(SessionRow.owner == owner).order_by(SessionRow.created_at)
            )
            return [session_record(row) for row in rows]

    def delete_session(self, session_id: str, owner: str) -> bool:
        with self._sessions.begin() as db:
            row = db.get(SessionRow, session_id)
            if row is None or row.owner != owner:
                return False
            db.execute(delete(PoseRow).where(PoseRow.session_id == session_id))
            db.execute(delete(SmoothedPoseRow).where(SmoothedPoseRow.session_id == session_id))
            db.delete(row)
        return True

    def note_resumed(self, session_id: str) -> None:
        with self._sessions.begin() as db:
            db.execute(
                update(SessionRow)
                .where(SessionRow.id == session_id)
                .values(resume_count=SessionRow.resume_count + 1)
            )

    # -- poses

    def add_pose(
        self,
        answer: FrameAnswer,
        fence: Fence | None = None,
        resume_state: dict[str, Any] | None = None,
        smoothed: Sequence[SmoothedPose] = (),
    ) -> None:
        """Store one answered frame (with the smoothed poses finalised at it) and advance the
        session counters, all in one transaction."""
        self.add_poses([PendingPose(answer, fence, resume_state, tuple(smoothed))])

    def add_poses(self, poses: list[PendingPose]) -> None:
        """Store answered poses of any sessions in one transaction (all or none).

        With a ``fence`` (the writer's lease) a pose's counters are only advanced while the
        session's lease token and holder are still the writer's, checked by the database in that
        UPDATE (which also renews the lease): otherwise :class:`LeaseLost` and nothing of the
        batch is written. Core statements on one connection, not the ORM's unit of work: its
        bookkeeping was most of the CPU a stored pose cost (docs/performance.md).
        """
        with self.engine.begin() as connection:
            for entry in poses:
                _advance_counters(connection, entry)
                _put_smoothed(connection, entry.session_id, entry.smoothed)
            connection.execute(
                insert(_POSES), [row_values(entry.answer, entry.fence) for entry in poses]
            )

    def pose_at(self, session_id: str, timestamp_ns: int) -> FrameAnswer | None:
        """The stored pose of the frame taken at ``timestamp_ns`` (a resent frame's answer)."""
        with self._sessions() as db:
            row = db.scalars(
                select(PoseRow).where(
                    PoseRow.session_id == session_id, PoseRow.timestamp_ns == timestamp_ns
                )
            ).first()
            return None if row is None else answer_of(session_id, row)

    def resume_point(
        self, session_id: str
    ) -> tuple[FrameAnswer | None, dict[str, Any] | None]:
        """The last stored pose and the estimator state stored with it, read together."""
        with self._sessions() as db:
            state = db.scalar(select(SessionRow.resume_state).where(SessionRow.id == session_id))
            row = _newest_pose_row(db, session_id)
            if row is None:
                return None, None
            return answer_of(session_id, row), state

    def last_pose(self, session_id: str) -> FrameAnswer | None:
        with self._sessions() as db:
            row = _newest_pose_row(db, session_id)
            return None if row is None else answer_of(session_id, row)

    def poses(
        self, session_id: str, start: int = 0, limit: int | None = None
    ) -> list[FrameAnswer]:
        """The session's poses from frame ``start`` on (a watcher catching up reads only new)."""
        with self._sessions() as db:
            rows = db.scalars(
                select(PoseRow)
                .where(PoseRow.session_id == session_id, PoseRow.frame_index >= start)
                .order_by(PoseRow.frame_index)
                .limit(limit)
            )
            return [answer_of(session_id, row) for row in rows]

    # -- smoothed poses

    def add_smoothed(self, session_id: str, smoothed: Sequence[SmoothedPose]) -> None:
        """Store final poses that came without a frame (the window flushed at a session's end)."""
        with self._sessions.begin() as db:
            _put_smoothed(db.connection(), session_id, smoothed)

    def smoothed(
        self, session_id: str, after_ns: int = -1, limit: int | None = None
    ) -> list[SmoothedPose]:
        """The session's smoothed poses stamped after ``after_ns``, oldest first."""
        with self._sessions() as db:
            rows = db.execute(
                select(SmoothedPoseRow.timestamp_ns, SmoothedPoseRow.pose)
                .where(
                    SmoothedPoseRow.session_id == session_id,
                    SmoothedPoseRow.timestamp_ns > after_ns,
                )
                .order_by(SmoothedPoseRow.timestamp_ns)
                .limit(limit)
            )
            return [(int(stamp), pose) for stamp, pose in rows]


def _advance_counters(connection: Connection, entry: PendingPose) -> None:
    """Move the session's counters to ``entry`` (renewing the writer's lease, if it has one)."""
    answer, fence = entry.answer, entry.fence
    # The state always belongs to the last pose (None: its pipeline has none to give).
    counters: dict[str, Any] = {
        "frame_count": answer.index + 1,
        "last_timestamp_ns": answer.timestamp_ns,
        "resume_state": entry.resume_state,
    }
    if fence is None:
        connection.execute(_ADVANCE, {"session": entry.session_id, **counters})
        return
    renewed = connection.execute(
        update(_SESSIONS)
        .where(
            _SESSIONS.c.id == entry.session_id,
            _SESSIONS.c.lease_token == fence.token,
            _SESSIONS.c.lease_holder == fence.holder,
        )
        .values(**counters, lease_expires_at=fence.expiry())
    )
    if renewed.rowcount != 1:
        raise LeaseLost(
            f"replica {fence.holder} no longer holds the lease of session "
            f"{entry.session_id} (token {fence.token}); the pose was not stored"
        )


def _put_smoothed(connection: Connection, session_id: str,
                  smoothed: Sequence[SmoothedPose]) -> None:
    """Insert final poses; a frame finalised again (a resumed back end) keeps the newest."""
    if not smoothed:
        return
    stamps = [int(stamp) for stamp, _ in smoothed]
    connection.execute(_UNSMOOTH, {"session": session_id, "stamps": stamps})
    connection.execute(insert(_SMOOTHED), [
        {"session_id": session_id, "timestamp_ns": stamp, "pose": list(pose)}
        for stamp, pose in zip(stamps, (pose for _, pose in smoothed), strict=True)
    ])


def _newest_pose_row(db: Session, session_id: str) -> PoseRow | None:
    """The session's pose with the highest frame index (its last answered frame)."""
    return db.scalars(
        select(PoseRow)
        .where(PoseRow.session_id == session_id)
        .order_by(PoseRow.frame_index.desc())
        .limit(1)
    ).first()
