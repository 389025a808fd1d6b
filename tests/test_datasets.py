"""Dataset readers (EuRoC/ASL, KITTI), ground-truth interpolation and trajectory files."""

from __future__ import annotations

import shutil
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from estimator.formats.datasets import (
    GroundTruth,
    detect_format,
    open_sequence,
    read_euroc_ground_truth,
    read_euroc_imu,
)
from estimator.formats.trajectory_io import (
    format_seconds,
    parse_seconds,
    read_kitti,
    read_tum,
    write_kitti,
    write_tum,
)
from estimator.geometry import make_pose, rotation_angle_deg
from estimator.rendered.synthetic import SynthOptions, synthesize

# ----------------------------------------------------------------------------- EuRoC (real)


@pytest.mark.euroc
def test_euroc_micro_pairs_frames_and_warns_about_the_unpaired(euroc_v101_micro):
    with pytest.warns(UserWarning, match=r"skipping 4 image\(s\) without a partner within 5 ms"):
        sequence = open_sequence(euroc_v101_micro)
    assert sequence.format == "euroc" and sequence.name == "euroc_v101_micro"
    assert len(sequence) == 95
    assert np.all(np.diff(sequence.timestamps_ns) > 0)
    frame = sequence.load(0)
    assert frame.left.shape == (480, 752) and frame.left.dtype == np.uint8
    assert frame.timestamp_ns == 1403715273262142976
    assert sequence.rig.baseline == pytest.approx(0.110, abs=1e-3)
    assert sequence.imu is not None and len(sequence.imu) == 981
    assert sequence.imu_noise.gyro_noise_density == pytest.approx(1.6968e-4)
    gt = sequence.ground_truth
    assert len(gt) == 99 and gt.velocities is not None and gt.accel_bias is not None
    assert gt.covers(sequence.timestamps_ns).all()


@pytest.mark.euroc
def test_euroc_accepts_the_mav0_folder_itself(euroc_v101_micro):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sequence = open_sequence(euroc_v101_micro / "mav0")
    assert len(sequence) == 95
    assert detect_format(euroc_v101_micro / "mav0") == "euroc"


@pytest.mark.euroc
def test_imu_between_is_start_exclusive_end_inclusive(euroc_v101_micro):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sequence = open_sequence(euroc_v101_micro)
    t0, t1 = sequence.timestamps_ns[:2]
    batch = sequence.imu_between(int(t0), int(t1))
    assert len(batch) == 10  # 200 Hz over 50 ms
    assert batch.timestamps_ns[0] > t0 and batch.timestamps_ns[-1] <= t1
    # Consecutive windows neither overlap nor leave gaps.
    t2 = int(sequence.timestamps_ns[2])
    joined = np.concatenate([batch.timestamps_ns, sequence.imu_between(int(t1), t2).timestamps_ns])
    np.testing.assert_array_equal(joined, sequence.imu_between(int(t0), t2).timestamps_ns)


@pytest.mark.euroc
def test_euroc_ground_truth_interpolation_on_real_rows(euroc_v101_micro):
    gt = read_euroc_ground_truth(euroc_v101_micro / "mav0/state_groundtruth_estimate0/data.csv")
    # Leave one row out, interpolate it from its neighbours: tiny error on a still drone.
    reduced = GroundTruth(np.delete(gt.timestamps_ns, 10), np.delete(gt.poses, 10, axis=0))
    estimate = reduced.interpolate([gt.timestamps_ns[10]])[0]
    assert np.linalg.norm(estimate[:3, 3] - gt.poses[10, :3, 3]) < 1e-3
    assert rotation_angle_deg(estimate[:3, :3].T @ gt.poses[10, :3, :3]) < 0.05


# ----------------------------------------------------------------------------- ground truth


def _rotating_gt() -> GroundTruth:
    """Two rows 1 s apart: moves 2 m along x while turning 90 deg about z."""
    poses = np.array(
        [
            make_pose(np.eye(3), [0.0, 0.0, 0.0]),
            make_pose(Rotation.from_euler("z", 90, degrees=True).as_matrix(), [2.0, 0.0, 0.0]),
        ]
    )
    return GroundTruth(np.array([10**18, 10**18 + 10**9], dtype=np.int64), poses)


def test_interpolation_is_linear_in_position_and_slerp_in_rotation():
    gt = _rotating_gt()
    quarter = gt.interpolate([10**18 + 250_000_000])[0]
    np.testing.assert_allclose(quarter[:3, 3], [0.5, 0.0, 0.0], atol=1e-12)
    expected = Rotation.from_euler("z", 22.5, degrees=True).as_matrix()
    np.testing.assert_allclose(quarter[:3, :3], expected, atol=1e-12)


def test_interpolation_is_exact_at_rows_and_rejects_outside_times():
    gt = _rotating_gt()
    np.testing.assert_array_equal(gt.interpolate(gt.timestamps_ns), gt.poses)
    with pytest.raises(ValueError, match="outside the ground-truth range"):
        gt.interpolate([10**18 - 1])
    with pytest.raises(ValueError, match="outside the ground-truth range"):
        gt.interpolate([10**18 + 10**9 + 1])


def test_ground_truth_rejects_bad_shapes_and_order():
    with pytest.raises(ValueError, match="increase strictly"):
        GroundTruth(np.array([2, 1]), np.tile(np.eye(4), (2, 1, 1)))
    with pytest.raises(ValueError, match="poses"):
        GroundTruth(np.array([1, 2]), np.tile(np.eye(4), (3, 1, 1)))


# ----------------------------------------------------------------------------- EuRoC (files)


@pytest.fixture(scope="module")
def small_euroc(tmp_path_factory) -> Path:
    """A 4-frame rendered EuRoC folder to corrupt in various ways (copied per test)."""
    root = tmp_path_factory.mktemp("euroc") / "seq"
    synthesize(root, SynthOptions(frames=4, length_m=0.5, seed=2))
    return root


@pytest.fixture
def euroc_copy(small_euroc, tmp_path) -> Path:
    target = tmp_path / "copy"
    shutil.copytree(small_euroc, target)
    return target


def test_malformed_csv_line_names_file_and_line(euroc_copy):
    csv = euroc_copy / "mav0/imu0/data.csv"
    lines = csv.read_text().splitlines()
    lines[5] = lines[5].replace(",", ",abc,", 1)
    csv.write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=r"imu0/data\.csv:6: malformed value"):
        read_euroc_imu(csv)
    with pytest.raises(ValueError, match=r"data\.csv:6"):
        open_sequence(euroc_copy)


def test_short_csv_row_is_reported(euroc_copy):
    csv = euroc_copy / "mav0/state_groundtruth_estimate0/data.csv"
    lines = csv.read_text().splitlines()
    lines[3] = "123,4.0"
    csv.write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=r"data\.csv:4: expected at least 8"):
        open_sequence(euroc_copy)


def test_non_increasing_camera_timestamps_are_rejected(euroc_copy):
    csv = euroc_copy / "mav0/cam0/data.csv"
    header, *rows = csv.read_text().splitlines()
    rows[1], rows[2] = rows[2], rows[1]
    csv.write_text("\n".join([header, *rows]) + "\n")
    with pytest.raises(ValueError, match="increase strictly"):
        open_sequence(euroc_copy)


def test_missing_image_file_is_skipped_with_a_warning(euroc_copy):
    images = sorted((euroc_copy / "mav0/cam1/data").iterdir())
    images[1].unlink()
    with pytest.warns(UserWarning, match="image file is missing"):
        sequence = open_sequence(euroc_copy)
    assert len(sequence) == 3
    assert images[1].stem not in {str(t) for t in sequence.timestamps_ns}
    assert [str(t) for t in sequence.missing_ns] == [images[1].stem]  # counted by a run


def test_missing_files_and_folders_fail_clearly(euroc_copy, tmp_path):
    with pytest.raises(FileNotFoundError, match="not found"):
        detect_format(tmp_path / "nowhere")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="cannot tell the dataset format"):
        detect_format(tmp_path / "empty")
    (euroc_copy / "mav0/cam1/sensor.yaml").unlink()
    with pytest.raises(FileNotFoundError, match=r"cam1/sensor\.yaml"):
        open_sequence(euroc_copy)
    with pytest.raises(ValueError, match="unknown dataset format"):
        open_sequence(euroc_copy, format="tum")  # type: ignore[arg-type]


def test_sequence_without_imu_and_ground_truth_still_opens(euroc_copy):
    shutil.rmtree(euroc_copy / "mav0/imu0")
    shutil.rmtree(euroc_copy / "mav0/state_groundtruth_estimate0")
    sequence = open_sequence(euroc_copy)
    assert sequence.imu is None and sequence.ground_truth is None
    assert len(sequence.imu_between(0, 2**62)) == 0


def test_16_bit_images_stay_16_bit(euroc_copy):
    record = open_sequence(euroc_copy).frames[0]
    image = cv2.imread(str(record.left_path), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(record.left_path), image.astype(np.uint16) * 257)
    frame = open_sequence(euroc_copy).load(0)
    assert frame.left.dtype == np.uint16 and frame.right.dtype == np.uint8
    np.testing.assert_array_equal(frame.left, image.astype(np.uint16) * 257)


# ----------------------------------------------------------------------------- KITTI


def _kitti_folder(root: Path, frames: int = 4, labelled: bool = True, times: bool = True) -> Path:
    root.mkdir(parents=True)
    rng = np.random.default_rng(0)
    for folder in ("image_0", "image_1"):
        (root / folder).mkdir()
        for i in range(frames):
            image = rng.integers(0, 255, (376, 1241), dtype=np.uint8)
            cv2.imwrite(str(root / folder / f"{i:06d}.png"), image)
    p0 = "718.856 0 607.1928 0 0 718.856 185.2157 0 0 0 1 0"
    p1 = "718.856 0 607.1928 -386.1448 0 718.856 185.2157 0 0 0 1 0"
    if labelled:
        text = f"P0: {p0}\nP1: {p1}\nP2: {p0}\nP3: {p1}\nTr: {p0}\n"
    else:
        text = f"{p0}\n{p1}\n"
    (root / "calib.txt").write_text(text)
    if times:
        (root / "times.txt").write_text("".join(f"{0.1036 * i:e}\n" for i in range(frames)))
    poses = np.tile(np.eye(4), (frames, 1, 1))
    poses[:, 2, 3] = np.arange(frames) * 0.8
    write_kitti(root / "poses.txt", poses)
    return root


@pytest.mark.parametrize("labelled", [True, False])
def test_kitti_sequence_with_both_calib_forms(tmp_path, labelled):
    root = _kitti_folder(tmp_path / "00", labelled=labelled)
    assert detect_format(root) == "kitti"
    sequence = open_sequence(root)
    assert sequence.format == "kitti" and len(sequence) == 4
    assert sequence.rig.baseline == pytest.approx(386.1448 / 718.856)
    assert sequence.rig.left.size == (1241, 376)
    np.testing.assert_array_equal(sequence.timestamps_ns, [0, 103600000, 207200000, 310800000])
    gt = sequence.ground_truth
    np.testing.assert_allclose(gt.poses[:, 2, 3], [0.0, 0.8, 1.6, 2.4])
    np.testing.assert_array_equal(sequence.rig.left.T_BS, np.eye(4))
    assert sequence.imu is None
    assert sequence.load(3).left.shape == (376, 1241)


def test_kitti_without_times_assumes_10_hz(tmp_path):
    sequence = open_sequence(_kitti_folder(tmp_path / "01", times=False))
    np.testing.assert_array_equal(sequence.timestamps_ns, np.arange(4) * 100_000_000)


def test_kitti_count_mismatch_and_missing_calib_fail_clearly(tmp_path):
    root = _kitti_folder(tmp_path / "02")
    (root / "times.txt").write_text("0.0\n0.1\n")
    with pytest.raises(ValueError, match=r"times\.txt has 2 entries"):
        open_sequence(root)
    (root / "times.txt").unlink()
    (root / "calib.txt").unlink()
    with pytest.raises(FileNotFoundError, match=r"calib\.txt"):
        open_sequence(root)


# ----------------------------------------------------------------------------- trajectory files


def _random_poses(count: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (count, 1, 1))
    poses[:, :3, :3] = Rotation.random(count, random_state=seed).as_matrix()
    poses[:, :3, 3] = rng.normal(0, 50, (count, 3))
    return poses


def test_tum_round_trip_keeps_nanoseconds_and_poses(tmp_path):
    timestamps = np.array(
        [1403715273262142976, 1403715273312143104, 1403715273312143105], dtype=np.int64
    )
    poses = _random_poses(3)
    write_tum(tmp_path / "t.tum", timestamps, poses)
    read_t, read_poses = read_tum(tmp_path / "t.tum")
    np.testing.assert_array_equal(read_t, timestamps)
    np.testing.assert_allclose(read_poses, poses, atol=1e-12)
    first = (tmp_path / "t.tum").read_text().splitlines()[1].split()
    assert first[0] == "1403715273.262142976" and len(first) == 8


def test_kitti_round_trip(tmp_path):
    poses = _random_poses(5, seed=1)
    write_kitti(tmp_path / "k.txt", poses)
    np.testing.assert_array_equal(read_kitti(tmp_path / "k.txt"), poses)


def test_seconds_formatting_is_exact():
    for value in (0, 1, 999_999_999, 1_000_000_000, 1403715273262142976, -1_500_000_000):
        assert parse_seconds(format_seconds(value)) == value
    assert format_seconds(-1_500_000_000) == "-1.500000000"
    assert parse_seconds("1.5") == 1_500_000_000
    with pytest.raises(ValueError, match="timestamp"):
        parse_seconds("soon")


def test_malformed_trajectory_files_fail_with_line_numbers(tmp_path):
    (tmp_path / "bad.tum").write_text("# header\n1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 1\n")
    with pytest.raises(ValueError, match=r"bad\.tum:3: expected 8 values"):
        read_tum(tmp_path / "bad.tum")
    (tmp_path / "zero.tum").write_text("1.0 0 0 0 0 0 0 0\n")
    with pytest.raises(ValueError, match="zero quaternion"):
        read_tum(tmp_path / "zero.tum")
    (tmp_path / "bad.txt").write_text("1 0 0 0 0 1 0 0 0 0 1\n")
    with pytest.raises(ValueError, match=r"bad\.txt:1: expected 12 numbers"):
        read_kitti(tmp_path / "bad.txt")
    with pytest.raises(FileNotFoundError):
        read_tum(tmp_path / "missing.tum")
    with pytest.raises(ValueError, match="timestamps for"):
        write_tum(tmp_path / "x.tum", np.array([1, 2]), _random_poses(3))
