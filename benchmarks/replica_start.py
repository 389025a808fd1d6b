"""How long a fresh replica takes to answer: start to /healthz, then a robot's first frames.

A replica's worker processes warm up before it answers (service.estimator_adapter); what that
costs depends on the JIT cache it finds. ``--cache`` names the numba cache folder the replica
uses (NUMBA_CACHE_DIR); ``--fill`` runs ``python -m service.warmup`` into it first, as the image
build does; an empty folder is what a replica saw in the image before the build filled a cache
its user can read. One worker, SQLite, a rendered flight (benchmarks/cluster.py caches it).
Old code: ``PYTHONPATH=/tmp/old python benchmarks/replica_start.py ...`` (without ``--fill``).

    python benchmarks/replica_start.py --cache /tmp/cache --fill --out /tmp/start.json
"""

from __future__ import annotations

import argparse
import json
import os
import secrets
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx

sys.path.insert(0, str(Path(__file__).resolve().parent))

from cluster import new_session, open_local_sequence, render_flights
from local_cluster import PROJECT_ROOT, REPLICA_CODE, free_port
from server_wait import wait_healthy


def post_frame(url: str, key: str, session_id: str, sequence, index: int
               ) -> tuple[float, int, str]:
    """Seconds to the answer, its status and (when refused) its reason."""
    left, right = sequence.frame_bytes(index)
    start = time.perf_counter()
    answer = httpx.post(
        f"{url}/v1/sessions/{session_id}/frames", headers={"Authorization": f"Bearer {key}"},
        files={"left": ("l.png", left, "image/png"), "right": ("r.png", right, "image/png")},
        data={"timestamp_ns": str(sequence.frames[index].timestamp_ns)}, timeout=900,
    )
    seconds = time.perf_counter() - start
    detail = "" if answer.status_code == 200 else answer.json().get("detail", "")[:120]
    return seconds, answer.status_code, detail


def rss_mb(pid: int) -> float:
    """The server process alone (its workers hold the estimator whatever the server does)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return round(int(line.split()[1]) / 1024, 1)
    raise RuntimeError(f"no VmRSS for process {pid}")


def measure(cache: Path, frames: int) -> dict[str, object]:
    sequence = open_local_sequence(render_flights(1, 20)[0])
    key = secrets.token_hex(8)
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    with tempfile.TemporaryDirectory(prefix="swarmvo-start-") as folder:
        env = {**os.environ, "OMP_NUM_THREADS": "1", "NUMBA_CACHE_DIR": str(cache),
               "SWARMVO_API_KEYS": key, "SWARMVO_WORKERS": "1", "SWARMVO_HOST": "127.0.0.1",
               "SWARMVO_PORT": str(port), "SWARMVO_DATA_DIR": folder}
        process = subprocess.Popen([sys.executable, "-c", REPLICA_CODE], cwd=PROJECT_ROOT,
                                   env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            healthy_s = wait_healthy(url, process, timeout_s=3600, poll_s=0.1)
            session = new_session(url, key, sequence, "fresh")
            answers = [post_frame(url, key, session, sequence, i) for i in range(frames)]
            server_rss_mb = rss_mb(process.pid)
        finally:
            process.terminate()
            process.wait(timeout=60)
    return {"start_to_healthy_s": round(healthy_s, 2),
            "frame_latency_s": [round(seconds, 3) for seconds, _s, _d in answers],
            "frame_status": [status for _l, status, _d in answers],
            "refusals": sorted({detail for _l, _s, detail in answers if detail}),
            "start_to_first_answer_s": round(healthy_s + answers[0][0], 2),
            "server_process_rss_mb": server_rss_mb}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cache", type=Path, required=True, help="NUMBA_CACHE_DIR of the replica")
    parser.add_argument("--fill", action="store_true", help="python -m service.warmup first")
    parser.add_argument("--frames", type=int, default=5)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    args.cache.mkdir(parents=True, exist_ok=True)
    if args.fill:
        subprocess.run([sys.executable, "-m", "service.warmup"], check=True, cwd=PROJECT_ROOT,
                       env={**os.environ, "OMP_NUM_THREADS": "1",
                            "NUMBA_CACHE_DIR": str(args.cache)})
    result = {"cache": str(args.cache), "filled_first": args.fill, **measure(args.cache,
                                                                             args.frames)}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
