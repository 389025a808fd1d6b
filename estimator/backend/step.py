"""One frame's additions to the factor graph, gathered before the smoother update."""

from __future__ import annotations

from dataclasses import dataclass, field

import gtsam

from estimator.backend.imu import GyroPreintegration, SpecificForceDelta
from estimator.types import ImuBatch

__all__ = ["Step"]


@dataclass
class Step:
    """One frame's additions to the graph while ``FusionBackend`` builds them."""

    previous: int
    current: int
    dt: float
    stamp: float  # smoother time of the new keys
    cutoff: float  # keys stamped before it are dropped by this update
    timestamp_ns: int = 0  # the new frame's time
    factors: gtsam.NonlinearFactorGraph = field(default_factory=gtsam.NonlinearFactorGraph)
    values: gtsam.Values = field(default_factory=gtsam.Values)
    keys: list[int] = field(default_factory=list)
    keep: list[int] = field(default_factory=list)  # existing keys to restamp
    notes: list[str] = field(default_factory=list)
    preintegration: GyroPreintegration | None = None
    delta: SpecificForceDelta | None = None
    rest_samples: ImuBatch | None = None  # the interval's IMU if it continues the rest
    still: bool = False
    accepted: bool = False  # the relative pose passed the gate
    rejected: bool = False  # the relative pose failed the gate
