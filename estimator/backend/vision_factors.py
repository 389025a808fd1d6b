"""The front end's relative pose in the factor graph: gated, then added as a factor.

A measurement is taken against a keyframe (its reference). While the reference is in the
smoother's window it ties the two frames directly; once it has left, ``old_reference`` decides
how it still counts: as a prior placing the frame in the world, chained through the last frame
with accepted vision, or through the keyframe's view (``keyframe_views.py``). Before any of
that the outlier gate (``gating.py``) compares it with the IMU's or the motion prior's
prediction, and with ``landmarks`` on its inliers join the graph as stereo landmarks
(``landmarks.py``).
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from estimator.backend.gating import agrees_with_standstill, gate_distance
from estimator.backend.keyframe_views import KeyframeViews
from estimator.backend.landmarks import LandmarkMap
from estimator.backend.noise import robust
from estimator.backend.observations import StereoObservations
from estimator.backend.placement_covariance import PlacementCovariance
from estimator.backend.smoother import Smoother, pose_key
from estimator.backend.step import Step
from estimator.backend.window import FrameWindow
from estimator.config import BackendConfig
from estimator.geometry import invert_pose, nearest_rigid

__all__ = ["PreviousFrame", "VisionFactors"]

# Fewer landmarks than this in a frame: the relative pose is added even without
# ``landmark_between`` (a few points tie a frame too loosely on their own).
_MIN_LANDMARKS = 20


@dataclass(frozen=True)
class PreviousFrame:
    """The frame before the new one, as the back end holds it when the measurement arrives."""

    body_pose: np.ndarray  # body in world, its estimate
    timestamp_ns: int
    motion: np.ndarray | None  # body T_k-2,k-1 (estimated), None before the second frame
    dt: float  # s, between those two frames


class VisionFactors:
    """Adds each frame's relative pose to the step's factors (see module doc)."""

    def __init__(
        self,
        config: BackendConfig,
        body_from_camera: np.ndarray,
        smoother: Smoother,
        window: FrameWindow,
    ) -> None:
        self._config = config
        self.body_from_camera = body_from_camera
        self.camera_from_body = invert_pose(body_from_camera)
        self._smoother = smoother
        self._window = window
        self._landmarks = LandmarkMap(config, body_from_camera) if config.landmarks else None
        self._views = KeyframeViews(smoother, config)
        # What a placement prior drops from the frame's covariance, added back when reported.
        self.placement = PlacementCovariance()
        # The newest frame with accepted vision (or the first): its time widens the gate after
        # a gap, and a measurement whose reference has left the window is chained through it.
        self.last_fix_index = 0
        self.last_fix_ns = 0

    @property
    def landmark_count(self) -> int:
        """Stereo landmarks in the window (0 without ``config.landmarks``)."""
        return len(self._landmarks) if self._landmarks is not None else 0

    def reset(self) -> None:
        """Forget the landmarks and keyframe views of a smoother that starts afresh; the
        placement covariance carries on from the newest report."""
        if self._landmarks is not None:
            self._landmarks.reset()
        self._views.reset()
        self.placement.anchor()

    def add(
        self,
        step: Step,
        previous: PreviousFrame,
        relative_pose: np.ndarray | None,
        covariance: np.ndarray | None,
        reference_ns: int | None,
        prediction: np.ndarray,
        stereo: StereoObservations | None = None,
    ) -> np.ndarray:
        """The front-end relative pose as a robust factor unless the gate rejects it.

        ``previous`` is the frame before this one as the back end holds it. Returns the
        initial guess of the body motion (the measurement when accepted, else the prediction);
        clears ``step.still`` when vision disagrees with a standstill.
        """
        reference = self._vision_reference(step, relative_pose, covariance, reference_ns)
        if reference is None:
            return prediction
        assert relative_pose is not None and covariance is not None
        body_measured = nearest_rigid(self.body_from_camera @ relative_pose @ self.camera_from_body)
        live = reference == step.previous or self._window.in_window(reference, step.cutoff)
        reference_pose = None
        if reference != step.previous:
            reference_pose = (
                self._smoother.pose(reference)
                if live
                else self._window.reference_pose(int(reference_ns))  # type: ignore[arg-type]
            )
        body_motion = _motion_from_previous(previous.body_pose, body_measured, reference_pose)
        if step.still:  # vision must agree with the standstill too
            step.still = agrees_with_standstill(body_motion, covariance)
        if not self._passes_gate(step, previous, body_motion, prediction, covariance):
            return prediction
        step.accepted = True
        observed = 0
        if self._landmarks is not None and stereo is not None and len(stereo):
            reference_body = previous.body_pose if reference == step.previous else reference_pose
            observed = self._landmarks.add(
                step, stereo, reference, reference_body if live else None, step.timestamp_ns
            )
        if self._config.landmark_between or observed < _MIN_LANDMARKS:
            self._add_accepted(
                step, previous, reference, reference_pose, live, body_measured, body_motion,
                covariance,
            )
        self._window.oldest_reference = max(self._window.oldest_reference, reference)
        if reference_ns is not None:
            self._window.used_as_reference(int(reference_ns))
        return body_motion

    def _vision_reference(
        self,
        step: Step,
        relative_pose: np.ndarray | None,
        covariance: np.ndarray | None,
        reference_ns: int | None,
    ) -> int | None:
        """Index of the frame the measurement was taken against; None (with a note when a
        measurement is lost) when there is nothing usable to add."""
        if relative_pose is None or covariance is None:
            return None
        reference = self._window.reference_index(reference_ns, step.previous)
        if reference is None:
            step.notes.append(
                f"relative pose not used (reference frame {reference_ns} is unknown or "
                "older than the latest reference)"
            )
        return reference

    def _passes_gate(
        self,
        step: Step,
        previous: PreviousFrame,
        body_motion: np.ndarray,
        prediction: np.ndarray,
        covariance: np.ndarray,
    ) -> bool:
        """The outlier gate: a measurement too far from the prediction is noted and dropped,
        so one bad front-end frame cannot pull the graph."""
        distance = gate_distance(
            body_motion,
            prediction,
            covariance,
            step.preintegration,
            step.dt,
            (previous.timestamp_ns - self.last_fix_ns) * 1e-9,
            previous.motion,
            previous.dt,
            self._config,
        )
        gate = self._config.outlier_gate_chi2
        if gate is None or distance <= gate:
            return True
        step.notes.append(
            f"relative pose rejected (squared Mahalanobis distance {distance:.0f} "
            f"> {gate:g} from the prediction)"
        )
        step.rejected = True
        return False

    def _add_accepted(
        self,
        step: Step,
        previous_frame: PreviousFrame,
        reference: int,
        reference_pose: np.ndarray | None,
        live: bool,
        body_measured: np.ndarray,
        body_motion: np.ndarray,
        covariance: np.ndarray,
    ) -> None:
        """The factor for an accepted measurement: between the reference and this frame while
        the reference is in the window, else a prior or a chain (``old_reference``); with
        ``"views"`` through the keyframe's view (``keyframe_views.py``) while it has one."""
        previous = step.previous
        mode = self._config.old_reference
        if mode == "views" and reference != previous:
            if self._views.add(step, reference, live, reference_pose, body_measured, covariance):
                return
            live = False  # neither the keyframe nor its view is left: as "prior-after-gap"
        base = gtsam.noiseModel.Gaussian.Covariance(covariance)
        noise = robust(base, self._config.robust_kernel, self._config.robust_parameter)
        after_gap = self.last_fix_index != previous
        placing = mode == "prior" or (mode in ("prior-after-gap", "views") and after_gap)
        if not live and placing:
            # The reference has left the window: its estimate and the measurement place this
            # frame in the world directly (as the front end's chain does), instead of through
            # recent frames whose estimates the smoother still moves (after a gap, frames
            # carried by the IMU alone).
            placed = reference_pose @ body_measured  # type: ignore[operator]
            self.placement.place(reference, body_measured, covariance)
            step.factors.add(
                gtsam.PriorFactorPose3(pose_key(step.current), gtsam.Pose3(placed), noise)
            )
            return
        source, measured = (reference, body_measured) if live else (previous, body_motion)
        if not live and after_gap:
            source, measured = self._chained(step, previous_frame, measured, body_motion)
        step.factors.add(
            gtsam.BetweenFactorPose3(
                pose_key(source),
                pose_key(step.current),
                gtsam.Pose3(measured),
                noise,
            )
        )

    def _chained(
        self, step: Step, previous: PreviousFrame, measured: np.ndarray, body_motion: np.ndarray
    ) -> tuple[int, np.ndarray]:
        """Source frame and relative pose for a measurement whose reference has left the
        window, after frames without vision: chained through the last frame with accepted
        vision while it is in the window, not through the previous (coasted) frame, whose
        IMU-only estimate would otherwise carry its error into every frame after the gap."""
        anchor = self.last_fix_index
        if not self._window.in_window(anchor, step.cutoff):
            return step.previous, measured
        # body_motion is T_prev_cur through the current estimates: T_anchor_cur follows.
        anchor_from_previous = invert_pose(self._smoother.pose(anchor)) @ previous.body_pose
        return anchor, nearest_rigid(anchor_from_previous @ body_motion)


def _motion_from_previous(
    previous_pose: np.ndarray, body_measured: np.ndarray, reference_pose: np.ndarray | None
) -> np.ndarray:
    """The measurement seen as a motion from the previous frame, through the current
    estimates: for the gate and the initial guess (and as the factor itself when the
    reference has already left the window). ``reference_pose`` is None when the
    reference is the previous frame."""
    if reference_pose is None:
        return body_measured
    return nearest_rigid(invert_pose(previous_pose) @ reference_pose @ body_measured)
