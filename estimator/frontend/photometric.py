"""Per-image photometric normalisation: the front end sees the scene, not the exposure.

Cameras change exposure time and gain on their own, and the left and right cameras of a rig
rarely do so in step. Every later stage compares grey values: FAST's threshold is in grey
levels, sub-pixel stereo compares left and right patches, and Lucas-Kanade assumes that a
point keeps its brightness from one frame to the next. An affine grey-level map per image,
I' = a I + b, that brings its mean and standard deviation to fixed values undoes a gain and
an offset exactly (up to rounding and to pixels clipped at 0 or 255), for every stage at once.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["normalise_contrast"]

# Contrast is raised at most this much: a dark or covered frame stays flat instead of having
# its sensor noise amplified into corners (gains of real auto exposure are far smaller).
_MAX_SCALE = 4.0


def normalise_contrast(image: np.ndarray, mean: float, std: float) -> np.ndarray:
    """8-bit ``image`` mapped affinely to the given mean and standard deviation (clipped)."""
    image_mean, image_std = cv2.meanStdDev(image)
    scale = min(std / max(float(image_std[0, 0]), 1e-6), _MAX_SCALE)
    offset = mean - scale * float(image_mean[0, 0])
    table = np.clip(np.rint(np.arange(256) * scale + offset), 0, 255).astype(np.uint8)
    return cv2.LUT(image, table)
