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
   O(N^2) pass costs the same at any outlier ratio.
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

Both score P particles against M pairs with one matrix product: for unit q the alignment
t_j . (q s_j q^-1) is the quadratic form q^T N_j q (``geometry.quat_quadratic_forms``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, fields

import numba
import numpy as np

from estimator.baselines import (
    check_positive,
    failed_result,
    pose_result,
    relative_scales,
    residual_norms,
)
from estimator.geometry import (
    horn,
    is_degenerate,
    kabsch,
    matrix_to_quat,
    quat_quadratic_forms,
    quat_to_rotation_vector,
    rotation_vector_to_quat,
)
from estimator.pso import optimise
from estimator.registration import RegistrationResult, register_method

__all__ = ["PsoSupportEstimator", "rigidity_scores", "rigidity_weights"]

MIN_SUPPORT = 4
# Scale ladder: double the threshold while support grows by at least this fraction.
LADDER_GAIN = 0.05


@dataclass(frozen=True)
class PsoSupportEstimator:
    """Options of both swarm estimators (defaults tuned on ``estimator.simulation``).

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
            delta_min=self.delta_min,
        )
        if self.delta_max < self.delta_min:
            raise ValueError(f"delta_max {self.delta_max} < delta_min {self.delta_min}")

    @classmethod
    def from_options(cls, robust: bool, options: dict[str, object]) -> PsoSupportEstimator:
        """Build from keyword options, with a clear error for a misspelt one."""
        known = {f.name for f in fields(cls)} - {"robust"}
        unknown = sorted(set(options) - known)
        if unknown:
            name = "pso-robust" if robust else "pso"
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
        centred_source = source - source.mean(axis=0)
        centred_target = target - target.mean(axis=0)
        objective = _RotationObjective(centred_source, centred_target, delta)
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
        weights = rigidity_weights(source, target, self.rigidity, scales)
        ranking = np.argsort(-rigidity_scores(weights), kind="stable")
        core = _rigid_core(weights, ranking, self.core_size)
        core_source, core_target = source[core], target[core]
        if is_degenerate(core_source) or is_degenerate(core_target):
            return failed_result(len(source), "no rigid, non-collinear core of pairs found")
        delta = self.delta or self._delta_from_core(weights[np.ix_(core, core)])

        # Anchor on the core (not all pairs) and search rotations around its Kabsch fit.
        seed_rotation, _ = kabsch(core_source, core_target)
        objective = _RotationObjective(
            (source - core_source.mean(axis=0)) @ seed_rotation.T,
            target - core_target.mean(axis=0),
            delta,
            scales,
        )
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
        fit = _fitter(scales)
        supporters, delta, pose = self._refine(source, target, supporters, delta, fit, scales)
        if self.delta is None:
            supporters, delta, pose = self._ladder(
                source, target, supporters, delta, pose, fit, scales
            )
        return _finish(source, target, supporters, delta, swarm.iterations, fit, pose, scales)

    def _refine(
        self,
        source: np.ndarray,
        target: np.ndarray,
        supporters: np.ndarray,
        delta: float,
        fit: Fit,
        scales: np.ndarray | None,
        adapt: bool = True,
        residual: np.ndarray | None = None,
        floor: float | None = None,
    ) -> tuple[np.ndarray, float, Pose | None]:
        """Fit the supporters, recount under the full pose, repeat until the set is stable.

        Returns the supporters, the threshold and their pose, or None when the set did not
        settle (or is too small) within ``refits`` rounds. With a ``floor`` the fits weigh
        each pair by 1 / max(u, floor)^2 of its normalised residual u at the previous pose
        (``residual`` to start): the ladder's stand-in for unknown per-pair noise.
        """
        adapt = adapt and self.delta is None
        for _ in range(self.refits):
            if np.count_nonzero(supporters) < MIN_SUPPORT:
                break
            if floor is None or residual is None:
                pose = fit(source, target, supporters)
            else:
                weights = 1.0 / np.maximum(residual[supporters], floor) ** 2
                if scales is not None:
                    weights = weights / scales[supporters] ** 2
                pose = weighted_horn(source[supporters], target[supporters], weights)
            residual = _normalised(residual_norms(pose[1], pose[2], source, target), scales)
            if adapt:
                delta = self._delta_from_residuals(residual[supporters])
            refreshed = residual < delta
            if np.array_equal(refreshed, supporters):
                return supporters, delta, (*pose, residual)
            supporters = refreshed
        return supporters, delta, None

    def _ladder(
        self,
        source: np.ndarray,
        target: np.ndarray,
        supporters: np.ndarray,
        delta: float,
        pose: Pose | None,
        fit: Fit,
        scales: np.ndarray | None,
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
                pose = _pose_of(source, target, supporters, fit, scales)
            if pose is None or wider <= delta:
                return supporters, delta, pose
            residual = pose[3]
            support = int(np.count_nonzero(supporters))
            gained = int(np.count_nonzero(residual < wider)) - support
            if gained < max(MIN_SUPPORT, LADDER_GAIN * support):
                return supporters, delta, pose
            supporters, delta, pose = self._refine(
                source, target, residual < wider, wider, fit, scales, False, residual, base
            )

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

    def _delta_from_residuals(self, residual: np.ndarray) -> float:
        sigma = math.sqrt(float(np.mean(residual**2)) / 3.0)
        return self._clip_delta(4.0 * sigma)

    def _clip_delta(self, delta: float) -> float:
        return min(max(delta, self.delta_min), self.delta_max)


class _RotationObjective:
    """Support and cost of rotation-vector particles against centred pairs, all at once."""

    def __init__(
        self,
        source: np.ndarray,
        target: np.ndarray,
        delta: float,
        scales: np.ndarray | None = None,
    ) -> None:
        # Dividing both points of pair j by its scale divides its residual by the scale.
        if scales is not None:
            source, target = source / scales[:, None], target / scales[:, None]
        self.forms = quat_quadratic_forms(source, target).reshape(len(source), 16).T
        self.norms = np.einsum("ij,ij->i", source, source) + np.einsum("ij,ij->i", target, target)
        self.delta_squared = delta * delta

    def squared_residuals(self, positions: np.ndarray) -> np.ndarray:
        """(P, M) ||t_j - q_p s_j q_p^-1||^2 via |t|^2 + |s|^2 - 2 q^T N_j q (normalised)."""
        quats = rotation_vector_to_quat(positions)
        outer = (quats[:, :, None] * quats[:, None, :]).reshape(len(quats), 16)
        return np.maximum(self.norms - 2.0 * (outer @ self.forms), 0.0)

    def sum_of_squares(self, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The paper: support (eq. 15) and the plain sum of squared residuals (eq. 13)."""
        squared = self.squared_residuals(positions)
        return np.count_nonzero(squared < self.delta_squared, axis=1), squared.sum(axis=1)

    def truncated(self, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Support and the MSAC cost sum min(r^2, delta^2), which outliers cannot dominate."""
        squared = self.squared_residuals(positions)
        support = np.count_nonzero(squared < self.delta_squared, axis=1)
        return support, np.minimum(squared, self.delta_squared).sum(axis=1)

    def supporters(self, position: np.ndarray) -> np.ndarray:
        return self.squared_residuals(position[None, :])[0] < self.delta_squared


# A least-squares pose (quaternion, rotation, translation) of the pairs in a mask.
Fit = Callable[[np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]
# (quaternion, rotation, translation, normalised residuals of all pairs) of a fit.
Pose = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def _pose_of(
    source: np.ndarray,
    target: np.ndarray,
    supporters: np.ndarray,
    fit: Fit,
    scales: np.ndarray | None,
) -> Pose | None:
    """The fit of the supporters and everyone's normalised residual; None if degenerate."""
    if np.count_nonzero(supporters) < MIN_SUPPORT or is_degenerate(source[supporters]):
        return None
    pose = fit(source, target, supporters)
    return (*pose, _normalised(residual_norms(pose[1], pose[2], source, target), scales))


def _normalised(residual: np.ndarray, scales: np.ndarray | None) -> np.ndarray:
    return residual if scales is None else residual / scales


def _fitter(scales: np.ndarray | None) -> Fit:
    """Horn's least squares, weighted by 1 / scale^2 when per-pair scales are known."""
    if scales is None:
        return lambda source, target, mask: horn(source[mask], target[mask])
    weights = 1.0 / scales**2
    return lambda source, target, mask: weighted_horn(source[mask], target[mask], weights[mask])


def weighted_horn(
    source: np.ndarray, target: np.ndarray, weights: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Horn's closed form for min sum_j w_j ||t_j - (R s_j + t)||^2 (weighted centroids).

    The summed Horn matrix is linear in the correlation C = sum_j w_j s_j t_j^T, and
    C = sum_k e_k C[k]^T, so it is the forms of (identity rows, rows of C) summed.
    """
    share = weights / weights.sum()
    source_mean, target_mean = share @ source, share @ target
    correlation = ((source - source_mean) * share[:, None]).T @ (target - target_mean)
    horn_matrix = quat_quadratic_forms(np.eye(3), correlation).sum(axis=0)
    _, vectors = np.linalg.eigh(horn_matrix)
    quaternion = vectors[:, -1] / np.linalg.norm(vectors[:, -1])
    quaternion = -quaternion if quaternion[0] < 0.0 else quaternion
    rotation = _unit_quat_to_matrix(quaternion)
    return quaternion, rotation, target_mean - rotation @ source_mean


def _unit_quat_to_matrix(quaternion: np.ndarray) -> np.ndarray:
    """Rotation of one unit quaternion; scalar arithmetic, ~20x cheaper than the batched
    ``geometry.quat_to_matrix`` for a single quaternion in the refit loop."""
    w, x, y, z = (float(value) for value in quaternion)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _arun(
    source: np.ndarray, target: np.ndarray, mask: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The paper's final step: SVD (Arun, with the det guard), then eq. 8 for t."""
    rotation, translation = kabsch(source[mask], target[mask])
    return matrix_to_quat(rotation), rotation, translation


def _finish(
    source: np.ndarray,
    target: np.ndarray,
    supporters: np.ndarray,
    delta: float,
    iterations: int,
    fit: Fit,
    pose: Pose | None = None,
    scales: np.ndarray | None = None,
) -> RegistrationResult:
    """Least-squares pose of the supporters: t = mean(p') - R mean(p) over them (eq. 8).

    ``pose`` is ``fit`` of the supporters when the caller has already computed it. The
    cost sum_j min(u_j^2, delta^2) is over residuals u_j normalised by ``scales``.
    """
    count = len(source)
    support = int(np.count_nonzero(supporters))
    if support < MIN_SUPPORT:
        return failed_result(
            count,
            f"only {support} pair(s) support the best rotation (need {MIN_SUPPORT}); "
            f"delta={delta:.3g} m may be too small for the noise",
            iterations=iterations,
        )
    if is_degenerate(source[supporters]) or is_degenerate(target[supporters]):
        return failed_result(count, "the supporting pairs are collinear", iterations=iterations)
    quaternion, rotation, translation = (pose or fit(source, target, supporters))[:3]
    residual = _normalised(residual_norms(rotation, translation, source, target), scales)
    cost = float(np.minimum(residual**2, delta * delta).sum())
    return pose_result(
        rotation, translation, supporters, cost=cost, iterations=iterations, quaternion=quaternion
    )


def _rigid_core(weights: np.ndarray, ranking: np.ndarray, size: int) -> np.ndarray:
    """Top-ranked pairs taken greedily when rigid-consistent with all pairs taken before.

    Falls back to the plain top of the ranking when no consistent core of 3 exists.
    """
    candidates = ranking[: 4 * size]
    consistent = weights[np.ix_(candidates, candidates)] > 0.0
    allowed = consistent[0].copy()  # compatible with everything taken so far
    taken = [0]
    while len(taken) < size:
        remaining = np.flatnonzero(allowed[taken[-1] + 1 :])
        if len(remaining) == 0:
            break
        taken.append(taken[-1] + 1 + int(remaining[0]))
        allowed &= consistent[taken[-1]]
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
    source32, target32 = _centred_float32(source), _centred_float32(target)
    if scales is None:
        return _rigidity_kernel(source32, target32, float(tolerance))
    half_squares = np.ascontiguousarray(0.5 * np.asarray(scales) ** 2, dtype=np.float32)
    return _scaled_rigidity_kernel(source32, target32, float(tolerance), half_squares)


def _centred_float32(points: np.ndarray) -> np.ndarray:
    """(3, N) contiguous float32 coordinates relative to the centroid."""
    return np.ascontiguousarray((points - points.mean(axis=0)).T, dtype=np.float32)


def rigidity_scores(weights: np.ndarray, power_steps: int = 2) -> np.ndarray:
    """Leading-eigenvector approximation of the weight matrix (spectral matching).

    The degree counts consistent partners; each power step also rewards partners that are
    themselves consistent with many, which is what separates a rigid cluster of inliers
    from chance agreements of outliers.
    """
    scores = weights.sum(axis=1)
    for _ in range(power_steps):
        scores = weights @ scores
        peak = scores.max()
        if peak <= 0.0:
            break
        scores = scores / peak
    return scores


@numba.njit(cache=True, fastmath=True, nogil=True)
def _rigidity_kernel(source: np.ndarray, target: np.ndarray, tolerance: float) -> np.ndarray:
    # Full rows over structure-of-arrays inputs: branch-free, SIMD-friendly inner loop.
    count = source.shape[1]
    weights = np.empty((count, count), dtype=np.float32)
    scale = np.float32(1.0 / (tolerance * tolerance))
    zero, one = np.float32(0.0), np.float32(1.0)
    sx, sy, sz = source[0], source[1], source[2]
    tx, ty, tz = target[0], target[1], target[2]
    for i in range(count):
        row = weights[i]
        for j in range(count):
            source_sq = (sx[j] - sx[i]) ** 2 + (sy[j] - sy[i]) ** 2 + (sz[j] - sz[i]) ** 2
            target_sq = (tx[j] - tx[i]) ** 2 + (ty[j] - ty[i]) ** 2 + (tz[j] - tz[i]) ** 2
            error = np.sqrt(source_sq) - np.sqrt(target_sq)
            row[j] = max(one - error * error * scale, zero)
        row[i] = zero
    return weights


@numba.njit(cache=True, fastmath=True, nogil=True)
def _scaled_rigidity_kernel(
    source: np.ndarray, target: np.ndarray, tolerance: float, half_squares: np.ndarray
) -> np.ndarray:
    # As _rigidity_kernel, dividing by tolerance^2 (s_i^2 + s_j^2) / 2 per pair of pairs.
    count = source.shape[1]
    weights = np.empty((count, count), dtype=np.float32)
    scale = np.float32(1.0 / (tolerance * tolerance))
    zero, one = np.float32(0.0), np.float32(1.0)
    sx, sy, sz = source[0], source[1], source[2]
    tx, ty, tz = target[0], target[1], target[2]
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


@register_method("pso")
def pso(source: np.ndarray, target: np.ndarray, *, seed: int | None = None, **options: object):
    """The paper's swarm: all-pairs centroids, eq. 13 cost, eq. 15 support, SVD refit."""
    return PsoSupportEstimator.from_options(False, options).estimate(source, target, seed)


@register_method("pso-robust")
def pso_robust(
    source: np.ndarray, target: np.ndarray, *, seed: int | None = None, **options: object
):
    """Rigidity-seeded, core-anchored swarm with an adaptive threshold and a refit loop."""
    return PsoSupportEstimator.from_options(True, options).estimate(source, target, seed)
