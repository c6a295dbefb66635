"""The simulated machine: drives, heat and structure of a vertical machining center.

Public API (see simulators/live.py for the contract with the device servers):

- :func:`load_scenario` / :func:`bundled_scenarios`: scenarios by bundled name or TOML path.
- :func:`simulate` -> :class:`SimulationResult`; :func:`write_run` writes ``<run>.csv`` (the recording)
  and ``<run>.truth.csv`` (ground truth the gateway never reads).
- :class:`LiveMachine`: a :class:`simulators.live.LiveSource` advancing with a :class:`gateway.clock.Clock`.
- :data:`CHANNELS`, :data:`FACTORS`: names as in ``profiles/sim-vmc.toml``.
- :class:`MachineParams` / :data:`DEFAULT_MACHINE`: every physical parameter, with its source.
"""

from __future__ import annotations

import importlib
from typing import Any

# name -> module; imported on first use so that ``cncgw --help`` does not load scipy
_EXPORTS = {
    "CHANNELS": "drives", "FACTORS": "drives", "EFFECTS": "effects", "Effects": "effects",
    "LiveMachine": "live", "DEFAULT_MACHINE": "params", "MachineParams": "params",
    "SimulationResult": "run", "simulate": "run", "write_run": "run", "Scenario": "scenario",
    "Segment": "scenario", "bundled_scenarios": "scenario", "load_scenario": "scenario",
    "parse_scenario_text": "scenario",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module 'simulators.machine' has no attribute {name!r}")
    return getattr(importlib.import_module(f"simulators.machine.{_EXPORTS[name]}"), name)
