"""Adapter between the service and the estimator: validate calibrations/configs, build pipelines.

The app receives a :class:`PipelineFactory`; production uses :class:`EstimatorFactory`
(the real ``Odometry``), tests may inject their own. Everything here raises ``ValueError`` with a
message fit for a 422 answer.
"""

from __future__ import annotations

import importlib
import logging
import math
import os
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from estimator.types import FrameReport, ImuBatch, ImuNoise, StereoFrame


class Pipeline(Protocol):
    def process(self, frame: StereoFrame, imu: ImuBatch | None = None) -> FrameReport: ...


@dataclass(frozen=True)
class PreparedSession:
    """A validated session description in the normalised form that gets stored."""

    calibration: dict[str, Any]
    config: dict[str, Any]
    imu_noise: dict[str, Any] | None
    image_size: tuple[int, int]  # (width, height)


class PipelineFactory(Protocol):
    def prepare(
        self,
        calibration: dict[str, Any],
        config: dict[str, Any],
        imu_noise: dict[str, Any] | None,
        frame_rate_hz: float | None = None,
    ) -> PreparedSession: ...

    def create(
        self, prepared: PreparedSession, initial_pose: np.ndarray | None, first_index: int
    ) -> Pipeline: ...


def reject_non_finite(value: Any, where: str) -> None:
    """NaN/inf anywhere in a JSON document is an input error, not a number to compute with."""
    if isinstance(value, float) and not math.isfinite(value):
        raise ValueError(f"{where} contains a non-finite number ({value})")
    if isinstance(value, dict):
        for key, item in value.items():
            reject_non_finite(item, f"{where}.{key}")
    elif isinstance(value, list | tuple):
        for position, item in enumerate(value):
            reject_non_finite(item, f"{where}[{position}]")


def normalise_imu_noise(imu_noise: dict[str, Any] | None) -> dict[str, Any] | None:
    if imu_noise is None:
        return None
    reject_non_finite(imu_noise, "imu_noise")
    try:
        noise = ImuNoise(**imu_noise)
    except TypeError as error:
        raise ValueError(f"invalid imu_noise: {error}") from error
    values = asdict(noise)
    for name, value in values.items():
        if not isinstance(value, int | float) or isinstance(value, bool):
            raise ValueError(f"imu_noise.{name} must be a number")
        if not math.isfinite(value) or value < 0:
            raise ValueError(f"imu_noise.{name} must be finite and >= 0, got {value}")
    if values["rate_hz"] <= 0:
        raise ValueError("imu_noise.rate_hz must be > 0")
    return {name: float(value) for name, value in values.items()}


class EstimatorFactory:
    """Production factory: ``StereoRig`` + ``SwarmvoConfig`` + the real ``Odometry``."""

    def prepare(
        self,
        calibration: dict[str, Any],
        config: dict[str, Any],
        imu_noise: dict[str, Any] | None,
        frame_rate_hz: float | None = None,
    ) -> PreparedSession:
        """Validated session; the frontend settings that follow from the rig (and the declared
        frame rate) are filled in where the config leaves them (``estimator.rig_settings``)."""
        from estimator.config import FRAME_INTERVAL_CONTEXT, SwarmvoConfig
        from estimator.formats.calibration import StereoRig
        from estimator.rig_settings import (
            RIG_SETTINGS_KEY,
            apply_rig_settings,
            interval_dependent,
            settings_record,
        )

        reject_non_finite(calibration, "calibration")
        config = {k: v for k, v in config.items() if k != RIG_SETTINGS_KEY}  # a copied session's
        reject_non_finite(config, "config")
        if frame_rate_hz is not None and not (math.isfinite(frame_rate_hz) and frame_rate_hz > 0):
            raise ValueError(f"frame_rate_hz must be a positive number, got {frame_rate_hz}")
        try:
            rig = StereoRig.from_dict(calibration)
        except (TypeError, KeyError) as error:
            raise ValueError(f"invalid calibration: {error}") from error
        interval = 1.0 / frame_rate_hz if frame_rate_hz else None
        try:
            context = {FRAME_INTERVAL_CONTEXT: interval}  # old keys counted in frames
            swarm_config = SwarmvoConfig.model_validate(config, context=context)
        except ValueError as error:  # pydantic.ValidationError is a ValueError
            raise ValueError(f"invalid config: {_short_validation(error)}") from error
        try:
            swarm_config, derived = apply_rig_settings(swarm_config, rig, interval)
        except ValueError as error:
            raise ValueError(f"invalid config: {_short_validation(error)}") from error
        stored = swarm_config.model_dump(mode="json")
        from_stamps = interval is None and interval_dependent(swarm_config)
        stored[RIG_SETTINGS_KEY] = settings_record(interval, derived, from_stamps)
        return PreparedSession(
            calibration=rig.to_dict(),
            config=stored,
            imu_noise=normalise_imu_noise(imu_noise),
            image_size=rig.size,
        )

    def check(self, prepared: PreparedSession) -> None:
        """Dry run at creation: what would fail every frame must fail here, with its reason.

        Builds the real ``Odometry`` (rig and config cross-checks: camera models, depth range),
        draws the first frame seed and runs the configured registration once on a few
        synthetic pairs (unknown or invalid ``registration.options``). Call it only after the
        work limits were checked: the registration runs with the session's options.
        """
        from estimator.formats.calibration import StereoRig
        from estimator.odometry import Odometry, frame_seed
        from estimator.registration.registry import estimator_spec, register

        config, _ = session_config(prepared.config)
        noise = None if prepared.imu_noise is None else ImuNoise(**prepared.imu_noise)
        try:
            Odometry(StereoRig.from_dict(prepared.calibration), config=config, imu_noise=noise)
            seed = frame_seed(config.seed, 0)
        except (TypeError, ValueError) as error:
            raise ValueError(f"the session cannot run: {error}") from error
        source = np.random.default_rng(0).uniform(-2.0, 2.0, (24, 3))
        source[:, 2] += 5.0
        target = source.copy()
        target[:, 0] += 0.05
        registration = config.registration
        options: dict[str, Any] = dict(registration.options)
        if registration.use_point_sigmas and estimator_spec(registration.method).takes_covariances:
            covariance = np.tile(np.eye(3) * 1e-4, (len(source), 1, 1))
            options["source_cov"], options["target_cov"] = covariance, covariance
        try:
            register(source, target, method=registration.method, seed=seed, **options)
        except (TypeError, ValueError) as error:
            raise ValueError(f"invalid registration.options: {error}") from error

    def warm_up(self) -> None:
        """Prepare a new worker process: imports, lazily loaded modules and compiled kernels.

        A few synthetic textured frames (with IMU) go through a throw-away ``Odometry`` with the
        default configuration, so this one-off cost (a few hundred ms) is not paid by the
        first frames of a robot. Best effort: a failure here only means a slower first frame.
        """
        start = time.perf_counter()
        for module in ("estimator.formats.calibration", "estimator.config", "estimator.odometry"):
            importlib.import_module(module)
        logger = logging.getLogger("swarmvo.service")
        try:
            synthetic_run(self)
            registration_kernels()
            detector_kernels()
        except Exception:
            logger.debug("warm-up run failed", exc_info=True)
        # Minutes instead of seconds here mean an empty or unreadable JIT cache (docker/).
        logger.info("worker process %d warmed up in %.1f s", os.getpid(),
                    time.perf_counter() - start)

    def create(
        self, prepared: PreparedSession, initial_pose: np.ndarray | None, first_index: int
    ) -> Pipeline:
        from estimator.formats.calibration import StereoRig
        from estimator.odometry import Odometry

        noise = None if prepared.imu_noise is None else ImuNoise(**prepared.imu_noise)
        rig = StereoRig.from_dict(prepared.calibration)
        config, from_stamps = session_config(prepared.config)
        odometry = Odometry(
            rig,
            config=config,
            imu_noise=noise,
            initial_pose=initial_pose,
            first_index=first_index,
        )
        answers = OdometryAnswers(odometry, rig.left.T_BS, config,
                                  resumed=initial_pose is not None)
        return IntervalSettings(answers, rig) if from_stamps else answers


class OdometryAnswers:
    """``Odometry`` plus the odometry message of each frame (``estimator.formats.odometry_msg``).

    The odom frame follows the library's rule from the session's first frame and its IMU
    samples. A pipeline resumed from a stored pose continues in the world of the stored poses:
    odom is that world with the back end (its world is the levelled, or without IMU the plain,
    first body pose) and the first body pose (T_BS from the first left camera) without it; the
    covariance chain starts again at the resumed pose.
    """

    def __init__(self, odometry: Any, body_from_camera: np.ndarray, config: Any,
                 resumed: bool) -> None:
        self.odometry = odometry
        self._body_from_camera = body_from_camera
        self._backend = config.backend
        self._odom_from_world = None
        if resumed:
            self._odom_from_world = np.eye(4) if config.backend.enabled else body_from_camera
        self._builder: Any = None
        self.last_odometry: dict[str, Any] | None = None

    def process(self, frame: StereoFrame, imu: ImuBatch | None = None) -> FrameReport:
        from estimator.formats.odometry_msg import OdometryBuilder

        report = self.odometry.process(frame, imu)
        if self._builder is None:
            self._builder = OdometryBuilder(
                self._body_from_camera,
                self._backend,
                first_accel=imu.accel if imu is not None else None,
                odom_from_world=self._odom_from_world,
            )
        self.last_odometry = self._builder.build(report).to_dict()
        return report

    def state(self) -> dict[str, Any]:
        """The odometry's state after the last frame (stored with its pose)."""
        return self.odometry.state()

    def restore(self, state: dict[str, Any]) -> None:
        self.odometry.restore(state)

    def finish(self) -> tuple[tuple[int, np.ndarray], ...]:
        """The back end's final poses of the frames still in its window (the session ends)."""
        return self.odometry.finish()


def session_config(stored: dict[str, Any]) -> tuple[Any, bool]:
    """A stored session configuration as ``SwarmvoConfig``, and whether its frame-interval
    settings still come from the first frames' stamps (no rate was declared)."""
    from estimator.config import SwarmvoConfig
    from estimator.rig_settings import RIG_SETTINGS_KEY

    record = stored.get(RIG_SETTINGS_KEY) or {}
    config = SwarmvoConfig.model_validate(
        {k: v for k, v in stored.items() if k != RIG_SETTINGS_KEY}
    )
    return config, bool(record.get("from_stamps", False))


class IntervalSettings:
    """A session without a declared frame rate: the settings that depend on the frame interval
    (the search window) follow from the stamps, before each frame is matched: from the first
    interval at the second frame, then from the median of the first intervals
    (``FrameIntervalEstimate``) whenever it moves."""

    def __init__(self, answers: OdometryAnswers, rig: Any) -> None:
        from estimator.rig_settings import FrameIntervalEstimate

        self.answers = answers
        self.rig = rig
        self._intervals = FrameIntervalEstimate()

    @property
    def last_odometry(self) -> dict[str, Any] | None:
        return self.answers.last_odometry

    def process(self, frame: StereoFrame, imu: ImuBatch | None = None) -> FrameReport:
        interval_s = self._intervals.add(int(frame.timestamp_ns))
        if interval_s is not None:
            self._derive(interval_s)
        return self.answers.process(frame, imu)

    def finish(self) -> tuple[tuple[int, np.ndarray], ...]:
        return self.answers.finish()

    def state(self) -> dict[str, Any]:
        return self.answers.state()

    def restore(self, state: dict[str, Any]) -> None:
        self.answers.restore(state)

    def _derive(self, interval_s: float) -> None:
        from estimator.config import FrontendConfig
        from estimator.rig_settings import derive_rig_settings

        odometry = self.answers.odometry
        values = {s.name: s.value
                  for s in derive_rig_settings(self.rig, interval_s, FrontendConfig())}
        values.pop("max_depth_m", None)  # from the rig alone: applied at creation
        frontend = odometry.config.frontend.model_copy(update=values)
        odometry.config = odometry.config.model_copy(update={"frontend": frontend})


def synthetic_run(factory: EstimatorFactory, frames: int = 4) -> None:
    """Blurred random texture seen by a stereo pair (8 px disparity) sliding 2 px per frame."""
    import cv2

    width, height, disparity, step = 320, 240, 8, 2
    rng = np.random.default_rng(0)
    noise = (rng.random((height, width + disparity + step * frames)) * 255).astype(np.uint8)
    texture = cv2.GaussianBlur(noise, (0, 0), 1.2)

    def camera(x: float) -> dict[str, Any]:
        transform = np.eye(4)
        transform[0, 3] = x
        return {"width": width, "height": height, "fx": 300.0, "fy": 300.0, "cx": width / 2,
                "cy": height / 2, "distortion_model": "none", "distortion": [],
                "T_BS": transform.tolist()}

    prepared = factory.prepare({"left": camera(0.0), "right": camera(0.1)}, {}, {})
    pipeline = factory.create(prepared, None, 0)
    period_ns = 50_000_000
    for k in range(frames):
        left = np.ascontiguousarray(texture[:, step * k : step * k + width])
        right = np.ascontiguousarray(
            texture[:, step * k + disparity : step * k + disparity + width]
        )
        imu = None
        if k:
            times = np.arange((k - 1) * period_ns + 5_000_000, k * period_ns + 1, 5_000_000)
            accel = np.tile([0.0, 0.0, 9.81], (len(times), 1))
            imu = ImuBatch(times.astype(np.int64), np.zeros((len(times), 3)), accel)
        pipeline.process(StereoFrame(k * period_ns, left, right), imu)


def registration_kernels() -> None:
    """Run the registration kernels the synthetic frames do not reach (real frames do).

    The threshold ladder judges an unsettled set only on real frames. Without this, a worker
    with an empty JIT cache compiles these kernels inside a frame, where the frame's CPU budget
    interrupts the compile: the frame is refused, and the cache is never written
    (docs/performance.md).
    """
    import estimator
    from estimator.registration.swarm_kernels import degenerate_points, fit_pose

    points = np.random.default_rng(0).normal(size=(60, 3))
    estimator.register(points, points + 1.0, seed=0)
    estimator.register(points, points + 1.0, seed=0, sigmas=np.ones(len(points)))
    estimator.register(points, points + 1.0, method="pso", seed=0)
    everyone = np.ones(len(points), dtype=bool)
    degenerate_points(points, np.flatnonzero(everyone))
    fit_pose(points, points + 1.0, everyone, np.ones(len(points)), np.ones(len(points)))


def detector_kernels() -> None:
    """Run the compiled detector on a small image whatever the session's configuration: its
    kernels compile (or load) here and ORB's test pairs are measured here (once per process,
    ``steered_brief.orb_pattern``), not inside a frame's CPU budget. ``fast-brief`` runs the
    same kernels."""
    import cv2

    from estimator.config import FrontendConfig
    from estimator.frontend.detection import FeatureDetector

    noise = (np.random.default_rng(0).random((120, 160)) * 255).astype(np.uint8)
    image = cv2.GaussianBlur(noise, (0, 0), 1.2)
    detector = FeatureDetector(FrontendConfig(max_features=50))
    detector.detect(image)
    detector.detect(image, same_scene=True)


def _short_validation(error: ValueError) -> str:
    errors = getattr(error, "errors", None)
    if callable(errors):
        parts = []
        for item in errors():
            location = ".".join(str(part) for part in item.get("loc", ()))
            parts.append(f"{location}: {item.get('msg', '')}" if location else item.get("msg", ""))
        return "; ".join(parts)
    return str(error)


# ----------------------------------------------------------------------------- uploaded files


def _with_files(files: dict[str, bytes], read: Any) -> Any:
    """Run a file-based reader on uploaded bytes, hiding the temporary paths from messages."""
    with tempfile.TemporaryDirectory(prefix="swarmvo-upload-") as folder:
        paths = {}
        for name, data in files.items():
            path = Path(folder) / name
            path.write_bytes(data)
            paths[name] = path
        try:
            return read(paths)
        except FileNotFoundError as error:
            raise ValueError(str(error).replace(folder + "/", "")) from error
        except ValueError as error:
            raise ValueError(str(error).replace(folder + "/", "")) from error
        except (TypeError, KeyError, UnicodeDecodeError) as error:
            raise ValueError(f"malformed calibration file: {error!r}") from error


def euroc_calibration(cam0_yaml: bytes, cam1_yaml: bytes) -> dict[str, Any]:
    """Plain calibration from EuRoC ``cam0/sensor.yaml`` and ``cam1/sensor.yaml`` contents."""
    from estimator.formats.calibration_files import load_euroc_rig

    rig = _with_files(
        {"cam0.yaml": cam0_yaml, "cam1.yaml": cam1_yaml},
        lambda p: load_euroc_rig(p["cam0.yaml"], p["cam1.yaml"]),
    )
    return rig.to_dict()


def euroc_imu_noise(imu_yaml: bytes) -> dict[str, Any]:
    """IMU noise from EuRoC ``imu0/sensor.yaml`` contents (read exactly as offline runs do)."""
    from estimator.formats.datasets import read_euroc_imu_noise

    noise = _with_files({"imu0.yaml": imu_yaml}, lambda p: read_euroc_imu_noise(p["imu0.yaml"]))
    return asdict(noise)


def euroc_frame_rate(cam0_yaml: bytes) -> float | None:
    """The camera rate (``rate_hz``) of EuRoC ``cam0/sensor.yaml`` contents, when it has one."""
    from estimator.formats.calibration_files import read_opencv_yaml

    data = _with_files({"cam0.yaml": cam0_yaml}, lambda p: read_opencv_yaml(p["cam0.yaml"]))
    rate = data.get("rate_hz")
    if rate is None:
        return None
    if isinstance(rate, bool) or not isinstance(rate, int | float) or not 0 < rate <= 10_000:
        raise ValueError(f"cam0 rate_hz must be a positive number, got {rate!r}")
    return float(rate)


def kitti_calibration(calib_txt: bytes, image_size: tuple[int, int]) -> dict[str, Any]:
    """Plain calibration from a KITTI ``calib.txt`` and the image size (width, height)."""
    from estimator.formats.calibration_files import load_kitti_rig

    rig = _with_files(
        {"calib.txt": calib_txt}, lambda p: load_kitti_rig(p["calib.txt"], image_size)
    )
    return rig.to_dict()
