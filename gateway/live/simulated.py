"""The live gateway against the bundled simulated machine: its profile with live addresses, its CNC settings.

Used by ``cncgw demo``, the tests and ``bench/runtime.py``: :func:`live_profile` writes the bundled profile
with the running simulated devices' addresses (:func:`simulators.devices.profile_out.profile_for`) plus a
``[compensation]`` section for the simulated CNC (int32 offsets in 0.1 um at holding 0-5, heartbeat at
holding 6, read-back at input 0-5, status at input 6; the CNC adds the offset: ``sign = -1``).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any


def compensation_toml(host: str, port: int, *, enabled: bool = True, limit_um: float = 200.0,
                      max_step_um: float = 2.0, deadband_um: float = 0.1, heartbeat_period_s: float = 1.0,
                      watchdog_s: float = 5.0, on_fault: str = "hold", fault_hold_s: float = 600.0,
                      extra: str = "") -> str:
    """A ``[compensation]`` section for the bundled simulated CNC at ``host:port``."""
    axes = "\n".join(f"[compensation.axes.{a}]\nregister = {2 * i}\nreadback = {2 * i}\nsign = -1\nunit_um = 0.1\n"
                     f'data_type = "int32"\nword_order = "big"\n' for i, a in enumerate("xyz"))
    return (f"[compensation]\nenabled = {str(enabled).lower()}\nhost = \"{host}\"\nport = {port}\ntimeout_s = 0.5\n"
            f"reconnect_s = 0.5\nenable_coil = 0\nheartbeat_register = 6\nstatus_register = 6\n"
            f"heartbeat_period_s = {heartbeat_period_s!r}\nwatchdog_s = {watchdog_s!r}\nlimit_um = {limit_um!r}\n"
            f"max_step_um = {max_step_um!r}\ndeadband_um = {deadband_um!r}\non_fault = \"{on_fault}\"\n"
            f"fault_hold_s = {fault_hold_s!r}\n{extra}\n{axes}")


def live_profile(devices: Any, out: str | Path, *, enabled: bool = True, period_s: float | None = None,
                 opcua_port: int | None = 0, live: str = "", **compensation: Any) -> Path:
    """Write the bundled profile reading ``devices``' ADC board over Modbus TCP and compensating on its CNC.

    ``period_s`` overrides the ADC's fast period; ``opcua_port`` adds an ``[opcua]`` section on 127.0.0.1
    (``None``: none, OPC UA off); ``live`` is extra ``[live]`` keys; the rest goes to :func:`compensation_toml`.
    """
    from simulators.devices.profile_out import profile_for

    text = profile_for(devices, "adc-tcp")
    if period_s is not None:
        text = re.sub(r"(\[devices\.adc\]\n)", rf"\g<1>period_s = {period_s!r}\n", text)
    host, port = devices.cnc.address
    text += "\n" + compensation_toml(host, port, enabled=enabled, **compensation)
    if live:
        text += f"\n[live]\n{live}\n"
    text += ("\n[opcua]\nenabled = false\n" if opcua_port is None else
             f'\n[opcua]\nenabled = true\nhost = "127.0.0.1"\nport = {opcua_port}\n')
    path = Path(out)
    path.write_text(text, encoding="utf-8")
    return path
