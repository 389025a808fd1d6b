"""Front-end error by keyframe: random or systematic, with and without the previous-frame chain.

The sequence is run twice (the bench's rendered configuration: pso-robust, IMU and back end),
with ``frontend.fuse_previous_frame`` off and on. Against the ground truth the front-end poses
are taken apart into each frame's error against its own keyframe and the error of each step
from one keyframe to the next; a trajectory's ATE grows with the steps' common part (their
mean), not with their spread, so both are printed.

    OMP_NUM_THREADS=1 python benchmarks/keyframe_step_errors.py DATASET

Prints a markdown table (nothing is written).
"""

from __future__ import annotations

from itertools import pairwise

import numpy as np
from clip_args import clip_parser, open_clip

from estimator.evaluation.metrics import camera_ground_truth
from estimator.geometry import invert_pose, rotation_vector
from estimator.pipeline import RunResult, build_config, run_sequence


def _error(estimate: np.ndarray, truth: np.ndarray, first: int, second: int) -> np.ndarray:
    """(rotation mdeg (3,), translation mm (3,)) of the relative pose first -> second."""
    relative = invert_pose(truth[first]) @ truth[second]
    measured = invert_pose(estimate[first]) @ estimate[second]
    error = invert_pose(relative) @ measured
    rotation = rotation_vector(error[:3, :3])
    return np.concatenate([np.degrees(rotation) * 1e3, error[:3, 3] * 1e3])


def _errors(run: RunResult) -> tuple[np.ndarray, np.ndarray]:
    """(per frame against its keyframe (N, 6), per keyframe step (K, 6))."""
    sequence = run.sequence
    assert sequence.ground_truth is not None, "the sequence needs a ground truth"
    stamps = run.timestamps_ns
    estimate = run.poses("frontend_pose")
    truth = camera_ground_truth(sequence.ground_truth, stamps, sequence.rig.left.T_BS)
    index = {int(stamp): n for n, stamp in enumerate(stamps)}
    frames, keyframes = [], []
    for n, report in enumerate(run.reports):
        reference = report.reference_timestamp_ns
        if reference is None or int(reference) not in index:
            continue
        keyframe = index[int(reference)]
        frames.append(_error(estimate, truth, keyframe, n))
        if keyframe not in keyframes:
            keyframes.append(keyframe)
    steps = [_error(estimate, truth, a, b) for a, b in pairwise(keyframes)]
    return np.array(frames), np.array(steps)


def _rms(values: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(values**2, axis=1))))


def main() -> int:
    parser = clip_parser(__doc__.splitlines()[0])
    args = parser.parse_args()
    sequence = open_clip(parser, args.dataset)
    print(
        "| fuse_previous_frame | frames: rot mdeg / trans mm RMS | keyframe steps | "
        "step rot RMS per axis mdeg | step rot mean per axis mdeg | step trans mean mm |"
    )
    print("|---|---|---|---|---|---|")
    for option in (False, True):
        config = build_config("pso-robust", args.seed, imu=True, backend=True)
        config.frontend.fuse_previous_frame = option
        frames, steps = _errors(run_sequence(sequence, config, progress=False))
        per_axis = np.sqrt(np.mean(steps[:, :3] ** 2, axis=0))
        print(
            f"| {'on' if option else 'off'} | {_rms(frames[:, :3]):.1f} / "
            f"{_rms(frames[:, 3:]):.2f} | {len(steps)}: {_rms(steps[:, :3]):.1f} / "
            f"{_rms(steps[:, 3:]):.2f} | {np.array2string(per_axis, precision=1)} | "
            f"{np.array2string(steps[:, :3].mean(axis=0), precision=2)} | "
            f"{np.array2string(steps[:, 3:].mean(axis=0), precision=2)} |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
