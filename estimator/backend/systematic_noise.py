"""Reported covariance of a vision measurement when no gyro can calibrate it.

With an IMU the reported covariances are scaled by a factor measured against the gyro
(``covariance_scale.py``). Without one, nothing independent sees the errors the stereo noise
model misses, so the reported covariance of each keyframe-to-frame measurement T_ref_cur is
built from what is known about their sources (``swarmvo bench consistency``, the rows without
the IMU; docs/robot-integration.md):

* the refinement's covariance (per-point stereo noise through the fit) - on rendered flights,
  whose calibration is exact, the actual errors are about 2x its variance;
* a floor, smaller than the one the back end's factors use (``backend.fit_min_*``): that one
  (0.1 mrad, 0.5 mm) lies above the fit's covariance on rendered flights and made their
  reported covariances 2-5x too large;
* a calibration term proportional to the measured motion: an error of the focal lengths, the
  rectification or the stereo baseline is common to every point of a frame, so the fit's
  residuals cannot show it, and it scales the measured motion: a focal-length or rectification
  error of a fraction g turns a rotation theta into (1 + g) theta, and depth = focal x baseline /
  disparity makes the translation's scale wrong by the focal and the baseline errors together.
  Per axis, sigma_rotation = ``calibration_rotation_gain`` x |theta| and sigma_translation =
  ``calibration_translation_gain`` x |t|. Unset, they follow from the rig
  (``calibration_gains``): 1 % and 2 % (the accuracy a target-based calibration of a small
  stereo rig achieves), 0 for a rig whose calibration is exact (a rendered one, which says so
  in its calibration files).
"""

from __future__ import annotations

import gtsam
import numpy as np

from estimator.config import BackendConfig
from estimator.geometry import transport_covariance

__all__ = [
    "CALIBRATION_ROTATION_GAIN",
    "CALIBRATION_TRANSLATION_GAIN",
    "EXACT_RIG_FIT_FLOOR",
    "REAL_RIG_FIT_FLOOR",
    "calibration_covariance",
    "calibration_gains",
    "drift_growth",
    "fit_floor",
    "fit_floor_covariance",
    "keyframe_error_correlation",
    "reported_measurement_covariance",
    "shared_error_growth",
]

# Relative calibration errors of a real rig (module doc), rotation and translation.
CALIBRATION_ROTATION_GAIN = 0.01
CALIBRATION_TRANSLATION_GAIN = 0.02
# The floor the graph adds to each relative pose's fit covariance (rad, m per axis): what a
# per-point noise model misses on a real rig (0.1 mrad, 0.5 mm), and a fifth of it on a rig
# whose calibration is exact. There the fit's own sigmas are the error: on the rendered drives
# (0.04 mrad per frame) the real-rig floor weighed vision 2x below its error and the gyro,
# with its bias, set the rotation (fused 0.0056 deg per frame against vision's 0.0025).
REAL_RIG_FIT_FLOOR = (1e-4, 5e-4)
EXACT_RIG_FIT_FLOOR = (2e-5, 1e-4)
# Lag-1 correlation of consecutive measurements' errors against one keyframe (``bench
# consistency`` measures +0.46 to +0.51 on rendered flights).
EXACT_RIG_KEYFRAME_ERROR_CORRELATION = 0.5


def calibration_gains(config: BackendConfig, calibration_exact: bool) -> tuple[float, float]:
    """The (rotation, translation) gains: the configured ones, else the rig's (module doc)."""
    rotation, translation = CALIBRATION_ROTATION_GAIN, CALIBRATION_TRANSLATION_GAIN
    if calibration_exact:
        rotation, translation = 0.0, 0.0
    if config.calibration_rotation_gain is not None:
        rotation = config.calibration_rotation_gain
    if config.calibration_translation_gain is not None:
        translation = config.calibration_translation_gain
    return rotation, translation


def fit_floor(config: BackendConfig, calibration_exact: bool = False) -> tuple[float, float]:
    """The (rotation rad, translation m) floor of the fit covariance: the configured one,
    else the rig's (unset: a rig not known to be exact, as before the rig settings apply)."""
    rotation, translation = EXACT_RIG_FIT_FLOOR if calibration_exact else REAL_RIG_FIT_FLOOR
    if config.fit_min_rotation_sigma_rad is not None:
        rotation = config.fit_min_rotation_sigma_rad
    if config.fit_min_translation_sigma_m is not None:
        translation = config.fit_min_translation_sigma_m
    return rotation, translation


def fit_floor_covariance(config: BackendConfig) -> np.ndarray:
    """The 6x6 diagonal (rotation, translation) covariance of ``fit_floor``."""
    rotation, translation = fit_floor(config)
    return np.diag([rotation**2] * 3 + [translation**2] * 3)


def calibration_covariance(
    relative_pose: np.ndarray, rotation_gain: float, translation_gain: float
) -> np.ndarray:
    """6x6 (rotation, translation) covariance of a motion-proportional calibration error."""
    tangent = np.asarray(gtsam.Pose3.Logmap(gtsam.Pose3(np.asarray(relative_pose, dtype=float))))
    rotation = (rotation_gain * np.linalg.norm(tangent[:3])) ** 2
    translation = (translation_gain * np.linalg.norm(relative_pose[:3, 3])) ** 2
    return np.diag([rotation] * 3 + [translation] * 3)


def reported_measurement_covariance(
    floored: np.ndarray, relative_pose: np.ndarray, config: BackendConfig
) -> np.ndarray:
    """The reported covariance of T_ref_cur (left camera tangent) from the one the back end
    weighs (``floored``: the fit's plus the ``fit_min_*`` floor): the fit's, the reporting
    floor and the calibration term (module doc; unset gains: a rig not known to be exact, as
    ``estimator.rig_settings`` fills them in from the rig before a run)."""
    graph_floor = fit_floor_covariance(config)
    report_floor = np.diag(
        [config.report_min_rotation_sigma_rad**2] * 3
        + [config.report_min_translation_sigma_m**2] * 3
    )
    calibration = calibration_covariance(relative_pose, *calibration_gains(config, False))
    covariance = np.asarray(floored, dtype=float) - graph_floor + report_floor + calibration
    return 0.5 * (covariance + covariance.T)


def drift_growth(
    current: np.ndarray, previous: np.ndarray, motion: np.ndarray
) -> np.ndarray:
    """What the chained pose covariance gained from the previous frame to this one (its
    positive part), as the covariance of the frame-to-frame motion.

    Consecutive frames measured against one keyframe share its points, so their errors largely
    cancel in the motion between them; the sum of both measurements' covariances (independent
    errors) made the integrated twist 5-12x too conservative. The growth of the chain, summed
    over a window, is the drift the pose covariance reports for it: a filter integrating the
    twist gets the same uncertainty as the poses say.
    """
    change = current - transport_covariance(previous, motion)
    values, vectors = np.linalg.eigh(0.5 * (change + change.T))
    return (vectors * np.clip(values, 0.0, None)) @ vectors.T


def keyframe_error_correlation(config: BackendConfig, calibration_exact: bool = False) -> float:
    """rho: the configured one, else the rig's: 0.5 on an exact rig, whose small fit floor
    no longer hides the shared error; 0 on a real rig (unset: as a real rig), where the floor
    and the placement priors' carried covariance (``placement_covariance.py``) already cover
    it and the factor made the real MH_01 fused pose covariance twice too large."""
    if config.keyframe_error_correlation is not None:
        return config.keyframe_error_correlation
    return EXACT_RIG_KEYFRAME_ERROR_CORRELATION if calibration_exact else 0.0


def shared_error_growth(config: BackendConfig) -> float:
    """Factor on the fused pose covariance for the keyframe-shared error of the measurements.

    Consecutive measurements against one keyframe share its points, so their errors are
    correlated (``keyframe_error_correlation``, rho: half of a fit's error is the keyframe's
    when both frames' points are equally noisy; ``swarmvo bench consistency`` measures +0.46
    to +0.51 on rendered flights). The graph, whose frames the gyro ties together, weighs them
    as independent, and its pose covariance grows like a sum of independent errors; a sum of n
    errors with lag-1 correlation rho has variance n (1 + 2 rho) sigma^2 for large n. A
    constant factor on the whole covariance is that factor on its growth.
    """
    return 1.0 + 2.0 * keyframe_error_correlation(config)
