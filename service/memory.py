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


# mallopt parameters (glibc's malloc.h).
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
# Frame-sized buffers (a 724 KB PNG pair and its copies in the server; image-sized arrays in a
# worker) stay below this, so they come from the heap and are reused frame after frame.
FRAME_BUFFER_BYTES = 4 << 20
# Free memory at the top of a heap that is left there (reused by the next frames) rather than
# given back after every free.
HEAP_SLACK_BYTES = 16 << 20


def reuse_frame_buffers(mmap_threshold: int = FRAME_BUFFER_BYTES,
                        trim_threshold: int = HEAP_SLACK_BYTES) -> bool:
    """Serve frame-sized allocations from the heap and keep freed ones for reuse.

    By default glibc maps every allocation above a threshold that it moves between 128 KB
    and the largest block freed so far, and gives the top of the heap back as soon as twice
    that is free: here nearly every frame-sized buffer came as fresh pages, each one a page
    fault on first touch (145 faults and 0.39 ms of CPU for a 724 KB pair split in two,
    against 0.02 ms reused; docs/performance.md). Fixed thresholds keep those buffers in the
    heap; what the process no longer uses is still given back by :func:`trim_free_memory`.
    False where the C library is not glibc.
    """
    libc = _glibc()
    if libc is None:
        return False
    libc.mallopt(_M_MMAP_THRESHOLD, mmap_threshold)
    libc.mallopt(_M_TRIM_THRESHOLD, trim_threshold)
    return True
