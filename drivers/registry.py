"""Driver registry: driver name -> ``"module:Class"``, imported lazily.

Built-in drivers are listed in :data:`BUILTIN`; third-party packages add theirs through the
``cncgw.drivers`` entry-point group. A driver is imported only when a profile uses it, so a missing
optional dependency breaks only that driver, with an error naming the driver and the module.

A driver class provides two class methods the profile loader calls while checking a profile:
``parse_device_options(table)`` for the keys of a ``[devices.NAME]`` table (besides ``driver``), and
``parse_channel_address(table)`` for the keys of a ``[channels.NAME]`` table on such a device (besides
``device`` and ``unit``). Both read with the typed getters of :class:`gateway.tomlcheck.Table`, so a bad key
is reported with the others. ``link_budget(options, addresses)`` may say how fast the link can go (see
:class:`drivers.base.Driver`). Built-in drivers: ``modbus_tcp``, ``modbus_rtu``, ``can``, ``dcon``, ``opcua``.
"""

from __future__ import annotations

import importlib
from functools import cache
from importlib.metadata import entry_points
from typing import Any

from gateway.errors import DriverError, did_you_mean

ENTRY_POINT_GROUP = "cncgw.drivers"

#: name -> "module:Class". The registry key equals the module name.
BUILTIN: dict[str, str] = {
    "modbus_tcp": "drivers.modbus_tcp:ModbusTcpDriver",
    "modbus_rtu": "drivers.modbus_rtu:ModbusRtuDriver",
    "can": "drivers.can:CanDriver",
    "dcon": "drivers.dcon:DconDriver",
    "opcua": "drivers.opcua:OpcUaDriver",
}


@cache
def _table() -> dict[str, str]:
    table = dict(BUILTIN)
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        table.setdefault(ep.name, ep.value)
    return table


def names() -> list[str]:
    """Every driver name known: built-in first, then those of installed packages."""
    return list(_table())


def load(name: str) -> Any:
    """Import and return the driver class registered under ``name``."""
    table = _table()
    if name not in table:
        raise DriverError(f'unknown driver "{name}"{did_you_mean(name, table)}; known: {", ".join(table) or "none"}')
    module_name, _, class_name = table[name].partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise DriverError(f'driver "{name}" cannot be loaded: importing {module_name} failed: {exc}') from None
    try:
        return getattr(module, class_name)
    except AttributeError:
        raise DriverError(f'driver "{name}": module {module_name} has no class {class_name}') from None


def parse_device_options(driver: str, table: Any) -> Any:
    """Check a ``[devices.NAME]`` table's driver-specific keys (the driver class decides)."""
    try:
        cls = load(driver)
    except DriverError as exc:
        table.problem("driver", str(exc))
        return None
    return cls.parse_device_options(table)


def link_budget(driver: str, options: Any, addresses: list[Any]) -> Any:
    """What the link of a ``driver`` device can sustain for one scan of ``addresses`` (``None``: no limit)."""
    return load(driver).link_budget(options, addresses)


def parse_channel_address(driver: str, table: Any) -> Any:
    """Check a ``[channels.NAME]`` table's address keys for a channel on a ``driver`` device."""
    try:
        cls = load(driver)
    except DriverError as exc:
        table.problem("device", str(exc))
        return None
    return cls.parse_channel_address(table)
