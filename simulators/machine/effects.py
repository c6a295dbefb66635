"""Switchable physical effects: what the paper's nine-factor model leaves out.

Each effect is off unless a scenario has its ``[effects.NAME]`` table (``enabled = false`` keeps the
parameters but switches it off); recordings never say which are on. Every parameter has a physical meaning
and a default from the same kind of estimate as :mod:`simulators.machine.params`. The ground truth of
each effect's contribution to the displacement is kept by the simulation (see
:class:`simulators.machine.run.SimulationResult`): the displacement with every effect of the scenario
minus the displacement of the same run with that one effect switched off.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

from simulators.machine.params import AXES


def _m(*, min: float | None = None, max: float | None = None, help: str = "",
       min_exclusive: bool = False) -> dict[str, Any]:
    """Field metadata for the scenario checker: bounds and a note."""
    return {"min": min, "max": max, "help": help, "min_exclusive": min_exclusive}


Vec3 = tuple[float, float, float]


@dataclass(frozen=True, kw_only=True)
class RoomCycle:
    """The workshop's air temperature.

    A daily sine plus a linear drift, acting on every node through its conductance to the room (the machine
    starts in the cycle's periodic steady state). With ``heated_h`` > 0 the cycle is a heated hall's instead:
    warm for that many hours a day (centred on ``peak_at_h``), cold the rest, switching within about an hour
    (a rectangle smoothed by a Gaussian of 0.5 h, as a Fourier series: :meth:`harmonics`), with the sine's mean
    and peak-to-peak swing. A room that is no sine: what a daily start fitted with a sine or a few harmonics
    meets in a real hall.
    """

    amplitude_k: float = field(default=1.5, metadata=_m(min=0.0, max=20.0, help="half the daily peak-to-peak swing"))
    period_h: float = field(default=24.0, metadata=_m(min=0.1, min_exclusive=True, max=1000.0))
    peak_at_h: float = field(default=15.0,
                             metadata=_m(min=0.0, max=1000.0, help="hours after the start of the warmest moment"))
    drift_k_per_h: float = field(default=0.0,
                                 metadata=_m(min=-5.0, max=5.0, help="slow change of the mean (weather, heating)"))
    heated_h: float = field(default=0.0, metadata=_m(min=0.0, max=23.0, help="hours a day the hall is heated "
                                                                                "(0: a sine)"))

    def harmonics(self) -> list[tuple[int, float]]:
        """(k, c_k): the room's deviation is sum_k c_k cos(k w (t - peak)), w = 2 pi / period (mean 0)."""
        if self.heated_h <= 0:
            return [(1, self.amplitude_k)]
        duty = self.heated_h / self.period_h
        w = 2.0 * math.pi / (self.period_h * 3600.0)
        out = []
        for k in range(1, 80):
            smooth = math.exp(-0.5 * (k * w * 1800.0) ** 2)
            if smooth < 1e-6:
                break
            # a rectangle of +-A (warm for duty of the period): 4 A / (pi k) sin(pi k duty), smoothed
            out.append((k, 4.0 * self.amplitude_k / (math.pi * k) * math.sin(math.pi * k * duty) * smooth))
        return out


@dataclass(frozen=True, kw_only=True)
class EddyLoss:
    """Iron eddy-current loss ~ speed^2 (the paper neglected it and named it as a likely error source)."""

    loss_w_at_1000rpm: float = field(default=15.0, metadata=_m(min=0.0, max=2000.0, help="at 4000 rpm it is 16 x this"))
    rotor_share: float = field(default=0.2, metadata=_m(min=0.0, max=1.0, help="the part generated in the rotor iron"))


@dataclass(frozen=True, kw_only=True)
class SlowPath:
    """A very slow thermal path.

    A massive part (column base, the concrete under the machine) that soaks up heat from ``from_node`` over
    many hours and moves the tool while it does.
    """

    from_node: str = field(default="head", metadata=_m(help="the node it draws heat from"))
    conductance_w_per_k: float = field(default=5.0, metadata=_m(min=0.0, min_exclusive=True, max=1000.0))
    room_w_per_k: float = field(default=2.0, metadata=_m(min=0.0, max=1000.0))
    time_constant_h: float = field(default=24.0,
                                   metadata=_m(min=12.0, max=1000.0, help="capacity / (conductance + room)"))
    um_per_k: Vec3 = field(default=(0.0, 0.0, 10.0),
                           metadata=_m(help="displacement per kelvin of the slow part's rise"))


@dataclass(frozen=True, kw_only=True)
class Cabinet:
    """Control cabinet and servo amplifiers.

    Losses ~ the sum of the motor currents squared, bolted to the back of the column. With ``cooler_w`` a
    cooling unit under a thermostat (on above ``cooler_on_k`` over the hall, off below ``cooler_off_k``) takes
    heat out while it runs: the cabinet's temperature then saws between the two and no longer follows the
    currents alone.
    """

    w_per_a2: float = field(default=0.3,
                            metadata=_m(min=0.0, max=100.0, help="amplifier loss per A^2 of motor current"))
    capacity_kj_per_k: float = field(default=60.0, metadata=_m(min=0.0, min_exclusive=True, max=1e5))
    room_w_per_k: float = field(default=15.0, metadata=_m(min=0.0, max=1e4, help="heat exchanger and walls"))
    column_w_per_k: float = field(default=6.0, metadata=_m(min=0.0, min_exclusive=True, max=1e4))
    cooler_w: float = field(default=0.0, metadata=_m(
        min=0.0, max=1e4, help="a cooling unit's heat removal while it runs (0: none); a thermostat switches it"))
    cooler_on_k: float = field(default=4.0, metadata=_m(
        min=0.0, min_exclusive=True, max=100.0, help="it starts when the cabinet is this much warmer than the hall"))
    cooler_off_k: float = field(default=2.5, metadata=_m(
        min=0.0, max=100.0, help="and stops when the cabinet has cooled to this much above the hall"))
    thermometer: bool = field(default=False, metadata=_m(
        help="record the cabinet's air temperature as a column, cabinet_c (a thermometer in the cabinet)"))


@dataclass(frozen=True, kw_only=True)
class BearingPreload:
    """Thermal preload.

    The shaft and inner rings run hotter than the housing, the preload grows and the bearing friction heat
    rises with it (a nonlinear feedback).
    """

    gain_per_k: float = field(default=0.01, metadata=_m(min=0.0, max=1.0,
                           help="extra friction heat per kelvin of bearing-over-head temperature"))


@dataclass(frozen=True, kw_only=True)
class CoolantDelay:
    """A coolant loop.

    The stator jacket hands ``fraction`` of the motor's heat to oil that reaches a tank on the back of the
    column after ``delay_s`` of transport.
    """

    fraction: float = field(default=0.5, metadata=_m(min=0.0, max=1.0))
    delay_s: float = field(default=300.0, metadata=_m(min=0.0, max=86400.0))
    tank_capacity_kj_per_k: float = field(default=150.0,
                                          metadata=_m(min=0.0, min_exclusive=True, max=1e5, help="80 l of oil"))
    tank_room_w_per_k: float = field(default=8.0, metadata=_m(min=0.0, max=1e4))
    tank_column_w_per_k: float = field(default=6.0, metadata=_m(min=0.0, min_exclusive=True, max=1e4))


@dataclass(frozen=True, kw_only=True)
class Chiller:
    """A coolant chiller that runs with the spindle.

    A conductance from ``node`` to oil held at room temperature, switched by the spindle and building up
    with the chiller's own time constant.
    """

    node: str = field(default="stator", metadata=_m())
    conductance_w_per_k: float = field(default=15.0, metadata=_m(min=0.0, min_exclusive=True, max=1e4))
    time_constant_s: float = field(default=180.0, metadata=_m(min=0.0, min_exclusive=True, max=86400.0))


@dataclass(frozen=True, kw_only=True)
class SensorArtefacts:
    """What the displacement sensors add.

    A step at one moment (a knock, a re-zeroing), a linear drift (the sensor's own temperature) and extra
    white noise.
    """

    step_at_h: float = field(default=6.0, metadata=_m(min=0.0))
    step_um: Vec3 = field(default=(0.0, 0.0, 0.0), metadata=_m())
    drift_um_per_h: Vec3 = field(default=(0.0, 0.0, 0.0), metadata=_m())
    noise_um: float = field(default=0.0, metadata=_m(min=0.0, max=100.0))


#: ``[effects.NAME]`` -> its parameter class
EFFECTS: dict[str, type] = {
    "room_cycle": RoomCycle,
    "eddy_loss": EddyLoss,
    "slow_path": SlowPath,
    "cabinet": Cabinet,
    "bearing_preload": BearingPreload,
    "coolant_delay": CoolantDelay,
    "chiller": Chiller,
    "sensor_artefacts": SensorArtefacts,
}


@dataclass(frozen=True, kw_only=True)
class Effects:
    """The effects a scenario switches on (``None``: off)."""

    room_cycle: RoomCycle | None = None
    eddy_loss: EddyLoss | None = None
    slow_path: SlowPath | None = None
    cabinet: Cabinet | None = None
    bearing_preload: BearingPreload | None = None
    coolant_delay: CoolantDelay | None = None
    chiller: Chiller | None = None
    sensor_artefacts: SensorArtefacts | None = None

    @property
    def enabled(self) -> tuple[str, ...]:
        return tuple(name for name in EFFECTS if getattr(self, name) is not None)

    def without(self, name: str) -> Effects:
        """The same effects with ``name`` switched off."""
        return dataclasses.replace(self, **{name: None})


def parse_effect(cls: type, table: Any, node_names: tuple[str, ...]) -> Any:
    """Read one ``[effects.NAME]`` table into ``cls`` with the typed getters (every problem recorded)."""
    values: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        meta = f.metadata
        if isinstance(f.default, bool):
            value = table.bool(f.name, default=f.default)
        elif isinstance(f.default, str):
            value = table.str(f.name, default=f.default, choices=node_names)
        elif isinstance(f.default, tuple):
            value = _vec3(table, f.name, f.default)
        else:
            value = table.float(f.name, default=f.default, min=meta["min"], max=meta["max"],
                                 min_exclusive=meta["min_exclusive"])
        if value is not None:
            values[f.name] = value
    return cls(**values)


def _vec3(table: Any, key: str, default: Vec3) -> Vec3:
    """``{ x = .., y = .., z = .. }`` (missing axes are 0)."""
    sub = table.table(key, expected="a table of axes such as { x = 0.0, y = 0.0, z = 1.5 }")
    if sub is None:
        return default
    out = tuple(sub.float(a, default=0.0) for a in AXES)
    sub.done()
    return tuple(0.0 if v is None else v for v in out)  # type: ignore[return-value]


def describe_effects() -> str:
    """Every effect with its parameters and defaults (for ``cncgw simulate list --effects``)."""
    lines = []
    for name, cls in EFFECTS.items():
        lines.append(f"[effects.{name}]  {(cls.__doc__ or '').split(chr(10))[0]}")
        for f in dataclasses.fields(cls):
            note = f.metadata.get("help", "")
            lines.append(f"  {f.name} = {_toml(f.default)}" + (f"  # {note}" if note else ""))
    return "\n".join(lines)


def _toml(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, tuple):
        return "{ " + ", ".join(f"{a} = {v!r}" for a, v in zip(AXES, value, strict=True)) + " }"
    if isinstance(value, str):
        return f'"{value}"'
    return repr(value)
