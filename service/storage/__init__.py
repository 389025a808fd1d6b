"""Persistence: the tables (:mod:`.tables`), what the store hands out (:mod:`.records`), the
connection and migrations (:mod:`.engine`) and the repository (:mod:`.store`)."""

from service.storage.engine import MIGRATIONS_DIR, make_engine, run_migrations, with_driver
from service.storage.records import (
    Fence,
    LeaseLost,
    PendingPose,
    SessionRecord,
    SmoothedPose,
)
from service.storage.store import Store
from service.storage.tables import Base, PoseRow, SessionRow, SmoothedPoseRow

__all__ = [
    "MIGRATIONS_DIR",
    "Base",
    "Fence",
    "LeaseLost",
    "PendingPose",
    "PoseRow",
    "SessionRecord",
    "SessionRow",
    "SmoothedPose",
    "SmoothedPoseRow",
    "Store",
    "make_engine",
    "run_migrations",
    "with_driver",
]
