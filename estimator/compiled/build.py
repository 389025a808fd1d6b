"""Build the kernels ahead of time: one extension module with every entry point, and its manifest.

Each entry point's variants are compiled by numba's ahead-of-time compiler (``numba.pycc``)
through a one-line trampoline that calls the kernel's own just-in-time dispatcher, so the
kernel keeps its options (fastmath, error model) and the helpers it calls are compiled in.
The machine code targets ``x86-64-v3`` on x86 (AVX2 and FMA: every x86 server and laptop CPU
since about 2015; measured as fast as numba's code for this machine's own CPU), so a build can
move to another machine; the manifest names the CPU features it needs.
"""

from __future__ import annotations

import ast
import importlib
import json
import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from estimator.compiled import KERNELS, MODE_VARIABLE, KernelMode, KernelSpec, active_mode
from estimator.compiled.built import (
    DIRECTORY,
    EXTENSION,
    MANIFEST,
    MANIFEST_FORMAT,
    PACKAGE_ROOT,
    cpu_flags,
    source_digest,
    versions,
)

__all__ = ["build", "kernel_modules", "main"]

# The CPU features of x86-64-v3 as /proc/cpuinfo names them ("abm" is LZCNT).
X86_64_V3 = ("avx", "avx2", "bmi1", "bmi2", "f16c", "fma", "movbe", "xsave", "abm")


def kernel_modules() -> list[str]:
    """Every estimator module that declares kernels (by the import of ``kernel``)."""
    names = []
    for path in sorted((PACKAGE_ROOT / "estimator").rglob("*.py")):
        if "from estimator.compiled import kernel" in path.read_text():
            relative = path.relative_to(PACKAGE_ROOT).with_suffix("")
            names.append(".".join(relative.parts))
    return names


def _source_files(modules: list[str]) -> list[str]:
    """The kernel modules' files and every estimator module they import, transitively: the
    sources whose change can change the compiled code (constants included). Of this package
    only the declaration (``__init__``) counts: the loader and the build are not compiled."""
    seen: set[str] = set()
    pending = list(modules)
    while pending:
        name = pending.pop()
        module = sys.modules.get(name)
        if name in seen or module is None or not getattr(module, "__file__", None):
            continue
        if name.startswith(f"{__package__}."):
            continue
        seen.add(name)
        tree = ast.parse(Path(module.__file__).read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("estimator"):
                pending.append(node.module)
                pending.extend(f"{node.module}.{alias.name}" for alias in node.names)
            elif isinstance(node, ast.Import):
                pending.extend(a.name for a in node.names if a.name.startswith("estimator"))
    files = {Path(sys.modules[name].__file__).resolve() for name in seen}
    return sorted(str(path.relative_to(PACKAGE_ROOT)) for path in files)


def _argument(numba_type: Any, kernel_name: str) -> dict[str, Any]:
    from numba.core import types

    if isinstance(numba_type, types.Array):
        if numba_type.layout not in ("C", "A"):
            raise ValueError(f"{kernel_name}: only C-contiguous or any-layout arrays")
        return {"kind": "array", "dtype": str(numba_type.dtype), "ndim": numba_type.ndim,
                "contiguous": numba_type.layout == "C"}
    if isinstance(numba_type, types.UniTuple):
        return {"kind": "tuple",
                "items": [_argument(numba_type.dtype, kernel_name)] * numba_type.count}
    for kind, family in (("boolean", types.Boolean), ("integer", types.Integer),
                         ("float", types.Float)):
        if isinstance(numba_type, family):
            return {"kind": kind}
    raise ValueError(f"{kernel_name}: argument type {numba_type} cannot be built ahead of time")


def _trampoline(target: Any, count: int) -> Any:
    """``def entry(a0, a1, ...): return target(a0, a1, ...)``: the exported function."""
    names = ", ".join(f"a{i}" for i in range(count))
    namespace: dict[str, Any] = {"target": target}
    exec(f"def entry({names}):\n    return target({names})\n", namespace)
    return namespace["entry"]


def _export(cc: Any, spec: KernelSpec) -> list[dict[str, Any]]:
    from numba.core import types

    module = sys.modules[spec.function.__module__]
    dispatcher = getattr(module, spec.function.__name__)
    variants = []
    for index, text in enumerate(spec.argument_types):
        argument_types = tuple(eval(f"({text},)", {}, dict(types.__dict__)))
        dispatcher.compile(argument_types)
        return_type = dispatcher.overloads[argument_types].signature.return_type
        symbol = f"{spec.name.replace('.', '__')}__{index}"
        cc.export(symbol, return_type(*argument_types))(
            _trampoline(dispatcher, len(argument_types))
        )
        variants.append({"symbol": symbol, "types": text,
                         "arguments": [_argument(t, spec.name) for t in argument_types]})
    return variants


def _release_gil_in_exports() -> None:
    """The exported wrappers release the GIL around the compiled code, as the just-in-time
    kernels (``nogil``) do; numba.pycc has no option for it, so its flags are extended."""
    from numba.pycc import compiler

    base = compiler.Flags

    class ReleasingFlags(base):  # type: ignore[misc, valid-type]
        def __init__(self, *args: object, **kwargs: object) -> None:
            super().__init__(*args, **kwargs)
            self.release_gil = True

    compiler.Flags = ReleasingFlags


def build(force: bool = False, quiet: bool = False) -> Path:
    """Compile every entry point into the extension beside this module; returns the manifest.
    Up to date (same sources, versions and CPU target): nothing is compiled."""
    if active_mode() is not KernelMode.BUILD:
        raise RuntimeError(
            f"the build runs with {MODE_VARIABLE}=build (python -m estimator.compiled)"
        )
    modules = kernel_modules()
    for name in modules:
        importlib.import_module(name)
    sources = _source_files(modules)
    x86 = platform.machine() in ("x86_64", "AMD64")
    target, flags = ("x86-64-v3", list(X86_64_V3)) if x86 else ("", [])
    manifest: dict[str, Any] = {
        "format": MANIFEST_FORMAT, "versions": versions(), "cpu": target or "generic",
        "cpu_flags": flags, "sources": sources, "digest": source_digest(sources),
    }
    if not force and _up_to_date(manifest):
        if not quiet:
            print(f"kernels built ahead of time are up to date ({MANIFEST})")
        return MANIFEST
    missing = sorted(set(flags) - cpu_flags())
    if missing:
        raise RuntimeError(f"this CPU lacks {', '.join(missing)} needed by {target}")
    from numba.pycc import CC

    _release_gil_in_exports()
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="swarmvo-kernels-") as scratch:
        cc = CC(EXTENSION.rsplit(".", 1)[-1])
        cc.output_dir = scratch
        cc.target_cpu = target
        cc.verbose = False
        entries = {spec.name: _export(cc, spec) for spec in KERNELS if spec.argument_types}
        try:
            cc.compile()
        except Exception as error:  # numba's and distutils' own errors: one line, not a trace
            raise RuntimeError(f"compiling the kernels failed (needs a C compiler such as gcc "
                               f"and the Python headers): {error}") from error
        (built,) = Path(scratch).glob("_kernels*.so")
        # The old manifest goes first: a process starting meanwhile finds no build (and
        # compiles just in time) instead of the new module under the old manifest.
        MANIFEST.unlink(missing_ok=True)
        for old in DIRECTORY.glob("_kernels*.so"):
            old.unlink()
        shutil.move(str(built), DIRECTORY / built.name)
    manifest["entries"] = entries
    temporary = MANIFEST.with_suffix(".json.tmp")
    temporary.write_text(json.dumps(manifest, indent=1) + "\n")
    os.replace(temporary, MANIFEST)
    if not quiet:
        variants = sum(len(v) for v in entries.values())
        print(f"built {len(entries)} kernels ({variants} variants) for {manifest['cpu']} in "
              f"{time.perf_counter() - start:.0f} s: {DIRECTORY.relative_to(PACKAGE_ROOT)}/")
    return MANIFEST


def _up_to_date(manifest: dict[str, Any]) -> bool:
    if not MANIFEST.exists() or not any(DIRECTORY.glob("_kernels*.so")):
        return False
    try:
        old = json.loads(MANIFEST.read_text())
    except ValueError:  # unreadable: build again
        return False
    return all(old.get(key) == value for key, value in manifest.items())


def main(argv: list[str] | None = None) -> int:
    import argparse

    parser = argparse.ArgumentParser(
        prog="python -m estimator.compiled",
        description="Build the estimator's numba kernels ahead of time (estimator/compiled).",
    )
    parser.add_argument("--force", action="store_true", help="rebuild even when up to date")
    parser.add_argument("--quiet", action="store_true")
    args = parser.parse_args(argv)
    try:
        build(force=args.force, quiet=args.quiet)
    except (RuntimeError, ValueError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 1
    return 0
