"""A generic, vectorised Particle Swarm Optimiser with a lexicographic (support, fitness) key.

Kennedy & Eberhart's swarm as used by the pose-estimation paper (its eqs. 4-5):

    v <- alpha v + c phi1 (pbest - x) + c phi2 (gbest - x)
    x <- x + v

with inertia ``alpha``, acceleration ``c`` and ``phi1, phi2 ~ U(0, 1)`` drawn per particle and
per dimension. One call of the objective scores *all* particles at once, so the objective
can evaluate particles x points in a single numpy expression.

"Better" is lexicographic: more support first, then lower fitness. That lets a robust
objective prefer the hypothesis explained by the most data and use the residual only to
break ties, as the paper does with its support count (eq. 15) and cost (eq. 13).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

__all__ = ["SwarmResult", "better", "optimise"]

# positions (P, D) -> (support (P,) int, fitness (P,) float)
Objective = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


@dataclass
class SwarmResult:
    """The global best of a swarm run."""

    position: np.ndarray  # (D,)
    support: int
    fitness: float
    iterations: int  # objective evaluations of the whole swarm (the initial one included)


def better(
    support: np.ndarray, fitness: np.ndarray, best_support: np.ndarray, best_fitness: np.ndarray
) -> np.ndarray:
    """Elementwise: is (support, fitness) strictly better than (best_support, best_fitness)?"""
    return (support > best_support) | ((support == best_support) & (fitness < best_fitness))


def optimise(
    objective: Objective,
    initial: np.ndarray,
    *,
    rng: np.random.Generator,
    max_iterations: int = 60,
    stagnation: int = 8,
    inertia: float = 0.72,
    acceleration: float = 1.49,
    max_speed: float | np.ndarray | None = None,
    initial_velocity: np.ndarray | None = None,
    tolerance: float = 1e-3,
) -> SwarmResult:
    """Run the swarm from the particle positions ``initial`` (P, D).

    Stops after ``max_iterations`` updates or when the global best has not improved for
    ``stagnation`` consecutive updates (a gain in support, or a relative fitness decrease of
    more than ``tolerance``, counts as an improvement). ``max_speed`` clamps each velocity
    component (keeps the swarm from exploding when ``inertia`` is large). The defaults are
    the constriction-equivalent constants (alpha 0.72, c 1.49) under which the swarm
    converges (Clerc & Kennedy 2002).
    """
    positions = np.array(initial, dtype=float)
    if positions.ndim != 2 or len(positions) == 0:
        raise ValueError(f"initial must be a non-empty (P, D) array, got shape {positions.shape}")
    if max_iterations < 0 or stagnation < 1:
        raise ValueError("max_iterations must be >= 0 and stagnation >= 1")
    velocity = np.zeros_like(positions) if initial_velocity is None else np.array(initial_velocity)
    support, fitness = _score(objective, positions)
    best_positions, best_support, best_fitness = positions.copy(), support, fitness
    leader = _leader(best_support, best_fitness)
    evaluations, quiet = 1, 0
    for _ in range(max_iterations):
        if quiet >= stagnation:
            break
        phi1, phi2 = rng.random((2, *positions.shape))
        velocity = (
            inertia * velocity
            + acceleration * phi1 * (best_positions - positions)
            + acceleration * phi2 * (best_positions[leader] - positions)
        )
        if max_speed is not None:
            velocity = np.clip(velocity, -max_speed, max_speed)
        positions = positions + velocity
        support, fitness = _score(objective, positions)
        evaluations += 1
        improved = better(support, fitness, best_support, best_fitness)
        best_positions[improved] = positions[improved]
        best_support = np.where(improved, support, best_support)
        best_fitness = np.where(improved, fitness, best_fitness)
        new_leader = _leader(best_support, best_fitness)
        gained = best_support[new_leader] > best_support[leader] or (
            best_fitness[new_leader] < best_fitness[leader] - tolerance * abs(best_fitness[leader])
        )
        quiet = 0 if gained else quiet + 1
        leader = new_leader
    return SwarmResult(
        best_positions[leader].copy(),
        int(best_support[leader]),
        float(best_fitness[leader]),
        evaluations,
    )


def _score(objective: Objective, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    support, fitness = objective(positions)
    support = np.asarray(support)
    fitness = np.asarray(fitness, dtype=float)
    if support.shape != (len(positions),) or fitness.shape != (len(positions),):
        raise ValueError("the objective must return one support and one fitness per particle")
    # A non-finite fitness never wins a comparison.
    return support, np.where(np.isfinite(fitness), fitness, np.inf)


def _leader(support: np.ndarray, fitness: np.ndarray) -> int:
    """Index of the best particle: most support, then lowest fitness (first on ties)."""
    return int(np.lexsort((fitness, -support))[0])
