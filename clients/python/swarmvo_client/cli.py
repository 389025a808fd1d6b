"""``swarmvo-client`` command line: replay a dataset folder against a running server."""

from __future__ import annotations

import argparse
import json
import os
import socket
import sys
import warnings
from pathlib import Path

import httpx
import websockets

from swarmvo_client.encoding import ENCODINGS
from swarmvo_client.errors import SwarmvoError
from swarmvo_client.replay import replay, write_tum


def _replay(args: argparse.Namespace) -> int:
    config = json.loads(args.config) if args.config else {}
    if args.seed is not None:
        config["seed"] = args.seed
    result = replay(
        args.url,
        args.dataset,
        api_key=args.api_key,
        use_ws=args.ws,
        limit=args.limit,
        config=config,
        progress=not args.quiet,
        session_id=args.session,
        encoding=args.encoding,
        bag={
            "calibration": args.calibration,
            "left_topic": args.left_topic,
            "right_topic": args.right_topic,
            "imu_topic": args.imu_topic,
            "stereo_sync_tolerance_ms": args.stereo_sync_tolerance,
        },
    )
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_tum(out / "trajectory.tum", result.timestamps_ns, result.matrices)
    odometry = [pose.odometry for pose in result.poses if pose.odometry is not None]
    if odometry:
        with (out / "odometry.jsonl").open("w") as handle:
            handle.writelines(json.dumps(message) + "\n" for message in odometry)
    statuses: dict[str, int] = {}
    for pose in result.poses:
        statuses[pose.status] = statuses.get(pose.status, 0) + 1
    summary = {
        "session_id": result.session.id,
        "frames_acknowledged": len(result.poses),
        "frames_dropped": len(result.dropped),
        "frames_rejected": len(result.rejected),
        "status_counts": statuses,
        "resumed": any(p.resumed for p in result.poses),
        "wall_time_s": round(result.wall_time_s, 3),
        "fps": round(len(result.poses) / result.wall_time_s, 2) if result.wall_time_s else None,
    }
    if result.error is not None:
        summary.update(
            ate_rmse_m=result.error.ate_rmse_m,
            ate_max_m=result.error.ate_max_m,
            gt_path_length_m=result.error.path_length_m,
            frames_evaluated=result.error.pairs,
        )
    (out / "replay.json").write_text(json.dumps(summary, indent=2) + "\n")
    for key, value in summary.items():
        print(f"{key:>20}: {value}")
    for event in result.rejected[:5]:
        print(f"rejected {event.timestamp_ns}: HTTP {event.status} {event.detail}", file=sys.stderr)
    also = f", {out / 'odometry.jsonl'}" if odometry else ""
    print(f"wrote {out / 'trajectory.tum'}{also} and {out / 'replay.json'}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="swarmvo-client", description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)
    sub = commands.add_parser(
        "replay", help="replay a EuRoC or KITTI folder or a ROS bag against a server"
    )
    sub.add_argument(
        "dataset", type=Path, help="EuRoC folder (with mav0), KITTI sequence or ROS 1/2 bag"
    )
    sub.add_argument("--url", default="http://127.0.0.1:8000", help="server base URL")
    sub.add_argument(
        "--api-key", default=os.environ.get("SWARMVO_API_KEY"),
        help="API key (default: $SWARMVO_API_KEY)",
    )
    sub.add_argument("--ws", action="store_true", help="stream over the WebSocket endpoint")
    sub.add_argument(
        "--encoding", choices=ENCODINGS, default="raw8",
        help="WebSocket images: raw8 decodes 8-bit grey PNG files here and sends the pixels "
        "(spares the server the decode; the default), file sends them as stored",
    )
    sub.add_argument("--limit", type=int, help="send only the first N frames")
    sub.add_argument("--seed", type=int, help="estimator seed (config override)")
    sub.add_argument("--config", help="JSON estimator config overrides")
    sub.add_argument("--session", help="continue this session instead of creating one")
    sub.add_argument("--out", default="replay-output", help="folder for trajectory.tum")
    sub.add_argument("--quiet", action="store_true", help="no progress bar")
    bag = sub.add_argument_group("ROS bags (needs the swarmvo package)")
    bag.add_argument("--calibration", type=Path, help="EuRoC folder, Kalibr camchain or rig")
    bag.add_argument("--left-topic", help="left images (default: guessed)")
    bag.add_argument("--right-topic", help="right images (default: guessed)")
    bag.add_argument("--imu-topic", help="sensor_msgs/Imu (default: the bag's only one)")
    bag.add_argument(
        "--stereo-sync-tolerance",
        type=float,
        metavar="MS",
        help="pair left/right images whose stamps are nearest each other and at most MS "
        "milliseconds apart (default: a tenth of the frame period; 0 = equal stamps only), "
        "as swarmvo run does",
    )
    sub.set_defaults(handler=_replay)
    return parser


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """Warnings as one plain line: the user needs the message, not our source line."""
    print(f"swarmvo-client: warning: {message}", file=file or sys.stderr)


def _explained(error: Exception, url: str | None) -> str:
    """One line; a server that cannot be reached is named."""
    text = " ".join(str(error).split()) or type(error).__name__
    unreachable = (httpx.TransportError, ConnectionError, TimeoutError, socket.gaierror)
    if url and isinstance(error, unreachable):
        return f"cannot reach the server at {url}: {text}"
    return text


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    warnings.showwarning = _show_warning
    try:
        return int(args.handler(args))
    except (SwarmvoError, httpx.HTTPError, websockets.WebSocketException, OSError,
            ValueError) as error:
        message = _explained(error, getattr(args, "url", None))
        print(f"swarmvo-client {args.command}: error: {message}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
