"""Waiting for a started server: one loop for every script that starts ``swarmvo serve``."""

from __future__ import annotations

import contextlib
import subprocess
import time

import httpx


def wait_healthy(
    url: str, process: subprocess.Popen, timeout_s: float, poll_s: float = 0.2
) -> float:
    """Seconds until ``url``/healthz answers 200; RuntimeError if the process exits first or
    the server is not healthy within ``timeout_s`` (the process is left to the caller)."""
    started = time.monotonic()
    while time.monotonic() - started < timeout_s:
        if process.poll() is not None:
            raise RuntimeError(f"the server exited during start-up (code {process.returncode})")
        with contextlib.suppress(httpx.HTTPError):
            if httpx.get(f"{url}/healthz", timeout=1).status_code == 200:
                return time.monotonic() - started
        time.sleep(poll_s)
    raise RuntimeError(f"the server was not healthy after {timeout_s:.0f} s")
