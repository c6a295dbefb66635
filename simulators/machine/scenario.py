"""Scenarios: what the simulated machine does, read from TOML and checked before anything runs.

A scenario file::

    [scenario]
    name = "spindle-1000rpm"          # default: the file name
    description = "..."
    seed = 1                          # sensor noise; same seed, same recording
    initial_idle_min = 30             # at rest before the first segment
    duration_h = 12                   # default: idle + segments; the rest is at rest
    start_time_s = 0                  # time stamp of the start in the recording's time column (e.g. Unix
                                      # time, as an exported recording carries); the physics ignores it

    [room]
    temperature_c = 20.0              # constant unless [effects.room_cycle] is on
    thermometer = false               # record a room_c column

    [sensors]
    noise_um = 0.1                    # white noise of each displacement sensor

    [plant]
    variant = 0                       # 0: the nominal machine; N > 0: gains and time constants perturbed
                                      # by seed N (simulators/machine/variants.py)
    viscous_drag_scale = 1.0          # times every viscous drag (spindle and feed axes: torque and heat)

    [segments.run]                    # segments run in file order
    minutes = 60
    spindle_rpm = 1000                # or [400, 600] with changes_per_min = 350 (alternate)
    stroke_mm = { x = 120, y = 160 }  # reciprocate along this vector (one axis or a diagonal)
    feed_mm_min = 6000                # path feed rate
    accel_m_s2 = 2.0                  # path acceleration (default: the axes' limit)
    dwell_s = 0.0                     # pause at each end of a stroke
    cutting_kw = 0.0                  # cutting power at the spindle while at speed (default 0: no cut);
                                      # its torque P / w at the commanded speed raises the motor currents

    [effects.eddy_loss]               # switch an effect on (see simulators/machine/effects.py)
    loss_w_at_1000rpm = 15

A scenario is named by a path or by the name of a bundled file in ``simulators/scenarios/``. Every
problem is reported at once, each with file, line, key path, bad value and what was expected.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

from gateway.errors import SimulationError, did_you_mean
from gateway.tomlcheck import NAME, Table, TomlDoc, describe
from simulators.machine.effects import EFFECTS, Effects, parse_effect
from simulators.machine.params import AXES, DEFAULT_MACHINE, RAD_PER_RPM, MachineParams, SpindleParams

BUNDLED_PACKAGE = "simulators.scenarios"


@dataclass(frozen=True, kw_only=True)
class Segment:
    """One stretch of the schedule. No speed and no stroke is a stretch at rest."""

    name: str
    start_s: float
    duration_s: float
    #: one speed, or several taken in turn every ``60 / changes_per_min`` seconds
    spindle_rpm: tuple[float, ...] = (0.0,)
    changes_per_min: float = 0.0
    #: reciprocating stroke per axis (x, y, z), mm; the first stroke goes this way, the next back
    stroke_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    feed_mm_min: float = 0.0
    accel_m_s2: float = 0.0
    dwell_s: float = 0.0
    #: cutting power taken at the spindle once it runs at its commanded speed (W); 0: no cut
    cutting_w: float = 0.0

    @property
    def end_s(self) -> float:
        return self.start_s + self.duration_s

    @property
    def moves(self) -> bool:
        return any(s != 0.0 for s in self.stroke_mm)


@dataclass(frozen=True, kw_only=True)
class Room:
    """The workshop: base air temperature and whether a room thermometer is recorded."""

    temperature_c: float = 20.0
    thermometer: bool = False


@dataclass(frozen=True, kw_only=True)
class Scenario:
    """A checked scenario: schedule, room, sensors and switched-on effects."""

    name: str
    description: str = ""
    source: str = ""
    seed: int = 0
    duration_s: float
    initial_idle_s: float = 0.0
    segments: tuple[Segment, ...] = ()
    room: Room = field(default_factory=Room)
    noise_um: float = 0.1
    effects: Effects = field(default_factory=Effects)
    #: time stamp of the run's start in a recording's time column (s); the physics ignores it
    start_time_s: float = 0.0
    #: plant variant (``[plant] variant``): 0 is the nominal machine (see :mod:`simulators.machine.variants`)
    variant: int = 0
    #: ``[plant] viscous_drag_scale``: every viscous drag (its torque and its ~ speed^2 heat) times this
    viscous_drag_scale: float = 1.0

    @property
    def duration_h(self) -> float:
        return self.duration_s / 3600.0

    @property
    def thermometers(self) -> tuple[str, ...]:
        """The temperature columns its recordings carry: ``room_c`` (a room thermometer), ``cabinet_c``."""
        cab = self.effects.cabinet
        return (*(("room_c",) if self.room.thermometer else ()),
                *(("cabinet_c",) if cab is not None and cab.thermometer else ()))


# --------------------------------------------------------------------------------------------------------
def bundled_scenarios() -> list[str]:
    """Names of the scenarios shipped in ``simulators/scenarios/``."""
    root = resources.files(BUNDLED_PACKAGE)
    return sorted(p.name[:-5] for p in root.iterdir() if p.name.endswith(".toml"))


def scenario_path(name_or_path: str | Path) -> Path:
    """The file a scenario argument means: an existing path, else a bundled scenario's name."""
    text = str(name_or_path)
    path = Path(text)
    if path.is_file():
        return path
    if path.suffix == ".toml" or "/" in text or "\\" in text:
        raise SimulationError(f"{path}: file not found")
    names = bundled_scenarios()
    if text not in names:
        raise SimulationError(f'no scenario "{text}": expected a TOML file or a bundled scenario, one of: '
                              f"{', '.join(names)}{did_you_mean(text, names)}")
    return Path(str(resources.files(BUNDLED_PACKAGE) / f"{text}.toml"))


def load_scenario(name_or_path: str | Path, *, machine: MachineParams = DEFAULT_MACHINE) -> Scenario:
    """Read and check a scenario named by path or bundled name.

    Raise :class:`SimulationError` listing every problem.
    """
    path = scenario_path(name_or_path)
    return parse_scenario(TomlDoc(path, error=SimulationError), machine=machine)


def parse_scenario_text(text: str, *, source: str = "<scenario>",
                        machine: MachineParams = DEFAULT_MACHINE) -> Scenario:
    """Check a scenario given as TOML text (``source`` names it in messages)."""
    return parse_scenario(TomlDoc(source, error=SimulationError, text=text), machine=machine)


def parse_scenario(doc: TomlDoc, *, machine: MachineParams = DEFAULT_MACHINE) -> Scenario:
    """Check a parsed TOML document and build the :class:`Scenario`."""
    root = doc.root
    head = root.table("scenario")
    name, description, seed, idle_min, duration_h, start_time = doc.path.stem, "", 0, 0.0, None, 0.0
    if head is not None:
        name = head.str("name", default=name) or name
        description = head.str("description", default="") or ""
        seed = head.int("seed", default=0, min=0)
        idle_min = head.float("initial_idle_min", default=0.0, min=0.0, max=1e6)
        duration_h = head.float("duration_h", default=None, min=0.0, min_exclusive=True, max=24 * 365)
        start_time = head.float("start_time_s", default=0.0, min=0.0, max=1e11) or 0.0
        head.done()

    room = Room()
    room_t = root.table("room")
    if room_t is not None:
        room = Room(temperature_c=room_t.float("temperature_c", default=20.0, min=-20.0, max=60.0) or 20.0,
                    thermometer=bool(room_t.bool("thermometer", default=False)))
        room_t.done()

    noise_um = 0.1
    sensors_t = root.table("sensors")
    if sensors_t is not None:
        noise = sensors_t.float("noise_um", default=0.1, min=0.0, max=100.0)
        noise_um = 0.1 if noise is None else noise
        sensors_t.done()

    variant, viscous_drag_scale = 0, 1.0
    plant_t = root.table("plant")
    if plant_t is not None:
        variant = plant_t.int("variant", default=0, min=0) or 0
        scale = plant_t.float("viscous_drag_scale", default=1.0, min=0.001, max=10.0)
        viscous_drag_scale = 1.0 if scale is None else scale
        plant_t.done()

    t = (idle_min or 0.0) * 60.0
    segments = []
    for seg_name, seg_t in _named_tables(root, "segments"):
        seg = _parse_segment(seg_name, seg_t, t, machine)
        if seg is not None:
            segments.append(seg)
            t = seg.end_s
    if "segments" not in root and head is not None and duration_h is None:
        root.problem("segments", "no schedule: expected [segments.NAME] tables or [scenario] duration_h")

    effects = _parse_effects(root, machine)
    window = machine.window_s
    # without an explicit length the run ends at rest at the next whole window
    duration_s = math.ceil(t / window - 1e-9) * window if duration_h is None else duration_h * 3600.0
    if duration_h is not None and duration_s + 1e-9 < t:
        doc.problem(("scenario", "duration_h"),
                    f"expected at least the schedule's {t / 3600.0:g} h (idle + segments), got {duration_h!r}")
    derived_from_broken_segments = duration_h is None and bool(doc.problems)
    if not derived_from_broken_segments and (
            duration_s < window or abs(duration_s / window - round(duration_s / window)) > 1e-9):
        where = ("scenario", "duration_h") if duration_h is not None else ("segments",)
        doc.problem(where, f"expected a run of whole {window:g} s windows (at least one), got "
                           f"{duration_s:g} s")
    root.done()
    doc.raise_problems()
    return Scenario(name=name, description=description, source=str(doc.path), seed=seed,
                    duration_s=duration_s, initial_idle_s=(idle_min or 0.0) * 60.0, segments=tuple(segments),
                    room=room, noise_um=noise_um, effects=effects, start_time_s=start_time, variant=variant,
                    viscous_drag_scale=viscous_drag_scale)


def _named_tables(root: Table, key: str) -> list[tuple[str, Table]]:
    """``[key.NAME]`` tables in file order (``Table.tables`` cannot iterate its table on this branch)."""
    outer = root.table(key)
    if outer is None:
        return []
    out = []
    for name in outer.data:
        sub = outer.table(name, expected=f"a table [{key}.{name}]")
        if sub is None:
            continue
        if not NAME.fullmatch(name):
            outer.problem(name, f'bad name "{name}": expected letters, digits and "_", starting with a letter')
            continue
        out.append((name, sub))
    return out


def _parse_segment(name: str, t: Table, start_s: float, machine: MachineParams) -> Segment | None:
    minutes = t.float("minutes", min=0.0, min_exclusive=True, max=1e6)
    sp = machine.spindle
    speeds, rate = _parse_speeds(t, sp.max_speed_rpm)
    stroke = (0.0, 0.0, 0.0)
    bad_stroke = False
    stroke_t = t.table("stroke_mm", expected="a table of axes such as { x = 120, y = 160 }")
    if stroke_t is not None:
        values = [stroke_t.float(a, default=0.0, min=-machine.axes[a].travel_mm, max=machine.axes[a].travel_mm,
                                 expected=f"a stroke in mm within the {a.upper()} travel of "
                                          f"{machine.axes[a].travel_mm:g} mm (either way)") for a in AXES]
        stroke_t.done()
        bad_stroke = any(v is None for v in values)
        stroke = tuple(v or 0.0 for v in values)
        if not bad_stroke and not any(stroke):
            t.problem("stroke_mm", "expected a non-zero stroke on at least one axis, got all zero")
    moving = any(stroke) or bad_stroke
    feed = t.float("feed_mm_min", default=None if moving else 0.0, min=0.0, min_exclusive=True, max=1e5)
    accel = t.float("accel_m_s2", default=0.0, min=0.0, min_exclusive=True, max=100.0)
    dwell = t.float("dwell_s", default=0.0, min=0.0, max=3600.0)
    cutting_kw = t.float("cutting_kw", default=0.0, min=0.0, max=1000.0)
    if cutting_kw and speeds is not None:
        cutting_kw = _check_cut(t, cutting_kw, speeds, machine)
    if not moving:
        for key in ("feed_mm_min", "accel_m_s2", "dwell_s"):
            if key in t:
                t.problem(key, "given without stroke_mm: expected stroke_mm = { x = ..., ... } as well")
    t.done()
    if minutes is None or speeds is None or bad_stroke or (moving and (feed is None or accel is None or dwell is None)):
        return None
    accel_value = accel or 0.0
    if moving:
        accel_value = _check_motion(t, stroke, feed, accel or None, dwell, minutes * 60.0, machine)
        if accel_value is None:
            return None
    return Segment(name=name, start_s=start_s, duration_s=minutes * 60.0, spindle_rpm=speeds,
                   changes_per_min=rate, stroke_mm=stroke, feed_mm_min=feed or 0.0,
                   accel_m_s2=accel_value, dwell_s=dwell or 0.0, cutting_w=(cutting_kw or 0.0) * 1000.0)


def _check_cut(t: Table, cutting_kw: float, speeds: tuple[float, ...], machine: MachineParams) -> float | None:
    """The cutting power if the spindle can take it at every speed of the segment, else ``None``.

    The cutting torque plus the friction at speed must lie within the drive's torque limit there
    (constant power above base speed).
    """
    sp = machine.spindle
    if min(speeds) <= 0.0:
        t.problem("cutting_kw", f"given for a segment with the spindle at 0 rpm: expected spindle_rpm > 0 "
                                f"with a cut, got cutting_kw = {cutting_kw:g}")
        return None
    for rpm in speeds:
        limit_nm, most_kw = cutting_limit(sp, rpm)
        if cutting_kw > most_kw:
            t.problem("cutting_kw", f"expected a cutting power the spindle can take at {rpm:g} rpm (cutting "
                                    f"torque plus friction <= {limit_nm:.4g} Nm, the drive's limit there: at most "
                                    f"{most_kw:.3g} kW), got {cutting_kw:g}")
            return None
    return cutting_kw


def cutting_limit(sp: SpindleParams, rpm: float) -> tuple[float, float]:
    """(the drive's torque limit at ``rpm`` in Nm, the most cutting power it leaves there in kW).

    The cutting torque plus the friction at speed must lie within the limit (constant power above base speed).
    """
    w = rpm * RAD_PER_RPM
    limit = sp.torque_limit_nm * min(1.0, sp.omega_base / w)
    return limit, (limit - sp.coulomb_nm - sp.viscous_nm_s * w) * w / 1000.0


def _parse_speeds(t: Table, max_rpm: float) -> tuple[tuple[float, ...] | None, float]:
    expected = (f"a speed in rpm in [0, {max_rpm:g}], or an array of such speeds to alternate between "
                f"(with changes_per_min)")
    raw = t.raw("spindle_rpm", default=0.0, expected=expected)
    values = raw if isinstance(raw, list) else [raw]
    ok = all(isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) and 0 <= v <= max_rpm
             for v in values) and (not isinstance(raw, list) or len(raw) >= 2)
    if not ok:
        t.problem("spindle_rpm", f"expected {expected}, got {describe(raw)}")
    rate = t.float("changes_per_min", default=0.0, min=0.0, max=3000.0)
    if isinstance(raw, list) and ok and not rate:
        t.problem("changes_per_min", f"missing: spindle_rpm = {raw!r} alternates, so expected changes_per_min "
                                     "> 0 as well (the paper's 400/600 rpm run: 350)")
        return None, 0.0
    if not isinstance(raw, list) and rate:
        t.problem("changes_per_min", f"given for one speed: expected an array of speeds in spindle_rpm, got "
                                     f"{raw!r}")
        return None, 0.0
    return (tuple(float(v) for v in values) if ok else None), (rate or 0.0)


def _check_motion(t: Table, stroke: tuple[float, ...], feed: float, accel: float | None, dwell: float,
                  duration_s: float, machine: MachineParams) -> float | None:
    """Check the move against the axes' limits; return the path acceleration to use."""
    length = math.sqrt(sum(s * s for s in stroke))
    share = [abs(s) / length for s in stroke]
    axes = [machine.axes[a] for a in AXES]
    max_feed = min(ax.max_feed_mm_min / u for ax, u in zip(axes, share, strict=True) if u > 0)
    max_accel = min(ax.max_accel_m_s2 / u for ax, u in zip(axes, share, strict=True) if u > 0)
    ok = True
    if feed > max_feed * (1 + 1e-12):
        t.problem("feed_mm_min", f"expected a path feed rate <= {max_feed:.6g} mm/min on this stroke (the axes' "
                                 f"rapid traverse), got {describe(t.data['feed_mm_min'])}")
        ok = False
    if accel is not None and accel > max_accel * (1 + 1e-12):
        t.problem("accel_m_s2", f"expected a path acceleration <= {max_accel:.6g} m/s^2 on this stroke (the "
                                f"axes' limit), got {describe(t.data['accel_m_s2'])}")
        ok = False
    a = accel if accel is not None else max_accel
    v = feed / 60000.0
    length_m = length / 1000.0
    t_move = (2 * v / a + (length_m - v * v / a) / v) if length_m >= v * v / a else 2 * math.sqrt(length_m / a)
    cycle = 2 * (t_move + dwell)
    if ok and cycle > duration_s:
        t.problem("minutes", f"expected at least one stroke cycle ({cycle:.6g} s there and back), got "
                             f"{duration_s / 60.0:g} min")
        ok = False
    return a if ok else None


def _parse_effects(root: Table, machine: MachineParams) -> Effects:
    node_names = tuple(n.name for n in machine.nodes)
    outer = root.table("effects")
    if outer is None:
        return Effects()
    on: dict[str, object] = {}
    for name in outer.data:
        if name not in EFFECTS:
            outer.raw(name)
            outer.problem(name, f"unknown effect{did_you_mean(name, EFFECTS)}: expected one of "
                                f"{', '.join(EFFECTS)}")
            continue
        sub = outer.table(name)
        if sub is None:
            continue
        enabled = sub.bool("enabled", default=True)
        value = parse_effect(EFFECTS[name], sub, node_names)
        if name == "cabinet" and value.cooler_w > 0 and not value.cooler_off_k < value.cooler_on_k:
            sub.problem("cooler_off_k", f"expected below cooler_on_k ({value.cooler_on_k:g} K: the thermostat stops "
                                        f"the cooling unit below where it starts it), got {value.cooler_off_k:g}")
        sub.done()
        if enabled:
            on[name] = value
    outer.done()
    return Effects(**on)  # type: ignore[arg-type]
