"""Modbus RTU devices on a serial line (pymodbus sync serial client): ``driver = "modbus_rtu"``.

Device keys: ``port`` (the serial device, required), ``baudrate`` (19200), ``parity`` ("N", "E", "O"),
``stopbits`` (1 or 2), ``unit_id`` (1), and the common keys of :class:`drivers.base.DeviceOptions`.
Channel keys: see :mod:`drivers.modbus_common`. One ``[devices.NAME]`` per serial line: several boards on
one RS-485 line are one device whose channels name their ``unit_id``; two devices cannot open the same port.

Link budget: one scan costs, per request, an 8-byte request and a ``5 + 2 * count`` byte answer, each
followed by the 3.5-character silence that ends an RTU frame. At 115200 baud 8N1 nine int16 registers
take 3.3 ms, so a 2 ms period is refused at profile load with what the line can do instead. The budget
is the wire alone: a device's own turnaround and the client's software time come on top (pymodbus's
sync serial client needs ~2.2 ms a transaction); reads that still overrun are skipped and counted.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

from pymodbus import FramerType
from pymodbus.client import ModbusSerialClient

from drivers.base import DeviceOptions, LinkBudget, serial_char_s
from drivers.modbus_common import ModbusDriver, RegisterAddress, describe_requests, plan_requests

BAUDRATES = (1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200, 230400, 460800, 921600)


@dataclass(frozen=True, kw_only=True, slots=True)
class ModbusRtuOptions(DeviceOptions):
    """A Modbus RTU device: its serial line and its device address."""

    port: str
    baudrate: int = 19200
    parity: str = "N"
    stopbits: int = 1
    unit_id: int = 1


class ModbusRtuDriver(ModbusDriver):
    """Reads register channels from a Modbus RTU device; one client, owned by the sampling thread."""

    kind: ClassVar[str] = "Modbus RTU"
    options_type: ClassVar[type] = ModbusRtuOptions

    @classmethod
    def _parse_link_options(cls, table: Any) -> dict[str, Any]:
        port = table.str("port", expected="a serial device path such as \"/dev/ttyUSB0\"")
        rates = ", ".join(str(b) for b in BAUDRATES)
        baudrate = table.int("baudrate", default=19200, expected=f"one of {rates}")
        if baudrate is not None and baudrate not in BAUDRATES:
            table.problem("baudrate", f"expected one of {rates}, got {baudrate} (an integer)")
            baudrate = None
        return {"port": port, "baudrate": baudrate, "parity": table.str("parity", default="N", choices=("N", "E", "O")),
                "stopbits": table.int("stopbits", default=1, min=1, max=2)}

    @classmethod
    def link_budget(cls, options: ModbusRtuOptions, addresses: Sequence[RegisterAddress]) -> LinkBudget:
        requests = plan_requests(addresses, options.unit_id)
        char_s = serial_char_s(options.baudrate, parity=options.parity, stopbits=options.stopbits)
        chars = sum(8 + 3.5 + 5 + 2 * r.count + 3.5 for r in requests)
        seconds = chars * char_s
        bits = round(char_s * options.baudrate)
        return LinkBudget(
            min_period_s=seconds,
            detail=f"Modbus RTU at {options.baudrate} baud ({bits} bits a character): one scan is "
                   f"{describe_requests(requests)}, {chars:g} characters on the line with the 3.5-character "
                   f"frame gaps = {seconds * 1000:.2f} ms")

    def _make_client(self) -> ModbusSerialClient:
        o = self.options
        return ModbusSerialClient(o.port, framer=FramerType.RTU, baudrate=o.baudrate, bytesize=8,
                                  parity=o.parity, stopbits=o.stopbits, timeout=o.timeout_s, retries=o.retries)

    def _where(self) -> str:
        return f"{self.options.port} ({self.options.baudrate} baud)"
