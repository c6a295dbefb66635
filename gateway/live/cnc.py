"""The CNC's compensation registers over Modbus TCP: a Modbus TCP driver that writes.

:class:`CncLink` is a :class:`drivers.modbus_tcp.ModbusTcpDriver` whose channels are the CNC's read-back
registers (the applied offset of each axis, the status word), so reading, decoding, connecting and
closing on any error (pymodbus keeps a dead socket until ``close()``) are the driver's. Its three writes go
through the driver's public write hook (:meth:`drivers.base.Driver.write`, which owns error wrapping and
reconnecting as ``read()`` does): the offset commands (one request per block of contiguous registers, so a
CNC that refuses one value refuses the whole block), the heartbeat, the enable coil. A refusal
(:class:`~gateway.errors.DeviceRefused`) becomes a :class:`CncRejected`, a compensation error.

Status word (input register ``status_register``), as the bundled simulated CNC lays it out: bit 0 ACTIVE,
1 WATCHDOG_TRIPPED, 2 RAMPING, 3 LAST_WRITE_REJECTED, 4 HEARTBEAT_OK.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

from drivers.modbus_common import RegisterAddress, RegisterWrite
from drivers.modbus_tcp import ModbusTcpDriver, ModbusTcpOptions
from gateway.clock import Clock
from gateway.errors import CompensationError, DeviceRefused
from gateway.profile.live import Compensation

ACTIVE, WATCHDOG_TRIPPED, RAMPING, LAST_WRITE_REJECTED, HEARTBEAT_OK = (1 << i for i in range(5))
#: registers one fc16 request may write (Modbus application protocol, 6.12)
MAX_WRITE_REGISTERS = 123


class CncRejected(CompensationError):
    """The CNC answered a write with a Modbus exception: nothing of that request was applied."""


@dataclass(frozen=True, kw_only=True, slots=True)
class CncState:
    """What the CNC reports: applied offsets (counts and um per axis) and its status word (``None``: not mapped)."""

    applied_counts: Mapping[str, int]
    applied_um: Mapping[str, float]
    status: int | None

    @property
    def active(self) -> bool | None:
        return None if self.status is None else bool(self.status & ACTIVE)

    @property
    def tripped(self) -> bool | None:
        return None if self.status is None else bool(self.status & WATCHDOG_TRIPPED)


class CncLink(ModbusTcpDriver):
    """The CNC's compensation registers (see the module docstring); one client, used by one thread."""

    kind: ClassVar[str] = "CNC compensation, Modbus TCP"

    def __init__(self, settings: Compensation, *, clock: Clock | None = None, name: str = "cnc") -> None:
        if settings.host is None:
            raise ValueError("the CNC link needs compensation.host")
        options = ModbusTcpOptions(host=settings.host, port=settings.port, unit_id=settings.unit_id,
                                   timeout_s=settings.timeout_s, retries=settings.retries)
        channels: list[tuple[str, Any]] = [
            (f"{a.axis}_applied", RegisterAddress(address=a.readback, function=4, data_type=a.data_type,
                                                  word_order=a.word_order)) for a in settings.axes]
        if settings.status_register is not None:
            channels.append(("status", RegisterAddress(address=settings.status_register, function=4,
                                                       data_type="uint16")))
        super().__init__(name=name, options=options, channels=channels, clock=clock)
        self.settings = settings

    # -- reading ------------------------------------------------------------------------------------------
    def state(self) -> CncState:
        """Read the applied offsets and the status word (raises :class:`DriverError` on failure)."""
        reading = self.read()
        s = self.settings
        counts = {a.axis: int(v) for a, v in zip(s.axes, reading.values, strict=False)}
        status = int(reading.values[-1]) if s.status_register is not None else None
        return CncState(applied_counts=counts, applied_um={a.axis: counts[a.axis] * a.unit_um for a in s.axes},
                        status=status)

    def read_words(self, address: int, count: int, *, function: int = 4) -> list[int]:
        """``count`` raw registers from ``address`` in one request (the probe block a CNC macro writes)."""
        return self.read_registers(address, count, function=function)

    # -- writing ------------------------------------------------------------------------------------------
    def write_offsets(self, counts: Mapping[str, int]) -> None:
        """Write the offset commands of the axes in ``counts``; contiguous registers go in one request."""
        words: dict[int, int] = {}
        for a in self.settings.axes:
            if a.axis in counts:
                for k, w in enumerate(a.encode(counts[a.axis])):
                    words[a.register + k] = w
        for start, block in _blocks(words):
            self._write(RegisterWrite(function=16, address=start, label="offsets"), block)

    def beat(self, value: int) -> None:
        """Write the heartbeat register (any change of value is a beat)."""
        reg = self.settings.heartbeat_register
        if reg is not None:
            self._write(RegisterWrite(function=6, address=reg, label="heartbeat"), value & 0xFFFF)

    def set_enabled(self, on: bool) -> None:
        """Write the enable coil (1 also clears a watchdog trip on the bundled CNC)."""
        coil = self.settings.enable_coil
        if coil is not None:
            self._write(RegisterWrite(function=5, address=coil, label="enable"), on)

    def _write(self, target: RegisterWrite, value: int | bool | Sequence[int]) -> None:
        try:
            self.write(target, value)
        except DeviceRefused as exc:  # the CNC said no: a compensation error, the link stays open
            raise CncRejected(str(exc)) from exc


def _blocks(words: Mapping[int, int]) -> list[tuple[int, list[int]]]:
    out: list[tuple[int, list[int]]] = []
    for addr in sorted(words):
        if out and out[-1][0] + len(out[-1][1]) == addr and len(out[-1][1]) < MAX_WRITE_REGISTERS:
            out[-1][1].append(words[addr])
        else:
            out.append((addr, [words[addr]]))
    return out
