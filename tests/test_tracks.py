"""The track front end (frontend.mode = "track"): tracks in time, stereo by LK, pairs by id."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from test_frontend import BASELINE, FOCAL, WIDTH, _rig, _shift, _texture, _two_plane_pair
from test_odometry import _config, _rendered_flight, _rendered_rig, _run

from estimator.config import FrontendConfig
from estimator.evaluation.metrics import relative_to_first
from estimator.frontend.stereo import StereoPoints
from estimator.frontend.tracks import KeyframeView, TrackedPoints, Tracker, match_tracks
from estimator.geometry import invert_pose
from estimator.odometry import Odometry
from estimator.types import FrameStatus, StereoFrame


def _tracked(config: FrontendConfig, images: list[tuple[np.ndarray, np.ndarray]]):
    tracker = Tracker(config, _rig().rectification)
    frames = []
    for left, right in images:
        tracker.follow(left)
        frames.append(tracker.stereo(right))
    return frames


def test_tracks_follow_a_known_image_shift() -> None:
    """Every pixel moves by the same known flow: the tracks keep their ids and land there."""
    texture = _texture(11)
    shift = (4.3, -2.6)
    first = _shift(texture, 0.0)[:, :WIDTH].clip(0, 255).astype(np.uint8)
    second = _shift(texture, *shift)[:, :WIDTH].clip(0, 255).astype(np.uint8)
    tracker = Tracker(FrontendConfig(max_tracks=300), _rig().rectification)
    tracker.follow(first)
    ids, pixels = tracker.live
    before = dict(zip(ids.tolist(), pixels, strict=True))
    assert len(before) > 200
    tracker.follow(second)
    ids, pixels = tracker.live
    after = dict(zip(ids.tolist(), pixels, strict=True))
    kept = [i for i in before if i in after]
    assert len(kept) > 0.9 * len(before)
    moved = np.array([after[i] - before[i] for i in kept])
    error = np.linalg.norm(moved - shift, axis=1)
    assert np.median(error) < 0.05
    assert np.mean(error < 0.3) > 0.95


def test_track_stereo_disparity_on_rendered_planes() -> None:
    depths = (1.7, 4.3)  # disparities 28.24 px and 11.16 px: both fractional
    points = _tracked(FrontendConfig(max_tracks=400), [_two_plane_pair(_texture(5), depths)])[0]
    assert isinstance(points, TrackedPoints)
    near = points.pixels[:, 0] < WIDTH // 2 - 20
    far = points.pixels[:, 0] > WIDTH // 2 + 20
    assert near.sum() > 80 and far.sum() > 80
    for mask, depth in ((near, depths[0]), (far, depths[1])):
        error = points.disparity[mask] - FOCAL * BASELINE / depth
        assert np.median(np.abs(error)) < 0.1
        assert np.mean(np.abs(error) < 0.5) > 0.9
        assert abs(np.median(points.points[mask, 2]) - depth) < 0.01 * depth
    assert len(np.unique(points.ids)) == len(points)


def test_track_pairs_carry_the_known_motion() -> None:
    """Pairs by track id between a reference and a shifted frame: the current points project
    where the reference pixels moved, with the disparity of the current frame."""
    texture = _texture(7)
    shift = (3.4, -1.7)
    depths = (2.0, 5.0)
    config = FrontendConfig(max_tracks=300)
    reference_images = _two_plane_pair(texture, depths)
    current_images = _two_plane_pair(texture, depths, *shift)
    reference, current = _tracked(config, [reference_images, current_images])
    rect = _rig().rectification
    pairs = match_tracks(
        reference, current, config, rect, images=(reference_images[0], current_images[0])
    )
    assert len(pairs) > 0.7 * len(reference)
    np.testing.assert_array_equal(
        reference.ids[pairs.reference_index], current.ids[pairs.current_index]
    )
    seen_at = pairs.current_points[:, :2] / pairs.current_points[:, 2:] * rect.fx
    seen_at += [rect.cx, rect.cy]
    expected = reference.pixels[pairs.reference_index] + shift
    assert np.median(np.linalg.norm(seen_at - expected, axis=1)) < 0.1
    with pytest.raises(ValueError, match="track front end"):
        match_tracks(StereoPoints.empty(), current, config, rect)


@pytest.mark.parametrize("recover_ratio", [0.5, 0.0])
def test_keyframe_tracks_found_again_after_a_black_frame(recover_ratio: float) -> None:
    """A black frame loses every track; the next frame finds the keyframe's tracks again from
    the keyframe's image (same ids, where the image moved), unless recovery is off."""
    texture = _texture(7)
    shift = (3.4, -1.7)
    depths = (2.0, 5.0)
    config = FrontendConfig(max_tracks=300, track_recover_ratio=recover_ratio)
    rect = _rig().rectification
    keyframe_images = _two_plane_pair(texture, depths)
    current_images = _two_plane_pair(texture, depths, *shift)
    black = np.zeros_like(keyframe_images[0])
    tracker = Tracker(config, rect)
    tracker.follow(keyframe_images[0])
    keyframe = tracker.stereo(keyframe_images[1])
    view = KeyframeView(keyframe, keyframe_images[0], np.eye(4))
    tracker.follow(black, None, view)
    assert len(tracker.stereo(black)) == 0
    tracker.follow(current_images[0], None, view)
    current = tracker.stereo(current_images[1])
    assert len(np.unique(current.ids)) == len(current)
    pairs = match_tracks(keyframe, current, config, rect, images=(keyframe_images[0],
                         current_images[0]))  # fmt: skip
    if recover_ratio == 0.0:
        assert len(pairs) == 0
        return
    assert len(pairs) > 0.7 * len(keyframe)
    moved = current.pixels[pairs.current_index] - keyframe.pixels[pairs.reference_index]
    assert np.median(np.linalg.norm(moved - shift, axis=1)) < 0.1


def test_track_mode_on_a_blank_image_has_no_points() -> None:
    blank = np.full((480, WIDTH), 90, np.uint8)
    points = _tracked(FrontendConfig(), [(blank, blank), (blank, blank)])
    assert [len(p) for p in points] == [0, 0]


@pytest.mark.slow
def test_rendered_flight_in_track_mode() -> None:
    """The flight of test_odometry in track mode: a wrong track or disparity shows up as
    centimetres and degrees, not the millimetres allowed here."""
    frames, truth = _rendered_flight()
    config = _config(backend={"enabled": False}, frontend={"mode": "track"})
    reports = _run(Odometry(_rendered_rig(), config), frames)
    assert all(report.status == FrameStatus.OK for report in reports)
    estimate = np.array([report.pose for report in reports])
    truth = relative_to_first(truth)
    path = float(np.linalg.norm(np.diff(truth[:, :3, 3], axis=0), axis=1).sum())
    error = invert_pose(truth) @ estimate
    ate = float(np.sqrt(np.mean(np.sum(error[:, :3, 3] ** 2, axis=1))))
    assert ate < 0.01 * path
    assert np.median([report.matches for report in reports[1:]]) > 60


@pytest.mark.slow
def test_track_mode_same_seed_same_trajectory() -> None:
    frames, _ = _rendered_flight()
    config = _config(backend={"enabled": False}, frontend={"mode": "track"}, seed=3)
    first = _run(Odometry(_rendered_rig(), config), frames[:6])
    second = _run(Odometry(_rendered_rig(), config), frames[:6])
    for a, b in zip(first, second, strict=True):
        np.testing.assert_array_equal(a.pose, b.pose)
        assert a.inliers == b.inliers


def test_forgotten_frame_leaves_the_tracks_as_they_were() -> None:
    """A frame without a vision estimate is undone in the tracker: the next frame follows the
    tracks from the last good image, with their ids."""
    texture = _texture(7)
    shift = (3.4, -1.7)
    first = _two_plane_pair(texture, (2.0, 5.0))
    second = _two_plane_pair(texture, (2.0, 5.0), *shift)
    tracker = Tracker(FrontendConfig(max_tracks=300), _rig().rectification)
    tracker.follow(first[0])
    tracker.stereo(first[1])
    ids, pixels = tracker.live
    tracker.follow(np.zeros_like(first[0]))
    assert len(tracker) == 0
    tracker.forget_frame()
    np.testing.assert_array_equal(tracker.live[0], ids)
    np.testing.assert_array_equal(tracker.live[1], pixels)
    tracker.follow(second[0])
    after_ids, after_pixels = tracker.live
    kept = np.isin(ids, after_ids)
    assert kept.mean() > 0.9
    moved = after_pixels[np.isin(after_ids, ids)] - pixels[kept]
    assert np.median(np.linalg.norm(moved - shift, axis=1)) < 0.1


def test_a_motion_blurred_frame_is_not_followed() -> None:
    """A frame streaked by motion blur leaves the tracks' LK residual several times the recent
    frames': it gets no points and the tracks wait for the next sharp frame; a level that
    stays (three such frames in a row) is taken as the new normal."""
    texture = _texture(3)
    frames = [_shift(texture, 1.5 * k, 0.5 * k)[:, :WIDTH].clip(0, 255).astype(np.uint8)
              for k in range(8)]  # fmt: skip
    streak = np.full((1, 25), 1 / 25, np.float32)
    blurred = cv2.filter2D(frames[5], -1, streak)
    tracker = Tracker(FrontendConfig(max_tracks=300), _rig().rectification)
    for image in frames[:5]:
        tracker.follow(image)
        assert len(tracker) > 200
    ids = tracker.live[0]
    tracker.follow(blurred)
    assert len(tracker) == 0
    tracker.forget_frame()
    tracker.follow(frames[6])  # two frames on from the last sharp one
    assert np.isin(ids, tracker.live[0]).mean() > 0.9
    followed = []
    for _ in range(3):  # as the odometry does: a frame without points is forgotten
        tracker.follow(cv2.filter2D(frames[7], -1, streak))
        followed.append(len(tracker) > 0)
        if not followed[-1]:
            tracker.forget_frame()
    assert followed == [False, False, True]
    off = Tracker(FrontendConfig(max_tracks=300, track_blur_ratio=0), _rig().rectification)
    for image in frames[:5]:
        off.follow(image)
    off.follow(blurred)
    assert len(off) > 0


@pytest.mark.slow
@pytest.mark.parametrize("recover_ratio", [0.5, 0.0])
def test_track_mode_frame_after_a_black_one_is_tracked(recover_ratio: float) -> None:
    """Only the black frame itself goes without a vision estimate (the tracker forgets it,
    and finds lost keyframe tracks again when recovery is on)."""
    frames, truth = _rendered_flight()
    frames = list(frames)
    black = frames[8]
    frames[8] = StereoFrame(black.timestamp_ns, np.zeros_like(black.left),
                            np.zeros_like(black.right))  # fmt: skip
    config = _config(
        backend={"enabled": False},
        frontend={"mode": "track", "track_recover_ratio": recover_ratio, "tracking": "keyframe"},
    )
    reports = _run(Odometry(_rendered_rig(), config), frames)
    assert [i for i, r in enumerate(reports) if r.status != FrameStatus.OK] == [8]
    assert reports[9].matches > 50
    estimate = np.array([report.pose for report in reports])
    error = invert_pose(relative_to_first(truth)) @ estimate
    assert np.sqrt(np.mean(np.sum(error[:, :3, 3] ** 2, axis=1))) < 0.01
