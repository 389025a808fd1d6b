"""The kernels built ahead of time: the extension module, its manifest, and the checks that it
may run here.

The manifest (``_kernels.json`` beside the extension) records what the build was made from:
a digest of the source files the kernels are compiled from, the numba, NumPy and Python
versions, the CPU features the machine code uses, and each entry point's argument types. The
extension is used only when all of them still hold, and each call is checked against the
argument types first: numba's compiled wrappers read an array's memory as the declared type
without checking its dtype, so a wrong argument would be read as garbage, not refused.
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.metadata
import json
import platform
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "EXTENSION",
    "MANIFEST",
    "BuiltKernels",
    "BuiltKernelsError",
    "CompiledEntry",
    "cpu_flags",
    "mismatch",
    "source_digest",
]

PACKAGE_ROOT = Path(__file__).resolve().parents[2]  # the folder holding ``estimator/``
DIRECTORY = Path(__file__).resolve().parent
EXTENSION = "estimator.compiled._kernels"
MANIFEST = DIRECTORY / "_kernels.json"
MANIFEST_FORMAT = 1


class BuiltKernelsError(RuntimeError):
    """The built kernels cannot be used here; ``present``: a build exists but does not fit."""

    def __init__(self, message: str, present: bool) -> None:
        super().__init__(message)
        self.present = present


def source_digest(files: Sequence[str]) -> str:
    """SHA-256 over the named files (paths relative to the folder holding ``estimator/``)."""
    digest = hashlib.sha256()
    for name in sorted(files):
        digest.update(name.encode() + b"\0")
        digest.update((PACKAGE_ROOT / name).read_bytes())
    return digest.hexdigest()


def cpu_flags() -> frozenset[str]:
    """The CPU's feature flags as Linux lists them (empty where /proc/cpuinfo is missing)."""
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as cpuinfo:
            for line in cpuinfo:
                if line.startswith(("flags", "Features")):
                    return frozenset(line.split(":", 1)[1].split())
    except OSError:
        pass
    return frozenset()


def versions() -> dict[str, str]:
    """What compiled code depends on besides its sources."""
    return {
        "python": f"{sys.version_info.major}.{sys.version_info.minor}",
        "numba": importlib.metadata.version("numba"),
        "numpy": np.__version__,
        "machine": platform.machine(),
    }


# What Python values a compiled scalar argument takes (numba converts them on the way in).
_SCALAR_TYPES: dict[str, tuple[type, ...]] = {
    "integer": (int, np.integer),
    "float": (int, float, np.integer, np.floating),
    "boolean": (bool, np.bool_),
}


def _test(value: str, argument: dict[str, Any], namespace: dict[str, Any]) -> str:
    """A Python expression that is true when ``value`` fits the compiled ``argument``."""
    kind = argument["kind"]
    if kind == "array":
        dtype = f"D{len(namespace)}"
        namespace[dtype] = np.dtype(argument["dtype"])
        test = (f"isinstance({value}, ndarray) and {value}.ndim == {argument['ndim']} and "
                f"({value}.dtype is {dtype} or {value}.dtype == {dtype})")
        return f"({test} and {value}.flags.c_contiguous)" if argument["contiguous"] else f"({test})"
    if kind == "tuple":
        items = [_test(f"{value}[{i}]", item, namespace)
                 for i, item in enumerate(argument["items"])]
        return (f"(isinstance({value}, tuple) and len({value}) == {len(items)} and "
                f"{' and '.join(items)})")
    types = f"T{len(namespace)}"
    namespace[types] = _SCALAR_TYPES[kind]
    if kind == "integer":  # True is an int to Python, not an integer to the kernel
        return f"(isinstance({value}, {types}) and not isinstance({value}, bool))"
    return f"isinstance({value}, {types})"


def _argument_check(arguments: list[dict[str, Any]]) -> Callable[[tuple], bool]:
    """``check(args)``: the arguments fit the compiled types. Generated as one expression: a
    generic loop over the arguments cost about 0.6 us per argument and call."""
    namespace: dict[str, Any] = {"ndarray": np.ndarray}
    tests = [f"len(args) == {len(arguments)}"]
    tests += [_test(f"args[{i}]", argument, namespace) for i, argument in enumerate(arguments)]
    exec(f"def check(args):\n    return {' and '.join(tests)}\n", namespace)
    return namespace["check"]


def _built_type(argument: dict[str, Any]) -> str:
    if argument["kind"] == "array":
        return f"{argument['dtype']}[{argument['ndim']}d{', C' if argument['contiguous'] else ''}]"
    if argument["kind"] == "tuple":
        return "(" + ", ".join(_built_type(item) for item in argument["items"]) + ")"
    return argument["kind"]


def _given_type(value: object) -> str:
    if isinstance(value, np.ndarray):
        layout = ", C" if value.flags.c_contiguous else ""
        return f"{value.dtype}[{value.ndim}d{layout}]"
    return type(value).__name__


class CompiledEntry:
    """One entry point: the built variants, each behind a check of its argument types."""

    __slots__ = ("__name__", "__qualname__", "expected", "name", "variants")

    def __init__(self, name: str, variants: list[tuple[Callable[..., Any], list[dict]]]) -> None:
        self.name = name
        self.variants = [(function, _argument_check(arguments)) for function, arguments in variants]
        self.expected = "; ".join(
            "(" + ", ".join(_built_type(a) for a in arguments) + ")" for _f, arguments in variants
        )
        self.__qualname__ = name
        self.__name__ = name.rsplit(".", 1)[-1]

    def __call__(self, *args: object) -> Any:
        for function, check in self.variants:
            if check(args):
                return function(*args)
        given = ", ".join(_given_type(value) for value in args)
        raise TypeError(f"{self.name} was built for {self.expected}, not ({given})")


@dataclass(frozen=True)
class BuiltKernels:
    """The loaded extension and its manifest."""

    module: Any
    manifest: dict[str, Any]

    @classmethod
    def load(cls) -> BuiltKernels:
        if not MANIFEST.exists():
            raise BuiltKernelsError(
                "no kernels built ahead of time (python -m estimator.compiled)", present=False
            )
        try:
            manifest = json.loads(MANIFEST.read_text())
            problem = mismatch(manifest)
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as error:
            raise BuiltKernelsError(
                f"the manifest of the built kernels ({MANIFEST}) is unreadable: {error!r}; "
                "rebuild: python -m estimator.compiled --force", present=True,
            ) from None
        if problem:
            raise BuiltKernelsError(f"the kernels built ahead of time {problem}", present=True)
        try:
            module = importlib.import_module(EXTENSION)
        except ImportError as error:
            raise BuiltKernelsError(
                f"cannot load the built kernels: {error}", present=True
            ) from None
        return cls(module, manifest)

    def entry(self, name: str) -> CompiledEntry:
        exported = self.manifest["entries"].get(name)
        if exported is None:
            raise BuiltKernelsError(f"{name} is missing from the built kernels", present=True)
        variants = [
            (getattr(self.module, variant["symbol"]), variant["arguments"]) for variant in exported
        ]
        return CompiledEntry(name, variants)


def mismatch(manifest: dict[str, Any]) -> str | None:
    """Why the build does not fit this process, or None."""
    if manifest.get("format") != MANIFEST_FORMAT:
        return "have an older manifest format"
    for key, value in versions().items():
        if manifest["versions"].get(key) != value:
            return f"were built for {key} {manifest['versions'].get(key)}, this is {value}"
    missing = sorted(set(manifest["cpu_flags"]) - cpu_flags())
    if missing:
        return f"need CPU features this machine lacks ({', '.join(missing)})"
    try:
        digest = source_digest(manifest["sources"])
    except OSError:
        return "were built from source files that are gone"
    if digest != manifest["digest"]:
        return "were built from other sources (rebuild: python -m estimator.compiled)"
    return None
