"""Tracking the displacement live: one model step per finished window, rebuilt from the durable records on start.

:class:`DisplacementTracker` turns each committed window into an estimate (:class:`EstimateUpdate`) with the
model's one stepper (:class:`~gateway.model.ModelStepper`), the gap policy and the derived inputs; the
offline counterpart is :mod:`gateway.replay` (``cncgw estimate``), the same discretisation in batch.

The estimator's state is a pure function of the factor history (``ModelStepper.from_history``), so nothing
private is persisted: on start the history is read back from the record store and the state recomputed in
batch; a ``kill -9`` loses nothing the store had committed.

Initial state: the model's ``reference`` levels (the machine idle in thermal equilibrium) at the start of
the first stored window, not that window's factors: the gateway can start in the middle of work.

Gap policy (``[live] gap_policy``), the same live and on rebuild, so a restart reproduces the state an
uninterrupted run would have had for the same records:

- a window that is missing (the gateway was down) or has no good factors (``insufficient``: devices down,
  too little coverage; or a NaN factor) is filled: ``"hold"`` takes the last good window's factors for
  windows ending at most ``gap_hold_max_s`` after it, then the reference (idle); ``"reference"`` takes the
  reference at once;
- every filled window is counted and reported (:class:`Gap`, health, logs, the audit log), and an estimate
  that rests on a filled window is not used for compensation (the writer holds).

Derived inputs (a diagnosed model's ``[inputs.NAME]``: speed squared, sums, flags, lags, a daily period, a
recorded column) are stepped with :class:`~gateway.model.inputs.InputStepper` from the factors after the
gap policy, the window's end time (epoch seconds, as in an exported recording) and, for a ``column``
input, the mean of the profile channel of that name (held over windows without it). They start settled at
the reference levels and at the channel's value in the oldest stored window (the equilibrium the
machine starts in), so a restart replays them to the same values.

Only history that can still matter is read on start: twenty times the model's slowest time constant
(``[live] history_max_h`` overrides); older inputs have decayed to less than e^-20 of their effect.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np

from gateway.adaptive.filter import Z95
from gateway.errors import ModelError
from gateway.model import ModelStepper, ThermalModel
from gateway.model.coverage import check_coverage
from gateway.model.inputs import Column, InputStepper, Product, initial_values, recorded_columns
from gateway.profile.live import Live
from gateway.windows import WindowRecord

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True, slots=True)
class Gap:
    """Windows ``first``..``last`` (indices) that had no good factors and were filled by the gap policy."""

    first: int
    last: int
    policy: str
    reason: str  # no record stored (gateway down, store failed) or why the windows were bad

    @property
    def windows(self) -> int:
        return self.last - self.first + 1

    def describe(self, window_s: float) -> str:
        return (f"windows {self.first}..{self.last} ({self.windows} x {window_s:g} s, {self.reason}) filled by "
                f"gap policy {self.policy}")


@dataclass(frozen=True, kw_only=True)
class EstimateUpdate:
    """The estimate after one window.

    ``usable``: the window's own factors were good and nothing before it within the estimator's memory was
    filled in place of bad data *in this window*: compensation may follow it. Otherwise ``reason`` says why.
    """

    index: int
    end_s: float
    estimate_um: Mapping[str, float]
    next_um: Mapping[str, float]  # predicted for the end of the next window, the factors held
    factors: Mapping[str, float]
    usable: bool
    reason: str = ""
    filled: int = 0  # windows filled (this one included when it was bad)
    first_live: bool = False  # the first window after start: the gateway joined it part-way
    notes: tuple[str, ...] = ()
    #: standard uncertainty per axis (um) when probes update the model (gateway.adaptive); empty otherwise
    sd_um: Mapping[str, float] = field(default_factory=lambda: MappingProxyType({}))
    #: why this window's factors lie outside the region the identification covered ("" inside, or the model
    #: records none): the estimate extrapolates (gateway.model.coverage)
    outside_coverage: str = ""
    #: what the estimator stepped on for this window: ``"window"``, its own factors (whatever ``usable`` says
    #: about writing); ``"held"``, the window had no good factors and the gap policy held the last good
    #: window's (``held_factors``, for at most ``gap_hold_max_s``); ``"reference"``, the machine assumed idle
    inputs: str = "window"
    #: the model's factors the estimator held in place of this window's (empty unless ``inputs == "held"``)
    held_factors: Mapping[str, float] = field(default_factory=lambda: MappingProxyType({}))

    @property
    def band95_um(self) -> Mapping[str, float]:
        """The 95 % half-band per axis (um): the true displacement is within +- this (empty without probes)."""
        return MappingProxyType({a: Z95 * v for a, v in self.sd_um.items()})


def bad_reason(record: WindowRecord, factors: Iterable[str], channels: Mapping[str, str] | None = None) -> str:
    """Why a record cannot drive the estimate (``""`` when it can).

    ``channels``: factor -> its channel; a factor channel with saturated samples makes the window bad (the
    converter sat at its limit: the true value, and so the factor, is beyond what was read).
    """
    if record.status != "good":
        return f"window {record.index} {record.status}: {record.quality()}"
    missing = [f for f in factors if not math.isfinite(record.factors.get(f, math.nan))]
    if missing:
        return f"window {record.index}: no finite value for {', '.join(missing)}"
    for f, ch in (channels or {}).items():
        stats = record.channels.get(ch)
        if stats is not None and stats.saturated:
            return f"window {record.index}: channel {ch} ({f}) saturated in {stats.saturated} samples"
    return ""


class FactorHistory:
    """Turns window records into the estimator's input columns (deviations from the reference), gaps filled."""

    def __init__(self, model: ThermalModel, window_s: float, live: Live,
                 channels: Mapping[str, str] | None = None) -> None:
        self.model = model
        self.channels = dict(channels or {})
        self.window_s = float(window_s)
        self.live = live
        self.reference = model.reference_vector()
        self.columns = recorded_columns(model.inputs)
        self._stepper: InputStepper | None = None
        self._start: np.ndarray | None = None  # the derived inputs' values in the initial equilibrium
        self.last_index: int | None = None
        self.last_good_du = np.zeros(len(model.factors))
        self.last_good_end_s: float | None = None
        self.last_good_factors: Mapping[str, float] = MappingProxyType({})
        self.gaps: list[Gap] = []
        self.filled_total = 0

    def holds(self, index: int) -> bool:
        """Window ``index``, if it has no good factors, gets the last good window's (else the reference)."""
        end = (index + 1) * self.window_s
        return (self.live.gap_policy == "hold" and self.last_good_end_s is not None
                and end - self.last_good_end_s <= self.live.gap_hold_max_s + 1e-9)

    def _fill_column(self, index: int) -> np.ndarray:
        return self.last_good_du.copy() if self.holds(index) else np.zeros_like(self.last_good_du)

    def _note_gap(self, first: int, last: int, reason: str) -> Gap:
        gap = Gap(first=first, last=last, policy=self.live.gap_policy, reason=reason)
        prev = self.gaps[-1] if self.gaps else None
        if prev is not None and prev.last == first - 1 and prev.reason == reason:
            gap = Gap(first=prev.first, last=last, policy=prev.policy, reason=reason)
            self.gaps[-1] = gap
        else:
            self.gaps.append(gap)
        self.filled_total += last - first + 1
        return gap

    def advance(self, record: WindowRecord) -> tuple[np.ndarray, int, str]:
        """Input columns (factors, k) up to and including ``record``: missing windows first, then its own.

        Returns ``(columns, filled, reason)``; ``reason`` is ``""`` when the record's own factors were used.
        """
        if self.last_index is not None and record.index <= self.last_index:
            raise ValueError(f"window {record.index} is not after window {self.last_index}")
        if self.model.inputs and self._stepper is None:
            self.begin([record])
        cols = []
        filled = 0
        if self.last_index is not None and record.index > self.last_index + 1:
            first, last = self.last_index + 1, record.index - 1
            for j in range(first, last + 1):
                cols.append(self._with_inputs(self._fill_column(j), (j + 1) * self.window_s, None))
            filled += last - first + 1
            self._note_gap(first, last, "no record stored: the gateway was down or the store failed")
        reason = bad_reason(record, self.model.factors, self.channels)
        if reason:
            cols.append(self._with_inputs(self._fill_column(record.index), record.end_s, record))
            filled += 1
            self._note_gap(record.index, record.index, "window without good factors")
        else:
            u = np.array([record.factors[f] for f in self.model.factors], dtype=float)
            du = u - self.reference
            self.last_good_du = du
            self.last_good_end_s = record.end_s
            self.last_good_factors = MappingProxyType({f: record.factors[f] for f in self.model.factors})
            cols.append(self._with_inputs(du, record.end_s, record))
        self.last_index = record.index
        return np.column_stack(cols), filled, reason

    def begin(self, records: Sequence[WindowRecord]) -> None:
        """Settle the derived inputs in the initial equilibrium at the first of ``records``.

        That is the reference levels, and each column input's channel at its first value in ``records`` (the
        oldest stored window first); a channel never seen counts as settled (deviation 0) and is logged.
        """
        initial = {f: float(v) for f, v in zip(self.model.factors, self.reference, strict=True)}
        for c in self.columns:
            initial[c] = next((v for v in (r.channel_mean(c) for r in records) if math.isfinite(v)), math.nan)
            if not math.isfinite(initial[c]):
                log.warning("channel %s (a column input of the model) has no value in the first window: its "
                            "deviation counts as 0", c)
        time0 = records[0].end_s
        self._stepper = InputStepper(self.model.inputs, dt_s=self.window_s, initial=initial, time0_s=time0)
        start = initial_values(self.model.inputs, initial, time0_s=time0)
        self._start = np.array([start[d.name] for d in self.model.inputs])

    def _with_inputs(self, du: np.ndarray, end_s: float, record: WindowRecord | None) -> np.ndarray:
        """``du`` followed by the derived inputs' deviations for the window ending at ``end_s``."""
        if self._stepper is None:
            return du
        assert self._start is not None
        signals = {f: float(r + d) for f, r, d in zip(self.model.factors, self.reference, du, strict=True)}
        columns = {c: math.nan if record is None else record.channel_mean(c) for c in self.columns}
        values = self._stepper.step(signals, time_s=end_s, columns=columns)
        derived = np.array([values[d.name] for d in self.model.inputs]) - self._start
        return np.concatenate([du, np.nan_to_num(derived, nan=0.0)])


def column_channel_problems(model: ThermalModel, channel_names: Iterable[str]) -> list[str]:
    """One message per derived ``column`` input of ``model`` that no profile channel of its name feeds."""
    have = set(channel_names)
    return [f'model input "{d.name}" reads recorded column "{d.column}", but the profile has no channel '
            f'"{d.column}" (channels: {", ".join(sorted(have)) or "none"}): add a [channels.{d.column}] table '
            f"that reads it" for d in model.inputs if isinstance(d, Column) and d.column not in have]


def history_windows(model: ThermalModel, window_s: float, live: Live) -> int:
    """How many windows of stored history the rebuild reads (see the module docstring)."""
    if live.history_max_h is not None:
        return max(1, math.ceil(live.history_max_h * 3600.0 / window_s))
    lags = [tau for d in model.inputs if isinstance(d, Product) for tau in d.lag_s]
    slowest = max([tau for p in model.paths.values() for t in p.terms for tau in t.time_constants_s] + lags,
                  default=window_s)
    delay = max((p.delay_s for p in model.paths.values()), default=0.0)
    return max(1, math.ceil((20.0 * slowest + delay) / window_s))


def retention_problems(model: ThermalModel, profile: Any) -> list[str]:
    """``[records] keep_days`` must keep the history a restart replays (:func:`history_windows`)."""
    keep = profile.records.keep_days
    if keep is None:
        return []
    need_days = history_windows(model, profile.sampling.window_s, profile.live) * profile.sampling.window_s / 86400.0
    if keep >= need_days:
        return []
    return [f"{profile.path}: records.keep_days = {keep:g} keeps less than the {need_days:.3g} days of history the "
            f"estimator replays on start (20 x the model's slowest time constant, or [live] history_max_h): "
            f"expected >= {need_days:.3g}, or a shorter [live] history_max_h"]


class DisplacementTracker:
    """Keeps the live displacement estimate of one model at one window length; steps on each record (a sink).

    Args:
        model: the identified model (inputs are deviations from ``model.reference``).
        window_s: the profile's window.
        live: the gap policy.
        channels: factor -> channel (saturated samples on it make a window bad).
        channel_names: every channel the profile reads; a derived ``column`` input needs one of its name
            (``None``: not checked).

    :meth:`rebuild` recomputes the state from stored records before the first live window.

    """

    def __init__(self, model: ThermalModel, *, window_s: float, live: Live,
                 channels: Mapping[str, str] | None = None, channel_names: Iterable[str] | None = None) -> None:
        if channel_names is not None:
            problems = column_channel_problems(model, channel_names)
            if problems:
                raise ModelError("; ".join(problems))
        self.model = model
        self.window_s = float(window_s)
        self.live = live
        self.dm = model.discretize(window_s)
        self.stepper: ModelStepper = self.dm.stepper()
        self.history = FactorHistory(model, window_s, live, channels)
        self.last: EstimateUpdate | None = None
        self.rebuilt_windows = 0
        self.live_windows = 0

    @property
    def axes(self) -> tuple[str, ...]:
        return self.model.axes

    def rebuild(self, records: Iterable[WindowRecord], *, origin: WindowRecord | None = None) -> int:
        """Recompute the state from stored ``records`` (window order) in batch; returns windows replayed.

        ``origin``: the oldest stored window, where derived column inputs start settled (default: the first
        of ``records``).
        """
        if self.history.last_index is not None:
            raise RuntimeError("rebuild() comes before the first live window")
        records = list(records)
        if self.model.inputs and records:
            self.history.begin(([origin] if origin is not None else []) + records)
        cols = []
        last = None
        for r in records:
            c, _, _ = self.history.advance(r)
            cols.append(c)
            last = r
        if not cols:
            return 0
        du = np.concatenate(cols, axis=1)
        self.stepper = ModelStepper.from_history(self.dm, du)
        self.rebuilt_windows = du.shape[1]
        self._rebuilt(last.index - du.shape[1] + 1 if last is not None else 0, du)
        assert last is not None
        y = self.stepper.output()
        self.last = EstimateUpdate(index=last.index, end_s=last.end_s, estimate_um=self._axes_map(y),
                                   next_um=self._predict(du[:, -1]),
                                   factors=MappingProxyType(dict(last.factors)), usable=False,
                                   reason="rebuilt from the records: no live window yet")
        return du.shape[1]

    def _stepped(self, index: int, du: np.ndarray) -> None:
        """Window ``index`` was stepped live (a filled one too) with inputs ``du``; a subclass layers on it."""

    def _rebuilt(self, first_index: int, du: np.ndarray) -> None:
        """The rebuild replayed windows ``first_index``.. with inputs ``du``; a subclass layers on it."""

    def outside_coverage(self, du: np.ndarray, record: WindowRecord | None = None) -> str:
        """Why input deviations ``du`` (one window) and ``record``'s columns lie outside the coverage ("" inside).

        An implausible column value (a thermometer in other units) says so.
        """
        cov = self.model.coverage
        if cov is None:
            return ""
        columns = {c: np.array([record.channel_mean(c)]) for c in self.history.columns} if record is not None else None
        check = check_coverage(cov, np.asarray(du, dtype=float)[: len(self.model.factors), None], self.model.factors,
                               columns=columns)
        return "; ".join(f"{e.what} {e.value:.4g} ({e.side} the covered {e.bound:.4g}"
                         f"{', implausible: other units or a faulty sensor?' if e.implausible else ''})"
                         for e in check.excursions)

    def _axes_map(self, y: np.ndarray) -> Mapping[str, float]:
        return MappingProxyType({a: float(v) for a, v in zip(self.model.axes, y, strict=True)})

    def _predict(self, du: np.ndarray) -> Mapping[str, float]:
        """The estimate one window ahead if the inputs stay at ``du`` (the state is not touched)."""
        return self._axes_map(self.stepper.peek(du))

    def update(self, record: WindowRecord) -> EstimateUpdate:
        """Step through ``record`` (and any windows missing before it); return the new estimate."""
        cols, filled, reason = self.history.advance(record)
        y = None
        for k in range(cols.shape[1]):
            y = self.stepper.step(cols[:, k])
            self._stepped(record.index - cols.shape[1] + 1 + k, cols[:, k])
        assert y is not None
        inputs = "window" if not reason else "held" if self.history.holds(record.index) else "reference"
        if filled and not reason:
            gap = self.history.gaps[-1]
            log.warning("%s", gap.describe(self.window_s))
        upd = EstimateUpdate(index=record.index, end_s=record.end_s, estimate_um=self._axes_map(y),
                             next_um=self._predict(cols[:, -1]),
                             factors=MappingProxyType(dict(record.factors)), usable=not reason, reason=reason,
                             filled=filled, first_live=self.live_windows == 0, notes=record.notes,
                             outside_coverage="" if reason else self.outside_coverage(cols[:, -1], record),
                             inputs=inputs,
                             held_factors=self.history.last_good_factors if inputs == "held" else MappingProxyType({}))
        self.live_windows += 1
        self.last = upd
        return upd
