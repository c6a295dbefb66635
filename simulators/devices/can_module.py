"""A CAN analog-input module: sends the machine's channels as periodic CAN frames.

Every ``period_s`` (wall seconds: a module's cycle time is real time) the module samples the
:class:`~simulators.live.LiveSource` at ``clock.now()`` and sends each frame of its map. Signals are
packed Intel-style (little-endian, as in a DBC ``@1``): bit ``start_bit`` is bit ``start_bit % 8`` of byte
``start_bit // 8``; ``raw = round((value - offset) / scale)``, saturating at the signal's range.

Transports (either or both):

- python-can's ``virtual`` bus (``virtual_channel``): in-process only; what tests and an in-process
  gateway use.
- an slcan adapter on a pseudo-terminal (``slcan_link``): crosses processes. The module behaves like a
  serial-line CAN adapter (LAWICEL protocol: ``O``/``L`` open, ``C`` close, ``Sn`` bitrate, ``V``
  version, ``F`` status); frames flow only while the channel is open. A client uses
  ``can.Bus(interface="slcan", channel=<path>, bitrate=500000, sleep_after_open=0)``.

SocketCAN (vcan) and udp_multicast are not offered: the first does not exist here, the second would
send to the host network.

Faults: ``drop_replies`` (the module falls silent), ``reply_delay_s`` (frames leave late, values from
their scheduled time), ``corrupt_replies`` (slcan: a line with non-hex data; virtual: the frame one byte
short), ``garbage_replies`` (random bytes: slcan on the line, virtual in the payload),
``freeze``/``force``, ``disconnect_clients()`` (slcan: the adapter is unplugged).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from dataclasses import dataclass
from pathlib import Path

import can

from gateway.clock import Clock
from simulators.devices.analog import SIM_VMC_ANALOG
from simulators.devices.faults import Faults
from simulators.devices.runtime import PtyPort, call_in_loop
from simulators.devices.sources import require_channels
from simulators.live import LiveSource

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class CanSignal:
    """One channel in a frame: ``value = raw * scale + offset``, ``raw`` Intel-packed."""

    channel: str
    start_bit: int
    length_bits: int
    signed: bool = True
    scale: float = 1.0  # engineering units per count
    offset: float = 0.0  # engineering value at raw 0

    def __post_init__(self) -> None:
        if not 1 <= self.length_bits <= 64 or self.start_bit < 0:
            raise ValueError(f"signal {self.channel!r}: need start_bit >= 0 and length_bits in 1..64")
        if self.scale == 0:
            raise ValueError(f"signal {self.channel!r}: scale must not be 0")

    @property
    def raw_range(self) -> tuple[int, int]:
        """Smallest and largest raw value."""
        if self.signed:
            return -(1 << (self.length_bits - 1)), (1 << (self.length_bits - 1)) - 1
        return 0, (1 << self.length_bits) - 1

    def raw(self, value: float) -> int:
        """The raw count for an engineering value, saturating at the signal's range (NaN: 0)."""
        lo, hi = self.raw_range
        if value != value:  # NaN
            return 0
        raw = (value - self.offset) / self.scale
        if raw >= hi:
            return hi
        if raw <= lo:
            return lo
        return round(raw)


@dataclass(frozen=True, kw_only=True)
class CanFrame:
    """One periodic frame and its signals."""

    frame_id: int
    signals: tuple[CanSignal, ...]
    dlc: int = 8
    extended_id: bool = False

    def __post_init__(self) -> None:
        top = 0x1FFFFFFF if self.extended_id else 0x7FF
        if not 0 <= self.frame_id <= top:
            raise ValueError(f"frame id {self.frame_id:#x} out of range 0..{top:#x}")
        if not 0 <= self.dlc <= 8:
            raise ValueError(f"frame {self.frame_id:#x}: dlc must be in 0..8. Got {self.dlc}")
        used = 0
        for s in self.signals:
            if s.start_bit + s.length_bits > 8 * self.dlc:
                raise ValueError(f"frame {self.frame_id:#x}: signal {s.channel!r} ends beyond byte {self.dlc}")
            bits = ((1 << s.length_bits) - 1) << s.start_bit
            if used & bits:
                raise ValueError(f"frame {self.frame_id:#x}: signal {s.channel!r} overlaps another signal")
            used |= bits

    def encode(self, values: dict[str, float]) -> bytes:
        """The frame's payload for the given channel values."""
        acc = 0
        for s in self.signals:
            acc |= (s.raw(values[s.channel]) & ((1 << s.length_bits) - 1)) << s.start_bit
        return acc.to_bytes(self.dlc, "little")


@dataclass(frozen=True, kw_only=True)
class CanModuleConfig:
    """The module's frames and cycle time."""

    frames: tuple[CanFrame, ...]
    period_s: float = 0.01  # wall seconds between two transmissions of every frame

    def __post_init__(self) -> None:
        if not self.frames:
            raise ValueError("a CAN module needs at least one frame")
        if not self.period_s > 0:
            raise ValueError(f"period_s must be > 0. Got {self.period_s!r}")
        ids = [(f.frame_id, f.extended_id) for f in self.frames]
        if len(set(ids)) != len(ids):
            raise ValueError("frame ids must be unique")

    def channel_names(self) -> tuple[str, ...]:
        """The machine channels this module sends, without repeats."""
        return tuple(dict.fromkeys(s.channel for f in self.frames for s in f.signals))


#: The default module for the bundled machine (standard ids, 8 bytes, every 10 ms):
#: 0x181 spindle: speed u16 @0 x0.25 rpm, i1 s16 @16 x0.01 A, i2 s16 @32 x0.01 A;
#: 0x281 feeds: x/y/z velocity s20 @0/@20/@40 x0.1 mm/min (20-bit signals cross byte boundaries);
#: 0x381 axis currents: x/y/z s16 @0/@16/@32 x0.01 A.
DEFAULT_CAN_CONFIG = CanModuleConfig(frames=(
    CanFrame(frame_id=0x181, signals=(
        CanSignal(channel="spindle_speed", start_bit=0, length_bits=16, signed=False, scale=0.25),
        CanSignal(channel="spindle_i1", start_bit=16, length_bits=16, scale=0.01),
        CanSignal(channel="spindle_i2", start_bit=32, length_bits=16, scale=0.01),
    )),
    CanFrame(frame_id=0x281, signals=tuple(
        CanSignal(channel=f"{axis}_velocity", start_bit=20 * i, length_bits=20, scale=0.1)
        for i, axis in enumerate("xyz")
    )),
    CanFrame(frame_id=0x381, signals=tuple(
        CanSignal(channel=f"{axis}_current", start_bit=16 * i, length_bits=16, scale=0.01)
        for i, axis in enumerate("xyz")
    )),
))
assert set(DEFAULT_CAN_CONFIG.channel_names()) == set(SIM_VMC_ANALOG)


def slcan_line(frame_id: int, data: bytes, *, extended: bool) -> bytes:
    """A frame as an slcan adapter reports it.

    ``t`` and 3 hex id digits (``T`` and 8 if extended), the dlc, the data in hex, a carriage return.
    """
    head = f"T{frame_id:08X}" if extended else f"t{frame_id:03X}"
    return f"{head}{len(data)}{data.hex().upper()}\r".encode("ascii")


class CanModule:
    """A CAN analog-input module fed by ``source``; see the module docstring.

    Args:
        source: the machine.
        clock: the shared clock (values at ``clock.now()``; the cycle runs in wall time).
        config: frames and cycle (default :data:`DEFAULT_CAN_CONFIG`).
        virtual_channel: python-can virtual channel to send on (``None``: none).
        slcan_link: path (a symlink) of the slcan adapter's pseudo-terminal (``None``: none).
        faults: the fault switches.
        name: for messages and logs.

    """

    kind = "CAN analog-input module"

    def __init__(self, *, source: LiveSource, clock: Clock, config: CanModuleConfig = DEFAULT_CAN_CONFIG,
                 virtual_channel: str | None = "cncgw-sim", slcan_link: Path | None = None,
                 faults: Faults | None = None, name: str = "can") -> None:
        if virtual_channel is None and slcan_link is None:
            raise ValueError(f"{name}: give virtual_channel, slcan_link or both")
        require_channels(source, config.channel_names(), device=name)
        self.name = name
        self.config = config
        self.faults = faults if faults is not None else Faults()
        self.virtual_channel = virtual_channel
        self._slcan_link = slcan_link
        self._source = source
        self._clock = clock
        self._bus: can.BusABC | None = None
        self._pty: PtyPort | None = None
        self._slcan_open = False
        self._commands = bytearray()
        self._task: asyncio.Task[None] | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        #: frames built and handed to the transports, periods skipped because the loop was late, frames a
        #: full receiver (virtual queue or pseudo-terminal buffer) could not take
        self.frames_sent = 0
        self.missed_periods = 0
        self.overflows = 0

    @property
    def slcan_port(self) -> str:
        """The path an slcan client opens."""
        if self._pty is None:
            raise RuntimeError(f"{self.name}: no slcan port running")
        return self._pty.path

    @property
    def endpoint(self) -> str:
        """Where clients find the module, for people."""
        parts = []
        if self.virtual_channel is not None:
            parts.append(f"can-virtual:{self.virtual_channel} (in-process)")
        if self._pty is not None:
            parts.append(f"slcan:{self._pty.path}")
        return ", ".join(parts) + f" every {self.config.period_s * 1000:g} ms"

    # -- lifecycle --------------------------------------------------------------------------------------
    async def start(self) -> None:
        """Start sending (in the device loop)."""
        self._loop = asyncio.get_running_loop()
        if self.virtual_channel is not None:
            self._bus = can.Bus(interface="virtual", channel=self.virtual_channel)
        if self._slcan_link is not None:
            self._pty = PtyPort(self._slcan_link)
            self._pty.attach(self._loop, self._on_slcan_bytes)
        self._task = asyncio.create_task(self._cycle(), name=f"{self.name} cycle")
        log.info("%s: sending on %s", self.name, self.endpoint)

    async def stop(self) -> None:
        """Stop sending and close the transports (idempotent)."""
        task, self._task = self._task, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        if self._bus is not None:
            self._bus.shutdown()
            self._bus = None
        if self._pty is not None:
            self._pty.close()
            self._pty = None

    def disconnect_clients(self) -> None:
        """Unplug the slcan adapter (the client's next read fails; reopening the path works)."""
        loop = self._loop
        if loop is None or self._task is None:
            raise RuntimeError(f"{self.name}: not running")

        def _hang_up() -> None:
            self.faults.note("disconnected")
            self._slcan_open = False
            if self._pty is not None:
                self._pty.hang_up()

        call_in_loop(loop, _hang_up)

    # -- sending ----------------------------------------------------------------------------------------
    async def _cycle(self) -> None:
        loop = asyncio.get_running_loop()
        period = self.config.period_s
        deadline = loop.time()
        while True:
            deadline += period
            late = loop.time() - deadline
            if late > period:  # skip the periods we slept through instead of sending a burst
                skipped = int(late // period)
                self.missed_periods += skipped
                deadline += skipped * period
            await asyncio.sleep(max(0.0, deadline - loop.time()))
            try:
                self._send_all()
            except Exception:  # a broken source must not stop the module for good
                log.exception("%s: cannot send", self.name)

    def _send_all(self) -> None:
        if self._bus is not None:
            while self._bus.recv(timeout=0) is not None:
                pass  # nobody reads the module's own receive queue: keep it empty
        if self.faults.drop_replies:
            self.faults.note("dropped")
            return
        values = self.faults.apply(self._source.values(self._clock.now()))
        payloads = [(frame, frame.encode(values)) for frame in self.config.frames]
        delay = self.faults.reply_delay_s
        if delay > 0:
            self.faults.note("delayed")
            assert self._loop is not None
            self._loop.call_later(delay, self._transmit, payloads)
        else:
            self._transmit(payloads)

    def _transmit(self, payloads: list[tuple[CanFrame, bytes]]) -> None:
        faults = self.faults
        for frame, data in payloads:
            corrupt, garbage = faults.corrupt_replies, faults.garbage_replies
            if corrupt or garbage:
                faults.note("corrupted" if corrupt else "garbage")
            if self._bus is not None:
                if garbage:
                    data = faults.garbage(len(data))
                elif corrupt:
                    data = data[:-1]
                msg = can.Message(arbitration_id=frame.frame_id, is_extended_id=frame.extended_id, data=data)
                try:
                    self._bus.send(msg, timeout=0)  # never block the loop on a full receiver
                except can.CanOperationError:
                    self.overflows += 1
            if self._pty is not None and self._slcan_open:
                line = slcan_line(frame.frame_id, data, extended=frame.extended_id)
                if garbage:
                    line = faults.garbage(len(line) - 1) + b"\r"
                elif corrupt:
                    line = line[:5] + b"G" * (len(line) - 6) + b"\r"  # not hex
                if self._pty.write(line):
                    self.overflows += 1
            self.frames_sent += 1

    # -- the slcan adapter's command side -----------------------------------------------------------------
    def _on_slcan_bytes(self, data: bytes) -> None:
        self._commands.extend(data)
        while b"\r" in self._commands:
            cut = self._commands.index(b"\r")
            command = bytes(self._commands[:cut]).decode("ascii", "replace")
            del self._commands[: cut + 1]
            reply = self._slcan_command(command)
            if self._pty is not None:
                self._pty.write(reply)

    def _slcan_command(self, command: str) -> bytes:
        ok, error = b"\r", b"\a"
        head = command[:1]
        if command == "":
            return ok
        if head in ("O", "L"):
            self._slcan_open = True
            return ok
        if head == "C":
            self._slcan_open = False
            if self._pty is not None:
                self._pty.flush_to_client()  # the next session must not start with this one's frames
            return ok
        if head == "S" and command[1:] in [str(i) for i in range(10)]:
            return error if self._slcan_open else ok
        if head == "s" and len(command) == 5:
            return error if self._slcan_open else ok
        if head == "V":
            return b"V1013\r"
        if head == "v":
            return b"vCNCGW\r"
        if head == "N":
            return b"NSIM1\r"
        if head == "F":
            return b"F00\r"
        if head in ("Z", "M", "m", "X"):
            return ok
        if head in ("t", "r"):
            return b"z\r" if self._slcan_open else error  # accepted and ignored: the module only sends
        if head in ("T", "R"):
            return b"Z\r" if self._slcan_open else error
        return error
