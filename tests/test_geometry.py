"""The shared math: quaternion algebra agrees with scipy, SE(3) inverts, Kabsch recovers."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from estimator import geometry as g

rotvecs = st.lists(st.floats(-3.0, 3.0, allow_nan=False), min_size=3, max_size=3).map(np.array)


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


def test_kabsch_batched_matches_kabsch_and_never_reflects() -> None:
    rng = np.random.default_rng(7)
    source = rng.normal(size=(40, 3, 3))
    target = rng.normal(size=(40, 3, 3))  # unrelated sets: many raw SVD fits would reflect
    rotations, translations = g.kabsch_batched(source, target)
    np.testing.assert_allclose(np.linalg.det(rotations), 1.0, atol=1e-9)
    for i in range(40):
        rotation, translation = g.kabsch(source[i], target[i])
        np.testing.assert_allclose(rotations[i], rotation, atol=1e-9)
        np.testing.assert_allclose(translations[i], translation, atol=1e-9)


def test_is_degenerate_flags_lines_points_and_tiny_sets() -> None:
    line = np.outer(np.arange(6.0), [1.0, 2.0, 3.0]) + 5.0
    assert g.is_degenerate(line)
    assert g.is_degenerate(np.ones((5, 3)))
    assert g.is_degenerate(np.zeros((2, 3)))
    triangle = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    assert not g.is_degenerate(triangle)
    assert not g.is_degenerate(triangle * 1e-4 + 1e3)  # small but well-formed, far away


def test_quat_quadratic_forms_give_the_rotated_alignment() -> None:
    rng = np.random.default_rng(3)
    quats = g.quat_normalize(rng.normal(size=(6, 4)))
    source, target = rng.normal(size=(9, 3)), rng.normal(size=(9, 3))
    forms = g.quat_quadratic_forms(source, target)
    assert forms.shape == (9, 4, 4)
    np.testing.assert_allclose(forms, np.swapaxes(forms, -1, -2))
    via_forms = np.einsum("pi,jik,pk->pj", quats, forms, quats)
    rotated = g.quat_rotate(quats[:, None, :], source[None, :, :])
    np.testing.assert_allclose(via_forms, np.einsum("jb,pjb->pj", target, rotated), atol=1e-12)


def test_horn_agrees_with_kabsch_and_returns_a_unit_quaternion() -> None:
    rng = np.random.default_rng(5)
    for trial in range(6):
        source = rng.normal(size=(15, 3))
        related = g.transform_points(
            g.make_pose(Rotation.random(random_state=trial).as_matrix(), rng.normal(size=3)),
            source,
        )
        # Alternate a noisy true relation with unrelated sets (where a reflection is closer).
        noise = rng.normal(size=(15, 3))
        target = related + 0.01 * noise if trial % 2 else noise
        quaternion, rotation, translation = g.horn(source, target)
        expected_rotation, expected_translation = g.kabsch(source, target)
        assert np.isclose(np.linalg.norm(quaternion), 1.0) and quaternion[0] >= 0.0
        np.testing.assert_allclose(g.quat_to_matrix(quaternion), rotation, atol=1e-12)
        np.testing.assert_allclose(rotation, expected_rotation, atol=1e-9)
        np.testing.assert_allclose(translation, expected_translation, atol=1e-9)


def test_nearest_rigid_projects_onto_se3_and_keeps_rigid_poses():
    rng = np.random.default_rng(3)
    pose = g.make_pose(Rotation.random(random_state=4).as_matrix(), [1.0, -2.0, 0.5])
    np.testing.assert_allclose(g.nearest_rigid(pose), pose, atol=1e-12)
    noisy = pose + np.vstack([rng.normal(scale=1e-4, size=(3, 4)), np.zeros((1, 4))])
    rigid = g.nearest_rigid(noisy)
    np.testing.assert_allclose(rigid[:3, :3] @ rigid[:3, :3].T, np.eye(3), atol=1e-12)
    assert np.linalg.det(rigid[:3, :3]) > 0
    np.testing.assert_allclose(rigid[:3, 3], noisy[:3, 3])
    assert g.rotation_angle_deg(rigid[:3, :3].T @ pose[:3, :3]) < 0.05
    np.testing.assert_array_equal(rigid[3], [0, 0, 0, 1])


def test_scale_motion_keeps_the_velocity() -> None:
    """Twice the time at the same velocity: the rotation applied twice, twice the translation;
    half the time: the rotation whose square is the original."""
    rotation = Rotation.from_rotvec([0.02, -0.05, 0.01]).as_matrix()
    motion = g.make_pose(rotation, [0.03, -0.01, 0.04])
    double = g.scale_motion(motion, 2.0)
    np.testing.assert_allclose(double[:3, :3], rotation @ rotation, atol=1e-12)
    np.testing.assert_allclose(double[:3, 3], 2 * motion[:3, 3], atol=1e-12)
    half = g.scale_motion(motion, 0.5)[:3, :3]
    np.testing.assert_allclose(half @ half, rotation, atol=1e-12)
    np.testing.assert_allclose(g.scale_motion(motion, 0.0), np.eye(4), atol=1e-12)
    np.testing.assert_array_equal(g.scale_motion(motion, 1.0), motion)


def _twist_hat(xi: np.ndarray) -> np.ndarray:
    """4x4 Lie-algebra matrix of xi = (omega, v), rotation first (GTSAM's Pose3 order)."""
    hat = np.zeros((4, 4))
    hat[:3, :3] = g.skew(xi[:3])
    hat[:3, 3] = xi[3:]
    return hat


def _twist_vee(hat: np.ndarray) -> np.ndarray:
    return np.array([hat[2, 1], hat[0, 2], hat[1, 0], *hat[:3, 3]])


@given(rotvecs, rotvecs)
@settings(max_examples=40, deadline=None)
def test_se3_adjoint_moves_a_right_perturbation_to_the_left(
    rotvec: np.ndarray, translation: np.ndarray
) -> None:
    """Ad(T) xi = log(T exp(xi) T^-1), with the matrix exponential and logarithm (scipy)."""
    from scipy.linalg import expm, logm

    pose = g.make_pose(g.quat_to_matrix(g.rotation_vector_to_quat(rotvec)), translation)
    xi = np.array([0.004, -0.011, 0.007, 0.02, 0.013, -0.009])
    conjugated = pose @ expm(_twist_hat(xi)) @ g.invert_pose(pose)
    expected = _twist_vee(np.real(logm(conjugated)))
    np.testing.assert_allclose(g.se3_adjoint(pose) @ xi, expected, atol=1e-10)
    inverse = g.se3_adjoint(pose, inverse=True)
    np.testing.assert_allclose(inverse, g.se3_adjoint(g.invert_pose(pose)), atol=1e-12)
    np.testing.assert_allclose(inverse @ g.se3_adjoint(pose), np.eye(6), atol=1e-12)


def test_transport_covariance_follows_a_perturbation_through_the_chain() -> None:
    """X exp(xi) T = X T exp(J xi): J measured column by column with expm/logm (scipy), then
    the transported covariance must be J C J^T."""
    from scipy.linalg import expm, logm

    rng = np.random.default_rng(4)
    pose = g.make_pose(
        g.quat_to_matrix(g.rotation_vector_to_quat(np.array([0.3, -0.5, 0.2]))),
        np.array([0.4, -0.2, 1.1]),
    )
    step = 1e-4
    jacobian = np.column_stack(
        [
            _twist_vee(np.real(logm(g.invert_pose(pose) @ expm(_twist_hat(step * unit)) @ pose)))
            / step
            for unit in np.eye(6)
        ]
    )
    factor = rng.normal(size=(6, 6)) * 1e-3
    covariance = factor @ factor.T
    np.testing.assert_allclose(
        g.transport_covariance(covariance, pose), jacobian @ covariance @ jacobian.T, atol=1e-12
    )


def test_se3_adjoint_is_gtsams_adjoint_map() -> None:
    """The back end hands these matrices to GTSAM factors: same block order (rotation first)
    and same values as Pose3.AdjointMap, for the pose and for its inverse."""
    import gtsam

    rng = np.random.default_rng(11)
    for _ in range(200):
        twist = rng.normal(size=6) * np.array([1.0, 1.0, 1.0, 5.0, 5.0, 5.0])
        pose = np.asarray(gtsam.Pose3.Expmap(twist).matrix())
        expected = np.asarray(gtsam.Pose3(pose).AdjointMap())
        np.testing.assert_allclose(g.se3_adjoint(pose), expected, rtol=0, atol=1e-12)
        expected_inverse = np.asarray(gtsam.Pose3(g.invert_pose(pose)).AdjointMap())
        np.testing.assert_allclose(
            g.se3_adjoint(pose, inverse=True), expected_inverse, rtol=0, atol=1e-12
        )
