"""Machine profiles: one TOML file per machine, parsed once into frozen typed objects.

A profile says which displacement axes are estimated, which heat-generating factors feed the model and
how each is computed from a live channel (mean, mean of squares, mean of |x| over a window), how
recordings are laid out, where the model file lives, and (filled by the acquisition and compensation
work) which devices and channels the gateway reads and how it writes compensation. See
``profiles/template.toml`` for every key with its meaning.

Nothing downstream sees a raw dict: :func:`load_profile` returns a :class:`Profile` or raises one
:class:`~gateway.errors.ProfileError` that lists every problem with file, line, key path, bad value and
what was expected.
"""

from __future__ import annotations

import enum
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any

from drivers.base import FASTEST_PERIOD_S
from gateway.errors import ProfileError
from gateway.profile.live import (
    Compensation,
    Live,
    OpcUa,
    Records,
    parse_compensation,
    parse_live,
    parse_opcua,
    parse_records,
)
from gateway.profile.mqtt import Mqtt, parse_mqtt
from gateway.profile.probes import Probes, parse_probes
from gateway.recording import MAX_PERIOD_S, MIN_PERIOD_S
from gateway.tomlcheck import NAME, Table, TomlDoc

__all__ = ["Channel", "Compensation", "Device", "Factor", "Live", "OpcUa", "Profile", "RecordingLayout", "Sampling",
           "Stat", "format_summary", "load_profile"]

AXES = ("x", "y", "z")
_UNIT = re.compile(r"[^\n]{1,32}")


class Stat(enum.StrEnum):
    """How a factor is computed from a channel's fast samples over one window."""

    MEAN = "mean"  # speed: friction and hysteresis heat ~ speed
    MEAN_SQUARE = "mean_square"  # current: Joule heat ~ I^2 (mean of squares, not square of mean)
    MEAN_ABS = "mean_abs"  # feed velocity: friction ~ |v| whichever the direction


@dataclass(frozen=True, kw_only=True, slots=True)
class Factor:
    """One heat-generating factor: an input of the thermal model."""

    name: str
    unit: str
    channel: str
    stat: Stat
    column: str
    description: str = ""


@dataclass(frozen=True, kw_only=True, slots=True)
class Sampling:
    """Fast sampling period and averaging window, and how displacement is read during identification.

    ``min_coverage``: the share of a window that good samples must cover for the window to count as good.
    ``displacement_channels``: axis -> channel of a displacement sensor, read as a burst of ``burst_s``
    at the end of every window and averaged over a whole number of spindle revolutions (speed from
    ``burst_speed_channel``, rpm) to cancel runout; empty outside identification runs.
    """

    fast_period_s: float
    window_s: float
    min_coverage: float = 0.9
    displacement_channels: MappingProxyType[str, str] = field(
        default_factory=lambda: MappingProxyType({}))
    burst_s: float = 3.0
    burst_speed_channel: str | None = None

    @property
    def samples_per_window(self) -> int:
        return round(self.window_s / self.fast_period_s)


@dataclass(frozen=True, kw_only=True, slots=True)
class RecordingLayout:
    """How per-window recordings of this machine are laid out (see ``gateway.recording``)."""

    time_column: str
    period_s: float
    displacement_columns: MappingProxyType[str, str]


@dataclass(frozen=True, kw_only=True, slots=True)
class Device:
    """A device the gateway reads (an ADC board, a CNC terminal). ``options`` are checked by its driver.

    ``period_s``: its fast period (its own ``period_s`` key, else ``sampling.fast_period_s``).
    """

    name: str
    driver: str
    options: Any
    period_s: float = 0.002


@dataclass(frozen=True, kw_only=True, slots=True)
class Channel:
    """A live signal on a device, in engineering units after the driver's scaling."""

    name: str
    device: str
    unit: str
    address: Any


@dataclass(frozen=True, kw_only=True, slots=True)
class Profile:
    """A machine, as its profile describes it."""

    path: Path
    name: str
    description: str
    axes: tuple[str, ...]
    sampling: Sampling
    factors: tuple[Factor, ...]
    recording: RecordingLayout
    model_path: Path
    devices: tuple[Device, ...] = ()
    channels: tuple[Channel, ...] = ()
    compensation: Compensation = field(default_factory=Compensation)
    live: Live = field(default_factory=Live)
    opcua: OpcUa = field(default_factory=OpcUa)
    mqtt: Mqtt = field(default_factory=Mqtt)
    records: Records = field(default_factory=Records)
    probes: Probes = field(default_factory=Probes)

    @property
    def factor_names(self) -> tuple[str, ...]:
        return tuple(f.name for f in self.factors)

    def device(self, name: str) -> Device:
        for d in self.devices:
            if d.name == name:
                return d
        raise KeyError(name)

    def channels_of(self, device: str) -> tuple[Channel, ...]:
        """The channels read from ``device``, in profile order."""
        return tuple(c for c in self.channels if c.device == device)

    def factor(self, name: str) -> Factor:
        for f in self.factors:
            if f.name == name:
                return f
        raise KeyError(name)


# --------------------------------------------------------------------------------------------------------
def bundled_profiles() -> list[str]:
    """Names of the profiles shipped with the package (``sim-vmc``, ``paper-vm40iii``, ``template``)."""
    from gateway import BUNDLED

    return sorted(p.stem for p in BUNDLED.glob("*.toml") if not p.name.endswith(".model.toml"))


def resolve_profile(path: str | Path) -> Path:
    """``path`` when it names a file; else ``NAME.toml`` here; else the bundled profile of that name.

    ``sim-vmc`` or ``sim-vmc.toml`` name the bundled one unless such a file is here. A bare name that is
    neither raises :class:`ProfileError` listing the bundled names, so an installed gateway finds its bundled
    profiles from any directory.
    """
    from gateway import BUNDLED

    p = Path(path)
    name = p.name[:-len(".toml")] if p.name.endswith(".toml") else p.name
    if not p.exists() and len(p.parts) != 1 and name in bundled_profiles():
        # the README's `profiles/sim-vmc.toml` typed outside a checkout (an installed wheel)
        raise ProfileError(f"{p}: file not found; {name} is a profile bundled with cncgw: from any directory, "
                           f"--profile {name}")
    if p.exists() or len(p.parts) != 1:
        return p
    if p.suffix != ".toml" and p.with_name(f"{p.name}.toml").is_file():
        return p.with_name(f"{p.name}.toml")  # `--profile vmc-3` for the vmc-3.toml `profile new` wrote here
    if name in bundled_profiles():
        return BUNDLED / f"{name}.toml"
    from gateway.errors import did_you_mean

    names = bundled_profiles()
    raise ProfileError(f"{p}: file not found, nor a bundled profile{did_you_mean(name, names)} "
                       f"(bundled: {', '.join(names)})")


def load_profile(path: str | Path) -> Profile:
    """Read and check a profile (a file or a bundled profile's name); raise :class:`ProfileError` with all problems."""
    doc = TomlDoc(resolve_profile(path), error=ProfileError)
    root = doc.root
    if "path" in root and "machine" not in root:
        # a model file given for the profile: one line, not a dozen unknown keys
        raise ProfileError(f"{doc.path}: a model file (it has [[path]] tables), not a profile: expected a machine "
                           "profile with [machine] and [factors.*]; pass the model with --model")

    machine = root.table("machine", required=True)
    name = description = ""
    axes: tuple[str, ...] = AXES
    if machine is not None:
        name = machine.str("name") or ""
        description = machine.str("description", default="")
        axes = machine.str_list("axes", default=AXES, choices=AXES, min_len=1) or AXES
        machine.done()

    sampling = _parse_sampling(root, axes)
    window = sampling.window_s

    factors = _parse_factors(root)

    rec_t = root.table("recording")
    time_column, period_s, disp_cols = "time_s", window, {a: f"{a}_um" for a in axes}
    if rec_t is not None:
        time_column = rec_t.str("time_column", default="time_s")
        period_s = rec_t.float("period_s", default=window, min=MIN_PERIOD_S, max=MAX_PERIOD_S,
                               expected=f"a row period from {MIN_PERIOD_S:g} s to {MAX_PERIOD_S:g} s (a day)") or window
        cols_t = rec_t.table("displacement_columns")
        if cols_t is not None:
            for a in axes:
                disp_cols[a] = cols_t.str(a, default=disp_cols[a])
            cols_t.done()
        rec_t.done()
    recording = RecordingLayout(time_column=time_column, period_s=period_s,
                                displacement_columns=MappingProxyType(disp_cols))
    _check_columns_distinct(root, factors, recording)

    model_t = root.table("model")
    model_file = f"{doc.path.stem}.model.toml"
    if model_t is not None:
        model_file = model_t.str("file", default=model_file)
        model_t.done()
    model_path = (doc.path.parent / model_file) if model_file else doc.path.with_suffix(".model.toml")

    devices, channels = _parse_acquisition(root, factors, sampling)

    live = parse_live(root, sampling.window_s)
    compensation = parse_compensation(root, axes, sampling.window_s)
    opcua = parse_opcua(root, doc.path.parent)
    mqtt = parse_mqtt(root, doc.path.parent)
    records = parse_records(root)
    probes = parse_probes(root)

    root.done()
    doc.raise_problems()
    return Profile(
        path=doc.path, name=name, description=description, axes=axes, sampling=sampling,
        factors=tuple(factors), recording=recording, model_path=model_path,
        devices=tuple(devices), channels=tuple(channels), compensation=compensation, live=live, opcua=opcua,
        mqtt=mqtt, records=records, probes=probes,
    )


def _parse_sampling(root: Table, axes: tuple[str, ...]) -> Sampling:
    sampling_t = root.table("sampling")
    fast = window = coverage = burst = speed_channel = None
    disp: dict[str, str] = {}
    if sampling_t is not None:
        fast = sampling_t.float("fast_period_s", default=0.002, min=FASTEST_PERIOD_S, max=10.0,
                                expected=f"a period from {FASTEST_PERIOD_S:g} s (2 kHz) to 10 s")
        window = sampling_t.float("window_s", default=60.0, min=0.0, min_exclusive=True, max=86400.0)
        coverage = sampling_t.float("min_coverage", default=0.9, min=0.0, max=1.0)
        disp_t = sampling_t.table("displacement_channels")
        if disp_t is not None:
            for a in axes:
                ch = disp_t.str(a, default=None, pattern=NAME, expected="a channel name")
                if ch is not None:
                    disp[a] = ch
            disp_t.done()
        burst = sampling_t.float("burst_s", default=3.0, min=0.0, min_exclusive=True, max=86400.0)
        speed_channel = sampling_t.str("burst_speed_channel", default=None, pattern=NAME,
                                       expected="a channel name (spindle speed in rpm)")
        sampling_t.done()
    fast = fast if fast is not None else 0.002
    window = window if window is not None else 60.0
    if sampling_t is not None and window < fast:
        sampling_t.problem("window_s", f"window ({window:g} s) must be at least one fast period ({fast:g} s)")
    burst = burst if burst is not None else 3.0
    if sampling_t is not None and disp and burst > window:
        sampling_t.problem("burst_s", f"a displacement burst ({burst:g} s) must fit in the window ({window:g} s)")
    if sampling_t is not None and disp and burst < fast:
        sampling_t.problem("burst_s", f"a displacement burst ({burst:g} s) must hold at least one fast sample "
                                      f"({fast:g} s)")
    return Sampling(fast_period_s=fast, window_s=window, min_coverage=coverage if coverage is not None else 0.9,
                    displacement_channels=MappingProxyType(disp), burst_s=burst, burst_speed_channel=speed_channel)


def _parse_factors(root: Table) -> list[Factor]:
    factors = []
    items = root.tables("factors", required=True, name_pattern=NAME,
                        expected="at least one [factors.NAME] table with unit and stat")
    if "factors" in root and not items and not root.doc.problems:
        root.problem("factors", "no factors defined: expected at least one [factors.NAME] table")
    for fname, t in items:
        unit = t.str("unit", pattern=_UNIT, expected="a unit such as \"rpm\" or \"A^2\"")
        stat = t.str("stat", choices=[s.value for s in Stat])
        channel = t.str("channel", default=fname)
        column = t.str("column", default=fname)
        desc = t.str("description", default="")
        t.done()
        if unit is None or stat is None:
            continue
        factors.append(Factor(name=fname, unit=unit, channel=channel or fname, stat=Stat(stat),
                              column=column or fname, description=desc or ""))
    return factors


def _check_columns_distinct(root: Table, factors: list[Factor], rec: RecordingLayout) -> None:
    seen: dict[str, str] = {}
    for f in factors:
        seen.setdefault(f.column, f"factors.{f.name}.column")
    for axis, col in rec.displacement_columns.items():
        if col in seen:
            root.doc.problem(("recording", "displacement_columns", axis),
                             f'column "{col}" is already used by {seen[col]}: expected a column of its own')
        seen.setdefault(col, f"recording.displacement_columns.{axis}")
    if rec.time_column in seen:
        root.doc.problem(("recording", "time_column"),
                         f'column "{rec.time_column}" is already used by {seen[rec.time_column]}')


def _parse_acquisition(root: Table, factors: list[Factor],
                       sampling: Sampling) -> tuple[list[Device], list[Channel]]:
    """``[devices.NAME]`` and ``[channels.NAME]``: their driver-specific keys are checked by the driver."""
    from drivers import registry  # the registry decides which drivers exist and what options they take
    from gateway.errors import did_you_mean

    devices: list[Device] = []
    drivers: dict[str, str] = {}  # every device whose driver is known, parsed or not: its channels are checked
    device_tables: list[str] = []
    for dname, t in root.tables("devices", name_pattern=NAME):
        device_tables.append(dname)
        known = registry.names()
        driver = t.str("driver", choices=known,
                       expected=None if known else "the name of an installed driver (none is installed)")
        if driver is None:
            continue
        options = registry.parse_device_options(driver, t)
        t.done()
        drivers[dname] = driver
        if options is None:
            continue
        period = getattr(options, "period_s", None) or sampling.fast_period_s
        if period > sampling.window_s:
            t.problem("period_s", f"the device's period ({period:g} s) must not exceed the window "
                                  f"({sampling.window_s:g} s)")
        serial = getattr(options, "port", None)
        if isinstance(serial, str):  # a serial line is opened by one device only
            other = next((d.name for d in devices if getattr(d.options, "port", None) == serial), None)
            if other is not None:
                what = {"modbus_rtu": "unit_id", "dcon": "module"}.get(driver)
                how = (f"one [devices.NAME] for the line, each channel naming its {what}" if what
                       else "one [devices.NAME] for the line")
                t.problem("port", f'"{serial}" is already the port of device "{other}": one serial line is one '
                                  f"device ({how})")
        devices.append(Device(name=dname, driver=driver, options=options, period_s=period))
    by_name = {d.name: d for d in devices}

    channels: list[Channel] = []
    channel_tables: list[str] = []  # every channel, parsed or not: a bad one is not also reported as missing
    for cname, t in root.tables("channels", name_pattern=NAME):
        channel_tables.append(cname)
        dev = t.str("device", choices=device_tables or None,
                    expected=f"the name of a [devices.NAME] table ({', '.join(device_tables)})" if device_tables
                    else "the name of a [devices.NAME] table (there are none)")
        unit = t.str("unit", default="")
        if dev is None or dev not in drivers:
            continue  # the device's own problem is reported with the device
        address = registry.parse_channel_address(drivers[dev], t)
        t.done()
        if address is None or dev not in by_name:
            continue
        channels.append(Channel(name=cname, device=dev, unit=unit or "", address=address))

    if devices and not root.doc.problems:
        _check_link_budgets(root, devices, channels, sampling)
    if channel_tables:
        names = channel_tables
        for f in factors:
            if f.channel not in names:
                root.doc.problem(("factors", f.name, "channel"),
                                 f'no channel "{f.channel}": expected the name of a [channels.NAME] table'
                                 f"{did_you_mean(f.channel, names)}")
        wanted = [(("sampling", "displacement_channels", a), c) for a, c in sampling.displacement_channels.items()]
        if sampling.burst_speed_channel is not None:
            wanted.append((("sampling", "burst_speed_channel"), sampling.burst_speed_channel))
        for path, c in wanted:
            if c not in names:
                root.doc.problem(path, f'no channel "{c}": expected the name of a [channels.NAME] table'
                                       f"{did_you_mean(c, names)}")
    return devices, channels


def _check_link_budgets(root: Table, devices: list[Device], channels: list[Channel], sampling: Sampling) -> None:
    """Refuse a period a device's link cannot physically meet, saying what it can."""
    from drivers import registry

    for d in devices:
        addresses = [c.address for c in channels if c.device == d.name]
        if not addresses:
            continue
        budget = registry.link_budget(d.driver, d.options, addresses)
        if budget is None or budget.min_period_s <= d.period_s:
            continue
        own = getattr(d.options, "period_s", None) is not None
        path = ("devices", d.name, "period_s") if own else ("devices", d.name)
        whose = "" if own else " (sampling.fast_period_s)"
        root.doc.problem(path, f"a period of {d.period_s * 1000:g} ms{whose} is faster than the link can go: "
                               f"{budget.detail}, so it sustains at most {budget.max_rate_hz:.0f} Hz: set "
                               f"devices.{d.name}.period_s >= {round_up_period(budget.min_period_s)}")


def round_up_period(seconds: float) -> str:
    """A period a little above ``seconds``, as a user would type it."""
    for step in (0.0001, 0.0005, 0.001, 0.005, 0.01, 0.05, 0.1, 0.5, 1.0):
        if seconds < 100 * step:
            return f"{math.ceil(seconds / step - 1e-9) * step:.4g}"
    return f"{math.ceil(seconds):g}"


# --------------------------------------------------------------------------------------------------------
def format_summary(profile: Profile) -> str:
    """Human summary printed by ``cncgw profile check``."""
    s = profile.sampling
    lines = [
        f"profile   {profile.path}: OK",
        f"machine   {profile.name}" + (f": {profile.description}" if profile.description else ""),
        f"axes      {', '.join(profile.axes)} (displacement in um)",
        f"sampling  fast period {s.fast_period_s * 1000:g} ms, window {s.window_s:g} s "
        f"({s.samples_per_window} samples per window)",
        f"factors   {len(profile.factors)}",
    ]
    rows = [(f.name, f.stat.value, f"of channel {f.channel}", f"[{f.unit}]", f"column {f.column}")
            for f in profile.factors]
    widths = [max(len(r[k]) for r in rows) for k in range(4)]
    for r in rows:
        lines.append("  " + "  ".join(c.ljust(w) for c, w in zip(r[:4], widths, strict=True)) + "  " + r[4])
    rec = profile.recording
    disp = ", ".join(f"{a}={c}" for a, c in rec.displacement_columns.items())
    lines.append(f"recording time column {rec.time_column}, period {rec.period_s:g} s, displacement {disp}")
    lines.append(f"model     {profile.model_path}" + ("" if profile.model_path.exists() else
                                                       " (not found: create it with `cncgw identify`)"))
    if profile.devices:
        lines.append(f"devices   {len(profile.devices)}: " +
                     ", ".join(f"{d.name} ({d.driver})" for d in profile.devices))
        from drivers import registry

        for d in profile.devices:
            chans = profile.channels_of(d.name)
            names = [c.name for c in chans]
            budget = registry.link_budget(d.driver, d.options, [c.address for c in chans]) if chans else None
            need = f" (the link needs {budget.min_period_s * 1000:.3g} ms a scan)" if budget else ""
            lines.append(f"  {d.name}: {d.driver}, every {d.period_s * 1000:g} ms{need}, {len(names)} channel"
                         f"{'s' if len(names) != 1 else ''}" + (f": {', '.join(names)}" if names else ""))
        lines.append(f"channels  {len(profile.channels)}: " + ", ".join(c.name for c in profile.channels))
        disp = profile.sampling.displacement_channels
        if disp:
            lines.append(f"displacement bursts of {profile.sampling.burst_s:g} s at each window's end: "
                         + ", ".join(f"{a}={c}" for a, c in disp.items())
                         + (f" (whole revolutions of {profile.sampling.burst_speed_channel})"
                            if profile.sampling.burst_speed_channel else ""))
    else:
        lines.append("devices   none (offline profile: recordings only)")
    lines.append(_compensation_line(profile))
    return "\n".join(lines)


def _plausible(a: Any) -> str:
    """The profile's tightening of an axis's plausibility bounds, for the summary line."""
    bounds = [f"|estimate| {a.plausible_um:g} um" if a.plausible_um is not None else "",
              f"a change of {a.plausible_change_um:g} um a window" if a.plausible_change_um is not None else ""]
    bounds = [b for b in bounds if b]
    return f"; held beyond {' or '.join(bounds)}" if bounds else ""


def _compensation_line(profile: Profile) -> str:
    c = profile.compensation
    if not c.enabled:
        return "compensation off (dry run)"
    axes = ", ".join(f"{a.axis} {'-' if a.sign < 0 else '+'}estimate -> holding {a.register} ({a.data_type}, "
                     f"{a.unit_um:g} um{_plausible(a)})" for a in c.axes)
    return (f"compensation ENABLED: writes to the CNC at {c.host}:{c.port}: {axes}; limit {c.limit_um:g} um, "
            f"step {c.max_step_um:g} um, deadband {c.deadband_um:g} um, on fault {c.on_fault}")
