"""Rigid registration by a particle swarm over rotations with a support count.

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
from collections.abc import Callable
from dataclasses import dataclass, fields

import numba
import numpy as np

from estimator.geometry import (
    is_degenerate,
    kabsch,
    matrix_to_quat,
    quat_to_rotation_vector,
)
from estimator.registration.methods import Estimator, EstimatorSpec, register_method
from estimator.registration.pso import optimise
from estimator.registration.refine import refine_pose_mahalanobis, squared_mahalanobis
from estimator.registration.result import (
    RegistrationResult,
    check_positive,
    failed_result,
    pose_result,
    relative_scales,
    residual_norms,
)

__all__ = ["PsoSupportEstimator", "rigidity_scores", "rigidity_weights"]

MIN_SUPPORT = 4
GATE_CHI2 = 16.266  # chi-square quantile 0.999 with 3 degrees of freedom
# Scale ladder: double the threshold while support grows by at least this fraction.
LADDER_GAIN = 0.05


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
        objective = _RotationObjective(source, target, everyone, np.eye(3), delta)
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
        return _finish(source, target, supporters, delta, swarm.iterations, _arun)

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
        sample = _graph_sample(len(source), self.graph_pairs, rng)
        sample_scales = None if scales is None else scales[sample]
        weights = rigidity_weights(source[sample], target[sample], self.rigidity, sample_scales)
        # Only the top of the ranking is ever looked at: select it, do not sort all pairs.
        ranking = _top_ranked(rigidity_scores(weights), 4 * self.core_size)
        local_core = _rigid_core(weights, ranking, self.core_size)
        core = sample[local_core]
        if _degenerate_rows(source, target, core):
            return failed_result(len(source), "no rigid, non-collinear core of pairs found")
        delta = self.delta or self._delta_from_core(weights[local_core[:, None], local_core])

        # Anchor on the core (not all pairs) and search rotations around its Kabsch fit.
        seed_rotation = np.ascontiguousarray(kabsch(source[core], target[core])[0])
        pairs = _Pairs.of(source, target, scales)
        objective = _RotationObjective(source, target, core, seed_rotation, delta, pairs.inverse)
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
        if self.delta is None:
            supporters, delta, pose = self._ladder(pairs, supporters, delta, pose)
        if self.source_cov is not None and self.target_cov is not None:
            # The isotropic search has found the rigid majority and its pose; the stereo
            # metric now decides, pair by pair, who supports it.
            covariances = _covariances(self.source_cov, self.target_cov, len(source))
            supporters, pose = _mahalanobis_support(
                source, target, *covariances, supporters, pose, self.gate_chi2, self.refits
            )
            delta = math.sqrt(self.gate_chi2)
        return _finish(source, target, supporters, delta, swarm.iterations, pairs.fit, pose)

    def _refine(
        self,
        pairs: _Pairs,
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
        (``residual`` to start): the ladder's stand-in for unknown per-pair noise.
        The whole loop is one compiled call (``_refit_loop``).
        """
        weighted = floor is not None and residual is not None
        supporters, delta, quaternion, rotation, translation, residual, settled = _refit_loop(
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

    def _ladder(
        self, pairs: _Pairs, supporters: np.ndarray, delta: float, pose: Pose | None
    ) -> tuple[np.ndarray, float, Pose | None]:
        """Double the adaptive threshold while that adds markedly more supporters.

        At the converged pose one Gaussian scale puts ~0.1 % of the inliers between 4 and 8
        sigma, and wrong matches rarely land that close to the model; a gain of
        ``LADDER_GAIN`` (and at least ``MIN_SUPPORT`` pairs) therefore means that the
        threshold fitted only the quietest pairs (heteroscedastic noise). (Homoscedastic
        noise along one axis, e.g. stereo rays, settles the RMS rule at ~2.1 sigma with
        ~96 % of the inliers; doubling gains ~4 %, below the bar, so it is left alone.)
        Each accepted step refits with the doubled threshold held fixed (re-estimating it
        from the RMS of mixed scales would shrink it again).
        """
        base = delta
        while True:
            wider = min(2.0 * delta, self.delta_max)
            if pose is None:  # the loop did not settle: judge the pose of its last set
                pose = pairs.pose_of(supporters)
            if pose is None or wider <= delta:
                return supporters, delta, pose
            residual = pose[3]
            support = int(np.count_nonzero(supporters))
            widened = residual < wider
            gained = int(np.count_nonzero(widened)) - support
            if gained < max(MIN_SUPPORT, LADDER_GAIN * support):
                return supporters, delta, pose
            supporters, delta, pose = self._refine(pairs, widened, wider, False, residual, base)

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


# (quaternion, rotation, translation, normalised residuals of all pairs) of a fit.
Pose = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
# A least-squares pose of the pairs in a mask, with everyone's normalised residual.
Fit = Callable[[np.ndarray, np.ndarray, np.ndarray], Pose]


@dataclass(frozen=True)
class _Pairs:
    """The pairs and their per-pair noise, as the refits use it.

    ``inverse`` = 1 / scale normalises residuals, ``weights`` = 1 / scale^2 weighs the
    least squares; both are all ones without ``sigmas``.
    """

    source: np.ndarray
    target: np.ndarray
    inverse: np.ndarray
    weights: np.ndarray

    @classmethod
    def of(cls, source: np.ndarray, target: np.ndarray, scales: np.ndarray | None) -> _Pairs:
        if scales is None:
            ones = np.ones(len(source))
            return cls(source, target, ones, ones)
        inverse = 1.0 / scales
        return cls(source, target, inverse, inverse * inverse)

    def fit(self, source: np.ndarray, target: np.ndarray, mask: np.ndarray) -> Pose:
        """Horn's least squares on the pairs in ``mask``, weighted by 1 / scale^2."""
        return _fit_pose(source, target, mask, self.weights, self.inverse)

    def pose_of(self, supporters: np.ndarray) -> Pose | None:
        """The fit of the supporters and everyone's normalised residual; None if degenerate."""
        rows = np.flatnonzero(supporters)
        if len(rows) < MIN_SUPPORT or _degenerate_points(self.source, rows):
            return None
        return self.fit(self.source, self.target, supporters)


class _RotationObjective:
    """Support and cost of rotation-vector particles against centred pairs, all at once.

    The pairs are anchored as R (p - c) and p' - c', with c, c' the centroids of the
    ``anchor`` rows, and divided by their scale (which divides the residual by it); each
    then enters as its Horn form, compressed to the 10 distinct coefficients of the
    symmetric 4x4 matrix (``_pair_forms``).
    """

    def __init__(
        self,
        source: np.ndarray,
        target: np.ndarray,
        anchor: np.ndarray,
        rotation: np.ndarray,
        delta: float,
        inverse_scales: np.ndarray | None = None,
    ) -> None:
        if inverse_scales is None:
            inverse_scales = np.ones(len(source))
        self.forms, self.norms = _pair_forms(source, target, anchor, rotation, inverse_scales)
        self.delta_squared = float(delta * delta)

    def squared_residuals(self, positions: np.ndarray) -> np.ndarray:
        """(P, M) ||t_j - q_p s_j q_p^-1||^2 via |t|^2 + |s|^2 - 2 q^T N_j q (normalised)."""
        positions = np.ascontiguousarray(positions, dtype=float)
        return _swarm_residuals(positions, self.forms, self.norms)

    def sum_of_squares(self, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The paper: support (eq. 15) and the plain sum of squared residuals (eq. 13)."""
        return _swarm_scores(positions, self.forms, self.norms, self.delta_squared, False)

    def truncated(self, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Support and the MSAC cost sum min(r^2, delta^2), which outliers cannot dominate."""
        return _swarm_scores(positions, self.forms, self.norms, self.delta_squared, True)

    def supporters(self, position: np.ndarray) -> np.ndarray:
        return self.squared_residuals(position[None, :])[0] < self.delta_squared


def weighted_horn(
    source: np.ndarray, target: np.ndarray, weights: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Horn's closed form for min sum_j w_j ||t_j - (R s_j + t)||^2 (weighted centroids).

    Returns (quaternion with w >= 0, R, t); the compiled fit every refit round uses.
    """
    source = np.ascontiguousarray(source, dtype=float)
    target = np.ascontiguousarray(target, dtype=float)
    weights = np.ascontiguousarray(weights, dtype=float)
    return _horn_fit(source, target, weights, np.ones(len(source), dtype=np.bool_))


def _arun(source: np.ndarray, target: np.ndarray, mask: np.ndarray) -> Pose:
    """The paper's final step: SVD (Arun, with the det guard), then eq. 8 for t."""
    rotation, translation = kabsch(source[mask], target[mask])
    residual = residual_norms(rotation, translation, source, target)
    return matrix_to_quat(rotation), rotation, translation, residual


def _finish(
    source: np.ndarray,
    target: np.ndarray,
    supporters: np.ndarray,
    delta: float,
    iterations: int,
    fit: Fit,
    pose: Pose | None = None,
) -> RegistrationResult:
    """Least-squares pose of the supporters: t = mean(p') - R mean(p) over them (eq. 8).

    ``pose`` is ``fit`` of the supporters when the caller has already computed it. The
    cost sum_j min(u_j^2, delta^2) is over the pose's (normalised) residuals u_j.
    """
    count = len(source)
    rows = np.flatnonzero(supporters)
    if len(rows) < MIN_SUPPORT:
        return failed_result(
            count,
            f"only {len(rows)} pair(s) support the best rotation (need {MIN_SUPPORT}); "
            f"delta={delta:.3g} m may be too small for the noise",
            iterations=iterations,
        )
    if _degenerate_rows(source, target, rows):
        return failed_result(count, "the supporting pairs are collinear", iterations=iterations)
    quaternion, rotation, translation, residual = pose or fit(source, target, supporters)
    cost = float(np.minimum(residual * residual, delta * delta).sum())
    return pose_result(
        rotation, translation, supporters, cost=cost, iterations=iterations, quaternion=quaternion
    )


def _graph_sample(count: int, limit: int, rng: np.random.Generator) -> np.ndarray:
    """All pair indices, or ``limit`` of them drawn at random (sorted) when there are more."""
    if count <= limit:
        return np.arange(count)
    return np.sort(rng.choice(count, limit, replace=False))


def _covariances(
    source_cov: object, target_cov: object, count: int
) -> tuple[np.ndarray, np.ndarray]:
    """Both (N, 3, 3) covariance arrays, checked: finite, one per pair."""
    arrays = []
    for name, value in (("source_cov", source_cov), ("target_cov", target_cov)):
        array = np.asarray(value, dtype=float)
        if array.shape != (count, 3, 3):
            raise ValueError(f"{name} must have shape ({count}, 3, 3), got {array.shape}")
        if not np.isfinite(array).all():
            raise ValueError(f"{name} must be finite")
        arrays.append(array)
    return arrays[0], arrays[1]


def _mahalanobis_support(
    source: np.ndarray,
    target: np.ndarray,
    source_cov: np.ndarray,
    target_cov: np.ndarray,
    supporters: np.ndarray,
    pose: Pose | None,
    gate: float,
    rounds: int,
) -> tuple[np.ndarray, Pose | None]:
    """Support as the Mahalanobis test of every pair, refitted by maximum likelihood.

    Stereo noise lies along the viewing ray and grows with depth squared: one isotropic
    threshold either rejects the near pairs' lateral error or accepts far wrong matches. Here a
    pair supports the pose when r^T (R C_src R^T + C_tgt)^-1 r < gate; the pose is then fitted
    to the supporters with those covariances (``refine.refine_pose_mahalanobis``), and the two
    steps repeat until the set is stable. Starts from the isotropic fit ``pose``.
    """
    if pose is None:
        return supporters, pose
    rotation, translation = pose[1], pose[2]
    squared = squared_mahalanobis(source, target, source_cov, target_cov, rotation, translation)
    for _ in range(rounds):
        chosen = squared < gate
        if np.count_nonzero(chosen) < MIN_SUPPORT:
            break
        refined = refine_pose_mahalanobis(
            source[chosen], target[chosen], source_cov[chosen], target_cov[chosen],
            rotation, translation, iterations=3, robust="cauchy",
        )  # fmt: skip
        if refined.success:
            rotation, translation = refined.rotation, refined.translation
        squared = squared_mahalanobis(source, target, source_cov, target_cov, rotation, translation)
        supporters = squared < gate
        if np.array_equal(supporters, chosen):
            break
    if np.count_nonzero(supporters) < MIN_SUPPORT:
        return supporters, None
    return supporters, (matrix_to_quat(rotation), rotation, translation, np.sqrt(squared))


def _rigid_core(weights: np.ndarray, ranking: np.ndarray, size: int) -> np.ndarray:
    """Top-ranked pairs taken greedily when rigid-consistent with all pairs taken before.

    ``ranking`` is best first (at least its first 4 * size entries). Falls back to the plain
    top of the ranking when no consistent core of 3 exists.
    """
    candidates = ranking[: 4 * size]
    taken = _greedy_core(weights, candidates, size)
    if len(taken) < 3:
        return ranking[:size]
    return candidates[taken]


def rigidity_weights(
    source: np.ndarray,
    target: np.ndarray,
    tolerance: float,
    scales: np.ndarray | None = None,
) -> np.ndarray:
    """(N, N) weights max(0, 1 - (||p_i - p_j|| - ||p'_i - p'_j||)^2 / tolerance^2), 0 diagonal.

    With per-pair noise ``scales`` s the tolerance of i, j is tolerance * sqrt((s_i^2 +
    s_j^2) / 2): the distance error has variance sigma_i^2 + sigma_j^2.
    O(N^2) time and memory, independent of the outlier ratio. Compiled, in float32 on
    centred coordinates (distance rounding ~1e-6 relative, far below any useful
    tolerance) so that the inner loop vectorises; numpy would need several (N, N)
    temporaries per step.
    """
    source = np.ascontiguousarray(source, dtype=float)
    target = np.ascontiguousarray(target, dtype=float)
    if scales is None:
        return _rigidity_kernel(source, target, float(tolerance))
    half_squares = np.ascontiguousarray(0.5 * np.asarray(scales) ** 2, dtype=np.float32)
    return _scaled_rigidity_kernel(source, target, float(tolerance), half_squares)


def rigidity_scores(weights: np.ndarray, power_steps: int = 2) -> np.ndarray:
    """Leading-eigenvector approximation of the weight matrix (spectral matching).

    The degree counts consistent partners; each power step also rewards partners that are
    themselves consistent with many, which is what separates a rigid cluster of inliers
    from chance agreements of outliers.
    """
    return _spectral_scores(np.ascontiguousarray(weights, dtype=np.float32), power_steps)


# ----------------------------------------------------------------------------- kernels
# Each call of pso-robust runs these on a few hundred pairs: compiled, a step costs
# microseconds, where the equivalent dozen small numpy calls would cost ten times more.
# They are written as scalar loops (no array expressions, matmul or linalg), which keeps
# their one-off compilation (cached on disk) short. error_model="numpy": a division is a
# plain IEEE division, not a ZeroDivisionError check, whose branch would stop the loops
# from vectorising (the scaled rigidity kernel ran 6x slower with it).


@numba.njit(cache=True, fastmath=True, nogil=True, error_model="numpy")
def _spectral_scores(weights: np.ndarray, power_steps: int) -> np.ndarray:
    # Row sums, then power steps scaled to a peak of 1, all in float32 (as the weights).
    count = weights.shape[0]
    scores = np.empty(count, dtype=np.float32)
    if count == 0:
        return scores
    for i in range(count):
        row = weights[i]
        total = np.float32(0.0)
        for j in range(count):
            total += row[j]
        scores[i] = total
    for _ in range(power_steps):
        stepped = np.empty(count, dtype=np.float32)
        for i in range(count):
            row = weights[i]
            total = np.float32(0.0)
            for j in range(count):
                total += row[j] * scores[j]
            stepped[i] = total
        peak = stepped[0]
        for i in range(1, count):
            peak = max(peak, stepped[i])
        if peak <= 0.0:
            return stepped
        for i in range(count):
            stepped[i] /= peak
        scores = stepped
    return scores


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _top_ranked(scores: np.ndarray, count: int) -> np.ndarray:
    # Indices of the ``count`` highest scores, highest first, ties by index: the head of a
    # stable descending argsort, by insertion into a short sorted list.
    size = max(min(count, len(scores)), 0)
    top = np.empty(size, dtype=np.int64)
    if size == 0:
        return top
    filled = 0
    for index in range(len(scores)):
        value = scores[index]
        if filled == size and not value > scores[top[size - 1]]:
            continue
        slot = min(filled, size - 1)  # the last slot is dropped when the list is full
        while slot > 0 and value > scores[top[slot - 1]]:
            top[slot] = top[slot - 1]
            slot -= 1
        top[slot] = index
        filled = min(filled + 1, size)
    return top


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _greedy_core(weights: np.ndarray, candidates: np.ndarray, size: int) -> np.ndarray:
    # Positions in ``candidates`` of the greedy core: each consistent (w > 0) with all before.
    taken = np.empty(max(min(size, len(candidates)), 0), dtype=np.int64)
    if len(taken) == 0:
        return taken
    taken[0] = 0
    found = 1
    for position in range(1, len(candidates)):
        if found == len(taken):
            break
        pair = candidates[position]
        consistent = True
        for earlier in range(found):
            if not weights[candidates[taken[earlier]], pair] > 0.0:
                consistent = False
                break
        if consistent:
            taken[found] = position
            found += 1
    return taken[:found]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _symmetric_eigen(matrix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    # Cyclic Jacobi for a small symmetric matrix: eigenvalues ascending, unit eigenvectors
    # as columns. For 3x3 and 4x4 it is faster than a LAPACK call and compiles in a
    # fraction of the time of numba's linalg wrappers. Accuracy ~1e-16 of the norm, as
    # LAPACK's: off-diagonal elements below 1e-18 of the norm are dropped, which also ends
    # the sweeps (quadratic convergence: a handful for 4x4).
    size = matrix.shape[0]
    a = np.empty((size, size))
    vectors = np.zeros((size, size))
    squares = 0.0
    for p in range(size):
        vectors[p, p] = 1.0
        for q in range(size):
            a[p, q] = matrix[p, q]
            squares += matrix[p, q] * matrix[p, q]
    negligible = 1e-18 * math.sqrt(squares)
    for _ in range(64):
        rotated = False
        for p in range(size - 1):
            for q in range(p + 1, size):
                apq = a[p, q]
                if abs(apq) <= negligible:
                    continue
                rotated = True
                theta = (a[q, q] - a[p, p]) / (2.0 * apq)
                if abs(theta) > 1e150:
                    tangent = 0.5 / theta
                elif theta >= 0.0:
                    tangent = 1.0 / (theta + math.sqrt(theta * theta + 1.0))
                else:
                    tangent = -1.0 / (-theta + math.sqrt(theta * theta + 1.0))
                cosine = 1.0 / math.sqrt(tangent * tangent + 1.0)
                sine = tangent * cosine
                for k in range(size):  # A <- A J (columns p, q)
                    akp, akq = a[k, p], a[k, q]
                    a[k, p] = cosine * akp - sine * akq
                    a[k, q] = sine * akp + cosine * akq
                for k in range(size):  # A <- J^T A (rows p, q)
                    apk, aqk = a[p, k], a[q, k]
                    a[p, k] = cosine * apk - sine * aqk
                    a[q, k] = sine * apk + cosine * aqk
                a[p, q] = 0.0
                a[q, p] = 0.0
                for k in range(size):  # V <- V J
                    vkp, vkq = vectors[k, p], vectors[k, q]
                    vectors[k, p] = cosine * vkp - sine * vkq
                    vectors[k, q] = sine * vkp + cosine * vkq
        if not rotated:
            break
    values = np.empty(size)
    for k in range(size):
        values[k] = a[k, k]
    for k in range(1, size):  # insertion sort, ascending, columns along
        j = k
        while j > 0 and values[j - 1] > values[j]:
            values[j - 1], values[j] = values[j], values[j - 1]
            for row in range(size):
                vectors[row, j - 1], vectors[row, j] = vectors[row, j], vectors[row, j - 1]
            j -= 1
    return values, vectors


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _degenerate_points(points: np.ndarray, rows: np.ndarray) -> bool:
    # ``geometry.is_degenerate`` of points[rows], without the copy: the same two criteria
    # on the singular values of the centred set (square roots of the scatter's eigenvalues).
    if len(rows) < 3:
        return True
    mean = np.zeros(3)
    peak = 0.0
    for row in rows:
        for axis in range(3):
            mean[axis] += points[row, axis]
            peak = max(peak, abs(points[row, axis]))
    for axis in range(3):
        mean[axis] /= len(rows)
    scatter = np.zeros((3, 3))
    for row in rows:
        for a in range(3):
            offset = points[row, a] - mean[a]
            for b in range(3):
                scatter[a, b] += offset * (points[row, b] - mean[b])
    values = _symmetric_eigen(scatter)[0]
    middle, largest = math.sqrt(max(values[1], 0.0)), math.sqrt(max(values[2], 0.0))
    return largest <= 1e-12 * max(peak, 1e-300) or middle <= 1e-6 * largest


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _degenerate_rows(source: np.ndarray, target: np.ndarray, rows: np.ndarray) -> bool:
    return _degenerate_points(source, rows) or _degenerate_points(target, rows)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _pair_forms(
    source: np.ndarray,
    target: np.ndarray,
    anchor: np.ndarray,
    rotation: np.ndarray,
    inverse_scales: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    # s_j = R (p_j - c) / scale_j, t_j = (p'_j - c') / scale_j with c, c' the centroids of
    # the anchor rows; returns the (10, M) forms
    # -2 (N00, N11, N22, N33, 2 N01, 2 N02, 2 N03, 2 N12, 2 N13, 2 N23) of Horn's matrix
    # N(s_j t_j^T) and |s_j|^2 + |t_j|^2, so that ||t_j - q s_j q^-1||^2 is
    # norms_j + forms[:, j] . (q0q0, q1q1, q2q2, q3q3, q0q1, q0q2, q0q3, q1q2, q1q3, q2q3).
    source_centre = np.zeros(3)
    target_centre = np.zeros(3)
    for row in anchor:
        for a in range(3):
            source_centre[a] += source[row, a]
            target_centre[a] += target[row, a]
    for a in range(3):
        source_centre[a] /= len(anchor)
        target_centre[a] /= len(anchor)
    count = len(source)
    forms = np.empty((10, count))
    norms = np.empty(count)
    s = np.empty(3)
    t = np.empty(3)
    for j in range(count):
        scale = inverse_scales[j]
        for a in range(3):
            s[a] = (
                rotation[a, 0] * (source[j, 0] - source_centre[0])
                + rotation[a, 1] * (source[j, 1] - source_centre[1])
                + rotation[a, 2] * (source[j, 2] - source_centre[2])
            ) * scale
            t[a] = (target[j, a] - target_centre[a]) * scale
        xx, xy, xz = s[0] * t[0], s[0] * t[1], s[0] * t[2]
        yx, yy, yz = s[1] * t[0], s[1] * t[1], s[1] * t[2]
        zx, zy, zz = s[2] * t[0], s[2] * t[1], s[2] * t[2]
        forms[0, j] = -2.0 * (xx + yy + zz)
        forms[1, j] = -2.0 * (xx - yy - zz)
        forms[2, j] = -2.0 * (yy - xx - zz)
        forms[3, j] = -2.0 * (zz - xx - yy)
        forms[4, j] = -4.0 * (yz - zy)
        forms[5, j] = -4.0 * (zx - xz)
        forms[6, j] = -4.0 * (xy - yx)
        forms[7, j] = -4.0 * (xy + yx)
        forms[8, j] = -4.0 * (zx + xz)
        forms[9, j] = -4.0 * (yz + zy)
        norms[j] = s[0] ** 2 + s[1] ** 2 + s[2] ** 2 + t[0] ** 2 + t[1] ** 2 + t[2] ** 2
    return forms, norms


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _quat_products(rotation_vector: np.ndarray, products: np.ndarray) -> None:
    # The exponential map (as geometry.rotation_vector_to_quat), then the 10 products of
    # the quaternion's components in the order of ``_pair_forms``, into ``products``.
    angle = math.sqrt(rotation_vector[0] ** 2 + rotation_vector[1] ** 2 + rotation_vector[2] ** 2)
    half = 0.5 * angle
    scale = 0.5 - angle * angle / 48.0 if angle < 1e-8 else math.sin(half) / angle
    w = math.cos(half)
    x, y, z = rotation_vector[0] * scale, rotation_vector[1] * scale, rotation_vector[2] * scale
    products[0], products[1], products[2], products[3] = w * w, x * x, y * y, z * z
    products[4], products[5], products[6] = w * x, w * y, w * z
    products[7], products[8], products[9] = x * y, x * z, y * z


@numba.njit(cache=True, fastmath=True, nogil=True, error_model="numpy")
def _swarm_residuals(positions: np.ndarray, forms: np.ndarray, norms: np.ndarray) -> np.ndarray:
    # (P, M) squared residuals of every particle against every pair.
    squared = np.empty((positions.shape[0], len(norms)))
    products = np.empty(10)
    for particle in range(positions.shape[0]):
        _quat_products(positions[particle], products)
        for j in range(len(norms)):
            value = norms[j]
            for k in range(10):
                value += forms[k, j] * products[k]
            squared[particle, j] = max(value, 0.0)
    return squared


@numba.njit(cache=True, fastmath=True, nogil=True, error_model="numpy")
def _swarm_scores(
    positions: np.ndarray, forms: np.ndarray, norms: np.ndarray, limit: float, truncate: bool
) -> tuple[np.ndarray, np.ndarray]:
    # Support (squared residual < limit) and cost (sum of squares, truncated at limit or not)
    # of every particle, without the (P, M) matrix. fastmath lets the sums vectorise
    # (reordered additions: ~1e-14 relative, deterministic for a given machine).
    support = np.zeros(positions.shape[0], dtype=np.int64)
    cost = np.zeros(positions.shape[0])
    products = np.empty(10)
    for particle in range(positions.shape[0]):
        _quat_products(positions[particle], products)
        count = 0
        total = 0.0
        for j in range(len(norms)):
            value = norms[j]
            for k in range(10):
                value += forms[k, j] * products[k]
            value = max(value, 0.0)
            if value < limit:
                count += 1
            total += min(value, limit) if truncate else value
        support[particle] = count
        cost[particle] = total
    return support, cost


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _horn_fit(
    source: np.ndarray, target: np.ndarray, weights: np.ndarray, mask: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    # Weighted Horn on the pairs in mask: centroids, correlation, top eigenvector of the
    # 4x4 Horn matrix as the quaternion (w >= 0), its rotation, t = c' - R c.
    total = 0.0
    for j in range(len(source)):
        if mask[j]:
            total += weights[j]
    source_mean = np.zeros(3)
    target_mean = np.zeros(3)
    for j in range(len(source)):
        if mask[j]:
            for a in range(3):
                source_mean[a] += weights[j] * source[j, a]
                target_mean[a] += weights[j] * target[j, a]
    for a in range(3):
        source_mean[a] /= total
        target_mean[a] /= total
    c = np.zeros((3, 3))
    for j in range(len(source)):
        if mask[j]:
            share = weights[j] / total
            for a in range(3):
                offset = share * (source[j, a] - source_mean[a])
                for b in range(3):
                    c[a, b] += offset * (target[j, b] - target_mean[b])
    horn_matrix = np.empty((4, 4))
    horn_matrix[0, 0] = c[0, 0] + c[1, 1] + c[2, 2]
    horn_matrix[1, 1] = c[0, 0] - c[1, 1] - c[2, 2]
    horn_matrix[2, 2] = c[1, 1] - c[0, 0] - c[2, 2]
    horn_matrix[3, 3] = c[2, 2] - c[0, 0] - c[1, 1]
    horn_matrix[0, 1] = horn_matrix[1, 0] = c[1, 2] - c[2, 1]
    horn_matrix[0, 2] = horn_matrix[2, 0] = c[2, 0] - c[0, 2]
    horn_matrix[0, 3] = horn_matrix[3, 0] = c[0, 1] - c[1, 0]
    horn_matrix[1, 2] = horn_matrix[2, 1] = c[0, 1] + c[1, 0]
    horn_matrix[1, 3] = horn_matrix[3, 1] = c[2, 0] + c[0, 2]
    horn_matrix[2, 3] = horn_matrix[3, 2] = c[1, 2] + c[2, 1]
    vectors = _symmetric_eigen(horn_matrix)[1]
    top = vectors[:, 3]
    length = math.sqrt(top[0] ** 2 + top[1] ** 2 + top[2] ** 2 + top[3] ** 2)
    sign = -1.0 if top[0] < 0.0 else 1.0
    quaternion = np.empty(4)
    for k in range(4):
        quaternion[k] = sign * top[k] / length
    w, x, y, z = quaternion[0], quaternion[1], quaternion[2], quaternion[3]
    rotation = np.empty((3, 3))
    rotation[0, 0], rotation[0, 1], rotation[0, 2] = (
        1 - 2 * (y * y + z * z),
        2 * (x * y - w * z),
        2 * (x * z + w * y),
    )
    rotation[1, 0], rotation[1, 1], rotation[1, 2] = (
        2 * (x * y + w * z),
        1 - 2 * (x * x + z * z),
        2 * (y * z - w * x),
    )
    rotation[2, 0], rotation[2, 1], rotation[2, 2] = (
        2 * (x * z - w * y),
        2 * (y * z + w * x),
        1 - 2 * (x * x + y * y),
    )
    translation = np.empty(3)
    for a in range(3):
        translation[a] = target_mean[a] - (
            rotation[a, 0] * source_mean[0]
            + rotation[a, 1] * source_mean[1]
            + rotation[a, 2] * source_mean[2]
        )
    return quaternion, rotation, translation


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _normalised_residuals(
    source: np.ndarray,
    target: np.ndarray,
    rotation: np.ndarray,
    translation: np.ndarray,
    inverse_scales: np.ndarray,
) -> np.ndarray:
    # ||p'_j - (R p_j + t)|| / scale_j for every pair.
    residual = np.empty(len(source))
    for j in range(len(source)):
        total = 0.0
        for a in range(3):
            difference = (
                target[j, a]
                - rotation[a, 0] * source[j, 0]
                - rotation[a, 1] * source[j, 1]
                - rotation[a, 2] * source[j, 2]
                - translation[a]
            )
            total += difference * difference
        residual[j] = math.sqrt(total) * inverse_scales[j]
    return residual


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _fit_pose(
    source: np.ndarray,
    target: np.ndarray,
    mask: np.ndarray,
    weights: np.ndarray,
    inverse_scales: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    quaternion, rotation, translation = _horn_fit(source, target, weights, mask)
    residual = _normalised_residuals(source, target, rotation, translation, inverse_scales)
    return quaternion, rotation, translation, residual


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _refit_loop(
    source: np.ndarray,
    target: np.ndarray,
    supporters: np.ndarray,
    delta: float,
    weights: np.ndarray,
    inverse_scales: np.ndarray,
    residual: np.ndarray,
    floor: float,
    weighted: bool,
    adapt: bool,
    refits: int,
    delta_min: float,
    delta_max: float,
) -> tuple[np.ndarray, float, np.ndarray, np.ndarray, np.ndarray, np.ndarray, bool]:
    # PsoSupportEstimator._refine: fit (weights, or with ``weighted`` weights /
    # max(residual, floor)^2 from the previous pose), recount, until the set repeats.
    # Adaptive delta: 4 sigma of the supporters' residuals, sigma = RMS / sqrt(3).
    quaternion, rotation, translation = np.zeros(4), np.zeros((3, 3)), np.zeros(3)
    fit_weights = weights.copy()
    for _ in range(refits):
        support = 0
        for j in range(len(supporters)):
            support += supporters[j]
        if support < MIN_SUPPORT:
            break
        if weighted:
            for j in range(len(supporters)):
                if supporters[j]:
                    fit_weights[j] = weights[j] / max(residual[j], floor) ** 2
        quaternion, rotation, translation = _horn_fit(source, target, fit_weights, supporters)
        residual = _normalised_residuals(source, target, rotation, translation, inverse_scales)
        if adapt:
            squares = 0.0
            for j in range(len(supporters)):
                if supporters[j]:
                    squares += residual[j] * residual[j]
            delta = 4.0 * math.sqrt(squares / support / 3.0)
            delta = min(max(delta, delta_min), delta_max)
        refreshed = np.empty_like(supporters)
        settled = True
        for j in range(len(supporters)):
            refreshed[j] = residual[j] < delta
            settled = settled and refreshed[j] == supporters[j]
        if settled:
            return supporters, delta, quaternion, rotation, translation, residual, True
        supporters = refreshed
    return supporters, delta, quaternion, rotation, translation, residual, False


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _centred_float32(points: np.ndarray) -> np.ndarray:
    # (3, N) float32 coordinates relative to the centroid: small numbers keep the float32
    # distances accurate, and rows of one coordinate make the kernels' inner loops SIMD.
    count = len(points)
    mean = np.zeros(3)
    for row in range(count):
        for axis in range(3):
            mean[axis] += points[row, axis]
    for axis in range(3):
        mean[axis] /= count
    centred = np.empty((3, count), dtype=np.float32)
    for row in range(count):
        for axis in range(3):
            centred[axis, row] = points[row, axis] - mean[axis]
    return centred


@numba.njit(cache=True, fastmath=True, nogil=True, error_model="numpy")
def _rigidity_kernel(source: np.ndarray, target: np.ndarray, tolerance: float) -> np.ndarray:
    # Full rows over structure-of-arrays inputs: branch-free, SIMD-friendly inner loop.
    source32, target32 = _centred_float32(source), _centred_float32(target)
    count = source32.shape[1]
    weights = np.empty((count, count), dtype=np.float32)
    scale = np.float32(1.0 / (tolerance * tolerance))
    zero, one = np.float32(0.0), np.float32(1.0)
    sx, sy, sz = source32[0], source32[1], source32[2]
    tx, ty, tz = target32[0], target32[1], target32[2]
    for i in range(count):
        row = weights[i]
        for j in range(count):
            source_sq = (sx[j] - sx[i]) ** 2 + (sy[j] - sy[i]) ** 2 + (sz[j] - sz[i]) ** 2
            target_sq = (tx[j] - tx[i]) ** 2 + (ty[j] - ty[i]) ** 2 + (tz[j] - tz[i]) ** 2
            error = np.sqrt(source_sq) - np.sqrt(target_sq)
            row[j] = max(one - error * error * scale, zero)
        row[i] = zero
    return weights


@numba.njit(cache=True, fastmath=True, nogil=True, error_model="numpy")
def _scaled_rigidity_kernel(
    source: np.ndarray, target: np.ndarray, tolerance: float, half_squares: np.ndarray
) -> np.ndarray:
    # As _rigidity_kernel, dividing by tolerance^2 (s_i^2 + s_j^2) / 2 per pair of pairs.
    source32, target32 = _centred_float32(source), _centred_float32(target)
    count = source32.shape[1]
    weights = np.empty((count, count), dtype=np.float32)
    scale = np.float32(1.0 / (tolerance * tolerance))
    zero, one = np.float32(0.0), np.float32(1.0)
    sx, sy, sz = source32[0], source32[1], source32[2]
    tx, ty, tz = target32[0], target32[1], target32[2]
    for i in range(count):
        row = weights[i]
        own = half_squares[i]
        for j in range(count):
            source_sq = (sx[j] - sx[i]) ** 2 + (sy[j] - sy[i]) ** 2 + (sz[j] - sz[i]) ** 2
            target_sq = (tx[j] - tx[i]) ** 2 + (ty[j] - ty[i]) ** 2 + (tz[j] - tz[i]) ** 2
            error = np.sqrt(source_sq) - np.sqrt(target_sq)
            row[j] = max(one - error * error * scale / (own + half_squares[j]), zero)
        row[i] = zero
    return weights


# The swarm's keyword options but the per-pair inputs (sigmas and covariances).
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
