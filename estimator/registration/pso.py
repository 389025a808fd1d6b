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

from estimator.compiled import kernel

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

    The bookkeeping between objective calls is compiled: a swarm of a dozen particles costs
    microseconds per update, which numpy's per-call overhead would multiply several times.
    """
    flight = _Flight.start(initial, initial_velocity, max_speed, max_iterations, stagnation)
    bests = _Bests.first(flight.positions, *_score(objective, flight.positions))
    evaluations, quiet = 1, 0
    for _ in range(max_iterations):
        if quiet >= stagnation:
            break
        flight.move(bests, rng.random((2, *flight.positions.shape)), inertia, acceleration)
        support, fitness = _score(objective, flight.positions)
        evaluations += 1
        improved = bests.remember(flight.positions, support, fitness, float(tolerance))
        quiet = 0 if improved else quiet + 1
    return bests.result(evaluations)


@dataclass
class _Flight:
    """The particles' current positions (P, D), velocities and per-axis speed limit."""

    positions: np.ndarray
    velocity: np.ndarray
    speed: np.ndarray
    clamp: bool

    @classmethod
    def start(
        cls,
        initial: np.ndarray,
        initial_velocity: np.ndarray | None,
        max_speed: float | np.ndarray | None,
        max_iterations: int,
        stagnation: int,
    ) -> _Flight:
        """Checked starting positions and velocities (``optimise``'s arguments)."""
        positions = np.array(initial, dtype=float, order="C")
        if positions.ndim != 2 or len(positions) == 0:
            shape = positions.shape
            raise ValueError(f"initial must be a non-empty (P, D) array, got shape {shape}")
        if max_iterations < 0 or stagnation < 1:
            raise ValueError("max_iterations must be >= 0 and stagnation >= 1")
        velocity = np.zeros_like(positions)
        if initial_velocity is not None:
            velocity[:] = initial_velocity
        speed = np.empty(positions.shape[1])
        speed[:] = np.inf if max_speed is None else max_speed
        return cls(positions, velocity, speed, max_speed is not None)

    def move(self, bests: _Bests, phi: np.ndarray, inertia: float, acceleration: float) -> None:
        """One velocity and position update towards the personal bests and the leader's."""
        _move(
            self.positions,
            self.velocity,
            bests.positions,
            bests.leader,
            phi,
            float(inertia),
            float(acceleration),
            self.clamp,
            self.speed,
        )


@dataclass
class _Bests:
    """Each particle's best position so far, its (support, fitness), and the swarm's leader."""

    positions: np.ndarray  # (P, D)
    support: np.ndarray  # (P,) int64
    fitness: np.ndarray  # (P,)
    leader: int

    @classmethod
    def first(cls, positions: np.ndarray, support: np.ndarray, fitness: np.ndarray) -> _Bests:
        # A non-finite fitness never wins a comparison: it counts as +inf.
        finite = np.where(np.isfinite(fitness), fitness, np.inf)
        return cls(positions.copy(), support.copy(), finite, _leader(support, finite))

    def remember(
        self, positions: np.ndarray, support: np.ndarray, fitness: np.ndarray, tolerance: float
    ) -> bool:
        """Take this round's improvements; True when the leader improved (``optimise``)."""
        self.leader, gained = _remember(
            support,
            fitness,
            positions,
            self.positions,
            self.support,
            self.fitness,
            self.leader,
            tolerance,
        )
        return bool(gained)

    def result(self, evaluations: int) -> SwarmResult:
        return SwarmResult(
            self.positions[self.leader].copy(),
            int(self.support[self.leader]),
            float(self.fitness[self.leader]),
            evaluations,
        )


def _score(objective: Objective, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    # The objective gets a copy: it may keep or modify what it is given.
    support, fitness = objective(positions.copy())
    support = np.asarray(support)
    fitness = np.asarray(fitness, dtype=float)
    if support.shape != (len(positions),) or fitness.shape != (len(positions),):
        raise ValueError("the objective must return one support and one fitness per particle")
    return support.astype(np.int64, copy=False), fitness


def _leader(support: np.ndarray, fitness: np.ndarray) -> int:
    """Index of the best particle: most support, then lowest fitness (first on ties)."""
    return int(_leader_index(support, fitness))


@kernel("int64[::1], float64[::1]")
def _leader_index(support: np.ndarray, fitness: np.ndarray) -> int:
    leader = 0
    for index in range(1, len(support)):
        if support[index] > support[leader] or (
            support[index] == support[leader] and fitness[index] < fitness[leader]
        ):
            leader = index
    return leader


@kernel(
    "float64[:, ::1], float64[:, ::1], float64[:, ::1], int64, float64[:, :, ::1], float64, "
    "float64, bool, float64[::1]",
)
def _move(
    positions: np.ndarray,
    velocity: np.ndarray,
    best_positions: np.ndarray,
    leader: int,
    phi: np.ndarray,
    inertia: float,
    acceleration: float,
    clamp: bool,
    speed: np.ndarray,
) -> None:
    # In place: v <- alpha v + c phi1 (pbest - x) + c phi2 (gbest - x), clamped; x <- x + v.
    for particle in range(positions.shape[0]):
        for axis in range(positions.shape[1]):
            here = positions[particle, axis]
            step = (
                inertia * velocity[particle, axis]
                + acceleration * phi[0, particle, axis] * (best_positions[particle, axis] - here)
                + acceleration * phi[1, particle, axis] * (best_positions[leader, axis] - here)
            )
            if clamp:
                step = min(max(step, -speed[axis]), speed[axis])
            velocity[particle, axis] = step
            positions[particle, axis] = here + step


@kernel(
    "int64[::1], float64[::1], float64[:, ::1], float64[:, ::1], int64[::1], float64[::1], int64, "
    "float64",
)
def _remember(
    support: np.ndarray,
    fitness: np.ndarray,
    positions: np.ndarray,
    best_positions: np.ndarray,
    best_support: np.ndarray,
    best_fitness: np.ndarray,
    leader: int,
    tolerance: float,
) -> tuple[int, bool]:
    # Personal bests in place (``better``, a non-finite fitness as +inf), then the new
    # leader and whether it gained.
    for particle in range(len(support)):
        value = fitness[particle] if np.isfinite(fitness[particle]) else np.inf
        if support[particle] > best_support[particle] or (
            support[particle] == best_support[particle] and value < best_fitness[particle]
        ):
            best_support[particle] = support[particle]
            best_fitness[particle] = value
            for axis in range(positions.shape[1]):
                best_positions[particle, axis] = positions[particle, axis]
    new_leader = _leader_index(best_support, best_fitness)
    gained = best_support[new_leader] > best_support[leader] or (
        best_fitness[new_leader] < best_fitness[leader] - tolerance * abs(best_fitness[leader])
    )
    return new_leader, gained
