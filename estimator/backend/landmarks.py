"""Stereo landmarks in the smoother's window: the inlier points as variables.

A relative pose from the front end summarises its inliers in one 6x6 covariance; the frames
that see the same points are then tied only pairwise. Here each accepted measurement's inliers
(at most ``landmark_max_per_frame``, spread over the image) become 3D points ``l<n>`` in the
world, observed by both frames as rectified stereo pixels (u_left, u_right, v) through
``GenericStereoFactor3D`` with the rig's ``Cal3_S2Stereo`` and the camera's place on the body.

A landmark is named by the frame point it was made from, and keeps its name in the frames that
see it again: the point a frame matched to a landmark names that landmark when the frame
becomes the reference (a keyframe) of later ones, so a point tracked across keyframes is one
variable. Its smoother stamp is the newest frame that observed it (restamped by each new
observation), so it leaves the fixed-lag window with the last of its frames, and only
landmarks still in the window receive new observations.

Noise: the session's measured pixel noise (``frontend/stereo_noise.py``: sigma of u, v and
disparity, per point) with u_right = u_left - d, so u_left and u_right share the column's
noise; real residuals have heavy tails, hence a Huber kernel.
"""

from __future__ import annotations

import gtsam
import numpy as np

from estimator.backend.observations import StereoObservations
from estimator.backend.smoother import STAMP_MARGIN_S, pose_key
from estimator.backend.step import Step
from estimator.config import BackendConfig
from estimator.geometry import transform_points

__all__ = ["LandmarkMap", "landmark_key", "spread_order", "stereo_covariance"]

_GRID = (8, 6)  # cells (columns, rows) the image is split into to spread the landmarks


def landmark_key(number: int) -> int:
    return gtsam.symbol("l", number)


def stereo_covariance(sigma_u: float, sigma_v: float, sigma_d: float) -> np.ndarray:
    """Covariance of (u_left, u_right, v) for independent u, v and disparity noise."""
    var_u, var_d = sigma_u**2, sigma_d**2
    return np.array([[var_u, var_u, 0.0], [var_u, var_u + var_d, 0.0], [0.0, 0.0, sigma_v**2]])


def spread_order(pixels: np.ndarray) -> np.ndarray:
    """Indices of stereo ``pixels`` (N, 3) in round-robin order over a grid of the image, the
    nearest point (largest disparity) of each cell first: any prefix is spread out."""
    if len(pixels) == 0:
        return np.zeros(0, dtype=np.intp)
    columns, rows = _GRID
    low, high = pixels[:, [0, 2]].min(axis=0), pixels[:, [0, 2]].max(axis=0)
    scaled = (pixels[:, [0, 2]] - low) / np.maximum(high - low, 1e-9)
    column = np.clip((scaled[:, 0] * columns).astype(int), 0, columns - 1)
    row = np.clip((scaled[:, 1] * rows).astype(int), 0, rows - 1)
    cell = row * columns + column
    order = np.lexsort((-(pixels[:, 0] - pixels[:, 1]), cell))
    sorted_cells = cell[order]
    first = np.searchsorted(sorted_cells, sorted_cells, side="left")
    rank = np.arange(len(order)) - first
    return order[np.argsort(rank, kind="stable")]


class LandmarkMap:
    """The landmarks in the window, the frame points that name them, and their stamps."""

    def __init__(self, config: BackendConfig, body_from_camera: np.ndarray) -> None:
        self.config = config
        self.body_from_camera = body_from_camera
        self._next = 0
        self._by_point: dict[tuple[int, int], int] = {}  # (frame ns, point index) -> landmark
        self._stamps: dict[int, float] = {}  # landmark -> smoother stamp of its key

    def __len__(self) -> int:
        return len(self._stamps)

    def reset(self) -> None:
        """Forget every landmark (the smoother restarted empty)."""
        self._by_point.clear()
        self._stamps.clear()

    def forget_before(self, cutoff: float) -> None:
        """Drop the landmarks the smoother marginalises in an update with ``cutoff``."""
        leaving = {n for n, stamp in self._stamps.items() if stamp <= cutoff + STAMP_MARGIN_S}
        if not leaving:
            return
        for number in leaving:
            del self._stamps[number]
        self._by_point = {p: n for p, n in self._by_point.items() if n not in leaving}

    def add(
        self,
        step: Step,
        observations: StereoObservations,
        reference: int,
        reference_pose: np.ndarray | None,
        timestamp_ns: int,
    ) -> int:
        """Stereo factors of one accepted measurement into ``step``; returns how many landmarks
        this frame observes. ``reference_pose`` (body in world) is None when the reference
        frame has left the window: then only landmarks still in it are observed."""
        self.forget_before(step.cutoff)
        known = np.array(
            [
                self._by_point.get((observations.reference_ns, int(i)), -1)
                for i in observations.reference_ids
            ],
            dtype=np.int64,
        )
        chosen = self._choose(observations, known, reference_pose is not None)
        if not len(chosen):
            return 0
        camera = observations.camera
        calibration = gtsam.Cal3_S2Stereo(
            camera.fx, camera.fx, 0.0, camera.cx, camera.cy, camera.baseline
        )
        body_from_rect = self.body_from_camera @ camera.camera_from_rect
        sensor = gtsam.Pose3(body_from_rect)
        sigmas = np.asarray(observations.sigmas_px) * self.config.landmark_noise_scale
        covariance = stereo_covariance(*sigmas)
        huber = gtsam.noiseModel.mEstimator.Huber.Create(self.config.landmark_huber)
        scales = (
            observations.flow_scale()
            if self.config.landmark_flow_noise
            else np.ones(len(observations))
        )

        def observe(frame: int, pixel: np.ndarray, number: int, scale: float) -> None:
            base = gtsam.noiseModel.Gaussian.Covariance(covariance * scale**2)
            noise = gtsam.noiseModel.Robust.Create(huber, base)
            measured = gtsam.StereoPoint2(*(float(value) for value in pixel))
            step.factors.add(
                gtsam.GenericStereoFactor3D(
                    measured, noise, pose_key(frame), landmark_key(number), calibration, sensor
                )
            )

        world = None
        if reference_pose is not None:
            world = transform_points(reference_pose @ body_from_rect, observations.reference_points)
        for i in chosen:
            number = int(known[i])
            if number < 0:
                assert world is not None  # new landmarks only while the reference is in
                number = self._new(step, world[i])
                self._by_point[(observations.reference_ns, int(observations.reference_ids[i]))] = (
                    number
                )
                observe(reference, observations.reference_pixels[i], number, 1.0)
            else:
                step.keep.append(landmark_key(number))
            self._stamps[number] = step.stamp
            if self.config.landmark_across_keyframes:
                self._by_point[(timestamp_ns, int(observations.current_ids[i]))] = number
            observe(step.current, observations.current_pixels[i], number, float(scales[i]))
        return len(chosen)

    def _choose(
        self, observations: StereoObservations, known: np.ndarray, may_create: bool
    ) -> np.ndarray:
        """The inliers to observe: every landmark already in the window (they tie this frame to
        the earlier ones), then new ones spread over the image, up to the per-frame limit."""
        limit = self.config.landmark_max_per_frame
        distinct = np.zeros(len(known), dtype=bool)  # one observation per current point
        distinct[np.unique(observations.current_ids, return_index=True)[1]] = True
        old = np.flatnonzero((known >= 0) & distinct)
        old = old[np.unique(known[old], return_index=True)[1]]  # and per landmark
        old = old[spread_order(observations.current_pixels[old])][:limit]
        if not may_create or len(old) >= limit:
            return old
        new = np.flatnonzero((known < 0) & distinct)
        new = new[spread_order(observations.reference_pixels[new])][: limit - len(old)]
        return np.concatenate([old, new])

    def _new(self, step: Step, point: np.ndarray) -> int:
        number = self._next
        self._next += 1
        step.values.insert(landmark_key(number), gtsam.Point3(*point))
        step.keys.append(landmark_key(number))
        return number
