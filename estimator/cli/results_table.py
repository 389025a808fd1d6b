"""The table ``swarmvo run`` prints at the end: what a user checks first after a run."""

from __future__ import annotations

from typing import Any

from estimator.types import FrameStatus

__all__ = ["results_table", "run_mode"]


def _rows(summary: dict[str, Any], estimated_path_m: float) -> list[tuple[str, str]]:
    counts = summary.get("status_counts", {})
    frames = summary["frames"]
    skipped = summary.get("frames_skipped", 0)
    coasting = "IMU / motion prior only" if summary.get("imu") else "motion prior only"
    rows = [
        (
            "frames",
            f"{frames}" + (f" ({skipped} skipped: image missing or unreadable)" if skipped else ""),
        ),
        ("tracked", f"{counts.get(str(FrameStatus.OK), 0)} (vision accepted)"),
        ("coasted", f"{counts.get(str(FrameStatus.DEGRADED), 0)} ({coasting})"),
        ("lost", f"{counts.get(str(FrameStatus.LOST), 0)}"),
    ]
    path = f"{estimated_path_m:.3g} m"
    if "ate_rmse_m" in summary:
        path += f" (ground truth {summary['path_length_m']:.3g} m)"
    rows.append(("path length", path))
    if "ate_rmse_m" in summary:
        rows.append(("ATE RMSE", f"{summary['ate_rmse_m'] * 1e3:.1f} mm"))
        rows.append(
            (
                "RPE per frame",
                f"{summary['rpe_trans_rmse_m'] * 1e3:.1f} mm, "
                f"{summary['rpe_rot_rmse_deg']:.4f} deg",
            )
        )
    elif "evaluation_error" in summary:
        rows.append(("ATE / RPE", f"not evaluated: {summary['evaluation_error']}"))
    else:
        rows.append(("ATE / RPE", "no ground truth"))
    if summary.get("kitti_segments"):
        rows.append(
            (
                "KITTI drift",
                f"{summary['kitti_trans_err_pct']:.2f} %, "
                f"{summary['kitti_rot_err_deg_per_100m']:.3f} deg / 100 m "
                f"({summary['kitti_segments']} segments)",
            )
        )
    fps = summary.get("fps")
    wall = summary.get("wall_time_s") or 0.0
    rows.append(("speed", f"{fps:.1f} fps ({wall:.1f} s)" if fps else "-"))
    return rows


def run_mode(summary: dict[str, Any]) -> str:
    """What produced the poses: only a run with the IMU in the back end fuses two sensors."""
    if not summary.get("backend"):
        return "front end only"
    if summary.get("imu"):
        return "fused, with IMU"
    return "vision + back end, no IMU"


def results_table(summary: dict[str, Any], estimated_path_m: float) -> str:
    """``metrics.json``'s summary as an aligned two-column table (the fused answer's errors
    when the back end ran, else the front end's)."""
    rows = _rows(summary, estimated_path_m)
    width = max(len(name) for name, _ in rows)
    title = (
        f"results: {summary.get('sequence', '')} "
        f"({summary.get('estimator', '')}, {run_mode(summary)})"
    )
    lines = [title, "  " + "-" * (width + 2 + max(len(value) for _, value in rows))]
    lines += [f"  {name:<{width}}  {value}" for name, value in rows]
    return "\n".join(lines)
