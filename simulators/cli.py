"""``cncgw simulate ...``: the simulated machine and its devices from the command line.

The machine's actions (``record``, ``plot``) live in :mod:`simulators.machine.cli`, the devices' (``serve``)
in :mod:`simulators.devices.cli`; each adds its own sub-parsers here.
"""

from __future__ import annotations

import argparse


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Add ``cncgw simulate`` and the actions of the machine and the devices."""
    from simulators.devices import cli as devices_cli
    from simulators.machine import cli as machine_cli

    p = sub.add_parser("simulate", help="run the bundled simulated machine and its devices")
    actions = p.add_subparsers(dest="simulate_command", metavar="ACTION", required=True)
    machine_cli.add_actions(actions)
    devices_cli.add_actions(actions)
