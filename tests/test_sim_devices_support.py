"""Support for the simulated-device tests (no tests here): a deterministic LiveSource and client helpers.

``WaveSource`` gives every channel its own sine of simulated time around its own mean, so a map that
swaps two channels, or a device that serves a stale time, reads visibly wrong; it records every
compensation the CNC hands it. With a ``ManualClock`` the expected value of a read is exactly
``source.values(clock.now())``.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Mapping

SIM_VMC_CHANNELS = ("spindle_speed", "spindle_i1", "spindle_i2", "x_velocity", "y_velocity", "z_velocity",
                    "x_current", "y_current", "z_current")

# channel: (mean, amplitude, period_s): all inside the default analog ranges, all different
_WAVES = {
    "spindle_speed": (6000.0, 4000.0, 600.0),
    "spindle_i1": (20.0, 15.0, 300.0),
    "spindle_i2": (-10.0, 12.0, 420.0),
    "x_velocity": (1000.0, 20000.0, 90.0),
    "y_velocity": (-2000.0, 15000.0, 70.0),
    "z_velocity": (500.0, 8000.0, 50.0),
    "x_current": (1.0, 12.0, 80.0),
    "y_current": (-2.0, 10.0, 60.0),
    "z_current": (8.0, 6.0, 40.0),
}


class WaveSource:
    """A LiveSource with one sine per channel; thread-safe; records compensation offsets."""

    def __init__(self, channels: tuple[str, ...] = SIM_VMC_CHANNELS) -> None:
        self._channels = channels
        self._lock = threading.Lock()
        self.compensation: list[dict[str, float]] = []

    def channel_names(self) -> tuple[str, ...]:
        return self._channels

    def values(self, t: float) -> Mapping[str, float]:
        out = {}
        for name in self._channels:
            mean, amp, period = _WAVES.get(name, (0.0, 1.0, 100.0))
            out[name] = mean + amp * math.sin(2 * math.pi * t / period + 0.3)
        return out

    def set_compensation(self, offsets_um: Mapping[str, float]) -> None:
        with self._lock:
            self.compensation.append(dict(offsets_um))

    def last_compensation(self) -> dict[str, float] | None:
        with self._lock:
            return dict(self.compensation[-1]) if self.compensation else None


def wait_for(predicate, *, timeout_s: float = 10.0, interval_s: float = 0.01):
    """Poll ``predicate`` until it returns something truthy; fail with its last value after ``timeout_s``.

    The limit is generous on purpose: it bounds a broken test, it does not measure speed.
    """
    import time

    deadline = time.monotonic() + timeout_s
    while True:
        result = predicate()
        if result:
            return result
        if time.monotonic() > deadline:
            raise AssertionError(f"condition not met within {timeout_s} s; last value {result!r}")
        time.sleep(interval_s)
