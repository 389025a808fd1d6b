"""Rendered stereo sequences with exact ground truth, written in the EuRoC/ASL or KITTI layout.

The pieces: the ideal stereo rig (``camera.py``), the flight loop and its IMU
(``trajectory.py``), the textured hall (``world.py``), drawing a view with occlusion and
motion blur (``render.py``), and the driving scene (``synthetic_driving.py``). This module
chooses the scene from ``SynthOptions``, renders every frame (with optional broken frames) and
writes the dataset files, whose calibration says it is exact (``calibration_exact``: the rig
is its calibration). ``standstill_s`` lets the body wait at its start pose first and then
start the same flight from rest (a smooth time warp, ``start_after_rest``).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Literal, get_args

import cv2
import numpy as np

from estimator.geometry import invert_pose, make_pose, matrix_to_quat
from estimator.rendered.camera import (
    CAMERA,
    CAMERAS,
    T_BS_CAM0,
    CameraName,
    SimCamera,
)
from estimator.rendered.render import blur_kernel, mean_flow
from estimator.rendered.trajectory import (
    START_RAMP_S,
    LoopTrajectory,
    TrajectoryState,
    loop_for_length,
    simulate_imu,
    start_after_rest,
)
from estimator.rendered.world import World, build_world
from estimator.types import ImuNoise

if TYPE_CHECKING:
    from estimator.rendered.synthetic_driving import DrivingTrajectory

__all__ = [
    "BROKEN_KINDS",
    "SCENARIO_CAMERAS",
    "SynthOptions",
    "SyntheticSequence",
    "read_broken_frames",
    "synthesize",
]

Scenario = Literal["flight", "driving"]
Layout = Literal["euroc", "kitti"]
BROKEN_KINDS = ("black", "blur", "shuffled")
BROKEN_FILE = "broken_frames.csv"
TRAFFIC_STREAM = 7  # the vehicles' random stream beside the scene's (seed, 7)
MAX_TRAFFIC_PER_100M = 10.0


# ----------------------------------------------------------------------------- options


# Each scenario's own stereo pair (``SynthOptions.camera`` None).
SCENARIO_CAMERAS: dict[str, CameraName] = {"flight": "euroc", "driving": "kitti"}


@dataclass
class SynthOptions:
    """What to render. Defaults give a 20 m loop in 200 frames (10 s at 20 Hz)."""

    frames: int = 200
    length_m: float = 20.0
    fps: float = 20.0
    seed: int = 0
    noise: float = 0.0  # Gaussian image noise, grey levels (sigma)
    brightness: float = 0.0  # relative amplitude of slow per-camera gain changes
    blur: float = 0.0  # exposure time as a fraction of the frame interval (motion blur)
    broken_fraction: float = 0.0  # fraction of frames made useless (black/blur/shuffled)
    imu_noise_scale: float = 1.0  # 1 = EuRoC's ADIS16448 noise, 0 = perfect IMU, zero bias
    imu_rate_hz: float = 200.0
    # The right shutter this many milliseconds after the left (cameras without a shared
    # trigger): the right image is rendered from the right camera's pose at that later time,
    # to the nearest IMU sample (5 ms at 200 Hz); at most 0.2 s either way.
    right_delay_ms: float = 0.0
    texture_px_per_m: float = 96.0
    # Seconds the body waits at its start pose before flying (extra frames in front of the
    # ``frames`` of the flight), as EuRoC's drones do: lets a VIO initialise its gyro bias.
    standstill_s: float = 0.0
    # "flight": EuRoC-like drone in a hall; "driving": KITTI-like car in a street
    # (estimator/rendered/synthetic_driving.py). Layout "kitti" writes KITTI's odometry folders.
    scenario: Scenario = "flight"
    layout: Layout = "euroc"
    # The stereo pair (camera.py); None: the scenario's own (EuRoC-like for the flight,
    # KITTI-like for the drive). The texture density above is for the scenario's own camera
    # and scales with the focal length of another, so that its images are as sharp.
    camera: CameraName | None = None
    # Driving only: moving vehicles per 100 m of road, and a lead vehicle in the ego's lane
    # (estimator/rendered/traffic.py); 0 = a static street.
    traffic: float = 0.0

    @classmethod
    def driving(cls, **overrides: object) -> SynthOptions:
        """Driving defaults: 60 s at 10 Hz over 660 m (11 m/s), 100 Hz IMU, coarser texture."""
        values: dict[str, object] = {
            "scenario": "driving",
            "frames": 600,
            "length_m": 660.0,
            "fps": 10.0,
            "imu_rate_hz": 100.0,
            "texture_px_per_m": 24.0,
        }
        return cls(**{**values, **overrides})

    def validate(self) -> None:
        if self.scenario not in get_args(Scenario):
            raise ValueError(f"scenario must be one of {get_args(Scenario)}, got {self.scenario!r}")
        if self.layout not in get_args(Layout):
            raise ValueError(f"layout must be one of {get_args(Layout)}, got {self.layout!r}")
        if self.camera is not None and self.camera not in CAMERAS:
            raise ValueError(f"camera must be one of {tuple(CAMERAS)}, got {self.camera!r}")

        if self.frames < 2:
            raise ValueError(f"frames must be >= 2, got {self.frames}")
        if self.seed < 0:  # NumPy's generator refuses it with no name attached
            raise ValueError(f"seed must be >= 0, got {self.seed}")
        if not 0.5 <= self.length_m <= 1000.0:
            raise ValueError(f"length_m must be in [0.5, 1000], got {self.length_m}")
        if self.fps <= 0 or self.imu_rate_hz <= 0:
            raise ValueError("fps and imu_rate_hz must be positive")
        ratio = self.imu_rate_hz / self.fps
        if abs(ratio - round(ratio)) > 1e-9:
            raise ValueError(f"imu_rate_hz ({self.imu_rate_hz}) must be a multiple of fps")
        if not abs(self.right_delay_ms) <= 200.0:  # NaN fails too
            raise ValueError(f"right_delay_ms must be within +-200, got {self.right_delay_ms}")
        for name in ("noise", "brightness", "blur", "imu_noise_scale", "standstill_s"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"{name} must be a finite number, got {getattr(self, name)}")
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.brightness >= 1.0:
            raise ValueError(
                f"brightness must be < 1 (relative gain change), got {self.brightness}"
            )
        if self.blur > 1.0:
            raise ValueError(f"blur is an exposure fraction in [0, 1], got {self.blur}")
        if not 0.0 <= self.broken_fraction <= 0.5:
            raise ValueError(f"broken_fraction must be in [0, 0.5], got {self.broken_fraction}")
        if self.standstill_s > 60.0:
            raise ValueError(f"standstill_s must be <= 60, got {self.standstill_s}")
        if not 0.0 <= self.traffic <= MAX_TRAFFIC_PER_100M:  # NaN fails too
            raise ValueError(
                f"traffic must be in [0, {MAX_TRAFFIC_PER_100M:g}] vehicles per 100 m, "
                f"got {self.traffic}"
            )
        if self.traffic and self.scenario != "driving":
            raise ValueError("traffic is for the driving scenario (vehicles on the road)")
        if self.texture_px_per_m < 8:
            raise ValueError(f"texture_px_per_m must be >= 8, got {self.texture_px_per_m}")
        if self.scenario == "driving" and not 2.0 <= self.length_m / self.duration_s <= 40.0:
            raise ValueError(
                f"a drive of {self.length_m} m in {self.duration_s:.1f} s is "
                f"{self.length_m / self.duration_s:.1f} m/s; keep it within 2..40 m/s"
            )

    @property
    def sim_camera(self) -> SimCamera:
        """The rendered stereo pair: ``camera``, or the scenario's own."""
        return CAMERAS[self.camera or SCENARIO_CAMERAS[self.scenario]]

    @property
    def texture_density(self) -> float:
        """Texture pixels per metre for ``sim_camera`` (``texture_px_per_m`` scaled from the
        scenario's own camera by the focal lengths)."""
        own = CAMERAS[SCENARIO_CAMERAS[self.scenario]]
        return self.texture_px_per_m * (self.sim_camera.f / own.f)  # exact for its own

    @property
    def duration_s(self) -> float:
        return max(self.frames - 1, 1) / self.fps if self.fps > 0 else float("nan")


# ----------------------------------------------------------------------------- sequence


@dataclass
class SyntheticSequence:
    """What ``synthesize`` wrote (all times in ns, poses body-in-world)."""

    root: Path
    options: SynthOptions
    frame_timestamps_ns: np.ndarray
    imu_timestamps_ns: np.ndarray
    body_poses: np.ndarray  # at the IMU timestamps
    broken: dict[int, str] = field(default_factory=dict)  # frame index -> kind
    path_length_m: float = 0.0
    world: World | None = None  # the rendered scene, for checks against the images
    trajectory: LoopTrajectory | DrivingTrajectory | None = None


START_NS = 1_600_000_000_000_000_000  # 19-digit timestamps, like EuRoC's


def _write_camera_yaml(
    path: Path, T_BS: np.ndarray, comment: str, camera: SimCamera = CAMERA, rate_hz: float = 20.0
) -> None:
    data = ", ".join(repr(float(v)) for v in T_BS.reshape(16))
    path.write_text(
        "%YAML:1.0\n"
        f"sensor_type: camera\ncomment: {comment}\n"
        f"T_BS:\n  cols: 4\n  rows: 4\n  data: [{data}]\n"
        f"rate_hz: {rate_hz:g}\nresolution: [{camera.width}, {camera.height}]\n"
        "camera_model: pinhole\n"
        f"intrinsics: [{camera.f}, {camera.f}, {camera.cx}, {camera.cy}]\n"
        "distortion_model: none\ndistortion_coefficients: []\ncalibration_exact: true\n"
    )


def _write_imu_yaml(path: Path, noise: ImuNoise) -> None:
    path.write_text(
        "%YAML:1.0\nsensor_type: imu\ncomment: simulated IMU\n"
        "T_BS:\n  cols: 4\n  rows: 4\n"
        "  data: [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]\n"
        f"rate_hz: {noise.rate_hz!r}\n"
        f"gyroscope_noise_density: {noise.gyro_noise_density!r}\n"
        f"gyroscope_random_walk: {noise.gyro_random_walk!r}\n"
        f"accelerometer_noise_density: {noise.accel_noise_density!r}\n"
        f"accelerometer_random_walk: {noise.accel_random_walk!r}\n"
    )


def _write_table(path: Path, header: str, timestamps: np.ndarray, values: np.ndarray) -> None:
    """CSV with exact integer ns timestamps and full-precision (17 digit) values."""
    rows = (
        f"{t}," + ",".join(f"{v:.17g}" for v in row)
        for t, row in zip(timestamps.tolist(), values.tolist(), strict=True)
    )
    path.write_text(header + "\n" + "\n".join(rows) + "\n")


def read_broken_frames(root: Path) -> dict[int, str]:
    """Frame index -> kind of the frames ``synthesize`` broke on purpose (empty if none)."""
    path = Path(root) / BROKEN_FILE
    if not path.is_file():
        return {}
    broken = {}
    for line in path.read_text().splitlines():
        if line and not line.startswith("#"):
            _, index, kind = line.split(",")
            broken[int(index)] = kind
    return broken


def synthesize(
    out_dir: Path,
    options: SynthOptions | None = None,
    progress: Callable[[int], object] | None = None,
) -> SyntheticSequence:
    """Render a stereo + IMU sequence into ``out_dir`` (EuRoC layout under ``out_dir/mav0``).

    ``progress`` is an optional callable taking the number of frames just rendered.
    """
    options = options or SynthOptions()
    options.validate()
    out_dir = Path(out_dir)
    mav0 = out_dir / "mav0"
    for existing in (mav0, out_dir / "image_0"):
        if existing.exists():
            raise ValueError(f"{existing} already exists; choose an empty output folder")
    rng = np.random.default_rng(options.seed)
    frame_step_ns = round(1e9 / options.fps)
    imu_step_ns = round(1e9 / options.imu_rate_hz)
    per_frame = frame_step_ns // imu_step_ns
    duration = (options.frames - 1) / options.fps
    rig = _scene(options, duration, rng)
    trajectory, world = rig.trajectory, rig.world

    # IMU and ground truth on one 200 Hz grid, 0.2 s beyond both ends; frames every per_frame.
    # A standstill prepends still frames; the flight then starts (from rest) at frame ``still``.
    still = round(options.standstill_s * options.fps)
    total = options.frames + still
    margin = round(0.2 * options.imu_rate_hz)
    imu_index = np.arange(-margin, (total - 1) * per_frame + margin + 1)
    imu_ns = START_NS + imu_index * imu_step_ns
    if still:
        flight_t = (imu_index - still * per_frame) * (imu_step_ns * 1e-9)
        state = start_after_rest(trajectory, flight_t, START_RAMP_S)
    else:
        state = trajectory.state(imu_index * (imu_step_ns * 1e-9))
    noise = ImuNoise(rate_hz=options.imu_rate_hz)
    gyro, accel, gyro_bias, accel_bias = simulate_imu(state, noise, rng, options.imu_noise_scale)
    frame_rows = margin + np.arange(total) * per_frame
    frame_ns = imu_ns[frame_rows]
    body_poses = state.poses()

    if options.layout == "kitti":
        writer = _kitti_writer(out_dir, rig, frame_ns, body_poses[frame_rows])
    else:
        writer = _euroc_writer(mav0, rig, options, imu_ns, state, (gyro, accel), frame_ns)
        _write_ground_truth(mav0, imu_ns, state, gyro_bias, accel_bias)

    broken = _choose_broken(options, total, rng)
    row_times = imu_index * (imu_step_ns * 1e-9)  # where the moving vehicles are
    rendered = _render_frames(
        rig, body_poses, (frame_rows, row_times), per_frame, options, rng, progress
    )
    _write_frames(writer, rendered, broken, total)
    if broken:
        lines = [f"{frame_ns[i]},{i},{kind}" for i, kind in sorted(broken.items())]
        (out_dir / BROKEN_FILE).write_text("#timestamp [ns],index,kind\n" + "\n".join(lines) + "\n")
    path_length = _write_summary(out_dir, options, rig, body_poses[frame_rows])
    return SyntheticSequence(
        out_dir, options, frame_ns, imu_ns, body_poses, broken, path_length, world, trajectory
    )


def _write_frames(
    writer: Callable[[int, np.ndarray, str], None],
    rendered: Iterator[tuple[int, np.ndarray, np.ndarray]],
    broken: dict[int, str],
    total: int,
) -> None:
    """Write every rendered pair, broken the way ``broken`` says (black, blurred, shuffled)."""
    # A shuffled frame gets the (unbroken) right image of the frame half a loop away.
    donors = {i: (i + total // 2) % total for i, kind in broken.items() if kind == "shuffled"}
    kept_right: dict[int, np.ndarray] = {}
    for index, left, right in rendered:
        if index in donors.values():
            kept_right[index] = right
        if broken.get(index) == "black":
            left, right = np.zeros_like(left), np.zeros_like(right)
        elif broken.get(index) == "blur":
            left, right = (cv2.GaussianBlur(im, (0, 0), 12.0) for im in (left, right))
        writer(index, left, "left")
        writer(index, right, "right")
    for index, donor in donors.items():
        writer(index, kept_right[donor], "right")


def _write_summary(
    out_dir: Path, options: SynthOptions, rig: SceneRig, frame_poses: np.ndarray
) -> float:
    """``synth.json``: the options, the scene and the body's path length (returned, m)."""
    trajectory, world = rig.trajectory, rig.world
    path_length = float(np.linalg.norm(np.diff(frame_poses[:, :3, 3], axis=0), axis=1).sum())
    scene = (
        {"loop_semi_axes_m": [trajectory.a, trajectory.b], "hall_half_extents_m": world.bounds}
        if isinstance(trajectory, LoopTrajectory)
        else {"turns": len(trajectory.turns), "mean_speed_mps": trajectory.mean_speed}
    )
    summary = {"options": asdict(options), "path_length_m": path_length, **scene}
    summary["planes"] = len(world.planes)
    if world.movers is not None:
        summary["moving_planes"] = len(world.movers(0.0))
    (out_dir / "synth.json").write_text(json.dumps(summary, indent=2))
    return path_length


@dataclass
class SceneRig:
    """What a scenario renders: the motion, the world and where the stereo pair sits on it."""

    trajectory: LoopTrajectory | DrivingTrajectory
    world: World
    T_BS_cam0: np.ndarray

    @property
    def camera(self) -> SimCamera:
        return self.world.camera

    @property
    def T_cam0_cam1(self) -> np.ndarray:
        return make_pose(np.eye(3), [self.camera.baseline, 0.0, 0.0])


def _scene(options: SynthOptions, duration: float, rng: np.random.Generator) -> SceneRig:
    if options.scenario == "driving":
        from estimator.rendered.synthetic_driving import (
            DRIVING_T_BS_CAM0,
            build_street,
            driving_for_length,
        )

        drive = driving_for_length(options.length_m, duration, rng)
        street = build_street(drive, rng, options.texture_density, options.sim_camera)
        if options.traffic:
            from estimator.rendered.traffic import build_traffic

            # Its own stream: the street stays the one rendered without traffic.
            vehicles = np.random.default_rng([options.seed, TRAFFIC_STREAM])
            street.movers = build_traffic(
                drive, options.traffic, vehicles, 2.0 * options.texture_density
            ).planes_at
        return SceneRig(drive, street, DRIVING_T_BS_CAM0)
    loop = loop_for_length(options.length_m, duration)
    world = build_world(loop, rng, options.texture_density, options.sim_camera)
    return SceneRig(loop, world, T_BS_CAM0)


Writer = Callable[[int, np.ndarray, str], None]


def _euroc_writer(
    mav0: Path,
    rig: SceneRig,
    options: SynthOptions,
    imu_ns: np.ndarray,
    state: TrajectoryState,
    imu: tuple[np.ndarray, np.ndarray],
    frame_ns: np.ndarray,
) -> Writer:
    """Write the EuRoC folders and sensor files; returns the image writer."""
    for name in ("cam0/data", "cam1/data", "imu0", "state_groundtruth_estimate0"):
        (mav0 / name).mkdir(parents=True, exist_ok=True)
    T_BS_cam1 = rig.T_BS_cam0 @ rig.T_cam0_cam1
    for name, T_BS, side in (("cam0", rig.T_BS_cam0, "left"), ("cam1", T_BS_cam1, "right")):
        _write_camera_yaml(
            mav0 / name / "sensor.yaml", T_BS, f"simulated {side} camera", rig.camera, options.fps
        )
    noise = ImuNoise(rate_hz=options.imu_rate_hz)
    _write_imu_yaml(mav0 / "imu0" / "sensor.yaml", noise)
    (mav0 / "body.yaml").write_text("%YAML:1.0\ncomment: swarmvo synthetic sequence\n")
    _write_table(
        mav0 / "imu0" / "data.csv",
        "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
        "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]",
        imu_ns,
        np.hstack(imu),
    )
    camera_rows = "\n".join(f"{t},{t}.png" for t in frame_ns.tolist())
    for camera in ("cam0", "cam1"):
        (mav0 / camera / "data.csv").write_text("#timestamp [ns],filename\n" + camera_rows + "\n")
    folders = {"left": mav0 / "cam0" / "data", "right": mav0 / "cam1" / "data"}

    def write(index: int, image: np.ndarray, side: str) -> None:
        cv2.imwrite(str(folders[side] / f"{frame_ns[index]}.png"), image)

    return write


def _write_ground_truth(
    mav0: Path,
    imu_ns: np.ndarray,
    state: TrajectoryState,
    gyro_bias: np.ndarray,
    accel_bias: np.ndarray,
) -> None:
    _write_table(
        mav0 / "state_groundtruth_estimate0" / "data.csv",
        "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], "
        "q_RS_z [], v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], "
        "b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], b_w_RS_S_z [rad s^-1], "
        "b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]",
        imu_ns,
        np.hstack(
            [
                state.positions,
                matrix_to_quat(state.rotations),
                state.velocities,
                gyro_bias,
                accel_bias,
            ]
        ),
    )


def _kitti_writer(
    out_dir: Path, rig: SceneRig, frame_ns: np.ndarray, frame_body_poses: np.ndarray
) -> Writer:
    """KITTI odometry layout: image_0/ image_1/ NNNNNN.png, calib.txt, times.txt, poses.txt.

    Poses are left-camera poses relative to the first one (KITTI's convention); times are
    seconds since the first frame. KITTI has no IMU, so none is written.
    """
    from estimator.formats.trajectory_io import format_seconds, write_kitti

    folders = {"left": out_dir / "image_0", "right": out_dir / "image_1"}
    for folder in folders.values():
        folder.mkdir(parents=True, exist_ok=True)
    c = rig.camera
    rows = []
    for label, offset in (("P0", 0.0), ("P1", -c.f * c.baseline)):
        values = [c.f, 0.0, c.cx, offset, 0.0, c.f, c.cy, 0.0, 0.0, 0.0, 1.0, 0.0]
        rows.append(f"{label}: " + " ".join(f"{v:.12e}" for v in values))
    rows.append("calibration_exact: 1")  # the rendered rig is its calibration (no error)
    (out_dir / "calib.txt").write_text("\n".join(rows) + "\n")
    relative_ns = frame_ns - frame_ns[0]
    (out_dir / "times.txt").write_text("".join(format_seconds(t) + "\n" for t in relative_ns))
    cameras = frame_body_poses @ rig.T_BS_cam0
    write_kitti(out_dir / "poses.txt", invert_pose(cameras[0]) @ cameras)

    def write(index: int, image: np.ndarray, side: str) -> None:
        cv2.imwrite(str(folders[side] / f"{index:06d}.png"), image)

    return write


def _choose_broken(options: SynthOptions, total: int, rng: np.random.Generator) -> dict[int, str]:
    """Frames to break among all ``total`` (never the first two, so the odometry can start)."""
    count = round(options.broken_fraction * total)
    candidates = np.arange(2, total)
    count = min(count, len(candidates))
    if count == 0:
        return {}
    chosen = np.sort(rng.choice(candidates, size=count, replace=False))
    kinds = rng.choice(len(BROKEN_KINDS), size=count)
    return {int(i): BROKEN_KINDS[k] for i, k in zip(chosen, kinds, strict=True)}


def _render_frames(
    rig: SceneRig,
    body_poses: np.ndarray,
    rows: tuple[np.ndarray, np.ndarray],
    per_frame: int,
    options: SynthOptions,
    rng: np.random.Generator,
    progress: Callable[[int], object] | None,
) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
    """Yield (index, left, right) rendered, with gain changes, motion blur and sensor noise;
    ``rows``: each frame's row of the IMU grid, and every row's time (s)."""
    phases = rng.uniform(0.0, 2 * np.pi, size=4)
    world, T_BS = rig.world, rig.T_BS_cam0
    delay_rows = round(options.right_delay_ms * 1e-3 * options.imu_rate_hz)
    frame_rows, times = rows
    for index, row in enumerate(frame_rows):
        T_WC0 = body_poses[row] @ T_BS
        left, inv_depth = world.render(T_WC0, time_s=times[row])
        right_row = row + delay_rows
        T_WC1 = body_poses[right_row] @ T_BS @ rig.T_cam0_cam1
        right, _ = world.render(T_WC1, time_s=times[right_row])
        if options.blur > 0:
            # Exposure ends at the frame time: the camera moved over the blur fraction before.
            steps = options.blur * per_frame
            earlier = body_poses[max(0, round(row - steps))] @ T_BS
            flow = mean_flow(inv_depth, invert_pose(T_WC0) @ earlier, world.camera)
            kernel = blur_kernel(flow)
            if kernel is not None:
                left, right = (cv2.filter2D(im, -1, kernel) for im in (left, right))
        if options.brightness > 0:
            t = index / options.fps
            gains = [
                1.0 + options.brightness * np.sin(2 * np.pi * t / 3.1 + phases[0]),
                1.0
                + options.brightness
                * (
                    np.sin(2 * np.pi * t / 3.1 + phases[0]) * 0.8
                    + 0.2 * np.sin(2 * np.pi * t / 1.7 + phases[1])
                ),
            ]
            left, right = (
                cv2.convertScaleAbs(im, alpha=g) for im, g in zip((left, right), gains, strict=True)
            )
        if options.noise > 0:
            left, right = (
                np.clip(im + rng.normal(0.0, options.noise, im.shape), 0, 255).astype(np.uint8)
                for im in (left, right)
            )
        if progress is not None:
            progress(1)
        yield index, left, right
