"""Connecting to the database: the driver, SQLite's pragmas, strict JSON, and the migrations
that run at every start."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from sqlalchemy import create_engine, event, func, select, text
from sqlalchemy.engine import Engine, make_url
from sqlalchemy.exc import ArgumentError, DBAPIError, NoSuchModuleError

from estimator.formats.folders import writable_folder

MIGRATIONS_DIR = Path(__file__).resolve().parents[1] / "migrations"
# PostgreSQL advisory lock id held while migrating (any constant other applications do not use).
MIGRATION_LOCK_KEY = 0x5357_564F_4D49_4752  # "SWVOMIGR"
# A replica stalled inside a transaction (paused, swapping, stopped between a pose's UPDATE and
# its COMMIT) keeps the session row locked, and another replica's lease takeover would wait on
# that lock until the stalled one resumes: its robots' frames would go unanswered meanwhile.
# PostgreSQL ends a transaction left idle this long, and its locks with it; the service's own
# transactions never wait between statements for more than milliseconds.
IDLE_IN_TRANSACTION_TIMEOUT_MS = 5000
# The databases the service runs on, and how their URLs look.
DATABASE_BACKENDS = ("sqlite", "postgresql")
URL_FORMS = "sqlite:///PATH or postgresql://USER:PASSWORD@HOST[:PORT]/DATABASE"
# How long the start-up check waits for PostgreSQL to answer (an unreachable host would
# otherwise hold the start for the system's TCP timeout).
CHECK_CONNECT_TIMEOUT_S = 10


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


def check_database_url(url: str) -> None:
    """A URL of a database the service runs on (the scheme only; nothing is connected)."""
    try:
        backend = make_url(with_driver(url)).get_backend_name()
    except ArgumentError:
        raise ValueError(f"not a database URL; expected {URL_FORMS}") from None
    if backend not in DATABASE_BACKENDS:
        raise ValueError(f"unsupported database {backend!r}; expected {URL_FORMS}")


def sqlite_folder(url: str) -> Path | None:
    """The folder of a SQLite database file; None for another database or one in memory."""
    parsed = make_url(with_driver(url))
    if parsed.get_backend_name() != "sqlite" or parsed.database in (None, "", ":memory:"):
        return None
    return Path(parsed.database).parent


def check_database(url: str) -> None:
    """Connect once and run ``SELECT 1``: a database that is away, refuses this user or lacks
    its driver is one clear line at start-up (the password hidden), not a traceback from the
    migrations. A SQLite file's folder is made, as the store makes it."""
    check_database_url(url)
    shown = make_url(with_driver(url)).render_as_string(hide_password=True)
    folder = sqlite_folder(url)
    try:
        if folder is not None:
            writable_folder(folder)
        engine = make_engine(url, connect_timeout_s=CHECK_CONNECT_TIMEOUT_S)
    except ValueError as error:
        raise ValueError(f"cannot open the database {shown}: {error}") from None
    except (ImportError, NoSuchModuleError):  # a driver named in the URL, missing or unknown
        driver = make_url(with_driver(url)).get_driver_name()
        raise ValueError(f"cannot open the database {shown}: driver {driver!r} is not "
                         "installed (plain postgresql:// uses psycopg 3)") from None
    try:
        with engine.connect() as connection:
            connection.execute(text("SELECT 1"))
    except DBAPIError as error:
        reason = str(error.orig or error).strip().splitlines()
        raise ValueError(f"cannot open the database {shown}: "
                         f"{reason[0] if reason else type(error).__name__}") from None
    finally:
        engine.dispose()


def make_engine(
    url: str, sqlite_synchronous: str = "NORMAL", connect_timeout_s: float | None = None
) -> Engine:
    """Engine for ``url``; SQLite gets WAL so readers never block the writer.
    ``connect_timeout_s``: how long a PostgreSQL connection may take to open (libpq's)."""
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
    connect: dict[str, Any] = {
        "options": f"-c idle_in_transaction_session_timeout={IDLE_IN_TRANSACTION_TIMEOUT_MS}"
    }
    if connect_timeout_s is not None:
        connect["connect_timeout"] = max(1, round(connect_timeout_s))  # libpq: whole seconds
    return create_engine(url, pool_pre_ping=True, json_serializer=_strict_json,
                         connect_args=connect)


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
