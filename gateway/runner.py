"""Every driver runs inside a :class:`DeviceRunner`: timing, error and timeout counters, off-scan back-off.

Modelled on Telegraf's ``running_input``: drivers only know their protocol; what happens when a device
fails is decided here, the same way for all of them:

- the first failure of a device that was working is retried at the next tick (a dropped TCP connection
  usually comes back at once: the driver has already closed it, the next read reconnects);
- a second failure in a row takes the device off-scan for ``backoff_s``, doubling at every further
  failure up to ``backoff_max_s``, with +/-20 % jitter so devices that failed together do not retry in
  lock-step; while off-scan the device is not touched and its ticks are counted as off-scan;
- a successful read puts it back on scan and resets the back-off.

Each transition is logged once (not once per tick), and counted, so a record can say which devices were
in error during its window. A runner belongs to the one thread that samples its device (pymodbus clients
are not thread-safe); only :meth:`DeviceRunner.close` may come from another thread, after that thread
has stopped.
"""

from __future__ import annotations

import logging
import random
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from drivers import registry
from drivers.base import Driver, Reading, backoff_delay_s
from gateway.clock import Clock
from gateway.errors import DeviceTimeout, DriverError
from gateway.profile import Channel, Device

log = logging.getLogger(__name__)


@dataclass(slots=True)
class RunnerCounters:
    """Counters of one device; the sampler takes and resets a copy at every window boundary."""

    reads_ok: int = 0
    reads_failed: int = 0
    timeouts: int = 0
    connects_failed: int = 0
    off_scan_ticks: int = 0
    recoveries: int = 0
    read_time_max_s: float = 0.0
    errors: list[str] = field(default_factory=list)  # distinct messages, first few only

    def note_error(self, message: str) -> None:
        if message not in self.errors and len(self.errors) < 5:
            self.errors.append(message)

    @property
    def in_error(self) -> bool:
        return bool(self.reads_failed or self.connects_failed or self.off_scan_ticks or self.errors)


class DeviceRunner:
    """One device's driver, wrapped; see the module docstring.

    Args:
        device: the profile's device.
        channels: the profile's channels on it (values come back in this order).
        clock: the shared clock (stamps readings).
        driver_factory: makes a fresh driver (default: the registry's class for ``device.driver``);
            a new one is made after every failure, so no state of a broken connection survives.
        seed: for the back-off jitter.
        monotonic: the time base of the back-off (wall time by default; the clock's time when a test
            steps a manual clock, whose ticks run faster than the wall).

    """

    def __init__(self, *, device: Device, channels: Sequence[Channel], clock: Clock,
                 driver_factory: Callable[[], Driver] | None = None, seed: int | None = None,
                 monotonic: Callable[[], float] = time.monotonic) -> None:
        if not channels:
            raise ValueError(f"device {device.name!r} has no channels to read")
        self.device = device
        self.channel_names = tuple(c.name for c in channels)
        self._factory = driver_factory or _registry_factory(device, channels, clock)
        self.options: Any = device.options
        self.counters = RunnerCounters()
        self.total = RunnerCounters()  # since start, for status and benchmarks
        self.driver: Driver | None = None
        self._failures = 0  # in a row
        self._retry_at = 0.0
        self._random = random.Random(seed)
        self._monotonic = monotonic
        self.state = "new"  # new, on_scan, off_scan, closed

    # -- the sampler's calls --------------------------------------------------------------------------------
    def poll(self) -> Reading | None:
        """Read the device once, or ``None`` when it is off-scan or the read failed (counted either way)."""
        if self.state == "off_scan" and self._monotonic() < self._retry_at:
            self.counters.off_scan_ticks += 1
            self.total.off_scan_ticks += 1
            return None
        if self.state == "closed":
            return None
        driver = self.driver
        if driver is None:
            try:
                driver = self._factory()
                driver.open()
            except DriverError as exc:
                if driver is not None:
                    driver.close()
                self.counters.connects_failed += 1
                self.total.connects_failed += 1
                self._failed(str(exc))
                return None
            self.driver = driver
        start = time.perf_counter()
        try:
            reading = driver.read()
        except DeviceTimeout as exc:
            self.counters.timeouts += 1
            self.total.timeouts += 1
            self._read_failed(driver, str(exc))
            return None
        except DriverError as exc:
            self._read_failed(driver, str(exc))
            return None
        elapsed = time.perf_counter() - start
        c = self.counters
        c.reads_ok += 1
        self.total.reads_ok += 1
        for message in reading.errors:  # a read that worked in part (a silent unit on a shared line)
            c.note_error(message)
            self.total.note_error(message)
        if elapsed > c.read_time_max_s:
            c.read_time_max_s = elapsed
        if self._failures:
            self._recovered()
        self.state = "on_scan"
        return reading

    def take_counters(self) -> RunnerCounters:
        """The counters since the last call (a window's worth), resetting them."""
        c, self.counters = self.counters, RunnerCounters()
        return c

    def close(self) -> None:
        """Close the driver (idempotent)."""
        self.state = "closed"
        driver, self.driver = self.driver, None
        if driver is not None:
            driver.close()

    # -- failure handling -----------------------------------------------------------------------------------
    def _read_failed(self, driver: Driver, message: str) -> None:
        self.counters.reads_failed += 1
        self.total.reads_failed += 1
        driver.close()  # a fresh driver next time: no dead socket or half-read frame survives
        self.driver = None
        self._failed(message)

    def _failed(self, message: str) -> None:
        self.counters.note_error(message)
        self.total.note_error(message)
        self._failures += 1
        if self._failures == 1 and self.state == "on_scan":
            log.warning("%s: %s; retrying at the next tick", self.device.name, message)
            return  # one failure of a working device: try again at once
        backoff = backoff_delay_s(self.options, self._failures - 2) * self._random.uniform(0.8, 1.2)
        self._retry_at = self._monotonic() + backoff
        if self.state != "off_scan":
            log.error("%s: %s; off-scan, retrying in %.1f s", self.device.name, message, backoff)
        else:
            log.debug("%s: still failing (%s); next try in %.1f s", self.device.name, message, backoff)
        self.state = "off_scan"

    def _recovered(self) -> None:
        log.warning("%s: back on scan after %d failed attempt%s", self.device.name, self._failures,
                    "s" if self._failures != 1 else "")
        self.counters.recoveries += 1
        self.total.recoveries += 1
        self._failures = 0


def _registry_factory(device: Device, channels: Sequence[Channel], clock: Clock) -> Callable[[], Driver]:
    cls = registry.load(device.driver)
    pairs = [(c.name, c.address) for c in channels]

    def make() -> Driver:
        return cls(name=device.name, options=device.options, channels=pairs, clock=clock)

    return make
