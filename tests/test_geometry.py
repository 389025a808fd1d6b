"""The shared math: quaternion algebra agrees with scipy, SE(3) inverts, Kabsch recovers."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from estimator import geometry as g

rotvecs = st.lists(
    st.floats(-3.0, 3.0, allow_nan=False), min_size=3, max_size=3
).map(np.array)


@given(rotvecs, rotvecs)
@settings(max_examples=60, deadline=None)
def test_quaternion_ops_match_rotation_matrices(a: np.ndarray, b: np.ndarray) -> None:
    qa, qb = g.rotation_vector_to_quat(a), g.rotation_vector_to_quat(b)
    assert np.isclose(np.linalg.norm(qa), 1.0)
    ra, rb = g.quat_to_matrix(qa), g.quat_to_matrix(qb)
    np.testing.assert_allclose(ra, Rotation.from_rotvec(a).as_matrix(), atol=1e-9)
    np.testing.assert_allclose(g.quat_to_matrix(g.quat_multiply(qa, qb)), ra @ rb, atol=1e-9)
    np.testing.assert_allclose(g.quat_to_matrix(g.quat_conjugate(qa)), ra.T, atol=1e-9)
    v = np.array([0.3, -1.2, 2.0])
    np.testing.assert_allclose(g.quat_rotate(qa, v), ra @ v, atol=1e-9)
    back = g.matrix_to_quat(ra)
    assert np.isclose(abs(back @ qa), 1.0, atol=1e-9)
    np.testing.assert_allclose(
        g.quat_to_matrix(g.rotation_vector_to_quat(g.quat_to_rotation_vector(qa))), ra, atol=1e-9
    )


def test_quat_rotate_broadcasts_particles_by_points() -> None:
    rng = np.random.default_rng(1)
    quats = g.quat_normalize(rng.normal(size=(7, 4)))
    points = rng.normal(size=(11, 3))
    rotated = g.quat_rotate(quats[:, None, :], points[None, :, :])
    assert rotated.shape == (7, 11, 3)
    expected = np.einsum("pij,nj->pni", g.quat_to_matrix(quats), points)
    np.testing.assert_allclose(rotated, expected, atol=1e-12)


def test_pose_inverse_and_compose() -> None:
    pose = g.make_pose(Rotation.from_rotvec([0.1, -0.4, 0.7]).as_matrix(), [1.0, 2.0, -3.0])
    np.testing.assert_allclose(g.compose(pose, g.invert_pose(pose)), np.eye(4), atol=1e-12)
    points = np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]])
    back = g.transform_points(g.invert_pose(pose), g.transform_points(pose, points))
    np.testing.assert_allclose(back, points, atol=1e-12)


def test_kabsch_recovers_and_never_reflects() -> None:
    rng = np.random.default_rng(2)
    source = rng.normal(size=(50, 3))
    rotation = Rotation.from_rotvec([0.3, 0.2, -1.1]).as_matrix()
    target = source @ rotation.T + [0.5, -1.0, 2.0]
    r, t = g.kabsch(source, target)
    np.testing.assert_allclose(r, rotation, atol=1e-10)
    np.testing.assert_allclose(t, [0.5, -1.0, 2.0], atol=1e-10)
    # A mirrored target has a reflection as best orthogonal fit; the guard returns a rotation.
    r_mirror, _ = g.kabsch(source, source * [1.0, 1.0, -1.0])
    assert np.isclose(np.linalg.det(r_mirror), 1.0)
