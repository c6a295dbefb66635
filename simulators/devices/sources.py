"""Checks between a device's map and the machine behind it."""

from __future__ import annotations

from collections.abc import Iterable

from gateway.errors import SimulationError, did_you_mean
from simulators.live import LiveSource


def require_channels(source: LiveSource, wanted: Iterable[str], *, device: str) -> None:
    """Raise :class:`SimulationError` naming every channel of ``device``'s map the machine lacks."""
    have = tuple(source.channel_names())
    missing = [name for name in wanted if name not in have]
    if missing:
        lines = [f'{device}: the machine has no channel "{name}"{did_you_mean(name, have)}' for name in missing]
        lines.append(f"{device}: the machine's channels are: {', '.join(have)}")
        raise SimulationError("\n".join(lines))
