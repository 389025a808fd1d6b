"""The GTSAM smoother behind the back end: its keys, their time stamps and its estimates.

One Pose3 ``x<k>`` per frame (body in world) and, with an IMU, one gyro bias ``b<k>``; world
gravity ``g0`` and the accelerometer bias ``a0`` are one variable each, restamped with every
update so the fixed-lag smoother keeps them (marginalising old frames folds their information
in). ``Smoother`` hides which GTSAM smoother runs (fixed-lag or full iSAM2) from the rest.
"""

from __future__ import annotations

import math

import gtsam
import numpy as np

from estimator.config import BackendConfig
from estimator.geometry import se3_adjoint

__all__ = ["ACCEL_BIAS_KEY", "GRAVITY_KEY", "STAMP_MARGIN_S", "Smoother", "bias_key", "pose_key"]

GRAVITY_KEY = gtsam.symbol("g", 0)
ACCEL_BIAS_KEY = gtsam.symbol("a", 0)
# A key is used by new factors only if its smoother stamp is this far inside the window.
STAMP_MARGIN_S = 1e-6


def pose_key(index: int) -> int:
    return gtsam.symbol("x", index)


def bias_key(index: int) -> int:
    return gtsam.symbol("b", index)


class Smoother:
    """The incremental smoother and the time origin of its key stamps."""

    def __init__(self, config: BackendConfig) -> None:
        self.config = config
        self.start_ns = 0
        self.graph = self._make()

    def reset(self) -> None:
        """A fresh, empty smoother (after a numerical failure)."""
        self.graph = self._make()

    @property
    def fixed_lag(self) -> bool:
        return not isinstance(self.graph, gtsam.ISAM2)

    def _make(self) -> gtsam.ISAM2 | gtsam.IncrementalFixedLagSmoother:
        config = self.config
        params = gtsam.ISAM2Params()
        thresholds = gtsam.ISAM2ThresholdMap()
        rotation, translation = config.relinearize_rotation_rad, config.relinearize_translation_m
        thresholds.insert(("x", np.array([rotation] * 3 + [translation] * 3)))
        thresholds.insert(("r", np.array([rotation] * 3 + [translation] * 3)))  # keyframe views
        thresholds.insert(("b", np.full(3, config.relinearize_bias)))
        thresholds.insert(("l", np.full(3, translation)))  # stereo landmarks (metres)
        # Gravity and accelerometer bias: the inertial factor is linear in both, so its
        # linearisation is exact at any point and a change of theirs never needs one.
        thresholds.insert(("g", np.full(3, np.inf)))
        thresholds.insert(("a", np.full(3, np.inf)))
        params.setRelinearizeThreshold(thresholds)
        # QR: the bias random walk (~4e-6 rad/s per frame) against a 0.05 rad/s prior is too
        # ill-conditioned for Cholesky when no gyro factor ties the biases to the poses.
        params.setFactorization(
            "CHOLESKY" if config.landmarks and config.landmark_cholesky else "QR"
        )
        params.relinearizeSkip = 1
        if config.smoother == "isam2":
            return gtsam.ISAM2(params)
        return gtsam.IncrementalFixedLagSmoother(config.smoother_lag_s, params)

    def isam(self) -> gtsam.ISAM2:
        graph = self.graph
        return graph if isinstance(graph, gtsam.ISAM2) else graph.getISAM2()

    def update(
        self,
        factors: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        keys: list[int],
        timestamp_ns: int,
        keep: tuple[int, ...] = (),
    ) -> None:
        """Add factors and values; ``keys`` (and ``keep``) are stamped with the frame's time.

        ``keep`` lists existing keys the new factors touch: restamping them stops the fixed-lag
        smoother from marginalising them in this very update (a frame gap longer than the lag),
        so their estimates can still be read afterwards.
        """
        if isinstance(self.graph, gtsam.ISAM2):
            self.graph.update(factors, values)
        else:
            stamp = self.stamp(timestamp_ns)
            self.graph.update(factors, values, dict.fromkeys([*keys, *keep], stamp))
        for _ in range(self.config.extra_iterations):
            self.graph.update()

    def stamp(self, timestamp_ns: int) -> float:
        """Smoother time of a frame's keys: seconds since the first frame, rounded down to
        ``marginalize_block_s``.

        GTSAM's fixed-lag smoother drops the keys stamped more than the lag before the newest
        one; each such marginalisation linearises again the factors around the dropped frames,
        so rounding the stamps down makes frames leave in blocks, at about the cost of one.
        """
        seconds = (timestamp_ns - self.start_ns) * 1e-9
        block = self.config.marginalize_block_s
        return math.floor(seconds / block) * block if block > 0 else seconds

    def pose(self, index: int) -> np.ndarray:
        return self.graph.calculateEstimatePose3(pose_key(index)).matrix()

    def bias(self, index: int) -> np.ndarray:
        return np.asarray(self.graph.calculateEstimateVector(bias_key(index)))

    def vector(self, key: int) -> np.ndarray:
        return np.asarray(self.graph.calculateEstimateVector(key))

    def has_pose(self, index: int) -> bool:
        return bool(self.isam().valueExists(pose_key(index)))

    def marginals(
        self, index: int, motion: np.ndarray | None
    ) -> tuple[np.ndarray | None, np.ndarray | None]:
        """Covariance of pose ``index`` and of the motion from the previous one.

        The motion M = X_prev^-1 X_cur has the right-perturbation error
        xi = xi_cur - Ad(M^-1) xi_prev, so its covariance needs the joint marginal of both.
        None where GTSAM cannot give it (a restarted graph without the previous frame).
        """
        isam = self.isam()
        current = pose_key(index)
        try:
            if motion is None or not isam.valueExists(pose_key(index - 1)):
                return np.asarray(isam.marginalCovariance(current)), None
            previous = pose_key(index - 1)
            joint = isam.jointMarginalCovariance(gtsam.KeyVector([previous, current]))
        except RuntimeError:  # numerical failure inside GTSAM
            return None, None
        jacobian = np.empty((6, 12))
        jacobian[:, :6], jacobian[:, 6:] = -se3_adjoint(motion, inverse=True), np.eye(6)
        blocks = np.empty((12, 12))  # filled block by block: np.block costs more than the rest
        current_block = np.asarray(joint.at(current, current))
        blocks[:6, :6], blocks[:6, 6:] = joint.at(previous, previous), joint.at(previous, current)
        blocks[6:, :6], blocks[6:, 6:] = joint.at(current, previous), current_block
        motion_covariance = jacobian @ blocks @ jacobian.T
        motion_covariance = 0.5 * (motion_covariance + motion_covariance.T)
        return current_block, motion_covariance
