"""Service settings: command-line flags override ``SWARMVO_*`` environment variables."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

# Where the odometry runs. process: each session's pipeline lives in one worker process (no GIL
# contention; the pipeline factory must be picklable). thread: everything in the server process
# (for factories that cannot be sent to another process, or that are inspected in-process).
Executor = Literal["process", "thread"]
# What a session's full frame queue does with one more frame: refuse it (429), or drop the
# oldest queued one.
QueuePolicy = Literal["reject", "drop_oldest"]


# Settings whose values are never repeated in an error message (they hold passwords or keys).
SECRET_SETTINGS = frozenset({"api_keys", "database_url"})


def hash_key(key: str) -> str:
    """Stored form of an API key: sessions are owned by this digest, never by the key itself."""
    return hashlib.sha256(key.encode("utf-8")).hexdigest()


class ServiceSettings(BaseSettings):
    """Everything ``swarmvo serve`` can be told; defaults are safe for a single machine."""

    model_config = SettingsConfigDict(env_prefix="SWARMVO_", extra="forbid")

    host: str = "127.0.0.1"
    port: int = Field(8000, ge=0, le=65535)
    data_dir: Path = Path("swarmvo-data")
    # Empty: a SQLite file in data_dir. postgresql+psycopg://user:pw@host/db switches to PostgreSQL.
    database_url: str = ""
    # SQLite durability per commit. NORMAL (in WAL mode): a committed pose survives a crash of
    # the server process; FULL also survives power loss at one fsync per pose.
    sqlite_synchronous: Literal["NORMAL", "FULL"] = "NORMAL"
    # Comma-separated API keys. Kept as one string so the environment form stays simple.
    api_keys: str = ""
    open: bool = False
    # Worker processes (or threads) running decode + odometry; frames of one session never
    # overlap and always go to the same worker.
    workers: int = Field(default_factory=lambda: max(1, os.cpu_count() or 1), ge=1, le=256)
    executor: Executor = "process"
    # Process mode: a frame not answered by its worker within this time gets a 503 and the
    # worker is killed and replaced (an estimator stuck in a loop must not hold a session).
    frame_timeout_s: float = Field(60.0, gt=0, le=3600)
    # Process mode: CPU seconds one frame (decode + odometry) may use. A frame beyond it fails
    # with a 422 and only its own session restarts from its last stored pose; the other
    # sessions of the worker keep their state. 0 = no budget.
    frame_cpu_budget_s: float = Field(0.5, ge=0, le=3600)
    # Process mode: shared-memory slots that carry a frame's encoded images to its worker
    # instead of pickling them through the worker's pipe (service.shared_images), and the bytes
    # of one slot (both images). A frame finding no free slot, or larger than one, goes
    # through the pipe. 0 slots = always the pipe.
    image_slots: int = Field(16, ge=0, le=4096)
    image_slot_bytes: int = Field(1 << 20, ge=1024, le=1 << 30)
    # Connections: idle keep-alive, request headers, and the gap between two body chunks.
    timeout_keep_alive_s: int = Field(5, ge=1, le=3600)
    request_header_timeout_s: float = Field(10.0, gt=0, le=3600)
    request_body_timeout_s: float = Field(30.0, gt=0, le=3600)

    # Limits (each produces a clear 4xx answer).
    max_request_bytes: int = Field(16 * 1024 * 1024, ge=1024)
    max_image_width: int = Field(4096, ge=1)
    max_image_height: int = Field(4096, ge=1)
    max_image_pixels: int = Field(4096 * 3072, ge=1)
    max_imu_batch: int = Field(10_000, ge=1)
    max_imu_buffer: int = Field(100_000, ge=1)
    max_sessions_per_key: int = Field(100, ge=1)
    # Live odometry pipelines kept in memory; the least recently used idle one is unloaded
    # beyond this and resumes from its last stored pose when frames arrive again.
    max_active_sessions: int = Field(64, ge=1)
    # Frames waiting for CPU per session, and what happens when a producer outruns it.
    queue_size: int = Field(8, ge=1, le=10_000)
    queue_policy: QueuePolicy = "reject"
    ws_max_message_bytes: int = Field(16 * 1024 * 1024, ge=1024)
    # Seconds between returns of the server's freed heap pages to the system (service.memory;
    # 0 = never).
    memory_trim_interval_s: float = Field(10.0, ge=0, le=3600)
    # Replicas on one PostgreSQL database (service.lease): a replica owns a session while it
    # streams, for this long after its last write; another one takes over after that. Short
    # means a quick failover, long tolerates longer stalls of a replica. Unused on SQLite.
    lease_ttl_s: float = Field(0.5, gt=0, le=600)
    # False only for a server that is alone on its database (no ownership, no fencing).
    leases: bool = True
    # This replica's name in the leases; empty: host name, process id and a random suffix.
    replica_id: str = Field("", max_length=64)

    @field_validator("database_url")
    @classmethod
    def _database_url(cls, value: str) -> str:
        from service.storage.engine import check_database_url

        value = value.strip()
        if value:
            check_database_url(value)
        return value

    @property
    def key_hashes(self) -> frozenset[str]:
        return frozenset(hash_key(k.strip()) for k in self.api_keys.split(",") if k.strip())

    def resolved_database_url(self) -> str:
        if self.database_url:
            return self.database_url
        return f"sqlite:///{(self.data_dir / 'swarmvo.sqlite3').resolve()}"

    def check_startable(self) -> None:
        """Refuse to run without protection unless open mode was asked for explicitly."""
        if not self.key_hashes and not self.open:
            raise ValueError(
                "no API keys configured: set SWARMVO_API_KEYS=key1,key2 (clients send "
                "'Authorization: Bearer KEY'), or pass --open / SWARMVO_OPEN=1 for an "
                "unauthenticated local development server"
            )
