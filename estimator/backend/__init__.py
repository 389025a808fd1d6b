"""GTSAM back end: fuses front-end relative poses with gyro rotation factors (docs/backend.md)."""

from estimator.backend.fusion import FusedEstimate, FusionBackend

__all__ = ["FusedEstimate", "FusionBackend"]
