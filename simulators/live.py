"""The contract between the simulated machine and the simulated devices.

A device server (ADC board, CAN module, DCON module, the CNC's compensation registers) knows nothing of
physics: it asks a :class:`LiveSource` for the instantaneous value of each channel at the current
simulated time, and hands compensation offsets back to it. The simulated machine implements this; a
test may implement it with a few lines of its own.

Conventions:
- channel values are in engineering units (rpm, A, mm/min), instantaneous (what an analog terminal
  shows at that moment, not a window mean);
- ``t`` comes from the one shared :class:`gateway.clock.Clock`; calls arrive with non-decreasing ``t``
  from several threads, so implementations lock;
- compensation offsets are in um per axis and are ADDED to the axis position: the tool-to-table error
  with compensation is ``displacement + offset``, so an offset of ``-estimate`` cancels the estimate.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Protocol, runtime_checkable


@runtime_checkable
class LiveSource(Protocol):
    """What device servers need of the machine behind them."""

    def channel_names(self) -> tuple[str, ...]:
        """Every channel this source can give, e.g. ``spindle_speed``, ``z_current``."""
        ...

    def values(self, t: float) -> Mapping[str, float]:
        """Instantaneous value of every channel at simulated time ``t`` (s)."""
        ...

    def set_compensation(self, offsets_um: Mapping[str, float]) -> None:
        """Offsets (um) the CNC now applies per axis (``x``, ``y``, ``z``); added to the position."""
        ...
