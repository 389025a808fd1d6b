"""Measurements against a keyframe that has left the window: a view variable of the keyframe.

``old_reference = "prior"`` places such a frame in the world from the keyframe's last estimate
with the measurement's covariance alone: in the graph its absolute covariance stops at one
measurement's while the keyframe's own uncertainty, and the drift before it, are dropped
(MH_01 fused pose NEES 15.5 per DOF when reported as is; ``placement_covariance.py`` adds them
back to the report).

Here every measurement against keyframe K goes through a view V_K of it, a Pose3 variable tied
to X_K by ``Between(X_K, V_K, I)`` when K is first measured against (while X_K is in the
window), and each frame j by ``Between(V_K, X_j, T_Kj)``. The view is restamped with each use,
so it stays in the smoother after X_K has been marginalised: the frames keep their tie to the
keyframe and its uncertainty (the marginal the smoother folds into V_K), and they share it.

Two properties of the front end's measurements shape the noise:

* they share an error (K's stereo points are the same for all): T_Kj measured =
  Exp(s) T_Kj Exp(u_j), s (left, at K) common, u_j (right, at j) independent. The fraction
  ``keyframe_shared_error`` of the measurement's covariance C_j goes to s, on the view's link
  (moved to K by Ad(T_Kj)), the rest to u_j; one measurement alone keeps exactly C_j.
* consecutive ones are strongly correlated (lag-1 correlation 0.87 against the same keyframe
  on MH_01, ``swarmvo bench consistency``), so n of them do not carry n times the information:
  the n-th measurement against a keyframe gets n ** ``keyframe_count_inflation`` C_j. With
  ``1`` the information of the n measurements grows like log n instead of n, and the frames'
  absolute covariance grows along a keyframe's measurements like a random walk, the way the
  errors do.

On MH_01 fused (real IMU) a larger shared fraction made the pose covariance less consistent
(the frames of one keyframe then hold together more tightly than their errors do), and the
inflation was what made it consistent (docs/backend.md has the table).
"""

from __future__ import annotations

import gtsam
import numpy as np

from estimator.backend.noise import robust
from estimator.backend.smoother import STAMP_MARGIN_S, Smoother, pose_key
from estimator.backend.step import Step
from estimator.config import BackendConfig
from estimator.geometry import se3_adjoint

__all__ = ["KeyframeViews", "view_key"]


def view_key(index: int) -> int:
    return gtsam.symbol("r", index)


class KeyframeViews:
    """The views of the keyframes measured against lately (see module doc)."""

    def __init__(self, smoother: Smoother, config: BackendConfig) -> None:
        self.smoother = smoother
        self.config = config
        self.stamps: dict[int, float] = {}  # keyframe index -> smoother stamp of its view
        self.counts: dict[int, int] = {}  # keyframe index -> measurements against it so far

    def reset(self) -> None:
        self.stamps.clear()
        self.counts.clear()

    def add(
        self,
        step: Step,
        reference: int,
        live: bool,
        reference_pose: np.ndarray | None,
        measured: np.ndarray,
        covariance: np.ndarray,
    ) -> bool:
        """The factors of the measurement ``measured`` (body T_Kj, right covariance at j)
        against keyframe ``reference`` through its view. False (nothing added) when the
        keyframe has neither a view nor a variable left in the smoother."""
        # A view stamped before the cutoff is marginalised by this update: not restamped at
        # the edge of the window (GTSAM then fails to marginalise it later).
        self.stamps = {
            index: stamp
            for index, stamp in self.stamps.items()
            if stamp > step.cutoff + STAMP_MARGIN_S
        }
        self.counts = {index: n for index, n in self.counts.items() if index in self.stamps}
        key = view_key(reference)
        shared = self.config.keyframe_shared_error
        if reference in self.stamps and self.smoother.isam().valueExists(key):
            step.keep.append(key)
        elif live and reference_pose is not None:
            adjoint = se3_adjoint(measured)
            shared_covariance = shared * adjoint @ covariance @ adjoint.T
            shared_covariance = 0.5 * (shared_covariance + shared_covariance.T)
            step.values.insert(key, gtsam.Pose3(reference_pose))
            step.keys.append(key)
            step.factors.add(
                gtsam.BetweenFactorPose3(
                    pose_key(reference),
                    key,
                    gtsam.Pose3(),
                    gtsam.noiseModel.Gaussian.Covariance(shared_covariance),
                )
            )
        else:
            return False
        self.stamps[reference] = step.stamp
        self.counts[reference] = self.counts.get(reference, 0) + 1
        inflation = float(self.counts[reference]) ** self.config.keyframe_count_inflation
        base = gtsam.noiseModel.Gaussian.Covariance(inflation * (1.0 - shared) * covariance)
        noise = robust(base, self.config.robust_kernel, self.config.robust_parameter)
        step.factors.add(
            gtsam.BetweenFactorPose3(key, pose_key(step.current), gtsam.Pose3(measured), noise)
        )
        return True
