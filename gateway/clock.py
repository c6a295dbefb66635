"""The one time source, injected everywhere.

The sampler, the simulated machine, the device servers and the records all ask a :class:`Clock` for the
time, so a 12 h experiment can run in seconds and they still agree on what time it is.

- :class:`RealClock`: wall time (``time.time``) with monotonic sleeping.
- :class:`ScaledClock`: simulated time that runs ``speedup`` times faster than the wall, for live device
  servers and the demo.
- :class:`ManualClock`: simulated time that moves only when told (``advance``), for tests and offline runs.

All times are seconds. ``now()`` is the time stamped on data (epoch seconds for :class:`RealClock`, seconds
since the simulation start for the simulated clocks unless an ``origin`` is given).
"""

from __future__ import annotations

import threading
import time
from typing import Protocol, runtime_checkable


@runtime_checkable
class Clock(Protocol):
    """What every component needs of time."""

    def now(self) -> float:
        """Current time in seconds."""
        ...

    def sleep_until(self, t: float) -> None:
        """Block until ``now() >= t`` (returns at once if already past)."""
        ...

    @property
    def speedup(self) -> float:
        """Simulated seconds per wall second (1 for real time, ``inf`` for a manual clock)."""
        ...


class RealClock:
    """Wall-clock time; sleeps against the monotonic clock so a wall-clock step cannot stall it."""

    speedup = 1.0

    def now(self) -> float:
        return time.time()

    def sleep_until(self, t: float) -> None:
        remaining = t - time.time()
        if remaining > 0:
            deadline = time.monotonic() + remaining
            while (left := deadline - time.monotonic()) > 0:
                time.sleep(left)


class ScaledClock:
    """Simulated time running ``speedup`` times faster than the wall clock.

    ``now() = origin + speedup * (monotonic() - start)``. Sleeping for a simulated interval sleeps
    ``interval / speedup`` wall seconds.
    """

    def __init__(self, speedup: float = 1.0, *, origin: float = 0.0) -> None:
        if not speedup > 0:
            raise ValueError(f"speedup must be > 0. Got {speedup!r}")
        self._speedup = float(speedup)
        self._origin = float(origin)
        self._start = time.monotonic()

    @property
    def speedup(self) -> float:
        return self._speedup

    def now(self) -> float:
        return self._origin + self._speedup * (time.monotonic() - self._start)

    def sleep_until(self, t: float) -> None:
        while (left := t - self.now()) > 0:
            time.sleep(left / self._speedup)


class ManualClock:
    """Simulated time that moves only through :meth:`advance` or :meth:`set`.

    ``sleep_until`` blocks the calling thread until another thread advances the clock past ``t``; a
    single-threaded caller should advance the clock itself instead of sleeping.
    """

    speedup = float("inf")

    def __init__(self, start: float = 0.0) -> None:
        self._t = float(start)
        self._cond = threading.Condition()

    def now(self) -> float:
        with self._cond:
            return self._t

    def advance(self, dt: float) -> float:
        """Move time forward by ``dt`` seconds and wake sleepers; returns the new time."""
        if dt < 0:
            raise ValueError(f"a clock cannot go backwards: dt must be >= 0. Got {dt!r}")
        with self._cond:
            self._t += dt
            self._cond.notify_all()
            return self._t

    def set(self, t: float) -> None:
        """Move time forward to ``t``."""
        with self._cond:
            if t < self._t:
                raise ValueError(f"a clock cannot go backwards: {t!r} < now {self._t!r}")
            self._t = float(t)
            self._cond.notify_all()

    def sleep_until(self, t: float) -> None:
        with self._cond:
            self._cond.wait_for(lambda: self._t >= t)
