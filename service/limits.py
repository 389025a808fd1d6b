"""Upper bounds on the work one session may ask of a shared worker, checked at creation.

Sessions of different API keys share worker processes, and a frame holds its worker until it is
done: a session configured for a huge swarm or a million features would stall everybody else's
frames. Every option that scales the work of a frame therefore has an upper bound here (a 422
at creation beyond it); the per-frame CPU budget of the workers (``frame_cpu_budget_s``) is the
backstop for what the bounds cannot foresee, such as very large images.

The bounds keep the most expensive session within about 1.3x (descriptor matching) to 2x
(KLT tracking) the CPU of a default one on the EuRoC clips (752x480); docs/service.md lists
them with the measurements behind them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from estimator.registration.methods import Estimator
from service.settings import ServiceSettings


@dataclass(frozen=True)
class Bound:
    """``section.key`` of ``SwarmvoConfig`` may not exceed ``maximum``."""

    section: str
    key: str
    maximum: float


CONFIG_BOUNDS: tuple[Bound, ...] = (
    Bound("frontend", "max_features", 1600),
    Bound("frontend", "detection_oversampling", 2.5),
    Bound("frontend", "grid_rows", 16),
    Bound("frontend", "grid_cols", 16),
    # Each extra pyramid level costs about half a default frame (docs/service.md).
    Bound("frontend", "orb_levels", 1),
    Bound("frontend", "klt_window", 10),
    Bound("frontend", "klt_levels", 3),
    Bound("frontend", "subpixel_window", 6),
    Bound("frontend", "temporal_refine_window", 6),
    Bound("registration", "refine_iterations", 8),
    Bound("backend", "smoother_lag_s", 1.0),
    Bound("backend", "extra_iterations", 2),
)

# SIFT costs about 16x ORB per EuRoC frame (440 ms against 27 ms): not offered on shared workers.
# ORB on one level and fast-brief run the same compiled kernels (docs/performance.md).
ALLOWED_DETECTORS = ("orb", "fast-brief")

# registration.options of each estimator that scale its work (other options are checked by the
# estimator itself when the session is created). Every estimator of the registry has an entry
# (tests/test_limits.py checks the keys against the registry and each estimator's options).
_SWARM = {"particles": 32, "max_iterations": 60, "stagnation": 60, "refits": 12,
          "core_size": 12, "graph_pairs": 512}
OPTION_BOUNDS: dict[Estimator, dict[str, float]] = {
    Estimator.PSO: _SWARM,
    Estimator.PSO_ROBUST: _SWARM,
    Estimator.MSAC: {"max_iterations": 20000, "batch_size": 128, "refits": 5},
    Estimator.SVD: {},
}


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def work_limit_problems(config: dict[str, Any]) -> list[str]:
    """Every bound a complete (validated, dumped) ``SwarmvoConfig`` exceeds, as messages."""
    problems = []
    for bound in CONFIG_BOUNDS:
        value = config.get(bound.section, {}).get(bound.key)
        if _is_number(value) and value > bound.maximum:
            problems.append(
                f"{bound.section}.{bound.key} = {value:g} exceeds the limit of {bound.maximum:g}"
            )
    detector = config.get("frontend", {}).get("detector")
    if detector is not None and detector not in ALLOWED_DETECTORS:
        problems.append(
            f"frontend.detector {detector!r} is not offered by this service "
            f"(allowed: {', '.join(ALLOWED_DETECTORS)}): it costs about 16x the CPU of orb"
        )
    registration = config.get("registration", {})
    bounds = OPTION_BOUNDS.get(registration.get("method", ""), {})
    for key, value in registration.get("options", {}).items():
        maximum = bounds.get(key)
        if maximum is not None and _is_number(value) and value > maximum:
            problems.append(
                f"registration.options.{key} = {value:g} exceeds the limit of {maximum:g} "
                f"for method {registration['method']!r}"
            )
    return problems


def image_size_problems(size: tuple[int, int], settings: ServiceSettings) -> list[str]:
    """A calibration for images the service would refuse makes a session that cannot run."""
    width, height = size
    problems = []
    if width > settings.max_image_width or height > settings.max_image_height:
        problems.append(
            f"calibration image size {width}x{height} exceeds the maximum image size "
            f"{settings.max_image_width}x{settings.max_image_height}"
        )
    elif width * height > settings.max_image_pixels:
        problems.append(
            f"calibration image size {width}x{height} = {width * height} pixels exceeds the "
            f"limit of {settings.max_image_pixels}"
        )
    return problems
