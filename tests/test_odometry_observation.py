"""The odometry's observer sees each measurement of a frame as it is made, and changes nothing."""

from __future__ import annotations

import numpy as np
from test_odometry import _config, _rendered_flight, _rendered_rig, _run

from estimator.odometry import MeasurementKind, ObservedMeasurement, Odometry
from estimator.odometry.measurements import CameraFrames


def _observed_run(**frontend) -> tuple[list, list, list[ObservedMeasurement]]:
    """The rendered flight vision alone, without and with an observer."""
    frames, _ = _rendered_flight()
    config = _config(backend={"enabled": False}, frontend=frontend)
    plain = _run(Odometry(_rendered_rig(), config), frames)
    seen: list[ObservedMeasurement] = []
    observed = _run(Odometry(_rendered_rig(), config, observer=seen.append), frames)
    return plain, observed, seen


def test_an_observer_changes_no_pose_and_no_covariance() -> None:
    plain, observed, seen = _observed_run()
    # The flight never returns to an older keyframe (revisits: tests/test_revisits.py).
    assert {m.kind for m in seen} == set(MeasurementKind) - {MeasurementKind.REVISIT}
    for first, second in zip(plain, observed, strict=True):
        np.testing.assert_array_equal(first.pose, second.pose)
        np.testing.assert_array_equal(first.relative_pose, second.relative_pose)
        if first.measurement_covariance is None:
            assert second.measurement_covariance is None
        else:
            np.testing.assert_array_equal(
                first.measurement_covariance, second.measurement_covariance
            )


def test_the_keyframe_measurement_and_the_links_are_seen_before_they_are_combined() -> None:
    """Each frame's keyframe measurement is one of its registrations as it came out; a link
    goes from an earlier frame that is not the keyframe. A frame's pose is its keyframe
    measurement's exactly when no link was combined with it, and differs when one was."""
    _, reports, seen = _observed_run()
    by_index = {report.index: report for report in reports}
    registrations = [m for m in seen if m.kind is MeasurementKind.REGISTRATION]
    keyframes = [m for m in seen if m.kind is MeasurementKind.KEYFRAME]
    linked = {m.index: m for m in seen if m.kind is MeasurementKind.LINK}
    assert len(keyframes) >= 10 and len(linked) >= 5
    for measured in keyframes:
        (same,) = [
            r
            for r in registrations
            if r.index == measured.index and r.reference is measured.reference
        ]
        np.testing.assert_array_equal(same.reference_from_current, measured.reference_from_current)
        np.testing.assert_array_equal(same.covariance, measured.covariance)
        report = by_index[measured.index]
        assert report.reference_timestamp_ns == measured.reference.timestamp_ns
        alone = measured.reference.pose @ measured.camera_reference_from_current
        link = linked.get(measured.index)
        assert np.array_equal(report.frontend_pose, alone) is (link is None)
        if link is not None:
            assert link.reference is not measured.reference
            assert link.reference.index < link.index


def test_an_observed_measurement_carries_its_pose_in_both_frames_and_its_inliers_motion() -> None:
    rig = _rendered_rig()
    _, _, seen = _observed_run()
    frames = CameraFrames(rig.rectification.R_left)
    for measured in seen:
        if measured.reference_from_current is None:
            assert measured.camera_reference_from_current is None
            continue
        np.testing.assert_allclose(
            measured.camera_reference_from_current,
            frames.in_camera(measured.reference_from_current),
        )
        assert measured.inliers is not None
        assert len(measured.inlier_flow_px) == int(measured.inliers.sum())
        assert measured.gate_chi2 > 0


def test_without_the_chain_no_link_is_seen() -> None:
    _, _, seen = _observed_run(fuse_previous_frame=False)
    kinds = [m.kind for m in seen]
    assert MeasurementKind.KEYFRAME in kinds and MeasurementKind.LINK not in kinds
