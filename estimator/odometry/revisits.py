"""Keyframe revisits: when the camera comes back to where an older keyframe was, measure
against that keyframe again instead of starting a new one.

A chain of keyframes drifts with every new one: each carries its own measurement error and
all the errors before it. A hand-held, hovering or back-and-forth camera keeps returning to
places it has already seen; measured against the keyframe it made there, the frames after a
return carry only that keyframe's error, not the drift collected since (on the real MH_01
clip vision alone 4.46 -> 3.95 mm ATE; docs/frontend.md, "Keyframe revisits"). This is the
front end's choice of reference, not a loop closure: nothing before the return is changed.

When the references are about to take a new keyframe, the stored keyframes at least
``revisit_min_age_s`` old whose pose is within ``revisit_max_rotation_deg`` and
``revisit_max_translation_m`` of the new one are candidates; the nearest is measured against
(the prediction is the front end's own relative pose, which holds the drift, so the search
window is the wide one). With ``revisit_min_inlier_ratio`` x ``keyframe_min_inliers`` inliers
or more it becomes the reference again, else the new keyframe stays (and is stored once a
later one replaces it, having been measured against).
"""

from __future__ import annotations

from collections import deque

import numpy as np

from estimator.config import FrontendConfig
from estimator.geometry import invert_pose, rotation_angle_deg
from estimator.odometry.estimation import PoseEstimation
from estimator.odometry.frames import CurrentFrame, Estimate, Reference
from estimator.odometry.measurements import CameraFrames
from estimator.odometry.observation import MeasurementKind
from estimator.odometry.references import References

__all__ = ["KeyframeRevisits", "revisits_on"]

# How much larger than a keyframe's own translation threshold the distance to a revisited
# keyframe may be (the same fraction of the scene's depth as keyframes are apart, and some).
_TRANSLATION_RATIO = 1.2
# A revisit's rotation may differ from the front end's own relative pose by the drift since
# the stored keyframe (the 11 revisits on MH_01 vision alone: at most 0.044 deg and 2.1 mm);
# more is a wrong fit, not drift.
_MAX_DRIFT_DEG = 1.0


def revisits_on(frontend: FrontendConfig, imu_fused: bool) -> bool:
    """``frontend.revisit_keyframes``; unset, on when no IMU is fused and in detect mode.

    With the IMU the gain on MH_01 is small (3.80 -> 3.74 mm) and every stored keyframe keeps
    its image (0.36 MB on EuRoC) in memory; track mode pairs points by track id, which an
    older keyframe hardly shares.
    """
    configured = frontend.revisit_keyframes
    if configured is not None:
        return configured
    return not imu_fused and frontend.mode == "detect"


class KeyframeRevisits:
    """The keyframes a later frame may return to, and the switch back to one of them."""

    def __init__(
        self,
        frontend: FrontendConfig,
        estimation: PoseEstimation,
        references: References,
        frames: CameraFrames,
    ) -> None:
        self.frontend = frontend
        self.estimation = estimation
        self.references = references
        self.frames = frames
        self.stored: deque[Reference] = deque(maxlen=frontend.revisit_max_keyframes)
        self.count = 0  # revisits so far

    def after_update(
        self, current: CurrentFrame, replaced: Reference | None, estimate: Estimate
    ) -> None:
        """After the references took ``current`` as their new keyframe (replacing
        ``replaced``, which ``estimate`` measured it against): go back to a stored keyframe
        near it, or keep the new one."""
        keyframe = self.references.reference
        if keyframe is None or keyframe.index != current.index:
            return  # no new keyframe
        measured = estimate.reference_from_current is not None
        if replaced is not None and estimate.reference is replaced and measured:
            self._store(replaced)  # the back end holds its pose: it was measured against
        candidate = self._nearest(keyframe)
        if candidate is None:
            return
        revisit = self._measured(candidate, keyframe, current)
        if revisit is not None:
            self.references.go_back_to(candidate, revisit)
            self.count += 1

    def _store(self, keyframe: Reference) -> None:
        if not any(stored is keyframe for stored in self.stored):
            self.stored.append(keyframe)

    def _nearest(self, keyframe: Reference) -> Reference | None:
        """The stored keyframe nearest to ``keyframe`` within the limits, old enough."""
        frontend = self.frontend
        max_translation = frontend.revisit_max_translation_m
        if max_translation is None:
            max_translation = _TRANSLATION_RATIO * self.references.keyframe_translation_m()
        min_age_ns = frontend.revisit_min_age_s * 1e9
        best, best_distance = None, np.inf
        for stored in self.stored:
            if keyframe.timestamp_ns - stored.timestamp_ns < min_age_ns:
                continue
            relative = invert_pose(stored.pose) @ keyframe.pose
            rotation = rotation_angle_deg(relative[:3, :3]) / frontend.revisit_max_rotation_deg
            translation = float(np.linalg.norm(relative[:3, 3])) / max_translation
            distance = rotation + translation
            if rotation < 1 and translation < 1 and distance < best_distance:
                best, best_distance = stored, distance
        return best

    def _measured(
        self, stored: Reference, keyframe: Reference, current: CurrentFrame
    ) -> Estimate | None:
        """The current frame against ``stored``, when it has enough inliers."""
        prediction = self.frames.in_rectified(invert_pose(stored.pose) @ keyframe.pose)
        estimate = self.estimation.against(stored, prediction, current)
        self.estimation.observe(MeasurementKind.REVISIT, estimate, current)
        measured = estimate.reference_from_current
        if measured is None or estimate.result is None:
            return None
        if rotation_angle_deg(prediction[:3, :3].T @ measured[:3, :3]) > _MAX_DRIFT_DEG:
            return None
        needed = self.frontend.revisit_min_inlier_ratio * self.frontend.keyframe_min_inliers
        return estimate if estimate.result.inliers.sum() >= needed else None
