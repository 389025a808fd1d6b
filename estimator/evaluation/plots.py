"""``trajectory.png`` of a run: top view against ground truth, per-frame errors, inliers."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only; never needs a display
import matplotlib.pyplot as plt
import numpy as np

from estimator.evaluation.metrics import TrajectoryEvaluation

__all__ = ["plot_run"]

COLORS = ("tab:blue", "tab:orange", "tab:green", "tab:red")


def plot_run(
    path: Path,
    timestamps_ns: np.ndarray,
    poses: np.ndarray,
    inliers: np.ndarray,
    evaluations: dict[str, TrajectoryEvaluation] | None = None,
    title: str = "",
) -> None:
    """Write the run figure; ``evaluations`` maps a label ("fused", "frontend") to its errors.

    With ground truth the top view shows the estimates after SE(3) alignment onto the ground
    truth, in its world (x-y plane, z up); without it the raw estimate in the first-camera
    frame (x-z plane).
    """
    evaluations = evaluations or {}
    t0 = timestamps_ns[0]
    seconds = (np.asarray(timestamps_ns) - t0) * 1e-9
    rows = 3 if evaluations else 2
    figure, axes = plt.subplots(rows, 1, figsize=(8, 3.2 * rows + 2), constrained_layout=True)
    _top_view(axes[0], poses, evaluations, title)
    if evaluations:
        _error_panel(axes[1], evaluations, t0)
    counts = axes[-1]
    counts.plot(seconds, inliers, lw=1, color="tab:green")
    counts.set_xlabel("time [s]")
    counts.set_ylabel("registration inliers")
    counts.grid(alpha=0.3)
    figure.savefig(path, dpi=110)
    plt.close(figure)


def _top_view(
    top: plt.Axes, poses: np.ndarray, evaluations: dict[str, TrajectoryEvaluation], title: str
) -> None:
    """Aligned estimates over the ground truth (x-y), or the raw estimate (x-z) without it."""
    if evaluations:
        first = next(iter(evaluations.values()))
        top.plot(*first.reference[:, :2, 3].T, "k-", lw=2, label="ground truth")
        for (label, evaluation), color in zip(evaluations.items(), COLORS, strict=False):
            top.plot(*evaluation.aligned[:, :2, 3].T, "-", lw=1, color=color, label=label)
        top.set_xlabel("x [m]")
        top.set_ylabel("y [m]")
    else:
        top.plot(poses[:, 0, 3], poses[:, 2, 3], "-", lw=1, label="estimate")
        top.set_xlabel("x [m] (first camera)")
        top.set_ylabel("z [m] (first camera)")
    top.set_aspect("equal", adjustable="datalim")
    top.legend(loc="best", fontsize=8)
    top.set_title(title or "trajectory (top view)")
    top.grid(alpha=0.3)


def _error_panel(errors: plt.Axes, evaluations: dict[str, TrajectoryEvaluation], t0: int) -> None:
    """ATE and per-frame rotation RPE over time, one colour per evaluated trajectory."""
    for (label, evaluation), color in zip(evaluations.items(), COLORS, strict=False):
        t = (evaluation.timestamps_ns - t0) * 1e-9
        errors.plot(t, evaluation.ate_errors_m, lw=1.2, color=color, label=f"{label} ATE [m]")
        errors.plot(
            t[1:],
            evaluation.rpe_rot_deg,
            lw=0.8,
            ls=":",
            color=color,
            label=f"{label} RPE rotation [deg/frame]",
        )
    errors.set_xlabel("time [s]")
    errors.set_ylabel("error")
    errors.legend(loc="best", fontsize=8)
    errors.grid(alpha=0.3)
