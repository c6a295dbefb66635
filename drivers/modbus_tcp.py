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

from drivers.base import DeviceOptions
from drivers.modbus_common import ModbusDriver, describe_requests


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
    options_type: ClassVar[type] = ModbusTcpOptions
    unit_ids: ClassVar[tuple[int, int]] = (0, 255)  # a TCP device answers any unit id it is set to

    @classmethod
    def _parse_link_options(cls, table: Any) -> dict[str, Any]:
        return {"host": table.str("host", expected="a host name or IP address"),
                "port": table.int("port", default=502, min=1, max=65535)}

    def _make_client(self) -> ModbusTcpClient:
        o = self.options
        # retries and timeout set explicitly: pymodbus's defaults (3 s x 4) stall a sampler for 12 s
        return ModbusTcpClient(o.host, port=o.port, timeout=o.timeout_s, retries=o.retries)

    def _where(self) -> str:
        return f"{self.options.host}:{self.options.port}"

    def _link_what(self) -> str:
        return f"Modbus TCP to {self._where()}: one scan is {describe_requests(self.requests)}"
