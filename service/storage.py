"""Persistence: sessions, every pose the service answered and the smoother's final poses.

The schema is owned by the Alembic migrations in ``service/migrations`` (run at start-up); the
ORM classes below mirror it. Poses are stored as JSON lists of 16 floats: Python's float repr
round-trips float64 exactly, so a trajectory read back equals the one answered, bit for bit.
On PostgreSQL the columns are ``json`` (kept as written), not ``jsonb`` (which would turn -0.0
into 0); both backends are exercised live by tests/test_service_postgres.py.
"""

from __future__ import annotations

import datetime as dt
import json
import uuid
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    DateTime,
    ForeignKey,
    Integer,
    String,
    Text,
    UniqueConstraint,
    create_engine,
    delete,
    event,
    func,
    select,
    update,
)
from sqlalchemy.engine import Engine
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, sessionmaker

from service.answer import FrameAnswer, flat_of, matrix_of

MIGRATIONS_DIR = Path(__file__).resolve().parent / "migrations"
# PostgreSQL advisory lock id held while migrating (any constant other applications do not use).
MIGRATION_LOCK_KEY = 0x5357_564F_4D49_4752  # "SWVOMIGR"


class Base(DeclarativeBase):
    pass


class SessionRow(Base):
    __tablename__ = "sessions"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    owner: Mapped[str] = mapped_column(String(64), index=True)
    name: Mapped[str] = mapped_column(String(200), default="")
    created_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))
    calibration: Mapped[dict[str, Any]] = mapped_column(JSON)
    config: Mapped[dict[str, Any]] = mapped_column(JSON)
    imu_noise: Mapped[dict[str, Any] | None] = mapped_column(JSON, nullable=True)
    image_width: Mapped[int] = mapped_column(Integer)
    image_height: Mapped[int] = mapped_column(Integer)
    frame_count: Mapped[int] = mapped_column(Integer, default=0)
    last_timestamp_ns: Mapped[int | None] = mapped_column(BigInteger, nullable=True)
    resume_count: Mapped[int] = mapped_column(Integer, default=0)
    # Ownership across replicas (service.lease): holder, expiry, and the fencing token that
    # rises at every change of holder (migration 0003).
    lease_holder: Mapped[str | None] = mapped_column(String(64), nullable=True)
    lease_expires_at: Mapped[dt.datetime | None] = mapped_column(
        DateTime(timezone=True), nullable=True
    )
    lease_token: Mapped[int] = mapped_column(BigInteger, default=0, server_default="0")
    # What the estimator needs to continue from the last stored pose (Odometry.state()).
    resume_state: Mapped[dict[str, Any] | None] = mapped_column(JSON, nullable=True)


class PoseRow(Base):
    __tablename__ = "poses"
    __table_args__ = (
        UniqueConstraint("session_id", "frame_index", name="uq_pose_frame"),
        # A resent frame gets the stored answer; a second pose for it is refused.
        UniqueConstraint("session_id", "timestamp_ns", name="uq_pose_timestamp"),
    )

    # 64-bit on PostgreSQL (migration 0002); SQLite's INTEGER PRIMARY KEY is its 64-bit rowid.
    id: Mapped[int] = mapped_column(
        BigInteger().with_variant(Integer, "sqlite"), primary_key=True, autoincrement=True
    )
    session_id: Mapped[str] = mapped_column(
        String(32), ForeignKey("sessions.id", ondelete="CASCADE"), index=True
    )
    frame_index: Mapped[int] = mapped_column(Integer)
    timestamp_ns: Mapped[int] = mapped_column(BigInteger)
    pose: Mapped[list[float]] = mapped_column(JSON)
    frontend_pose: Mapped[list[float]] = mapped_column(JSON)
    relative_pose: Mapped[list[float]] = mapped_column(JSON)
    status: Mapped[str] = mapped_column(String(16))
    matches: Mapped[int] = mapped_column(Integer, default=0)
    inliers: Mapped[int] = mapped_column(Integer, default=0)
    support: Mapped[int] = mapped_column(Integer, default=0)
    timings: Mapped[dict[str, float]] = mapped_column(JSON)
    message: Mapped[str] = mapped_column(Text, default="")
    resumed: Mapped[bool] = mapped_column(Boolean, default=False)
    # The lease token and replica the pose was written under (None without leases: SQLite).
    fence_token: Mapped[int | None] = mapped_column(BigInteger, nullable=True)
    writer: Mapped[str | None] = mapped_column(String(64), nullable=True)


class LeaseLost(Exception):
    """A pose write by a replica whose lease token is no longer the session's."""


@dataclass(frozen=True)
class Fence:
    """A writer's lease: its holder id, fencing token and how long a write renews it for."""

    holder: str
    token: int
    ttl_s: float

    def expiry(self) -> Any:
        """The new expiry on the database's clock (replicas' clocks never enter the lease)."""
        return func.now() + dt.timedelta(seconds=self.ttl_s)


class SmoothedPoseRow(Base):
    """The back end's final (smoothed) estimate of one frame, left camera in world."""

    __tablename__ = "smoothed_poses"
    __table_args__ = (
        UniqueConstraint("session_id", "timestamp_ns", name="uq_smoothed_stamp"),
    )

    id: Mapped[int] = mapped_column(
        BigInteger().with_variant(Integer, "sqlite"), primary_key=True, autoincrement=True
    )
    session_id: Mapped[str] = mapped_column(
        String(32), ForeignKey("sessions.id", ondelete="CASCADE"), index=True
    )
    timestamp_ns: Mapped[int] = mapped_column(BigInteger)
    pose: Mapped[list[float]] = mapped_column(JSON)


# A smoothed pose as answered: (timestamp_ns, row-major flat 4x4 left camera in world).
SmoothedPose = tuple[int, list[float]]


@dataclass(frozen=True)
class SessionRecord:
    id: str
    owner: str
    name: str
    created_at: dt.datetime
    calibration: dict[str, Any]
    config: dict[str, Any]
    imu_noise: dict[str, Any] | None
    image_width: int
    image_height: int
    frame_count: int
    last_timestamp_ns: int | None
    resume_count: int


@dataclass(frozen=True)
class PendingPose:
    """One answered frame waiting to be stored, with the writer's lease and resume state."""

    answer: FrameAnswer
    fence: Fence | None = None
    resume_state: dict[str, Any] | None = None
    smoothed: Sequence[SmoothedPose] = ()  # the back end's poses finalised at this frame

    @property
    def session_id(self) -> str:
        return self.answer.session_id


def _session_record(row: SessionRow) -> SessionRecord:
    created = row.created_at
    if created.tzinfo is None:  # SQLite drops the zone; everything is stored in UTC
        created = created.replace(tzinfo=dt.UTC)
    else:  # PostgreSQL answers in its session time zone: the API speaks UTC on every backend
        created = created.astimezone(dt.UTC)
    return SessionRecord(
        id=row.id,
        owner=row.owner,
        name=row.name,
        created_at=created,
        calibration=row.calibration,
        config=row.config,
        imu_noise=row.imu_noise,
        image_width=row.image_width,
        image_height=row.image_height,
        frame_count=row.frame_count,
        last_timestamp_ns=row.last_timestamp_ns,
        resume_count=row.resume_count,
    )


def _answer_of(session_id: str, row: PoseRow) -> FrameAnswer:
    """A stored row as the frame's answer (the live-only fields stay at their defaults)."""
    return FrameAnswer(
        session_id=session_id,
        index=row.frame_index,
        timestamp_ns=row.timestamp_ns,
        pose=matrix_of(row.pose),
        frontend_pose=matrix_of(row.frontend_pose),
        relative_pose=matrix_of(row.relative_pose),
        status=row.status,
        matches=row.matches,
        inliers=row.inliers,
        support=row.support,
        timings_s=row.timings,
        message=row.message,
        resumed=row.resumed,
    )


def _row_of(answer: FrameAnswer, fence: Fence | None = None) -> PoseRow:
    """What storage keeps of an answer: everything but the live-only fields, with the lease
    it was written under."""
    return PoseRow(
        session_id=answer.session_id,
        frame_index=answer.index,
        timestamp_ns=answer.timestamp_ns,
        pose=flat_of(answer.pose),
        frontend_pose=flat_of(answer.frontend_pose),
        relative_pose=flat_of(answer.relative_pose),
        status=answer.status,
        matches=answer.matches,
        inliers=answer.inliers,
        support=answer.support,
        timings=answer.timings_s,
        message=answer.message,
        resumed=answer.resumed,
        fence_token=None if fence is None else fence.token,
        writer=None if fence is None else fence.holder,
    )


def _strict_json(value: Any) -> str:
    """JSON without NaN/Infinity: PostgreSQL's json type refuses them, so SQLite must too.

    Otherwise a non-finite pose would be stored on one backend and refused on the other (and
    once stored, no JSON answer could carry it).
    """
    return json.dumps(value, allow_nan=False)


def with_driver(url: str) -> str:
    """A plain ``postgresql://`` (or ``postgres://``) URL gets the psycopg 3 driver.

    SQLAlchemy would otherwise pick psycopg2, which the ``postgres`` extra does not install.
    """
    for scheme in ("postgresql://", "postgres://"):
        if url.startswith(scheme):
            return "postgresql+psycopg://" + url.removeprefix(scheme)
    return url


def make_engine(url: str, sqlite_synchronous: str = "NORMAL") -> Engine:
    """Engine for ``url``; SQLite gets WAL so readers never block the writer."""
    if sqlite_synchronous not in ("NORMAL", "FULL"):
        raise ValueError(f"sqlite_synchronous must be NORMAL or FULL, not {sqlite_synchronous!r}")
    url = with_driver(url)
    if url.startswith("sqlite"):
        engine = create_engine(
            url,
            connect_args={"check_same_thread": False, "timeout": 30},
            json_serializer=_strict_json,
        )

        @event.listens_for(engine, "connect")
        def _sqlite_pragmas(dbapi_connection: Any, _record: Any) -> None:
            cursor = dbapi_connection.cursor()
            cursor.execute("PRAGMA journal_mode=WAL")
            cursor.execute(f"PRAGMA synchronous={sqlite_synchronous}")
            cursor.execute("PRAGMA foreign_keys=ON")
            cursor.close()

        return engine
    return create_engine(url, pool_pre_ping=True, json_serializer=_strict_json)


def run_migrations(engine: Engine) -> None:
    """Bring the schema to the newest Alembic revision (idempotent; runs at every start)."""
    from alembic import command
    from alembic.config import Config

    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS_DIR))
    with engine.begin() as connection:
        if connection.dialect.name == "postgresql":
            # Replicas starting together on an empty database would otherwise all create the
            # tables and all but one fail; the lock ends with this transaction.
            connection.execute(select(func.pg_advisory_xact_lock(MIGRATION_LOCK_KEY)))
        config.attributes["connection"] = connection
        command.upgrade(config, "head")


class Store:
    """Repository over the tables; every method is one short transaction."""

    def __init__(self, engine: Engine) -> None:
        self.engine = engine
        self._sessions = sessionmaker(engine, expire_on_commit=False)

    @classmethod
    def open(cls, url: str, sqlite_synchronous: str = "NORMAL") -> Store:
        if url.startswith("sqlite:///"):
            Path(url.removeprefix("sqlite:///")).parent.mkdir(parents=True, exist_ok=True)
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
        return _session_record(row)

    def count_sessions(self, owner: str) -> int:
        with self._sessions() as db:
            query = select(func.count()).select_from(SessionRow).where(SessionRow.owner == owner)
            return int(db.scalar(query) or 0)

    def get_session(self, session_id: str, owner: str | None = None) -> SessionRecord | None:
        with self._sessions() as db:
            row = db.get(SessionRow, session_id)
            if row is None or (owner is not None and row.owner != owner):
                return None
            return _session_record(row)

    def list_sessions(self, owner: str) -> list[SessionRecord]:
        with self._sessions() as db:
            rows = db.scalars(
                select(SessionRow).where(SessionRow.owner == owner).order_by(SessionRow.created_at)
            )
            return [_session_record(row) for row in rows]

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
        batch is written.
        """
        with self._sessions.begin() as db:
            for entry in poses:
                self._advance_counters(db, entry)
                _put_smoothed(db, entry.session_id, entry.smoothed)
                db.add(_row_of(entry.answer, entry.fence))

    @staticmethod
    def _advance_counters(db: Any, entry: PendingPose) -> None:
        answer, fence = entry.answer, entry.fence
        # The state always belongs to the last pose (None: its pipeline has none to give).
        counters: dict[str, Any] = {
            "frame_count": answer.index + 1,
            "last_timestamp_ns": answer.timestamp_ns,
            "resume_state": entry.resume_state,
        }
        if fence is None:
            session = SessionRow.id == entry.session_id
            db.execute(update(SessionRow).where(session).values(**counters))
            return
        renewed = db.execute(
            update(SessionRow)
            .where(
                SessionRow.id == entry.session_id,
                SessionRow.lease_token == fence.token,
                SessionRow.lease_holder == fence.holder,
            )
            .values(**counters, lease_expires_at=fence.expiry())
        )
        if renewed.rowcount != 1:
            raise LeaseLost(
                f"replica {fence.holder} no longer holds the lease of session "
                f"{entry.session_id} (token {fence.token}); the pose was not stored"
            )

    def pose_at(self, session_id: str, timestamp_ns: int) -> FrameAnswer | None:
        """The stored pose of the frame taken at ``timestamp_ns`` (a resent frame's answer)."""
        with self._sessions() as db:
            row = db.scalars(
                select(PoseRow).where(
                    PoseRow.session_id == session_id, PoseRow.timestamp_ns == timestamp_ns
                )
            ).first()
            return None if row is None else _answer_of(session_id, row)

    def resume_point(
        self, session_id: str
    ) -> tuple[FrameAnswer | None, dict[str, Any] | None]:
        """The last stored pose and the estimator state stored with it, read together."""
        with self._sessions() as db:
            state = db.scalar(select(SessionRow.resume_state).where(SessionRow.id == session_id))
            row = db.scalars(
                select(PoseRow)
                .where(PoseRow.session_id == session_id)
                .order_by(PoseRow.frame_index.desc())
                .limit(1)
            ).first()
            if row is None:
                return None, None
            return _answer_of(session_id, row), state

    def last_pose(self, session_id: str) -> FrameAnswer | None:
        with self._sessions() as db:
            row = db.scalars(
                select(PoseRow)
                .where(PoseRow.session_id == session_id)
                .order_by(PoseRow.frame_index.desc())
                .limit(1)
            ).first()
            return None if row is None else _answer_of(session_id, row)

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
            return [_answer_of(session_id, row) for row in rows]

    # -- smoothed poses

    def add_smoothed(self, session_id: str, smoothed: Sequence[SmoothedPose]) -> None:
        """Store final poses that came without a frame (the window flushed at a session's end)."""
        with self._sessions.begin() as db:
            _put_smoothed(db, session_id, smoothed)

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


def _put_smoothed(db: Any, session_id: str, smoothed: Sequence[SmoothedPose]) -> None:
    """Insert final poses; a frame finalised again (a resumed back end) keeps the newest."""
    if not smoothed:
        return
    stamps = [int(stamp) for stamp, _ in smoothed]
    db.execute(
        delete(SmoothedPoseRow).where(
            SmoothedPoseRow.session_id == session_id, SmoothedPoseRow.timestamp_ns.in_(stamps)
        )
    )
    db.add_all(
        SmoothedPoseRow(session_id=session_id, timestamp_ns=stamp, pose=list(pose))
        for stamp, pose in zip(stamps, (pose for _, pose in smoothed), strict=True)
    )
