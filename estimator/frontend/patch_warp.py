"""Reference patches warped into the current view before the sub-pixel refinement in time.

Lucas-Kanade aligns a reference patch with the current image by a translation only. Between a
keyframe and a frame several steps later the patch has also turned (a roll of the camera) and
grown or shrunk (the camera moved towards or away from a point under a metre away): a
translation cannot fit that, and the best translation of a corner that is not symmetric lands
off the corner by a fraction of a pixel, the same way for every frame measured against that
keyframe. (On the real MH_01 clip the pixel error against the ground truth grows with the
keyframe's age, 0.2 px one frame apart to 0.6 px five frames apart, but warping did not
reduce it: the option stays off; docs/frontend.md.)

Here each reference patch is resampled through the local affine map that the predicted motion
induces at its pixel (its point taken on a plane facing the reference camera), so the
template LK aligns already looks like the current view. The warped patches are laid out as
tiles of one image the size of the current one, so a single ``cv2.remap`` builds them and a
single ``cv2.calcOpticalFlowPyrLK`` aligns them all.
"""

from __future__ import annotations

import cv2
import numpy as np

from estimator.formats.calibration import Rectification
from estimator.geometry import transform_points

__all__ = ["local_affine", "warped_templates"]

# Pixels around the LK window kept in each tile (image gradients need a border).
_TILE_BORDER = 2
# Local maps whose singular values leave this range (a turn or zoom beyond what a patch
# survives) are not applied: the patch is then used as it is.
_MIN_STRETCH, _MAX_STRETCH = 0.5, 2.0


def local_affine(
    pixels: np.ndarray,
    points: np.ndarray,
    current_from_reference: np.ndarray,
    rectification: Rectification,
) -> np.ndarray:
    """(N, 2, 2) d(current pixel) / d(reference pixel) at each reference point.

    The neighbourhood of a point is taken on the plane through it that faces the reference
    camera (its depth for every neighbour): the surface normal is unknown, and the roll and
    the change of scale, which a translation-only fit cannot follow, do not depend on it.
    """
    f, cx, cy = rectification.fx, rectification.cx, rectification.cy
    depth = points[:, 2:3]

    def moved(offset: np.ndarray) -> np.ndarray:
        shifted = pixels + offset
        lifted = np.column_stack(
            [(shifted[:, 0] - cx) * depth[:, 0] / f, (shifted[:, 1] - cy) * depth[:, 0] / f, depth]
        )
        camera = transform_points(current_from_reference, lifted)
        with np.errstate(divide="ignore", invalid="ignore"):
            return f * camera[:, :2] / camera[:, 2:3]

    centre = moved(np.zeros(2))
    affine = np.empty((len(pixels), 2, 2))
    affine[:, :, 0] = moved(np.array([1.0, 0.0])) - centre
    affine[:, :, 1] = moved(np.array([0.0, 1.0])) - centre
    usable = np.all(np.isfinite(affine), axis=(1, 2))
    stretch = np.full((len(pixels), 2), 1.0)
    stretch[usable] = np.linalg.svd(affine[usable], compute_uv=False)
    usable &= np.all((stretch >= _MIN_STRETCH) & (stretch <= _MAX_STRETCH), axis=1)
    usable &= np.linalg.det(np.where(usable[:, None, None], affine, np.eye(2))) > 0
    affine[~usable] = np.eye(2)
    return affine


def warped_templates(
    reference_image: np.ndarray,
    reference_pixels: np.ndarray,
    affine: np.ndarray,
    half_window: int,
    shape: tuple[int, int],
) -> tuple[np.ndarray, np.ndarray] | None:
    """One image of ``shape`` holding each reference patch as the current view should see it,
    and each patch's centre in it; None when the tiles do not fit (more points than tiles).

    Tile pixel at offset o from its centre samples the reference image at
    ``reference_pixel + A^-1 o`` (bilinear).
    """
    tile = 2 * (half_window + _TILE_BORDER) + 1
    per_row, rows = shape[1] // tile, shape[0] // tile
    n = len(reference_pixels)
    if n == 0 or n > per_row * rows:
        return None
    index = np.arange(n)
    origin = np.column_stack([(index % per_row) * tile, (index // per_row) * tile])
    half = tile // 2
    centres = (origin + half).astype(np.float32)
    steps = np.arange(tile) - half
    offset_x, offset_y = np.meshgrid(steps, steps)  # (tile, tile) each
    offsets = np.stack([offset_x, offset_y], axis=-1).reshape(-1, 2).astype(float)  # (T, 2)
    inverse = np.linalg.inv(affine)  # (N, 2, 2)
    source = reference_pixels[:, None, :] + np.einsum("nij,tj->nti", inverse, offsets)
    map_x = np.full(shape, -1.0, np.float32)
    map_y = np.full(shape, -1.0, np.float32)
    target_x = (origin[:, 0:1] + half + offsets[None, :, 0]).astype(int)
    target_y = (origin[:, 1:2] + half + offsets[None, :, 1]).astype(int)
    map_x[target_y, target_x] = source[:, :, 0]
    map_y[target_y, target_x] = source[:, :, 1]
    mosaic = cv2.remap(
        reference_image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
    )
    return mosaic, centres
