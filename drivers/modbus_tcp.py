"""Modbus TCP devices (pymodbus sync client): ``driver = "modbus_tcp"``.

Device keys: ``host`` (required), ``port`` (502), ``unit_id`` (1), and the common keys of
:class:`drivers.base.DeviceOptions` (``period_s``, ``timeout_s``, ``retries``, ``backoff_s``,
``backoff_max_s``). Channel keys: see :mod:`drivers.modbus_common`.

Link budget: measured, not computed. A network's round trip (a switch, a Modbus TCP-to-RTU gateway, a
board's own turnaround) is known only by trying it, so at start the gateway times whole scans
(:meth:`drivers.base.Driver.measure_link`: one round trip per planned request) and refuses a period shorter
than the median scan, saying what the link can do (0.25 ms a scan on loopback for nine registers; a board
behind a serial gateway can need 10 ms and more). Reads that still overrun are skipped and counted.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

from pymodbus.client import ModbusTcpClient

from drivers.base import DeviceOptions, parse_common_options
from drivers.modbus_common import ModbusDriver, RegisterAddress, describe_requests, parse_register_address


@dataclass(frozen=True, kw_only=True, slots=True)
class ModbusTcpOptions(DeviceOptions):
    """A Modbus TCP device: where it listens and which unit id it answers."""

    host: str
    port: int = 502
    unit_id: int = 1


class ModbusTcpDriver(ModbusDriver):
    """Reads register channels from a Modbus TCP device; one client, owned by the sampling thread."""

    kind: ClassVar[str] = "Modbus TCP"
    measured_link: ClassVar[bool] = True

    @classmethod
    def parse_device_options(cls, table: Any) -> ModbusTcpOptions | None:
        host = table.str("host", expected="a host name or IP address")
        port = table.int("port", default=502, min=1, max=65535)
        unit_id = table.int("unit_id", default=1, min=0, max=255)
        common = parse_common_options(table)
        if None in (host, port, unit_id):
            return None
        return ModbusTcpOptions(host=host, port=port, unit_id=unit_id, **common)

    @classmethod
    def parse_channel_address(cls, table: Any) -> RegisterAddress | None:
        return parse_register_address(table)

    def _make_client(self) -> ModbusTcpClient:
        o = self.options
        # retries and timeout set explicitly: pymodbus's defaults (3 s x 4) stall a sampler for 12 s
        return ModbusTcpClient(o.host, port=o.port, timeout=o.timeout_s, retries=o.retries)

    def _where(self) -> str:
        return f"{self.options.host}:{self.options.port}"

    def _link_what(self) -> str:
        return f"Modbus TCP to {self._where()}: one scan is {describe_requests(self.requests)}"
