"""swarmvo estimator: robust rigid registration and stereo visual odometry.

The registration API is loaded on first use, not with the package: importing any part of the
estimator (the CLI's parser, say) should not compile or load the kernels behind it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from estimator.registration.registry import RegistrationResult, available_methods, register

__all__ = ["RegistrationResult", "available_methods", "register"]
__version__ = "0.1.0"


def __getattr__(name: str) -> Any:
    if name in __all__:
        from estimator.registration import registry

        return getattr(registry, name)
    raise AttributeError(f"module 'estimator' has no attribute {name!r}")
