"""What a back end is given, for whoever wants to keep it.

The back end alone can be run again on one front end's output with another configuration in
seconds instead of the minute the front end takes (``benchmarks/backend_replay.py``). An
observer passed to ``FusionBackend`` (or through ``Odometry`` and ``run_sequence``) sees its
construction once and then every frame as it arrives; without one nothing is formed.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from estimator.config import BackendConfig
from estimator.types import ImuNoise

__all__ = ["BackendFrame", "BackendInput", "BackendObserver", "BackendSetup"]


@dataclass(frozen=True)
class BackendSetup:
    """The back end's construction arguments, as given."""

    config: BackendConfig
    body_from_camera: np.ndarray
    imu_noise: ImuNoise | None


@dataclass(frozen=True)
class BackendFrame:
    """One ``FusionBackend.add_frame`` call: ``add_frame(timestamp_ns, **arguments)`` repeats
    it. The arguments are the caller's own objects (not copied): an observer that keeps them
    past the call copies them."""

    timestamp_ns: int
    arguments: dict[str, Any]


BackendInput = BackendSetup | BackendFrame
BackendObserver = Callable[[BackendInput], None]
