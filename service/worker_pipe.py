"""One worker process and the pipe through which the server's event loop talks to it.

A ``ProcessPoolExecutor`` wakes two threads of the server for every call (its manager thread,
and its call queue's feeder thread that pickles and writes the call), each taking the GIL from
the event loop. Here the event loop writes a call to the worker's pipe itself (non-blocking;
what the pipe does not take at once waits for ``add_writer``) and reads the answers when the
pipe is readable (``add_reader``); the process's sentinel tells it when the worker is gone, and
every call still open then fails with :class:`WorkerDied`. A call costs the server about a
seventh of the pool's CPU (docs/performance.md, "Service: one pipe per worker").

The frames use :mod:`multiprocessing.connection`'s layout (a 4-byte big-endian length, or -1
and an 8-byte one), so that the worker reads and writes with a plain ``Connection``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import signal
import struct
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from multiprocessing.context import BaseContext
from multiprocessing.reduction import ForkingPickler
from typing import Any

from service.worker_process import worker_serve

logger = logging.getLogger("swarmvo.service")

_SHORT = struct.Struct("!i")
_LONG = struct.Struct("!Q")
_READ_SIZE = 1 << 16


class WorkerDied(RuntimeError):
    """The worker process ended before it answered the call."""


@dataclass
class _Call:
    future: asyncio.Future[Any]
    over: list[Callable[[], None]] = field(default_factory=list)  # once the worker is done


def frame_header(size: int) -> bytes:
    """What precedes a message of ``size`` bytes for ``Connection.recv_bytes``: its length."""
    if size > 0x7FFFFFFF:
        return _SHORT.pack(-1) + _LONG.pack(size)
    return _SHORT.pack(size)


def frame_bytes(payload: bytes) -> bytes:
    """A message as ``Connection.recv_bytes`` expects it: its length, then the bytes."""
    return frame_header(len(payload)) + payload


def split_frames(buffer: bytearray) -> list[bytes]:
    """Take every complete message off the front of ``buffer`` (the rest stays in it)."""
    messages = []
    while len(buffer) >= 4:
        (size,) = _SHORT.unpack_from(buffer)
        start = 4
        if size == -1:
            if len(buffer) < 12:
                break
            (size,) = _LONG.unpack_from(buffer, 4)
            start = 12
        if len(buffer) < start + size:
            break
        messages.append(bytes(buffer[start:start + size]))
        del buffer[:start + size]
    return messages


class WorkerPipe:
    """A spawned worker running ``worker_serve``; calls are written and answered on the loop.

    ``on_exit`` runs on the loop once the process is gone and its open calls have failed.
    ``ready`` completes with the worker's pid once it is warmed up, or fails if it died first.
    """

    def __init__(self, context: BaseContext, factory: Any,
                 on_exit: Callable[[WorkerPipe], None]) -> None:
        self.loop = asyncio.get_running_loop()
        self.on_exit = on_exit
        self.ready: asyncio.Future[int] = self.loop.create_future()
        self.ready.add_done_callback(_ignore_outcome)
        self.exited: asyncio.Future[None] = self.loop.create_future()
        self.alive = True
        self._pipe_open = True
        self._calls: dict[int, _Call] = {}
        self._next_id = 0
        self._inbox = bytearray()
        self._drained: asyncio.Future[None] | None = None  # set when the last open call ends
        self._outbox: deque[memoryview] = deque()
        ours, theirs = context.Pipe(duplex=True)
        self.process = context.Process(  # type: ignore[attr-defined]
            target=worker_serve, args=(theirs, factory), name="swarmvo-worker"
        )
        try:
            self.process.start()  # pickles the factory: an unpicklable one fails here
        except BaseException:
            ours.close()
            raise
        finally:
            theirs.close()  # the child has its own copy; ours must go for EOF to be seen
        self._connection = ours
        self._fd = ours.fileno()
        os.set_blocking(self._fd, False)
        self._sentinel = self.process.sentinel
        self.loop.add_reader(self._fd, self._readable)
        self.loop.add_reader(self._sentinel, self._exited)

    @property
    def pid(self) -> int | None:
        return self.process.pid

    @property
    def open_calls(self) -> int:
        return len(self._calls)

    def call(self, function: Callable[..., Any], *args: Any,
             over: Callable[[], None] | None = None) -> asyncio.Future[Any]:
        """Send ``function(*args)`` (module-level function); ``over`` runs once the worker is
        done with it (answered, failed or died), even if the returned future was cancelled."""
        if not (self.alive and self._pipe_open):
            raise WorkerDied("the worker process is gone or stopping")
        payload = ForkingPickler.dumps((self._next_id + 1, function, args))
        self._next_id += 1
        call = _Call(self.loop.create_future())
        if over is not None:
            call.over.append(over)
        self._calls[self._next_id] = call
        if len(payload) < _READ_SIZE:  # one write
            self._write(memoryview(frame_bytes(bytes(payload))))
        else:  # no copy of a large payload (a frame's images when no slot was free)
            self._write(memoryview(frame_header(len(payload))))
            self._write(memoryview(payload))
        return call.future

    def _write(self, view: memoryview) -> None:
        if not self._outbox:
            try:
                view = view[os.write(self._fd, view):]
            except BlockingIOError:
                pass
            except OSError:  # the worker is gone: its sentinel says so next
                return
            if not view:
                return
            self.loop.add_writer(self._fd, self._writable)
        self._outbox.append(view)

    def _writable(self) -> None:
        while self._outbox:
            view = self._outbox[0]
            try:
                written = os.write(self._fd, view)
            except BlockingIOError:
                return
            except OSError:
                self._outbox.clear()
                break
            if written < len(view):
                self._outbox[0] = view[written:]
                return
            self._outbox.popleft()
        self.loop.remove_writer(self._fd)

    def _readable(self) -> None:
        while True:
            try:
                data = os.read(self._fd, _READ_SIZE)
            except BlockingIOError:
                break
            except OSError:
                data = b""
            if not data:  # end of file: the worker is gone, its sentinel says so
                self.loop.remove_reader(self._fd)
                break
            self._inbox += data
            if len(data) < _READ_SIZE:
                break
        for message in split_frames(self._inbox):
            self._answer(ForkingPickler.loads(message))

    def _answer(self, message: tuple[Any, bool, Any]) -> None:
        call_id, ok, value = message
        if call_id == 0:  # the warm-up is over (value: the pid) or failed (value: the error)
            if not self.ready.done():
                if ok:
                    self.ready.set_result(value)
                else:
                    self.ready.set_exception(RuntimeError(value))
            return
        call = self._calls.pop(call_id, None)
        if call is None:
            return
        _close(call)
        if not self._calls and self._drained is not None and not self._drained.done():
            self._drained.set_result(None)
        if call.future.done():  # cancelled by its caller: nobody waits for it
            return
        if ok:
            call.future.set_result(value)
        else:
            call.future.set_exception(value)

    def _exited(self) -> None:
        """The process ended: read what it still answered, fail the rest, tell the owner."""
        self.loop.remove_reader(self._sentinel)
        if self._pipe_open:
            self._readable()
        self.alive = False
        self._close_pipe()
        # Reap it: its sentinel closes as it exits, so this wait is for the last moment of
        # the exit (a timeout of 0 could leave a zombie behind).
        self.process.join(1.0)
        calls, self._calls = self._calls, {}
        died = WorkerDied(f"worker process {self.pid} ended (exit code {self.process.exitcode})")
        for call in calls.values():
            _close(call)
            if not call.future.done():
                call.future.set_exception(died)
        if not self.ready.done():
            self.ready.set_exception(died)
        if self._drained is not None and not self._drained.done():
            self._drained.set_result(None)
        self.exited.set_result(None)
        self.on_exit(self)

    def _close_pipe(self) -> None:
        if not self._pipe_open:
            return
        self._pipe_open = False
        self.loop.remove_reader(self._fd)
        self.loop.remove_writer(self._fd)
        self._outbox.clear()
        self._connection.close()

    def close_pipe_now(self) -> None:
        """Close the server's end without the loop (at interpreter exit): the worker reads its
        end of file and leaves."""
        self._pipe_open = False
        self._connection.close()

    async def stop(self, grace_s: float) -> None:
        """Let the open calls finish, then close the pipe (the worker leaves on its end of
        file). A worker still busy after ``grace_s`` (a stuck call nobody waits for any more),
        or still there ``grace_s`` after its pipe closed, is killed: a stop never hangs."""
        try:
            await asyncio.wait_for(self._drain(), grace_s)
        except TimeoutError:
            logger.error("worker process %s still busy after %g s; killing it", self.pid, grace_s)
            self.kill()
        self._close_pipe()
        if self.alive:
            try:
                await asyncio.wait_for(asyncio.shield(self.exited), grace_s)
            except TimeoutError:
                self.kill()
                await self.exited

    async def _drain(self) -> None:
        """Until the worker has no open call (their futures may be cancelled: the worker is
        what is waited for) or is gone."""
        while self._calls and self.alive:
            self._drained = self.loop.create_future()
            await self._drained

    def kill(self) -> None:
        """SIGKILL the worker (the caller says why); its sentinel then ends it here."""
        if self.alive and self.pid is not None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.pid, signal.SIGKILL)


def _close(call: _Call) -> None:
    for over in call.over:
        try:
            over()
        except Exception:  # a release callback must not stop the others
            logger.exception("a call's clean-up failed")


def _ignore_outcome(future: asyncio.Future[Any]) -> None:
    if not future.cancelled():
        future.exception()
