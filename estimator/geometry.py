"""Shared rigid-body math: quaternions, SE(3) (poses and their adjoint) and the Kabsch/Arun fit.

Every other module uses these functions; there is exactly one implementation of each
operation. Quaternions are scalar-first ``(w, x, y, z)`` and unit norm. All quaternion
functions broadcast over leading axes, so ``quat_rotate(q[:, None], points[None])`` rotates
every point by every quaternion at once (particles x points), which is what the swarm needs.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "compose",
    "horn",
    "invert_pose",
    "is_degenerate",
    "kabsch",
    "kabsch_batched",
    "make_pose",
    "matrix_to_quat",
    "nearest_rigid",
    "quat_conjugate",
    "quat_multiply",
    "quat_normalize",
    "quat_quadratic_forms",
    "quat_rotate",
    "quat_to_matrix",
    "quat_to_rotation_vector",
    "rotation_angle_deg",
    "rotation_vector",
    "rotation_vector_to_quat",
    "scale_motion",
    "se3_adjoint",
    "skew",
    "transform_points",
    "transport_covariance",
    "wahba",
]


# ----------------------------------------------------------------------------- quaternions


def quat_normalize(q: np.ndarray) -> np.ndarray:
    """Unit quaternion(s) with w >= 0 (one representative of +-q)."""
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0.0, -q, q)


def quat_multiply(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product p * q, broadcasting over leading axes."""
    pw, px, py, pz = np.moveaxis(np.asarray(p, dtype=float), -1, 0)
    qw, qx, qy, qz = np.moveaxis(np.asarray(q, dtype=float), -1, 0)
    return np.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        axis=-1,
    )


def quat_conjugate(q: np.ndarray) -> np.ndarray:
    """q^-1 for a unit quaternion."""
    q = np.asarray(q, dtype=float)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def quat_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """q v q^-1 in Rodrigues form: v + 2w (u x v) + 2 u x (u x v), u the vector part.

    Cheaper than two Hamilton products and broadcast-friendly: ``q`` (..., 4) and ``v``
    (..., 3) broadcast against each other.
    """
    q = np.asarray(q, dtype=float)
    v = np.asarray(v, dtype=float)
    w = q[..., :1]
    u = q[..., 1:]
    uv = np.cross(u, v)
    return v + 2.0 * (w * uv + np.cross(u, uv))


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix (..., 3, 3) of unit quaternion(s) (..., 4), normalised first.

    One quaternion (the refinement's step, a prediction) goes through plain floats: a dozen
    numpy calls on 4-element arrays cost more than the arithmetic itself.
    """
    q = np.asarray(q, dtype=float)
    if q.shape == (4,):
        w, x, y, z = (float(c) for c in q)
        norm = math.sqrt(w * w + x * x + y * y + z * z)
        w, x, y, z = w / norm, x / norm, y / norm, z / norm
        return np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
            ]
        )
    w, x, y, z = np.moveaxis(q / np.linalg.norm(q, axis=-1, keepdims=True), -1, 0)
    matrix = np.empty((*q.shape[:-1], 3, 3))
    matrix[..., 0, 0], matrix[..., 0, 1] = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z)
    matrix[..., 0, 2], matrix[..., 1, 0] = 2 * (x * z + w * y), 2 * (x * y + w * z)
    matrix[..., 1, 1], matrix[..., 1, 2] = 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
    matrix[..., 2, 0], matrix[..., 2, 1] = 2 * (x * z - w * y), 2 * (y * z + w * x)
    matrix[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return matrix


def _orthonormal_rotations(rotation: object) -> np.ndarray:
    """(..., 3, 3) rotation matrices, checked: a reflection or a singular matrix is an error,
    one that is orthonormal only to a tolerance is projected onto SO(3) (closest, Frobenius)."""
    matrices = np.asarray(rotation, dtype=float)
    if matrices.ndim < 2 or matrices.shape[-2:] != (3, 3):
        raise ValueError(f"rotation matrices must have shape (..., 3, 3), got {matrices.shape}")
    determinant = np.linalg.det(matrices)
    if not (determinant > 0).all():
        raise ValueError("a rotation matrix has a non-positive determinant (a reflection)")
    gram = matrices @ np.swapaxes(matrices, -1, -2)
    orthonormal = np.abs(gram - np.eye(3)) <= _ORTHONORMAL_ATOL + _ORTHONORMAL_RTOL * np.eye(3)
    orthonormal = orthonormal.all(axis=(-2, -1))
    if not orthonormal.all():
        matrices = matrices.copy()
        u, _, vt = np.linalg.svd(matrices[~orthonormal])
        matrices[~orthonormal] = u @ vt
    return matrices


# A matrix whose rows are orthonormal to this tolerance is converted as it is.
_ORTHONORMAL_ATOL, _ORTHONORMAL_RTOL = 1e-12, 1e-5


def _shepperd(m: np.ndarray) -> list[float]:
    """(x, y, z, w) up to scale of one orthonormal 3x3 matrix, in plain floats.

    Of 4w^2 = 1 + tr R and 4x^2 = 1 + 2 R_xx - tr R (y, z alike) the largest is the root
    taken, so the divisor is never small; the others come from the off-diagonal entries.
    """
    (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = m.tolist()
    trace = m00 + m11 + m22
    largest = max(m00, m11, m22, trace)  # ties go to the first, as the order here lists
    if largest == m00:
        return [1 - trace + 2 * m00, m10 + m01, m20 + m02, m21 - m12]
    if largest == m11:
        return [m10 + m01, 1 - trace + 2 * m11, m21 + m12, m02 - m20]
    if largest == m22:
        return [m20 + m02, m21 + m12, 1 - trace + 2 * m22, m10 - m01]
    return [m21 - m12, m02 - m20, m10 - m01, 1 + trace]


def matrix_to_quat(rotation: np.ndarray) -> np.ndarray:
    """Unit quaternion(s) (w >= 0) of rotation matrix/matrices (..., 3, 3).

    Shepperd's branch formula (``_shepperd``): exact near the identity and near 180 degrees
    alike. A reflection raises ValueError; a matrix orthonormal only roughly is projected
    onto SO(3) first.
    """
    # Normalised as (x, y, z, w), then again as (w, x, y, z): the same rounding as before.
    matrix = np.asarray(rotation, dtype=float)
    if matrix.shape == (3, 3) and _is_rotation(matrix):
        return _single_quat(matrix)
    return quat_normalize(np.roll(_unit_xyzw(matrix), 1, axis=-1))


def _single_quat(matrix: np.ndarray) -> np.ndarray:
    """``matrix_to_quat`` of one rotation in plain floats: the same divisions, and the norms
    summed in NumPy's order for four values, so the same bits (tested) at a tenth of the
    time of the array calls (the estimate stage converts a few rotations per frame)."""
    xyzw = _shepperd(matrix)
    norm = math.sqrt(sum(c * c for c in xyzw))
    x, y, z, w = (c / norm for c in xyzw)
    norm = math.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / norm, x / norm, y / norm, z / norm
    return np.array([-w, -x, -y, -z] if w < 0.0 else [w, x, y, z])


def _unit_xyzw(rotation: object) -> np.ndarray:
    """Unit (x, y, z, w) of rotation matrices, any sign; one matrix in plain floats.

    Its rounding is what ``matrix_to_quat`` promises to keep, so it is unit-tested directly.
    """
    matrix = np.asarray(rotation, dtype=float)
    if matrix.shape == (3, 3) and _is_rotation(matrix):
        xyzw = _shepperd(matrix)
        norm = math.sqrt(sum(c * c for c in xyzw))
        return np.array(xyzw) / norm
    matrices = _orthonormal_rotations(matrix)
    if matrices.ndim == 2:
        xyzw = np.array(_shepperd(matrices))
    else:
        xyzw = _shepperd_batch(matrices)
    return xyzw / np.linalg.norm(xyzw, axis=-1, keepdims=True)


def _is_rotation(m: np.ndarray) -> bool:
    """A 3x3 matrix with positive determinant and orthonormal rows (tolerance as in
    ``_orthonormal_rotations``), checked in plain floats; False sends it the long way."""
    rows = m.tolist()
    r0, r1, r2 = rows
    cross = (
        r1[1] * r2[2] - r1[2] * r2[1],
        r1[2] * r2[0] - r1[0] * r2[2],
        r1[0] * r2[1] - r1[1] * r2[0],
    )
    if not r0[0] * cross[0] + r0[1] * cross[1] + r0[2] * cross[2] > 0:
        return False
    for i in range(3):
        for j in range(i, 3):
            dot = rows[i][0] * rows[j][0] + rows[i][1] * rows[j][1] + rows[i][2] * rows[j][2]
            tolerance = _ORTHONORMAL_ATOL + (_ORTHONORMAL_RTOL if i == j else 0.0)
            if not abs(dot - (1.0 if i == j else 0.0)) <= tolerance:
                return False
    return True


def _shepperd_batch(m: np.ndarray) -> np.ndarray:
    """``_shepperd`` of (..., 3, 3) matrices at once: all four branches, then a pick."""
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    trace = m00 + m11 + m22
    branches = np.stack(
        [
            np.stack([1 - trace + 2 * m00, m10 + m01, m20 + m02, m21 - m12], axis=-1),
            np.stack([m10 + m01, 1 - trace + 2 * m11, m21 + m12, m02 - m20], axis=-1),
            np.stack([m20 + m02, m21 + m12, 1 - trace + 2 * m22, m10 - m01], axis=-1),
            np.stack([m21 - m12, m02 - m20, m10 - m01, 1 + trace], axis=-1),
        ],
        axis=-2,
    )
    choice = np.argmax(np.stack([m00, m11, m22, trace], axis=-1), axis=-1)
    return np.take_along_axis(branches, choice[..., None, None], axis=-2)[..., 0, :]


def rotation_vector_to_quat(rotvec: np.ndarray) -> np.ndarray:
    """Exponential map: axis-angle 3-vector(s) -> unit quaternion(s), exact for any input.

    Any 3-vector maps to a valid unit quaternion, which makes it a 3-DOF parameterisation
    a swarm can move freely without ever leaving the rotation group.
    """
    rotvec = np.asarray(rotvec, dtype=float)
    if rotvec.shape == (3,):  # one step of the refinement: plain floats, same formula
        x, y, z = rotvec.tolist()
        angle_1 = math.sqrt(x * x + y * y + z * z)
        scale_1 = 0.5 - angle_1**2 / 48.0 if angle_1 < 1e-8 else math.sin(0.5 * angle_1) / angle_1
        return np.array([math.cos(0.5 * angle_1), x * scale_1, y * scale_1, z * scale_1])
    angle = np.linalg.norm(rotvec, axis=-1, keepdims=True)
    half = 0.5 * angle
    # sin(a/2)/a with its Taylor series near zero, so tiny rotations stay exact.
    small = angle < 1e-8
    safe = np.where(small, 1.0, angle)
    scale = np.where(small, 0.5 - angle**2 / 48.0, np.sin(half) / safe)
    return np.concatenate([np.cos(half), rotvec * scale], axis=-1)


def quat_to_rotation_vector(q: np.ndarray) -> np.ndarray:
    """Logarithm map of unit quaternion(s) (w >= 0 branch): the inverse of the exponential map."""
    q = quat_normalize(q)
    vec = q[..., 1:]
    sin_half = np.linalg.norm(vec, axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(sin_half, q[..., :1])
    small = sin_half < 1e-12
    scale = np.where(small, 2.0, angle / np.where(small, 1.0, sin_half))
    return vec * scale


def rotation_vector(rotation: np.ndarray) -> np.ndarray:
    """Logarithm map of rotation matrix (or matrices, (..., 3, 3)): axis x angle in radians."""
    return quat_to_rotation_vector(matrix_to_quat(rotation))


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices [v]x (skew(a) @ b == a x b), broadcast over leading axes."""
    v = np.asarray(v, dtype=float)
    out = np.zeros((*v.shape[:-1], 3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


# ----------------------------------------------------------------------------- SE(3)


def make_pose(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """4x4 homogeneous transform from R (3x3) and t (3,)."""
    pose = np.eye(4)
    pose[:3, :3] = rotation
    pose[:3, 3] = np.asarray(translation, dtype=float).reshape(3)
    return pose


def invert_pose(pose: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform without a general matrix inverse."""
    rotation = pose[..., :3, :3]
    translation = pose[..., :3, 3]
    inverse = np.zeros_like(pose, dtype=float)
    inverse[..., :3, :3] = np.swapaxes(rotation, -1, -2)
    inverse[..., :3, 3] = -np.einsum("...ji,...j->...i", rotation, translation)
    inverse[..., 3, 3] = 1.0
    return inverse


def nearest_rigid(pose: np.ndarray) -> np.ndarray:
    """``pose`` with its rotation block projected onto SO(3) (closest in Frobenius norm).

    Products of poses, or transforms printed with a few digits, are orthonormal only to
    rounding; fed back into a chain or a graph, that deviation compounds.
    """
    rigid = np.array(pose, dtype=float).reshape(4, 4)
    u, _, vt = np.linalg.svd(rigid[:3, :3])
    rigid[:3, :3] = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    rigid[3] = (0.0, 0.0, 0.0, 1.0)
    return rigid


def scale_motion(pose: np.ndarray, factor: float) -> np.ndarray:
    """The motion at the same velocity over ``factor`` times the time: rotation vector and
    translation scaled (constant-velocity prediction across unequal frame intervals)."""
    if factor == 1.0:
        return np.array(pose, dtype=float)
    rotvec = rotation_vector(pose[:3, :3]) * factor
    return make_pose(quat_to_matrix(rotation_vector_to_quat(rotvec)), pose[:3, 3] * factor)


def compose(*poses: np.ndarray) -> np.ndarray:
    """Left-to-right product of 4x4 transforms: compose(A, B, C) = A @ B @ C."""
    result = np.eye(4)
    for pose in poses:
        result = result @ pose
    return result


def transform_points(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 rigid transform to points (N, 3)."""
    return points @ pose[:3, :3].T + pose[:3, 3]


def se3_adjoint(pose: np.ndarray, *, inverse: bool = False) -> np.ndarray:
    """Adjoint Ad(T) (6x6) of a 4x4 pose T; with ``inverse``, Ad(T^-1).

    Tangent vectors are GTSAM's Pose3 ones, rotation first: xi = (omega, v), with the
    perturbation on the right, T exp(xi) ~ (R Exp(omega), t + R v) (the refinement's and the
    back end's convention). The adjoint moves a perturbation from the right of T to its left:
    T exp(xi) = exp(Ad(T) xi) T, i.e. Ad(T) xi = log(T exp(xi) T^-1), with

        Ad(T) = [[R, 0], [[t]x R, R]],   Ad(T^-1) = [[R^T, 0], [-R^T [t]x, R^T]].

    Translation-first conventions (e.g. ROS covariances) swap the blocks: [[R, [t]x R], [0, R]].
    The products are summed in GTSAM's order (not through BLAS), so the matrix is
    Pose3.AdjointMap's to the last bit and covariances handed to the back end do not depend
    on which of the two built them.
    """
    if inverse:
        pose = invert_pose(pose)
    rotation = pose[:3, :3]
    # [t]x R term by term, k = 0, 1, 2 in turn, as Eigen's fixed-size product does.
    coupling = (skew(pose[:3, 3])[:, :, None] * rotation[None, :, :]).sum(axis=1)
    adjoint = np.zeros((6, 6))
    adjoint[:3, :3] = rotation
    adjoint[3:, :3] = coupling
    adjoint[3:, 3:] = rotation
    return adjoint


def transport_covariance(covariance: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Covariance (6x6, right perturbation, rotation first) of X moved on to X @ ``pose``.

    X exp(xi) pose = X pose exp(Ad(pose^-1) xi), so a perturbation of X is one of X @ pose
    seen through Ad(pose^-1): C -> Ad(pose^-1) C Ad(pose^-1)^T (:func:`se3_adjoint`). This is
    how a chained pose inherits the covariance of its first factor, and how a covariance
    held at one frame is compared with one held at the next.
    """
    adjoint = se3_adjoint(pose, inverse=True)
    return adjoint @ covariance @ adjoint.T


def rotation_angle_deg(rotation: np.ndarray) -> np.ndarray:
    """Geodesic angle of rotation matrix/matrices in degrees (robust near 0 and 180).

    From the quaternion, 2 atan2(|v|, |w|): the arccosine of the trace loses half the digits
    near 0 and 180 degrees, the atan2 none. The angle is taken as the length of the rotation
    vector (angle / sin(angle / 2)) v, with its series below 1e-3 rad, which rounds exactly as
    the previous (SciPy) implementation did.
    """
    matrix = np.asarray(rotation, dtype=float)
    if matrix.shape == (3, 3) and _is_rotation(matrix):
        return _single_angle_deg(matrix)
    xyzw = _unit_xyzw(matrix)
    vector = xyzw[..., :3]
    angle = 2.0 * np.arctan2(np.linalg.norm(vector, axis=-1), np.abs(xyzw[..., 3]))
    small = angle <= 1e-3
    squared = angle**2
    series = 2 + squared / 12 + 7 * squared**2 / 2880
    scale = np.where(small, series, angle / (np.sin(angle / 2.0) + small))
    return np.degrees(np.linalg.norm(scale[..., None] * vector, axis=-1))


def _single_angle_deg(matrix: np.ndarray) -> np.float64:
    """``rotation_angle_deg`` of one rotation in plain floats, the same operations in the same
    order (NumPy's own ``arctan2`` and ``sin``, whose last bits can differ from ``math``'s),
    so the same bits (tested) at a fifth of the time."""
    xyzw = _shepperd(matrix)
    norm = math.sqrt(sum(c * c for c in xyzw))
    x, y, z, w = (c / norm for c in xyzw)
    angle = 2.0 * float(np.arctan2(math.sqrt(x * x + y * y + z * z), abs(w)))
    if angle <= 1e-3:
        squared = angle * angle
        scale = 2 + squared / 12 + 7 * (squared * squared) / 2880
    else:
        scale = angle / float(np.sin(angle / 2.0))
    x, y, z = scale * x, scale * y, scale * z
    return np.float64(math.degrees(math.sqrt(x * x + y * y + z * z)))


# ----------------------------------------------------------------------------- Kabsch / Arun


def kabsch(
    source: np.ndarray, target: np.ndarray, weights: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rigid fit target ~ R source + t (Arun et al. 1987, with the det guard).

    The SVD of the cross-covariance can return a reflection (det = -1) for noisy or
    degenerate sets; flipping the sign of the smallest singular direction gives the closest
    proper rotation instead. ``weights`` (N,) allows a weighted fit.
    """
    source = np.asarray(source, dtype=float)
    target = np.asarray(target, dtype=float)
    if weights is None:
        weights = np.ones(len(source))
    weights = np.asarray(weights, dtype=float)
    total = weights.sum()
    source_mean = weights @ source / total
    target_mean = weights @ target / total
    rotation = wahba(source - source_mean, target - target_mean, weights)
    translation = target_mean - rotation @ source_mean
    return rotation, translation


def wahba(source: np.ndarray, target: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Least-squares rotation target ~ R source with no translation (Wahba's problem).

    The rotation part of :func:`kabsch`; on its own it fits directions (unit bearing vectors,
    gravity vectors), where centring would throw away the common direction.
    """
    source = np.asarray(source, dtype=float)
    target = np.asarray(target, dtype=float)
    if weights is None:
        weights = np.ones(len(source))
    covariance = source.T @ (target * np.asarray(weights, dtype=float)[:, None])
    u, _, vt = np.linalg.svd(covariance)
    sign = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    return vt.T @ np.diag([1.0, 1.0, sign]) @ u.T


def kabsch_batched(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unweighted Kabsch for a batch of small sets at once: (B, k, 3) -> R (B, 3, 3), t (B, 3).

    One batched SVD instead of B Python calls; this is what makes scoring many minimal
    (3-point) hypotheses per numpy call possible. Same det guard as :func:`kabsch`.
    """
    source = np.asarray(source, dtype=float)
    target = np.asarray(target, dtype=float)
    source_mean = source.mean(axis=-2)
    target_mean = target.mean(axis=-2)
    covariance = np.swapaxes(source - source_mean[..., None, :], -1, -2) @ (
        target - target_mean[..., None, :]
    )
    u, _, vt = np.linalg.svd(covariance)
    v_ut = np.swapaxes(vt, -1, -2) @ np.swapaxes(u, -1, -2)
    sign = np.where(np.linalg.det(v_ut) < 0.0, -1.0, 1.0)
    flip = np.ones((*source.shape[:-2], 3))
    flip[..., 2] = sign
    rotation = np.swapaxes(vt, -1, -2) @ (flip[..., :, None] * np.swapaxes(u, -1, -2))
    translation = target_mean - np.einsum("...ij,...j->...i", rotation, source_mean)
    return rotation, translation


def is_degenerate(points: np.ndarray, relative_tolerance: float = 1e-6) -> bool:
    """True when points cannot fix a rotation: fewer than 3, coincident, or all on one line.

    Uses the singular values of the centred set: a line has one non-zero value, a single
    location none. The line test is relative to the spread, so it does not depend on units.
    """
    points = np.asarray(points, dtype=float)
    if len(points) < 3:
        return True
    centred = points - points.mean(axis=0)
    # Eigenvalues of the 3x3 scatter are the squared singular values of the centred set.
    spread = np.sqrt(np.maximum(np.linalg.eigvalsh(centred.T @ centred), 0.0))
    # Coincident: no spread beyond rounding of the coordinates; a line: no second direction.
    coincident = spread[2] <= 1e-12 * max(float(np.abs(points).max()), 1e-300)
    return bool(coincident or spread[1] <= relative_tolerance * spread[2])


def _horn_matrix(c: np.ndarray) -> np.ndarray:
    """Horn's symmetric 4x4 matrix of a 3x3 correlation c[a, b] = sum s_a t_b (..., 3, 3)."""
    xx, xy, xz = c[..., 0, 0], c[..., 0, 1], c[..., 0, 2]
    yx, yy, yz = c[..., 1, 0], c[..., 1, 1], c[..., 1, 2]
    zx, zy, zz = c[..., 2, 0], c[..., 2, 1], c[..., 2, 2]
    rows = [
        [xx + yy + zz, yz - zy, zx - xz, xy - yx],
        [yz - zy, xx - yy - zz, xy + yx, zx + xz],
        [zx - xz, xy + yx, yy - xx - zz, yz + zy],
        [xy - yx, zx + xz, yz + zy, zz - xx - yy],
    ]
    return np.stack([np.stack(row, axis=-1) for row in rows], axis=-2)


# The Horn matrix is linear in the correlation: one (9, 16) map applies it to many at once.
_HORN_BASIS = _horn_matrix(np.eye(9).reshape(9, 3, 3)).reshape(9, 16)


def quat_quadratic_forms(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Horn's (1987) symmetric 4x4 matrices: target_j . (q source_j q^-1) = q^T N_j q.

    For a unit quaternion the alignment of every pair is a quadratic form in q, so the
    squared residual ||t_j - q s_j q^-1||^2 = |t_j|^2 + |s_j|^2 - 2 q^T N_j q of P
    quaternions against M pairs is one (P, 16) @ (16, M) product: no rotation matrices and
    no per-particle rotations of the points. Returns (..., 4, 4) for (..., 3) inputs.
    """
    s = np.asarray(source, dtype=float)
    t = np.asarray(target, dtype=float)
    correlation = (s[..., :, None] * t[..., None, :]).reshape(*s.shape[:-1], 9)
    return (correlation @ _HORN_BASIS).reshape(*s.shape[:-1], 4, 4)


def horn(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares rigid fit target ~ q source q^-1 + t in closed form (Horn 1987).

    Same optimum as :func:`kabsch`, but the rotation comes out as a unit quaternion (the
    top eigenvector of the summed Horn matrix; always a proper rotation), so no
    matrix-to-quaternion conversion is needed. Returns (quaternion with w >= 0, R, t).
    """
    source = np.asarray(source, dtype=float)
    target = np.asarray(target, dtype=float)
    source_mean = source.mean(axis=0)
    target_mean = target.mean(axis=0)
    correlation = (source - source_mean).T @ (target - target_mean)
    _, vectors = np.linalg.eigh((correlation.reshape(9) @ _HORN_BASIS).reshape(4, 4))
    quaternion = vectors[:, -1] / np.linalg.norm(vectors[:, -1])
    quaternion = -quaternion if quaternion[0] < 0.0 else quaternion
    # t . R s = q^T N(s t^T) q, so the same basis read backwards gives R (transposed).
    rotation = (_HORN_BASIS @ np.outer(quaternion, quaternion).reshape(16)).reshape(3, 3).T
    return quaternion, rotation, target_mean - rotation @ source_mean
