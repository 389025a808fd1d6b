"""Closed-form rotation conversions: Shepperd's matrix -> quaternion, the rotation angle and
quaternion -> matrix, against known rotations, SciPy, and the edge cases (identity, 180 deg)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from estimator import geometry as g


def _rotations(count: int, seed: int) -> np.ndarray:
    return Rotation.random(count, random_state=seed).as_matrix()


def test_known_rotations() -> None:
    half = np.sqrt(0.5)
    cases = {
        (1.0, 0.0, 0.0, 0.0): np.eye(3),
        (half, 0.0, 0.0, half): np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
        (0.0, 1.0, 0.0, 0.0): np.diag([1.0, -1.0, -1.0]),  # 180 deg about x
        (0.0, 0.0, 1.0, 0.0): np.diag([-1.0, 1.0, -1.0]),
        (0.0, 0.0, 0.0, 1.0): np.diag([-1.0, -1.0, 1.0]),
    }
    for quat, matrix in cases.items():
        np.testing.assert_allclose(g.matrix_to_quat(matrix), quat, atol=1e-15)
        np.testing.assert_allclose(g.quat_to_matrix(np.array(quat)), matrix, atol=1e-15)
    assert g.rotation_angle_deg(np.eye(3)) == 0.0
    assert g.rotation_angle_deg(cases[(half, 0.0, 0.0, half)]) == pytest.approx(90.0, abs=1e-12)
    assert g.rotation_angle_deg(np.diag([1.0, -1.0, -1.0])) == pytest.approx(180.0, abs=1e-12)


def test_matrix_to_quat_matches_scipy_in_every_branch() -> None:
    rng = np.random.default_rng(3)
    axes = rng.normal(size=(300, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.concatenate([rng.uniform(0, 1e-7, 100), rng.uniform(0, np.pi, 100),
                             np.pi - rng.uniform(0, 1e-7, 100)])  # fmt: skip
    matrices = np.concatenate([Rotation.from_rotvec(axes * angles[:, None]).as_matrix(),
                               _rotations(500, 4)])  # fmt: skip
    quats = g.matrix_to_quat(matrices)
    expected = np.roll(Rotation.from_matrix(matrices).as_quat(), 1, axis=-1)
    expected *= np.where(expected[:, :1] < 0, -1.0, 1.0)
    np.testing.assert_allclose(quats, expected, atol=1e-15)
    assert (quats[:, 0] >= 0).all()
    np.testing.assert_allclose(np.linalg.norm(quats, axis=1), 1.0, atol=1e-15)
    np.testing.assert_allclose(g.quat_to_matrix(quats), matrices, atol=1e-14)
    # One matrix at a time (the plain-float path) gives the very same numbers as the batch.
    singles = np.array([g.matrix_to_quat(m) for m in matrices[::7]])
    np.testing.assert_array_equal(singles, quats[::7])
    random_angles = np.linalg.norm(Rotation.from_matrix(matrices[300:]).as_rotvec(), axis=1)
    expected_deg = np.degrees(np.concatenate([angles, random_angles]))
    np.testing.assert_allclose(g.rotation_angle_deg(matrices), expected_deg, rtol=1e-12, atol=1e-12)


def test_angle_near_identity_keeps_its_digits() -> None:
    for angle in (1e-12, 1e-9, 1e-6):
        matrix = Rotation.from_rotvec([0.0, angle, 0.0]).as_matrix()
        assert g.rotation_angle_deg(matrix) == pytest.approx(np.degrees(angle), rel=1e-9)


def test_batch_shapes() -> None:
    matrices = _rotations(24, 5).reshape(2, 3, 4, 3, 3)
    quats = g.matrix_to_quat(matrices)
    assert quats.shape == (2, 3, 4, 4)
    assert g.rotation_angle_deg(matrices).shape == (2, 3, 4)
    assert g.quat_to_matrix(quats).shape == (2, 3, 4, 3, 3)
    np.testing.assert_allclose(g.quat_to_matrix(quats), matrices, atol=1e-14)
    assert g.matrix_to_quat(np.zeros((0, 3, 3))).shape == (0, 4)
    assert g.rotation_angle_deg(matrices[0, 0, 0]).shape == ()


def test_quat_to_matrix_normalises_and_ignores_the_sign() -> None:
    quat = np.array([0.9, -0.2, 0.3, 0.1])
    unit = quat / np.linalg.norm(quat)
    np.testing.assert_allclose(g.quat_to_matrix(3.0 * quat), g.quat_to_matrix(unit), atol=1e-15)
    np.testing.assert_allclose(g.quat_to_matrix(-unit), g.quat_to_matrix(unit), atol=1e-16)
    np.testing.assert_allclose(g.quat_to_matrix(unit[None])[0], g.quat_to_matrix(unit),
                               atol=1e-16)  # fmt: skip


def test_nearly_orthonormal_is_projected_and_reflections_refused() -> None:
    rotation = _rotations(1, 6)[0]
    noisy = rotation + 1e-7 * np.random.default_rng(7).normal(size=(3, 3))
    np.testing.assert_allclose(g.quat_to_matrix(g.matrix_to_quat(noisy)), rotation, atol=1e-6)
    with pytest.raises(ValueError, match="determinant"):
        g.matrix_to_quat(np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ValueError, match="determinant"):
        g.rotation_angle_deg(np.stack([np.eye(3), -np.eye(3)]))
    with pytest.raises(ValueError, match="shape"):
        g.matrix_to_quat(np.eye(4))


def test_one_rotation_in_plain_floats_equals_the_array_route_bit_for_bit() -> None:
    """The single-matrix path keeps the array route's rounding (near 0 and 180 deg too)."""
    rng = np.random.default_rng(21)
    axes = rng.normal(size=(3000, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    near_half_turn = rng.uniform(np.pi - 1e-3, np.pi, 1000)
    tiny = 10.0 ** rng.uniform(-9, -3, 1000)
    angles = np.concatenate([rng.uniform(0, np.pi, 1000), tiny, near_half_turn])
    for vector in axes * angles[:, None]:
        matrix = g.quat_to_matrix(g.rotation_vector_to_quat(vector))
        array_route = g.quat_normalize(np.roll(g._unit_xyzw(matrix), 1, axis=-1))
        np.testing.assert_array_equal(g.matrix_to_quat(matrix), array_route)
        assert g.rotation_angle_deg(matrix) == _angle_array_route(matrix)


def _angle_array_route(matrix: np.ndarray) -> float:
    """``rotation_angle_deg`` of a stack of one matrix: the array formula it uses for stacks."""
    return float(g.rotation_angle_deg(matrix[None])[0])
