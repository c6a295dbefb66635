"""Simulated devices: real protocols on loopback, fed by the simulated machine.

See simulators/live.py for the contract between machine and devices. The integrator's entry point is
:func:`serve` (or :class:`DeviceSet`); each device can also be run on its own in a :class:`DeviceLoop`.

Names are imported on first use, so ``cncgw --help`` does not pay for pymodbus and python-can.
"""

from __future__ import annotations

import importlib
from typing import Any

_WHERE = {
    "DEFAULT_ADC_CONFIG": "analog", "SIM_VMC_ANALOG": "analog", "AdcBoardConfig": "analog",
    "AnalogScale": "analog", "RegisterChannel": "analog",
    "DEFAULT_CAN_CONFIG": "can_module", "CanFrame": "can_module", "CanModule": "can_module",
    "CanModuleConfig": "can_module", "CanSignal": "can_module",
    "STATUS_BITS": "cnc", "CompensationConfig": "cnc", "CompensationServer": "cnc", "CompensationStatus": "cnc",
    "DEFAULT_DCON_CONFIG": "dcon", "DconChannel": "dcon", "DconLine": "dcon", "DconLineConfig": "dcon",
    "DconModuleConfig": "dcon",
    "DeviceSet": "deviceset", "DeviceSetConfig": "deviceset", "serve": "deviceset",
    "Faults": "faults",
    "ModbusAdc": "modbus_adc",
    "RtuBus": "modbus_base", "RtuTransport": "modbus_base", "TcpTransport": "modbus_base",
    "DeviceLoop": "runtime",
}

__all__ = sorted(_WHERE)


def __getattr__(name: str) -> Any:
    module = _WHERE.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{module}"), name)
