"""Derived model inputs: signals computed from recorded columns rather than read as profile factors.

Diagnosis extends a model with physics the profile's factors do not carry directly; each extension is an
input of its own feeding ordinary paths, so an extended model is still a matrix of transfer functions:

- :class:`Product`: the product of two signals, each optionally behind a first-order lag; the square of
  the spindle speed (iron eddy loss ~ n^2), or the speed times a lag of itself (bearing friction that
  grows with the bearing's own temperature: a nonlinear gain).
- :class:`Sum`: the sum of signals, e.g. every amplifier current squared (control cabinet losses).
- :class:`Flag`: 1 while a signal is above a threshold (the spindle running: a chiller switching with it).
- :class:`Column`: a recorded column that is not a factor, e.g. the room temperature ``room_c``.
- :class:`Periodic`: sin or cos of the time of day (a daily room cycle nobody recorded).
- :class:`Same`: a factor again, so that a second path from it can have a dead time of its own.

Signals named in ``of`` are profile factors or derived inputs declared earlier. Every derived input is a
causal function of the window values with constant work per window: :class:`InputStepper` computes it
live, :func:`evaluate_inputs` in batch with the same recursion, so the two agree. The model works on
deviations from the initial equilibrium: a lag starts settled at its signal's initial value, and
``prepare`` subtracts each derived input's initial value like a factor's.

The square of a window MEAN understates the mean of the square when the speed varies inside the window
(by the variance within the window); a profile factor with ``stat = "mean_square"`` on the speed channel
is exact and is the better choice for live use once the physics is known.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from gateway.model import limits
from gateway.tomlcheck import NAME, Table

#: signal values a derived input may read: factor and earlier input values, keyed by name
Signals = Mapping[str, np.ndarray]


@dataclass(frozen=True, kw_only=True, slots=True)
class Product:
    """``lag(of[0], lag_s[0]) * lag(of[1], lag_s[1])``; a lag of 0 s is the signal itself."""

    kind: ClassVar[str] = "product"
    name: str
    of: tuple[str, str]
    lag_s: tuple[float, float] = (0.0, 0.0)
    unit: str = ""
    note: str = ""

    def __post_init__(self) -> None:
        if len(self.of) != 2 or len(self.lag_s) != 2:
            raise ValueError(f"input {self.name}: product needs two signals and two lags. Got of={self.of!r}, "
                             f"lag_s={self.lag_s!r}")
        if not all(math.isfinite(t) and t >= 0 for t in self.lag_s):
            raise ValueError(f"input {self.name}: lag_s must be finite and >= 0. Got {self.lag_s!r}")

    def describe(self) -> str:
        parts = [s if t == 0 else f"lag({s}, {t / 60:.3g} min)" for s, t in zip(self.of, self.lag_s, strict=True)]
        return " * ".join(parts)


@dataclass(frozen=True, kw_only=True, slots=True)
class Sum:
    """The sum of signals ``of``."""

    kind: ClassVar[str] = "sum"
    name: str
    of: tuple[str, ...]
    unit: str = ""
    note: str = ""

    def __post_init__(self) -> None:
        if not self.of:
            raise ValueError(f"input {self.name}: sum needs at least one signal")

    def describe(self) -> str:
        return " + ".join(self.of)


@dataclass(frozen=True, kw_only=True, slots=True)
class Flag:
    """1 while signal ``of`` is above ``above``, else 0."""

    kind: ClassVar[str] = "flag"
    name: str
    of: str
    above: float = 0.0
    unit: str = "1"
    note: str = ""

    def describe(self) -> str:
        return f"1 if {self.of} > {self.above:g} else 0"


#: how the paths of a recorded column start (:class:`Column`): "settled" in equilibrium with its first value;
#: "daily" as if it had cycled before the recording as it cycles in its first day (:func:`daily_start`)
COLUMN_STARTS = ("settled", "daily")


@dataclass(frozen=True, kw_only=True, slots=True)
class Column:
    """A recorded column that is not a factor (e.g. ``room_c``).

    ``start``: "settled" (its paths start in equilibrium with its first value, as the factors' do) or "daily"
    (a room thermometer: the days before the recording are taken to have cycled as its first day does; see
    :func:`daily_start`).
    """

    kind: ClassVar[str] = "column"
    name: str
    column: str
    unit: str = ""
    note: str = ""
    start: str = "settled"

    def __post_init__(self) -> None:
        if self.start not in COLUMN_STARTS:
            raise ValueError(f"input {self.name}: start must be one of {COLUMN_STARTS}. Got {self.start!r}")

    def describe(self) -> str:
        return f"recorded column {self.column}" + (", cycling daily before the start" if self.start == "daily"
                                                   else "")


@dataclass(frozen=True, kw_only=True, slots=True)
class Periodic:
    """``sin`` or ``cos`` of 2 pi t / period_s, t the row's time stamp (time of day for 86400 s)."""

    kind: ClassVar[str] = "periodic"
    name: str
    period_s: float
    phase: str = "sin"
    unit: str = "1"
    note: str = ""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.period_s) and self.period_s > 0) or self.phase not in ("sin", "cos"):
            raise ValueError(f"input {self.name}: periodic needs period_s > 0 and phase 'sin' or 'cos'. Got "
                             f"period_s={self.period_s!r}, phase={self.phase!r}")

    def describe(self) -> str:
        return f"{self.phase}(2 pi t / {self.period_s / 3600:g} h)"


@dataclass(frozen=True, kw_only=True, slots=True)
class Same:
    """The factor ``of`` itself, for a second path from it (with its own dead time)."""

    kind: ClassVar[str] = "same"
    name: str
    of: str
    unit: str = ""
    note: str = ""

    def describe(self) -> str:
        return f"{self.of} (second path)"


DerivedInput = Product | Sum | Flag | Column | Periodic | Same
INPUT_KINDS = {c.kind: c for c in (Product, Sum, Flag, Column, Periodic, Same)}


def sources(inp: DerivedInput) -> tuple[str, ...]:
    """The signals (factors or earlier inputs) a derived input reads."""
    if isinstance(inp, Product | Sum):
        return tuple(inp.of)
    if isinstance(inp, Flag | Same):
        return (inp.of,)
    return ()


def recorded_columns(inputs: Sequence[DerivedInput]) -> tuple[str, ...]:
    """The recorded columns (not factors) the inputs read, each once, in declaration order."""
    return tuple(dict.fromkeys(d.column for d in inputs if isinstance(d, Column)))


def check_order(inputs: Sequence[DerivedInput], factors: Sequence[str]) -> list[str]:
    """Problems with names and references: each ``of`` must be a factor or an input declared before."""
    problems = []
    known = set(factors)
    for inp in inputs:
        if inp.name in known:
            problems.append(f"input {inp.name}: the name is already used by a factor or an earlier input")
        for s in sources(inp):
            if s not in known:
                problems.append(f'input {inp.name}: "{s}" is neither a factor nor an input declared before it')
        known.add(inp.name)
    return problems


def lag_coefficient(tau_s: float, dt_s: float) -> float:
    """Pole of a unit-gain first-order lag under the zero-order hold: y_k = a y_{k-1} + (1 - a) u_k."""
    return math.exp(-dt_s / tau_s) if tau_s > 0 else 0.0


def initial_values(inputs: Sequence[DerivedInput], initial: Mapping[str, float], *,
                   time0_s: float) -> dict[str, float]:
    """Every signal's value in the initial equilibrium: ``initial`` (factors, recorded columns) and each input.

    Lags are settled there, so a product of lags is the product of the initial values; a periodic input has
    no equilibrium and takes its value at the first window, ``time0_s``.
    """
    values = dict(initial)
    for inp in inputs:
        if isinstance(inp, Product):
            v = float(values[inp.of[0]]) * float(values[inp.of[1]])
        elif isinstance(inp, Sum):
            v = float(sum(float(values[s]) for s in inp.of))
        elif isinstance(inp, Flag):
            v = 1.0 if float(values[inp.of]) > inp.above else 0.0
        elif isinstance(inp, Same):
            v = float(values[inp.of])
        elif isinstance(inp, Periodic):
            arg = 2.0 * math.pi * time0_s / inp.period_s
            v = math.sin(arg) if inp.phase == "sin" else math.cos(arg)
        else:
            v = float(values.get(inp.column, 0.0))
        values[inp.name] = v
    return values


def evaluate_inputs(inputs: Sequence[DerivedInput], signals: Signals, *, time_s: np.ndarray, dt_s: float,
                    columns: Mapping[str, np.ndarray] | None = None,
                    initial: Mapping[str, float] | None = None) -> dict[str, np.ndarray]:
    """Values (not deviations) of every derived input over a whole recording, in declaration order.

    ``signals`` holds the factors' window values (gaps already filled by the caller's policy), ``columns``
    the recording's other numeric columns. A column's missing values hold the last value seen (the first
    seen before it), the same rule the live :class:`InputStepper` follows. ``initial`` is the equilibrium
    the machine starts in (factors and columns; default: the first window), where every lag starts settled.
    """
    columns = {k: hold_missing(np.asarray(v, float)) for k, v in (columns or {}).items()}
    if initial is None:
        initial = {k: float(v[0]) for k, v in {**signals, **columns}.items() if len(v)}
    time_s = np.asarray(time_s, float)
    start = initial_values(inputs, initial, time0_s=float(time_s[0]) if time_s.size else 0.0)
    values: dict[str, np.ndarray] = {k: np.asarray(v, float) for k, v in signals.items()}
    out: dict[str, np.ndarray] = {}
    for inp in inputs:
        if isinstance(inp, Product):
            a = _lag(values[inp.of[0]], inp.lag_s[0], dt_s, start[inp.of[0]])
            b = _lag(values[inp.of[1]], inp.lag_s[1], dt_s, start[inp.of[1]])
            v = a * b
        elif isinstance(inp, Sum):
            v = np.sum([values[s] for s in inp.of], axis=0)
        elif isinstance(inp, Flag):
            v = (values[inp.of] > inp.above).astype(float)
        elif isinstance(inp, Same):
            v = values[inp.of].copy()
        elif isinstance(inp, Periodic):
            arg = 2.0 * math.pi * time_s / inp.period_s
            v = np.sin(arg) if inp.phase == "sin" else np.cos(arg)
        else:
            if inp.column not in columns:
                raise KeyError(inp.column)
            v = columns[inp.column]
        values[inp.name] = out[inp.name] = v
    return out


DAY_S = 86400.0
#: a daily start needs this much of the column: in less than half a day a cycle is not told from a drift
DAILY_MIN_S = 12 * 3600.0
#: ... and runs this long before the recording: the lags a room acts through are a day at most in diagnosis's
#: search (a casting follows the room within hours, a massive bed within a day), and e^-5 of a start settled
#: before the lead is left at its end
DAILY_LEAD_S = 5 * DAY_S
#: harmonics of the day fitted where the column spans a whole day (a sine alone where it spans less)
DAILY_HARMONICS = 3


@dataclass(frozen=True, slots=True)
class DailyStart:
    """What :func:`daily_start` found: the column over the lead (values, oldest first) and its leading gaps filled."""

    lead: np.ndarray
    values: np.ndarray
    amplitude: float
    fitted_s: float
    harmonics: int = 1


def daily_start(time_s: np.ndarray, values: np.ndarray, dt_s: float) -> DailyStart | str:
    """The days before a recording of a column that cycles daily (a room thermometer), as its first day shows.

    The room does not start with the recording: before it, the air cycled over the days as it does in it, and
    the structure's lags (hours to a day) carry that into the first hours. Taken to start settled at its first
    value, a room path is off there by as much as the room's daily swing through it (bench/diagnose.py, room
    recorded: fresh-day z 3.1-5.4 um from a settled start, 0.9-2.2 um from this one, with the same model).

    So an offset, a linear drift and a cycle of one day (:data:`DAILY_HARMONICS` harmonics over a whole day, a
    sine over less; on the time stamps: the clock need not be set) are fitted to the column's first day of values
    (all of them if fewer), and the column before its first value is taken as that value plus the cycle's change
    since: over :data:`DAILY_LEAD_S` before the recording (``lead``) and over
    the recording's own windows before its first value (``values``, gaps within left as they are). The drift is
    not carried back (the weather before is not known): the mean before the start is the first value's.

    A sentence saying why not instead: less than :data:`DAILY_MIN_S` of values, or a fitted cycle larger than the
    column's whole swing over the fitted span (half a day of drift that a sine extrapolates).
    """
    t = np.asarray(time_s, float)
    v = np.asarray(values, float)
    ok = np.flatnonzero(np.isfinite(v))
    if ok.size < 3 or t[ok[-1]] - t[ok[0]] < DAILY_MIN_S:
        span = (t[ok[-1]] - t[ok[0]]) / 3600.0 if ok.size else 0.0
        return (f"{span:.3g} h of values, {DAILY_MIN_S / 3600:g} h needed to tell a daily cycle from a drift: "
                "started settled at its first value")
    t0 = t[ok[0]]
    day = ok[t[ok] - t0 <= DAY_S]
    tt = t[day] - t0
    # a whole day shows the cycle's shape (a hall heated from 9 to 21 h is no sine), less than one its sine only
    k = np.arange(1, (DAILY_HARMONICS if tt[-1] >= DAY_S - 2.0 * dt_s else 1) + 1)
    w = 2.0 * math.pi / DAY_S

    def cycle(x: np.ndarray) -> np.ndarray:  # (len(x), 2 per harmonic): the sines, then the cosines
        return np.column_stack([np.sin(np.outer(x, w * k)), np.cos(np.outer(x, w * k))])

    A = np.column_stack([np.ones_like(tt), tt / DAY_S, cycle(tt)])
    c = np.linalg.lstsq(A, v[day], rcond=None)[0][2:]
    one_day = cycle(np.linspace(0.0, DAY_S, 289)) @ c
    amplitude = float(np.ptp(one_day)) / 2.0
    swing = float(np.ptp(v[day]))
    what = "sine" if len(k) == 1 else f"cycle ({len(k)} harmonics)"
    if not amplitude <= swing:
        return (f"a daily {what} of +-{amplitude:.3g} fitted over its first {tt[-1] / 3600:.3g} h, larger than its "
                f"swing there ({swing:.3g}): a drift, not a cycle; started settled at its first value")
    at0 = cycle(np.zeros(1)) @ c

    def change(at: np.ndarray) -> np.ndarray:  # the cycle's change since the first value
        return cycle(at - t0) @ c - at0

    n = round(DAILY_LEAD_S / dt_s)
    lead = v[ok[0]] + change(t[0] - dt_s * np.arange(n, 0, -1))
    filled = v.copy()
    filled[: ok[0]] = v[ok[0]] + change(t[: ok[0]])
    return DailyStart(lead=lead, values=filled, amplitude=amplitude, fitted_s=float(tt[-1]), harmonics=len(k))


def start_leads(inputs: Sequence[DerivedInput], time_s: np.ndarray, columns: Mapping[str, np.ndarray],
                dt_s: float) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], list[str]]:
    """The daily-start columns' values (leading gaps filled), their leads and what was done, in words.

    Returns (columns, leads, notes): ``columns`` is ``columns`` with each daily-start column's leading gaps
    filled by :func:`daily_start`; ``leads`` holds, per daily-start column read, its values over the
    :data:`DAILY_LEAD_S` before the first window (absent where it starts settled, said in ``notes``).
    """
    out = dict(columns)
    leads: dict[str, np.ndarray] = {}
    notes: list[str] = []
    for inp in inputs:
        if not isinstance(inp, Column) or inp.start != "daily" or inp.column in leads or inp.column not in columns:
            continue
        got = daily_start(time_s, columns[inp.column], dt_s)
        if isinstance(got, str):
            notes.append(f"column {inp.column} (a daily start): {got}")
            continue
        out[inp.column] = got.values
        leads[inp.column] = got.lead
        shape = "a sine" if got.harmonics == 1 else f"a cycle of {got.harmonics} harmonics"
        notes.append(f"column {inp.column}: its paths start as if it had cycled daily before the recording as in its "
                     f"first {got.fitted_s / 3600:.3g} h ({shape} of +-{got.amplitude:.3g} fitted there, about its "
                     f"first value; the {DAILY_LEAD_S / DAY_S:g} days before run first)")
    return out, leads, notes


def _lag(x: np.ndarray, tau_s: float, dt_s: float, settled_at: float) -> np.ndarray:
    """First-order lag of ``x``, its state settled at ``settled_at`` before the first window."""
    if tau_s == 0 or x.size == 0:
        return x
    a = lag_coefficient(tau_s, dt_s)
    from scipy.signal import lfilter  # imported when used: it is slow to import (see gateway.model.discrete)

    y, _ = lfilter([1.0 - a], [1.0, -a], x, zi=[a * settled_at])
    return y


def hold_missing(x: np.ndarray) -> np.ndarray:
    """Missing values replaced by the last value seen (leading ones by the first value seen)."""
    ok = np.isfinite(x)
    if ok.all():
        return x.copy()
    if not ok.any():
        return np.zeros_like(x)
    idx = np.where(ok, np.arange(len(x)), 0)
    np.maximum.accumulate(idx, out=idx)
    out = x[idx]
    out[: int(np.flatnonzero(ok)[0])] = x[ok][0]
    return out


class InputStepper:
    """Live evaluation of derived inputs, one window at a time, with constant work per window.

    Start it with the initial equilibrium (factor values, and the first value of every recorded column an
    input reads); each :meth:`step` takes one window's values and returns the derived inputs' values, the
    same numbers :func:`evaluate_inputs` gives in batch.
    """

    def __init__(self, inputs: Sequence[DerivedInput], *, dt_s: float, initial: Mapping[str, float],
                 time0_s: float = 0.0) -> None:
        self.inputs = tuple(inputs)
        self.dt_s = float(dt_s)
        start = initial_values(self.inputs, initial, time0_s=time0_s)
        # lag states (settled at the initial equilibrium) and the last value seen of every column
        self._lags = {(inp.name, k): float(start[inp.of[k]]) for inp in self.inputs if isinstance(inp, Product)
                      for k in range(2)}
        self._held = {inp.column: float(start[inp.name]) for inp in self.inputs if isinstance(inp, Column)}

    def step(self, signals: Mapping[str, float], *, time_s: float,
             columns: Mapping[str, float] | None = None) -> dict[str, float]:
        """Values of every derived input for one window (``signals``: factor values of that window)."""
        values: dict[str, float] = {k: float(v) for k, v in signals.items()}
        out: dict[str, float] = {}
        for inp in self.inputs:
            if isinstance(inp, Product):
                parts = []
                for k in range(2):
                    x = values[inp.of[k]]
                    if inp.lag_s[k] > 0:
                        a = lag_coefficient(inp.lag_s[k], self.dt_s)
                        x = a * self._lags[(inp.name, k)] + (1.0 - a) * x
                        self._lags[(inp.name, k)] = x
                    parts.append(x)
                v = parts[0] * parts[1]
            elif isinstance(inp, Sum):
                v = float(sum(values[s] for s in inp.of))
            elif isinstance(inp, Flag):
                v = 1.0 if values[inp.of] > inp.above else 0.0
            elif isinstance(inp, Same):
                v = values[inp.of]
            elif isinstance(inp, Periodic):
                arg = 2.0 * math.pi * time_s / inp.period_s
                v = math.sin(arg) if inp.phase == "sin" else math.cos(arg)
            else:
                x = math.nan if columns is None else float(columns.get(inp.column, math.nan))
                if math.isfinite(x):
                    self._held[inp.column] = x
                v = self._held[inp.column]
            values[inp.name] = out[inp.name] = v
        return out


# ------------------------------------------------------------------------------------------------ TOML --
def input_to_toml(inp: DerivedInput) -> dict[str, object]:
    """The ``[inputs.NAME]`` table of a derived input (floats always, for an exact round trip)."""
    d: dict[str, object] = {"kind": inp.kind}
    if isinstance(inp, Product):
        d |= {"of": list(inp.of), "lag_s": [float(t) for t in inp.lag_s]}
    elif isinstance(inp, Sum):
        d["of"] = list(inp.of)
    elif isinstance(inp, Flag):
        d |= {"of": inp.of, "above": float(inp.above)}
    elif isinstance(inp, Same):
        d["of"] = inp.of
    elif isinstance(inp, Periodic):
        d |= {"period_s": float(inp.period_s), "phase": inp.phase}
    else:
        d["column"] = inp.column
        if inp.start != "settled":
            d["start"] = inp.start
    d["unit"] = inp.unit
    if inp.note:
        d["note"] = inp.note
    return d


def parse_inputs(root: Table) -> list[DerivedInput]:
    """Every ``[inputs.NAME]`` table, checked with the typed getters (problems recorded, not raised)."""
    out: list[DerivedInput] = []
    for name, t in root.tables("inputs", name_pattern=NAME):
        kind = t.str("kind", choices=list(INPUT_KINDS))
        unit = t.str("unit", default="") or ""
        note = t.str("note", default="") or ""
        inp: DerivedInput | None = None
        if kind == "product":
            of = t.str_list("of", unique=False, min_len=2)
            lags = t.float_list("lag_s", default=(0.0, 0.0), expected=limits.LAG_EXPECTED)
            if of is not None and len(of) != 2:
                t.problem("of", f"expected exactly two signal names, got {len(of)}")
                of = None
            if lags is not None and (len(lags) != 2 or not all(limits.lag_ok(x) for x in lags)):
                t.problem("lag_s", f"expected {limits.LAG_EXPECTED}, got {list(lags)!r}")
                lags = None
            if of is not None and lags is not None:
                inp = Product(name=name, of=(of[0], of[1]), lag_s=(lags[0], lags[1]), unit=unit, note=note)
        elif kind == "sum":
            of = t.str_list("of", min_len=1)
            if of is not None:
                inp = Sum(name=name, of=tuple(of), unit=unit, note=note)
        elif kind == "flag":
            of1 = t.str("of")
            above = t.float("above", default=0.0)
            if of1 is not None and above is not None:
                inp = Flag(name=name, of=of1, above=above, unit=unit or "1", note=note)
        elif kind == "same":
            of1 = t.str("of")
            if of1 is not None:
                inp = Same(name=name, of=of1, unit=unit, note=note)
        elif kind == "periodic":
            period = t.float("period_s", min=limits.PERIOD_MIN_S, max=limits.PERIOD_MAX_S,
                             expected=limits.PERIOD_EXPECTED)
            phase = t.str("phase", choices=("sin", "cos"))
            if period is not None and phase is not None:
                inp = Periodic(name=name, period_s=period, phase=phase, unit=unit or "1", note=note)
        elif kind == "column":
            col = t.str("column")
            start = t.str("start", default="settled", choices=COLUMN_STARTS)
            if col is not None and start is not None:
                inp = Column(name=name, column=col, unit=unit, note=note, start=start)
        t.done()
        if inp is not None:
            out.append(inp)
    return out
