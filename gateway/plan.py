"""Experiment design: the next experiments that most reduce the uncertainty of what a production schedule uses.

``cncgw plan --profile P EXPERIMENTS... --production RECORDINGS...``:

1. The experiments are identified (joint method, no path pruned, so every path has its time constants).
2. With those time constants held, every axis is linear in its term gains. Their uncertainty is a Gaussian
   posterior: the experiments' information (each recording with its own free offset, the residual
   variance inflated for autocorrelation) plus the identification's gain prior
   (:mod:`gateway.identify.shrink`, kappa as identification chose it, or 1), so a factor the experiments
   never moved keeps the prior's width instead of an infinite one.
3. The production recordings (factors only: displacement is not needed) give the target: per axis the
   variance of the predicted displacement, averaged over the production windows, relative to the square
   of the axis's predicted production peak (V-optimal design: the uncertainty where production goes).
4. Candidates are built from production's own operating states (its windows grouped by factor levels
   relative to their production maxima, the most frequent first): each state held for 1-8 h from rest,
   and stairs of two or three states in increasing order, every candidate at most ``max_hours`` long with
   rest after it. A candidate's factors are the state's levels (what the machine showed in production),
   so it needs no model of the drives.
5. Greedily, the candidate that lowers the summed relative variance most is taken, its information added,
   and so on, up to ``max_experiments``, while one still lowers it by at least ``MIN_GAIN``; among
   candidates within 5 % of the best the shortest wins.

Held fixed and said so: the time constants (their uncertainty is not in the variance) and the
structure. What a proposal must reach is read from the model's coverage: the factor levels and ratios of
co-varying factors beyond what the experiments covered.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from gateway.errors import IdentificationError
from gateway.identify.api import IdentifyResult
from gateway.model.coverage import check_coverage
from gateway.model.model import PathTF, ThermalModel
from gateway.model.terms import FirstOrder
from gateway.prepare import Prepared

#: a proposal is kept only when it lowers the summed relative variance by at least this share
MIN_GAIN = 0.05
#: operating states: production windows grouped on this grid of levels relative to their production maxima
STATE_GRID = 0.2
#: at most this many states make candidates
MAX_STATES = 8
#: (hours on, total hours) of a single-state candidate
STEPS = ((1.0, 6.0), (2.0, 6.0), (4.0, 8.0), (4.0, 12.0), (8.0, 12.0))
#: rest before a candidate's first state (min): the experiment starts in equilibrium
LEAD_IN_MIN = 30.0
#: a state cuts when the ratio of two spindle current factors (rotor to stator current squared) lies beyond the
#: experiments' covered range by more than the coverage margin, with the larger one at least this share of its
#: production maximum
CUT_SHARE = 0.1
#: units a spindle speed factor is given in
SPEED_UNITS = ("rpm", "1/min", "min^-1", "min-1")


@dataclass(frozen=True, kw_only=True)
class State:
    """An operating state production spends time in: factor deviations, hours, a label."""

    levels: Mapping[str, float]
    hours: float
    label: str
    #: the spindle current factors above their no-load level at this speed: production cut here, and an
    #: experiment reaches these levels only by cutting a test piece at this speed
    cutting: bool = False


@dataclass(frozen=True, kw_only=True)
class Proposal:
    """One proposed experiment: states held in turn after a rest, then rest to ``hours``."""

    name: str
    steps: tuple[tuple[State, float], ...]  # (state, minutes)
    hours: float
    #: per axis: the production estimate's standard uncertainty (um, RMS over the windows) before and after
    sd_um: Mapping[str, tuple[float, float]]
    reaches: tuple[str, ...] = ()  # the factor levels and ratios beyond the coverage it must reach
    relative_variance: float = 0.0  # the design criterion after it (summed over axes)

    @property
    def cuts(self) -> bool:
        """Whether a step cuts (on a real machine: a test piece cut at the step's speed and currents)."""
        return any(s.cutting for s, _ in self.steps)

    def describe(self) -> str:
        body = "; then ".join(f"{m / 60:.3g} h at {s.label}" for s, m in self.steps)
        text = f"{self.name} ({self.hours:.3g} h): {LEAD_IN_MIN:g} min at rest, {body}; then at rest"
        if self.cuts:
            text += (" (cutting: hold the spindle at the step's speed and cut a test piece with a load that brings "
                     "its currents to the step's levels, as production's cutting jobs did)")
        return text


@dataclass(kw_only=True)
class PlanResult:
    """What ``cncgw plan`` proposes and the figures behind it."""

    proposals: list[Proposal]
    states: list[State]
    #: per axis: the production estimate's uncertainty (um, RMS over windows) from the experiments alone
    sd_before_um: dict[str, float]
    relative_variance_before: float
    candidates: int
    notes: list[str] = field(default_factory=list)


def _terms(model: ThermalModel, axis: str, factor: str, default_tau_s: float) -> PathTF:
    p = model.path(axis, factor)
    if p.kind != "zero":
        return PathTF(axis=axis, factor=factor, terms=tuple(t.with_gain(1.0) for t in p.terms), delay_s=p.delay_s)
    return PathTF(axis=axis, factor=factor, terms=(FirstOrder(gain=1.0, tau_s=default_tau_s),))


class AxisDesign:
    """One axis's term-gain regressors at fixed time constants, its prior and its experiments' information."""

    def __init__(self, model: ThermalModel, axis: str, dt_s: float, *, sigma2: float, d_um: float, kappa: float,
                 u_max: np.ndarray) -> None:
        taus = [t for f in model.factors for term in model.path(axis, f).terms for t in term.time_constants_s]
        default = float(np.exp(np.mean(np.log(taus)))) if taus else 3600.0
        self.axis = axis
        self.factors = model.factors
        self.sections = []  # (factor index, section)
        for j, f in enumerate(model.factors):
            for _, sec in _terms(model, axis, f, default).sections(dt_s):
                self.sections.append((j, sec))
        self.p = len(self.sections)
        self.sigma2 = sigma2
        owner = np.array([j for j, _ in self.sections])
        prior = np.zeros((self.p, self.p))
        k = kappa if math.isfinite(kappa) else 1.0
        for j in range(len(model.factors)):
            cols = owner == j
            if not cols.any():
                continue
            scale = max(u_max[j], 1e-12) / max(k * d_um, 1e-12)
            v = cols.astype(float)
            # on the static gain as identification's prior, and ten times weaker on each term (a two-mode
            # path's shape stays nearly free, but never infinitely uncertain)
            prior += scale**2 * np.outer(v, v) + (0.1 * scale) ** 2 * np.diag(v)
        self.prior = prior
        self.info = prior.copy()

    def regressors(self, du: np.ndarray) -> np.ndarray:
        """(N, p): every term's unit response to ``du`` (factors, N), from rest."""
        return np.column_stack([sec.filter(np.nan_to_num(du[j])) for j, sec in self.sections])

    def information(self, du: np.ndarray) -> np.ndarray:
        """What a recording of ``du`` adds (its own offset free)."""
        X = self.regressors(du)
        X = X - X.mean(axis=0)
        return X.T @ X / self.sigma2


def spindle_factors(factors: Sequence[str], units: Mapping[str, str], coverage) -> tuple[str | None, tuple[str, ...]]:
    """The spindle speed factor and the current factors the experiments moved with it, or (None, ()).

    The speed factor is the one factor given in a speed unit (``SPEED_UNITS``); its current factors are those
    the model's coverage holds a co-varying ratio of per that speed.
    """
    speeds = [f for f in factors if units.get(f, "").strip().lower() in SPEED_UNITS]
    if len(speeds) != 1 or coverage is None:
        return None, ()
    return speeds[0], tuple(r.of for r in coverage.ratios if r.per == speeds[0])


def is_cutting(levels: Mapping[str, float], coverage, loads: Sequence[str], top: Mapping[str, float]) -> bool:
    """Whether a state's spindle currents show a cutting load (a ratio beyond the experiments' no-load running).

    At constant speed without a cut only friction loads the spindle, so the torque-carrying (rotor) current is
    small beside the magnetising (stator) one; accelerating raises both, a cut raises the torque current at
    speed for as long as it lasts. A ratio (of / per, both co-varying with the speed) above the highest the
    experiments covered, by more than the coverage margin, with ``of`` at least ``CUT_SHARE`` of its production
    maximum ``top``, is a cut.
    """
    if coverage is None:
        return False
    for r in coverage.ratios:
        if r.of in loads and r.per in loads and r.high > 0:
            of, per = levels.get(r.of, 0.0), levels.get(r.per, 0.0)
            if per > 0 and of > CUT_SHARE * top.get(r.of, 0.0) and of / per > r.high * (1.0 + coverage.margin):
                return True
    return False


def operating_states(preps: Sequence[Prepared], factors: Sequence[str], units: Mapping[str, str],
                     reference: Mapping[str, float], *, max_states: int = MAX_STATES, coverage=None,
                     loads: Sequence[str] = ()) -> list[State]:
    """Production windows grouped by their factor levels relative to the production maxima, most frequent first.

    With the model's ``coverage`` and the spindle's current factors ``loads``, a state whose currents show a
    cut (:func:`is_cutting`) is marked ``cutting``.
    """
    du = np.concatenate([np.nan_to_num(p.du[: len(factors)]) for p in preps], axis=1)
    dt = preps[0].dt_s
    top = np.maximum(np.abs(du).max(axis=1), 1e-300)
    rel = du / top[:, None]
    on = np.any(rel > 0.1, axis=0)
    keys: dict[tuple[int, ...], list[int]] = {}
    for k in np.flatnonzero(on):
        keys.setdefault(tuple(np.round(rel[:, k] / STATE_GRID).astype(int).tolist()), []).append(int(k))
    groups = sorted(keys.values(), key=len, reverse=True)[:max_states]
    out = []
    for g in groups:
        levels = {f: float(np.median(du[j, g])) for j, f in enumerate(factors)}
        shown = [f"{f} {levels[f] + reference.get(f, 0.0):.4g}{(' ' + units[f]) if units.get(f) else ''}"
                 for j, f in enumerate(factors) if abs(levels[f]) > 0.05 * top[j]]
        cutting = is_cutting(levels, coverage, loads, {f: float(top[j]) for j, f in enumerate(factors)})
        label = (", ".join(shown) or "rest") + (" (cutting)" if cutting else "")
        out.append(State(levels=levels, hours=len(g) * dt / 3600.0, label=label, cutting=cutting))
    return out


def _schedule(steps: Sequence[tuple[State, float]], hours: float, factors: Sequence[str], dt_s: float) -> np.ndarray:
    n = round(hours * 3600.0 / dt_s)
    du = np.zeros((len(factors), n))
    k = round(LEAD_IN_MIN * 60.0 / dt_s)
    for state, minutes in steps:
        m = round(minutes * 60.0 / dt_s)
        du[:, k: k + m] = np.array([state.levels[f] for f in factors])[:, None]
        k += m
    return du


def candidates(states: Sequence[State], max_hours: float) -> list[tuple[str, tuple[tuple[State, float], ...], float]]:
    """(name, steps, total hours) of every candidate, each at most ``max_hours`` long."""
    out = []
    for i, s in enumerate(states):
        for on_h, total in STEPS:
            if total <= max_hours + 1e-9:
                out.append((f"state {i + 1} for {on_h:g} h", ((s, on_h * 60.0),), total))
    def norm(s: State) -> float:
        return sum(abs(v) / max(max(abs(t.levels[f]) for t in states), 1e-300) for f, v in s.levels.items())

    by_size = sorted(states, key=norm)
    for n_steps, step_h in ((2, 2.0), (3, 2.0), (3, 3.0)):
        for first in range(len(by_size) - n_steps + 1):
            chain = tuple((by_size[first + k], step_h * 60.0) for k in range(n_steps))
            total = min(max_hours, LEAD_IN_MIN / 60.0 + n_steps * step_h + 4.0)
            if LEAD_IN_MIN / 60.0 + n_steps * step_h < total:
                idx = [states.index(s) + 1 for s, _ in chain]
                out.append((f"stairs of states {'-'.join(map(str, idx))}, {step_h:g} h each", chain, total))
    return out


def plan(result: IdentifyResult, experiments: Sequence[Prepared], production: Sequence[Prepared], *,
         max_experiments: int = 3, max_hours: float = 12.0) -> PlanResult:
    """Propose up to ``max_experiments`` experiments (module docstring). ``result``: the experiments' identification."""
    model = result.model
    factors = model.factors
    if not production:
        raise IdentificationError("plan needs production recordings (--production): the experiments are chosen "
                                  "for what production uses")
    dt = experiments[0].dt_s
    if any(abs(p.dt_s - dt) > 1e-9 * dt for p in production):
        raise IdentificationError(f"production recordings and experiments have different window lengths: expected "
                                  f"{dt:g} s in every one")
    u_max = np.max([np.abs(np.nan_to_num(p.du[: len(factors)])).max(axis=1) for p in [*experiments, *production]],
                   axis=0)
    sel = {s.axis: s for s in result.selections}
    shr = {s.axis: s for s in result.shrinkage}
    designs: dict[str, AxisDesign] = {}
    peaks: dict[str, float] = {}
    prod_gram: dict[str, np.ndarray] = {}
    prod_rows: dict[str, list[np.ndarray]] = {}
    dm = model.discretize(dt)
    for i, a in enumerate(model.axes):
        s = sel.get(a)
        if s is None:
            continue
        sigma2 = s.chosen.rss / max(s.chosen.n, 1) * (s.chosen.n / max(s.n_eff, 1.0))
        d_um = max(float(np.nanmax(p.y[i]) - np.nanmin(p.y[i])) for p in experiments if np.isfinite(p.y[i]).any())
        kappa = shr[a].kappa if a in shr else 1.0
        d = AxisDesign(model, a, dt, sigma2=sigma2, d_um=d_um, kappa=kappa, u_max=u_max)
        for p in experiments:
            if np.isfinite(p.y[i]).any():
                d.info += d.information(p.du)
        rows = [d.regressors(p.du) for p in production]
        prod_rows[a] = rows
        n = sum(r.shape[0] for r in rows)
        prod_gram[a] = sum(r.T @ r for r in rows) / n
        # with the days before each recording a daily-start column runs (Prepared.lead), as estimate does
        n_in = len(model.input_names)
        peaks[a] = max(max(float(np.abs(dm.simulate(p.du[:n_in], None if p.lead is None else p.lead[:n_in])[i]).max())
                           for p in production), 1e-9)
        designs[a] = d

    def criterion(infos: Mapping[str, np.ndarray]) -> tuple[float, dict[str, float]]:
        total, sd = 0.0, {}
        for a, _d in designs.items():
            cov = np.linalg.pinv(infos[a], rcond=1e-14, hermitian=True)
            var = float(np.trace(cov @ prod_gram[a]))
            sd[a] = math.sqrt(max(var, 0.0))
            total += var / peaks[a] ** 2
        return total, sd

    infos = {a: d.info for a, d in designs.items()}
    j0, sd0 = criterion(infos)
    speed, loads = spindle_factors(factors, model.units, model.coverage)
    states = operating_states(production, factors, model.units, model.reference, coverage=model.coverage,
                              loads=loads)
    cands = candidates(states, max_hours)
    cand_info = []
    for name, steps, hours in cands:
        du = _schedule(steps, hours, factors, dt)
        cand_info.append((name, steps, hours, du, {a: d.information(du) for a, d in designs.items()}))
    proposals: list[Proposal] = []
    current, j_cur, sd_cur = infos, j0, sd0
    for k in range(max_experiments):
        scored = []
        for name, steps, hours, du, add in cand_info:
            j, sd = criterion({a: current[a] + add[a] for a in designs})
            scored.append((j, hours, name, steps, du, add, sd))
        if not scored:
            break
        best = min(s[0] for s in scored)
        if best > (1.0 - MIN_GAIN) * j_cur:
            break
        # among the candidates within 5 % of the best reduction, the shortest
        gain = j_cur - best
        j, hours, name, steps, du, add, sd = min((s for s in scored if j_cur - s[0] >= 0.95 * gain),
                                                 key=lambda s: (s[1], s[0]))
        reaches = ()
        if model.coverage is not None:
            check = check_coverage(model.coverage, du, factors, model.units)
            reaches = tuple(f"{e.what} {('up to' if e.side == 'above' else 'down to')} {e.how_far()}"
                            for e in check.excursions)
        proposals.append(Proposal(name=f"experiment {k + 1}: {name}", steps=steps, hours=hours,
                                  sd_um={a: (sd_cur[a], sd[a]) for a in designs}, reaches=reaches,
                                  relative_variance=j))
        current = {a: current[a] + add[a] for a in designs}
        j_cur, sd_cur = j, sd
    notes = [f"time constants and structures held at the experiments' identification; the uncertainty is of the "
             f"gains only ({len(cands)} candidates from {len(states)} production states)"]
    if speed is None:
        notes.append("no spindle speed factor (unit rpm) with current factors the experiments moved with it: cutting "
                     "loads were not looked for")
    else:
        n_cut = sum(s.cutting for s in states)
        notes.append(f"{n_cut} of {len(states)} production states cut (a ratio of {', '.join(loads)} beyond the "
                     f"experiments' no-load running)" if n_cut else
                     f"no production state cuts (the ratios of {', '.join(loads)} within the experiments' no-load "
                     f"running)")
    return PlanResult(proposals=proposals, states=states, sd_before_um=sd0, relative_variance_before=j0,
                      candidates=len(cands), notes=notes)
