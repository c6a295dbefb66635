"""``cncgw simulate ...``: the simulated machine and its devices from the command line."""

from __future__ import annotations

import argparse


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Add ``cncgw simulate``."""
    p = sub.add_parser("simulate", help="run the bundled simulated machine")
    p.add_subparsers(dest="simulate_command", metavar="ACTION", required=True)
