"""Back-end variants on one recorded front end: what the fused error is made of.

The odometry is run once on a clip (fused with its IMU, default configuration) and every
input the back end received is recorded (its observer, ``estimator/backend/recording.py``).
The back end alone is then replayed on those inputs
with each configuration variant given (``backend`` fields as JSON), a few seconds per run
instead of a minute; the front end does not see the variant (the gate's rejections do not feed
back into its keyframes), so a variant's final numbers come from ``swarmvo bench odometry``.

Why replays, and why several per variant: on the real MH_01 clip the fused ATE of one run moves
by up to a millimetre with changes that should not matter (iSAM2's relinearisation thresholds,
one more iteration, the marginalisation block). Each variant is therefore replayed under a few
such solver perturbations and reported as mean +- standard deviation: a difference inside the
spread is not a result.

The online answer's rotation error per frame is also taken apart: the online pose of frame k
differs from that of frame k-1 by the motion the graph solved at k (``body_motion``) and by how
much the new measurement moved its estimate of frame k-1 (the revision).

    OMP_NUM_THREADS=1 python benchmarks/backend_replay.py [DATASET] \\
        [--variants '[{}, {"old_reference": "prior"}]'] [--recording FILE]

Prints one line per variant (nothing is written besides the recording, kept in the system's
temporary directory and reused when it exists).
"""

from __future__ import annotations

import argparse
import copy
import json
import pickle
import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gtsam
import numpy as np

from estimator.backend import FusionBackend
from estimator.backend.recording import BackendFrame, BackendInput, BackendSetup
from estimator.config import BackendConfig
from estimator.evaluation.metrics import camera_ground_truth, evaluate_trajectory
from estimator.formats.datasets import Sequence, open_sequence
from estimator.geometry import invert_pose
from estimator.pipeline import build_config, run_sequence

ROOT = Path(__file__).resolve().parents[1]
DEFAULT = ROOT.parent / "shared/data/euroc_mh01_moving"
# Changes that should not move the answer: the spread they cause is the noise floor.
PERTURBATIONS: tuple[dict[str, Any], ...] = (
    {},
    {"extra_iterations": 2},
    {"relinearize_rotation_rad": 0.01},
    {"relinearize_translation_m": 0.0025},
    {"relinearize_translation_m": 0.01},
    {"marginalize_block_s": 0.15},
)


@dataclass
class Recording:
    """The back end's construction arguments and every ``add_frame`` call of one run."""

    config: dict[str, Any]
    body_from_camera: np.ndarray
    imu_noise: Any
    calls: list[BackendFrame]

    def observe(self, given: BackendInput) -> None:
        """Keep a copy of what the back end is given (its observer)."""
        if isinstance(given, BackendSetup):
            self.config = given.config.model_dump()
            self.body_from_camera = np.array(given.body_from_camera, dtype=float)
            self.imu_noise = given.imu_noise
        else:
            self.calls.append(copy.deepcopy(given))


@dataclass
class Replay:
    """One replay: online and smoothed poses (left camera), the solved motions (body)."""

    timestamps_ns: np.ndarray
    online: np.ndarray
    smoothed: np.ndarray
    body_poses: np.ndarray
    motions: list[np.ndarray | None]


def open_clip(path: Path) -> Sequence:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # unpaired camera rows are expected in EuRoC
        return open_sequence(path)


def record(sequence: Sequence) -> Recording:
    """Run the default fused odometry once, keeping what its back end was given."""
    recording = Recording({}, np.eye(4), None, [])
    config = build_config("pso-robust", 0, imu=True, backend=True)
    run_sequence(sequence, config, backend_observer=recording.observe)
    return recording


def replay(recording: Recording, overrides: dict[str, Any]) -> Replay:
    """The back end alone on the recorded inputs, with ``overrides`` on its configuration."""
    config = BackendConfig.model_validate({**recording.config, **overrides})
    backend = FusionBackend(config, recording.body_from_camera, recording.imu_noise)
    stamps, online, body, motions, smoothed = [], [], [], [], {}
    for call in recording.calls:
        fused = backend.add_frame(call.timestamp_ns, **call.arguments)
        stamps.append(int(call.timestamp_ns))
        online.append(fused.pose)
        body.append(fused.body_pose)
        motions.append(fused.body_motion)
        smoothed.update(dict(fused.final_poses))
    smoothed.update(dict(backend.flush()))
    return Replay(
        np.array(stamps),
        np.array(online),
        np.array([smoothed[stamp] for stamp in stamps]),
        np.array(body),
        motions,
    )


def scores(result: Replay, sequence: Sequence) -> np.ndarray:
    """Online and smoothed (ATE mm, rotation error deg per frame, final drift mm)."""
    assert sequence.ground_truth is not None
    values = []
    for poses in (result.online, result.smoothed):
        metrics = evaluate_trajectory(
            result.timestamps_ns, poses, sequence.ground_truth, sequence.rig.left.T_BS
        ).metrics
        values += [
            metrics["ate_rmse_m"] * 1e3,
            metrics["rpe_rot_rmse_deg"],
            metrics["final_drift_m"] * 1e3,
        ]
    return np.array(values)


def _angle_deg(pose: np.ndarray) -> float:
    return float(np.degrees(np.linalg.norm(gtsam.Rot3.Logmap(gtsam.Rot3(pose[:3, :3])))))


def rotation_parts(result: Replay, sequence: Sequence) -> tuple[float, float, float]:
    """RMS over frames (deg) of the online rotation error per frame, of the solved motion's
    error, and of the revision of the previous frame's estimate by the new frame."""
    assert sequence.ground_truth is not None
    truth = camera_ground_truth(sequence.ground_truth, result.timestamps_ns, np.eye(4))
    online, motion, revision = [], [], []
    for k in range(1, len(truth)):
        true_motion = invert_pose(truth[k - 1]) @ truth[k]
        estimated = invert_pose(result.body_poses[k - 1]) @ result.body_poses[k]
        online.append(_angle_deg(invert_pose(true_motion) @ estimated))
        solved = result.motions[k]
        if solved is None:
            continue
        motion.append(_angle_deg(invert_pose(true_motion) @ solved))
        previous_now = result.body_poses[k] @ invert_pose(solved)
        revision.append(_angle_deg(invert_pose(result.body_poses[k - 1]) @ previous_now))

    def rms(values: list[float]) -> float:
        return float(np.sqrt(np.mean(np.square(values)))) if values else float("nan")

    return rms(online), rms(motion), rms(revision)


def _line(variant: dict[str, Any], runs: np.ndarray, parts: tuple[float, float, float]) -> str:
    mean, spread = runs.mean(axis=0), runs.std(axis=0)
    return (
        f"| {json.dumps(variant)} | {mean[0]:.2f} +- {spread[0]:.2f} | {mean[1]:.4f} +- "
        f"{spread[1]:.4f} | {mean[2]:.1f} +- {spread[2]:.1f} | {mean[3]:.2f} | {mean[4]:.4f} | "
        f"{parts[1]:.4f} | {parts[2]:.4f} |"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", nargs="?", type=Path, default=DEFAULT)
    parser.add_argument("--variants", default="[{}]", help="JSON list of backend overrides")
    parser.add_argument("--recording", type=Path, default=None)
    args = parser.parse_args()
    try:
        variants = json.loads(args.variants)
    except json.JSONDecodeError as error:
        parser.error(f"--variants is not JSON: {error}")
    if not isinstance(variants, list) or not all(isinstance(v, dict) for v in variants):
        parser.error("--variants must be a JSON list of objects")
    for variant in variants:
        try:
            BackendConfig.model_validate(variant)
        except ValueError as error:  # pydantic's ValidationError: an unknown or bad field
            parser.error(f"variant {json.dumps(variant)}: {error}")
    sequence = open_clip(args.dataset)
    if sequence.ground_truth is None:
        parser.error(f"{args.dataset} has no ground truth")
    path = args.recording or Path(tempfile.gettempdir()) / f"backend_replay_{sequence.name}.pkl"
    if path.exists():
        recording = pickle.loads(path.read_bytes())
    else:
        recording = record(sequence)
        path.write_bytes(pickle.dumps(recording))
    print(
        f"{sequence.name}, {len(recording.calls)} frames; mean +- std over "
        f"{len(PERTURBATIONS)} solver perturbations; rotation parts of the unperturbed replay\n"
    )
    print(
        "| variant | online ATE mm | online deg/frame | final drift mm | smoothed ATE mm | "
        "smoothed deg/frame | solved motion deg | revision deg |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for variant in variants:
        runs = np.array(
            [scores(replay(recording, {**p, **variant}), sequence) for p in PERTURBATIONS]
        )
        parts = rotation_parts(replay(recording, variant), sequence)
        print(_line(variant, runs, parts), flush=True)


if __name__ == "__main__":
    main()
