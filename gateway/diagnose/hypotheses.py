"""Hypotheses of missing physics, each a model extension of the same transfer-function type.

A :class:`Hypothesis` has a physical name, an explanation a machine-tool engineer recognises, and per axis
a grid of :class:`Setting` s: the nonlinear parameters (time constants, dead times, which existing path
shape a new heat source shares) with the components whose gains are fitted linearly. Accepted, a setting
becomes derived inputs and path terms (:mod:`gateway.diagnose.extend`).

Where the physics says WHERE a missing heat source sits, the hypothesis reuses the identified path of the
heat already known to be there, with one gain: iron eddy loss is generated in the motor iron beside the
stator copper, so it moves the tool as the stator current's heat does; extra bearing friction from thermal
preload moves it as the speed's (bearing friction) heat does. One gain instead of a free path makes these
hypotheses cheap to test and tells them apart by their dynamics.

Measurement artefacts (a sensor's drift) are hypotheses too, flagged ``artefact``: they enter the fits as
nuisance columns and never the model.
"""

from __future__ import annotations

import functools
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from gateway.diagnose.data import Component, Part, Stack, lag, log_grid
from gateway.model.inputs import DAILY_HARMONICS, DAY_S, Column, DerivedInput, Flag, Periodic, Product, Sum
from gateway.model.model import ThermalModel
from gateway.model.terms import FirstOrder, SecondOrder

#: names of recorded columns taken to be the room (ambient) temperature
ROOM_NAMES = re.compile(r"(room|ambient|amb\b|ambi|umgebung|hall|air|t_?amb)", re.IGNORECASE)
#: a static path is a lag far shorter than any window: the periodic disturbance's lag is in its phase
STATIC_TAU_S = 1.0


@dataclass(frozen=True)
class FactorInfo:
    """What diagnosis needs to know about a profile factor."""

    name: str
    unit: str = ""
    stat: str = "mean"
    description: str = ""

    @property
    def group(self) -> str:
        """The drive it belongs to: the name's first word (spindle, x, y, z)."""
        return self.name.split("_")[0]

    @property
    def is_speed(self) -> bool:
        return self.stat == "mean" and self.unit.lower().replace(" ", "") in ("rpm", "1/min", "min^-1", "r/min")

    @property
    def is_current_sq(self) -> bool:
        return self.stat == "mean_square"

    @property
    def is_rotor(self) -> bool:
        text = f"{self.name} {self.description}".lower()
        return "rotor" in text or "secondary" in text or re.search(r"(^|_)i2(_|$)", self.name) is not None


@dataclass(frozen=True)
class Setting:
    """One point of a hypothesis's grid on one axis."""

    params: tuple[tuple[str, float | str], ...]
    components: tuple[Component, ...]
    chain: tuple[DerivedInput, ...] = ()
    #: nuisance columns: ("decay", tau_s) unknown initial state of a mode, ("ramp", 0) a sensor's drift,
    #: ("ramp", tau_s) a slow drift of the surroundings through a lag, one per recording
    nuisance: tuple[tuple[str, float], ...] = ()
    #: required sign of each component's gain (+1, -1; 0: any)
    signs: tuple[int, ...] = ()
    #: largest plausible |gain| of each component (inf: no bound)
    limits: tuple[float, ...] = ()

    def param(self, name: str) -> float | str | None:
        return dict(self.params).get(name)


@dataclass(frozen=True)
class Hypothesis:
    """A named piece of missing physics (or a measurement artefact) with its grid per axis."""

    key: str
    family: str
    title: str
    explanation: str
    settings: dict[str, list[Setting]] = field(hash=False, compare=False)
    artefact: bool = False
    #: nested simpler hypotheses: preferred unless this one is significantly better
    simpler: tuple[str, ...] = ()
    #: machine-wide parameters (a transport delay, a bearing's time constant): one value for every axis
    shared: tuple[str, ...] = ()
    #: the recorded column a hypothesis of unknown meaning rests on ("" for the rest)
    signal: str = ""
    #: a structural change of an identified path (an extra mode, a dead time) rather than a named mechanism:
    #: it can mimic most slow heat sources, so it counts one parameter more when hypotheses are ranked
    generic: bool = False
    #: what would tell it apart from a factor's path when these recordings cannot (see diagnose.confusable)
    tell_apart: str = ""

    @functools.cached_property
    def complexity(self) -> int:
        """Free parameters: the most gains of any setting plus every parameter the grid varies."""
        n = 0
        for grid in self.settings.values():
            gains = max((len(s.components) for s in grid), default=0)
            # one pass over the grid (a grid has hundreds of settings; the report asks for every trial's)
            values: dict[str, set] = {}
            holders: dict[str, int] = {}
            for s in grid:
                params = dict(s.params)
                for k, v in params.items():
                    values.setdefault(k, set()).add(v)
                    holders[k] = holders.get(k, 0) + 1
            # varied: two values, or present in some settings only
            varied = [k for k, vs in values.items() if len(vs) > 1 or holders[k] < len(grid)]
            n = max(n, gains + len(varied))
        return n


def _tau_text(t: float) -> str:
    return f"{t / 60:.3g} min" if t < 5400 else f"{t / 3600:.3g} h"


def safe_name(text: str, taken: Sequence[str]) -> str:
    """A model input name (letters, digits, _) for a recorded column, not clashing with ``taken``."""
    name = re.sub(r"[^A-Za-z0-9_]+", "_", text).strip("_") or "column"
    if not name[0].isalpha():
        name = "c_" + name
    while name in taken:
        name += "_"
    return name


def catalogue(stack: Stack, model: ThermalModel, factors: Sequence[FactorInfo], *,
              families: Sequence[str] | None = None) -> list[Hypothesis]:
    """Every hypothesis that can be tested on these recordings with this model and profile."""
    info = {f.name: f for f in factors}
    for f in model.factors:
        info.setdefault(f, FactorInfo(name=f, unit=model.units.get(f, "")))
    span = [float(np.nanmax(np.abs(stack.du[f]))) if stack.n else 0.0 for f in model.factors]
    active = [f for f, s in zip(model.factors, span, strict=True) if s > 0]
    ctx = _Ctx(stack=stack, model=model, info=info, active=active)
    makers = {
        "room_recorded": _room_recorded, "recorded_signal": _recorded_signal, "room_daily": _room_daily,
        "eddy_loss": _eddy, "bearing_preload": _preload, "cabinet": _cabinet, "chiller": _chiller,
        "slow_mode": _slow_mode, "higher_order": _higher_order, "dead_time": _dead_time,
        "sensor_drift": _sensor_drift,
    }
    out: list[Hypothesis] = []
    for fam, make in makers.items():
        if families is None or fam in families:
            out += [h for h in make(ctx) if any(h.settings.values())]
    return out


@dataclass
class _Ctx:
    stack: Stack
    model: ThermalModel
    info: dict[str, FactorInfo]
    active: list[str]

    @property
    def axes(self) -> tuple[str, ...]:
        return self.model.axes

    @property
    def dt(self) -> float:
        return self.stack.dt_s

    def base_terms(self, axis: str, factor: str) -> tuple:
        return self.model.path(axis, factor).terms

    def taken(self) -> list[str]:
        return list(self.model.input_names)


# ---------------------------------------------------------------------------------------------- families --
def _lag_pairs(lo1: float, hi1: float, lo2: float, hi2: float) -> list[tuple[float, float | None]]:
    """Single lags and pairs (fast, slow) at least a factor 3 apart."""
    fast = log_grid(lo1, hi1, 3)
    slow = log_grid(lo2, hi2, 3)
    out: list[tuple[float, float | None]] = [(t, None) for t in log_grid(lo1, hi2, 5)]
    out += [(a, b) for a in fast for b in slow if b >= 3 * a]
    return out


def _column_settings(ctx: _Ctx, col: str, *, start: str = "settled") -> list[Setting]:
    inp = Column(name=safe_name(col, ctx.taken()), column=col, unit="", note=f"recorded column {col}", start=start)
    out = []
    # a casting follows the room within hours, a massive bed within a day: longer lags would only fit a
    # drift and extrapolate it
    for t1, t2 in _lag_pairs(ctx.dt, 4 * 3600.0, 2 * 3600.0, DAY_S):
        comps = [Component((Part(inp.name, lag(t1)),), f"lag {_tau_text(t1)}")]
        params: list[tuple[str, float | str]] = [("tau_s", t1)]
        nuis = [("decay", t1)]
        if t2 is not None:
            comps.append(Component((Part(inp.name, lag(t2)),), f"lag {_tau_text(t2)}"))
            params = [("tau_fast_s", t1), ("tau_slow_s", t2)]
            nuis.append(("decay", t2))
        out.append(Setting(params=tuple(params), components=tuple(comps), chain=(inp,), nuisance=tuple(nuis)))
    return out


#: a recorded column is tried as an input where it has values in at least this share of the windows, in two
#: recordings at least (all there are, if fewer). Where a recording lacks it, its hypotheses take it as constant
#: there, as the identified model does: a room thermometer on the production days only (47 % of the windows
#: beside nine experiments) was not tried at 50 %, and the room's drift went to a slow mode of the spindle
MIN_COLUMN_SHARE = 0.25
MIN_COLUMN_RECORDINGS = 2


def _recorded_in(stack: Stack, v: np.ndarray) -> list[int]:
    return [r for r, (a, b) in enumerate(stack.bounds) if np.isfinite(v[a:b]).any()]


def _usable(stack: Stack, col: str) -> bool:
    v = stack.extras[col]
    return (np.isfinite(v).sum() >= MIN_COLUMN_SHARE * len(v) and stack.is_signal(col)
            and len(_recorded_in(stack, v)) >= min(MIN_COLUMN_RECORDINGS, len(stack.bounds)))


def _usable_columns(ctx: _Ctx) -> list[str]:
    return [col for col in ctx.stack.extras if _usable(ctx.stack, col)]


def partial_columns(stack: Stack) -> list[str]:
    """Sentences on the recorded signals some recordings lack: too sparse to be tried, or taken as constant there."""
    out = []
    for col, v in stack.extras.items():
        have = _recorded_in(stack, v)
        if not have or len(have) == len(stack.bounds) or not stack.is_signal(col):
            continue
        share = float(np.isfinite(v).mean())
        where = (f"column {col} is recorded in {len(have)} of {len(stack.bounds)} recordings ({100 * share:.0f} % of "
                 f"the windows: {', '.join(stack.labels[r] for r in have[:4])}{', ...' if len(have) > 4 else ''})")
        if _usable(stack, col):
            out.append(where + ": its hypotheses take it as constant in the others, as the identified model does, "
                       "and a model written with it needs it in every recording it estimates; record it in every "
                       "recording, the identification experiments too")
            continue
        out.append(where + ": no hypothesis on it was tried (it needs values in at least "
                   f"{100 * MIN_COLUMN_SHARE:.0f} % of the windows, in {MIN_COLUMN_RECORDINGS} recordings at least); "
                   "record it in every recording, the identification experiments too, or diagnose the recordings "
                   "that have it on their own")
    return out


def _room_recorded(ctx: _Ctx) -> list[Hypothesis]:
    return [Hypothesis(
        key=f"room_recorded:{col}", family="room_recorded", title=f"room temperature (recorded as {col})",
        explanation=(f"The workshop air ({col}) heats and cools the whole structure through its surfaces; the "
                     "model has no input for it. It acts through lags (hours for a casting), so the "
                     "displacement follows the room late and smoothed. The room did not start with a recording: "
                     "its paths start as if it had cycled before it as in the recording's first day."),
        # the room cycled before each recording as it does in it: its paths start so, not settled (the days
        # before it run first, in estimate too: see gateway.model.inputs.daily_start)
        settings={a: _column_settings(ctx, col, start="daily") for a in ctx.axes})
        for col in _usable_columns(ctx) if ROOM_NAMES.search(col)]


def _recorded_signal(ctx: _Ctx) -> list[Hypothesis]:
    return [Hypothesis(
        key=f"recorded_signal:{col}", family="recorded_signal", title=f"recorded signal {col} (meaning unknown)",
        explanation=(f"Column {col} is recorded but not a model input; if the displacement follows it "
                     "through a lag, it carries heat (or is a temperature of a part) the factors miss. "
                     "Its meaning must be checked on the machine before it is used in production."),
        settings={a: _column_settings(ctx, col) for a in ctx.axes}, signal=col)
        for col in _usable_columns(ctx) if not ROOM_NAMES.search(col)]


#: the share of the day a daily cycle is tried on: in one recording, or on the clock the recordings cover together
DAY_SHOWN = 0.75


def shows_the_day(stack: Stack) -> bool:
    """Whether a daily cycle can be told from a drift on these recordings.

    Most of a day in one recording, or on the clock the recordings cover together with the longest a quarter of
    a day at least (days cut at 10 h beside experiments run at other hours show the whole day between them, each
    recording's own drift fitted apart: bench/diagnose.py --cut-days 10, the room not recorded, sine and heated
    hall v1-v3, named in 6 of 6 where it was tried in none).
    """
    span = max((b - a for a, b in stack.bounds), default=0) * stack.dt_s
    return span >= DAY_SHOWN * DAY_S or (stack.longest_s() >= DAY_S / 4 and stack.day_covered() >= DAY_SHOWN)


def _room_daily(ctx: _Ctx) -> list[Hypothesis]:
    if not shows_the_day(ctx.stack):
        return []  # a daily cycle cannot be told from a drift
    if any(ROOM_NAMES.search(col) and len(_recorded_in(ctx.stack, ctx.stack.extras[col])) == len(ctx.stack.bounds)
           for col in _usable_columns(ctx)):
        return []  # the room is recorded: its thermometer says more than any guess of its shape
    # ... recorded in some recordings only, the time of day is known in all of them: both are tried (the bench's
    # "room recorded on days": the thermometer's model predicted the fresh day 2.3-4.9 um pooled RMS, the daily
    # cycle's 0.3-0.9 um, as it had before the thermometer was tried at all)
    static = (FirstOrder(gain=1.0, tau_s=STATIC_TAU_S),)

    def grid(harmonics: int) -> list[Setting]:
        chain: list[Periodic] = []
        comps: list[Component] = []
        for k in range(1, harmonics + 1):
            tag = "day" if k == 1 else f"day{k}"
            for phase in ("sin", "cos"):
                p = Periodic(name=f"{tag}_{phase}", period_s=DAY_S / k, phase=phase,
                             note="time of day (daily room cycle)" if k == 1 else
                             f"time of day (daily room cycle, harmonic {k})")
                chain.append(p)
                comps.append(Component((Part(p.name, static),), phase if k == 1 else f"{phase} {k}"))
        head: tuple[tuple[str, float | str], ...] = (("period_h", 24.0),) + (
            (("harmonics", float(harmonics)),) if harmonics > 1 else ())
        # the room's mean moves with the weather too: a drift of its own in every recording, through the lag of
        # the structure, which no recording's neighbour predicts (a nuisance: fitted, never written)
        out = [Setting(params=(*head, ("drift_tau_s", "none")), chain=tuple(chain), components=tuple(comps))]
        out += [Setting(params=(*head, ("drift_tau_s", tau)), chain=tuple(chain), components=tuple(comps),
                        nuisance=(("ramp", tau),)) for tau in (0.0, 4 * 3600.0, 12 * 3600.0)]
        return out

    sine = grid(1)
    explained = ("The workshop warms by day and cools by night; without a thermometer the model can "
                 "still take it as a 24 h periodic disturbance: in its periodic steady state any lag "
                 "only shifts the phase, so a sine and a cosine of the time of day describe it. The "
                 "room's mean drifts with the weather as well, differently every day: that part is "
                 "fitted per recording (a drift through the structure's lag) and cannot be predicted "
                 "without a thermometer.")
    # a hall heated by day (9-21 h) is no sine: the day's first harmonics, each with a gain and a phase of its
    # own (in the periodic steady state a lag shifts and scales each). Nested: taken over the sine only where it
    # predicts the held-out blocks significantly better (a sine hall fitted with three harmonics wrote six
    # inputs and gained nothing on the fresh day)
    harmonics = grid(DAILY_HARMONICS)  # as many as a recorded thermometer's daily start fits
    return [
        Hypothesis(key="room_daily", family="room_daily", title="daily room-temperature cycle (not recorded)",
                   explanation=explained, settings={a: sine for a in ctx.axes}),
        Hypothesis(key=f"room_daily:{DAILY_HARMONICS}_harmonics", family="room_daily",
                   title=f"daily room-temperature cycle, not a sine ({DAILY_HARMONICS} harmonics; not recorded)",
                   explanation=explained + (f" A hall heated by day is no sine: the day's first {DAILY_HARMONICS} "
                                            "harmonics, each with a gain and a phase of its own, are tried as well "
                                            "and taken only where they predict significantly better than the "
                                            "sine."),
                   settings={a: harmonics for a in ctx.axes}, simpler=("room_daily",)),
    ]


def _motor_shapes(ctx: _Ctx, axis: str, speed: str, *, stator_only: bool = False) -> list[str]:
    """Current factors of the speed's drive with a path on ``axis``: where the motor's heat acts."""
    group = ctx.info[speed].group
    return [f for f in ctx.model.factors if ctx.info[f].group == group and ctx.info[f].is_current_sq
            and ctx.base_terms(axis, f) and not (stator_only and ctx.info[f].is_rotor)]


def _eddy(ctx: _Ctx) -> list[Hypothesis]:
    out = []
    for n in (f for f in ctx.active if ctx.info[f].is_speed):
        sq = Product(name=safe_name(f"{n}_sq", ctx.taken()), of=(n, n), unit=f"({ctx.info[n].unit})^2",
                     note=f"{n} squared: iron eddy-current loss and viscous friction ~ speed^2")
        settings: dict[str, list[Setting]] = {}
        for a in ctx.axes:
            # in the motor's iron (eddy loss: where the motor current's heat acts; a free lag where the profile
            # does not say which current is the motor's) or in the bearings (viscous friction: where the speed's
            # own friction heat acts)
            motor = _motor_shapes(ctx, a, n)
            shapes = [*motor, *([n] if motor and ctx.base_terms(a, n) else [])]
            grid = [Setting(params=(("path_shape", f),), chain=(sq,),
                            components=(Component((Part(sq.name, ctx.base_terms(a, f)),), f"as {f}"),), signs=(1,))
                    for f in shapes]
            if not motor:  # where the motor's heat acts is unknown: a free lag (one place-parameter either way)
                grid = [Setting(params=(("tau_s", t),), chain=(sq,), components=(Component((Part(sq.name, lag(t)),)),))
                        for t in log_grid(5 * ctx.dt, 12 * 3600.0, 4)]
            settings[a] = grid
        out.append(Hypothesis(
            key=f"eddy_loss:{n}", family="eddy_loss", title=f"heat ~ {n}^2 (iron eddy-current loss, viscous friction)",
            explanation=("Eddy currents in the motor's iron dissipate heat ~ speed^2 (hysteresis ~ speed is "
                         "already in the speed factor); the paper neglected it. The heat is made in the motor "
                         "iron beside the stator winding, so it moves the tool as the motor current's heat does "
                         "(path shape: a current's). Viscous friction (bearing grease, oil-air churning, air in the "
                         "gap) also grows ~ speed^2; in the bearings it moves the tool as the speed's own friction "
                         "heat does (path shape: the speed's). Which place fits better is the path shape chosen."),
            settings=settings))
    return out


def _preload(ctx: _Ctx) -> list[Hypothesis]:
    out = []
    for n in (f for f in ctx.active if ctx.info[f].is_speed):
        settings: dict[str, list[Setting]] = {}
        for a in ctx.axes:
            shape = ctx.base_terms(a, n)
            grid = []
            if shape:
                # a lag of one window is speed x speed in the bearings: viscous friction (heat ~ speed^2 as
                # the speed), not a preload that grows as the bearing warms
                for tau in log_grid(ctx.dt, 2 * 3600.0, 4)[1:]:
                    inp = Product(name=safe_name(f"{n}_x_lag{round(tau)}s", ctx.taken()), of=(n, n), lag_s=(0.0, tau),
                                  unit=f"({ctx.info[n].unit})^2",
                                  note=f"{n} times its lag ({_tau_text(tau)}): bearing friction growing with heat")
                    grid.append(Setting(params=(("bearing_tau_s", tau),), chain=(inp,), signs=(1,),
                                        components=(Component((Part(inp.name, shape),), f"as {n}"),)))
            settings[a] = grid
        out.append(Hypothesis(
            key=f"bearing_preload:{n}", family="bearing_preload",
            title=f"bearing preload growing with heat (nonlinear gain of {n})",
            explanation=("The shaft and inner rings run hotter than the housing, the preload rises and the "
                         "bearing friction with it: the speed path's heat is multiplied by (1 + k dT), dT the "
                         "bearing's over-temperature, a lag of the speed's own heat. Same place as the bearing "
                         "friction, so the same path shape. As the lag shrinks it becomes heat ~ speed^2 in the "
                         "bearings (viscous friction), so it is named only where it predicts significantly better "
                         "than that: where the bearing's lag shows."),
            settings=settings, shared=("bearing_tau_s",), simpler=(f"eddy_loss:{n}",)))
    return out


def _cabinet(ctx: _Ctx) -> list[Hypothesis]:
    currents = [f for f in ctx.model.factors if ctx.info[f].is_current_sq and not ctx.info[f].is_rotor]
    if len(currents) < 2 or not any(f in ctx.active for f in currents):
        return []
    inp = Sum(name=safe_name("amplifier_i_sq", ctx.taken()), of=tuple(currents), unit="A^2",
              note="sum of every amplifier current squared: control cabinet and servo amplifier losses")
    grid = []
    for t1, t2 in _lag_pairs(5 * ctx.dt, 4 * 3600.0, 2 * 3600.0, 2 * DAY_S):
        comps = [Component((Part(inp.name, lag(t1)),), f"lag {_tau_text(t1)}")]
        params: list[tuple[str, float | str]] = [("tau_s", t1)]
        if t2 is not None:
            comps.append(Component((Part(inp.name, lag(t2)),), f"lag {_tau_text(t2)}"))
            params = [("tau_fast_s", t1), ("tau_slow_s", t2)]
        grid.append(Setting(params=tuple(params), components=tuple(comps), chain=(inp,)))
    return [Hypothesis(
        key="cabinet", family="cabinet", title="control cabinet / servo amplifier heat ~ sum of I^2",
        explanation=("The amplifiers lose heat ~ the sum of their motor currents squared, in a cabinet bolted "
                     "to the column; it warms the column through a slow lag. No factor carries it: every "
                     "current factor heats its own motor, not the cabinet."),
        settings={a: grid for a in ctx.axes}, shared=("tau_s", "tau_fast_s", "tau_slow_s"),
        # measured (bench/diagnose.py, variants 1-7): a cabinet thermometer whose reading only follows the
        # currents ("cabinet recorded") named nothing, every verdict as without it; one in a cabinet whose
        # cooling unit switches ("cabinet cooled recorded") was named in 6 of 7
        tell_apart=("record the cabinet's air temperature as a column and diagnose with --use-signal: that tells "
                    "them apart only where it varies for reasons of its own (its cooling unit switching, the "
                    "door, the hall), since a cabinet that merely follows the currents adds nothing the paths "
                    "lack; or run the feed axes hard for hours with the spindle at rest"))]


def _chiller(ctx: _Ctx) -> list[Hypothesis]:
    out = []
    for n in (f for f in ctx.active if ctx.info[f].is_speed):
        flag = Flag(name=safe_name(f"{n}_on", ctx.taken()), of=n, above=1.0, note=f"1 while {n} > 1")
        group = ctx.info[n].group
        # the motor's temperature, for the heat the chiller takes: a lag of the speed or of a motor current
        proxies = [n] + [f for f in ctx.model.factors if ctx.info[f].group == group and ctx.info[f].is_current_sq
                         and not ctx.info[f].is_rotor]
        chiller: dict[str, list[Setting]] = {}
        loop: dict[str, list[Setting]] = {}
        late = _late_heat(ctx)
        for a in ctx.axes:
            chiller[a], loop[a] = [], []
            for f in _motor_shapes(ctx, a, n, stator_only=True):
                shape = ctx.base_terms(a, f)
                chiller[a].append(Setting(params=(("path_shape", f), ("proxy", "none"), ("motor_tau_s", 0.0)),
                                          chain=(flag,), signs=(-1,),
                                          components=(Component((Part(flag.name, shape),), f"on, as {f}"),)))
                for proxy in proxies:
                    for tau in log_grid(2 * ctx.dt, 6 * 3600.0, 3):
                        prod = _motor_heat(ctx, n, flag, proxy, tau)
                        chiller[a].append(Setting(params=(("path_shape", f), ("proxy", proxy), ("motor_tau_s", tau)),
                                                  chain=(flag, prod), signs=(-1,),
                                                  components=(Component((Part(prod.name, shape),), f"as {f}"),)))
                    # a coolant loop: the heat taken from the motor comes back after a transport delay
                    for tau in (ctx.dt,):  # the heat the coolant takes follows the motor's heat closely
                        prod = _motor_heat(ctx, n, flag, proxy, tau)
                        for d, land, label in late:
                            loop[a].append(Setting(
                                params=(("path_shape", f), ("proxy", proxy), ("motor_tau_s", tau), *d, *land[0]),
                                # the late heat's sign is held positive: free (a tank that moves an axis
                                # the other way), the bench's no-effect cases none v3 and none v7 and four
                                # effect cases took a coolant loop that is not there, and no coolant case
                                # gained its name (measured 2 Dec, variants 1-7)
                                chain=(flag, prod), signs=(-1, 1),
                                components=(Component((Part(prod.name, shape),), f"taken at the motor, as {f}"),
                                            Component((Part(prod.name, land[1], d[0][1]),), label))))
        out.append(Hypothesis(
            key=f"chiller:{n}", family="chiller", title=f"coolant chiller switching with the spindle ({n} > 0)",
            explanation=("A chiller (or coolant pump) that runs only with the spindle takes heat out of the motor "
                         "~ its temperature over the coolant's while it runs, and nothing when it stops: a "
                         "switched heat sink at the motor, so the same path shape as the motor current's heat."),
            settings=chiller, shared=("proxy", "motor_tau_s")))
        out.append(Hypothesis(
            key=f"dead_time:coolant:{n}", family="dead_time",
            title=f"coolant loop with a transport delay (dead time) on the motor heat of {n}",
            explanation=("Coolant or oil takes heat out of the motor while it runs and releases it elsewhere (a "
                         "tank, the casting it flows through) after a transport delay: a sink at the motor plus "
                         "the same heat, late, through a lag. A dead time on a path."),
            settings=loop, shared=("proxy", "motor_tau_s", "delay_s"), simpler=(f"chiller:{n}",)))
    return out


def _motor_heat(ctx: _Ctx, n: str, flag: Flag, proxy: str, tau: float) -> Product:
    return Product(name=safe_name(f"{n}_on_x_{proxy}_lag{round(tau)}s", ctx.taken()), of=(flag.name, proxy),
                   lag_s=(0.0, tau), unit=ctx.info[proxy].unit,
                   note=f"running flag times a lag ({_tau_text(tau)}) of {proxy}: motor temperature")


def _late_heat(ctx: _Ctx) -> list[tuple[tuple[tuple[str, float], ...], tuple, str]]:
    """(dead time, where the late heat lands, label): one lag, or two in series (a tank, then a casting)."""
    delays = [d * 60.0 for d in (10, 20, 30, 60, 90) if d * 60.0 >= ctx.dt]
    lands: list[tuple[tuple[tuple[str, float], ...], tuple]] = [
        ((("tau_s", t),), lag(t)) for t in log_grid(5 * ctx.dt, 12 * 3600.0, 2)]
    lands += [((("tau_fast_s", t1), ("tau_slow_s", t2)), (SecondOrder.from_time_constants(gain=1.0, tau1_s=t1,
                                                                                           tau2_s=t2),))
              for t1 in log_grid(5 * ctx.dt, 2 * 3600.0, 1.5) for t2 in log_grid(1800.0, 12 * 3600.0, 1.5)
              if t2 >= 2 * t1]
    return [((("delay_s", d),), land, f"late by {_tau_text(d)}") for d in delays for land in lands]


def _extra_mode(ctx: _Ctx, f: str, taus: Sequence[float]) -> dict[str, list[Setting]]:
    settings = {}
    for a in ctx.axes:
        base = ctx.base_terms(a, f)
        grid = []
        for tau in taus:
            comps = [Component((Part(f, lag(tau)),), f"mode {_tau_text(tau)}")]
            if base:
                comps.insert(0, Component((Part(f, base),), "gain correction", corrects=f))
            grid.append(Setting(params=(("tau_s", tau),), components=tuple(comps),
                                limits=(1.0, math.inf) if base else (math.inf,)))
        settings[a] = grid
    return settings


def identification_length_s(model: ThermalModel) -> float:
    """How long the identification runs were (model info), else its slowest time constant, else 12 h."""
    length = model.info.get("longest_experiment_s")
    if isinstance(length, int | float) and length > 0:
        return float(length)
    taus = [t for p in model.paths.values() for term in p.terms for t in term.time_constants_s]
    return max(taus, default=12 * 3600.0)


#: the slowest mode tried, in lengths of the longest recording: a mode much slower than every recording is a ramp
#: on each of them (its gain over its time constant is all they show), and the gain that ramp asks of it is
#: reached only over runs far longer than any recording (a 480 h mode taken for a room's drift on 24 h days
#: moved z 33 um a day on a week-long file)
SLOW_MODE_SPAN = 3.0
#: its time constants per decade (12 .. 72 h on 24 h days: 6 values, where 12 h .. 20 days took 8 at 4 a decade)
SLOW_MODE_PER_DECADE = 6


def slowest_mode_s(model: ThermalModel, stack: Stack) -> float:
    """The slowest extra mode diagnosis tries: 3x the longest recording, 4x the identification runs at least."""
    return max(4 * identification_length_s(model), SLOW_MODE_SPAN * stack.longest_s())


def _slow_mode(ctx: _Ctx) -> list[Hypothesis]:
    lo = identification_length_s(ctx.model)
    taus = log_grid(lo, slowest_mode_s(ctx.model, ctx.stack), SLOW_MODE_PER_DECADE)
    return [Hypothesis(
        key=f"slow_mode:{f}", family="slow_mode",
        title=f"slow thermal mode beyond the identification runs (heat of {f})",
        explanation=(f"A massive part (column base, bed, foundation) soaks up the heat of {f} over many hours; "
                     f"identification runs of {lo / 3600:.3g} h cannot see a mode slower than themselves (the "
                     "paper saw an offset long after the spindle stopped). One slow mode on the path."),
        settings=_extra_mode(ctx, f, taus), shared=("tau_s",)) for f in ctx.active]


def _higher_order(ctx: _Ctx) -> list[Hypothesis]:
    lo = identification_length_s(ctx.model)
    taus = [t for t in log_grid(ctx.dt, lo, 4) if t < lo]
    return [Hypothesis(
        key=f"higher_order:{f}", family="higher_order", title=f"higher order on the path of {f}",
        explanation=(f"The path from {f} has one more thermal mode than identified (heat reaching a second "
                     "part), within the time scale of the identification runs; the identified terms keep "
                     "their shape, their gain may change."),
        settings=_extra_mode(ctx, f, taus), generic=True) for f in ctx.active]


def _dead_time(ctx: _Ctx) -> list[Hypothesis]:
    out = []
    late = _late_heat(ctx)
    for f in ctx.active:
        settings = {}
        for a in ctx.axes:
            base = ctx.base_terms(a, f)
            grid = []
            for d, (params, terms), label in late:
                comps = [Component((Part(f, terms, d[0][1]),), label)]
                if base:
                    comps.insert(0, Component((Part(f, base),), "gain correction", corrects=f))
                grid.append(Setting(params=(*d, *params), components=tuple(comps),
                                    limits=(1.0, math.inf) if base else (math.inf,)))
            for d in sorted({d[0][1] for d, _, _ in late}):
                if base:  # a share of the identified path itself arrives late
                    grid.append(Setting(params=(("delay_s", d), ("tau_s", "path")),
                                        components=(Component((Part(f, base, d),), "delayed share"),
                                                    Component((Part(f, base),), "gain correction", corrects=f)),
                                        limits=(1.5, 1.5)))
            settings[a] = grid
        out.append(Hypothesis(
            key=f"dead_time:{f}", family="dead_time", title=f"dead time on the heat of {f} (transport delay)",
            explanation=(f"Part of the heat of {f} arrives late: coolant or oil carries it away and releases it "
                         "elsewhere after a transport delay, or it crosses a long conduction path. A dead time "
                         "on a path, beside the identified immediate part."),
            settings=settings, simpler=(f"higher_order:{f}", f"slow_mode:{f}"), shared=("delay_s",), generic=True))
    return out


def _sensor_drift(ctx: _Ctx) -> list[Hypothesis]:
    setting = Setting(params=(), components=(), nuisance=(("ramp", 0.0),))
    return [Hypothesis(
        key="sensor_drift", family="sensor_drift", title="displacement sensor drift (measurement artefact)",
        explanation=("The displacement reading drifts linearly in time whatever the machine does (the sensor's "
                     "own temperature, a creeping fixture): not machine physics, so it is removed from the "
                     "fits and kept out of the model."),
        settings={a: [setting] for a in ctx.axes}, artefact=True)]
