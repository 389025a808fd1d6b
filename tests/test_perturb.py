"""Camera perturbations of a recorded sequence: seeded, per camera, and what they claim to be."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from estimator.formats.calibration import StereoRig
from estimator.formats.datasets import FrameRecord, GroundTruth, Sequence
from estimator.geometry import make_pose
from estimator.rendered.perturb import PERTURBATIONS, Perturbation, perturb_sequence

WIDTH, HEIGHT, FOCAL = 320, 240, 300.0
FRAME_NS = 50_000_000
YAW_RATE = 0.5  # rad/s about the camera's vertical axis (ground truth of the delay test)


def _texture(seed: int) -> np.ndarray:
    """Mid-grey random blobs (no clipping at 0 or 255 before any perturbation)."""
    rng = np.random.default_rng(seed)
    noise = rng.normal(size=(HEIGHT // 6 + 2, WIDTH // 6 + 2)).astype(np.float32)
    image = cv2.resize(noise, (WIDTH, HEIGHT), interpolation=cv2.INTER_CUBIC)
    image = (image - image.min()) / (image.max() - image.min())
    return np.rint(60 + 120 * image).astype(np.uint8)


def _sequence(tmp_path: Path, frames: int = 12) -> Sequence:
    camera = {
        "width": WIDTH, "height": HEIGHT, "fx": FOCAL, "fy": FOCAL, "cx": WIDTH / 2,
        "cy": HEIGHT / 2, "distortion_model": "none", "distortion": [],
    }  # fmt: skip
    rig = StereoRig.from_dict(
        {
            "left": {**camera, "T_BS": np.eye(4).tolist()},
            "right": {**camera, "T_BS": make_pose(np.eye(3), [0.1, 0, 0]).tolist()},
        }
    )
    records = []
    for index in range(frames):
        paths = []
        for camera_name, seed in (("left", index), ("right", 1000 + index)):
            path = tmp_path / f"{camera_name}_{index:03d}.png"
            cv2.imwrite(str(path), _texture(seed))
            paths.append(path)
        records.append(FrameRecord((index + 1) * FRAME_NS, *paths))
    # The body (= both cameras' orientation) turns about its y axis at YAW_RATE.
    times = np.arange(0, frames + 2) * FRAME_NS
    poses = []
    for t in times:
        angle = YAW_RATE * t * 1e-9
        c, s = np.cos(angle), np.sin(angle)
        poses.append(make_pose(np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]), np.zeros(3)))
    truth = GroundTruth(times, np.array(poses))
    return Sequence("toy", "euroc", tmp_path, rig, records, ground_truth=truth)


def _pixels(sequence: Sequence, order: list[int]) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    return {index: (f.left, f.right) for index in order for f in [sequence.load(index)]}


def test_same_seed_same_pixels_in_any_order(tmp_path: Path) -> None:
    sequence = _sequence(tmp_path)
    effects = Perturbation(gain=(0.6, 1.4), noise_sigma=4.0, blur_every=3, seed=5)
    forward = _pixels(perturb_sequence(sequence, effects), [0, 1, 2, 3])
    backward = _pixels(perturb_sequence(sequence, effects), [3, 2, 1, 0])
    for index in range(4):
        for a, b in zip(forward[index], backward[index], strict=True):
            np.testing.assert_array_equal(a, b)
    other = perturb_sequence(sequence, Perturbation(gain=(0.6, 1.4), noise_sigma=4.0, seed=6))
    assert not np.array_equal(other.load(0).left, forward[0][0])


def test_gain_is_drawn_per_frame_and_camera(tmp_path: Path) -> None:
    sequence = _sequence(tmp_path)
    perturbed = perturb_sequence(sequence, Perturbation(gain=(0.6, 1.4)))
    gains = []
    for index in range(len(sequence)):
        original, changed = sequence.load(index), perturbed.load(index)
        pair = []
        for before, after in ((original.left, changed.left), (original.right, changed.right)):
            unclipped = after < 255
            x, y = before[unclipped].astype(float), after[unclipped].astype(float)
            gain = float(x @ y / (x @ x))
            # A pure gain: every unclipped pixel is the original times it, to rounding (plus
            # the fit's own error); an offset or a curve would leave several grey levels.
            assert np.abs(y - gain * x).max() <= 1.0
            pair.append(gain)
        gains.append(pair)
    gains = np.array(gains)
    assert gains.min() >= 0.6 - 0.01 and gains.max() <= 1.4 + 0.01
    assert np.abs(gains[:, 0] - gains[:, 1]).max() > 0.1  # left and right not in step
    assert gains.std() > 0.1


def test_frame_rate_drops_black_and_blurred_frames(tmp_path: Path) -> None:
    sequence = _sequence(tmp_path)
    half = perturb_sequence(sequence, Perturbation(keep_every=2))
    np.testing.assert_array_equal(half.timestamps_ns, sequence.timestamps_ns[::2])
    dropped = perturb_sequence(sequence, Perturbation(drop_probability=0.5, seed=3))
    assert dropped.timestamps_ns[0] == sequence.timestamps_ns[0]  # the first frame arrives
    assert 2 <= len(dropped) < len(sequence)
    assert set(dropped.timestamps_ns) <= set(sequence.timestamps_ns)
    black = perturb_sequence(sequence, Perturbation(black_every=4))
    dark = [i for i in range(len(black)) if black.load(i).left.max() == 0]
    assert dark == [3, 7, 11] and black.load(3).right.max() == 0
    blurred = perturb_sequence(sequence, Perturbation(blur_every=4))

    def sharpness(image: np.ndarray) -> float:
        return float(np.mean(np.abs(cv2.Laplacian(image.astype(np.float32), cv2.CV_32F))))

    assert sharpness(blurred.load(3).left) < 0.7 * sharpness(sequence.load(3).left)
    np.testing.assert_array_equal(blurred.load(2).left, sequence.load(2).left)


def test_noise_has_the_requested_sigma(tmp_path: Path) -> None:
    sequence = _sequence(tmp_path)
    noisy = perturb_sequence(sequence, Perturbation(noise_sigma=6.0))
    difference = noisy.load(0).left.astype(float) - sequence.load(0).left
    assert abs(difference.mean()) < 0.2
    assert abs(difference.std() - np.sqrt(6.0**2 + 1 / 12)) < 0.15  # plus rounding


def test_late_right_shutter_sees_the_later_rotation(tmp_path: Path) -> None:
    """Turning about y at 0.5 rad/s, a 20 ms late right image is shifted by f * 0.01 = 3 px."""
    sequence = _sequence(tmp_path)
    late = perturb_sequence(sequence, Perturbation(right_delay_ms=20.0))
    original, delayed = sequence.load(4), late.load(4)
    np.testing.assert_array_equal(delayed.left, original.left)
    window = cv2.createHanningWindow((WIDTH, HEIGHT), cv2.CV_32F)  # ignore the borders
    (shift_x, shift_y), _ = cv2.phaseCorrelate(
        original.right.astype(np.float32), delayed.right.astype(np.float32), window
    )
    expected = -FOCAL * np.tan(YAW_RATE * 0.020)  # the camera turns right: the scene moves left
    # The shift grows towards the sides, f theta (1 + (x / f)^2): 3.0 px at the centre, 3.8 px
    # at the borders; the (windowed) image-wide estimate lies in between, near the centre's.
    assert expected - 0.25 < shift_x < expected and abs(shift_y) < 0.1


def test_suite_and_bad_settings() -> None:
    assert "none" in PERTURBATIONS and PERTURBATIONS["none"] == Perturbation()
    for bad in (
        {"gain": (1.4, 0.6)},
        {"keep_every": 0},
        {"drop_probability": 1.0},
        {"black_every": -1},
        {"noise_sigma": -1.0},
        {"right_delay_ms": -5.0},
    ):
        with pytest.raises(ValueError):
            Perturbation(**bad)


@pytest.mark.slow
@pytest.mark.euroc
def test_real_clip_with_gain_flicker_keeps_every_frame(euroc_mh01_moving: Path) -> None:
    """The real MH_01 clip with exposure flickering per frame and camera in [0.6, 1.4]: the
    front end still tracks every frame with most of its temporal matches."""
    import warnings

    from estimator.config import SwarmvoConfig
    from estimator.formats.datasets import open_sequence
    from estimator.pipeline import run_sequence

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # unpaired camera rows of the recording
        sequence = open_sequence(euroc_mh01_moving)
    config = SwarmvoConfig.model_validate(
        {"backend": {"enabled": False}, "registration": {"use_point_sigmas": False}}
    )
    runs = {}
    for name in ("none", "gain flicker 0.6-1.4"):
        perturbed = perturb_sequence(sequence, PERTURBATIONS[name])
        runs[name] = run_sequence(perturbed, config, limit=40).reports[1:]
    flicker = runs["gain flicker 0.6-1.4"]
    assert all(report.status == "ok" for report in flicker)
    clean_matches = np.median([report.matches for report in runs["none"]])
    assert np.median([report.matches for report in flicker]) >= 0.7 * clean_matches


@pytest.mark.slow
@pytest.mark.euroc
def test_perturbation_benchmark_writes_and_compares(
    euroc_mh01_moving: Path, tmp_path: Path
) -> None:
    import json

    from estimator.cli.main import main

    out = tmp_path / "bench"
    args = ["bench", "perturbations", "--data", str(euroc_mh01_moving), "--out", str(out)]
    args += ["--frames", "6", "--settings", "msac", "--modes", "vision"]
    assert main([*args, "--perturbations", "black every 10th"]) == 0
    results = json.loads((out / "perturbations.json").read_text())
    summary = results["black every 10th"]["vision/msac"]
    assert summary["frames"] == 6 and summary["frames_failed"] == 0  # frame 9 is the first black
    assert summary["ate_rmse_m"] < 0.05
    (tmp_path / "before.json").write_text(json.dumps(results))
    compare = ["--compare", str(tmp_path / "before.json"), "--report-only"]
    assert main([*args, "--perturbations", "none", *compare]) == 0
    table = (out / "perturbations.md").read_text()
    assert "| black every 10th | " in table and " -> " in table
