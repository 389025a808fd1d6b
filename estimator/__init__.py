"""swarmvo estimator: robust rigid registration and stereo visual odometry."""

from estimator.registration.registry import RegistrationResult, available_methods, register

__all__ = ["RegistrationResult", "available_methods", "register"]
__version__ = "0.1.0"
