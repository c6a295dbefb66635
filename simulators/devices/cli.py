"""``cncgw simulate`` actions of the simulated devices."""

from __future__ import annotations

import argparse


def add_actions(actions: argparse._SubParsersAction) -> None:
    """Add this part's actions to ``cncgw simulate``."""
