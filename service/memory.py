"""Giving freed heap memory back to the system (glibc), in the server and in its workers.

glibc keeps freed memory in its heaps for reuse: a server that received a few hundred 724 KB
frames, or a worker that dropped a session's pipeline, keeps those pages resident until the
same process allocates again. ``malloc_trim(0)`` returns every free page of every heap (the
pages in the middle of a heap too, by ``madvise``); it costs about a millisecond, so it runs
when a session's pipeline is dropped and on a timer in the server, never per frame.

The server runs about ten threads (event loop, I/O pool, the process pools' feeder threads),
and glibc gives each thread that allocates its own heap ("arena"): the feeder threads pickle
the frames, so each of them holds megabytes of freed buffers. ``cap_malloc_arenas`` lets them
share two. On other C libraries (musl, macOS) both functions do nothing and say so.
Numbers: docs/performance.md, "Service: memory".
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import logging

logger = logging.getLogger("swarmvo.service")

# mallopt's parameter number for the arena limit (glibc malloc.h: M_ARENA_MAX).
_M_ARENA_MAX = -8


@functools.cache
def _glibc() -> ctypes.CDLL | None:
    """The process's C library when it is glibc (it has ``malloc_trim``), else None."""
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    try:
        libc = ctypes.CDLL(name)
    except OSError:
        return None
    if not hasattr(libc, "malloc_trim") or not hasattr(libc, "mallopt"):
        return None
    libc.malloc_trim.argtypes = [ctypes.c_size_t]
    libc.malloc_trim.restype = ctypes.c_int
    libc.mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    libc.mallopt.restype = ctypes.c_int
    return libc


def trim_free_memory() -> bool:
    """Return the free pages of every heap to the system; False where that is not possible.

    (glibc's own return value only says whether the top of a heap shrank, not whether pages
    in the middle were given back, so it is not passed on.)"""
    libc = _glibc()
    if libc is None:
        return False
    libc.malloc_trim(0)
    return True


def cap_malloc_arenas(count: int) -> bool:
    """Let the threads of this process share at most ``count`` heaps (call it early: heaps
    that exist already stay). False where that is not possible."""
    if count < 1:
        raise ValueError(f"at least one arena is needed, got {count}")
    libc = _glibc()
    if libc is None:
        return False
    return bool(libc.mallopt(_M_ARENA_MAX, count))
