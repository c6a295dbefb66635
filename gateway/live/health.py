"""The live gateway's health: one frozen snapshot that OPC UA, the logs, the demo and benchmarks read by attribute.

:meth:`gateway.live.runtime.LiveGateway.health` takes it; every part is itself frozen (the last window's
:class:`~gateway.windows.WindowRecord`, the :class:`~gateway.live.tracking.EstimateUpdate` that followed
it, the compensation writer's :class:`~gateway.live.compensation.WriterStatus`, the acquisition's
:class:`~gateway.sampler.DeviceStatus` per device, the active :class:`~gateway.live.audit.Alarm` s), so a
snapshot handed to another thread cannot change under it, and a misspelt field is an ``AttributeError``
where a misspelt dict key was a silent ``None``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType

from gateway.live.audit import Alarm
from gateway.live.compensation import WriterStatus
from gateway.live.tracking import EstimateUpdate
from gateway.sampler import DeviceStatus
from gateway.windows import WindowRecord


@dataclass(frozen=True, kw_only=True, slots=True)
class GapStatus:
    """Windows the estimator filled by its gap policy since start (rebuild included), and the last such gap."""

    filled_windows: int = 0
    policy: str = "hold"
    last: str = ""  # the last gap described ("" when there was none)


@dataclass(frozen=True, kw_only=True, slots=True)
class Health:
    """What the live gateway knows at clock time ``clock_s``; see the module docstring.

    ``uptime_s``: wall seconds since start; ``windows_live``: windows closed since start;
    ``rebuilt_windows``: windows replayed from the records at start; ``stale_after_s``: the profile's
    ``[live] stale_after_s`` (see :attr:`stale`).
    """

    machine: str
    clock_s: float
    uptime_s: float = 0.0
    windows_live: int = 0
    rebuilt_windows: int = 0
    devices: tuple[DeviceStatus, ...] = ()
    last_window: WindowRecord | None = None
    estimate: EstimateUpdate | None = None
    compensation: WriterStatus | None = None
    gaps: GapStatus = GapStatus()
    alarms: tuple[Alarm, ...] = ()
    stale_after_s: float = math.inf

    @property
    def factors(self) -> Mapping[str, float]:
        """The last window's factors (empty before the first window)."""
        return MappingProxyType({}) if self.last_window is None else self.last_window.factors

    @property
    def stale(self) -> bool:
        """No window has ended within ``stale_after_s`` of ``clock_s`` (the writer holds the offsets then too)."""
        w = self.last_window
        return w is not None and self.clock_s - w.end_s > self.stale_after_s

    @property
    def sample_rate_hz(self) -> float:
        """The lowest device's good reads per wall second since start (NaN without devices or on a stepped clock)."""
        return min((d.rate_hz for d in self.devices if not math.isnan(d.rate_hz)), default=math.nan)
