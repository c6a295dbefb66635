"""The one driver interface: a device, its channels, one ``read()`` that returns timestamped values.

Modelled on python-can's ``BusABC``: the base class owns the public calls (:meth:`Driver.open`,
:meth:`Driver.read`, an idempotent :meth:`Driver.close`, the context manager and a warning when a driver
is dropped open); a protocol overrides three small hooks (``_connect``, ``_read_raw``, ``_disconnect``)
and two class methods the profile loader calls (``parse_device_options``, ``parse_channel_address``).
A protocol that can write (the CNC's compensation registers over Modbus) also overrides ``_write_raw``
(and ``_write_what`` for messages); :meth:`Driver.write` is its public call, owned here like ``read()``.

Errors: anything a read or write hook raises is closed over (the transport is closed, so the next call
reconnects and starts clean: pymodbus keeps a dead socket until ``close()``) and re-raised as a
:class:`~gateway.errors.DriverError` (or :class:`~gateway.errors.DeviceTimeout`) naming the device. A
:class:`~gateway.errors.DeviceRefused` (the device answered a write with a refusal) passes through with the
link left open: the device is there, it said no. Timing, retries of the whole device, error counters and
off-scan back-off are not here: the gateway's runner (:mod:`gateway.runner`) wraps every driver the same
way, with the one back-off formula below (:func:`backoff_delay_s`).

Quality: every value comes with a :class:`Quality`. ``GOOD`` and ``SATURATED`` values are used (a
saturated converter reads a bound, so it is counted and reported); ``STALE`` (no fresh data, e.g. no CAN
frame for a while) and ``BAD`` (a frame that did not decode) are not.
"""

from __future__ import annotations

import abc
import enum
import math
import statistics
import struct
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

from gateway.clock import Clock, RealClock
from gateway.errors import DeviceRefused, DeviceTimeout, DriverError
from gateway.tomlcheck import describe


class Quality(enum.IntEnum):
    """How far a value can be trusted; ordered from best to worst."""

    GOOD = 0
    SATURATED = 1  # the converter sat at its limit: the true value is beyond it
    STALE = 2  # nothing new arrived for longer than the device allows: not used
    BAD = 3  # the device answered but this value could not be decoded: not used


@dataclass(frozen=True, slots=True)
class Reading:
    """One read of a device: clock time of the request, one value and one quality per channel.

    ``errors``: what went wrong without failing the read (a silent unit on a shared line: its channels are
    ``BAD`` and the line's other units were read); the runner reports them like a failed read's message.
    """

    t_s: float
    values: tuple[float, ...]
    quality: tuple[Quality, ...]
    errors: tuple[str, ...] = ()


@dataclass(frozen=True, kw_only=True, slots=True)
class DeviceOptions:
    """Keys every ``[devices.NAME]`` table takes, whatever its driver.

    ``period_s``: the fast period of this device (``None``: the profile's ``sampling.fast_period_s``);
    ``timeout_s`` and ``retries``: per request; ``backoff_s`` .. ``backoff_max_s``: how long a failing device
    stays off-scan (doubling, capped, jittered) before it is tried again.
    """

    period_s: float | None = None
    timeout_s: float = 0.5
    retries: int = 0
    backoff_s: float = 1.0
    backoff_max_s: float = 60.0


#: the shortest fast period a device may be sampled at: a Python sampler thread cannot tick faster (2 kHz)
FASTEST_PERIOD_S = 0.0005
#: a channel's ``scale`` (engineering units per count or reading): magnitude in [SCALE_MIN, SCALE_MAX];
#: ``offset``: magnitude at most OFFSET_MAX. Wider is no instrument: a raw value times it overflows or vanishes.
SCALE_MIN = 1e-12
SCALE_MAX = 1e9
OFFSET_MAX = 1e9


def parse_common_options(table: Any, *, timeout_s: float = 0.5) -> dict[str, Any]:
    """Read the keys of :class:`DeviceOptions` from a ``[devices.NAME]`` table (typed, with bounds)."""
    out = {
        "period_s": table.float("period_s", default=None, min=FASTEST_PERIOD_S, max=60.0,
                                expected=f"a period from {FASTEST_PERIOD_S:g} s (2 kHz) to 60 s"),
        "timeout_s": table.float("timeout_s", default=timeout_s, min=0.0, min_exclusive=True, max=60.0),
        "retries": table.int("retries", default=0, min=0, max=10),
        "backoff_s": table.float("backoff_s", default=1.0, min=0.0, min_exclusive=True, max=3600.0),
        "backoff_max_s": table.float("backoff_max_s", default=60.0, min=0.0, min_exclusive=True, max=86400.0),
    }
    for key, default in (("timeout_s", timeout_s), ("retries", 0), ("backoff_s", 1.0), ("backoff_max_s", 60.0)):
        if out[key] is None:  # a bad value: already reported; keep going with the default
            out[key] = default
    if out["backoff_max_s"] < out["backoff_s"]:
        table.problem("backoff_max_s", f"expected a number >= backoff_s ({out['backoff_s']:g}), "
                                       f"got {out['backoff_max_s']:g}")
        out["backoff_max_s"] = out["backoff_s"]
    return out


def parse_scaling(table: Any, per: str = "count") -> tuple[float | None, float | None]:
    """A channel's ``scale`` and ``offset`` (``value = raw * scale + offset``), checked against the bounds above."""
    expected = (f"a non-zero number of engineering units per {per}, from {SCALE_MIN:g} to {SCALE_MAX:g} in "
                "magnitude (negative to reverse)")
    scale = table.float("scale", default=1.0, expected=expected)
    if scale is not None and not SCALE_MIN <= abs(scale) <= SCALE_MAX:
        table.problem("scale", f"expected {expected}, got {describe(table.data['scale'])}")
        scale = None
    offset = table.float("offset", default=0.0, min=-OFFSET_MAX, max=OFFSET_MAX,
                         expected=f"an offset in engineering units within +-{OFFSET_MAX:g}")
    return scale, offset


@dataclass(frozen=True, kw_only=True, slots=True)
class LinkBudget:
    """What a link can physically sustain for one scan of a device's channels.

    ``min_period_s``: the shortest period one scan fits in; ``detail``: how that was worked out, for
    the message that rejects a faster period.
    """

    min_period_s: float
    detail: str

    @property
    def max_rate_hz(self) -> float:
        return 1.0 / self.min_period_s if self.min_period_s > 0 else math.inf


def serial_char_s(baudrate: int, *, bytesize: int = 8, parity: str = "N", stopbits: float = 1) -> float:
    """Seconds one character takes on an asynchronous serial line (start bit + data + parity + stop)."""
    bits = 1 + bytesize + (0 if parity == "N" else 1) + stopbits
    return bits / baudrate


class Driver(abc.ABC):
    """One device and the channels read from it; see the module docstring.

    Args:
        name: the device's name in the profile (every message names it).
        options: what ``parse_device_options`` returned for the device.
        channels: ``(channel name, address)`` pairs, the addresses as ``parse_channel_address`` returned
            them; values come back in this order.
        clock: stamps each reading (the request's time).

    """

    #: protocol, for people: "Modbus TCP"
    kind: ClassVar[str] = "device"
    #: the link's speed is known only by trying it (a network, a server's own pace): the gateway times
    #: whole scans with :meth:`measure_link` at start and refuses a period the link cannot hold
    measured_link: ClassVar[bool] = False

    def __init__(self, *, name: str, options: Any, channels: Sequence[tuple[str, Any]],
                 clock: Clock | None = None) -> None:
        if not channels:
            raise ValueError(f"device {name!r}: a driver needs at least one channel")
        self.name = name
        self.options = options
        self.channel_names = tuple(c for c, _ in channels)
        self.addresses = tuple(a for _, a in channels)
        self.clock: Clock = clock if clock is not None else RealClock()
        self._is_open = False
        self._closed = False
        #: problems of the current scan that do not fail it; ``_read_raw`` appends, :meth:`read` reports
        self.scan_errors: list[str] = []

    # -- what the profile loader calls -------------------------------------------------------------------
    @classmethod
    @abc.abstractmethod
    def parse_device_options(cls, table: Any) -> Any:
        """Check the keys of a ``[devices.NAME]`` table (besides ``driver``); return frozen options."""

    @classmethod
    @abc.abstractmethod
    def parse_channel_address(cls, table: Any) -> Any:
        """Check the address keys of a ``[channels.NAME]`` table; return a frozen address."""

    @classmethod
    def link_budget(cls, options: Any, addresses: Sequence[Any]) -> LinkBudget | None:
        """What the link can sustain for one scan of ``addresses``; ``None`` when it sets no limit."""
        return None

    def measure_link(self, *, scans: int = 30) -> LinkBudget:
        """Time ``scans`` whole scans on this (opened) link, wall time; the budget is their median.

        The median, not a high percentile: a scan that now and then overruns its period costs a skipped
        tick (counted in the window's quality), while a link whose typical scan does not fit the period
        cannot hold it at all. The detail names the link (:meth:`_link_what`) and the spread seen.
        """
        if scans < 3:
            raise ValueError(f"measure_link needs at least 3 scans. Got {scans}")
        self.read()  # a first scan pays for connection set-up: not counted
        times = []
        for _ in range(scans):
            t0 = time.perf_counter()
            self.read()
            times.append(time.perf_counter() - t0)
        times.sort()
        median = statistics.median(times)
        p95 = times[min(len(times) - 1, math.ceil(0.95 * len(times)) - 1)]
        return LinkBudget(min_period_s=median,
                          detail=f"{self._link_what()}, measured at start over {scans} scans: median "
                                 f"{median * 1000:.3g} ms, p95 {p95 * 1000:.3g} ms, "
                                 f"max {times[-1] * 1000:.3g} ms a scan")

    def _link_what(self) -> str:
        """The link, for :meth:`measure_link`'s message (``Modbus TCP to 10.0.0.5:502, one scan is ...``)."""
        return f"{self.kind} device {self.name!r}"

    # -- what protocols provide --------------------------------------------------------------------------
    @abc.abstractmethod
    def _connect(self) -> None:
        """Open the transport (called by :meth:`open`)."""

    @abc.abstractmethod
    def _read_raw(self) -> tuple[Sequence[float], Sequence[Quality]]:
        """One scan of every channel: values in engineering units and their qualities."""

    @abc.abstractmethod
    def _disconnect(self) -> None:
        """Close the transport; must not raise (called after errors too)."""

    def _write_raw(self, target: Any, value: Any) -> None:
        """Write ``value`` to ``target`` (an address in the protocol's own terms); drivers that write override it.

        Raise :class:`~gateway.errors.DeviceRefused` when the device answers with a refusal.
        """
        raise DriverError(f'device "{self.name}" ({self.kind}): this driver does not write')

    def _write_what(self, target: Any, value: Any) -> str:
        """The write, for messages (``heartbeat fc6 120``)."""
        return f"write to {target!r}"

    # -- the public calls --------------------------------------------------------------------------------
    @property
    def is_open(self) -> bool:
        return self._is_open

    def open(self) -> None:
        """Connect; raise :class:`DriverError` naming the device when it cannot."""
        if self._closed:
            raise DriverError(f'device "{self.name}": the driver was closed; make a new one')
        if self._is_open:
            return
        try:
            self._connect()
        except DriverError:
            self._disconnect()
            raise
        except Exception as exc:  # every transport has its own exceptions: name the device, keep the cause
            self._disconnect()
            raise DriverError(f'device "{self.name}" ({self.kind}): cannot connect: {_describe(exc)}') from exc
        self._is_open = True

    def read(self) -> Reading:
        """Read every channel once. On any failure the transport is closed and :class:`DriverError` raised."""
        if not self._is_open:
            self.open()
        t = self.clock.now()
        self.scan_errors = []
        values, quality = self._transaction("read", self._read_raw)
        return Reading(t_s=t, values=tuple(values), quality=tuple(quality), errors=tuple(self.scan_errors))

    def write(self, target: Any, value: Any) -> None:
        """Write ``value`` to ``target`` (connecting first when the link is closed).

        On a failure the transport is closed (the next call reconnects) and :class:`DriverError` (or
        :class:`DeviceTimeout`) raised; a :class:`DeviceRefused` leaves the link open.
        """
        if not self._is_open:
            self.open()
        self._transaction(self._write_what(target, value), lambda: self._write_raw(target, value))

    def _transaction(self, what: str, call: Callable[[], Any]) -> Any:
        """``call()`` with the errors every read and write maps the same way (see the module docstring)."""
        try:
            return call()
        except DeviceRefused:
            raise  # the device answered: the link is fine
        except DriverError:
            self._drop()
            raise
        except TimeoutError as exc:
            self._drop()
            raise DeviceTimeout(f'device "{self.name}" ({self.kind}): no answer: {_describe(exc)}') from exc
        except Exception as exc:  # every transport has its own exceptions: name the device, keep the cause
            self._drop()
            raise DriverError(f'device "{self.name}" ({self.kind}): {what} failed: {_describe(exc)}') from exc

    def close(self) -> None:
        """Close the transport (idempotent); the driver cannot be opened again."""
        self._closed = True
        self._drop()

    def _drop(self) -> None:
        if self._is_open:
            self._is_open = False
        self._disconnect()

    def __enter__(self) -> Driver:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:
        if getattr(self, "_is_open", False) and not getattr(self, "_closed", True):
            warnings.warn(f"device {self.name!r} was not closed properly", ResourceWarning, stacklevel=1)
            self._drop()

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r}, channels={list(self.channel_names)})"


class SharedLine:
    """Per-unit off-scan for the units (boards, modules) that share one serial line.

    :meth:`scan` asks every unit in turn. A unit that fails while another one answers in the same scan has
    its channels cleared (``BAD``) and is not asked again for ``backoff_s``, doubling per failure up to
    ``backoff_max_s`` (clock time): a silent board does not cost the line a timeout every scan, and the
    other boards are read on. Every scan notes why a unit is missing in the driver's ``scan_errors``. When
    no unit answers, the line itself is down: the first failure is raised and the driver fails as a whole.
    """

    def __init__(self, driver: Driver) -> None:
        self._driver = driver
        self._retry: dict[Any, float] = {}
        self._failures: dict[Any, int] = {}
        self._why: dict[Any, str] = {}

    def scan(self, units: Sequence[Any], read: Callable[[Any], None], clear: Callable[[Any], None],
             label: Callable[[Any], str]) -> None:
        """Ask every unit once (see the class docstring).

        ``read(unit)`` reads a unit's channels (raising :class:`DriverError`), ``clear(unit)`` resets them to
        ``BAD``, ``label(unit)`` names it (``unit 5``, ``module 03``).
        """
        driver = self._driver
        now = driver.clock.now()
        answered = 0
        failed: list[tuple[Any, DriverError]] = []
        for unit in units:
            if now < self._retry.get(unit, -math.inf):
                driver.scan_errors.append(f"{label(unit)} off-scan: {self._why[unit]}")
                continue
            try:
                read(unit)
            except DriverError as exc:
                failed.append((unit, exc))
                clear(unit)  # what it answered before failing is not kept
                continue
            answered += 1
            self._failures.pop(unit, None)
            self._retry.pop(unit, None)
        if failed and not answered:
            raise failed[0][1]
        for unit, exc in failed:
            n = self._failures[unit] = self._failures.get(unit, 0) + 1
            self._retry[unit] = now + backoff_delay_s(driver.options, n - 1)
            self._why[unit] = str(exc)
            driver.scan_errors.append(f"{exc} ({label(unit)} off-scan; the line's other units are read on)")


def backoff_delay_s(options: DeviceOptions, doublings: int) -> float:
    """How long a failing device (or unit) stays off-scan: ``backoff_s`` doubled, capped at ``backoff_max_s``.

    ``doublings``: how many times (failures beyond the first that took it off-scan); the runner adds its
    jitter on top, a shared line's units go without.
    """
    return min(options.backoff_s * 2.0 ** min(max(doublings, 0), 30), options.backoff_max_s)


def _describe(exc: BaseException) -> str:
    text = str(exc).strip()
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


# -- helpers several drivers share ----------------------------------------------------------------------
_STRUCT = {"int16": ">h", "uint16": ">H", "int32": ">i", "uint32": ">I", "float32": ">f"}


def unpack_words(words: Sequence[int], data_type: str, *, word_order: str, byte_order: str) -> float:
    """Decode Modbus registers (16-bit words as received) into a number.

    ``word_order="big"``: the first register holds the high word (ABCD); ``"little"``: the low word
    (CDAB). ``byte_order="little"``: the two bytes inside each register are swapped (BADC / DCBA).
    """
    ws = list(words)
    if word_order == "little":
        ws.reverse()
    raw = b"".join(w.to_bytes(2, "big") for w in ws)
    if byte_order == "little":
        raw = b"".join(raw[i:i + 2][::-1] for i in range(0, len(raw), 2))
    return float(struct.unpack(_STRUCT[data_type], raw)[0])
