"""The one typed configuration of swarmvo, with sane defaults.

Each stage owns one section; ``SwarmvoConfig`` is what the pipeline, the CLI and the service
pass around (the service accepts JSON overrides of it).
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid")


class RegistrationConfig(_Section):
    """Relative-pose estimator used by the odometry (``estimator.register``)."""

    method: Literal["pso-robust", "pso", "msac", "svd"] = "pso-robust"
    # Extra keyword options passed to the estimator (e.g. {"particles": 48}).
    options: dict[str, float | int | str | bool] = Field(default_factory=dict)


class FrontendConfig(_Section):
    """Features, stereo matching, triangulation and temporal matching."""

    detector: Literal["orb", "sift"] = "orb"
    max_features: int = Field(1200, gt=0)


class BackendConfig(_Section):
    """GTSAM fusion of relative poses with IMU rotation priors."""

    enabled: bool = True
    use_imu: bool = True


class SwarmvoConfig(_Section):
    """Everything the odometry needs besides the calibration."""

    seed: int = 0
    registration: RegistrationConfig = Field(default_factory=RegistrationConfig)
    frontend: FrontendConfig = Field(default_factory=FrontendConfig)
    backend: BackendConfig = Field(default_factory=BackendConfig)
