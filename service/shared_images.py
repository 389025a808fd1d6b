"""A frame's encoded images handed to a worker process through shared memory.

Pickling a request through the worker's pipe copies the two images (about 0.7 MB for a
752x480 PNG pair) on both sides and takes several writes and reads of the pipe
(docs/performance.md, "Service: where a frame's CPU goes"). Here the server copies
them once into a slot of one shared segment and sends only the slot's place; the worker reads
them where they are. A slot is given back once the worker's call is over (answered, failed,
cancelled or the worker died), never earlier, so a worker never reads a slot being refilled.
No free slot, or images larger than a slot: the request goes through the pipe as before.

The server creates and unlinks the segment (its resource tracker unlinks it if the server is
killed); workers only attach, by name.
"""

from __future__ import annotations

import secrets
import threading
from dataclasses import dataclass
from multiprocessing import shared_memory

__all__ = ["ImageSlots", "SharedPair", "read_pair"]


@dataclass(frozen=True)
class SharedPair:
    """Where a stereo pair lies in shared memory: segment, slot, and the two lengths."""

    segment: str
    slot: int
    offset: int
    left_len: int
    right_len: int


class ImageSlots:
    """``count`` slots of ``slot_bytes`` in one shared segment, owned by the server process.

    Thread-safe (slots are taken and given back on the event loop; a lock costs little).
    The most recently freed slot is taken first, so that only as many slots as are in use at
    once are ever touched (pages of unused slots are never mapped in).
    """

    def __init__(self, count: int, slot_bytes: int) -> None:
        if count < 1 or slot_bytes < 1:
            raise ValueError("image slots need a count and a size of at least 1")
        self.count = count
        self.slot_bytes = slot_bytes
        self._memory: shared_memory.SharedMemory | None = shared_memory.SharedMemory(
            name=f"swarmvo-{secrets.token_hex(6)}", create=True, size=count * slot_bytes
        )
        self.name = self._memory.name
        self._free = list(range(count - 1, -1, -1))  # a stack: slot 0 on top
        self._lock = threading.Lock()
        self.handed = 0  # pairs that went through a slot (the rest went through the pipe)

    @property
    def free(self) -> int:
        with self._lock:
            return len(self._free)

    def put(self, left: bytes | memoryview, right: bytes | memoryview) -> SharedPair | None:
        """Copy a pair into a free slot; None when none is free or the pair does not fit."""
        size = len(left) + len(right)
        if size > self.slot_bytes or self._memory is None:
            return None
        with self._lock:
            if not self._free:
                return None
            slot = self._free.pop()
            self.handed += 1
        offset = slot * self.slot_bytes
        buffer = self._memory.buf
        buffer[offset:offset + len(left)] = left
        buffer[offset + len(left):offset + size] = right
        return SharedPair(self.name, slot, offset, len(left), len(right))

    def release(self, pair: SharedPair) -> None:
        """Give a slot back (once the worker is done with it); a second release is ignored."""
        with self._lock:
            if pair.segment == self.name and pair.slot not in self._free:
                self._free.append(pair.slot)

    def close(self) -> None:
        """Unlink the segment; call once no worker reads it any more (workers stopped)."""
        memory, self._memory = self._memory, None
        if memory is None:
            return
        memory.close()
        memory.unlink()


# Worker side: the segments this process has attached, by name (one per server in practice).
_attached: dict[str, shared_memory.SharedMemory] = {}


def read_pair(pair: SharedPair) -> tuple[memoryview, memoryview]:
    """The pair's two encoded images as views into the segment (valid until the call ends)."""
    memory = _attached.get(pair.segment)
    if memory is None:
        memory = _attached[pair.segment] = shared_memory.SharedMemory(name=pair.segment)
    start = pair.offset
    middle = start + pair.left_len
    return memory.buf[start:middle], memory.buf[middle:middle + pair.right_len]
