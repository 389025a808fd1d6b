"""The stereo odometry pipeline: one stereo frame in, one pose report out.

Per frame: rectify -> detect -> match stereo -> triangulate -> match in time -> estimate the
relative pose by rigid 3D-3D registration (optionally refined on its inliers with the full
stereo point covariances, ``registration.mahalanobis_refine``) -> chain it onto the reference
pose -> fuse with the IMU in the back end. Frames are matched against a *reference*: by default
a keyframe that is kept while the view still overlaps well, so that standing still (or hovering)
measures the same relative pose again and again instead of integrating frame-to-frame noise into
a creeping drift; ``frontend.tracking = "frame"`` matches against the previous frame instead.
Vision alone, a frame that would become a new keyframe where an older keyframe was is measured
against that one instead, which is the reference again (keyframe revisits).

Geometry runs in the rectified left camera frame; reported poses are of the original
(unrectified) left camera, so the relative pose is conjugated by the rectifying rotation.
When the keyframe cannot be tracked the previous frame is tried before giving up. A frame
without any estimate coasts at the last measured velocity (``degraded``) for at most
``frontend.max_coast_s`` since the last estimate, after which the pose is held (``lost``). An
estimate that is implausible (its rotation far from the constant-velocity prediction) or that
the back end's gate rejects counts as none: it neither updates the noise model nor becomes a
reference, so one wrong fit cannot spoil the frames after it. While it coasts, the next frame
is matched against the last good references at once (predictions scale with the time between
frames); once the pose is held, a frame with enough points becomes the new reference, so
tracking restarts from it. With the back end enabled, the fused pose and status are the back
end's (it bridges such frames with the IMU).

Modules, one job each:

- ``core``: :class:`Odometry`, whose ``process`` reads as the steps above.
- ``frames``: input images and seeds, and the per-frame records (current frame, reference,
  estimate).
- ``tracking``: the track step: against the keyframe, or the retries when it is lost.
- ``estimation``: the estimate + refine step, its plausibility check and the noise update.
- ``combination``: the keyframe measurement combined with the chains through the previous
  frame and the keyframe before (``chains``: the combination's math).
- ``references``: the reference (keyframe) policy and the measured motion that predicts.
- ``revisits``: the older keyframes a returning camera is measured against again.
- ``measurements``: a rectified estimate as the back end and the reports take it.
- ``fusion_step``: the fuse step: the frame handed to the back end, its answer in the world.
- ``gyro_prediction``: the gyro's rotation that centres the search windows.
- ``observation``: the measurements of a frame as an optional observer sees them
  (evaluations, benchmarks).
"""

from estimator.odometry.core import Odometry
from estimator.odometry.frames import frame_seed, to_grey8
from estimator.odometry.observation import (
    MeasurementKind,
    MeasurementObserver,
    ObservedMeasurement,
)

__all__ = [
    "MeasurementKind",
    "MeasurementObserver",
    "ObservedMeasurement",
    "Odometry",
    "frame_seed",
    "to_grey8",
]
