"""The fleet harness's verdict: every answer checked against the database, the failover gap
and its phases, the pose jump at takeover, the accuracy of robots whose replica was killed
against the others, and the printed table (used by benchmarks/cluster.py)."""

from __future__ import annotations

import itertools
import json
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from swarmvo_client import Client, LocalSequence

from estimator.geometry import kabsch

if TYPE_CHECKING:
    from cluster import Fleet, RobotRun


def _camera_poses(sequence: LocalSequence, body_from_camera: np.ndarray
                  ) -> dict[int, np.ndarray]:
    """Ground-truth left-camera poses at the frame timestamps (exact ground-truth rows)."""
    assert sequence.gt_timestamps_ns is not None and sequence.gt_positions is not None
    assert sequence.gt_rotations is not None
    rows = {int(t): i for i, t in enumerate(sequence.gt_timestamps_ns)}
    poses = {}
    for frame in sequence.frames:
        i = rows.get(frame.timestamp_ns)
        if i is None:
            continue
        body = np.eye(4)
        body[:3, :3], body[:3, 3] = sequence.gt_rotations[i], sequence.gt_positions[i]
        poses[frame.timestamp_ns] = body @ body_from_camera
    return poses


def _step_error(poses: dict[int, np.ndarray], truth: dict[int, np.ndarray], previous: int,
                current: int) -> float | None:
    """|estimated step - true step| of the camera from ``previous`` to ``current`` [m]."""
    if not all(t in poses and t in truth for t in (previous, current)):
        return None
    estimated = np.linalg.inv(poses[previous]) @ poses[current]
    true = np.linalg.inv(truth[previous]) @ truth[current]
    return float(np.linalg.norm(estimated[:3, 3] - true[:3, 3]))


def _ate(poses: dict[int, np.ndarray], truth: dict[int, np.ndarray]) -> float | None:
    """RMS position error [m] after the rigid fit of the estimate onto the truth."""
    stamps = sorted(t for t in poses if t in truth)
    if len(stamps) < 3:
        return None
    estimate = np.array([poses[t][:3, 3] for t in stamps])
    reference = np.array([truth[t][:3, 3] for t in stamps])
    rotation, translation = kabsch(estimate, reference)
    residual = estimate @ rotation.T + translation - reference
    return float(np.sqrt(np.mean(np.sum(residual**2, axis=1))))


def _phases(robot: RobotRun, kill: dict[str, Any]) -> dict[str, float] | None:
    """Where one affected robot's failover gap went, in seconds from the kill:

    - ``noticed``: the client saw its stream break (nginx closed it when the replica died);
    - ``reconnected``: a replica greeted it again through nginx;
    - ``lease_taken``: the new owner holds the session's lease (the old one expired first);
    - ``answered``: the first frame answered again (state restored, pipeline built, frame
      computed and stored).
    """
    at = kill["at"]
    outage = next((o for o in robot.outages if o.lost_at >= at - 0.05), None)
    taken = kill["lease_taken_at"].get(robot.session_id)
    if outage is None or outage.answered_at is None:
        return None
    return {
        "noticed": outage.lost_at - at,
        "reconnected": (outage.reconnected_at or outage.answered_at) - at,
        "lease_taken": (taken if taken is not None else outage.answered_at) - at,
        "answered": outage.answered_at - at,
        "connections": outage.connections,
    }


@dataclass
class _Tally:
    """Counts and samples gathered robot by robot, turned into the verdict at the end."""

    lost: int = 0
    mismatched: int = 0
    duplicates: int = 0
    unfenced: int = 0
    unanswered: int = 0
    takeover_jumps: list[float] = field(default_factory=list)
    ordinary: list[float] = field(default_factory=list)
    accuracy: list[dict[str, Any]] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)


def _check_answers(robot: RobotRun, rows: list, tally: _Tally) -> None:
    """Every pose a robot was answered must be stored, with the same pose and index."""
    stored = {int(r[0]): r for r in rows}
    tally.duplicates += len(rows) - len(stored)
    tally.unanswered += len(robot.sequence.frames) - len(robot.answers)
    for stamp, (pose, _when) in robot.answers.items():
        row = stored.get(stamp)
        if row is None:
            tally.lost += 1
            tally.problems.append(f"{robot.name}: {stamp} answered, not stored")
        elif json.loads(row[2]) != pose.pose.reshape(16).tolist() or row[1] != pose.index:
            tally.mismatched += 1
            tally.problems.append(f"{robot.name}: {stamp} stored differs from the answer "
                                  f"(index {row[1]} vs {pose.index})")


def _unfenced(rows: list) -> int:
    """Fencing: tokens never go back along the trajectory and each has one writer."""
    unfenced = 0
    writers: dict[int, set[str]] = {}
    highest = 0
    for _stamp, _index, _pose, token, writer, _resumed in rows:
        if token is None or token < highest:
            unfenced += 1
            continue
        highest = token
        writers.setdefault(token, set()).add(writer)
    return unfenced + sum(len(w) - 1 for w in writers.values())


def _check_accuracy(fleet: Fleet, robot: RobotRun, rows: list, calibration: dict[str, Any],
                    run: dict[str, Any], tally: _Tally) -> None:
    """ATE of the stored and smoothed trajectories, and the pose jump: the step into each
    frame a new owner computed first, against the truth (ordinary steps for comparison)."""
    body_from_camera = np.array(calibration["left"]["T_BS"], dtype=float)
    truth = _camera_poses(robot.sequence, body_from_camera)
    estimated = {int(r[0]): np.array(json.loads(r[2])).reshape(4, 4) for r in rows}
    affected = any(robot.session_id in kill["sessions"] for kill in run["kills"])
    smoothed = {int(stamp): np.array(json.loads(pose)).reshape(4, 4) for stamp, pose in
                fleet.sql("SELECT timestamp_ns, pose::text FROM smoothed_poses "
                          "WHERE session_id = %s", robot.session_id)}
    tally.accuracy.append({"robot": robot.name, "affected": affected,
                           "ate_m": _ate(estimated, truth),
                           "smoothed_ate_m": _ate(smoothed, truth),
                           "frames_without_smoothed": len(set(estimated) - set(smoothed))})
    stamps = [int(r[0]) for r in rows]
    for previous, current, row in zip(stamps, stamps[1:], rows[1:], strict=False):
        error = _step_error(estimated, truth, previous, current)
        if error is not None:
            (tally.takeover_jumps if row[5] else tally.ordinary).append(error)


def _failover(robots: list[RobotRun], run: dict[str, Any]
              ) -> tuple[list[float], list[dict[str, float]]]:
    """For each kill and each robot it hit: the gap to its next answer and the gap's phases."""
    gaps: list[float] = []
    phases: list[dict[str, float]] = []
    for kill in run["kills"]:
        for robot in robots:
            if robot.session_id not in kill["sessions"]:
                continue
            after = [when for _pose, when in robot.answers.values() if when > kill["at"]]
            if after:
                gaps.append(min(after) - kill["at"])
            phase = _phases(robot, kill)
            if phase is not None:
                phases.append({k: round(v, 3) for k, v in phase.items()})
    return gaps, phases


def check(fleet: Fleet, robots: list[RobotRun], run: dict[str, Any]) -> dict[str, Any]:
    """Compare what robots were answered with what the database holds."""
    tally = _Tally()
    with Client(fleet.replicas[0].url, fleet.key, timeout=60) as client:
        calibrations = {r.name: client.get_session(r.session_id).calibration for r in robots}
    for robot in robots:
        rows = fleet.sql(
            "SELECT timestamp_ns, frame_index, pose::text, fence_token, writer, resumed "
            "FROM poses WHERE session_id = %s ORDER BY frame_index", robot.session_id)
        _check_answers(robot, rows, tally)
        tally.unfenced += _unfenced(rows)
        _check_accuracy(fleet, robot, rows, calibrations[robot.name], run, tally)
    gaps, phases = _failover(robots, run)
    return _verdict(tally, robots, gaps, phases)


def _verdict(tally: _Tally, robots: list[RobotRun], gaps: list[float],
             phases: list[dict[str, float]]) -> dict[str, Any]:
    """The result's failover section, in the order the table and the JSON show it."""
    takeover_jumps, ordinary, accuracy = tally.takeover_jumps, tally.ordinary, tally.accuracy
    return {
        "acknowledged_poses_lost": tally.lost + tally.mismatched,
        "duplicate_poses": tally.duplicates,
        "poses_without_lease": tally.unfenced,
        "frames_unanswered": tally.unanswered,
        "problems": tally.problems[:10],
        "frames_rejected": sum(len(r.rejected) for r in robots),
        "rejections": [rej for r in robots for rej in r.rejected][:10],
        "answers_from_stored_pose": sum(r.duplicates for r in robots),
        "reconnects": sum(r.reconnects for r in robots),
        "frames_resent": sum(r.resent for r in robots),
        "failover_gaps_s": [round(g, 3) for g in gaps],
        "failover_gap_p95_s": _p95(gaps),
        "failover_phases_s": phases,
        "failover_phase_median_s": _phase_medians(phases),
        "takeover_jumps_m": [round(j, 5) for j in takeover_jumps],
        "accuracy": accuracy,
        "ate_median_m": _ate_medians(accuracy, "ate_m"),
        "smoothed_ate_median_m": _ate_medians(accuracy, "smoothed_ate_m"),
        "takeover_jump_max_m": max(takeover_jumps) if takeover_jumps else None,
        "ordinary_step_error_median_m": float(np.median(ordinary)) if ordinary else None,
        "ordinary_step_error_p95_m": _p95(ordinary),
    }


def _p95(values: list[float]) -> float | None:
    return float(np.percentile(values, 95)) if values else None


def _ate_medians(accuracy: list[dict[str, Any]], key: str) -> dict[str, float | None]:
    """Median ATE of the robots whose replica was killed and of the others."""
    def median(affected: bool) -> float | None:
        values = [a[key] for a in accuracy if a["affected"] == affected and a[key] is not None]
        return float(np.median(values)) if values else None
    return {"affected": median(True), "unaffected": median(False)}


PHASES = ("noticed", "reconnected", "lease_taken", "answered")


def _phase_medians(phases: list[dict[str, float]]) -> dict[str, float]:
    """Median time of each phase boundary after the kill, and of each phase itself."""
    if not phases:
        return {}
    medians = {name: float(np.median([p[name] for p in phases])) for name in PHASES}
    steps = {f"{b} - {a}": float(np.median([p[b] - p[a] for p in phases]))
             for a, b in itertools.pairwise(PHASES)}
    return {**medians, **steps}


def table(result: dict[str, Any]) -> str:
    failover = result["failover"]
    rows = [
        ("acknowledged poses lost", failover["acknowledged_poses_lost"], "0"),
        ("duplicate poses", failover["duplicate_poses"], "0"),
        ("poses written without the lease", failover["poses_without_lease"], "0"),
        ("frames never answered", failover["frames_unanswered"], "0"),
        ("failover gap p95 [s]", _fmt(failover["failover_gap_p95_s"]), "<= 2"),
        *_phase_rows(failover.get("failover_phase_median_s", {})),
        ("pose jump at takeover, max [mm]", _fmt(failover["takeover_jump_max_m"], 1000),
         "<= 10"),
        *_ate_rows(failover),
        ("ordinary step error median / p95 [mm]",
         f"{_fmt(failover['ordinary_step_error_median_m'], 1000)} / "
         f"{_fmt(failover['ordinary_step_error_p95_m'], 1000)}", "-"),
    ]
    if "overhead" in result:
        over = result["overhead"]
        rows.append(("per-frame overhead nginx + lease", f"{100 * over['overhead']:+.1f} % "
                     f"({over['fleet_ms']:.1f} vs {over['direct_ms']:.1f} ms)", "<= 10 %"))
    for level in result.get("throughput", []):
        rows.append((f"frames/s, {level['replicas']} replica(s), {level['robots']} robots",
                     f"{level['frames_per_s']:.1f} ({level['frames_per_s_per_core']:.1f} per "
                     f"core, {level['replica_cpu_ms_per_frame']:.0f} ms CPU/frame)", "-"))
    width = max(len(r[0]) for r in rows)
    lines = [f"{'measure':<{width}}  {'value':<44}  target", "-" * (width + 56)]
    lines += [f"{name:<{width}}  {value!s:<44}  {target}" for name, value, target in rows]
    return "\n".join(lines)


def _ate_rows(failover: dict[str, Any]) -> list[tuple[str, str, str]]:
    rows = []
    for key, label in (("ate_median_m", "ATE"), ("smoothed_ate_median_m", "smoothed ATE")):
        medians = failover.get(key) or {}
        rows.append((f"{label} median, killed / other robots [mm]",
                     f"{_fmt(medians.get('affected'), 1000)} / "
                     f"{_fmt(medians.get('unaffected'), 1000)}", "-"))
    missing = [a["frames_without_smoothed"] for a in failover.get("accuracy", [])
               if a["affected"]]
    rows.append(("frames without a smoothed pose, killed robots", str(missing), "-"))
    return rows


def _phase_rows(medians: dict[str, float]) -> list[tuple[str, str, str]]:
    """The gap's phases: median time after the kill at which each one ended."""
    labels = {"noticed": "stream broken seen by the client", "reconnected":
              "greeted again through nginx", "lease_taken": "lease taken by the new owner",
              "answered": "first frame answered"}
    return [(f"  median: {labels[name]} [s after kill]", _fmt(medians[name]), "-")
            for name in PHASES if name in medians]


def _fmt(value: float | None, scale: float = 1.0) -> str:
    return "n/a" if value is None else f"{value * scale:.2f}"
