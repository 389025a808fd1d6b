"""Service demo: start a server, stream a rendered sequence over WebSocket, print the error.

1. start ``swarmvo serve`` on 127.0.0.1 (a free port, a fresh data folder, a random API key);
2. wait for /healthz;
3. render a short sequence with ``swarmvo synth`` (or use ``--dataset DIR``);
4. replay it through the Python client over the WebSocket stream;
5. print the trajectory error against ground truth, stop the server.

Every step is bounded in time; the server is stopped whatever happens.
"""

from __future__ import annotations

import argparse
import json
import os
import secrets
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from server_wait import wait_healthy
from swarmvo_client import replay, write_tum

PROJECT_ROOT = Path(__file__).resolve().parents[1]


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def main(argv: list[str] | None = None) -> int:
    args = _parse_args(argv)
    started = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="swarmvo-demo-") as folder:
        dataset = args.dataset if args.dataset is not None else _render(Path(folder), args)
        result = _serve_and_replay(Path(folder) / "data", dataset, args)
    args.out.mkdir(parents=True, exist_ok=True)
    write_tum(args.out / "trajectory.tum", result.timestamps_ns, result.matrices)
    summary = _summary(result)
    (args.out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    _print_summary(summary, result)
    print(f"wrote {args.out / 'trajectory.tum'}; demo took {time.perf_counter() - started:.0f} s")
    return 0 if result.poses and not result.rejected else 1


def _parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", type=Path, help="EuRoC/KITTI folder (default: render one)")
    parser.add_argument("--frames", type=int, default=60, help="frames to render / replay")
    parser.add_argument("--length-m", type=float, default=3.0, help="rendered path length")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=PROJECT_ROOT / "demo-output" / "service")
    parser.add_argument("--timeout", type=float, default=600, help="bound for the replay [s]")
    return parser.parse_args(argv)


def _render(folder: Path, args: argparse.Namespace) -> Path:
    """Step 3: a rendered sequence in ``folder`` (``swarmvo synth``)."""
    dataset = folder / "synthetic"
    print(f"rendering {args.frames} frames ({args.length_m} m) with swarmvo synth ...")
    subprocess.run(
        [sys.executable, "-m", "estimator.cli.main", "synth", str(dataset), "--frames",
         str(args.frames), "--length-m", str(args.length_m), "--seed", str(args.seed),
         "--quiet"],
        cwd=PROJECT_ROOT, check=True, timeout=300,
    )
    return dataset


def _serve_and_replay(data: Path, dataset: Path, args: argparse.Namespace):
    """Steps 1, 2 and 4: a server on a free port, healthy, replayed into; always stopped."""
    key = secrets.token_hex(16)
    port = _free_port()
    url = f"http://127.0.0.1:{port}"
    env = {**os.environ, "SWARMVO_API_KEYS": key}
    server = subprocess.Popen(
        [sys.executable, "-m", "estimator.cli.main", "serve", "--host", "127.0.0.1", "--port",
         str(port), "--data-dir", str(data), "--log-level", "warning"],
        cwd=PROJECT_ROOT, env=env,
    )
    try:
        wait_healthy(url, server, 90, poll_s=0.25)
        print(f"server healthy at {url} (pid {server.pid}); replaying over WebSocket ...")
        return _bounded_replay(url, dataset, key, args, timeout=args.timeout)
    finally:
        server.send_signal(signal.SIGTERM)
        try:
            server.wait(timeout=30)
        except subprocess.TimeoutExpired:
            server.kill()
            server.wait()


def _summary(result) -> dict:
    summary = {
        "frames_acknowledged": len(result.poses),
        "frames_dropped": len(result.dropped),
        "frames_rejected": len(result.rejected),
        "replay_fps": round(len(result.poses) / result.wall_time_s, 2),
        "median_odometry_ms": _median_ms(result.poses, "odometry"),
        "median_latency_in_server_ms": _median_ms(result.poses, "total"),
    }
    if result.error is not None:
        summary.update(
            ate_rmse_m=round(result.error.ate_rmse_m, 4),
            ate_max_m=round(result.error.ate_max_m, 4),
            path_length_m=round(result.error.path_length_m, 3),
        )
    return summary


def _print_summary(summary: dict, result) -> None:
    """Step 5: the summary and the trajectory error."""
    print()
    for name, value in summary.items():
        print(f"{name:>20}: {value}")
    if result.error is not None:
        relative = 100 * result.error.ate_rmse_m / max(result.error.path_length_m, 1e-9)
        print(f"trajectory error: ATE RMSE {result.error.ate_rmse_m:.4f} m over "
              f"{result.error.path_length_m:.2f} m ({relative:.2f} % of the path)")


def _median_ms(poses: list, stage: str) -> float | None:
    values = sorted(p.timings_s[stage] for p in poses if stage in p.timings_s)
    return round(1000 * values[len(values) // 2], 1) if values else None


def _bounded_replay(url: str, dataset: Path, key: str, args: argparse.Namespace,
                    timeout: float):
    """Replay with a hard time bound (the WebSocket replay runs its own event loop)."""
    import concurrent.futures

    with concurrent.futures.ThreadPoolExecutor(1) as pool:
        future = pool.submit(replay, url, dataset, key, use_ws=True, limit=args.frames,
                             config={"seed": args.seed}, progress=True)
        return future.result(timeout=timeout)


if __name__ == "__main__":
    sys.exit(main())
