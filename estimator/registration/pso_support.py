"""Rigid registration by a particle swarm over rotations with a support count.

(The estimator's steps read as one algorithm here; its parts live beside it: the compiled
kernels in ``rigidity.py`` (steps 1-2) and ``swarm_kernels.py`` (steps 3-4), the pairs, the
rotation objective and the final fit in ``support_pairs.py``, the scale ladder (step 5) in
``support_ladder.py`` and the Mahalanobis support (step 6) in ``stereo_support.py``.)

``pso`` follows the paper ("Robot Pose Estimation Based on Visual Information and Particle
Swarm Optimization"): both point sets are centred on the centroids of *all* pairs, each
particle is a rotation, its cost is eq. 13, sum_j ||r'_j - q r_j q^-1||^2, and its support
(eq. 15) is the number of pairs whose residual is below ``delta``. The best particle has the
most support, then the lowest cost; its supporters are refitted with SVD (Arun) and the
translation follows from eq. 8, t = mean(p') - R mean(p) over the supporters. With outliers
the all-pairs centroids are wrong, every residual is shifted, and the support collapses.

``pso-robust`` keeps the swarm as the rotation search and removes that weakness:

1. Rigidity graph. A rigid motion preserves distances, so two correct pairs i, j satisfy
   ||p_i - p_j|| = ||p'_i - p'_j||. Each pair of pairs gets a weight
   max(0, 1 - (difference / rigidity)^2). Correct pairs are all mutually consistent, wrong
   matches only by chance, so a few power iterations of the weight matrix (its leading
   eigenvector, "spectral matching") rank correct pairs first even at 95 % outliers. The
   O(M^2) pass costs the same at any outlier ratio; it only has to find a small core, so on
   more than ``graph_pairs`` pairs it is built on a random subset of that size (the same
   outlier ratio) and the whole call grows linearly with the pairs.
2. Core and anchor. Greedily taking top-ranked pairs that are consistent with every pair
   already taken gives a small mutually rigid core. Its centroids replace the all-pairs
   centroids (no outlier bias) and its Kabsch rotation seeds the swarm.
3. Swarm. Particles are rotation vectors (the exponential map makes every particle a valid
   unit quaternion) around the seed rotation; support and truncated cost are counted over
   *all* pairs, so a wrong core costs support and the swarm moves away from it.
4. Refit. Least squares (Horn's closed form, which yields the quaternion directly) on the
   supporters, recount the support under the full pose, refit, until the supporter set is
   stable. Without a user ``delta`` the threshold adapts to the noise: first from the
   rigidity errors inside the core, then from the supporters' residuals.
5. Scale ladder. A threshold estimated from a few pairs fits *their* noise; with
   heteroscedastic noise (stereo depth error grows with depth squared) the core may be
   the quiet pairs and the loop converges on them alone. So, after the loop, the
   threshold is doubled while that adds markedly more supporters (>= 5 % and >= 4 pairs)
   than one Gaussian scale allows (0.1 % between 4 and 8 sigma), refitting each time with
   weights 1 / max(u, delta_0)^2 from the previous residuals u (an IRLS step standing in
   for the unknown per-pair noise, so the noisy newcomers do not dilute the accuracy).
   When the core's threshold passes too few pairs to fit a pose at all (a core on one
   distant patch, whose noise along the rays its distances hardly see), the ladder
   starts from the core's own fit.
6. Stereo support and a second core. With per-point covariances the Mahalanobis test decides
   the supporters (``_mahalanobis_support``). The most connected pairs can all lie on one
   distant patch (a wall 20-40 m away on a drive): their depth error, along the rays, hardly
   changes their mutual distances, so they form the core, yet it tilts the core's rotation
   by a degree and shifts its anchor, and the search around it keeps only that patch. When
   fewer than ``SECOND_CORE_SHARE`` of the pairs support the pose, steps 2-5 run again from a
   core of the most precise well-ranked pairs (``precise_ranking``), and the pose with more
   stereo support wins. Where the isotropic refits did not settle (before the ladder), their
   own set is kept instead when it holds most of the stereo set (``keeps_isotropic_set``).

Per-pair noise. ``sigmas`` (N,) gives each pair's residual std; only their ratios matter:
residuals are divided by sigma_j / median(sigma), so ``delta`` (given or adaptive) is the
threshold of a median pair, each pair of pairs gets the rigidity tolerance
rigidity * sqrt((s_i^2 + s_j^2) / 2) of those relative scales, and the refits weigh the
pairs by 1 / sigma_j^2 (the maximum-likelihood fit for such noise).

Both score P particles against M pairs without rotating a point: for unit q the alignment
t_j . (q s_j q^-1) is the quadratic form q^T N_j q (``geometry.quat_quadratic_forms``), so
each pair is reduced once to the 10 coefficients of its symmetric N_j and a particle costs
10 multiply-adds per pair. The per-call work (a few hundred pairs, a dozen particles, a
handful of refits) is small enough that numpy's per-call overhead would dominate it, so
the hot steps are compiled kernels (numba, cached on disk).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, fields
from typing import NamedTuple

import numpy as np

from estimator.geometry import is_degenerate, kabsch, quat_to_rotation_vector
from estimator.registration.methods import Estimator, EstimatorSpec, register_method
from estimator.registration.pso import optimise
from estimator.registration.result import (
    RegistrationResult,
    check_positive,
    failed_result,
    relative_scales,
)
from estimator.registration.rigidity import (
    graph_sample,
    precise_ranking,
    rigid_core,
    rigidity_scores,
    rigidity_weights,
    top_ranked,
)
from estimator.registration.stereo_support import (
    GATE_CHI2,
    SECOND_CORE_SHARE,
    checked_covariances,
    keeps_isotropic_set,
    mahalanobis_support,
)
from estimator.registration.support_ladder import climb_ladder
from estimator.registration.support_pairs import (
    Graph,
    Pairs,
    Pose,
    RotationObjective,
    arun_fit,
    finish,
    weighted_horn,
)
from estimator.registration.swarm_kernels import MIN_SUPPORT, degenerate_rows, refit_loop

__all__ = ["PsoSupportEstimator", "weighted_horn"]


class Search(NamedTuple):
    """What steps 2-5 found from one core."""

    supporters: np.ndarray
    delta: float
    iterations: int  # swarm evaluations
    pose: Pose | None
    # The refits' last set when they did not settle (before the ladder), else None.
    unsettled: np.ndarray | None


@dataclass(frozen=True)
class PsoSupportEstimator:
    """Options of both swarm estimators (defaults tuned on ``estimator.rendered.simulation``).

    All lengths are in metres and tuned for stereo points at 2-10 m with noise up to ~5 cm.

    delta: support threshold on the residual norm; None = 0.15 for ``pso`` and adaptive
        for ``pso-robust`` (4.5 noise sigmas estimated inside the core, then 4 sigmas of
        the supporters' residuals, clipped to [delta_min, delta_max], then the ladder).
    particles, max_iterations, stagnation: the swarm; None = 48 / 100 / 15 for ``pso``
        (global search from random rotations) and 12 / 30 / 3 for ``pso-robust`` (local
        search around the seed rotation).
    inertia, acceleration: alpha and c of the velocity update (``pso.optimise``).
    rigidity: distance-difference tolerance of the rigidity graph (robust only).
    core_size: pairs in the mutually rigid core (robust only).
    spread_deg: std (degrees) of the initial particles around the seed (robust only).
    refits: maximal fit/recount rounds after the swarm (robust only).
    sigmas: (N,) per-pair residual std in metres, e.g. from stereo depth uncertainty
        (robust only; ``pso`` ignores it). Only ratios matter: see the module docstring.
    source_cov, target_cov: (N, 3, 3) covariances of the points (robust only), e.g. stereo
        points' ray-aligned covariances: support is then the Mahalanobis test
        r^T (R C_src R^T + C_tgt)^-1 r < gate_chi2 (see ``_mahalanobis_support``).
    gate_chi2: that gate; the default keeps 99.9 % of the inliers (chi-square, 3 DOF).
    graph_pairs: most pairs in the rigidity graph (robust only): larger inputs build it on a
        random subset, so the cost grows linearly with the pairs instead of quadratically.
    """

    robust: bool = True
    delta: float | None = None
    particles: int | None = None
    max_iterations: int | None = None
    stagnation: int | None = None
    inertia: float = 0.72
    acceleration: float = 1.49
    rigidity: float = 0.2
    core_size: int = 8
    spread_deg: float = 2.0
    refits: int = 8
    delta_min: float = 0.005
    delta_max: float = 0.5
    sigmas: np.ndarray | None = None
    source_cov: np.ndarray | None = None
    target_cov: np.ndarray | None = None
    gate_chi2: float = GATE_CHI2
    graph_pairs: int = 512

    def __post_init__(self) -> None:
        for name in ("delta", "particles", "stagnation"):
            value = getattr(self, name)
            if value is not None:
                check_positive(**{name: value})
        if self.max_iterations is not None and self.max_iterations < 0:
            raise ValueError(f"max_iterations must be >= 0, got {self.max_iterations}")
        check_positive(
            inertia=self.inertia + 1.0,  # inertia may be 0
            acceleration=self.acceleration,
            rigidity=self.rigidity,
            core_size=self.core_size - 2,  # needs >= 3 pairs
            spread_deg=self.spread_deg,
            refits=self.refits + 1,
            graph_pairs=self.graph_pairs - 4 * self.core_size + 1,  # room for the core search
            delta_min=self.delta_min,
        )
        if self.delta_max < self.delta_min:
            raise ValueError(f"delta_max {self.delta_max} < delta_min {self.delta_min}")
        check_positive(gate_chi2=self.gate_chi2)
        if (self.source_cov is None) != (self.target_cov is None):
            raise ValueError("source_cov and target_cov must be given together")

    @classmethod
    def from_options(cls, robust: bool, options: dict[str, object]) -> PsoSupportEstimator:
        """Build from keyword options, with a clear error for a misspelt one."""
        if not options:  # the common call: a shared (frozen) instance, validated once
            return _defaults(cls, robust)
        known = _option_names(cls)
        unknown = sorted(set(options) - known)
        if unknown:
            name = Estimator.PSO_ROBUST if robust else Estimator.PSO
            raise ValueError(f"{name}: unknown option(s) {unknown}; known: {sorted(known)}")
        return cls(robust=robust, **options)  # type: ignore[arg-type]

    def estimate(
        self, source: np.ndarray, target: np.ndarray, seed: int | None = None
    ) -> RegistrationResult:
        count = len(source)
        scales = None if self.sigmas is None else relative_scales(self.sigmas, count)
        if count < MIN_SUPPORT:
            return failed_result(count, f"need at least {MIN_SUPPORT} pairs, got {count}")
        rng = np.random.default_rng(seed)
        # Contiguous float64 once, so every compiled kernel below sees one array layout.
        source = np.ascontiguousarray(source, dtype=float)
        target = np.ascontiguousarray(target, dtype=float)
        if self.robust:
            # Degenerate data shows up as a degenerate core or supporter set (checked there).
            return self._robust(source, target, rng, scales)
        if is_degenerate(source) or is_degenerate(target):
            return failed_result(count, "points are coincident or collinear: rotation undetermined")
        return self._faithful(source, target, rng)

    # ------------------------------------------------------------------ the paper's method

    def _faithful(
        self, source: np.ndarray, target: np.ndarray, rng: np.random.Generator
    ) -> RegistrationResult:
        delta = 0.15 if self.delta is None else self.delta
        everyone = np.arange(len(source))
        objective = RotationObjective(source, target, everyone, np.eye(3), delta)
        # Uniformly random rotations: normalised Gaussian 4-vectors, as rotation vectors.
        particles = self.particles or 48
        start = quat_to_rotation_vector(rng.normal(size=(particles, 4)))
        # Random initial velocities keep the swarm from collapsing onto its first leader.
        max_speed = 0.5
        swarm = optimise(
            objective.sum_of_squares,
            start,
            rng=rng,
            max_iterations=100 if self.max_iterations is None else self.max_iterations,
            stagnation=self.stagnation or 15,
            inertia=self.inertia,
            acceleration=self.acceleration,
            max_speed=max_speed,
            initial_velocity=rng.uniform(-max_speed, max_speed, size=start.shape),
        )
        supporters = objective.supporters(swarm.position)
        return finish(source, target, supporters, delta, swarm.iterations, arun_fit)

    # ------------------------------------------------------------------ the improved method

    def _robust(
        self,
        source: np.ndarray,
        target: np.ndarray,
        rng: np.random.Generator,
        scales: np.ndarray | None,
    ) -> RegistrationResult:
        # The O(M^2) graph only has to find a small rigid core: on a random subset of at most
        # ``graph_pairs`` pairs (same outlier ratio) the cost stops growing with N.
        sample = graph_sample(len(source), self.graph_pairs, rng)
        sample_scales = None if scales is None else scales[sample]
        weights = rigidity_weights(source[sample], target[sample], self.rigidity, sample_scales)
        scores = rigidity_scores(weights)
        # Only the top of the ranking is ever looked at: select it, do not sort all pairs.
        ranking = top_ranked(scores, 4 * self.core_size)
        graph = Graph(sample, weights)
        pairs = Pairs.of(source, target, scales)
        found = self._from_core(pairs, graph, ranking, rng)
        if found is None:
            return failed_result(len(source), "no rigid, non-collinear core of pairs found")
        if self.source_cov is None or self.target_cov is None:
            supporters, delta, iterations, pose, _ = found
            return finish(source, target, supporters, delta, iterations, pairs.fit, pose)
        covariances = checked_covariances(self.source_cov, self.target_cov, len(source))
        supporters, pose = self._stereo_support(pairs, covariances, found)
        if np.count_nonzero(supporters) < SECOND_CORE_SHARE * len(source):
            # A core on one distant patch: the most connected pairs, but its depth error
            # (along the rays) tilts its rotation and shifts its anchor, and the search
            # around it keeps only that patch. Try again from the most precise pairs.
            noise = np.trace(covariances[0], axis1=1, axis2=2)[sample]
            noise = noise + np.trace(covariances[1], axis1=1, axis2=2)[sample]
            precise = precise_ranking(scores, noise, 4 * self.core_size)
            second = self._from_core(pairs, graph, precise, rng)
            if second is not None:
                other, other_pose = self._stereo_support(pairs, covariances, second)
                if np.count_nonzero(other) > np.count_nonzero(supporters):
                    found, supporters, pose = second, other, other_pose
        iterations = found.iterations
        return finish(
            source, target, supporters, math.sqrt(self.gate_chi2), iterations, pairs.fit, pose
        )

    def _from_core(
        self, pairs: Pairs, graph: Graph, ranking: np.ndarray, rng: np.random.Generator
    ) -> Search | None:
        """Core from ``ranking`` (positions in the graph), swarm, refits and ladder; None for
        a degenerate core."""
        source, target = pairs.source, pairs.target
        local_core = rigid_core(graph.weights, ranking, self.core_size)
        core = graph.sample[local_core]
        if degenerate_rows(source, target, core):
            return None
        delta = self.delta or self._delta_from_core(graph.weights[local_core[:, None], local_core])

        # Anchor on the core (not all pairs) and search rotations around its Kabsch fit.
        seed_rotation = np.ascontiguousarray(kabsch(source[core], target[core])[0])
        objective = RotationObjective(source, target, core, seed_rotation, delta, pairs.inverse)
        particles = self.particles or 12
        # Particle 0 is the seed itself; the others scatter around it.
        start = rng.normal(0.0, math.radians(self.spread_deg), size=(particles, 3))
        start[0] = 0.0
        swarm = optimise(
            objective.truncated,
            start,
            rng=rng,
            max_iterations=30 if self.max_iterations is None else self.max_iterations,
            stagnation=self.stagnation or 3,
            inertia=self.inertia,
            acceleration=self.acceleration,
            max_speed=math.radians(5.0),
        )
        supporters = objective.supporters(swarm.position)
        supporters, delta, pose = self._refine(pairs, supporters, delta)
        unsettled = supporters if pose is None else None
        if self.delta is None:
            supporters, delta, pose = climb_ladder(
                pairs, supporters, delta, pose, core, self._refine, self.delta_max
            )
        return Search(supporters, delta, swarm.iterations, pose, unsettled)

    def _stereo_support(
        self,
        pairs: Pairs,
        covariances: tuple[np.ndarray, np.ndarray],
        found: Search,
    ) -> tuple[np.ndarray, Pose | None]:
        """The isotropic search has found the rigid majority and its pose; the stereo metric
        now decides, pair by pair, who supports it. Where the isotropic refits did not settle,
        their own set is kept instead when it holds most of the stereo set
        (``keeps_isotropic_set``); it is then fitted by ``finish``."""
        supporters, pose = mahalanobis_support(
            pairs.source, pairs.target, *covariances, found.supporters, found.pose,
            self.gate_chi2, self.refits,
        )  # fmt: skip
        if found.unsettled is not None and keeps_isotropic_set(found.unsettled, supporters):
            return found.unsettled, None
        return supporters, pose

    def _refine(
        self,
        pairs: Pairs,
        supporters: np.ndarray,
        delta: float,
        adapt: bool = True,
        residual: np.ndarray | None = None,
        floor: float | None = None,
    ) -> tuple[np.ndarray, float, Pose | None]:
        """Fit the supporters, recount under the full pose, repeat until the set is stable.

        Returns the supporters, the threshold and their pose, or None when the set did not
        settle (or is too small) within ``refits`` rounds. With a ``floor`` the fits weigh
        each pair by 1 / max(u, floor)^2 of its normalised residual u at the previous pose
        (``residual`` to start): the ladder's stand-in for unknown per-pair noise. The
        compiled loop is unit-tested directly against a plain reimplementation.
        The whole loop is one compiled call (``refit_loop``).
        """
        weighted = floor is not None and residual is not None
        supporters, delta, quaternion, rotation, translation, residual, settled = refit_loop(
            pairs.source,
            pairs.target,
            supporters,
            float(delta),
            pairs.weights,
            pairs.inverse,
            residual if weighted else pairs.inverse,
            float(floor) if weighted else 0.0,
            weighted,
            adapt and self.delta is None,
            int(self.refits),
            float(self.delta_min),
            float(self.delta_max),
        )
        pose = (quaternion, rotation, translation, residual) if settled else None
        return supporters, delta, pose

    def _delta_from_core(self, core_weights: np.ndarray) -> float:
        """Noise scale from the rigidity errors inside the core (read back from the weights).

        Noise of std sigma per axis on the target points changes a distance by about
        N(0, 2 sigma^2); the residual norm of a 3-D point is ~ sigma * chi(3), whose 99.9 %
        quantile is 4.0 sigma. The anchored residuals also carry the core's own error, hence
        the extra margin (4.5).
        """
        size = len(core_weights)  # zero diagonal: off-diagonal mean of 1 - w below
        mean_deficit = (size * (size - 1) - float(core_weights.sum())) / (size * (size - 1))
        sigma = self.rigidity * math.sqrt(max(mean_deficit, 0.0) / 2.0)
        return self._clip_delta(4.5 * sigma)

    def _clip_delta(self, delta: float) -> float:
        return min(max(delta, self.delta_min), self.delta_max)


@functools.cache
def _option_names(estimator: type) -> frozenset[str]:
    return frozenset(f.name for f in fields(estimator)) - {"robust"}


@functools.cache
def _defaults(estimator: type[PsoSupportEstimator], robust: bool) -> PsoSupportEstimator:
    return estimator(robust=robust)


_TUNING_OPTIONS = _option_names(PsoSupportEstimator) - {"sigmas", "source_cov", "target_cov"}


@register_method(
    EstimatorSpec(
        Estimator.PSO,
        "the paper's swarm: all-pairs centroids, SVD refit",
        options=_TUNING_OPTIONS,
        takes_sigmas=True,
    )
)
def pso(source: np.ndarray, target: np.ndarray, *, seed: int | None = None, **options: object):
    """The paper's swarm: all-pairs centroids, eq. 13 cost, eq. 15 support, SVD refit."""
    return PsoSupportEstimator.from_options(False, options).estimate(source, target, seed)


@register_method(
    EstimatorSpec(
        Estimator.PSO_ROBUST,
        "rigidity-seeded, core-anchored swarm with an adaptive threshold",
        options=_TUNING_OPTIONS,
        takes_sigmas=True,
        takes_covariances=True,
    )
)
def pso_robust(
    source: np.ndarray, target: np.ndarray, *, seed: int | None = None, **options: object
):
    """Rigidity-seeded, core-anchored swarm with an adaptive threshold and a refit loop."""
    return PsoSupportEstimator.from_options(True, options).estimate(source, target, seed)
