"""The Odometry pipeline: real standstill, rendered motion with exact truth, and bad input."""

from __future__ import annotations

import dataclasses
import json
from functools import cache
from itertools import pairwise
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from estimator.backend.recording import BackendFrame, BackendInput
from estimator.config import SwarmvoConfig
from estimator.evaluation.metrics import camera_ground_truth, eq20_errors, relative_to_first
from estimator.formats.calibration import StereoRig
from estimator.formats.datasets import open_sequence
from estimator.frontend.temporal import Correspondences
from estimator.geometry import (
    invert_pose,
    make_pose,
    quat_to_matrix,
    rotation_angle_deg,
    rotation_vector_to_quat,
    scale_motion,
)
from estimator.odometry import Odometry, frame_seed, to_grey8
from estimator.odometry.combination import ChainCombination, measurement_bias
from estimator.odometry.frames import Estimate
from estimator.odometry.observation import MeasurementKind, ObservedMeasurement
from estimator.registration.result import RegistrationResult
from estimator.rendered.camera import CAMERA, T_BS_CAM0
from estimator.rendered.trajectory import loop_for_length
from estimator.rendered.world import build_world
from estimator.rig_settings import apply_rig_settings
from estimator.types import FrameStatus, ImuNoise, StereoFrame

FRAME_NS = 50_000_000  # 20 Hz


def _config(**sections) -> SwarmvoConfig:
    return SwarmvoConfig.model_validate(sections)


# ----------------------------------------------------------------------------- rendered rig

# A right camera that is slightly rotated and offset: rectification is not the identity, so the
# conversion between the rectified and the original left camera frame is exercised.
_RIGHT_ROTATION = quat_to_matrix(rotation_vector_to_quat(np.radians([0.6, -0.8, 0.5])))
T_LEFT_RIGHT = make_pose(_RIGHT_ROTATION, [CAMERA["baseline"], 0.004, -0.003])


def _rendered_rig() -> StereoRig:
    camera = {
        "width": CAMERA["width"], "height": CAMERA["height"], "fx": CAMERA["f"],
        "fy": CAMERA["f"], "cx": CAMERA["cx"], "cy": CAMERA["cy"],
        "distortion_model": "none", "distortion": [],
    }  # fmt: skip
    return StereoRig.from_dict(
        {
            "left": {**camera, "T_BS": T_BS_CAM0.tolist()},
            "right": {**camera, "T_BS": (T_BS_CAM0 @ T_LEFT_RIGHT).tolist()},
        }
    )


@cache
def _rendered_flight(frames: int = 16, length_m: float = 1.5):
    """Raw (unrectified) stereo frames along a loop flight and the true left-camera poses."""
    duration = (frames - 1) * FRAME_NS * 1e-9
    trajectory = loop_for_length(length_m, duration)
    world = build_world(trajectory, np.random.default_rng(0), px_per_m=96.0)
    times = np.arange(frames) * FRAME_NS * 1e-9
    cameras = trajectory.state(times).poses() @ T_BS_CAM0
    stereo_frames = []
    for index, left_pose in enumerate(cameras):
        left, _ = world.render(left_pose)
        right, _ = world.render(left_pose @ T_LEFT_RIGHT)
        stereo_frames.append(StereoFrame(1_000 + index * FRAME_NS, left, right))
    return stereo_frames, cameras


def _run(odometry: Odometry, frames) -> list:
    return [odometry.process(frame) for frame in frames]


@pytest.mark.slow
@pytest.mark.parametrize(
    ("tracking", "method"),
    [("keyframe", "msac"), ("frame", "msac"), ("keyframe", "pso-robust"), ("frame", "pso-robust")],
)
def test_rendered_flight_is_tracked(tracking: str, method: str) -> None:
    frames, truth = _rendered_flight()
    # MSAC isolates the front end and the chaining from the swarm estimator; pso-robust (with
    # the per-pair stereo noise handed to it) must track the same flight as well.
    config = _config(
        backend={"enabled": False}, frontend={"tracking": tracking}, registration={"method": method}
    )
    rig = _rendered_rig()
    assert not rig.rectification.is_identity
    reports = _run(Odometry(rig, config), frames)
    assert all(report.status == FrameStatus.OK for report in reports)
    estimate = np.array([report.pose for report in reports])
    truth = relative_to_first(truth)
    path = float(np.linalg.norm(np.diff(truth[:, :3, 3], axis=0), axis=1).sum())
    assert path > 1.0
    error = invert_pose(truth) @ estimate
    # Frame-to-frame motion is 0.1 m and several degrees; a wrong direction or a missing
    # rectification conjugation shows up as errors of that size, not millimetres.
    relative_rotation_error = [
        rotation_angle_deg(
            (invert_pose(invert_pose(truth[k - 1]) @ truth[k]) @ reports[k].relative_pose)[:3, :3]
        )
        for k in range(1, len(reports))
    ]
    assert np.median(relative_rotation_error) < 0.15
    assert np.linalg.norm(error[-1, :3, 3]) < 0.03 * path
    assert rotation_angle_deg(error[-1, :3, :3]) < 1.0


def _relative_errors(reports: list, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame relative pose errors: rotation (deg) and translation (m)."""
    errors = [
        invert_pose(invert_pose(truth[k - 1]) @ truth[k]) @ reports[k].relative_pose
        for k in range(1, len(reports))
    ]
    return (
        np.array([rotation_angle_deg(error[:3, :3]) for error in errors]),
        np.array([np.linalg.norm(error[:3, 3]) for error in errors]),
    )


@pytest.mark.slow
def test_mahalanobis_refinement_cuts_the_per_frame_error() -> None:
    """Weighing each stereo point by its ray-aligned covariance removes most of the depth
    noise from the relative poses; the registration's inlier set stays the same. (msac: it
    fits isotropically; pso-robust already fits with the covariances itself.)"""
    frames, truth = _rendered_flight()
    truth = relative_to_first(truth)
    runs = {}
    for refine in (False, True):
        registration = {"mahalanobis_refine": refine, "method": "msac"}
        config = _config(backend={"enabled": False}, registration=registration)
        runs[refine] = _run(Odometry(_rendered_rig(), config), frames)
        assert all(report.status == FrameStatus.OK for report in runs[refine])
    # Same keyframe, same prediction, same seed: the first steps match the same pairs.
    assert [r.inliers for r in runs[True][:3]] == [r.inliers for r in runs[False][:3]]
    rotation_on, translation_on = _relative_errors(runs[True], truth)
    rotation_off, translation_off = _relative_errors(runs[False], truth)
    # Measured: 0.039 -> 0.005 deg and 3.2 -> 0.5 mm per frame; ask for half.
    assert np.median(rotation_on) < 0.5 * np.median(rotation_off)
    assert np.mean(translation_on) < 0.5 * np.mean(translation_off)


@pytest.mark.slow
def test_rendered_flight_rotation_errors_are_noise_not_a_bias() -> None:
    """Keyframe-to-keyframe rotation errors of a 20 m rendered flight average to zero.

    Each keyframe is measured once, against the previous keyframe, so the errors of those
    measurements are independent draws and their sum is the rotation drift; errors of frames
    in between telescope away. A systematic error (rectification conjugation, a calibration
    or sub-pixel offset, errors added at keyframe switches) of more than ~0.25 mrad per step
    (~1.7 mrad/s at ~7 keyframes/s) pushes an axis mean beyond 4 standard errors; the
    finer stages are checked with their own truths in test_synthetic / test_frontend.
    """
    frames, truth = _rendered_flight.__wrapped__(frames=200, length_m=20.0)  # not cached
    odometry = Odometry(_rendered_rig(), _config(backend={"enabled": False}))
    poses, references = [], []
    for frame in frames:
        report = odometry.process(frame)
        assert report.status == FrameStatus.OK
        poses.append(report.frontend_pose)
        references.append(odometry.reference_index)
    keyframes = sorted(set(references))
    estimate = np.array(poses)
    errors = []
    for a, b in pairwise(keyframes):
        measured = invert_pose(estimate[a]) @ estimate[b]
        error = invert_pose(invert_pose(truth[a]) @ truth[b]) @ measured
        errors.append(Rotation.from_matrix(error[:3, :3]).as_rotvec())
    errors = np.array(errors)
    assert len(errors) > 40
    mean = errors.mean(axis=0)
    standard_error = errors.std(axis=0, ddof=1) / np.sqrt(len(errors))
    # With the measured noise level the per-step noise is small enough that 4 standard errors
    # fall to ~0.02 mrad, ten times below the systematic errors this test is for; a bias below
    # 0.05 mrad per step (0.003 deg) is accepted as negligible (docs/estimators.md notes the
    # 0.022 mrad about the optical axis seen on this flight).
    assert np.all(np.abs(mean) < np.maximum(4.0 * standard_error, 5e-5)), (mean, standard_error)
    # The noise itself: ~0.2-0.6 mrad RMS per step and axis, from the stereo disparities.
    assert np.all(np.sqrt(np.mean(errors**2, axis=0)) < 1.2e-3)


@pytest.mark.slow
def test_same_seed_same_trajectory() -> None:
    frames, _ = _rendered_flight()
    config = _config(backend={"enabled": False}, seed=7)
    first = _run(Odometry(_rendered_rig(), config), frames[:6])
    second = _run(Odometry(_rendered_rig(), config), frames[:6])
    for a, b in zip(first, second, strict=True):
        np.testing.assert_array_equal(a.pose, b.pose)
        assert a.inliers == b.inliers


def test_frame_seed_differs_per_frame_and_seed() -> None:
    seeds = {frame_seed(seed, index) for seed in range(3) for index in range(50)}
    assert len(seeds) == 150
    assert frame_seed(3, 9) == frame_seed(3, 9)


# ----------------------------------------------------------------------------- EuRoC standstill


def _euroc_run(root: Path, config: SwarmvoConfig):
    sequence = open_sequence(root)
    odometry = Odometry(sequence.rig, config, imu_noise=sequence.imu_noise)
    timestamps = sequence.timestamps_ns
    reports = []
    previous = int(timestamps[0]) - FRAME_NS
    for frame in sequence:
        imu = sequence.imu_between(previous, frame.timestamp_ns)
        previous = frame.timestamp_ns
        reports.append(odometry.process(frame, imu))
    truth = camera_ground_truth(sequence.ground_truth, timestamps, sequence.rig.left.T_BS)
    return reports, relative_to_first(truth)


def _drift(poses: np.ndarray, truth: np.ndarray) -> tuple[float, float, float]:
    """Final translation and rotation error (m, deg) and eq. 20 RMS over all frames."""
    estimate = relative_to_first(poses)
    final = invert_pose(truth[-1]) @ estimate[-1]
    eq20 = float(np.sqrt(np.mean(eq20_errors(estimate, truth) ** 2)))
    return float(np.linalg.norm(final[:3, 3])), float(rotation_angle_deg(final[:3, :3])), eq20


@pytest.mark.slow
@pytest.mark.euroc
def test_euroc_standstill_stays_still(euroc_v101_micro: Path) -> None:
    reports, truth = _euroc_run(euroc_v101_micro, SwarmvoConfig())
    assert len(reports) == 95
    assert all(report.status == FrameStatus.OK for report in reports)
    assert np.median([report.inliers for report in reports[1:]]) > 150
    for name in ("frontend_pose", "pose"):
        poses = np.array([getattr(report, name) for report in reports])
        translation, rotation, eq20 = _drift(poses, truth)
        assert translation < 0.01, name
        assert eq20 < 0.005, name
        # The ground truth's own attitude disagrees with the images by ~0.25 deg at the last
        # frame (refined PnP on the same matches: docs/frontend.md), so 0.2 deg against it is
        # out of reach for a correct estimate; this bound is looser than that target.
        assert rotation < 0.35, name
        # Standing still: the reported motion itself stays tiny.
        final = relative_to_first(poses)[-1]
        assert np.linalg.norm(final[:3, 3]) < 0.01, name


@pytest.mark.slow
def test_rendered_broken_frames_fused_with_the_imu_beats_the_front_end(tmp_path: Path) -> None:
    """Rendered 8 m flights, 20 % broken frames (black, blurred, shuffled), simulated IMU."""
    from estimator.evaluation.metrics import evaluate_trajectory
    from estimator.pipeline import run_sequence
    from estimator.rendered.synthetic import SynthOptions, synthesize

    ate = {refine: {"frontend_pose": [], "pose": [], "smoothed": []} for refine in (False, True)}
    for seed in (0, 1, 2):
        options = SynthOptions(frames=80, length_m=8.0, seed=seed, broken_fraction=0.2)
        sequence = open_sequence(synthesize(tmp_path / str(seed), options).root)
        for refine, errors in ate.items():
            # Off: the isotropic front end (no point covariances in the estimator either).
            registration = {"mahalanobis_refine": refine, "use_point_sigmas": refine}
            config = SwarmvoConfig(seed=seed, registration=registration)
            run = run_sequence(sequence, config)
            assert not any(report.status == FrameStatus.LOST for report in run.reports)
            for which, values in errors.items():
                metrics = evaluate_trajectory(
                    run.timestamps_ns, run.poses(which), sequence.ground_truth,
                    sequence.rig.left.T_BS,
                ).metrics  # fmt: skip
                values.append(metrics["ate_rmse_m"])
    # Gyro + accelerometer: below the front end on every seed, by at least 30 % with the refined
    # front end, 10 % with the isotropic one (measured: refined -64 / -81 / -66 %; isotropic
    # -15 / -27 / -54 % with per-point search windows, -24 / -39 / -53 % with one 40 px window:
    # the isotropic fused runs move by 10-20 % between such settings, the refined ones by 2 %).
    for refine, errors in ate.items():
        fused, frontend = np.array(errors["pose"]), np.array(errors["frontend_pose"])
        assert np.all(fused < (0.7 if refine else 0.9) * frontend), (refine, ate)
        # The smoother's final estimates revise the online answers with later frames
        # (measured 5-49 % lower).
        assert np.sum(errors["smoothed"]) < np.sum(errors["pose"]), (refine, ate)
    # The refined front end (the default) gives the better fused trajectory (measured 0.41x).
    assert np.sum(ate[True]["pose"]) < 0.7 * np.sum(ate[False]["pose"]), ate


# ----------------------------------------------------------------------------- input handling


def _flat_rig() -> StereoRig:
    camera = {
        "width": 64, "height": 48, "fx": 50.0, "fy": 50.0, "cx": 32.0, "cy": 24.0,
        "distortion_model": "none", "distortion": [],
    }  # fmt: skip
    return StereoRig.from_dict(
        {
            "left": {**camera, "T_BS": np.eye(4).tolist()},
            "right": {**camera, "T_BS": make_pose(np.eye(3), [0.1, 0, 0]).tolist()},
        }
    )


def _blank(timestamp: int, shape=(48, 64), dtype=np.uint8) -> StereoFrame:
    return StereoFrame(timestamp, np.zeros(shape, dtype), np.zeros(shape, dtype))


def test_wrong_image_size_is_rejected() -> None:
    odometry = Odometry(_flat_rig(), _config(backend={"enabled": False}))
    with pytest.raises(ValueError, match="expects 64x48"):
        odometry.process(_blank(1, shape=(480, 640)))


def test_timestamps_must_increase() -> None:
    odometry = Odometry(_flat_rig(), _config(backend={"enabled": False}))
    odometry.process(_blank(100))
    with pytest.raises(ValueError, match="must increase"):
        odometry.process(_blank(50))
    with pytest.raises(ValueError, match="must increase"):
        odometry.process(_blank(100))
    odometry.process(_blank(150))  # a rejected frame leaves the session usable
    assert odometry.frame_count == 2


def test_unsupported_image_type_is_rejected() -> None:
    odometry = Odometry(_flat_rig(), _config(backend={"enabled": False}))
    with pytest.raises(ValueError, match="uint8 or uint16"):
        odometry.process(_blank(1, dtype=np.float32))
    with pytest.raises(ValueError, match="grey"):
        odometry.process(_blank(2, shape=(48, 64, 2)))


def test_grey_conversion() -> None:
    colour = np.zeros((4, 5, 3), np.uint8)
    colour[..., 1] = 200
    grey = to_grey8(colour)
    assert grey.shape == (4, 5) and grey.dtype == np.uint8
    assert abs(int(grey[0, 0]) - round(0.587 * 200)) <= 1
    deep = np.array([[0, 65535, 32896]], np.uint16)
    np.testing.assert_array_equal(to_grey8(deep), [[0, 255, 128]])
    assert to_grey8(np.zeros((4, 5, 1), np.uint8)).shape == (4, 5)


def test_featureless_frames_are_lost_and_hold_the_pose() -> None:
    odometry = Odometry(
        _flat_rig(), _config(backend={"enabled": False}, frontend={"max_coast_s": 0})
    )
    first = odometry.process(_blank(0))
    assert first.status == FrameStatus.OK
    second = odometry.process(_blank(FRAME_NS))
    assert second.status == FrameStatus.LOST
    assert "temporal matches" in second.message
    np.testing.assert_array_equal(second.pose, first.pose)
    np.testing.assert_array_equal(second.relative_pose, np.eye(4))


def test_failed_frames_coast_then_hold() -> None:
    two_frames_s = 2 * FRAME_NS * 1e-9
    odometry = Odometry(
        _flat_rig(), _config(backend={"enabled": False}, frontend={"max_coast_s": two_frames_s})
    )
    statuses = [odometry.process(_blank(k * FRAME_NS)).status for k in range(5)]
    assert statuses == [
        FrameStatus.OK,
        FrameStatus.DEGRADED,
        FrameStatus.DEGRADED,
        FrameStatus.LOST,
        FrameStatus.LOST,
    ]


@pytest.mark.slow
def test_coasting_keeps_the_velocity() -> None:
    """A black frame in a flight: the pose moves on at the last velocity, then tracking resumes."""
    frames, truth = _rendered_flight()
    config = _config(backend={"enabled": False}, registration={"method": "msac"})
    odometry = Odometry(_rendered_rig(), config)
    reports = [odometry.process(frame) for frame in frames[:6]]
    black = frames[6]
    black = StereoFrame(black.timestamp_ns, np.zeros_like(black.left), np.zeros_like(black.right))
    reports.append(odometry.process(black))
    reports += [odometry.process(frame) for frame in frames[7:10]]
    assert reports[6].status == FrameStatus.DEGRADED
    assert "constant velocity" in reports[6].message
    np.testing.assert_allclose(reports[6].relative_pose, reports[5].relative_pose, atol=1e-12)
    assert all(report.status == FrameStatus.OK for report in reports[7:])
    truth = relative_to_first(truth)
    # Frame 6 coasts at the velocity of frame 5: its error is the velocity change over one
    # frame, millimetres here instead of the whole step. Frame 7 is measured against the last
    # good references again, so the coasting error does not carry over.
    step = np.linalg.norm(truth[6, :3, 3] - truth[5, :3, 3])
    assert np.linalg.norm(reports[6].pose[:3, 3] - truth[6, :3, 3]) < 0.2 * step
    error = np.linalg.norm(reports[9].pose[:3, 3] - truth[9, :3, 3])
    assert error < 0.05 * step


@pytest.mark.slow
def test_coasting_scales_with_the_time_between_frames() -> None:
    """Two frames missing, then a black one: it coasts three frame intervals at the velocity."""
    frames, _ = _rendered_flight()
    config = _config(backend={"enabled": False}, registration={"method": "msac"})
    odometry = Odometry(_rendered_rig(), config)
    reports = _run(odometry, frames[:6])
    late = frames[8]
    black = StereoFrame(late.timestamp_ns, np.zeros_like(late.left), np.zeros_like(late.right))
    coasted = odometry.process(black)
    assert coasted.status == FrameStatus.DEGRADED
    expected = scale_motion(reports[5].relative_pose, 3.0)
    np.testing.assert_allclose(coasted.relative_pose, expected, atol=1e-9)


@pytest.mark.parametrize(
    ("configured", "backend", "imu", "expected"),
    [
        (None, {"enabled": False}, False, True),  # front end alone: vision alone
        (None, {}, False, True),  # back end without IMU samples (--no-imu)
        (None, {"use_imu": False}, True, True),  # back end told to leave the IMU out
        (None, {}, True, False),  # fused with the IMU
        (True, {}, True, True),  # a configured value wins
        (False, {"enabled": False}, False, False),
    ],
)
def test_the_chain_through_the_previous_frame_is_on_by_default_only_without_the_imu(
    configured: bool | None, backend: dict, imu: bool, expected: bool
) -> None:
    """Fused with the IMU the chain cost MH_01 ATE (docs/frontend.md); vision alone it lowers
    the rotation error per frame, so unset it follows whether an IMU is fused."""
    frontend = {} if configured is None else {"fuse_previous_frame": configured}
    config = _config(backend=backend, frontend=frontend)
    odometry = Odometry(_rendered_rig(), config, imu_noise=ImuNoise() if imu else None)
    assert odometry.fuses_previous_frame is expected
    assert config.frontend.fuse_previous_frame is configured  # the caller's config untouched


def test_the_chain_links_bias_is_its_rate_times_the_inliers_image_motion() -> None:
    """``frontend.chain_link_rotation_bias`` x the median flow of the link's inliers over the
    focal length, per rotation axis; an outlier's motion does not count."""
    config = _config(backend={"enabled": False}, frontend={"chain_link_rotation_bias": 0.01})
    odometry = Odometry(_rendered_rig(), config)
    focal = odometry.rectification.fx
    depth = 4.0
    shifts = np.array([0.01, 0.02, 0.03, 2.0])  # metres sideways at 4 m; the last an outlier
    current = np.column_stack([np.linspace(-1, 1, 4), np.zeros(4), np.full(4, depth)])
    reference = current + np.column_stack([shifts, np.zeros(4), np.zeros(4)])
    index = np.arange(4)
    pairs = Correspondences(index, index, reference, current)
    inliers = np.array([True, True, True, False])
    result = RegistrationResult(np.eye(3), np.zeros(3), np.array([1.0, 0, 0, 0]), inliers, 3,
                                0.0, 1, 0.0, True)  # fmt: skip
    estimate = Estimate(np.eye(4), result, "", pairs)
    rate = config.frontend.chain_link_rotation_bias  # a link's own (the configured) rate
    covariance = measurement_bias(estimate, rate, odometry.rectification)
    sigma = 0.01 * (focal * 0.02 / depth) / focal  # median inlier flow 0.02 m at 4 m, in px
    np.testing.assert_allclose(np.diag(covariance)[:3], sigma**2, rtol=1e-9)
    assert not np.diag(covariance)[3:].any()


@pytest.mark.parametrize(("min_flow_px", "chained"), [(1.0, False), (0.0, True)])
def test_at_rest_the_chain_through_the_previous_frame_is_left_out(
    min_flow_px: float, chained: bool
) -> None:
    """A camera at rest: the keyframe measurement alone is as good as the combination, which
    would nearly double the frame's matching and estimation (``frontend.chain_min_flow_px``);
    with the threshold at 0 the chain runs on the same frames."""
    frames, _ = _rendered_flight()
    still = [
        StereoFrame(1_000 + k * FRAME_NS, frames[0].left, frames[0].right) for k in range(6)
    ]
    config = _config(backend={"enabled": False}, frontend={"chain_min_flow_px": min_flow_px})
    seen: list[ObservedMeasurement] = []
    odometry = Odometry(_rendered_rig(), config, observer=seen.append)
    reports = _run(odometry, still)
    assert all(report.status == FrameStatus.OK for report in reports)
    links = [m for m in seen if m.kind is MeasurementKind.LINK]
    assert (len(links) >= 3) is chained and (len(links) == 0) is not chained


@pytest.mark.parametrize(("exact", "configured", "expected"), [
    (False, None, 0.005), (True, None, 0.0), (True, 0.002, 0.002), (False, 0.0, 0.0),
])  # fmt: skip
def test_the_common_error_rate_follows_the_rigs_calibration(
    exact: bool, configured: float | None, expected: float
) -> None:
    """A real rig's measurements share an error the combination cannot average out; an exact
    (rendered) rig's hardly: unset, the rate follows the rig; a configured rate wins, also in
    the settings ``swarmvo run`` derives and prints."""
    rig = dataclasses.replace(_rendered_rig(), calibration_exact=exact)
    frontend = {} if configured is None else {"chain_common_rotation_bias": configured}
    config = _config(backend={"enabled": False}, frontend=frontend)
    assert Odometry(rig, config).common_rotation_bias == expected
    derived, settings = apply_rig_settings(config, rig, 0.05)
    assert derived.frontend.chain_common_rotation_bias == expected
    (setting,) = [s for s in settings if s.name == "chain_common_rotation_bias"]
    assert setting.overridden is (configured is not None)


def test_the_combined_measurement_counts_the_common_error_once_and_the_link_not_at_all(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Vision alone, a frame's combined measurement carries, on top of the combination's
    covariance, the keyframe measurement's motion-proportional error (shared by both estimates
    through the current frame's blur, so not averaged out); the next frame's chain link takes
    the combination's covariance without it, since that link adds its own."""
    frames, _ = _rendered_flight()
    odometry = Odometry(
        _rendered_rig(),
        _config(backend={"enabled": False}, frontend={"chain_common_rotation_bias": 0.005}),
    )
    assert odometry.fuses_previous_frame
    original = ChainCombination.combined
    combined: list[tuple[np.ndarray, object]] = []
    seen_references = []

    def recording(self, estimate, *args, **kwargs):
        # from the keyframe measurement's own inliers, at the rig's common rate
        common = measurement_bias(estimate, self.common_rate, self.rectification)
        result = original(self, estimate, *args, **kwargs)
        seen_references.append(self.references)
        if result.chain_covariance is not None:
            combined.append((common, result))
        return result

    monkeypatch.setattr(ChainCombination, "combined", recording)
    links_checked = 0
    for frame in frames:
        odometry.process(frame)
        if not seen_references:
            continue
        references = seen_references[-1]  # the odometry's, updated by this frame
        if combined and combined[-1][1].chain_covariance is not None:
            last = combined[-1][1]
            if references.reference is last.reference:  # the keyframe was kept
                assert references.reference_from_previous_covariance is last.chain_covariance
                links_checked += 1
    assert len(combined) >= 5 and links_checked >= 3
    for common, estimate in combined:
        assert np.diag(common)[:3].min() > 0
        np.testing.assert_allclose(estimate.covariance - estimate.chain_covariance, common)


@pytest.mark.slow
@pytest.mark.parametrize("loss", ["black", "foreign", "dropped"])
def test_a_lost_frame_does_not_damage_the_frames_after_it(loss: str) -> None:
    """Frame 6 is black, shows something else entirely (plenty of stereo points, nothing to
    match: a shaken or covered camera), or never arrives. The frames after it are matched
    against the last good references at once and come out exactly as without the loss (with
    the fixed noise model: the measured one has seen one frame fewer, and without the chain
    through the previous frame, which is another frame after a loss: test below)."""
    frames, _ = _rendered_flight()
    registration = {"method": "msac", "noise_model": "fixed"}
    config = _config(
        backend={"enabled": False},
        registration=registration,
        frontend={"fuse_previous_frame": False},
    )
    clean = _run(Odometry(_rendered_rig(), config), frames)
    lost = frames[6]
    if loss == "dropped":
        perturbed = frames[:6] + frames[7:]
    else:
        left, right = (
            (np.zeros_like(lost.left), np.zeros_like(lost.right))
            if loss == "black"
            else (np.roll(lost.left, 200, axis=1), np.roll(lost.right, 200, axis=1))
        )
        perturbed = [*frames[:6], StereoFrame(lost.timestamp_ns, left, right), *frames[7:]]
    reports = _run(Odometry(_rendered_rig(), config), perturbed)
    after = {r.timestamp_ns: r for r in reports if r.timestamp_ns > lost.timestamp_ns}
    if loss != "dropped":
        assert reports[6].status == FrameStatus.DEGRADED
    for report in clean[7:]:
        assert after[report.timestamp_ns].status == FrameStatus.OK
        np.testing.assert_allclose(after[report.timestamp_ns].pose, report.pose, atol=1e-6)


@pytest.mark.slow
def test_a_lost_frame_barely_moves_the_frames_after_it_with_the_measured_noise() -> None:
    """The measured noise level has seen one frame fewer after a black frame and the first
    frame after it is chained through another previous frame: the poses after it differ from
    the clean run only through that (< 0.5 mm)."""
    frames, _ = _rendered_flight()
    config = _config(backend={"enabled": False}, registration={"method": "msac"})
    clean = _run(Odometry(_rendered_rig(), config), frames)
    lost = frames[6]
    black = StereoFrame(lost.timestamp_ns, np.zeros_like(lost.left), np.zeros_like(lost.right))
    reports = _run(Odometry(_rendered_rig(), config), [*frames[:6], black, *frames[7:]])
    for report, reference in zip(reports[7:], clean[7:], strict=True):
        assert report.status == FrameStatus.OK
        np.testing.assert_allclose(report.pose, reference.pose, atol=5e-4)


def _rigid(rotvec: list[float], translation: list[float]) -> np.ndarray:
    return make_pose(quat_to_matrix(rotation_vector_to_quat(np.array(rotvec))), translation)


@pytest.mark.slow
def test_the_back_end_gets_the_keyframe_measurement_with_its_reference_and_points() -> None:
    """After a black frame the back end gets T_ref_cur against the pre-gap reference itself."""
    frames, truth = _rendered_flight()
    config = _config(backend={"enabled": True, "use_imu": False}, registration={"method": "msac"})
    calls: list[dict] = []

    def spy(given: BackendInput) -> None:
        if isinstance(given, BackendFrame):
            calls.append({"timestamp_ns": given.timestamp_ns, **given.arguments})

    odometry = Odometry(_rendered_rig(), config, backend_observer=spy)
    black = StereoFrame(frames[6].timestamp_ns, *(np.zeros_like(frames[6].left),) * 2)
    reports = [odometry.process(frame) for frame in [*frames[:6], black, *frames[7:10]]]
    stamps = [frame.timestamp_ns for frame in frames]
    assert calls[6]["relative_pose"] is None  # no vision (no IMU either: "lost")
    after = calls[7]
    reference = stamps.index(after["reference_ns"])
    assert reference < 6  # spans the gap from a measured frame, not from the coasted one
    expected = invert_pose(truth[reference]) @ truth[7]
    assert np.linalg.norm(after["relative_pose"][:3, 3] - expected[:3, 3]) < 0.01
    assert rotation_angle_deg(after["relative_pose"][:3, :3].T @ expected[:3, :3]) < 0.2
    # The inliers, in the current (original) left camera: in front of it, one per inlier.
    points = after["inlier_points"]
    assert points.shape == (after["inlier_count"], 3) == (reports[7].inliers, 3)
    assert np.all(points[:, 2] > 0)
    assert len(after["inlier_residuals"]) == reports[7].inliers
    assert all(report.status == FrameStatus.OK for report in reports[7:])


@pytest.mark.parametrize("backend", [False, True])
def test_resume_from_stored_pose(backend: bool) -> None:
    stored = make_pose(quat_to_matrix(rotation_vector_to_quat([0.1, 0.2, -0.3])), [1, 2, 3])
    odometry = Odometry(
        _flat_rig(), _config(backend={"enabled": backend, "use_imu": False}), initial_pose=stored
    )
    report = odometry.process(_blank(5))
    assert "resumed from stored pose" in report.message
    np.testing.assert_allclose(report.pose, stored, atol=1e-9)
    np.testing.assert_allclose(report.frontend_pose, stored, atol=1e-9)
    later = odometry.process(_blank(5 + FRAME_NS))
    assert np.allclose(later.frontend_pose, stored)  # nothing seen: held


def test_bad_initial_pose() -> None:
    with pytest.raises(ValueError, match="initial_pose"):
        Odometry(_flat_rig(), initial_pose=np.eye(3))
    with pytest.raises(ValueError, match="rigid"):
        Odometry(_flat_rig(), initial_pose=np.diag([1.0, 1.0, 2.0, 1.0]))


@pytest.mark.parametrize(
    "overrides",
    [
        {"frontend": {"pixel_sigma_u_px": float("inf")}},
        {"backend": {"rest_z": float("nan")}},
        {"registration": {"no_such_option": 1}},
    ],
)
def test_config_refuses_unknown_keys_and_non_finite_numbers(overrides) -> None:
    with pytest.raises(ValueError, match=r"finite|Extra inputs"):
        SwarmvoConfig(**overrides)


@pytest.mark.parametrize("backend", [False, True])
def test_a_run_continued_from_its_state_has_no_jump(backend: bool) -> None:
    """Another process continues from state() (through JSON, as the service stores it): the
    step into its first frame is predicted at the measured velocity, close to the true step;
    resuming from the pose alone would stand still for that step (a 10 cm jump here)."""
    frames, cameras = _rendered_flight()
    config = _config(backend={"enabled": backend, "use_imu": False})
    whole = _run(Odometry(_rendered_rig(), config), frames)
    first = Odometry(_rendered_rig(), config)
    _run(first, frames[:8])
    state = json.loads(json.dumps(first.state()))
    continued = Odometry(_rendered_rig(), config, initial_pose=np.array(state["pose"]),
                         first_index=8)
    continued.restore(state)
    rest = _run(continued, frames[8:])
    assert [r.index for r in rest] == list(range(8, len(frames)))

    def step(previous: np.ndarray, current: np.ndarray) -> np.ndarray:
        return (invert_pose(previous) @ current)[:3, 3]

    true_step = step(cameras[7], cameras[8])
    jump = np.linalg.norm(step(whole[7].pose, rest[0].pose) - true_step)
    assert np.linalg.norm(true_step) > 0.08
    assert jump < 0.01, jump
    # It goes on tracking: the following steps are as good as the uninterrupted run's.
    for k in range(9, len(frames)):
        error = np.linalg.norm(step(rest[k - 9].pose, rest[k - 8].pose) - step(cameras[k - 1],
                                                                                 cameras[k]))
        assert error < 0.01, (k, error)
    with pytest.raises(ValueError, match="before the first frame"):
        continued.restore(state)
