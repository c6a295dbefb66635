"""Recordings prepared for a model and stacked end to end, with the responses hypotheses are made of.

Every recording starts from its own initial equilibrium (the model works on deviations), so responses are
filtered per recording, from rest, and concatenated. A :class:`Part` is one input through some terms
behind a dead time; a :class:`Component` is a sum of parts sharing one fitted gain. Columns of the
regression are the components' responses, computed with the model's own discretisation
(:class:`~gateway.model.discrete.Section`), so an accepted hypothesis written into the model file predicts
exactly what diagnosis fitted.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gateway.errors import GatewayError
from gateway.model.coverage import check_coverage
from gateway.model.inputs import DAY_S, Column, DerivedInput, evaluate_inputs, hold_missing, initial_values, start_leads
from gateway.model.model import PathTF, ThermalModel
from gateway.model.terms import FirstOrder, Term
from gateway.prepare import MIN_PROBE_POINTS, Prepared, prepare
from gateway.recording import Recording, split_file, split_part
from gateway.replay import LEAD_IN_MAX


class DiagnosisError(GatewayError):
    """Diagnosis cannot proceed (no measured displacement, nothing to compare)."""

    exit_code = 10


@dataclass(frozen=True, slots=True)
class Part:
    """Input ``input`` (a factor or a derived input) through ``terms`` behind ``delay_s``."""

    input: str
    terms: tuple[Term, ...]
    delay_s: float = 0.0


@dataclass(frozen=True, slots=True)
class Component:
    """Parts that share one fitted gain: the gain scales every part's terms."""

    parts: tuple[Part, ...]
    label: str = ""
    #: the gain of an identified path itself (the input whose path it scales): a re-identification refits
    #: that path anyway, so it drops such a component
    corrects: str = ""


def lag(tau_s: float) -> tuple[Term, ...]:
    """One unit-gain first-order lag."""
    return (FirstOrder(gain=1.0, tau_s=float(tau_s)),)


@dataclass(kw_only=True)
class Stack:
    """Recordings prepared with the model and stacked: every array has one entry per window (N)."""

    names: tuple[str, ...]
    sources: tuple[str, ...]
    dt_s: float
    bounds: tuple[tuple[int, int], ...]
    time_s: np.ndarray
    present: np.ndarray
    axes: tuple[str, ...]
    factors: tuple[str, ...]
    du: dict[str, np.ndarray]  # deviations of every model input, per recording from its start
    raw: dict[str, np.ndarray]  # factor values (gaps filled by the policy)
    extras: dict[str, np.ndarray]  # other numeric columns (NaN where a recording lacks them)
    y: np.ndarray  # (A, N) measured displacement, NaN where not measured
    base: np.ndarray  # (A, N) the model's prediction
    contributions: np.ndarray  # (A, inputs, N) the model's prediction per input
    notes: list[str] = field(default_factory=list)
    fingerprints: tuple[str, ...] = ()  # per recording (:meth:`Recording.fingerprint` of the model's factors)
    #: (A, N) the stated uncertainty of each measured value (probes' probe_sd_um), NaN where none is stated
    y_sd: np.ndarray | None = None
    #: per recording: measured only at probe instants (:attr:`gateway.prepare.Prepared.sparse`)
    sampled: tuple[bool, ...] = ()
    #: per recording, the windows of work run before its own first window (a start fitted as hours of work, see
    #: :func:`gateway.diagnose.api.start_histories`): no displacement there; times are told from its own start
    lead: tuple[int, ...] = ()
    #: per recording: its time stamps are the clock's (:attr:`gateway.recording.Recording.clock`; empty: all are)
    clock: tuple[bool, ...] = ()
    #: per model input that starts from days before each recording (a daily-start column, see
    #: :func:`gateway.model.inputs.daily_start`), its deviations over them, per recording (empty: none)
    leads: dict[str, tuple[np.ndarray, ...]] = field(default_factory=dict)
    _cache: dict[object, object] = field(default_factory=dict, repr=False)

    @property
    def n(self) -> int:
        return len(self.time_s)

    @property
    def labels(self) -> list[str]:
        """Per recording, its short name in reports (:func:`recording_labels`: distinct where files share one)."""
        key = "labels"
        if key not in self._cache:
            self._cache[key] = recording_labels(self.sources)
        return self._cache[key]  # type: ignore[return-value]

    def identified(self, model: ThermalModel) -> list[bool]:
        """Per recording, whether ``model`` was identified on it.

        One of its experiments (by name or content) or a production run joined with ``identify --production``
        (by content only: production files are named ``day1.csv`` on every machine, and a name alone would take
        an unseen day for a trained one).
        """
        return [identified_on(model, name, fp)
                for name, fp in zip(self.names, self.fingerprints or [""] * len(self.names), strict=True)]

    def own_start(self, r: int) -> int:
        """The index of recording ``r``'s own first window (after the work run before it, if any)."""
        return self.bounds[r][0] + (self.lead[r] if self.lead else 0)

    def longest_s(self) -> float:
        """The longest recording's own length (the work run before one, if any, not counted), in seconds."""
        return max((b - self.own_start(r) for r, (_, b) in enumerate(self.bounds)), default=0) * self.dt_s

    def day_covered(self, bins: int = 96) -> float:
        """The share of the 24 h clock the recordings' own windows cover together (their time stamps' time of day).

        Recordings without a clock (:attr:`clock`: a file read with a row period) cover nothing of it.
        """
        hit = np.zeros(bins, dtype=bool)
        for r, (_, b) in enumerate(self.bounds):
            if self.clock and not self.clock[r]:
                continue
            t = self.time_s[self.own_start(r):b]
            hit[np.minimum((np.mod(t, DAY_S) * bins // DAY_S).astype(int), bins - 1)] = True
        return float(hit.mean())

    def start_s(self, r: int) -> float:
        """The time of recording ``r``'s own first window."""
        return float(self.time_s[self.own_start(r)])

    @property
    def own_windows(self) -> int:
        """Windows of the recordings themselves: the stack without the work run before some of them."""
        return self.n - sum(self.lead)

    def rec_index(self) -> np.ndarray:
        out = np.empty(self.n, dtype=int)
        for r, (a, b) in enumerate(self.bounds):
            out[a:b] = r
        return out

    def rel_time_s(self) -> np.ndarray:
        """Seconds since each recording's first window."""
        out = np.empty(self.n)
        for a, b in self.bounds:
            out[a:b] = self.time_s[a:b] - self.time_s[a]
        return out

    # -- inputs and responses ------------------------------------------------------------------------------
    def input_du(self, name: str, chain: tuple[DerivedInput, ...] = ()) -> np.ndarray:
        """Deviations of a model input, or of an input of ``chain`` (derived inputs, in order; cached)."""
        if not any(d.name == name for d in chain):
            return self.du[name]
        return self._chain(chain)[0][name]

    def input_lead(self, name: str, chain: tuple[DerivedInput, ...] = ()) -> tuple[np.ndarray, ...] | None:
        """Per recording, the deviations of an input over the days run before it (:attr:`leads`); None: none."""
        if not any(d.name == name for d in chain):
            return self.leads.get(name)
        return self._chain(chain)[1].get(name)

    def _chain(self, chain: tuple[DerivedInput, ...]) -> tuple[dict[str, np.ndarray],
                                                                dict[str, tuple[np.ndarray, ...]]]:
        key = ("inputs", chain)
        if key not in self._cache:
            self._cache[key] = self._derived(chain)
        return self._cache[key]  # type: ignore[return-value]

    def _derived(self, chain: tuple[DerivedInput, ...]) -> tuple[dict[str, np.ndarray],
                                                                  dict[str, tuple[np.ndarray, ...]]]:
        """The chain's deviations (as :func:`gateway.prepare.prepare` computes them) and its daily-start leads."""
        out = {d.name: np.zeros(self.n) for d in chain}
        leads: dict[str, list[np.ndarray]] = {}
        cols_needed = [d.column for d in chain if isinstance(d, Column)]
        for a, b in self.bounds:
            sig = {f: self.raw[f][a:b] for f in self.factors}
            cols = {c: self.extras[c][a:b] for c in cols_needed}
            initial = {f: float(v[0]) for f, v in sig.items()}
            initial |= {c: float(hold_missing(v)[0]) for c, v in cols.items()}
            cols, by_column, _ = start_leads(chain, self.time_s[a:b], cols, self.dt_s)
            values = evaluate_inputs(chain, sig, time_s=self.time_s[a:b], dt_s=self.dt_s, columns=cols,
                                     initial=initial)
            start = initial_values(chain, initial, time0_s=float(self.time_s[a]))
            for d in chain:
                out[d.name][a:b] = values[d.name] - start[d.name]
                if isinstance(d, Column) and d.start == "daily":
                    leads.setdefault(d.name, []).append(by_column[d.column] - start[d.name]
                                                        if d.column in by_column else np.zeros(0))
        return out, {k: tuple(v) for k, v in leads.items() if any(x.size for x in v)}

    def response(self, u: np.ndarray, terms: Sequence[Term], delay_s: float = 0.0,
                 lead: Sequence[np.ndarray] | None = None) -> np.ndarray:
        """Response of ``terms`` (with their gains) behind ``delay_s`` to ``u``, each recording from rest.

        ``lead``: per recording, ``u`` over the windows before it, run first (:attr:`leads`).
        """
        out = np.zeros(self.n)
        if not terms:
            return out
        path = PathTF(axis="x", factor="u", terms=tuple(terms), delay_s=delay_s)
        for gain, sec in path.sections(self.dt_s):
            if gain == 0.0:
                continue
            for r, (a, b) in enumerate(self.bounds):
                out[a:b] += gain * sec.filter(u[a:b], None if lead is None else lead[r])
        return out

    def column(self, comp: Component, chain: tuple[DerivedInput, ...] = ()) -> np.ndarray:
        """The response of a component at unit gain (cached by its definition)."""
        key = ("component", comp, chain)
        if key not in self._cache:
            total = np.zeros(self.n)
            for p in comp.parts:
                total += self.response(self.input_du(p.input, chain), p.terms, p.delay_s,
                                       self.input_lead(p.input, chain))
            if len(self._cache) > 20000:  # a long search: keep memory bounded
                self._cache.clear()
            self._cache[key] = total
        return self._cache[key]  # type: ignore[return-value]

    def lead_in(self, r: int) -> np.ndarray:
        """The windows of recording ``r`` its measured zero is taken from, as ``cncgw estimate`` aligns it.

        Its idle lead-in: the windows before any factor moves (at most ``LEAD_IN_MAX``, at least the first).
        """
        lo, hi = self.bounds[r]
        moving = np.zeros(hi - lo, dtype=bool)
        for f in self.factors:
            u = self.du[f][lo:hi]
            size = float(np.max(np.abs(u))) if u.size else 0.0
            if size > 0:
                moving |= np.abs(u) > 0.01 * size
        first = np.flatnonzero(moving)
        out = np.zeros(hi - lo, dtype=bool)
        out[: max(1, min(int(first[0]) if first.size else hi - lo, LEAD_IN_MAX))] = True
        return out

    def is_signal(self, col: str) -> bool:
        """Whether recorded column ``col`` varies and is no counter: a physical signal to try as an input.

        A counter is, in every recording, a row index or a day number (whole numbers that never fall) or a clock
        (values rising linearly with time); one that starts again in each run of a split file (``sample_index``
        of a file of days) is a counter too, where the stacked column falls at every run's start.
        """
        v = self.extras[col]
        if not np.isfinite(v).any() or np.nanstd(v) == 0:
            return False
        for a, b in self.bounds:
            ok = np.isfinite(v[a:b])
            x, t = v[a:b][ok], self.time_s[a:b][ok]
            if len(x) < 2:
                continue
            rising = bool(np.all(np.diff(x) >= 0) and np.allclose(x, np.round(x)))
            span = float(np.ptp(x))
            clock = span > 0 and bool(np.allclose(x, np.polyval(np.polyfit(t, x, 1), t), rtol=0, atol=1e-6 * span))
            if not (rising or clock):
                return True
        return False

    def per_recording(self) -> list[np.ndarray]:
        """Indicator columns, one per recording (free offsets: sensors are zeroed anywhere)."""
        cols = []
        for a, b in self.bounds:
            c = np.zeros(self.n)
            c[a:b] = 1.0
            cols.append(c)
        return cols

    def decays(self, tau_s: float) -> list[np.ndarray]:
        """exp(-t / tau) from each recording's start: an unknown initial state of a mode with ``tau_s`` (cached)."""
        return self._decays_from("decays", tau_s, self.bounds)

    def history_decays(self, tau_s: float) -> list[np.ndarray]:
        """exp(-t / tau) from the own first window of each recording that runs from a fitted history (``lead``).

        What that history leaves there is a guess (hours of work its first hours show): a free decay per mode
        lets a fit take the guess's error beside the paths instead of in them.
        """
        return self._decays_from("history decays", tau_s, [(self.own_start(r), b) for r, (_, b) in
                                                           enumerate(self.bounds) if self.lead and self.lead[r]])

    def _decays_from(self, kind: str, tau_s: float, spans: Sequence[tuple[int, int]]) -> list[np.ndarray]:
        """exp(-t / tau) over each span (start, end) of windows, t from one window before its start (cached)."""
        key = (kind, tau_s)
        if key in self._cache:
            return self._cache[key]  # type: ignore[return-value]
        cols = []
        for a, b in spans:
            c = np.zeros(self.n)
            c[a:b] = np.exp(-(self.time_s[a:b] - self.time_s[a] + self.dt_s) / tau_s)
            cols.append(c)
        self._cache[key] = cols
        return cols

    def ramps(self, tau_s: float = 0.0) -> list[np.ndarray]:
        """Hours since each recording's start (a sensor's linear drift), through a lag of ``tau_s`` if > 0.

        Through a lag: the machine's answer to a slow change of its surroundings (the weather moving the
        room's mean) that began with the recording, as the structure's thermal mass smooths it.
        """
        key = ("ramps", tau_s)
        if key in self._cache:
            return self._cache[key]  # type: ignore[return-value]
        t = self.rel_time_s() / 3600.0
        cols = []
        for a, b in self.bounds:
            c = np.zeros(self.n)
            c[a:b] = t[a:b]
            cols.append(self.response(c, lag(tau_s)) if tau_s > 0 else c)
        self._cache[key] = cols
        return cols


def identified_on(model: ThermalModel, name: str, fingerprint: str) -> bool:
    """Whether ``model`` was identified on the recording ``name`` of ``fingerprint`` (:meth:`Stack.identified`)."""
    names = set(model.info.get("experiments", []) or [])
    prints = set(model.info.get("experiment_fingerprints", []) or [])
    prints |= set(model.info.get("production_fingerprints", []) or [])
    return name in names or (bool(fingerprint) and fingerprint in prints)


def build_stack(model: ThermalModel, recordings: Sequence[Recording], *, gap_policy: str = "hold") -> Stack:
    """Prepare every recording for ``model`` and stack them; checks that they can be compared at all."""
    if not recordings:
        raise DiagnosisError("no recordings given")
    dts = {round(r.period_s, 9) for r in recordings}
    if len(dts) != 1:
        raise DiagnosisError("recordings have different window lengths: " +
                             ", ".join(f"{r.name} {r.period_s:g} s" for r in recordings))
    dt = recordings[0].period_s
    dm = model.discretize(dt)
    names, srcs, bounds, notes, prints = [], [], [], [], []
    times, present, ys, bases, contribs = [], [], [], [], []
    du: dict[str, list[np.ndarray]] = {k: [] for k in model.input_names}
    leads: dict[str, list[np.ndarray]] = {k: [] for k in model.input_names}
    raw: dict[str, list[np.ndarray]] = {f: [] for f in model.factors}
    extra_names = sorted({k for r in recordings for k in r.extras})
    extras: dict[str, list[np.ndarray]] = {k: [] for k in extra_names}
    start = 0
    sds, sampled = [], []
    # notes name each recording as it is known (its file's stem); files of the same name by their folders too
    stems = [r.name for r in recordings]
    called = [name if stems.count(name) == 1 else label
              for name, label in zip(stems, recording_labels([r.source for r in recordings]), strict=True)]
    for rec, call in zip(recordings, called, strict=True):
        p = prepare(rec, factors=model.factors, axes=model.axes, initial="first", gap_policy=gap_policy,
                    inputs=model.inputs, probe_points=True)
        notes += [f"{call}: {n}" for n in p.notes]
        notes += _measured_note(p, rec, model.axes)
        sds.append(p.y_sd if p.y_sd is not None else np.full(p.y.shape, np.nan))
        sampled.append(p.sparse)
        if model.coverage is not None:  # where the model extrapolates, a residual is not missing physics alone
            notes += [f"{call}: {n}" for n in
                      check_coverage(model.coverage, p.du, model.factors, model.units,
                                     columns=model.coverage.columns_of(rec.extras)).notes(dt)]
        names.append(p.name)
        srcs.append(rec.source)
        prints.append(rec.fingerprint(model.factors))
        bounds.append((start, start + p.n))
        start += p.n
        times.append(p.time_s)
        present.append(p.present)
        ys.append(p.y)
        c = dm.contributions(p.du, p.lead)
        contribs.append(c)
        bases.append(c.sum(axis=1))
        for j, k in enumerate(model.input_names):
            du[k].append(p.du[j])
            leads[k].append(p.lead[j] if p.lead is not None and np.any(p.lead[j]) else np.zeros(0))
        for j, f in enumerate(model.factors):
            raw[f].append(p.du[j] + p.u0[j])
        for k in extra_names:
            extras[k].append(np.asarray(rec.extras[k], float) if k in rec.extras else np.full(p.n, np.nan))
    y = np.concatenate(ys, axis=1)
    if not np.isfinite(y).any():
        raise DiagnosisError("no recording has measured displacement on any of the model's axes "
                             f"({', '.join(model.axes)}): diagnosis compares measured with simulated")
    return Stack(names=tuple(names), sources=tuple(srcs), dt_s=dt, bounds=tuple(bounds),
                 time_s=np.concatenate(times), present=np.concatenate(present), axes=model.axes,
                 factors=model.factors, du={k: np.concatenate(v) for k, v in du.items()},
                 raw={k: np.concatenate(v) for k, v in raw.items()},
                 extras={k: np.concatenate(v) for k, v in extras.items()}, y=y,
                 base=np.concatenate(bases, axis=1), contributions=np.concatenate(contribs, axis=2),
                 notes=notes, fingerprints=tuple(prints), y_sd=np.concatenate(sds, axis=1), sampled=tuple(sampled),
                 clock=tuple(r.clock for r in recordings),
                 leads={k: tuple(v) for k, v in leads.items() if any(x.size for x in v)})


def _measured_note(p: Prepared, rec: Recording, axes: Sequence[str]) -> list[str]:
    """What of a recording can be scored: nothing (said), or its probe points only (said, counted).

    A recording measured only at probe cycles is scored at those instants; one with fewer than
    :data:`MIN_PROBE_POINTS` on every axis cannot be judged (its first point only fixes its zero) and is an error.
    """
    counts = np.isfinite(p.y).sum(axis=1)
    if not counts.any():
        return [f"{rec.source}: no measured displacement (no displacement or probe_* columns with values): its "
                "factors are simulated with the others, none of its windows is scored"]
    if not p.sparse:
        return []
    per_axis = ", ".join(f"{a} {int(c)}" for a, c in zip(axes, counts, strict=True))
    instants = int(np.isfinite(p.y).any(axis=0).sum())
    what = "probe columns" if p.y_source == "probes" else "sparse displacement columns"
    if counts.max() < MIN_PROBE_POINTS:
        raise DiagnosisError(
            f"{rec.source}: {instants} probe instant(s) in its {what} ({per_axis}): a recording measured by probes "
            f"needs at least {MIN_PROBE_POINTS} on an axis to be judged (its first measured point fixes its zero); "
            "join a longer run or probe more often")
    return [f"{rec.source}: displacement measured at {instants} probe instants only (its {what}; {per_axis}): "
            "scored at those instants, nowhere else"]


def log_grid(lo: float, hi: float, per_decade: float = 5.0) -> list[float]:
    """Log-spaced values from ``lo`` to ``hi`` inclusive."""
    if hi <= lo:
        return [float(lo)]
    n = max(2, math.ceil(math.log10(hi / lo) * per_decade) + 1)
    return [float(v) for v in np.geomspace(lo, hi, n)]


def recording_labels(sources: Sequence[str]) -> list[str]:
    """:func:`recording_label` of each source, made distinct where two share one.

    Day folders often hold files of the same name (``day1/log.csv``, ``day2/log.csv``): those are named by as
    many of their folders as tell them apart (``day1/log``, ``day2/log``), the runs of two split files by their
    file too (``a day 7``, ``b day 7``).
    """
    labels = [recording_label(s) for s in sources]
    clash = {x for x in labels if labels.count(x) > 1}
    if not clash:
        return labels
    out = []
    for s, label in zip(sources, labels, strict=True):
        if label not in clash:
            out.append(label)
            continue
        group = sorted({t for t, m in zip(sources, labels, strict=True) if m == label})
        out.append(_distinct(s, group) if len(group) > 1 else label)
    return out


def _distinct(source: str, group: Sequence[str]) -> str:
    """``source``'s label, with as many folders as tell it from the others of ``group`` (one label, all).

    A run of a split file is named by its file first; the source itself where nothing tells them apart.
    """

    def parts(src: str) -> tuple[Path, tuple[str, str] | None]:
        file, part = split_file(src)
        return Path(file), part

    def named(src: str, depth: int) -> str:
        file, part = parts(src)
        stem = "/".join([*file.parent.parts[len(file.parent.parts) - depth:], file.stem]) if depth else file.stem
        return f"{stem} {part[0]} {part[1]}" if part else stem

    for depth in range(0 if split_part(source) else 1, 1 + max(len(parts(t)[0].parts) for t in group)):
        if len({named(t, depth) for t in group}) == len(group):
            return named(source, depth)
    return source


def recording_label(source: str) -> str:
    """A short name for a recording: its file's stem, or "day 7" for the part of a file split by a column."""
    part = split_part(source)
    if part:
        return f"{part[0]} {part[1]}"
    return Path(source).stem if source else "recording"
