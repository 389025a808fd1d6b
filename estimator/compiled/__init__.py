"""Compiled kernels: numba's just-in-time compiler, or the same kernels built ahead of time.

A numba kernel costs a process about 130 MB before it does any work: importing numba loads
LLVM (65 MB), and the first call initialises LLVM's code generator (64 MB) even when the
machine code comes from numba's cache. A service worker runs the same few dozen kernels all
its life, so ``python -m estimator.compiled`` compiles them once into an extension module
(numba's ahead-of-time compiler) that a process loads without numba (docs/performance.md,
"Kernels built ahead of time").

``@kernel(...)`` marks a kernel. With argument types (``"float64[:, ::1], int64"``, numba's
notation) it is an entry point, called from Python and built ahead of time for exactly those
types; without, it is a helper that only other kernels call. Which code runs is chosen once
per process by ``SWARMVO_KERNELS``:

- ``auto`` (default): the built module when it was built from the current sources for a CPU
  this one can run, else the just-in-time compiler (with a warning when a build is stale);
- ``jit``: always the just-in-time compiler;
- ``aot``: the built module, or an error naming what is wrong with it.
"""

from __future__ import annotations

import functools
import logging
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any, Literal

__all__ = ["KERNELS", "KernelMode", "KernelSpec", "active_mode", "kernel", "running_ahead_of_time"]

_LOG = logging.getLogger(__name__)
MODE_VARIABLE = "SWARMVO_KERNELS"


class KernelMode(StrEnum):
    AUTO = "auto"
    JIT = "jit"
    AOT = "aot"
    # Set by the build itself: just-in-time dispatchers without numba's disk cache, which the
    # ahead-of-time compiler links into the extension.
    BUILD = "build"


@dataclass(frozen=True)
class KernelSpec:
    """One kernel as declared: the Python function, its entry types and numba's options."""

    function: Callable[..., Any]
    argument_types: tuple[str, ...]
    options: dict[str, Any] = field(default_factory=dict)

    @property
    def name(self) -> str:
        return f"{self.function.__module__}.{self.function.__qualname__}"


# Every kernel declared in this process, in import order (the build reads it).
KERNELS: list[KernelSpec] = []


def kernel(
    *argument_types: str,
    fastmath: bool = False,
    error_model: Literal["python", "numpy"] = "python",
    inline: Literal["never", "always"] = "never",
) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """Declare a kernel: an entry point when ``argument_types`` lists one or more signatures'
    argument types (one string per variant), a helper for other kernels when it is empty."""
    options: dict[str, Any] = {"nogil": True}
    if fastmath:
        options["fastmath"] = True
    if error_model != "python":
        options["error_model"] = error_model
    if inline != "never":
        options["inline"] = inline

    def declare(function: Callable[..., Any]) -> Callable[..., Any]:
        spec = KernelSpec(function, argument_types, options)
        KERNELS.append(spec)
        built = _built_kernels()
        if built is None:
            import numba

            cache = active_mode() is not KernelMode.BUILD
            return numba.njit(cache=cache, **options)(function)
        if argument_types:
            return built.entry(spec.name)
        return _helper_only(spec.name)

    return declare


def active_mode() -> KernelMode:
    """The mode ``SWARMVO_KERNELS`` asks for (``auto`` when unset)."""
    value = os.environ.get(MODE_VARIABLE, KernelMode.AUTO.value)
    try:
        return KernelMode(value)
    except ValueError:
        choices = ", ".join(m.value for m in KernelMode if m is not KernelMode.BUILD)
        raise ValueError(f"{MODE_VARIABLE}={value!r}: expected one of {choices}") from None


def running_ahead_of_time() -> bool:
    """True when this process's kernels come from the built module."""
    return _built_kernels() is not None


@functools.cache
def _built_kernels() -> Any:
    """The built module's entry points, or None for the just-in-time compiler (decided once)."""
    mode = active_mode()
    if mode in (KernelMode.JIT, KernelMode.BUILD):
        return None
    from estimator.compiled.built import BuiltKernels, BuiltKernelsError

    try:
        return BuiltKernels.load()
    except BuiltKernelsError as problem:
        if mode is KernelMode.AOT:
            raise
        if problem.present:
            _LOG.warning("%s; compiling kernels just in time instead", problem)
        return None


def _helper_only(name: str) -> Callable[..., Any]:
    """What a helper is outside the kernels when they were built ahead of time: its code lives
    inside the entry points that call it, and it has no Python-callable copy."""

    def refuse(*_args: object, **_kwargs: object) -> Any:
        raise RuntimeError(
            f"{name} is compiled into other kernels only; call it from a kernel, or set "
            f"{MODE_VARIABLE}=jit"
        )

    refuse.__name__ = name.rsplit(".", 1)[-1]
    refuse.__qualname__ = name
    return refuse
