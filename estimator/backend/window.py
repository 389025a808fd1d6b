"""The frames the back end still holds: the smoother's open frames, whose final estimate is
handed out once when they leave the window, and the frames a keyframe measurement may still
refer to (with their latest pose, also after they have left the smoother)."""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np

from estimator.backend.imu import SpecificForceDelta
from estimator.backend.smoother import STAMP_MARGIN_S, Smoother
from estimator.config import MAX_REVISIT_KEYFRAMES

__all__ = ["FrameWindow", "OpenFrame"]

# Frames measured against, kept after a newer one is in use: a front end that revisits a
# place measures against its keyframes again (frontend.revisit_keyframes). Frames measured
# against that were no keyframe (the previous frame after a failed one) count too, hence
# a few times the keyframes a front end keeps.
_KEPT_KEYFRAMES = 4 * MAX_REVISIT_KEYFRAMES


@dataclass
class OpenFrame:
    """A frame the smoother still holds: what is needed to finish it."""

    index: int
    timestamp_ns: int
    stamp_s: float  # smoother time of its keys
    delta: SpecificForceDelta | None  # accelerometer over the interval ending here
    body_pose: np.ndarray = field(default_factory=lambda: np.eye(4))  # latest estimate


class FrameWindow:
    """Open frames (oldest first), the final poses not yet handed out, and the references."""

    def __init__(self, smoother: Smoother, body_from_camera: np.ndarray) -> None:
        self.smoother = smoother
        self.body_from_camera = body_from_camera
        self.open: OrderedDict[int, OpenFrame] = OrderedDict()
        self._final_poses: list[tuple[int, np.ndarray]] = []
        # Frames that may still be referenced by a keyframe measurement: stamp -> (index,
        # latest body pose estimate), the pose for references that have left the window.
        self.references: OrderedDict[int, tuple[int, np.ndarray]] = OrderedDict()
        self.oldest_reference = 0
        # Frames measured against before (stamp -> (index, latest body pose)), kept when
        # newer references are in use: a revisit measures against them again.
        self.keyframes: OrderedDict[int, tuple[int, np.ndarray]] = OrderedDict()

    def take_final_poses(self) -> tuple[tuple[int, np.ndarray], ...]:
        """The final poses gathered since the last call (each frame once)."""
        final_poses, self._final_poses = tuple(self._final_poses), []
        return final_poses

    def finish_before(self, stamp_s: float, read: bool = True) -> None:
        """Finish the frames stamped before ``stamp_s`` (the smoother is about to drop them).

        Their estimate is read one last time (``read=False``: the last one read, after a
        numerical failure) and handed out as final.
        """
        while self.open:
            frame = next(iter(self.open.values()))
            if frame.stamp_s >= stamp_s:
                break
            del self.open[frame.index]
            if read:
                try:
                    frame.body_pose = self.smoother.pose(frame.index)
                except (IndexError, RuntimeError):  # GTSAM: unknown key / numerical failure
                    pass  # keep the latest estimate read
            self._final_poses.append((frame.timestamp_ns, frame.body_pose @ self.body_from_camera))
            if frame.timestamp_ns in self.keyframes:
                self.keyframes[frame.timestamp_ns] = (frame.index, frame.body_pose)

    def in_window(self, index: int, cutoff: float) -> bool:
        """Whether frame ``index`` has a variable that survives an update dropping the keys
        stamped before ``cutoff`` (the same comparison GTSAM makes, with a small margin).

        A reference that would be marginalised is not kept alive by restamping it: with its
        neighbours already gone, GTSAM's fixed-lag smoother fails to marginalise it later
        ("remove variables ... that are not unused"); such a measurement is chained through
        the previous frame instead.
        """
        if not self.smoother.fixed_lag:
            return self.smoother.has_pose(index)
        frame = self.open.get(index)
        return (
            frame is not None
            and frame.stamp_s > cutoff + STAMP_MARGIN_S
            and self.smoother.has_pose(index)
        )

    def remember(self, timestamp_ns: int, index: int, body_pose: np.ndarray) -> None:
        """Keep the pose of frames that may still be referenced: none older than the latest
        reference, since a front end's references only move forward."""
        self.references[timestamp_ns] = (index, body_pose)
        while self.references and next(iter(self.references.values()))[0] < self.oldest_reference:
            self.references.popitem(last=False)

    def used_as_reference(self, reference_ns: int) -> None:
        """Keep the pose of frame ``reference_ns`` (measured against) for later revisits."""
        frame = self.references.get(int(reference_ns))
        if frame is None or int(reference_ns) in self.keyframes:
            return
        self.keyframes[int(reference_ns)] = frame
        while len(self.keyframes) > _KEPT_KEYFRAMES:
            self.keyframes.popitem(last=False)

    def kept_indices(self) -> set[int]:
        """Indices of the kept keyframes (their reported covariances stay too)."""
        return {index for index, _ in self.keyframes.values()}

    def reference_index(self, reference_ns: int | None, latest: int) -> int | None:
        """Frame index of ``reference_ns`` (None: ``latest``, the previous frame; unknown:
        None)."""
        if reference_ns is None:
            return latest
        frame = self._referable(int(reference_ns))
        return None if frame is None else frame[0]

    def reference_pose(self, reference_ns: int) -> np.ndarray:
        """The latest body pose of a frame that may be referenced."""
        frame = self._referable(int(reference_ns))
        assert frame is not None, reference_ns
        return frame[1]

    def _referable(self, reference_ns: int) -> tuple[int, np.ndarray] | None:
        """(index, latest body pose) of a recent frame or a kept keyframe; None: unknown."""
        return self.references.get(reference_ns) or self.keyframes.get(reference_ns)
