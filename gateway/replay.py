"""Estimate displacement for a recording with a model, and judge it against what was measured.

Alignment: measured displacement has an arbitrary zero (sensors are zeroed whenever someone zeroes
them). ``align="start"`` (the paper's convention: displacement relative to the start) shifts the
measurement so that it equals the estimate over the idle lead-in (the windows before any factor moves,
at most :data:`LEAD_IN_MAX`, at least the first measured one), which averages the sensor noise out of the
zero; ``"none"`` takes it as it is (sensors zeroed at the reference state); ``"offset"`` subtracts the
best constant offset (reported, and optimistic: it uses the whole run).
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from gateway.model.coverage import CoverageCheck, check_coverage
from gateway.model.model import ThermalModel
from gateway.prepare import prepare
from gateway.recording import Recording, continued, format_recording, gap_between
from gateway.strict_json import nan_to_none

ALIGN_CHOICES = ("start", "none", "offset")
#: how the model's state at a recording's start is known: at rest, or fitted to its first hour
INITIAL_STATES = ("rest", "fit")
#: the stretch of measured displacement an initial state is fitted on
INITIAL_FIT_S = 3600.0
#: the heat history a warm start is fitted as: each input held over one of these spans before the start
#: (hours back: the last hour, 1-3 h, 3-8 h, 8-24 h), at a level up to :data:`INITIAL_FIT_LEVEL` x its largest
#: deviation in the identification experiments or in the recording, whichever is larger
INITIAL_HISTORY_H = (1.0, 3.0, 8.0, 24.0)
INITIAL_FIT_LEVEL = 1.5
#: windows of the running median whose move in the first hour says a recording does not start at rest
WARM_SMOOTH = 5
#: a first hour the model started at rest misses by more than this many times the noise (and a warm state
#: follows to a third of that) does not start at rest
WARM_MISS_SIGMA = 4.0
#: most windows of idle lead-in averaged for the measured zero
LEAD_IN_MAX = 10


@dataclass(frozen=True, kw_only=True)
class AxisFigures:
    """Errors of one axis over some windows: RMS, max |error|, peak |displacement|, max error as % of peak.

    The one metrics type: ``cncgw estimate`` reports it per axis of a recording, diagnosis per axis of its
    held-out blocks, adequacy (:class:`gateway.diagnose.adequacy.AxisAdequacy`) extends it with its verdict.
    """

    axis: str
    windows: int
    rms_um: float
    max_abs_error_um: float
    peak_um: float
    max_error_pct_of_peak: float

    @classmethod
    def of(cls, axis: str, err: np.ndarray, measured: np.ndarray) -> AxisFigures:
        """The figures of ``err`` (estimate minus measurement, um) against ``measured``; NaN without windows."""
        if not err.size:
            return cls(axis=axis, windows=0, rms_um=math.nan, max_abs_error_um=math.nan, peak_um=math.nan,
                       max_error_pct_of_peak=math.nan)
        peak = float(np.max(np.abs(measured)))
        max_err = float(np.max(np.abs(err)))
        return cls(axis=axis, windows=int(err.size), rms_um=float(np.sqrt(np.mean(err**2))),
                   max_abs_error_um=max_err, peak_um=peak,
                   max_error_pct_of_peak=100.0 * max_err / peak if peak > 0 else math.inf)

    def line(self) -> str:
        """One line for people: ``z: RMS 0.412 um, max |error| ...``."""
        share = (f"max error {self.max_error_pct_of_peak:.1f} % of peak" if math.isfinite(self.max_error_pct_of_peak)
                 else "no displacement to take a share of")
        return (f"{self.axis}: RMS {self.rms_um:.3f} um, max |error| {self.max_abs_error_um:.3f} um, "
                f"peak |displacement| {self.peak_um:.3f} um, {share} ({self.windows} windows)")


@dataclass(frozen=True, kw_only=True)
class Estimate:
    """Estimated and (aligned) measured displacement of one recording, with metrics per axis."""

    recording: str
    axes: tuple[str, ...]
    time_s: np.ndarray
    estimated: np.ndarray  # (axes, N) um
    measured: np.ndarray  # (axes, N) um after alignment, NaN where not measured
    present: np.ndarray
    metrics: dict[str, AxisFigures]  # over the windows that have a measurement
    offsets_um: dict[str, float] = field(default_factory=dict)  # per axis: what alignment subtracted from it
    notes: tuple[str, ...] = ()
    settings: dict[str, str] = field(default_factory=dict)
    #: where the recording left the factor region the identification covered (None: the model records none)
    coverage: CoverageCheck | None = None

    @property
    def residual(self) -> np.ndarray:
        return self.measured - self.estimated

    def to_json(self) -> dict[str, object]:
        return {
            "recording": self.recording,
            "settings": self.settings,
            "axes": {a: nan_to_none({**asdict(m), "offset_um": self.offsets_um[a]}) for a, m in self.metrics.items()},
            "notes": list(self.notes),
            "coverage": None if self.coverage is None else coverage_json(self.coverage, self.window_s),
        }

    @property
    def window_s(self) -> float:
        return float(np.median(np.diff(self.time_s))) if len(self.time_s) > 1 else 0.0

    def to_csv(self, meta: dict[str, str] | None = None) -> str:
        cols: dict[str, np.ndarray] = {}
        for i, a in enumerate(self.axes):
            cols[f"{a}_est_um"] = self.estimated[i]
            cols[f"{a}_meas_um"] = self.measured[i]
            cols[f"{a}_resid_um"] = self.residual[i]
        if self.coverage is not None:
            cols["outside_coverage"] = self.coverage.outside.astype(float)
            if self.coverage.beyond is not None:  # how far beyond: log(1 + covered spans), the largest factor
                cols["beyond_coverage"] = self.coverage.beyond
        return format_recording(time_s=self.time_s, columns=cols, meta={**self.settings, **(meta or {})})


def estimate(
    model: ThermalModel,
    rec: Recording,
    *,
    initial: str = "first",
    gap_policy: str = "hold",
    align: str = "start",
    history: Recording | None = None,
    initial_state: str = "rest",
) -> Estimate:
    """Run the model over a recording (batch replay of the same discretisation the live estimator uses).

    The model starts in equilibrium at the recording's first window (``initial``), unless

    - ``history``: a recording that ended before this one (the previous day, the stored history): the model
      runs over both, so this one starts in the state the history left (what ``cncgw run`` does with its
      records after a restart);
    - ``initial_state="fit"``: the state at the start is estimated from the first
      :data:`INITIAL_FIT_S` of measured displacement, as the state some heat history of the model's inputs
      leaves (for a recording that starts warm, mid-work, with no history; see :func:`_fit_initial_state`).
      Said so in the notes; the first hour then scores the fit, not the model.
    """
    if align not in ALIGN_CHOICES:
        raise ValueError(f"align must be one of {ALIGN_CHOICES}. Got {align!r}")
    if initial_state not in INITIAL_STATES:
        raise ValueError(f"initial_state must be one of {INITIAL_STATES}. Got {initial_state!r}")
    run = continued(history, rec) if history is not None else rec
    skip = len(run) - len(rec)
    prep = prepare(run, factors=model.factors, axes=model.axes, initial=initial, reference=model.reference,
                   gap_policy=gap_policy, inputs=model.inputs)
    est = model.discretize(rec.period_s).simulate(prep.du, prep.lead)[:, skip:]
    du = prep.du[:, skip:]
    measured = prep.y[:, skip:].copy()
    time_s = prep.time_s[skip:]
    check = None if model.coverage is None else check_coverage(
        model.coverage, du, model.factors, model.units,
        columns={c: v[skip:] for c, v in model.coverage.columns_of(run.extras).items()})
    notes = list(prep.notes) + (check.notes(rec.period_s) if check is not None else extrapolation_notes(model, du))
    if history is not None:
        gap_s = gap_between(history, rec)
        between = (f"; it ends {gap_s / 3600:.3g} h before this one starts, and the hours in the gap note count from "
                   "its start" if gap_s > 0.5 * rec.period_s else "")
        working = _away_from_rest(model, history, -1, "last") if between and gap_policy == "hold" else ""
        if working:  # held over the gap: hours more of work the machine may not have done (a helper's 29 um RMS)
            between += (f"; {working}, and the gap policy hold keeps it so over the gap: --gap-policy reference "
                        "takes the machine idle there")
        notes.append(f"started in the state {history.source} left (its {len(history)} windows run first{between})")
    if initial_state == "fit":
        # whether it starts at rest is the check estimate's note and --validate make (one verdict, not two)
        at_rest = history is None and not starts_warm(model, rec, gap_policy=gap_policy)
        est, text = _fit_initial_state(model, rec.period_s, time_s, est, measured, du, at_rest=at_rest)
        notes.append(text)
    metrics: dict[str, AxisFigures] = {}
    offsets: dict[str, float] = {}
    lead_n = min(_lead_in(du - du[:, :1]), LEAD_IN_MAX)
    for i, a in enumerate(model.axes):
        ok = np.isfinite(measured[i])
        if not ok.any():
            if a in rec.displacement:
                notes.append(f"axis {a}: no measured value in any window")
            elif rec.displacement:  # the others measured: a column missing or renamed, not a file of inputs only
                notes.append(f"axis {a}: not in this file (no displacement column for it, where "
                             f"{', '.join(rec.displacement)} {'has' if len(rec.displacement) == 1 else 'have'} one): "
                             "estimated, not scored")
            continue
        if align == "start":
            lead = np.zeros_like(ok)
            lead[:lead_n] = True
            use = lead & ok
            if not use.any():
                use = np.zeros_like(ok)
                use[int(np.flatnonzero(ok)[0])] = True
            offset = float(np.mean(measured[i, use] - est[i, use]))
        elif align == "offset":
            offset = float(np.mean(measured[i, ok] - est[i, ok]))
        else:
            offset = 0.0
        measured[i] -= offset
        metrics[a] = AxisFigures.of(a, measured[i, ok] - est[i, ok], measured[i, ok])
        offsets[a] = offset
    if metrics and len(rec) < MIN_SCORED_WINDOWS:
        notes.append(f"only {len(rec)} window(s) ({len(rec) * rec.period_s / 60:.3g} min): too short for its figures "
                     f"to say anything (diagnose --validate takes at least {MIN_SCORED_WINDOWS} measured)")
    settings = {"initial": initial, "gap_policy": gap_policy, "align": align, "initial_state": initial_state}
    if history is not None:
        settings["history"] = history.source
    return Estimate(recording=rec.source, axes=model.axes, time_s=time_s, estimated=est,
                    measured=measured, present=prep.present[skip:], metrics=metrics, offsets_um=offsets,
                    notes=tuple(notes), settings=settings, coverage=check)


#: fewer measured windows than this say nothing of a model (a 5-minute file: "max error 100 % of peak")
MIN_SCORED_WINDOWS = 10


def coverage_json(check: CoverageCheck, window_s: float) -> dict[str, object]:
    """The coverage check as JSON: windows outside, and per excursion what, how far, how long."""
    return {"windows_outside": check.windows_outside,
            "excursions": [{"what": e.what, "kind": e.kind, "side": e.side, "value": e.value, "bound": e.bound,
                            "windows": e.windows, "longest_s": e.longest * window_s, "first_window": e.first + 1,
                            "unit": e.unit} for e in check.excursions]}


def _fit_initial_state(model: ThermalModel, period_s: float, time_s: np.ndarray, est: np.ndarray,
                       measured: np.ndarray, du: np.ndarray, *, at_rest: bool = False) -> tuple[np.ndarray, str]:
    """``est`` plus the model's free response from the state a heat history leaves, fitted to the first hour.

    The state is not free: a machine is warm because it worked, so its state is one the model's own inputs
    can leave. The unknown history is each input held at a level over one of :data:`INITIAL_HISTORY_H`'s spans
    before the start (levels from 0 up to :data:`INITIAL_FIT_LEVEL` x its largest deviation in the experiments
    or in this recording: heat only where the input only heats, either sign where it moved both ways), fitted
    over every axis at once with a constant per axis (the zero): bounded linear least squares. One state moves
    every axis by the model's own gains and time constants, so what the first hour shows carries into the hours
    after it. A free decay per axis fitted to the hour (what this did before) extrapolated slow modes far off:
    the bundled production day cut at 8, 10, 12 and 14 h, z RMS 30.8 / 6.2 / 35.3 / 7.1 um that way, 10.1 / 1.0 /
    6.2 / 1.9 um this way, 41.7 / 22.1 / 33.4 / 16.1 um started at rest (the bundled model).

    ``at_rest``: the recording seems to start at rest (:func:`starts_warm` finds nothing): the note says the
    fitted state may only follow noise and small misses, not that it does not start at rest.
    """
    import scipy.optimize

    rel = time_s - time_s[0] + (time_s[1] - time_s[0] if len(time_s) > 1 else 0.0)
    first = rel <= INITIAL_FIT_S
    dm = model.discretize(period_s)
    names = model.input_names
    covered = model.info.get("deviation_range", {}) or {}
    back = round(INITIAL_HISTORY_H[-1] * 3600.0 / period_s)
    n = est.shape[1]
    responses: list[np.ndarray] = []
    for j, name in enumerate(names):
        # the levels it had in the experiments or has in this recording, whichever reach further (before its start
        # the machine worked as it does in it)
        lo, hi = (float(v) for v in covered.get(name, (0.0, 0.0)))
        if du.shape[1]:
            lo, hi = min(lo, float(du[j].min())), max(hi, float(du[j].max()))
        for level in (v for v in (hi, lo) if v != 0.0):
            for newer, older in zip((0.0, *INITIAL_HISTORY_H[:-1]), INITIAL_HISTORY_H, strict=True):
                u = np.zeros((len(names), back + n))
                u[j, back - round(older * 3600.0 / period_s): back - round(newer * 3600.0 / period_s)] = (
                    INITIAL_FIT_LEVEL * level)
                responses.append(dm.simulate(u)[:, back:])
    ok = [first & np.isfinite(measured[i] - est[i]) for i in range(len(model.axes))]
    fitted = [a for i, a in enumerate(model.axes) if ok[i].sum() >= 5]
    if not responses or not fitted:
        return est.copy(), (f"initial state: no input or too few measured windows in the first "
                            f"{INITIAL_FIT_S / 3600:g} h to estimate it from; started at rest")
    rows, target = [], []
    for i, a in enumerate(model.axes):
        if a not in fitted:
            continue
        zero = np.zeros((int(ok[i].sum()), len(model.axes)))
        zero[:, i] = 1.0
        rows.append(np.column_stack([r[i][ok[i]] for r in responses] + [zero]))
        target.append((measured[i] - est[i])[ok[i]])
    A, b = np.vstack(rows), np.concatenate(target)
    scale = np.linalg.norm(A, axis=0)
    scale[scale == 0] = 1.0
    k = len(responses)
    bounds = (np.r_[np.zeros(k), np.full(len(model.axes), -np.inf)] * scale,
              np.r_[np.ones(k), np.full(len(model.axes), np.inf)] * scale)
    w = scipy.optimize.lsq_linear(A / scale, b, bounds=bounds).x[:k] / scale[:k]
    out = est + sum((wk * r for wk, r in zip(w, responses, strict=True)), np.zeros_like(est))
    moved = float(np.max(np.abs(out - est))) if out.size else 0.0
    if moved < 1e-3:  # no heat history fits the first hour better than none (a cold start: heat only adds)
        return est.copy(), (f"initial state: no state a heat history of the inputs leaves fits the first "
                            f"{INITIAL_FIT_S / 3600:g} h better than rest; started at rest")
    spans = ", ".join(f"{newer:g}-{older:g} h" for newer, older in zip((0.0, *INITIAL_HISTORY_H[:-1]),
                                                                       INITIAL_HISTORY_H, strict=True))
    together = ", fitted over the axes together" if len(fitted) > 1 else ""
    scored = ("that hour scores the fit, not the model" if float(rel[-1]) > INITIAL_FIT_S else
              "the whole recording lies in that hour: its figures score the fit, not the model")
    # a recording that starts at rest gets a state fitted all the same (heat only adds, but noise and small
    # misses of the model's draw it): said, not called a warm start (the bundled day from 0 h: z 4.01 -> 4.57 um)
    start = ("yet the recording seems to start at rest (by the check estimate makes of a start at rest): the state "
             "may only follow noise and small misses of the model (--initial-state rest)" if at_rest else
             "the recording does not start at rest")
    return out, (f"initial state estimated from the first {INITIAL_FIT_S / 3600:g} h of measured displacement on "
                 f"{', '.join(fitted)}: the state the model's inputs leave when held before the start ({spans} "
                 f"back, each up to {INITIAL_FIT_LEVEL:g}x its largest in the experiments or here){together}: "
                 f"{start}; {scored}")


#: hours of work a history before a recording that starts warm may hold (:func:`working_history`)
WORK_HISTORY_H = (0.25, 0.5, 1.0, 2.0, 3.0, 4.0, 6.0, 8.0, 12.0, 16.0, 24.0)
#: the stretch of measured displacement that history is chosen on: longer than estimate's hour, since hours of
#: work differ in slow modes (bench/diagnose.py --cut-days 10, variants 1-3: on the first hour 19 of 51 fresh days
#: 30 % better and 2 worse; on the first 3 h 18 and none)
WORK_FIT_S = 3 * 3600.0
#: ... and it must leave at most this share of the squared error a start at rest leaves there
WORK_MIN_SHARE = 0.75


def working_history(model: ThermalModel, rec: Recording, *, gap_policy: str = "hold") -> tuple[Recording, str] | None:
    """The hours of work before ``rec`` its first hours show, as a recording that ends one window before it.

    The machine is taken to have worked before the start as it works in the recording: its factors held, from
    rest, for H hours at the levels of the recording's first window or at their mean over the windows it works in
    (any factor over a hundredth of its largest deviation from its rest level); H (from :data:`WORK_HISTORY_H`) and
    the levels are those whose run through the model, then through ``rec``, meets the first :data:`WORK_FIT_S`
    of measured displacement best (a free zero per axis). Returned with what was chosen, in words; None when
    none leaves under :data:`WORK_MIN_SHARE` of a start at rest's squared error there (or fewer than 5 windows
    are measured there). A recording that works at its first window (:func:`works_at_start`) has no neutral
    default: without a history it runs as if it had worked so for ever, so that (None) and a start at rest (one
    window at rest before it: "no work") are choices beside the hours of work, the best fit taken.

    Not the state ``--initial-state fit`` fits (:func:`_fit_initial_state`: any mix of the inputs over four spans,
    whichever meets the hour best for this model; for bench/diagnose.py's slow mode v3, day 3 from 10 h, it held
    the spindle at 4500 rpm and z's feed at 16000 mm/min over the 8-24 h before, where the machine had rested):
    a history is run through other models too (paths refitted, terms the model lacks), and only one the machine
    could have worked makes their states right. The displacement is unmeasured there.
    """
    names = list(model.factors)
    prep = prepare(rec, factors=model.factors, axes=model.axes, initial="reference", reference=model.reference,
                   gap_policy=gap_policy, inputs=model.inputs)
    du = prep.du[: len(names)]
    rel = prep.time_s - prep.time_s[0] + rec.period_s
    first = (rel <= WORK_FIT_S)[None, :] & np.isfinite(prep.y)
    if first.sum() < 5 or not du.shape[1]:
        return None
    working = _moving(du).any(axis=0)
    levels = {"its first window's": du[:, 0]}
    if working.any():
        levels["its mean working"] = du[:, working].mean(axis=1)
    dm = model.discretize(rec.period_s)

    def miss(est: np.ndarray) -> float:  # squared error over the first hours, a free zero per axis
        total = 0.0
        for i in range(len(model.axes)):
            e = (prep.y[i] - est[i])[first[i]]
            total += float(np.sum((e - e.mean()) ** 2)) if e.size else 0.0
        return total

    at_rest = miss(dm.simulate(prep.du, prep.lead))
    best = (at_rest, None, "")
    bar = WORK_MIN_SHARE * at_rest  # noise and small misses of the model draw some history: one that matters
    # removes a share of the miss
    if works_at_start(model, rec):
        # working at its first window, the recording starts neither at rest nor in equilibrium with that window
        # for certain: without a history it runs as if it had worked so for ever, so that is one more choice here,
        # and a start at rest (no work before it) another, none of them the default a share must beat
        # (bench/diagnose.py --cut-days 13, variant 3: day 4 starts with a feed job, and for ever put x 210 % of
        # its peak off where a cold start, which no history beat by a quarter, was close)
        ever = prepare(rec, factors=model.factors, axes=model.axes, initial="first", reference=model.reference,
                       gap_policy=gap_policy, inputs=model.inputs)
        rest = prep.u0[: len(names)]
        best = min((at_rest, _held(rec, names, rest, rest, 0), "no work"),
                   (miss(dm.simulate(ever.du, ever.lead)), None, ""), key=lambda c: c[0])
        bar = math.inf  # no default a share must beat
    for said, level in levels.items():
        if not np.any(level):
            continue
        for hours in WORK_HISTORY_H:
            k = round(hours * 3600.0 / rec.period_s)
            hist = _held(rec, names, prep.u0[: len(names)], prep.u0[: len(names)] + level, k)
            run = prepare(continued(hist, rec), factors=model.factors, axes=model.axes, initial="reference",
                          reference=model.reference, gap_policy=gap_policy, inputs=model.inputs)
            score = miss(dm.simulate(run.du, run.lead)[:, k + 1:])
            if score < best[0]:
                best = (score, hist, f"{hours:g} h at {said} levels")
    return (best[1], best[2]) if best[1] is not None and best[0] < bar else None


def _held(rec: Recording, names: Sequence[str], rest: np.ndarray, values: np.ndarray, windows: int) -> Recording:
    """``names`` at ``rest``, then held at ``values`` over ``windows`` windows that end one window before ``rec``.

    The window at rest first: whatever starts a run in equilibrium with its first window (``initial="first"``, as
    diagnosis stacks recordings) starts this one at rest, as the reference levels do. No displacement.
    """
    t = rec.time_s[0] - rec.period_s * np.arange(windows + 1, 0, -1)
    return Recording(source=f"{rec.source} (work before it)", period_s=rec.period_s, time_s=t,
                     present=np.ones(windows + 1, dtype=bool),
                     factors={f: np.r_[r, np.full(windows, float(v))]
                              for f, r, v in zip(names, rest, values, strict=True)},
                     displacement={a: np.full(windows + 1, np.nan) for a in rec.displacement})


def extrapolation_notes(model: ThermalModel, du: np.ndarray, *, margin: float = 1.2) -> list[str]:
    """Factors driven beyond ``margin`` times the range the identification experiments covered.

    The model is linear in each factor, but how co-varying factors (speed, I1^2, I2^2) share a response is
    only pinned down over the ratios the experiments had: beyond their range the estimate extrapolates.
    """
    covered = model.info.get("deviation_range", {})
    notes = []
    for j, f in enumerate(model.factors):
        if f not in covered or du.shape[1] == 0:
            continue
        lo, hi = covered[f]
        top, bottom = float(np.max(du[j])), float(np.min(du[j]))
        unit = f" {model.units[f]}" if model.units.get(f) else ""
        tail = "the model extrapolates there"
        if hi > 0 and top > margin * hi:
            notes.append(f"factor {f} reaches {top:.4g}{unit} above its reference, {top / hi:.1f}x the largest "
                         f"in the identification experiments ({hi:.4g}{unit}): {tail}")
        elif hi <= 0 < top:
            notes.append(f"factor {f} rises {top:.4g}{unit} above its reference, which no identification "
                         f"experiment did: {tail}")
        if lo < 0 and bottom < margin * lo:
            notes.append(f"factor {f} falls {-bottom:.4g}{unit} below its reference, {bottom / lo:.1f}x the most "
                         f"in the identification experiments: {tail}")
    return notes


def _moving(du: np.ndarray, share: float = 0.01) -> np.ndarray:
    """Per factor and window, whether it is away from rest by more than ``share`` of its largest move."""
    size = np.abs(du).max(axis=1, keepdims=True)
    return (np.abs(du) > share * size) & (size > 0)


def _lead_in(du: np.ndarray, share: float = 0.01) -> int:
    """Windows before any factor moves by more than ``share`` of its largest move (at least 1)."""
    first = np.flatnonzero(_moving(du, share).any(axis=0))
    return max(int(first[0]) if first.size else du.shape[1], 1)


def plot_estimates(estimates: Sequence[Estimate], path: str | Path, *, title: str = "") -> Path:
    """Measured vs estimated displacement per axis, and the residual, for one or more recordings."""
    from gateway.plotting import pyplot

    plt = pyplot()

    axes = estimates[0].axes
    fig, grid = plt.subplots(2, len(axes), figsize=(4.2 * len(axes), 6.5), sharex="col", squeeze=False)
    for k, e in enumerate(estimates):
        hours = (e.time_s - e.time_s[0]) / 3600.0
        label = Path(e.recording).stem if len(estimates) > 1 else None
        for i, a in enumerate(axes):
            top, bottom = grid[0, i], grid[1, i]
            color = f"C{k % 10}"
            top.plot(hours, e.measured[i], color=color, lw=1.0, alpha=0.6,
                     label=f"{label} measured" if label else "measured")
            top.plot(hours, e.estimated[i], color=color, lw=1.6, ls="--",
                     label=f"{label} estimated" if label else "estimated")
            bottom.plot(hours, e.residual[i], color=color, lw=1.0)
            m = e.metrics.get(a)
            if m and len(estimates) == 1:
                top.set_title(f"{a}: peak {m.peak_um:.1f} um, max error {m.max_abs_error_um:.2f} um "
                              f"({m.max_error_pct_of_peak:.0f} %)", fontsize=9)
            elif len(estimates) > 1:
                top.set_title(a)
            top.set_ylabel(f"{a} displacement (um)")
            bottom.set_ylabel(f"{a} measured - estimated (um)")
            bottom.set_xlabel("time (h)")
            bottom.axhline(0, color="k", lw=0.5)
    grid[0, 0].legend(fontsize=7, loc="best")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def metrics_json(estimates: Sequence[Estimate]) -> str:
    """The metrics of every estimate as a JSON document (for ``--json``)."""
    return json.dumps([e.to_json() for e in estimates], indent=2)


def works_at_start(model: ThermalModel, rec: Recording) -> str:
    """A factor away from its rest level at ``rec``'s first window, and how far ("" when none is).

    Such a recording is not estimated from rest by default: ``initial="first"`` takes it in equilibrium with
    that window, as if it had worked so for ever. Whether it was warm or had just started, its first window
    does not say (a cold machine starting a job at 1500 rpm: z 36.9 um RMS in equilibrium with that window,
    0.25 um from the reference levels).
    """
    return _away_from_rest(model, rec, 0, "first")


def _away_from_rest(model: ThermalModel, rec: Recording, at: int, which: str) -> str:
    """A factor over a tenth of its covered range away from its rest level at ``rec``'s finite value ``at``."""
    covered = model.info.get("deviation_range", {}) or {}
    for f in model.factors:
        v = rec.factors.get(f)
        if v is None or not np.isfinite(v).any():
            continue
        level = float(v[np.isfinite(v)][at]) - float(model.reference.get(f, 0.0))
        lo, hi = covered.get(f, [0.0, 0.0])
        span = max(abs(float(lo)), abs(float(hi)))
        if span > 0 and abs(level) > 0.1 * span:
            unit = f" {model.units[f]}" if model.units.get(f) else ""
            return f"{f} is {level:+.4g}{unit} from its rest level at the {which} window"
    return ""


def starts_warm(model: ThermalModel, rec: Recording, *, gap_policy: str = "hold") -> str:
    """Why ``rec`` does not start in equilibrium ("" when it seems to).

    A factor away from its rest level at its first window (:func:`works_at_start`); a displacement that moves
    in its first hour, or over the idle windows it starts with, far more than the model started at rest
    predicts; or a first hour the model started at rest misses by far more than the noise where the state some
    heat history leaves (:func:`_fit_initial_state`) follows it.
    """
    working = works_at_start(model, rec)
    if working:
        return working
    e = estimate(model, rec, gap_policy=gap_policy)
    rel = e.time_s - e.time_s[0]
    hour = rel <= INITIAL_FIT_S
    # ... and the idle windows it starts with, when it starts idle: a machine cooling before its first job moves
    # there while the model predicts nothing, though over the whole hour the job's own heat hides it (the bundled
    # production day cut at noon: z 10.9 um over 45 idle minutes, unflagged, estimated 33 um RMS off from rest)
    du = prepare(rec, factors=model.factors, axes=model.axes, initial="first", reference=model.reference,
                 gap_policy=gap_policy, inputs=model.inputs).du
    idle = np.zeros_like(hour)
    idle[: _lead_in(du - du[:, :1])] = True
    for i, a in enumerate(model.axes):
        y = e.measured[i]
        sigma = _noise_um(y)
        for span, when, least in ((hour, "in the first hour", 5), (hour & idle, "while it rests at the start", 10)):
            ok = span & np.isfinite(y)
            if ok.sum() < least:
                continue
            # the move of its running median over WARM_SMOOTH windows: the raw spread of an hour of noise alone
            # passes 6 sigma in a few axis-hours of 100 (0.6 um moves flagged in 41 of 686 bench recordings
            # that start at rest), and a running mean still passed it with one spike of 3 um (a sensor's)
            k = min(WARM_SMOOTH, int(ok.sum()))
            moved = float(np.ptp(np.median(np.lib.stride_tricks.sliding_window_view(y[ok], k), axis=1)))
            if float(np.max(np.abs(np.diff(y[ok])))) > 0.5 * float(np.ptp(y[ok])):
                continue  # most of it in one window: a sensor's step (knocked, re-zeroed), not heat leaving
            predicted = float(np.ptp(e.estimated[i][ok]))
            if moved > max(6.0 * sigma, 3.0 * predicted, 1e-9):
                return (f"axis {a} moves {moved:.3g} um {when} where the model, started at rest, predicts "
                        f"{predicted if predicted >= 5e-4 else 0.0:.3g} um")
    # ... and a first hour that a warm state follows where rest misses it: a part cut from a day while the machine
    # works starts at a window of a pause between jobs, and the next job's heat hides the cooling in how far it
    # moves (the bundled production day cut at 10 h: z 22 um RMS from rest, 0.97 um fitted, unflagged before)
    fitted, _ = _fit_initial_state(model, rec.period_s, e.time_s, e.estimated, e.measured, du)
    missed = _first_hour_misses(model.axes, e.time_s, e.measured, e.estimated, fitted)
    if missed:
        rest, warm, a = missed[0]
        return (f"axis {a}: started at rest, the model misses its first hour by {rest:.3g} um RMS; the state a "
                f"heat history leaves follows it to {warm:.3g} um")
    return ""


def _noise_um(y: np.ndarray) -> float:
    """The noise of a measured series: the robust spread of its first differences, per window."""
    d = np.diff(y[np.isfinite(y)])
    return float(np.median(np.abs(d - np.median(d)))) / 0.6745 / math.sqrt(2) if d.size else 0.0


def _first_hour_misses(axes: Sequence[str], time_s: np.ndarray, measured: np.ndarray, rest: np.ndarray,
                       fitted: np.ndarray) -> list[tuple[float, float, str]]:
    """Axes whose first hour rest misses and a fitted state follows: (RMS miss from rest, fitted, axis).

    Those missed from rest by over :data:`WARM_MISS_SIGMA` x their noise where the fitted state follows to a
    third; the largest first.
    """
    hour = time_s - time_s[0] <= INITIAL_FIT_S
    out = []
    for i, a in enumerate(axes):
        ok = hour & np.isfinite(measured[i])
        if ok.sum() < 10:
            continue
        r, w = (float(np.std(measured[i][ok] - est[ok])) for est in (rest[i], fitted[i]))
        if r > max(WARM_MISS_SIGMA * _noise_um(measured[i]), 1e-9) and w < r / 3.0:
            out.append((r, w, a))
    return sorted(out, reverse=True)
