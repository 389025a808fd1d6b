"""``python -m service.warmup``: compile the estimator's numba kernels into the JIT cache.

With the kernels built ahead of time (``python -m estimator.compiled``, estimator/compiled)
there is nothing to compile: the run only checks that the workers' first frames work.

A worker process runs a few synthetic frames before it takes sessions (``worker_init``); with an
empty or unreadable cache that run compiles every kernel, which takes minutes on a busy core, and
a replica is not answering while it does. The image build runs this module once, as the user
the service runs as and into the cache folder the service reads (``NUMBA_CACHE_DIR``), so a fresh
replica only loads the compiled code. ``--expect-cached`` fails when a kernel still had to be
compiled: the build checks with it that a new process finds the cache.
"""

from __future__ import annotations

import argparse
import gc
import os
import sys
import time
from dataclasses import dataclass


@dataclass(frozen=True)
class WarmUp:
    seconds: float
    compiled: int  # kernel signatures compiled in this process (cache misses)
    loaded: int  # kernel signatures loaded from the cache
    ahead_of_time: bool = False  # the kernels came from the build: nothing compiled or cached


def cached_kernels() -> dict[str, tuple[int, int]]:
    """Cache misses and hits of each cached numba kernel alive in this process, by name."""
    from numba.core.caching import NullCache
    from numba.core.registry import CPUDispatcher

    counts: dict[str, tuple[int, int]] = {}
    for obj in gc.get_objects():
        if isinstance(obj, CPUDispatcher) and not isinstance(obj._cache, NullCache):
            name = f"{obj.py_func.__module__}.{obj.py_func.__qualname__}"
            misses, hits = counts.get(name, (0, 0))
            counts[name] = (misses + sum(obj.stats.cache_misses.values()),
                            hits + sum(obj.stats.cache_hits.values()))
    return counts


def warm_up() -> WarmUp:
    """The workers' own warm-up run (synthetic frames and the registration kernels they do
    not reach), failing loudly."""
    from estimator.compiled import running_ahead_of_time
    from service.estimator_adapter import (
        EstimatorFactory,
        detector_kernels,
        registration_kernels,
        synthetic_run,
    )
    from service.images import warm_up_decoder

    start = time.perf_counter()
    synthetic_run(EstimatorFactory())
    registration_kernels()
    detector_kernels()
    warm_up_decoder()
    seconds = time.perf_counter() - start
    if running_ahead_of_time():  # numba was never imported: do not load it to count nothing
        return WarmUp(seconds, 0, 0, ahead_of_time=True)
    counts = cached_kernels().values()
    return WarmUp(seconds, sum(m for m, _h in counts), sum(h for _m, h in counts))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m service.warmup", description=__doc__)
    parser.add_argument("--expect-cached", action="store_true",
                        help="exit 1 if any kernel was compiled instead of loaded from the cache")
    args = parser.parse_args(argv)
    result = warm_up()
    if result.ahead_of_time:
        print(f"warm-up: {result.seconds:.1f} s, kernels built ahead of time")
        return 0
    where = os.environ.get("NUMBA_CACHE_DIR") or "beside the installed modules"
    print(f"warm-up: {result.seconds:.1f} s, {result.compiled} kernels compiled, "
          f"{result.loaded} loaded from the cache ({where})")
    if args.expect_cached and (result.compiled or not result.loaded):
        print("error: the JIT cache was not used (is NUMBA_CACHE_DIR writable by this user?)",
              file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
