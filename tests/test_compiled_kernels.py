"""Kernels built ahead of time (estimator/compiled): the same answers as numba's just-in-time
kernels, no numba in a process that uses them, argument types checked before the compiled code
reads memory, and a stale build never used."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from estimator.compiled import KernelMode, active_mode, running_ahead_of_time
from estimator.compiled.built import MANIFEST, BuiltKernels, CompiledEntry, mismatch

PROJECT_ROOT = Path(__file__).resolve().parents[1]

needs_build = pytest.mark.skipif(
    not MANIFEST.exists(), reason="no kernels built ahead of time (make kernels)"
)

# One run of the pipeline on the real clip in a fresh interpreter: the modules it loaded, its
# resident memory and its trajectory.
RUN_SCRIPT = """
import json, sys
from estimator.cli.main import main
from service.estimator_adapter import EstimatorFactory
EstimatorFactory().warm_up()
main(["run", sys.argv[1], "--limit", "40", "--no-imu", "--quiet", "--out", sys.argv[2]])
status = open("/proc/self/status").read()
rss = int(next(l for l in status.splitlines() if l.startswith("VmHWM")).split()[1]) / 1024
print(json.dumps({"numba": "numba" in sys.modules, "llvmlite": "llvmlite" in sys.modules,
                  "peak_rss_mb": rss}))
"""


def _run(mode: str, clip: Path, out: Path) -> tuple[dict, np.ndarray]:
    environment = {**os.environ, "SWARMVO_KERNELS": mode, "OMP_NUM_THREADS": "1"}
    done = subprocess.run(
        [sys.executable, "-c", RUN_SCRIPT, str(clip), str(out)], cwd=PROJECT_ROOT, env=environment,
        capture_output=True, text=True, timeout=1200,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    facts = json.loads(done.stdout.strip().splitlines()[-1])
    return facts, np.loadtxt(out / "trajectory.tum")


@needs_build
@pytest.mark.slow
def test_built_kernels_track_the_real_clip_as_the_jit_does_without_numba(
    euroc_mh01_moving: Path, tmp_path: Path
) -> None:
    built, built_poses = _run("aot", euroc_mh01_moving, tmp_path / "aot")
    jit, jit_poses = _run("jit", euroc_mh01_moving, tmp_path / "jit")
    assert not built["numba"] and not built["llvmlite"], built
    assert jit["numba"], jit
    assert built_poses.shape == jit_poses.shape and len(built_poses) >= 35
    np.testing.assert_allclose(built_poses, jit_poses, rtol=0, atol=1e-9)
    # The point of the build: a worker without LLVM is well over 100 MB smaller.
    assert built["peak_rss_mb"] < jit["peak_rss_mb"] - 100, (built, jit)


@needs_build
def test_a_wrong_argument_type_is_refused_before_the_compiled_code_reads_it() -> None:
    if not running_ahead_of_time():
        pytest.skip(f"this process compiles just in time (SWARMVO_KERNELS={active_mode().value})")
    from estimator.frontend import fast_kernels

    entry = fast_kernels._fast_corners
    assert isinstance(entry, CompiledEntry)
    image = np.zeros((40, 40), dtype=np.uint8)
    scratch = np.zeros(image.shape, dtype=np.int16)
    xs, _ys, _scores = entry(image, 20, 3, scratch)
    assert len(xs) == 0
    with pytest.raises(TypeError, match=r"_fast_corners was built for \(uint8\[2d, C\]"):
        entry(image.astype(np.float32), 20, 3, scratch)
    with pytest.raises(TypeError, match="not"):
        entry(image[:, ::2], 20, 3, scratch)  # not contiguous
    with pytest.raises(TypeError):
        entry(image, 20.5, 3, scratch)  # a float where an integer is compiled
    with pytest.raises(TypeError):
        entry(image, 20, 3)  # one argument short


@needs_build
def test_a_helper_inlined_into_the_kernels_has_no_python_copy() -> None:
    if not running_ahead_of_time():
        pytest.skip(f"this process compiles just in time (SWARMVO_KERNELS={active_mode().value})")
    from estimator.frontend import fast_kernels

    with pytest.raises(RuntimeError, match="compiled into other kernels only"):
        fast_kernels._raw_corners(np.zeros((8, 8), np.uint8), 20, 3)


@needs_build
def test_a_build_is_used_only_where_it_fits() -> None:
    manifest = json.loads(MANIFEST.read_text())
    assert mismatch(manifest) is None, mismatch(manifest)
    other_sources = {**manifest, "digest": "0" * 64}
    assert "other sources" in (mismatch(other_sources) or "")
    other_cpu = {**manifest, "cpu_flags": [*manifest["cpu_flags"], "no-such-feature"]}
    assert "no-such-feature" in (mismatch(other_cpu) or "")
    other_numba = {**manifest, "versions": {**manifest["versions"], "numba": "0.1"}}
    assert "numba 0.1" in (mismatch(other_numba) or "")
    # Every entry point the kernels declare is in the build, each variant loadable.
    built = BuiltKernels.load()
    for name in manifest["entries"]:
        assert callable(built.entry(name))


def test_an_unreadable_manifest_is_a_stale_build_not_a_crash(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from estimator.compiled import built

    for text in ("{not json", '{"format": 1}', "[]"):
        corrupt = tmp_path / "_kernels.json"
        corrupt.write_text(text)
        monkeypatch.setattr(built, "MANIFEST", corrupt)
        with pytest.raises(built.BuiltKernelsError, match="unreadable") as raised:
            BuiltKernels.load()
        assert raised.value.present  # auto mode warns and compiles just in time


def test_an_unknown_kernel_mode_is_one_line_from_the_cli() -> None:
    environment = {**os.environ, "SWARMVO_KERNELS": "fast"}
    done = subprocess.run([sys.executable, "-m", "estimator.cli", "config"], cwd=PROJECT_ROOT,
                          env=environment, capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    assert done.stderr == "swarmvo: error: SWARMVO_KERNELS='fast': expected one of auto, jit, aot\n"
    assert KernelMode("aot") is KernelMode.AOT
