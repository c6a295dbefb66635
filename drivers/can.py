"""CAN analog-input modules (python-can): ``driver = "can"``.

A CAN module sends its inputs in periodic frames; the driver keeps the latest value of every signal and
a read returns those (sample and hold, as any CAN gateway does). Each read first drains every frame
received since the last one (``recv(timeout=0)``), so no receive thread is needed and python-can's
unbounded receive queue cannot grow.

Device keys: ``interface`` ("socketcan" on a Linux edge PC, "slcan" for a serial-line adapter,
"virtual" for python-can's in-process bus, or any other python-can interface), ``channel`` ("can0",
"/dev/ttyACM0", a virtual channel name), ``bitrate`` (500000; not used by socketcan and virtual),
``open_delay_s`` (slcan: wait after opening the port, 2 s as python-can does for adapters that reset on
open), and the common keys (``timeout_s`` here means: a signal without a fresh frame for that long is
``STALE``, and no frame at all for that long is a device timeout).

Channel keys: ``frame_id``, ``extended_id`` (false), ``start_bit``, ``length_bits``, ``signed`` (false),
``byte_order`` ("little": Intel, bit ``start_bit`` is bit ``start_bit % 8`` of byte ``start_bit // 8``;
"big": Motorola as in a DBC file, ``start_bit`` is the most significant bit), ``scale`` (1),
``offset`` (0): ``value = raw * scale + offset``.

Bad frames: a frame too short for a signal makes that signal ``BAD`` until a good frame arrives; an slcan
line with non-hex data is dropped and counted (python-can raises ``ValueError`` for it). Undecodable bytes
leave python-can's slcan buffer stuck, so that error closes the bus and the runner reopens it.
"""

from __future__ import annotations

import contextlib
import math
import time
from dataclasses import dataclass
from typing import Any, ClassVar

import can

from drivers.base import DeviceOptions, Driver, Quality, parse_common_options, parse_scaling
from gateway.errors import DeviceTimeout, DriverError

INTERFACES = tuple(sorted(can.VALID_INTERFACES))


@dataclass(frozen=True, kw_only=True, slots=True)
class CanOptions(DeviceOptions):
    """A CAN interface and how to open it."""

    interface: str
    channel: str
    bitrate: int = 500000
    open_delay_s: float = 2.0


@dataclass(frozen=True, kw_only=True, slots=True)
class CanSignalAddress:
    """Where a signal sits in a frame and how to scale it."""

    frame_id: int
    extended_id: bool = False
    start_bit: int = 0
    length_bits: int = 16
    signed: bool = False
    byte_order: str = "little"
    scale: float = 1.0
    offset: float = 0.0

    def bytes_needed(self) -> int:
        """The shortest payload that holds the signal."""
        if self.byte_order == "little":
            return (self.start_bit + self.length_bits + 7) // 8
        return (_motorola_position(self.start_bit) + self.length_bits + 7) // 8

    def decode(self, data: bytes | bytearray) -> float:
        """The signal's engineering value (the payload must hold it: see :meth:`bytes_needed`)."""
        n = self.length_bits
        if self.byte_order == "little":
            raw = (int.from_bytes(data, "little") >> self.start_bit) & ((1 << n) - 1)
        else:
            total = 8 * len(data)
            raw = (int.from_bytes(data, "big") >> (total - _motorola_position(self.start_bit) - n)) & ((1 << n) - 1)
        if self.signed and raw >> (n - 1):
            raw -= 1 << n
        return raw * self.scale + self.offset


def _motorola_position(start_bit: int) -> int:
    """A DBC Motorola start bit (the MSB, numbered ``8 * byte + bit``) as a position from the frame's first bit."""
    return 8 * (start_bit // 8) + 7 - start_bit % 8


class CanDriver(Driver):
    """Latest decoded value of every signal, drained from the bus at each read."""

    kind: ClassVar[str] = "CAN"

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self._by_frame: dict[tuple[int, bool], list[int]] = {}
        for i, a in enumerate(self.addresses):
            self._by_frame.setdefault((a.frame_id, a.extended_id), []).append(i)
        n = len(self.addresses)
        self._values = [math.nan] * n
        self._quality = [Quality.STALE] * n
        self._heard = [-math.inf] * n  # monotonic time of each signal's last frame
        self._opened_at = 0.0
        self._last_frame = -math.inf  # monotonic time of the last frame of ours, decodable or not
        self._bus: can.BusABC | None = None
        #: slcan lines dropped for non-hex data, frames too short for a signal
        self.bad_lines = 0
        self.short_frames = 0

    @classmethod
    def parse_device_options(cls, table: Any) -> CanOptions | None:
        interface = table.str("interface", choices=INTERFACES)
        channel = table.str("channel", expected='a channel such as "can0", "/dev/ttyACM0" or a virtual bus name')
        bitrate = table.int("bitrate", default=500000, min=10000, max=8000000)
        open_delay = table.float("open_delay_s", default=2.0, min=0.0, max=10.0)
        common = parse_common_options(table, timeout_s=0.1)
        if None in (interface, channel, bitrate, open_delay):
            return None
        return CanOptions(interface=interface, channel=channel, bitrate=bitrate, open_delay_s=open_delay, **common)

    @classmethod
    def parse_channel_address(cls, table: Any) -> CanSignalAddress | None:
        extended = table.bool("extended_id", default=False)
        top = 0x1FFFFFFF if extended else 0x7FF
        frame_id = table.int("frame_id", min=0, max=top,
                             expected=f"a frame id in 0..{top:#x}" + ("" if extended else " (standard 11-bit id; "
                                                                     "set extended_id = true for 29-bit ids)"))
        start = table.int("start_bit", min=0, max=63)
        length = table.int("length_bits", min=1, max=64)
        signed = table.bool("signed", default=False)
        order = table.str("byte_order", default="little", choices=("little", "big"))
        scale, offset = parse_scaling(table, "count")
        if None in (extended, frame_id, start, length, signed, order, scale, offset):
            return None
        address = CanSignalAddress(frame_id=frame_id, extended_id=extended, start_bit=start, length_bits=length,
                                   signed=signed, byte_order=order, scale=scale, offset=offset)
        if address.bytes_needed() > 8:
            table.problem("length_bits", f"a {length}-bit signal at start bit {start} ({order} byte order) "
                                         "does not fit in 8 data bytes")
            return None
        return address

    # -- transport ----------------------------------------------------------------------------------------
    def _connect(self) -> None:
        o = self.options
        kwargs: dict[str, Any] = {"interface": o.interface, "channel": o.channel}
        if o.interface == "slcan":
            kwargs |= {"bitrate": o.bitrate, "sleep_after_open": o.open_delay_s}
        elif o.interface not in ("virtual", "socketcan"):
            kwargs["bitrate"] = o.bitrate
        self._bus = can.Bus(**kwargs)
        self._opened_at = time.monotonic()
        self._quality = [Quality.STALE] * len(self.addresses)

    def _disconnect(self) -> None:
        bus, self._bus = self._bus, None
        if bus is not None:
            with contextlib.suppress(Exception):  # shutting down after an error must never raise
                bus.shutdown()

    def _read_raw(self) -> tuple[list[float], list[Quality]]:
        bus = self._bus
        assert bus is not None
        now = time.monotonic()
        while True:
            try:
                msg = bus.recv(timeout=0)
            except ValueError:  # slcan: a line with non-hex data; python-can has consumed it
                self.bad_lines += 1
                continue
            except can.CanOperationError as exc:
                raise DriverError(f'device "{self.name}" (CAN {self.options.interface}): {exc}'
                                  + (f" ({exc.__cause__})" if exc.__cause__ else "")) from exc
            if msg is None:
                break
            if msg.is_error_frame or msg.is_remote_frame:
                continue
            members = self._by_frame.get((msg.arbitration_id, msg.is_extended_id))
            if members is None:
                continue
            data = msg.data
            self._last_frame = now
            for i in members:
                a = self.addresses[i]
                if len(data) < a.bytes_needed():
                    self.short_frames += 1
                    self._quality[i] = Quality.BAD
                    continue
                self._values[i] = a.decode(data)
                self._quality[i] = Quality.GOOD
                self._heard[i] = now
        limit = self.options.timeout_s
        if now - max(self._opened_at, self._last_frame) > limit:
            raise DeviceTimeout(f'device "{self.name}" (CAN {self.options.interface} {self.options.channel}): '
                                f"no frame for the device's signals for {limit:g} s (timeout_s)")
        quality = list(self._quality)
        for i, heard in enumerate(self._heard):
            if now - heard > limit and quality[i] is not Quality.BAD:
                quality[i] = Quality.STALE
        values = [v if q <= Quality.SATURATED else math.nan for v, q in zip(self._values, quality, strict=True)]
        return values, quality

