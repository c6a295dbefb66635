"""Plumbing shared by the device servers.

- :class:`DeviceLoop`: one asyncio event loop in one thread; every device of a set lives in it, so a set
  costs one thread however many devices it serves.
- :func:`check_loopback`: the simulators listen on loopback only, never on 0.0.0.0.
- :class:`PtyPort`: a pseudo-terminal that clients open by a stable path (a symlink, like
  ``/dev/serial/by-id/...``), which can be "unplugged" and plugged in again behind the same path.
- :class:`LineTime`: the time bytes take on a serial line at a given baud rate (pseudo-terminals ignore
  the baud rate, so the simulators add it themselves).
"""

from __future__ import annotations

import asyncio
import ipaddress
import logging
import os
import termios
import threading
import tty
from collections.abc import Callable, Coroutine
from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

log = logging.getLogger(__name__)

T = TypeVar("T")

#: wall seconds a device call from another thread may take before it is reported as hung
CALL_TIMEOUT_S = 10.0


def check_loopback(host: str) -> str:
    """Return ``host`` if it is a loopback address (``localhost`` becomes ``127.0.0.1``).

    The simulated devices speak real protocols on real sockets; they must never be reachable from
    beyond this machine, so anything else is a programming error.
    """
    if host == "localhost":
        return "127.0.0.1"
    try:
        ip = ipaddress.ip_address(host)
    except ValueError:
        raise ValueError(f"simulated devices listen on a loopback address only. Got {host!r}") from None
    if not ip.is_loopback:
        raise ValueError(f"simulated devices listen on a loopback address only. Got {host!r}")
    return host


class DeviceLoop:
    """An asyncio event loop running in its own thread until :meth:`stop`.

    Devices are created and run inside the loop (pymodbus servers need a running loop); other threads
    reach them through :meth:`run` (wait for a coroutine's result) and :meth:`call` (run a plain
    function in the loop thread and wait for its result).
    """

    def __init__(self, name: str = "cncgw-devices") -> None:
        self.name = name
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop_event: asyncio.Event | None = None
        self._ready = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()

    @property
    def loop(self) -> asyncio.AbstractEventLoop:
        """The running loop (only valid between :meth:`start` and :meth:`stop`)."""
        if self._loop is None:
            raise RuntimeError(f"{self.name}: the device loop is not running")
        return self._loop

    def start(self) -> DeviceLoop:
        """Start the loop thread and wait until the loop runs."""
        with self._lock:
            if self._thread is not None:
                raise RuntimeError(f"{self.name}: already started")
            # daemon: a caller that forgets stop() must not keep the interpreter alive forever
            self._thread = threading.Thread(target=self._run, name=self.name, daemon=True)
            self._thread.start()
        if not self._ready.wait(CALL_TIMEOUT_S):
            raise RuntimeError(f"{self.name}: the device loop did not start")
        return self

    def _run(self) -> None:
        asyncio.run(self._main())

    async def _main(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._stop_event = asyncio.Event()
        self._ready.set()
        await self._stop_event.wait()

    def in_loop_thread(self) -> bool:
        """True when called from the loop's own thread."""
        return self._thread is not None and threading.current_thread() is self._thread

    def run(self, coro: Coroutine[Any, Any, T], timeout_s: float = CALL_TIMEOUT_S) -> T:
        """Run ``coro`` in the loop and return its result (from any thread but the loop's own)."""
        if self.in_loop_thread():
            coro.close()
            raise RuntimeError(f"{self.name}: run() called from the loop thread would deadlock")
        future = asyncio.run_coroutine_threadsafe(coro, self.loop)
        return future.result(timeout_s)

    def call(self, fn: Callable[[], T], timeout_s: float = CALL_TIMEOUT_S) -> T:
        """Run ``fn()`` in the loop thread and return its result (directly when already there)."""
        return call_in_loop(self.loop, fn, timeout_s)

    def stop(self) -> None:
        """Stop the loop and join its thread (idempotent). Stop the devices first."""
        with self._lock:
            thread, self._thread = self._thread, None
        if thread is None:
            return
        if self._loop is not None and self._stop_event is not None and not self._loop.is_closed():
            self._loop.call_soon_threadsafe(self._stop_event.set)
        thread.join(CALL_TIMEOUT_S)
        if thread.is_alive():
            raise RuntimeError(f"{self.name}: the device loop did not stop within {CALL_TIMEOUT_S:g} s")
        self._loop = None


@dataclass(frozen=True, kw_only=True)
class LineTime:
    """Time on a serial line: ``bits_per_char`` bits per byte (10 for 8N1: start, 8 data, stop)."""

    baudrate: int
    bits_per_char: int = 10

    def __post_init__(self) -> None:
        if self.baudrate <= 0:
            raise ValueError(f"baudrate must be > 0. Got {self.baudrate!r}")

    def seconds(self, n_bytes: int) -> float:
        """Wall seconds ``n_bytes`` take on the line."""
        return n_bytes * self.bits_per_char / self.baudrate


class PtyPort:
    """A pseudo-terminal whose slave side clients open through the symlink ``link_path`` (if given).

    We keep our own descriptor of the slave side open, in raw mode: without it the line discipline would
    echo what we write back to us until a client opens the port, and reading the master would fail with
    EIO whenever no client holds the port. :meth:`hang_up` closes the pair (a client's next read or write
    fails, as when a USB adapter is unplugged) and opens a new one behind the same link, so a client that
    reopens the port by its path gets going again.
    """

    def __init__(self, link_path: Path | None = None) -> None:
        self.link_path = Path(link_path) if link_path is not None else None
        self.master_fd = -1
        self._slave_fd = -1
        self.tty_path = ""
        #: counts hang-ups, so a write scheduled for the previous client can be recognised and dropped
        self.generation = 0
        self._loop: asyncio.AbstractEventLoop | None = None
        self._on_data: Callable[[bytes], None] | None = None
        self._open()

    @property
    def path(self) -> str:
        """The path clients open: the stable link if there is one, else the tty itself."""
        return str(self.link_path) if self.link_path is not None else self.tty_path

    def attach(self, loop: asyncio.AbstractEventLoop, on_data: Callable[[bytes], None]) -> None:
        """Call ``on_data(bytes)`` in ``loop`` whenever the client writes (call from the loop thread)."""
        self._loop, self._on_data = loop, on_data
        loop.add_reader(self.master_fd, self._readable)

    def _readable(self) -> None:
        data = self.read()
        if data and self._on_data is not None:
            self._on_data(data)

    def _detach_reader(self) -> None:
        if self._loop is not None and self.master_fd >= 0:
            self._loop.remove_reader(self.master_fd)

    def _open(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)
        os.set_blocking(master, False)
        self.master_fd, self._slave_fd = master, slave
        self.tty_path = os.ttyname(slave)
        if self.link_path is None:
            return
        tmp = self.link_path.with_name(self.link_path.name + ".new")
        if tmp.is_symlink():
            tmp.unlink()
        os.symlink(self.tty_path, tmp)
        os.replace(tmp, self.link_path)  # atomic: a client never sees the link missing

    def _close_fds(self) -> None:
        for fd in (self.master_fd, self._slave_fd):
            if fd >= 0:
                os.close(fd)
        self.master_fd = self._slave_fd = -1

    def hang_up(self) -> None:
        """Close the pseudo-terminal under the clients and open a fresh one behind the same link.

        Call from the loop thread when attached.
        """
        self._detach_reader()
        self._close_fds()
        self.generation += 1
        self._open()
        if self._loop is not None:
            self._loop.add_reader(self.master_fd, self._readable)

    def flush_to_client(self) -> None:
        """Discard bytes written for the client that it has not read yet."""
        if self._slave_fd >= 0:
            termios.tcflush(self._slave_fd, termios.TCIFLUSH)

    def write(self, data: bytes, generation: int | None = None) -> int:
        """Write to the client without blocking; returns the bytes dropped because its buffer is full.

        With ``generation``, the bytes are dropped if the port was hung up since.
        """
        if self.master_fd < 0 or (generation is not None and generation != self.generation):
            return len(data)
        try:
            written = os.write(self.master_fd, data)
        except BlockingIOError:
            return len(data)
        except OSError as exc:
            log.debug("%s: write failed: %s", self.link_path, exc)
            return len(data)
        return len(data) - written

    def read(self) -> bytes:
        """Whatever the client has written (possibly nothing)."""
        try:
            return os.read(self.master_fd, 4096)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError as exc:
            log.debug("%s: read failed: %s", self.link_path, exc)
            return b""

    def close(self) -> None:
        """Close the pseudo-terminal and remove the link (idempotent; from the loop thread when attached)."""
        self._detach_reader()
        self._loop = self._on_data = None
        self._close_fds()
        if self.link_path is not None and self.link_path.is_symlink():
            self.link_path.unlink()


class LineWriter:
    """Delivers bytes to a :class:`PtyPort` the way a serial line would.

    One frame after another, each arriving when its last byte has crossed the line at the baud rate (at
    once without ``line``).

    Lives in the loop thread. Frames scheduled for a client that has been hung up since are dropped.
    """

    def __init__(self, loop: asyncio.AbstractEventLoop, port: PtyPort, line: LineTime | None) -> None:
        self._loop = loop
        self._port = port
        self._line = line
        self._free_at = 0.0  # loop time when the line is free again
        self.dropped_bytes = 0

    def send(self, data: bytes, *, earliest: float | None = None) -> None:
        """Put ``data`` on the line, starting no earlier than loop time ``earliest``."""
        now = self._loop.time()
        start = max(now, self._free_at, earliest if earliest is not None else now)
        done = start + (self._line.seconds(len(data)) if self._line is not None else 0.0)
        self._free_at = done
        if done <= now:
            self._write(data, self._port.generation)
        else:
            self._loop.call_at(done, self._write, data, self._port.generation)

    def _write(self, data: bytes, generation: int) -> None:
        self.dropped_bytes += self._port.write(data, generation)


def call_in_loop(loop: asyncio.AbstractEventLoop, fn: Callable[[], T], timeout_s: float = CALL_TIMEOUT_S) -> T:
    """Run ``fn()`` in ``loop``'s thread and return its result; directly if already there."""
    try:
        running = asyncio.get_running_loop()
    except RuntimeError:
        running = None
    if running is loop:
        return fn()
    future: Future[T] = Future()

    def _do() -> None:
        try:
            future.set_result(fn())
        except BaseException as exc:  # handed to the caller's thread
            future.set_exception(exc)

    loop.call_soon_threadsafe(_do)
    return future.result(timeout_s)
