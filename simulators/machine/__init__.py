"""The simulated machine: drives, heat and structure of a vertical machining center.

Public API (see simulators/live.py for the contract with the device servers):

- :func:`load_scenario` / :func:`bundled_scenarios`: scenarios by bundled name or TOML path.
- :func:`simulate` -> :class:`SimulationResult`; :func:`write_run` writes ``<run>.csv`` (the recording)
  and ``<run>.truth.csv`` (ground truth the gateway never reads).
- :class:`LiveMachine`: a :class:`simulators.live.LiveSource` advancing with a :class:`gateway.clock.Clock`.
- :data:`CHANNELS`, :data:`FACTORS`: names as in ``profiles/sim-vmc.toml``.
- :class:`MachineParams` / :data:`DEFAULT_MACHINE`: every physical parameter, with its source.
"""

from simulators.machine.drives import CHANNELS, FACTORS
from simulators.machine.effects import EFFECTS, Effects
from simulators.machine.live import LiveMachine
from simulators.machine.params import DEFAULT_MACHINE, MachineParams
from simulators.machine.run import SimulationResult, simulate, write_run
from simulators.machine.scenario import Scenario, Segment, bundled_scenarios, load_scenario, parse_scenario_text

__all__ = [
    "CHANNELS",
    "DEFAULT_MACHINE",
    "EFFECTS",
    "FACTORS",
    "Effects",
    "LiveMachine",
    "MachineParams",
    "Scenario",
    "Segment",
    "SimulationResult",
    "bundled_scenarios",
    "load_scenario",
    "parse_scenario_text",
    "simulate",
    "write_run",
]
