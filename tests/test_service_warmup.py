"""The worker warm-up (``python -m service.warmup``, run by the image build and by the cluster
harness) reaches every JIT kernel a session needs: after it, real frames compile nothing more.
A kernel it misses would be compiled during a robot's first frames on every fresh replica.
These run with ``SWARMVO_KERNELS=jit``: with the kernels built ahead of time there is no
just-in-time cache to fill (tests/test_compiled_kernels.py)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

PROJECT_ROOT = Path(__file__).resolve().parents[1]
JIT = {**os.environ, "SWARMVO_KERNELS": "jit"}

# Runs in a fresh interpreter: kernels compiled by other tests in this process would hide a miss.
SCRIPT = """
import json, sys
from service.warmup import cached_kernels, warm_up
from estimator.cli.main import main
warm_up()
before = cached_kernels()
main(["run", sys.argv[1], "--limit", "8", "--quiet", "--out", sys.argv[2]])
print(json.dumps({"warm_up": before, "after": cached_kernels()}))
"""


@pytest.mark.slow
def test_real_frames_compile_nothing_after_the_warm_up(
    euroc_mh01_moving: Path, tmp_path: Path
) -> None:
    done = subprocess.run(
        [sys.executable, "-c", SCRIPT, str(euroc_mh01_moving), str(tmp_path / "run")],
        cwd=PROJECT_ROOT, env=JIT, capture_output=True, text=True, timeout=1200,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    counts = json.loads(done.stdout.strip().splitlines()[-1])
    warmed, after = counts["warm_up"], counts["after"]
    assert len(warmed) >= 10, warmed
    # Every kernel signature the real frames use was compiled or loaded by the warm-up.
    assert after == warmed, {k: v for k, v in after.items() if warmed.get(k) != v}

def test_expect_cached_refuses_a_warm_up_that_compiled(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """The image build's check: a process that had to compile (no usable cache) fails it."""
    from service import warmup

    monkeypatch.setattr(warmup, "warm_up", lambda: warmup.WarmUp(1.0, compiled=3, loaded=15))
    assert warmup.main(["--expect-cached"]) == 1
    assert "3 kernels compiled" in capsys.readouterr().out
    monkeypatch.setattr(warmup, "warm_up", lambda: warmup.WarmUp(1.0, compiled=0, loaded=18))
    assert warmup.main(["--expect-cached"]) == 0
    assert warmup.main([]) == 0
    # Kernels built ahead of time: nothing to compile and no cache to find.
    monkeypatch.setattr(warmup, "warm_up", lambda: warmup.WarmUp(0.5, 0, 0, ahead_of_time=True))
    assert warmup.main(["--expect-cached"]) == 0
    assert "kernels built ahead of time" in capsys.readouterr().out


WORKER_SCRIPT = """
import json
from service.estimator_adapter import EstimatorFactory
from service.warmup import cached_kernels
EstimatorFactory().warm_up()
print(json.dumps(cached_kernels()))
"""


def test_a_worker_warm_up_reaches_the_registration_kernels_of_real_frames() -> None:
    """A worker's own warm-up (not only the image build's) runs the ladder's refit kernel: with
    an empty JIT cache it is compiled before the worker takes frames, never inside a frame's
    CPU budget, which would interrupt the compile and refuse the frame."""
    done = subprocess.run([sys.executable, "-c", WORKER_SCRIPT], cwd=PROJECT_ROOT, env=JIT,
                          capture_output=True, text=True, timeout=1200)
    assert done.returncode == 0, done.stderr[-3000:]
    counts = json.loads(done.stdout.strip().splitlines()[-1])
    for kernel in ("fit_pose", "degenerate_points"):
        misses, hits = counts[f"estimator.registration.swarm_kernels.{kernel}"]
        assert misses + hits > 0, (kernel, counts)
    # The compiled detector (ORB on one level, the default, and fast-brief).
    for kernel in ("fast_kernels._fast_corners", "steered_brief._describe"):
        misses, hits = counts[f"estimator.frontend.{kernel}"]
        assert misses + hits > 0, (kernel, counts)
