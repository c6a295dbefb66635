"""The region of factor space a model's identification data covered, and where a recording leaves it.

A model is linear in each factor, but how it splits a response between factors that change together
(spindle speed, stator and rotor current squared; a feed and its motor current squared) is fixed only
along the combinations its data showed. Identification records:

- per factor, the range of its deviation from the reference (lowest, highest);
- per pair of co-varying factors (factors that every identification recording moves together or not at
  all), the range of their ratio ``du_of / du_per`` over the windows where ``per`` is on (at least
  ``on_share`` of its highest deviation): e.g. stator current squared per rpm (field weakening lowers it at
  high speed), rotor current squared per stator current squared (a cutting load raises it).

A recording leaves the region where a factor goes beyond its range by more than ``margin`` of the range, or
a ratio beyond its range by more than the factor ``1 + margin`` (ratios that stay positive) or ``margin``
of its span; :func:`check_coverage` says which factor or ratio, how far and for how long, and marks every
such window. There the estimate extrapolates from what the identification saw.

A model with an input that reads a recorded column (a room thermometer, ``room_c``) records the range of that
column's values too (absolute, not deviations: the model takes the column's change from its first window, so a
thermometer reading in other units, degF for degC, or moved to another place shows in its level first). A
recording leaves the region where the column goes beyond its range by more than ``margin`` of it, and reads an
implausible value where it lies :data:`IMPLAUSIBLE_SPANS` widths beyond (the width at least
:data:`COLUMN_WIDTH_SHARE` of the column's size: a hall held to +/- 0.5 K still has summers).

In the model file::

    [coverage]
    source = "identification: 9 experiments"
    on_share = 0.1           # a ratio counts in windows where its "per" factor is at least this share on
    margin = 0.2
    [coverage.range]         # deviation from the reference, [lowest, highest]
    spindle_speed = [0.0, 1000.0]
    [coverage.ratio]         # "of/per" = [lowest, highest] ratio of the deviations
    "spindle_i1_sq/spindle_speed" = [0.19, 1.4]
    [coverage.column]        # a recorded column a model input reads = [lowest, highest] value
    room_c = [17.6, 23.1]
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from gateway.tomlcheck import Table

#: a ratio counts over the windows where its denominator is at least this share of its highest deviation
ON_SHARE = 0.1
#: tolerance beyond a range (share of its span) or a positive ratio range (factor 1 + MARGIN)
MARGIN = 0.2
#: a factor "moves" in a recording when its deviation exceeds this share of its largest in all of them
MOVES_SHARE = 0.01
#: bounds on stored values: anything beyond is a corrupt file, not a machine
MAX_VALUE = 1e12


@dataclass(frozen=True, kw_only=True, slots=True)
class Ratio:
    """``du_of / du_per`` ranged over [low, high] where ``per`` was on."""

    of: str
    per: str
    low: float
    high: float

    @property
    def key(self) -> str:
        return f"{self.of}/{self.per}"


@dataclass(frozen=True, kw_only=True)
class Coverage:
    """Ranges of the factors' deviations and of the ratios of co-varying factors the identification saw."""

    ranges: Mapping[str, tuple[float, float]]
    ratios: tuple[Ratio, ...] = ()
    source: str = ""
    on_share: float = ON_SHARE
    margin: float = MARGIN
    #: recorded columns the model's inputs read: [lowest, highest] value (not deviation) in the data fitted on
    columns: Mapping[str, tuple[float, float]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name in ("ranges", "columns"):
            object.__setattr__(self, name, MappingProxyType({k: (float(a), float(b))
                                                             for k, (a, b) in getattr(self, name).items()}))
        object.__setattr__(self, "ratios", tuple(self.ratios))

    def columns_of(self, extras: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """The columns of a recording's ``extras`` that this coverage ranges (for :func:`check_coverage`)."""
        return {c: extras[c] for c in self.columns if c in extras}


#: a factor beyond its covered range by more than this many times the range's width is implausible (production
#: at 3x the highest speed an identification covered is 2 widths beyond it; a cell of -1e9 rpm, a million)
IMPLAUSIBLE_SPANS = 5.0
#: how a note on an implausible value starts (``cncgw estimate`` prints it as a warning)
IMPLAUSIBLE = "implausible value:"
#: a recorded column's covered width, for judging how far beyond it a value lies, is at least this share of the
#: column's size (its largest |value| covered): a room held to 20 +/- 0.5 C that reads 27 C one summer is outside
#: the coverage, not implausible; one that reads 68 (degF) is
COLUMN_WIDTH_SHARE = 0.25


@dataclass(frozen=True, kw_only=True, slots=True)
class Excursion:
    """One way a recording left the covered region: a factor's range or a ratio's, how far, how long."""

    what: str  # the factor, "of per per", or the recorded column
    kind: str  # "range", "ratio" or "column"
    side: str  # "above" or "below"
    value: float  # the most extreme value reached
    bound: float  # the covered bound it passed (highest or lowest)
    windows: int  # windows outside
    longest: int  # windows in the longest unbroken stretch outside
    first: int  # index of the first window outside
    unit: str = ""
    #: the width of the covered range (a factor's range; a column's, at least COLUMN_WIDTH_SHARE of its size; 0 for
    #: a ratio): how far beyond it is judged against it
    span: float = 0.0

    @property
    def implausible(self) -> bool:
        """Beyond the covered range by over :data:`IMPLAUSIBLE_SPANS` times its width: a glitch or a sentinel."""
        return (self.kind in ("range", "column") and self.span > 0
                and abs(self.value - self.bound) > IMPLAUSIBLE_SPANS * self.span)

    def how_far(self) -> str:
        """The extreme value against the covered bound, as a multiple when that means something."""
        u = f" {self.unit}" if self.unit else ""
        if self.kind == "column":  # a level (a temperature): its difference says how far, a ratio would not
            return (f"{self.value:.4g}{u}, {abs(self.value - self.bound):.3g}{u} {self.side} the "
                    f"{_word(self.side)} covered ({self.bound:.4g}{u})")
        if self.bound != 0 and self.value / self.bound > 0:
            return (f"{self.value:.4g}{u}, {self.value / self.bound:.2g}x the {_word(self.side)} covered "
                    f"({self.bound:.4g}{u})")
        return f"{self.value:.4g}{u}, {self.side} the covered {_word(self.side)} {self.bound:.4g}{u}"

    def describe(self, window_s: float) -> str:
        name = f"{self.what} ({self.kind})" if self.kind != "range" else self.what
        reach = "up to" if self.side == "above" else "down to"
        return (f"{name} {self.side} coverage: {reach} {self.how_far()}; {self.windows} windows "
                f"({duration_text(self.windows * window_s)}), longest stretch "
                f"{duration_text(self.longest * window_s)}, "
                f"first at window {self.first + 1}")


def _word(side: str) -> str:
    return "highest" if side == "above" else "lowest"


def _suspects(e: Excursion) -> str:
    """What an implausible value most likely is."""
    if e.kind == "column":
        return (f"the column in other units than the model was fitted on ({e.bound:.4g} covered; degF for degC?), "
                "a sensor moved or faulty, or a sentinel value (leave such a cell empty to make it a gap)")
    return ("a glitch or a sentinel value (-9999, 32767; leave such a cell empty to make it a gap), or a machine run "
            "far beyond anything identified")


def duration_text(s: float) -> str:
    """Seconds as minutes below an hour, else hours ("30 min", "1 h", "2.5 h")."""
    return f"{s / 3600:.3g} h" if s >= 3600 else f"{s / 60:.3g} min"


@dataclass(frozen=True, kw_only=True)
class CoverageCheck:
    """Per window whether it lies outside the covered region, and every excursion."""

    outside: np.ndarray  # (N,) bool
    excursions: tuple[Excursion, ...] = ()
    #: per window, the excursions that window is in (indices into ``excursions``): for a per-window flag
    reasons: tuple[tuple[int, ...], ...] = field(default=())
    #: (N,) how far the window lies beyond the region, the largest over factors (:func:`beyond_coverage`)
    beyond: np.ndarray | None = None

    @property
    def windows_outside(self) -> int:
        return int(np.count_nonzero(self.outside))

    def notes(self, window_s: float) -> list[str]:
        """One line per excursion, for a report; an implausible one first, said as such."""
        odd = [f"{IMPLAUSIBLE} {e.what} reaches {e.value:.4g}{f' {e.unit}' if e.unit else ''} ({e.windows} windows, "
               f"first at window {e.first + 1}), {abs(e.value - e.bound) / e.span:.2g}x the width of the covered "
               f"range beyond it: {_suspects(e)}? either way the estimate from there on means little"
               for e in self.excursions if e.implausible]
        return odd + [f"outside the identification's coverage: {e.describe(window_s)}: the estimate extrapolates "
                      "there" for e in self.excursions]

    def window_reason(self, k: int) -> str:
        """Why window ``k`` is outside (``""`` inside)."""
        if not self.reasons or not self.outside[k]:
            return ""
        return "; ".join(f"{self.excursions[i].what} {self.excursions[i].side}" for i in self.reasons[k])


# ------------------------------------------------------------------------------------------------ building --
def co_varying_pairs(factors: Sequence[str], moving: np.ndarray) -> list[tuple[str, str]]:
    """(of, per) pairs of factors that move together in every recording (``moving``: recordings x factors).

    ``per`` comes first in ``factors``. A factor no recording moves pairs with nothing.
    """
    moving = np.asarray(moving, dtype=bool)
    out = []
    for a in range(len(factors)):
        for b in range(a + 1, len(factors)):
            ma, mb = moving[:, a], moving[:, b]
            if ma.any() and np.array_equal(ma, mb):
                out.append((factors[b], factors[a]))
    return out


def coverage_of(du_list: Iterable[np.ndarray], factors: Sequence[str], *, source: str = "",
                on_share: float = ON_SHARE, margin: float = MARGIN) -> Coverage:
    """The region covered by recordings given as deviations ``du`` (factors first, N), NaN allowed."""
    dus = [np.asarray(du, dtype=float)[: len(factors)] for du in du_list]
    dus = [du for du in dus if du.shape[1]]
    if not dus:
        return Coverage(ranges={f: (0.0, 0.0) for f in factors}, source=source, on_share=on_share, margin=margin)
    pooled = np.concatenate(dus, axis=1)
    lo = np.nan_to_num(np.nanmin(np.where(np.isfinite(pooled), pooled, np.nan), axis=1), nan=0.0)
    hi = np.nan_to_num(np.nanmax(np.where(np.isfinite(pooled), pooled, np.nan), axis=1), nan=0.0)
    lo, hi = np.minimum(lo, 0.0), np.maximum(hi, 0.0)  # the reference itself is covered
    size = np.maximum(np.abs(lo), np.abs(hi))
    moving = np.array([[np.nanmax(np.abs(du[j])) > MOVES_SHARE * size[j] if size[j] > 0 else False
                        for j in range(len(factors))] for du in dus])
    ratios = []
    for of, per in co_varying_pairs(factors, moving):
        i, j = factors.index(of), factors.index(per)
        if hi[j] <= 0:
            continue
        on = np.isfinite(pooled[i]) & (pooled[j] >= on_share * hi[j])
        if not on.any():
            continue
        r = pooled[i, on] / pooled[j, on]
        ratios.append(Ratio(of=of, per=per, low=float(r.min()), high=float(r.max())))
    return Coverage(ranges={f: (float(lo[k]), float(hi[k])) for k, f in enumerate(factors)}, ratios=tuple(ratios),
                    source=source, on_share=on_share, margin=margin)


def column_ranges(values: Mapping[str, Iterable[np.ndarray]]) -> dict[str, tuple[float, float]]:
    """[lowest, highest] finite value of each recorded column over its arrays (a column with none is left out)."""
    out = {}
    for c, arrays in values.items():
        finite = [a[np.isfinite(a)] for a in (np.asarray(x, dtype=float) for x in arrays)]
        finite = [a for a in finite if a.size]
        if finite:
            out[c] = (float(min(a.min() for a in finite)), float(max(a.max() for a in finite)))
    return out


# ------------------------------------------------------------------------------------------------ checking --
def _runs(mask: np.ndarray) -> tuple[int, int]:
    """(longest unbroken run of True, index of the first True)."""
    idx = np.flatnonzero(mask)
    if not idx.size:
        return 0, -1
    breaks = np.flatnonzero(np.diff(idx) > 1)
    starts = np.concatenate([[0], breaks + 1])
    ends = np.concatenate([breaks, [idx.size - 1]])
    return int((ends - starts + 1).max()), int(idx[0])


def check_coverage(cov: Coverage, du: np.ndarray, factors: Sequence[str],
                   units: Mapping[str, str] | None = None,
                   columns: Mapping[str, np.ndarray] | None = None) -> CoverageCheck:
    """Where the deviations ``du`` (factors first, N windows) leave ``cov``; NaN windows count as inside.

    ``columns``: the recording's values (N each) of the recorded columns ``cov`` holds ranges of; a column not
    given is not checked.
    """
    du = np.asarray(du, dtype=float)
    n = du.shape[1] if du.ndim == 2 else 0
    units = units or {}
    masks: list[np.ndarray] = []
    excursions: list[Excursion] = []

    def add(mask: np.ndarray, values: np.ndarray, what: str, kind: str, side: str, bound: float, unit: str,
            span: float = 0.0) -> None:
        if not mask.any():
            return
        v = values[mask]
        longest, first = _runs(mask)
        excursions.append(Excursion(what=what, kind=kind, side=side, bound=bound, windows=int(mask.sum()),
                                    value=float(v.max() if side == "above" else v.min()), longest=longest,
                                    first=first, unit=unit, span=span))
        masks.append(mask)

    index = {f: k for k, f in enumerate(factors)}
    for f, (lo, hi) in cov.ranges.items():
        if f not in index or n == 0:
            continue
        x = np.nan_to_num(du[index[f]], nan=0.0)
        span = hi - lo
        # a factor the identification never moved: any move beyond rounding leaves the region
        tol = cov.margin * span if span > 0 else 1e-9 * (1.0 + float(np.max(np.abs(x), initial=0.0)))
        add(x > hi + tol, x, f, "range", "above", hi, units.get(f, ""), span)
        add(x < lo - tol, x, f, "range", "below", lo, units.get(f, ""), span)
    for r in cov.ratios:
        if r.of not in index or r.per not in index or n == 0:
            continue
        on, ratio = _ratio(cov, r, du[index[r.of]], du[index[r.per]])
        if r.low > 0:
            above, below = r.high * (1 + cov.margin), r.low / (1 + cov.margin)
        else:
            w = cov.margin * max(r.high - r.low, abs(r.high), abs(r.low), 1e-300)
            above, below = r.high + w, r.low - w
        u_of, u_per = units.get(r.of, ""), units.get(r.per, "")
        unit = f"{u_of}/{u_per}" if u_of and u_per else ""
        with np.errstate(invalid="ignore"):
            add(on & (ratio > above), ratio, f"{r.of} per {r.per}", "ratio", "above", r.high, unit)
            add(on & (ratio < below), ratio, f"{r.of} per {r.per}", "ratio", "below", r.low, unit)
    for c, (lo, hi) in cov.columns.items():
        if columns is None or c not in columns or n == 0:
            continue
        x = np.asarray(columns[c], dtype=float)
        if x.shape != (n,):
            raise ValueError(f"column {c}: {x.shape[0] if x.ndim == 1 else x.shape} values for {n} windows")
        x = np.where(np.isfinite(x), x, (lo + hi) / 2)  # a gap is no excursion
        tol = cov.margin * (hi - lo) if hi > lo else 1e-9 * (1.0 + max(abs(lo), abs(hi)))
        width = max(hi - lo, COLUMN_WIDTH_SHARE * max(abs(lo), abs(hi)))
        add(x > hi + tol, x, c, "column", "above", hi, units.get(c, ""), width)
        add(x < lo - tol, x, c, "column", "below", lo, units.get(c, ""), width)
    outside = np.zeros(n, dtype=bool)
    for m in masks:
        outside |= m
    reasons = tuple(tuple(i for i, m in enumerate(masks) if m[k]) for k in range(n)) if excursions else ()
    far = beyond_coverage(cov, du[: len(factors)], factors) if n else np.zeros((len(factors), 0))
    return CoverageCheck(outside=outside, excursions=tuple(excursions), reasons=reasons,
                         beyond=far.max(axis=0) if len(factors) else np.zeros(n))


def _ratio(cov: Coverage, r: Ratio, x_of: np.ndarray, x_per: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where a ratio of co-varying factors is judged, and its value there (NaN elsewhere).

    Judged where the "per" factor is on: at least ``on_share`` of its covered maximum.
    """
    hi_per = cov.ranges.get(r.per, (0.0, 0.0))[1]
    on = np.isfinite(x_of) & np.isfinite(x_per) & (x_per >= cov.on_share * hi_per) & (x_per > 0)
    return on, np.where(on, x_of / np.where(on, x_per, 1.0), np.nan)


def beyond_coverage(cov: Coverage, du: np.ndarray, factors: Sequence[str]) -> np.ndarray:
    """How far each factor's deviation lies beyond the covered region, per window: (len(factors), N), >= 0.

    Measured from where :func:`check_coverage` flags a window (the bound plus its margin), so it is 0 exactly
    where the window is inside, on a log scale: ``log(1 + b)`` with ``b`` for a range in spans of the covered
    range (half the covered span beyond the flag: log 1.5), for a ratio of co-varying factors in the same
    relative measure (a ratio twice the flagged highest: log 2), given to both factors of the ratio (how the
    model splits their response is what is unknown). Log, because the factors grow together and their
    squares with them: at three times the covered speed the speed lies 2 spans beyond and a current^2 8.7;
    in proportion (log 3 and log 9.7) they say the same. A factor the identification never moved counts
    log 2 wherever it moves. NaN windows count as inside.
    """
    du = np.asarray(du, dtype=float)
    n = du.shape[1] if du.ndim == 2 else 0
    out = np.zeros((len(factors), n))
    index = {f: k for k, f in enumerate(factors)}
    for f, (lo, hi) in cov.ranges.items():
        if f not in index or n == 0:
            continue
        x = np.nan_to_num(du[index[f]], nan=0.0)
        span = hi - lo
        if span > 0:
            d = np.maximum((x - hi) / span, (lo - x) / span) - cov.margin
        else:
            d = np.where(np.abs(x) > 1e-9 * (1.0 + float(np.max(np.abs(x), initial=0.0))), 1.0, 0.0)
        out[index[f]] = np.maximum(out[index[f]], np.maximum(d, 0.0))
    for r in cov.ratios:
        if r.of not in index or r.per not in index or n == 0:
            continue
        on, ratio = _ratio(cov, r, du[index[r.of]], du[index[r.per]])
        with np.errstate(invalid="ignore", divide="ignore"):
            if r.low > 0:
                above, below = r.high * (1 + cov.margin), r.low / (1 + cov.margin)
                d = np.maximum(ratio / above - 1.0, below / np.where(ratio > 0, ratio, np.nan) - 1.0)
                d = np.where(on & (ratio <= 0), 1.0, d)
            else:
                w = max(r.high - r.low, abs(r.high), abs(r.low), 1e-300)
                d = np.maximum(ratio - (r.high + cov.margin * w), (r.low - cov.margin * w) - ratio) / w
        d = np.where(on, np.nan_to_num(np.maximum(d, 0.0), nan=0.0), 0.0)
        for f in (r.of, r.per):
            out[index[f]] = np.maximum(out[index[f]], d)
    return np.log1p(out)


# ------------------------------------------------------------------------------------------------ TOML -----
def coverage_to_toml(cov: Coverage) -> dict[str, Any]:
    """The ``[coverage]`` table."""
    out: dict[str, Any] = {}
    if cov.source:
        out["source"] = cov.source
    out["on_share"] = float(cov.on_share)
    out["margin"] = float(cov.margin)
    out["range"] = {f: [float(lo), float(hi)] for f, (lo, hi) in cov.ranges.items()}
    if cov.ratios:
        out["ratio"] = {r.key: [float(r.low), float(r.high)] for r in cov.ratios}
    if cov.columns:
        out["column"] = {c: [float(lo), float(hi)] for c, (lo, hi) in cov.columns.items()}
    return out


def _pair(t: Table, key: str, expected: str) -> tuple[float, float] | None:
    pair = t.float_list(key, expected=expected)
    if pair is None:
        return None
    if len(pair) != 2 or pair[0] > pair[1] or any(abs(v) > MAX_VALUE for v in pair):
        t.problem(key, f"expected {expected}, got {list(pair)!r}")
        return None
    return pair[0], pair[1]


def parse_coverage(t: Table, factors: Sequence[str], columns: Sequence[str] = ()) -> Coverage | None:
    """Read ``[coverage]``; ``None`` after reporting a problem. ``columns``: the recorded columns the model reads."""
    source = t.str("source", default="")
    on_share = t.float("on_share", default=ON_SHARE, min=0.0, max=1.0, min_exclusive=True,
                       expected="the share of its highest deviation a ratio's denominator must reach, in (0, 1]")
    margin = t.float("margin", default=MARGIN, min=0.0, max=100.0,
                     expected="the tolerance beyond a covered range, a share of it, in [0, 100]")
    ok = on_share is not None and margin is not None
    ranges = _pairs(t, "range", factors, required=True, table="a table of factor -> [lowest, highest] deviation",
                    unknown=f"not a factor of this model (factors: {', '.join(factors)})",
                    pair="[lowest, highest] deviation of the factor in the identification data, lowest <= highest")
    ratios = []
    qt = t.table("ratio", expected='a table of "of/per" -> [lowest, highest] ratio')
    if qt is not None:
        for key in qt:
            parts = key.split("/")
            if len(parts) != 2 or parts[0] not in factors or parts[1] not in factors or parts[0] == parts[1]:
                qt.problem(key, f'expected a key "of/per" naming two different factors of this model (factors: '
                                f'{", ".join(factors)})')
                qt.raw(key)
                ok = False
                continue
            pair = _pair(qt, key, "[lowest, highest] ratio of the two factors' deviations, lowest <= highest")
            if pair is None:
                ok = False
            else:
                ratios.append(Ratio(of=parts[0], per=parts[1], low=pair[0], high=pair[1]))
        qt.done()
    covered = _pairs(t, "column", columns, table="a table of recorded column -> [lowest, highest] value",
                     unknown="not a recorded column an input of this model reads ("
                     + (f"columns: {', '.join(columns)}" if columns else "it reads none") + ")",
                     pair="[lowest, highest] value of the column in the data the model was fitted on, lowest <= "
                          "highest")
    t.done()
    if not ok or ranges is None or covered is None:
        return None
    return Coverage(ranges=ranges, ratios=tuple(ratios), source=source or "", on_share=on_share, margin=margin,
                    columns=covered)


def _pairs(t: Table, key: str, names: Sequence[str], *, table: str, unknown: str, pair: str,
           required: bool = False) -> dict[str, tuple[float, float]] | None:
    """The table ``key`` of name -> [lowest, highest] for ``names`` (``{}`` when absent); ``None`` after a problem."""
    out: dict[str, tuple[float, float]] = {}
    sub = t.table(key, required=required, expected=table)
    if sub is None:
        return None if required else out
    ok = True
    for name in sub:
        if name not in names:
            sub.problem(name, unknown)
            sub.raw(name)
            ok = False
            continue
        got = _pair(sub, name, pair)
        if got is None:
            ok = False
        else:
            out[name] = got
    sub.done()
    return out if ok else None


def describe_coverage(cov: Coverage | None, units: Mapping[str, str] | None = None) -> list[str]:
    """Lines for ``cncgw model show``."""
    if cov is None:
        return ["coverage: none recorded (a model written before cncgw recorded one: estimates are not checked "
                "against the identification's factor region)"]
    units = units or {}
    lines = [f"coverage ({cov.source or 'source not stated'}): deviations from the reference"]
    for f, (lo, hi) in cov.ranges.items():
        u = f" {units[f]}" if units.get(f) else ""
        lines.append(f"  {f}: {lo:.4g} .. {hi:.4g}{u}")
    for r in cov.ratios:
        lines.append(f"  {r.of} per {r.per}: {r.low:.4g} .. {r.high:.4g} (where {r.per} >= "
                     f"{cov.on_share:g} of its highest)")
    for c, (lo, hi) in cov.columns.items():
        lines.append(f"  recorded column {c}: {lo:.4g} .. {hi:.4g} (its values)")
    return lines


__all__ = ["Coverage", "CoverageCheck", "Excursion", "Ratio", "check_coverage", "co_varying_pairs", "column_ranges",
           "coverage_of", "coverage_to_toml", "describe_coverage", "parse_coverage"]
