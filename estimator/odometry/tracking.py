"""The tracking step: the frame's relative pose against the keyframe, combined with the chains
through other references, or when the keyframe is lost against the frames after it."""

from __future__ import annotations

from dataclasses import dataclass

from estimator.odometry.combination import ChainCombination
from estimator.odometry.estimation import PoseEstimation
from estimator.odometry.frames import CurrentFrame, Estimate, Reference
from estimator.odometry.observation import MeasurementKind
from estimator.odometry.references import References

__all__ = ["Tracking"]


@dataclass
class Tracking:
    """Relative pose against the keyframe; if that fails, against the previous good frame,
    and then against the last failed frame that had points (its pose coasted). An estimate
    far from the constant-velocity prediction counts as failed."""

    estimation: PoseEstimation
    references: References
    combination: ChainCombination

    def track(self, current: CurrentFrame) -> Estimate:
        """The ``current`` frame's estimate against one of the references (a keyframe is set)."""
        references = self.references
        keyframe, previous = references.reference, references.previous
        assert keyframe is not None and previous is not None
        previous_ns = current.timestamp_ns - previous.timestamp_ns
        prediction = references.predicted_reference_from(current.timestamp_ns)
        estimate = self.estimation.measured(
            keyframe, prediction, current, previous_ns,
            references.prediction_uncertainty(previous_ns),
        )  # fmt: skip
        if estimate.reference_from_current is None:
            return self._retried(estimate, keyframe, current)
        self.estimation.observe(MeasurementKind.KEYFRAME, estimate, current)
        return self.combination.combined(estimate, current)

    def _retried(self, estimate: Estimate, keyframe: Reference, current: CurrentFrame) -> Estimate:
        """The first estimate against the previous frame or the fallback that is not the
        keyframe and succeeds (predicted at constant velocity), or the keyframe's failed one."""
        references = self.references
        retries = ((references.previous, "the previous frame"),
                   (references.fallback, "the last frame with points"))  # fmt: skip
        for reference, name in retries:
            if reference is None or reference is keyframe:
                continue
            span_ns = current.timestamp_ns - reference.timestamp_ns
            retry = self.estimation.measured(
                reference, references.motion_over(span_ns), current, span_ns,
                references.prediction_uncertainty(span_ns),
            )  # fmt: skip
            if retry.reference_from_current is not None:
                retry.message = (
                    f"keyframe {keyframe.index} not tracked ({estimate.message}); "
                    f"tracked against {name}"
                )
                return retry
        return estimate
