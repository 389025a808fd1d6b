"""The service on a live PostgreSQL: a throwaway cluster (initdb + pg_ctl) in a temp directory.

- the Alembic migrations build the schema on an empty database (also when several servers
  start at once), with the column types the data needs (BIGINT nanoseconds, exact JSON floats);
- the storage layer round-trips sessions and poses exactly as SQLite does, and survives a
  restart of the database;
- a real ``swarmvo serve`` on PostgreSQL, killed mid-sequence and started again, keeps every
  session and pose and continues the session; its trajectory (JSON, TUM, KITTI) equals the one
  the same replay gives on SQLite.

Skipped with a reason when no PostgreSQL server binaries are installed; CI installs them.
"""

from __future__ import annotations

import datetime as dt
import os
import pwd
import shutil
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import numpy as np
import pytest
from swarmvo_client import Client, Pose, replay
from test_service_server import KEY, SEED, Server, process_alive

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from local_cluster import Postgres, postgres_binaries

from service.answer import FrameAnswer, flat_of, matrix_of
from service.storage import Store

psycopg = pytest.importorskip(
    "psycopg", reason="the PostgreSQL driver is missing: pip install -e '.[postgres]'"
)

USER = "swarmvo"
# A zone far from UTC: answers must still be in UTC whatever the database server's zone is.
SERVER_TIMEZONE = "Asia/Kolkata"
FIRST, MORE = 8, 6  # frames before the server is killed, frames after it comes back


class Cluster(Postgres):
    """The test's private PostgreSQL cluster, in a time zone far from UTC."""

    def __init__(self) -> None:
        super().__init__({"timezone": SERVER_TIMEZONE})


@pytest.fixture(scope="module")
def cluster() -> Iterator[Cluster]:
    binaries = postgres_binaries()
    if binaries is None:
        pytest.skip("no PostgreSQL server binaries (initdb, pg_ctl) found in "
                    "/usr/lib/postgresql/*/bin or on PATH; install the 'postgresql' package")
    if os.geteuid() == 0:
        try:
            pwd.getpwnam("postgres")
        except KeyError:
            pytest.skip("running as root, and there is no 'postgres' user to run PostgreSQL as")
        if shutil.which("runuser") is None:
            pytest.skip("running as root, and runuser (util-linux) is missing")
    running = Cluster()
    try:
        yield running
    finally:
        running.remove()
    assert running.postmaster is not None and not process_alive(running.postmaster)
    assert not running.root.exists()


@pytest.fixture
def database(cluster: Cluster, request: pytest.FixtureRequest) -> Iterator[str]:
    """A fresh, empty database for one test; dropped afterwards."""
    name = "t_" + request.node.name.lower().replace("[", "_").replace("]", "")[:50]
    cluster.admin(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')
    cluster.admin(f'CREATE DATABASE "{name}"')
    yield name
    cluster.admin(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')


def test_a_writer_stalled_inside_a_transaction_does_not_lock_its_session_for_good(
    cluster: Cluster, database: str
) -> None:
    """A replica paused between a pose's UPDATE and its COMMIT holds the session row's lock;
    another replica's takeover must not wait for it to resume (the robot's frames would go
    unanswered). PostgreSQL ends the idle transaction (service/storage/engine.py)."""
    import time

    from sqlalchemy import text
    from sqlalchemy.exc import DBAPIError

    from service.storage.engine import IDLE_IN_TRANSACTION_TIMEOUT_MS, make_engine

    stalled, other = make_engine(cluster.url(database)), make_engine(cluster.url(database))
    try:
        with other.begin() as connection:
            connection.execute(text("CREATE TABLE leases (id int PRIMARY KEY, holder text)"))
            connection.execute(text("INSERT INTO leases VALUES (1, 'a')"))
        paused = stalled.connect()
        paused.begin()
        paused.execute(text("UPDATE leases SET holder = 'a' WHERE id = 1"))  # then nothing
        start = time.monotonic()
        with other.begin() as connection:
            connection.execute(text("SET LOCAL statement_timeout = '30s'"))  # fail, not hang
            connection.execute(text("UPDATE leases SET holder = 'b' WHERE id = 1"))
        waited = time.monotonic() - start
        assert waited < IDLE_IN_TRANSACTION_TIMEOUT_MS / 1000 + 5.0, waited
        with other.connect() as connection:
            assert connection.execute(text("SELECT holder FROM leases")).scalar() == "b"
        with pytest.raises(DBAPIError, match="idle-in-transaction timeout"):
            paused.execute(text("SELECT 1"))
            paused.commit()
    finally:
        stalled.dispose()
        other.dispose()


def _calibration() -> dict:
    camera = {"width": 64, "height": 48, "fx": 50.0, "fy": 50.0, "cx": 32.0, "cy": 24.0,
              "distortion_model": "none", "distortion": [], "T_BS": np.eye(4).tolist()}
    return {"left": camera, "right": {**camera, "T_BS": [[1, 0, 0, 0.1], [0, 1, 0, 0],
                                                         [0, 0, 1, 0], [0, 0, 0, 1]]}}


# ----------------------------------------------------------------------------- schema


def test_migrations_build_the_schema_on_an_empty_database(
    cluster: Cluster, database: str
) -> None:
    from alembic.autogenerate import compare_metadata
    from alembic.config import Config
    from alembic.migration import MigrationContext
    from alembic.script import ScriptDirectory

    from service.storage import MIGRATIONS_DIR, Base

    assert cluster.query(database, "SELECT count(*) FROM pg_tables WHERE schemaname = 'public'"
                         ) == [(0,)]
    version = cluster.query(database, "SHOW server_version_num")[0][0]
    assert int(version) >= 130000  # DROP DATABASE ... WITH (FORCE) above
    store = Store.open(cluster.url(database))
    try:
        with store.engine.connect() as connection:
            assert compare_metadata(MigrationContext.configure(connection), Base.metadata) == []
    finally:
        store.close()
    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS_DIR))
    head = ScriptDirectory.from_config(config).get_current_head()
    assert cluster.query(database, "SELECT version_num FROM alembic_version") == [(head,)]
    types = dict(cluster.query(
        database, "SELECT table_name || '.' || column_name, data_type "
        "FROM information_schema.columns WHERE table_schema = 'public'"))
    assert types["poses.timestamp_ns"] == "bigint"
    assert types["sessions.last_timestamp_ns"] == "bigint"
    assert types["poses.id"] == "bigint"  # migration 0002: beyond 2^31 stored poses
    assert cluster.query(
        database, "SELECT data_type FROM information_schema.sequences "
        "WHERE sequence_name = 'poses_id_seq'") == [("bigint",)]
    assert types["sessions.created_at"] == "timestamp with time zone"
    # json keeps the text it was given (jsonb would turn -0.0 into 0 and reorder keys).
    assert {types[f"poses.{c}"] for c in ("pose", "frontend_pose", "relative_pose")} == {"json"}
    cascade = cluster.query(database, "SELECT confdeltype FROM pg_constraint WHERE contype = 'f'"
                            " AND conrelid = 'poses'::regclass")
    assert cascade == [("c",)]
    # A second start changes nothing; a plain postgresql:// URL gets the installed driver.
    plain = cluster.url(database).replace("postgresql+psycopg://", "postgresql://")
    Store.open(plain).close()
    assert cluster.query(database, "SELECT version_num FROM alembic_version") == [(head,)]


def test_servers_starting_together_on_an_empty_database_all_come_up(
    cluster: Cluster, database: str
) -> None:
    """Replicas run the migrations at the same moment; exactly one may build the schema."""
    code = ("import sys\nfrom service.storage import Store\nprint('ready', flush=True)\n"
            f"sys.stdin.readline()\nStore.open({cluster.url(database)!r}).close()\n")
    starts = [subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
              for _ in range(6)]
    for start in starts:  # all imported: the migrations then begin as close together as can be
        assert start.stdout is not None and start.stdout.readline() == "ready\n"
    for start in starts:
        assert start.stdin is not None
        start.stdin.write("go\n")
        start.stdin.flush()
    outputs = [start.communicate(timeout=60) for start in starts]
    failures = [err for start, (_out, err) in zip(starts, outputs, strict=True)
                if start.returncode != 0]
    assert failures == []
    assert cluster.query(database, "SELECT count(*) FROM alembic_version") == [(1,)]


# ----------------------------------------------------------------------------- storage


def _awkward_floats() -> list[float]:
    """Sixteen values that a lossy float path would change: extremes, -0.0, 0.1 + 0.2..."""
    rng = np.random.default_rng(7)
    special = [5e-324, 2.2250738585072014e-308, 1.7976931348623157e308, -0.0, 0.1 + 0.2,
               1 / 3, -np.pi, 1e-300]
    return special + [float(v) for v in rng.normal(size=8) * 1e3]


def _bare(session_id: str, index: int, timestamp: int, flat: list[float], status: str
          ) -> FrameAnswer:
    """An answer with only its poses and status set (the rest zero or empty)."""
    matrix = matrix_of(flat)
    return FrameAnswer(
        session_id=session_id, index=index, timestamp_ns=timestamp, pose=matrix,
        frontend_pose=matrix, relative_pose=matrix, status=status, matches=0, inliers=0,
        support=0, timings_s={}, message="", resumed=False,
    )


def _fill(store: Store) -> str:
    """The same session and poses, whichever backend ``store`` is on."""
    values = _awkward_floats()
    record = store.create_session("owner-a", "Ünïcode ✓ \"quoted\" 'name'", _calibration(),
                                  {"seed": 3, "nested": {"list": [1, 2.5, None, True]}},
                                  {"rate_hz": 200.0}, (64, 48))
    for index, timestamp in enumerate((0, 1_403_715_273_262_142_976, 2**62, 2**63 - 1)):
        pose = values[index:] + values[:index]
        store.add_pose(FrameAnswer(
            session_id=record.id, index=index, timestamp_ns=timestamp, pose=matrix_of(pose),
            frontend_pose=matrix_of(pose[::-1]), relative_pose=matrix_of(values),
            status="ok" if index % 2 else "degraded", matches=2**31 - 1, inliers=index,
            support=7, timings_s={"persist": 1.25e-4, "x": 0.1},
            message="line one\nline two ✓", resumed=index == 2,
        ))
    return record.id


def test_storage_round_trips_exactly_and_equals_sqlite(
    cluster: Cluster, database: str, tmp_path: Path
) -> None:
    on_postgres = Store.open(cluster.url(database))
    on_sqlite = Store.open(f"sqlite:///{tmp_path / 'db.sqlite3'}")
    try:
        ids = {store: _fill(store) for store in (on_postgres, on_sqlite)}
        poses = {store: store.poses(sid) for store, sid in ids.items()}
        # Model equality, every field (the session ids differ; nothing else may).
        assert [p.model_dump(exclude={"session_id"}) for p in poses[on_postgres]] == [
            p.model_dump(exclude={"session_id"}) for p in poses[on_sqlite]]
        stored = poses[on_postgres]
        assert [p.timestamp_ns for p in stored] == [0, 1_403_715_273_262_142_976, 2**62, 2**63 - 1]
        assert flat_of(stored[0].relative_pose) == _awkward_floats()
        assert [np.copysign(1, v) for v in flat_of(stored[0].pose)] == [
            np.copysign(1, v) for v in _awkward_floats()]  # -0.0 kept its sign
        sessions = {store: store.get_session(sid, "owner-a") for store, sid in ids.items()}
        pg_session, sqlite_session = sessions[on_postgres], sessions[on_sqlite]
        assert pg_session is not None and sqlite_session is not None
        assert pg_session.created_at.utcoffset() == dt.timedelta(0)
        assert pg_session.created_at.tzinfo is dt.UTC  # not the database server's zone
        assert abs(pg_session.created_at - dt.datetime.now(dt.UTC)) < dt.timedelta(minutes=5)
        for name in ("name", "calibration", "config", "imu_noise", "frame_count",
                     "last_timestamp_ns", "resume_count", "image_width", "image_height"):
            assert getattr(pg_session, name) == getattr(sqlite_session, name), name
        assert pg_session.last_timestamp_ns == 2**63 - 1 and pg_session.frame_count == 4
        assert on_postgres.get_session(ids[on_postgres], "owner-b") is None
        assert [s.id for s in on_postgres.list_sessions("owner-a")] == [ids[on_postgres]]

        # A second pose for a stored frame index is refused on both backends.
        for store, sid in ids.items():
            with pytest.raises(Exception, match=r"uq_pose_frame|UNIQUE"):
                store.add_pose(_bare(sid, 0, 5, [0.0] * 16, "ok"))
            assert len(store.poses(sid)) == 4

        # Non-finite numbers are not JSON: refused on both backends, nothing half-stored.
        for store, sid in ids.items():
            nan = [float("nan")] * 16
            with pytest.raises(Exception, match="not JSON compliant"):
                store.add_pose(_bare(sid, 4, 2**63 - 1, nan, "lost"))
            assert len(store.poses(sid)) == 4
            assert store.get_session(sid).frame_count == 4  # type: ignore[union-attr]

        # The database restarts under a running service: the next request reconnects.
        cluster.restart()
        on_postgres.note_resumed(ids[on_postgres])
        assert on_postgres.get_session(ids[on_postgres]).resume_count == 1  # type: ignore[union-attr]

        assert on_postgres.delete_session(ids[on_postgres], "owner-a")
        assert on_postgres.poses(ids[on_postgres]) == []
        assert cluster.query(database, "SELECT count(*) FROM poses") == [(0,)]
    finally:
        on_postgres.close()
        on_sqlite.close()


def test_smoothed_poses_are_stored_and_flushed_on_postgresql(
    cluster: Cluster, database: str, tmp_path: Path
) -> None:
    from test_service_smoothed import check_smoothed_flow

    check_smoothed_flow(cluster.url(database), tmp_path)
    types = dict(cluster.query(
        database, "SELECT column_name, data_type FROM information_schema.columns "
        "WHERE table_name = 'smoothed_poses'"))
    assert types["timestamp_ns"] == "bigint" and types["pose"] == "json"
    assert types["id"] == "bigint"


# ----------------------------------------------------------------------------- real server


@dataclass
class Run:
    """What one kill-and-restart replay left behind."""

    poses: list[Pose]
    session: dict
    tum: str
    kitti: str


def _same_answer(stored: list[Pose], answered: list[Pose]) -> None:
    """Stored equals answered, bit for bit (timings aside: those are measured per request)."""
    assert len(stored) == len(answered)
    for s, a in zip(stored, answered, strict=True):
        assert (s.index, s.timestamp_ns, s.status, s.matches, s.inliers, s.support,
                s.message, s.resumed) == (a.index, a.timestamp_ns, a.status, a.matches,
                                          a.inliers, a.support, a.message, a.resumed)
        for name in ("pose", "frontend_pose", "relative_pose"):
            assert getattr(s, name).tolist() == getattr(a, name).tolist(), name


def _kill_restart_continue(dataset: Path, folder: Path, *extra: str) -> Run:
    """Replay FIRST frames, SIGKILL the server, start it again, check, continue MORE frames."""
    folder.mkdir()
    data, log = folder / "data", folder / "server.log"
    first = Server(data, log, *extra)
    try:
        result = replay(first.url, dataset, KEY, limit=FIRST, config={"seed": SEED},
                        progress=False)
        with Client(first.url, KEY) as client:
            before = client.get_session(result.session.id)
    finally:
        first.kill()  # nothing gets flushed: what was answered must already be committed
    session_id = result.session.id
    assert len(result.poses) == FIRST and not result.rejected

    second = Server(data, log, *extra)
    try:
        with Client(second.url, KEY) as client:
            listed = client.list_sessions()
            assert [s.id for s in listed] == [session_id]
            assert listed[0].created_at == before.created_at
            assert listed[0].frame_count == FIRST
            stored = client.trajectory(session_id)
        assert isinstance(stored, list)
        _same_answer(stored, result.poses)

        continued = replay(second.url, dataset, KEY, use_ws=True, limit=MORE,
                           session_id=session_id, progress=False)
        assert [p.index for p in continued.poses] == list(range(FIRST, FIRST + MORE))
        assert continued.poses[0].resumed
        assert "resumed from the stored pose" in continued.poses[0].message
        assert not any(p.resumed for p in continued.poses[1:])

        with httpx.Client(base_url=second.url, headers={"Authorization": f"Bearer {KEY}"},
                          timeout=30) as http:
            session = http.get(f"/v1/sessions/{session_id}").json()
            tum = http.get(f"/v1/sessions/{session_id}/trajectory?format=tum")
            kitti = http.get(f"/v1/sessions/{session_id}/trajectory?format=kitti")
        assert tum.status_code == 200 and kitti.status_code == 200
        assert session["frame_count"] == FIRST + MORE and session["resume_count"] == 1
        with Client(second.url, KEY) as client:
            everything = client.trajectory(session_id)
        assert isinstance(everything, list)
        _same_answer(everything, result.poses + continued.poses)
        assert second.stop()
    finally:
        if second.process.poll() is None:
            second.kill()
    assert "Traceback" not in log.read_text(), log.read_text()
    return Run(everything, session, tum.text, kitti.text)


@pytest.mark.slow
@pytest.mark.euroc
def test_real_server_on_postgresql_restarts_losing_nothing_and_equals_sqlite(
    cluster: Cluster, database: str, euroc_v101_micro: Path, tmp_path: Path
) -> None:
    on_postgres = _kill_restart_continue(euroc_v101_micro, tmp_path / "postgres",
                                         "--database-url", cluster.url(database))
    # Everything went to PostgreSQL: no SQLite file appeared, and the rows are there.
    assert not (tmp_path / "postgres" / "data" / "swarmvo.sqlite3").exists()
    assert cluster.query(database, "SELECT count(*), max(frame_index) FROM poses") == [
        (FIRST + MORE, FIRST + MORE - 1)]
    assert cluster.query(database, "SELECT frame_count, resume_count FROM sessions") == [
        (FIRST + MORE, 1)]
    on_sqlite = _kill_restart_continue(euroc_v101_micro, tmp_path / "sqlite")
    assert (tmp_path / "sqlite" / "data" / "swarmvo.sqlite3").exists()

    # The created time is UTC on both backends, whatever the database server's zone.
    for run in (on_postgres, on_sqlite):
        created = dt.datetime.fromisoformat(run.session["created_at"])
        assert created.utcoffset() == dt.timedelta(0), run.session["created_at"]
    assert on_postgres.session["image_width"] == on_sqlite.session["image_width"]
    assert on_postgres.session["calibration"] == on_sqlite.session["calibration"]
    assert on_postgres.session["config"] == on_sqlite.session["config"]

    # Same replay, same seed: the same trajectory whichever database stored it.
    assert [p.timestamp_ns for p in on_postgres.poses] == [p.timestamp_ns for p in on_sqlite.poses]
    assert [p.status for p in on_postgres.poses] == [p.status for p in on_sqlite.poses]
    for name in ("pose", "frontend_pose", "relative_pose"):
        np.testing.assert_allclose(
            np.array([getattr(p, name) for p in on_postgres.poses]),
            np.array([getattr(p, name) for p in on_sqlite.poses]), rtol=0, atol=1e-12,
        )
    for export in ("tum", "kitti"):
        pg_rows = np.loadtxt(getattr(on_postgres, export).splitlines(), ndmin=2)
        sqlite_rows = np.loadtxt(getattr(on_sqlite, export).splitlines(), ndmin=2)
        assert pg_rows.shape == sqlite_rows.shape == (FIRST + MORE, 8 if export == "tum" else 12)
        np.testing.assert_allclose(pg_rows, sqlite_rows, rtol=0, atol=1e-12)
