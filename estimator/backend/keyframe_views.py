"""Measurements against one keyframe share an error: a view variable per keyframe carries it.

The front end measures frame j against keyframe K from K's stereo points. Their triangulation
errors are the same for every frame measured against K, so the measurement errors are
strongly correlated (on the real MH_01 clip the lag-1 correlation of consecutive errors
against the same keyframe is about 0.87, ``swarmvo bench consistency``). Independent
factors K -> j would count that shared error once per frame: a graph tying the frames
together with the IMU then believes K -> j to a fraction of what it knows, and its reported
covariances are too small.

Model: T_Kj measured = Exp(s) T_Kj Exp(u_j) with s (left, at K) shared by all frames measured
against K and u_j (right, at j) independent; the measurement's covariance C_j is split into
``shared`` C_j for s and (1 - ``shared``) C_j for u_j. The view V_K = X_K Exp(s) is a variable
of its own: ``Between(X_K, V_K, I)`` with covariance ``shared`` Ad(T) C_j Ad(T)^T (the right
perturbation at j moved to a left one at K) from the first measurement, and
``Between(V_K, X_j, T_Kj)`` with (1 - ``shared``) C_j for each measurement. One measurement
alone gets exactly its covariance C_j back.

The view stays in the smoother while measurements refer to it (its key is restamped with each
use), also after X_K itself has been marginalised: the frames keep their tie to the keyframe
and its uncertainty, instead of a pose prior from its last estimate that drops both. A view not
used for a lag is marginalised like any frame.
"""

from __future__ import annotations

import gtsam
import numpy as np

from estimator.backend.noise import robust
from estimator.backend.smoother import STAMP_MARGIN_S, Smoother, pose_key
from estimator.backend.step import Step
from estimator.config import BackendConfig

__all__ = ["KeyframeViews", "view_key"]


def view_key(index: int) -> int:
    return gtsam.symbol("r", index)


class KeyframeViews:
    """The views of the keyframes measured against lately (see module doc)."""

    def __init__(self, smoother: Smoother, config: BackendConfig) -> None:
        self.smoother = smoother
        self.config = config
        self.stamps: dict[int, float] = {}  # keyframe index -> smoother stamp of its view

    def reset(self) -> None:
        self.stamps.clear()

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
        key = view_key(reference)
        shared = self.config.keyframe_shared_error
        if reference in self.stamps and self.smoother.isam().valueExists(key):
            step.keep.append(key)
        elif live and reference_pose is not None:
            adjoint = np.asarray(gtsam.Pose3(measured).AdjointMap())
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
        base = gtsam.noiseModel.Gaussian.Covariance((1.0 - shared) * covariance)
        noise = robust(base, self.config.robust_kernel, self.config.robust_parameter)
        step.factors.add(
            gtsam.BetweenFactorPose3(key, pose_key(step.current), gtsam.Pose3(measured), noise)
        )
        return True
