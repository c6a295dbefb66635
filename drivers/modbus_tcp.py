"""Modbus TCP devices (pymodbus sync client): ``driver = "modbus_tcp"``.

Device keys: ``host`` (required), ``port`` (502), ``unit_id`` (1), and the common keys of
:class:`drivers.base.DeviceOptions` (``period_s``, ``timeout_s``, ``retries``, ``backoff_s``,
``backoff_max_s``). Channel keys: see :mod:`drivers.modbus_common`.

No link budget: on a LAN a read takes a fraction of a millisecond (0.14 ms median on loopback for 8
registers); the runner counts and reports reads that overrun their period.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

from pymodbus.client import ModbusTcpClient

from drivers.base import DeviceOptions, parse_common_options
from drivers.modbus_common import ModbusDriver, RegisterAddress, parse_register_address


@dataclass(frozen=True, kw_only=True, slots=True)
class ModbusTcpOptions(DeviceOptions):
    """A Modbus TCP device: where it listens and which unit id it answers."""

    host: str
    port: int = 502
    unit_id: int = 1


class ModbusTcpDriver(ModbusDriver):
    """Reads register channels from a Modbus TCP device; one client, owned by the sampling thread."""

    kind: ClassVar[str] = "Modbus TCP"

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
