"""Link budgets measured at start: a period a network link cannot hold is refused before sampling begins.

A serial line's budget is arithmetic (characters on the wire, checked when the profile loads); a network
link's is not: the round trip through switches, a Modbus TCP-to-RTU gateway or an OPC UA server's stack is
known only by trying it. For every device whose driver says so (``Driver.measured_link``),
:func:`check_measured_links` opens a driver of its own, times whole scans (``Driver.measure_link``: the
median of 30), closes it, and raises one :class:`~gateway.errors.ProfileError` (exit status 3, a bad
profile: a service manager must not restart into it) naming every device whose period is shorter than its
median scan, with what the link can do::

    live.toml: devices.adc.period_s: a period of 2 ms is faster than the link can go: Modbus TCP to
    10.0.0.5:502: one scan is 1 request (fc4 0..8), measured at start over 30 scans: median 4.1 ms, p95
    4.6 ms, max 5.2 ms a scan, so it sustains at most 244 Hz: set devices.adc.period_s >= 0.0045

A CPU busy with something else at start (a loaded edge PC, a restart while another service starts) makes
a link look slower than it is, and a refusal is final (a service manager does not restart into it): a
period the first measurement says the link cannot hold is measured again, up to ``attempts`` times
``pause_s`` apart, and the best median counts. A link that is too slow is too slow every time. (Seen: at
load 5 the loopback to the simulated board measured 3.7 ms a scan and refused the restart of a 2 ms
recording that had held it seconds before.)

A device that cannot be reached at start is not refused (it may come up later, and the runner retries
it): the check is logged as skipped. A median that fits with a slower tail is accepted: those reads
overrun and are counted as skipped ticks in the windows' quality (on a loaded 2-core PC the loopback scan
had a 0.2 ms median and a 2.4 ms p95).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace

from drivers import registry
from drivers.base import Driver, LinkBudget
from gateway.clock import Clock
from gateway.errors import DriverError, ProfileError
from gateway.profile import Device, Profile, round_up_period

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True, slots=True)
class LinkCheck:
    """What the start-up measurement of one device's link found; ``budget`` is ``None`` when it was not measured."""

    device: str
    period_s: float
    budget: LinkBudget | None
    skipped: str = ""

    @property
    def holds(self) -> bool:
        return self.budget is None or self.budget.min_period_s <= self.period_s


def check_measured_links(profile: Profile, *, clock: Clock,
                         driver_factories: Mapping[str, Callable[[], Driver]] | None = None,
                         scans: int = 30, attempts: int = 3, pause_s: float = 0.5) -> list[LinkCheck]:
    """Measure every network link of ``profile`` (see the module docstring); raise if one cannot hold its period."""
    factories = dict(driver_factories or {})
    checks: list[LinkCheck] = []
    for d in profile.devices:
        channels = profile.channels_of(d.name)
        if not channels:
            continue
        try:
            cls = registry.load(d.driver)
        except DriverError:
            continue  # the runner reports it, once per retry, like any device that cannot be made
        if not getattr(cls, "measured_link", False):
            continue
        checks.append(_measure(d, factories.get(d.name) or _factory(cls, d, profile, clock), scans,
                               attempts=attempts, pause_s=pause_s))
    bad = [c for c in checks if not c.holds]
    if bad:
        raise ProfileError("\n".join(_refusal(profile, profile.device(c.device), c) for c in bad))
    for c in checks:
        if c.budget is None:
            log.warning("%s: link budget not measured at start (%s); the runner retries the device", c.device,
                        c.skipped)
        else:
            log.info("%s: %s", c.device, c.budget.detail)
    return checks


def _factory(cls: type[Driver], d: Device, profile: Profile, clock: Clock) -> Callable[[], Driver]:
    pairs = [(c.name, c.address) for c in profile.channels_of(d.name)]
    return lambda: cls(name=d.name, options=d.options, channels=pairs, clock=clock)


def _measure(d: Device, make: Callable[[], Driver], scans: int, *, attempts: int, pause_s: float) -> LinkCheck:
    """The device's link measured on a driver of its own; again (up to ``attempts``) while it seems too slow."""
    best: LinkBudget | None = None
    for attempt in range(1, max(1, attempts) + 1):
        if attempt > 1:
            log.info("%s: the link measured %.3g ms a scan against a %g ms period: measuring again (%d of %d)",
                     d.name, best.min_period_s * 1000, d.period_s * 1000, attempt, attempts)
            time.sleep(pause_s)
        driver: Driver | None = None
        try:
            driver = make()
            driver.open()
            budget = driver.measure_link(scans=scans)
        except DriverError as exc:
            return LinkCheck(device=d.name, period_s=d.period_s, budget=None, skipped=str(exc))
        finally:
            if driver is not None:
                driver.close()
        if best is None or budget.min_period_s < best.min_period_s:
            best = budget
        if best.min_period_s <= d.period_s:
            break
    assert best is not None
    if attempt > 1:
        best = replace(best, detail=f"{best.detail} (the best of {attempt} measurements "
                                                f"{pause_s:g} s apart)")
    return LinkCheck(device=d.name, period_s=d.period_s, budget=best)


def _refusal(profile: Profile, d: Device, c: LinkCheck) -> str:
    assert c.budget is not None
    own = getattr(d.options, "period_s", None) is not None
    key = f"devices.{d.name}.period_s" if own else f"devices.{d.name}"
    whose = "" if own else " (sampling.fast_period_s)"
    return (f"{profile.path}: {key}: a period of {d.period_s * 1000:g} ms{whose} is faster than the link can go: "
            f"{c.budget.detail}, so it sustains at most {c.budget.max_rate_hz:.0f} Hz: set "
            f"devices.{d.name}.period_s >= {round_up_period(c.budget.min_period_s * 1.1)}")
