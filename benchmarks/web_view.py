"""The live view in headless Chromium: a 10,000-pose session, then 20 new poses a second.

1. write a session of ``--poses`` poses (a climbing spiral, some degraded and lost frames)
   straight into a fresh SQLite store, and start ``swarmvo serve`` on it;
2. open the session's page and time the first draw: from navigation start until the whole
   backlog is drawn (page load, watcher handshake, store read, transfer and drawing);
3. append poses at ``--rate`` Hz for ``--seconds`` while the page follows, sampling the page's
   update count, its drawing time and the JavaScript heap (after a garbage collection);
4. print a table and write ``benchmarks/results/web_view/web_view.json``.

Poses come from the store, not the odometry (which could not produce 20 frames a second
here): this measures the service's watcher channel and the browser, which is the point.
``screenshots`` instead streams a rendered flight and the real EuRoC MH01 clip through the real
odometry and saves the two pictures of docs/web-view.md.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import platform
import secrets
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from server_wait import wait_healthy

from service.answer import FrameAnswer, matrix_of
from service.settings import hash_key
from service.storage import Store
from service.web.browser import Browser, find_chromium

PROJECT_ROOT = Path(__file__).resolve().parents[1]
RESULTS = PROJECT_ROOT / "benchmarks" / "results" / "web_view"
SHARED_DATA = PROJECT_ROOT.parent / "shared" / "data"


def spiral_pose(session_id: str, index: int, rate_hz: float) -> FrameAnswer:
    """Frame ``index`` of a climbing spiral flown at 1 m/s (what a long survey looks like)."""
    t = index / rate_hz
    radius = 4.0 + 0.002 * index
    angle = t / radius
    position = (radius * math.cos(angle), radius * math.sin(angle), 0.01 * t)
    heading = angle + math.pi / 2
    c, s = math.cos(heading), math.sin(heading)
    # Camera axes in a z-up world: x right, y down, z forward along the heading.
    rotation = [[s, 0.0, c], [-c, 0.0, s], [0.0, -1.0, 0.0]]
    pose = [*rotation[0], position[0], *rotation[1], position[1], *rotation[2], position[2],
            0.0, 0.0, 0.0, 1.0]
    status = "lost" if index % 997 == 500 else "degraded" if index % 101 == 50 else "ok"
    return FrameAnswer(
        session_id=session_id, index=index, timestamp_ns=int(1e9 * t) + 1,
        pose=matrix_of(pose), frontend_pose=matrix_of(pose),
        relative_pose=matrix_of([1.0, 0, 0, 0, 0, 1.0, 0, 0, 0, 0, 1.0, 0, 0, 0, 0, 1.0]),
        status=status, matches=400, inliers=250 + (index * 37) % 150, support=0, message="",
        resumed=False,
        timings_s={"queue_wait": 0.001, "decode": 0.004, "odometry": 0.03 + 0.01 * (index % 7),
                   "transfer": 0.001},
    )


def _free_port() -> int:
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


class Service:
    """``swarmvo serve`` on a data folder, stopped on exit."""

    def __init__(self, data: Path, key: str) -> None:
        self.port = _free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        env = {**os.environ, "SWARMVO_API_KEYS": key, "OMP_NUM_THREADS": "1"}
        self.process = subprocess.Popen(
            [sys.executable, "-m", "estimator.cli.main", "serve", "--port", str(self.port),
             "--data-dir", str(data), "--workers", "1", "--log-level", "warning"],
            cwd=PROJECT_ROOT, env=env,
        )
        try:
            wait_healthy(self.url, self.process, 90, poll_s=0.25)
        except RuntimeError:
            self.stop()
            raise

    def __enter__(self) -> Service:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.stop()

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()


def open_page(browser: Browser, url: str, key: str, session_id: str) -> None:
    """The session's page with the key already in the tab's storage (as if typed before)."""
    browser.navigate(f"{url}/web/static/style.css")  # same origin, no script that could race
    browser.wait_for(f"location.origin === {json.dumps(url)} && "
                     "document.readyState === 'complete'", what="the service's page")
    browser.evaluate(f"sessionStorage.setItem('swarmvo.key', {json.dumps(key)})")
    browser.navigate(f"{url}/sessions/{session_id}")


def stats(browser: Browser) -> dict:
    return json.loads(browser.evaluate("JSON.stringify(window.swarmvoView.stats)"))


def bench(args: argparse.Namespace) -> int:
    chromium = find_chromium()
    if chromium is None:
        print("no Chromium found: apt-get install chromium", file=sys.stderr)
        return 2
    key = secrets.token_hex(16)
    RESULTS.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="swarmvo-webbench-") as folder:
        data = Path(folder) / "data"
        store = Store.open(f"sqlite:///{data / 'swarmvo.sqlite3'}")
        session_id = write_backlog(store, key, args)
        page = measure_page(data, key, chromium, store, session_id, args)
        store.close()
    summary = {
        **first_draw_summary(args, page),
        **following_summary(args, page),
        **environment(chromium),
    }
    (RESULTS / "web_view.json").write_text(json.dumps(summary, indent=2) + "\n")
    print_table(summary)
    ok = page.first < 1000 and summary["page_updates_per_s"] >= 0.9 * args.rate and not page.errors
    return 0 if ok else 1


@dataclass
class PageRun:
    """What the page reported: the first draw, its stats before and after following, the heap
    after a garbage collection at both ends, the per-second samples and any page errors."""

    first: float
    start: dict
    end: dict
    heap_start: int
    heap_end: int
    samples: list
    errors: list


def write_backlog(store: Store, key: str, args: argparse.Namespace) -> str:
    """Step 1: the ``--poses`` spiral session, written straight into the store; its id."""
    record = store.create_session(hash_key(key), "10k-pose spiral", {}, {}, None, (752, 480))
    began = time.perf_counter()
    for index in range(args.poses):
        store.add_pose(spiral_pose(record.id, index, args.rate))
    print(f"wrote {args.poses} poses in {time.perf_counter() - began:.1f} s")
    return record.id


def measure_page(
    data: Path, key: str, chromium: str, store: Store, session_id: str, args: argparse.Namespace
) -> PageRun:
    """Steps 2 and 3: a server on ``data``, the page's first draw, then following new poses."""
    with Service(data, key) as service, Browser(chromium) as browser:
        open_page(browser, service.url, key, session_id)
        first = browser.wait_for(
            f"window.swarmvoView?.stats.drawn === {args.poses} && "
            "window.swarmvoView.stats.firstDrawMs", timeout=60, what="the first draw")
        start = stats(browser)
        browser.screenshot(RESULTS / "web_view_10k.png")
        heap_start = browser.heap_used()
        samples = follow(browser, store, session_id, args)
        end = stats(browser)
        heap_end = browser.heap_used()
        errors = browser.exceptions()
    return PageRun(first, start, end, heap_start, heap_end, samples, errors)


def first_draw_summary(args: argparse.Namespace, page: PageRun) -> dict:
    start = page.start
    return {
        "poses_at_start": args.poses,
        "first_draw_ms": round(page.first, 1),
        "first_path_on_screen_ms": round(start["firstPathMs"], 1),
        "watcher_hello_ms": round(start["helloMs"], 1),
        "backlog_received_ms": round(start["syncedMs"], 1),
        "full_redraw_ms": round(start["fullDrawMs"], 1),
        "page_message_handling_ms": round(start["messageMs"], 1),
        "page_drawing_until_first_draw_ms": round(start["drawMsTotal"], 1),
        "vertices_drawn_at_start": start["vertices"],
    }


def following_summary(args: argparse.Namespace, page: PageRun) -> dict:
    start, end, samples = page.start, page.end, page.samples
    duration = samples[-1]["t"] - samples[0]["t"]
    added = samples[-1]["poses"] - samples[0]["poses"]
    updates = samples[-1]["updates"] - samples[0]["updates"]
    return {
        "rate_hz_sent": args.rate,
        "seconds": round(duration, 1),
        "poses_added": end["poses"] - start["poses"],
        "page_updates_per_s": round(updates / duration, 1),
        "poses_received_per_s": round(added / duration, 1),
        "mean_update_draw_ms": round(
            (end["drawMsTotal"] - start["drawMsTotal"]) / max(1, end["updates"] - start["updates"]),
            2),
        "max_update_draw_ms": round(end["drawMsMax"], 1),
        "full_redraws_during_updates": end["redraws"] - start["redraws"],
        "heap_after_gc_start_mb": round(page.heap_start / 2**20, 2),
        "heap_after_gc_end_mb": round(page.heap_end / 2**20, 2),
        "heap_growth_kb": round((page.heap_end - page.heap_start) / 1024, 1),
        "heap_after_gc_every_10_s_mb": [round(s["heap"] / 2**20, 2) for s in samples if s["gc"]],
        "heap_samples_mb": [round(s["heap"] / 2**20, 2) for s in samples],
        "page_errors": page.errors,
    }


def environment(chromium: str) -> dict:
    return {
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, shared with other work",
        "load_average_1min": round(os.getloadavg()[0], 1),
        "browser": subprocess.run([chromium, "--version"], capture_output=True, text=True,
                                  check=False).stdout.strip(),
    }


def follow(browser: Browser, store: Store, session_id: str, args: argparse.Namespace) -> list:
    """Append poses at ``args.rate`` Hz in a thread; sample the page once a second."""
    stop = threading.Event()

    def writer() -> None:
        index = args.poses
        next_at = time.perf_counter()
        while not stop.is_set():
            store.add_pose(spiral_pose(session_id, index, args.rate))
            index += 1
            next_at += 1.0 / args.rate
            time.sleep(max(0.0, next_at - time.perf_counter()))

    thread = threading.Thread(target=writer, daemon=True)
    samples = []
    thread.start()
    try:
        end = time.monotonic() + args.seconds
        while time.monotonic() < end:
            time.sleep(1.0)
            page = stats(browser)
            # Every tenth sample after a garbage collection: the trend of live memory.
            collect = len(samples) % 10 == 9
            samples.append({"t": time.monotonic(), "updates": page["updates"],
                            "poses": page["poses"], "gc": collect,
                            "heap": browser.heap_used(collect=collect)})
    finally:
        stop.set()
        thread.join()
    return samples


def print_table(summary: dict) -> None:
    rows = [
        ("poses on the page at start", summary["poses_at_start"]),
        ("first draw (navigation -> all drawn)", f"{summary['first_draw_ms']} ms"),
        ("  first part of the path on screen at", f"{summary['first_path_on_screen_ms']} ms"),
        ("  page loaded, watcher answered at", f"{summary['watcher_hello_ms']} ms"),
        ("  backlog received (read, sent, parsed) at", f"{summary['backlog_received_ms']} ms"),
        ("  the last full draw itself", f"{summary['full_redraw_ms']} ms"),
        ("  page: handling messages / all drawing",
         f"{summary['page_message_handling_ms']} / "
         f"{summary['page_drawing_until_first_draw_ms']} ms"),
        ("  vertices drawn after decimation", summary["vertices_drawn_at_start"]),
        ("poses sent", f"{summary['rate_hz_sent']} Hz for {summary['seconds']} s"),
        ("poses received by the page", f"{summary['poses_received_per_s']} /s"),
        ("page updates (redraws with new poses)", f"{summary['page_updates_per_s']} /s"),
        ("drawing time per update, mean / max",
         f"{summary['mean_update_draw_ms']} / {summary['max_update_draw_ms']} ms"),
        ("full redraws while following", summary["full_redraws_during_updates"]),
        ("JS heap after GC, start -> end",
         f"{summary['heap_after_gc_start_mb']} -> {summary['heap_after_gc_end_mb']} MB "
         f"({summary['heap_growth_kb']:+} kB)"),
        ("  after GC every 10 s",
         " ".join(f"{v:.2f}" for v in summary["heap_after_gc_every_10_s_mb"]) + " MB"),
        ("page errors", len(summary["page_errors"])),
        ("machine load average (1 min)", summary["load_average_1min"]),
    ]
    width = max(len(name) for name, _ in rows)
    print(f"\n{'live view, headless ' + summary['browser']:^{width + 24}}")
    for name, value in rows:
        print(f"{name:<{width}}  {value}")


def screenshots(args: argparse.Namespace) -> int:
    """Two pictures for the docs: a rendered flight while it streams, a finished real run."""
    from swarmvo_client import Client
    from swarmvo_client.datasets import open_local_sequence
    from swarmvo_client.replay import create_session_for, replay_ws

    chromium = find_chromium()
    if chromium is None:
        print("no Chromium found: apt-get install chromium", file=sys.stderr)
        return 2
    key = secrets.token_hex(16)
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="swarmvo-webshots-") as folder:
        rendered = Path(folder) / "rendered"
        subprocess.run(
            [sys.executable, "-m", "estimator.cli.main", "synth", str(rendered), "--frames", "160",
             "--length-m", "6", "--seed", "4", "--broken-fraction", "0.04", "--quiet"],
            cwd=PROJECT_ROOT, check=True, timeout=900,
        )
        with Service(Path(folder) / "data", key) as service, Browser(chromium) as browser:
            runs = [(rendered, "rendered flight", "web-view-live.png", 0.6)]
            euroc = SHARED_DATA / "euroc_mh01_moving"
            if (euroc / "mav0").is_dir():
                runs.append((euroc, "EuRoC MH01 (real)", "web-view-finished.png", None))
            for dataset, name, picture, live_fraction in runs:
                sequence = open_local_sequence(dataset)
                with Client(service.url, key) as api:
                    session = create_session_for(api, sequence, {"seed": 3}, name=name)
                open_page(browser, service.url, key, session.id)
                browser.wait_for("window.swarmvoView?.stats.synced", timeout=30)
                thread = threading.Thread(target=lambda s=session, q=sequence: asyncio.run(
                    replay_ws(service.url, key, s, q, progress=False, window=2)), daemon=True)
                thread.start()
                total = len(sequence.frames)
                if live_fraction is not None:
                    enough = int(live_fraction * total)
                    browser.wait_for(f"window.swarmvoView.stats.poses >= {enough} && "
                                     "window.swarmvoView.stats.activity === 'live'", timeout=900)
                    time.sleep(0.3)
                    browser.screenshot(args.out / picture)
                thread.join()
                if live_fraction is None:
                    browser.wait_for("window.swarmvoView.stats.activity === 'idle' && "
                                     "!document.querySelector('#summary').hidden", timeout=60)
                    time.sleep(0.5)
                    browser.screenshot(args.out / picture)
                print(f"wrote {args.out / picture}")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)
    run = commands.add_parser("bench", help="10,000 poses, then 20 Hz updates")
    run.add_argument("--poses", type=int, default=10_000)
    run.add_argument("--rate", type=float, default=20.0, help="new poses per second")
    run.add_argument("--seconds", type=float, default=60.0)
    shots = commands.add_parser("screenshots", help="the two pictures of docs/web-view.md")
    shots.add_argument("--out", type=Path, default=PROJECT_ROOT / "docs")
    args = parser.parse_args(argv)
    return bench(args) if args.command == "bench" else screenshots(args)


if __name__ == "__main__":
    sys.exit(main())
