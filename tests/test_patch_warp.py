"""Warped reference patches for the sub-pixel refinement in time (frontend/patch_warp.py)."""

from __future__ import annotations

import cv2
import numpy as np

from estimator.formats.calibration import StereoRig
from estimator.frontend.patch_warp import local_affine, warped_templates
from estimator.frontend.temporal import refine_pixels
from estimator.geometry import make_pose

SHAPE = (480, 752)


def _rectification():
    camera = {
        "width": SHAPE[1], "height": SHAPE[0], "fx": 436.0, "fy": 436.0, "cx": 376.0,
        "cy": 240.0, "distortion_model": "none", "distortion": [],
    }  # fmt: skip
    right = make_pose(np.eye(3), np.array([0.11, 0.0, 0.0]))
    return StereoRig.from_dict(
        {
            "left": {**camera, "T_BS": np.eye(4).tolist()},
            "right": {**camera, "T_BS": right.tolist()},
        }
    ).rectification


def _texture(seed: int) -> np.ndarray:
    noise = np.random.default_rng(seed).uniform(0, 255, SHAPE).astype(np.float32)
    return cv2.GaussianBlur(noise, (0, 0), 2.0)


def _rotation_z(degrees: float) -> np.ndarray:
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def test_local_affine_of_a_roll_and_an_approach() -> None:
    rect = _rectification()
    pixels = np.array([[200.0, 150.0], [rect.cx, rect.cy], [600.0, 400.0]])
    depth = 1.0
    points = np.column_stack(
        [(pixels[:, 0] - rect.cx) * depth / rect.fx, (pixels[:, 1] - rect.cy) * depth / rect.fx,
         np.full(3, depth)]
    )  # fmt: skip
    # A roll of 5 degrees about the optical axis turns every patch by 5 degrees.
    roll = local_affine(pixels, points, make_pose(_rotation_z(5.0), np.zeros(3)), rect)
    np.testing.assert_allclose(
        roll, np.broadcast_to(_rotation_z(5.0)[:2, :2], (3, 2, 2)), atol=1e-9
    )
    # Moving 0.2 m towards a plane 1 m away enlarges its patches by 1 / 0.8.
    approach = local_affine(pixels, points, make_pose(np.eye(3), np.array([0, 0, -0.2])), rect)
    np.testing.assert_allclose(approach, np.broadcast_to(np.eye(2) / 0.8, (3, 2, 2)), atol=1e-9)
    # A map beyond what a patch survives (3x zoom) is left out: identity.
    zoom = local_affine(pixels, points, make_pose(np.eye(3), np.array([0, 0, -0.7])), rect)
    np.testing.assert_allclose(zoom, np.broadcast_to(np.eye(2), (3, 2, 2)))


def test_warped_refinement_finds_turned_and_enlarged_corners() -> None:
    reference = _texture(3)
    centre = np.array([376.0, 240.0])
    affine = 1.15 * _rotation_z(12.0)[:2, :2]
    shift = np.array([2.3, -1.6])
    # current(x) = reference(A^-1 (x - centre - shift) + centre)
    forward = np.column_stack([affine, centre + shift - affine @ centre])
    current = cv2.warpAffine(reference, forward, SHAPE[::-1], flags=cv2.INTER_CUBIC)
    grid = np.stack(np.meshgrid(np.arange(250, 500, 25.0), np.arange(150, 330, 20.0)), -1)
    reference_pixels = grid.reshape(-1, 2) + 0.37
    truth = (reference_pixels - centre) @ affine.T + centre + shift
    start = truth + np.random.default_rng(1).uniform(-0.6, 0.6, truth.shape)
    images = (reference.astype(np.uint8), current.astype(np.uint8))
    maps = np.broadcast_to(affine, (len(truth), 2, 2))
    warped, found_w = refine_pixels(*images, reference_pixels, start, 5, maps)
    plain, found_p = refine_pixels(*images, reference_pixels, start, 5)
    error_w = np.linalg.norm(warped - truth, axis=1)[found_w]
    error_p = np.linalg.norm(plain - truth, axis=1)[found_p]
    assert found_w.mean() > 0.95
    assert np.median(error_w) < 0.05
    assert np.median(error_w) < 0.5 * np.median(error_p)


def test_warped_templates_refuse_more_points_than_tiles() -> None:
    image = _texture(0).astype(np.uint8)
    many = np.full((5000, 2), 100.0)
    assert warped_templates(image, many, np.broadcast_to(np.eye(2), (5000, 2, 2)), 5, SHAPE) is None
    assert warped_templates(image, many[:0], np.zeros((0, 2, 2)), 5, SHAPE) is None
