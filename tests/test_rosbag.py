"""ROS bags in and out: bags written from the real EuRoC clip give the folder's trajectory."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest
import yaml

from estimator.cli.main import main
from estimator.formats.bag_calibration import load_bag_calibration, load_kalibr_rig
from estimator.formats.calibration_files import load_euroc_rig
from estimator.formats.datasets import open_sequence
from estimator.formats.rosbag_io import open_bag
from estimator.formats.rosbag_write import (
    CAMERA_POSE_TOPIC,
    ODOMETRY_TOPIC,
    _BagWriter,
    read_pose_topic,
    write_stereo_bag,
)
from estimator.formats.trajectory_io import read_tum
from estimator.geometry import invert_pose
from estimator.odometry import to_grey8
from estimator.types import ImuNoise

pytestmark = pytest.mark.euroc
FRAMES = 20


def _sequence(path: Path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # EuRoC's unpaired camera rows
        return open_sequence(path)


@pytest.fixture(scope="module")
def folder_run(euroc_mh01_moving, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("folder") / "out"
    args = ["run", str(euroc_mh01_moving), "--limit", str(FRAMES), "--out", str(out), "--quiet"]
    assert main(args) == 0
    return out


def _run_bag(bag: Path, calibration: Path, out: Path, *extra: str) -> int:
    return main(
        ["run", str(bag), "--calibration", str(calibration), "--out", str(out), "--quiet", *extra]
    )


@pytest.mark.slow
@pytest.mark.parametrize(
    ("name", "encoding", "storage"),
    [("clip.bag", "mono8", "sqlite3"), ("clip_ros2", "mono16", "sqlite3")],
)
def test_bag_gives_the_folder_trajectory_and_exports_it(
    euroc_mh01_moving, folder_run, tmp_path, name, encoding, storage
):
    bag = tmp_path / name
    write_stereo_bag(bag, _sequence(euroc_mh01_moving), FRAMES, encoding, storage)
    out, exported = (
        tmp_path / "out",
        tmp_path / ("export.bag" if name.endswith(".bag") else "export"),
    )
    assert _run_bag(bag, euroc_mh01_moving, out, "--export-bag", str(exported)) == 0
    for file in ("trajectory.tum", "trajectory_smoothed.tum", "odometry.tum"):
        stamps, poses = read_tum(out / file)
        folder_stamps, folder_poses = read_tum(folder_run / file)
        assert np.array_equal(stamps, folder_stamps) and len(stamps) == FRAMES
        assert np.abs(poses[:, :3, 3] - folder_poses[:, :3, 3]).max() <= 1e-9, file
    lines = (out / "odometry.jsonl").read_text().splitlines()
    assert lines == (folder_run / "odometry.jsonl").read_text().splitlines()
    # The exported bag read back: Odometry = odometry.tum, PoseStamped = trajectory.tum.
    for topic, file in ((ODOMETRY_TOPIC, "odometry.tum"), (CAMERA_POSE_TOPIC, "trajectory.tum")):
        stamps, poses = read_pose_topic(exported, topic)
        tum_stamps, tum_poses = read_tum(out / file)
        assert np.array_equal(stamps, tum_stamps)
        assert np.abs(poses - tum_poses).max() < 1e-12, topic
    first = json.loads(lines[0])
    assert first["header"]["frame_id"] == "odom" and first["child_frame_id"] == "base_link"


def test_kalibr_camchain_gives_the_euroc_rig_and_topics(euroc_mh01_moving, tmp_path):
    mav0 = euroc_mh01_moving / "mav0"
    rig = load_euroc_rig(mav0 / "cam0" / "sensor.yaml", mav0 / "cam1" / "sensor.yaml")
    chain = {}
    for index, camera in enumerate((rig.left, rig.right)):
        chain[f"cam{index}"] = {
            "camera_model": "pinhole",
            "intrinsics": [camera.fx, camera.fy, camera.cx, camera.cy],
            "distortion_model": "radtan",
            "distortion_coeffs": list(camera.distortion),
            "resolution": [camera.width, camera.height],
            "T_cam_imu": invert_pose(camera.T_BS).tolist(),
            "rostopic": f"/cam{index}/image_raw",
        }
    path = tmp_path / "camchain.yaml"
    path.write_text(yaml.safe_dump(chain))
    kalibr, topics = load_kalibr_rig(path)
    assert topics == ("/cam0/image_raw", "/cam1/image_raw")
    for ours, theirs in ((kalibr.left, rig.left), (kalibr.right, rig.right)):
        assert np.allclose(ours.T_BS, theirs.T_BS, atol=1e-12)
        assert ours.K.tolist() == theirs.K.tolist()
    calibration = load_bag_calibration(path)
    assert calibration.left_topic == "/cam0/image_raw"
    # cam1 placed through T_cn_cnm1 instead of its own T_cam_imu: the same rig.
    del chain["cam1"]["T_cam_imu"]
    chain["cam1"]["T_cn_cnm1"] = (invert_pose(rig.right.T_BS) @ rig.left.T_BS).tolist()
    path.write_text(yaml.safe_dump(chain))
    assert np.allclose(load_kalibr_rig(path)[0].right.T_BS, rig.right.T_BS, atol=1e-9)


def test_kalibr_imu_yaml_beside_the_camchain_sets_the_imu_noise(
    euroc_mh01_moving, small_bag, tmp_path
):
    mav0 = euroc_mh01_moving / "mav0"
    rig = load_euroc_rig(mav0 / "cam0" / "sensor.yaml", mav0 / "cam1" / "sensor.yaml")
    chain = {
        f"cam{index}": {
            "intrinsics": [camera.fx, camera.fy, camera.cx, camera.cy],
            "distortion_model": "radtan", "distortion_coeffs": list(camera.distortion),
            "resolution": [camera.width, camera.height],
            "T_cam_imu": invert_pose(camera.T_BS).tolist(),
        }
        for index, camera in enumerate((rig.left, rig.right))
    }
    camchain = tmp_path / "camchain-imucam-flight.yaml"
    camchain.write_text(yaml.safe_dump(chain))
    assert load_bag_calibration(camchain).imu_file is None  # none beside it: the default
    values = {"accelerometer_noise_density": 1.86e-3, "accelerometer_random_walk": 4.33e-4,
              "gyroscope_noise_density": 1.87e-4, "gyroscope_random_walk": 2.66e-5,
              "update_rate": 200.0}
    # Kalibr's input form (flat) as imu.yaml; its result form (under imu0) as imu-NAME.yaml.
    (tmp_path / "imu.yaml").write_text(yaml.safe_dump({**values, "rostopic": "/imu0"}))
    expected = ImuNoise(gyro_noise_density=1.87e-4, gyro_random_walk=2.66e-5,
                        accel_noise_density=1.86e-3, accel_random_walk=4.33e-4, rate_hz=200.0)
    calibration = load_bag_calibration(camchain)
    assert calibration.imu_noise == expected and calibration.imu_topic == "/imu0"
    result = {**values, "update_rate": 400.0, "rostopic": "/imu0"}
    (tmp_path / "imu-flight.yaml").write_text(yaml.safe_dump({"imu0": result}))
    calibration = load_bag_calibration(camchain)
    assert calibration.imu_file == tmp_path / "imu-flight.yaml"
    assert calibration.imu_noise.rate_hz == 400.0
    # The bag's sequence carries it to the back end (run_sequence hands it to the odometry).
    sequence = open_bag(small_bag, calibration)
    assert sequence.topics.imu == "/imu0" and sequence.imu_noise == calibration.imu_noise
    # A malformed file is a one-line error.
    (tmp_path / "imu-flight.yaml").write_text(yaml.safe_dump({"imu0": {"update_rate": 200}}))
    with pytest.raises(ValueError, match="missing Kalibr IMU field"):
        load_bag_calibration(camchain)


# ----------------------------------------------------------------------------- bad input


@pytest.fixture(scope="module")
def small_bag(euroc_mh01_moving, tmp_path_factory) -> Path:
    bag = tmp_path_factory.mktemp("small") / "small.bag"
    write_stereo_bag(bag, _sequence(euroc_mh01_moving), 3)
    return bag


def _write_images(path: Path, topics_and_stamps, encoding: str = "mono8") -> None:
    image = np.zeros((480, 752), dtype=np.uint8)
    with _BagWriter(path) as writer:
        for topic, stamp in topics_and_stamps:
            message = writer.type("sensor_msgs/msg/Image")(
                header=writer.header(stamp, "cam"),
                height=480,
                width=752,
                encoding=encoding,
                is_bigendian=0,
                step=752,
                data=image.ravel(),
            )
            writer.write(topic, "sensor_msgs/msg/Image", stamp, message)


def test_left_and_right_pair_by_the_nearest_stamp_within_the_tolerance(
    euroc_mh01_moving, tmp_path
):
    """Cameras stamped up to 2 ms apart pair (each image with its own partner); an image
    without a partner within the tolerance is dropped with one warning that counts it."""
    period = 50_000_000
    jitter = (np.array([1.2, -0.3, 2.0, 0.1, -1.8, 0.4]) * 1e6).astype(np.int64)
    bag = tmp_path / "jitter.bag"
    with _BagWriter(bag) as writer:
        for k in range(6):
            for topic, stamp, value in (("/left", k * period + 10**9, k),
                                        ("/right", k * period + 10**9 + int(jitter[k]), 100 + k)):
                image = np.full((480, 752), value, dtype=np.uint8)
                message = writer.type("sensor_msgs/msg/Image")(
                    header=writer.header(stamp, "cam"), height=480, width=752,
                    encoding="mono8", is_bigendian=0, step=752, data=image.ravel())
                writer.write(topic, "sensor_msgs/msg/Image", stamp, message)
        stray = 10**9 + 2 * period + period // 2  # half way between two frames
        message = writer.type("sensor_msgs/msg/Image")(
            header=writer.header(stray, "cam"), height=480, width=752, encoding="mono8",
            is_bigendian=0, step=752, data=np.zeros(480 * 752, dtype=np.uint8))
        writer.write("/right", "sensor_msgs/msg/Image", stray, message)
    calibration = load_bag_calibration(euroc_mh01_moving)
    with pytest.warns(UserWarning, match=r"skipping 1 image\(s\) without a partner within 5 ms"):
        sequence = open_bag(bag, calibration, "/left", "/right")
    assert [f.timestamp_ns for f in sequence.frames] == [k * period + 10**9 for k in range(6)]
    for k in (0, 3, 5, 2):  # out of order too: the stream restarts
        frame = sequence.load(k)
        assert frame.timestamp_ns == k * period + 10**9
        assert frame.left[0, 0] == k and frame.right[0, 0] == 100 + k
    # A tolerance below the jitter drops the pairs that are farther apart.
    with pytest.warns(UserWarning, match="without a partner within 0.5 ms"):
        strict = open_bag(bag, calibration, "/left", "/right", stereo_sync_tolerance_ns=500_000)
    assert [f.timestamp_ns for f in strict.frames] == [k * period + 10**9 for k in (1, 3, 5)]
    # The client's replay pairs the same way (``--stereo-sync-tolerance MS``).
    from swarmvo_client.bags import open_local_bag
    from swarmvo_client.cli import build_parser

    args = build_parser().parse_args(["replay", str(bag), "--stereo-sync-tolerance", "0.5"])
    with pytest.warns(UserWarning, match="without a partner within 0.5 ms"):
        replayed = open_local_bag(bag, euroc_mh01_moving, "/left", "/right",
                                  stereo_sync_tolerance_ms=args.stereo_sync_tolerance)
    assert [f.timestamp_ns for f in replayed.frames] == [f.timestamp_ns for f in strict.frames]
    with pytest.raises(ValueError, match="must be >= 0 ms"):
        open_local_bag(bag, euroc_mh01_moving, "/left", "/right", stereo_sync_tolerance_ms=-1)


def _one_error_line(capsys, code: int, *expected: str) -> None:
    error = capsys.readouterr().err
    assert code == 2
    lines = [line for line in error.splitlines() if line.startswith("swarmvo run: error:")]
    assert len(lines) == 1 and "Traceback" not in error, error
    for text in expected:
        assert text in lines[0], lines[0]


def test_bad_bags_give_one_error_line(euroc_mh01_moving, small_bag, tmp_path, capsys):
    out = tmp_path / "out"
    code = _run_bag(small_bag, euroc_mh01_moving, out, "--left-topic", "/missing")
    _one_error_line(capsys, code, "/missing", "not in the bag", "/cam0/image_raw")
    code = main(["run", str(small_bag), "--out", str(out), "--quiet"])
    _one_error_line(capsys, code, "--calibration")
    # Truncated file.
    truncated = tmp_path / "truncated.bag"
    truncated.write_bytes(small_bag.read_bytes()[: small_bag.stat().st_size // 2])
    _one_error_line(capsys, _run_bag(truncated, euroc_mh01_moving, out), "truncated.bag")
    # Left and right stamps that never come within the tolerance (0.1 s at 1 Hz).
    mismatched = tmp_path / "mismatched.bag"
    _write_images(
        mismatched,
        [
            ("/left", 10**9),
            ("/right", 10**9 + 300_000_000),
            ("/left", 2 * 10**9),
            ("/right", 2 * 10**9 + 300_000_000),
        ],
    )
    _one_error_line(
        capsys, _run_bag(mismatched, euroc_mh01_moving, out), "no left/right image pair",
        "within 100 ms",
    )
    code = _run_bag(mismatched, euroc_mh01_moving, out, "--stereo-sync-tolerance", "-1")
    _one_error_line(capsys, code, "--stereo-sync-tolerance must be >= 0")
    # Ambiguous topics: names that do not tell left from right.
    ambiguous = tmp_path / "ambiguous"
    _write_images(ambiguous, [("/a/image", 10**9), ("/b/image", 10**9)])
    _one_error_line(capsys, _run_bag(ambiguous, euroc_mh01_moving, out), "/a/image", "/b/image")
    # An encoding the reader does not know.
    unknown = tmp_path / "unknown.bag"
    _write_images(
        unknown,
        [(t, s) for s in (10**9, 2 * 10**9) for t in ("/left", "/right")],
        encoding="yuv422",
    )
    _one_error_line(capsys, _run_bag(unknown, euroc_mh01_moving, out), "yuv422")


@pytest.mark.parametrize(
    ("name", "encoding", "storage"),
    [("c.bag", "bgr8", "sqlite3"), ("c_mcap", "png", "mcap"), ("c_mcap16", "mono16", "mcap")],
)
def test_every_encoding_and_storage_decodes_to_the_folder_pixels(
    euroc_mh01_moving, tmp_path, name, encoding, storage
):
    """Equal pixels, stamps and IMU: the pipeline then gives the folder's trajectory."""
    sequence = _sequence(euroc_mh01_moving)
    write_stereo_bag(tmp_path / name, sequence, 3, encoding, storage)
    bag = open_bag(tmp_path / name, load_bag_calibration(euroc_mh01_moving))
    for index in range(3):
        frame, expected = bag.load(index), sequence.load(index)
        assert frame.timestamp_ns == expected.timestamp_ns
        for ours, theirs in ((frame.left, expected.left), (frame.right, expected.right)):
            assert np.array_equal(to_grey8(ours), theirs)
    assert bag.imu is not None
    reference = sequence.imu_between(bag.imu.timestamps_ns[0] - 1, bag.imu.timestamps_ns[-1])
    assert np.array_equal(bag.imu.gyro, reference.gyro)
    assert np.array_equal(bag.imu.accel, reference.accel)


def test_streaming_restarts_and_closes(euroc_mh01_moving, small_bag):
    bag = open_bag(small_bag, load_bag_calibration(euroc_mh01_moving))
    sequence = _sequence(euroc_mh01_moving)
    assert bag.topics is not None and bag.topics.imu == "/imu0" and len(bag) == 3
    for index in (0, 2, 1, 2):  # out of order: the stream starts again
        frame = bag.load(index)
        assert np.array_equal(frame.left, sequence.load(index).left)
    bag.close()
    with pytest.raises(IndexError):
        bag.load(3)


def test_one_corrupt_compressed_image_skips_its_frame(euroc_mh01_moving, tmp_path, capsys):
    import cv2

    sequence = _sequence(euroc_mh01_moving)
    bag = tmp_path / "corrupt.bag"
    with _BagWriter(bag) as writer:
        for index in range(4):
            frame = sequence.load(index)
            for topic, image in (("/cam0/image_raw", frame.left), ("/cam1/image_raw", frame.right)):
                data = cv2.imencode(".png", image)[1].ravel()
                if index == 1 and topic == "/cam0/image_raw":
                    data = data[:100]  # cut short: not decodable
                message = writer.type("sensor_msgs/msg/CompressedImage")(
                    header=writer.header(frame.timestamp_ns, "cam"), format="png", data=data
                )
                writer.write(topic, "sensor_msgs/msg/CompressedImage", frame.timestamp_ns, message)
    out = tmp_path / "out"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert _run_bag(bag, euroc_mh01_moving, out, "--no-backend") == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frames"] == 3 and metrics["frames_skipped"] == 1
    assert len((out / "odometry.jsonl").read_text().splitlines()) == 3
    code = _run_bag(bag, euroc_mh01_moving, tmp_path / "strict", "--strict")
    _one_error_line(capsys, code, "cannot decode a compressed image")
