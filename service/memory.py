"""Giving freed heap memory back to the system (glibc), in the server and in its workers.

glibc keeps freed memory in its heaps for reuse: a server that received a few hundred 724 KB
frames, or a worker that dropped a session's pipeline, keeps those pages resident until the
same process allocates again. ``malloc_trim(0)`` returns every free page of every heap (the
pages in the middle of a heap too, by ``madvise``); it costs a few milliseconds when there is
much to give back (0.02 ms when not), so it runs when a session's pipeline is dropped and on a
timer in the server, never per frame. On other C libraries (musl, macOS) it does nothing and
says so. Numbers: docs/performance.md, "Service: memory".
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools


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
    if not hasattr(libc, "malloc_trim"):
        return None
    libc.malloc_trim.argtypes = [ctypes.c_size_t]
    libc.malloc_trim.restype = ctypes.c_int
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
