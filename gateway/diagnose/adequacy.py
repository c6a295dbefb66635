"""Is the model fit for compensation at all? Judged before any hypothesis, on what it did not train on.

A model identified while something it does not know acted (the room drifting during the experiments) can
predict 50-100 um where the machine moved 15-50 um. No term added to it repairs that, and "nothing
significant is missing" must never be printed over it. Two checks:

- On the recordings the model did not train on (not its identification experiments, known by name or by
  content: :meth:`~gateway.diagnose.data.Stack.identified`), aligned at their
  start as ``cncgw estimate`` aligns them: the largest error against the peak displacement
  (:data:`MAX_ERROR_SHARE`), predictions beyond anything measured (:data:`PREDICTION_EXCESS`), and a
  residual as large as the displacement itself (:data:`RESIDUAL_SHARE`).
- Drift while every input rests (:func:`resting_drift`): stretches of at least :data:`REST_MIN_S` where no
  factor moves and the model predicts no change, yet the displacement moves. That is a disturbance no
  factor carries (room temperature, coolant, a neighbouring machine), or heat slower than every mode of
  the model; the identification experiments' own idle stretches are checked too.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from gateway.diagnose.data import Stack
from gateway.model.model import ThermalModel
from gateway.replay import AxisFigures

#: max |error| beyond this share of the peak |displacement| is unfit for compensation
MAX_ERROR_SHARE = 0.30
#: predicting more than this times the largest measured displacement (plus the noise band) is unfit
PREDICTION_EXCESS = 1.25
#: a residual RMS at least this share of the displacement's own RMS: the model explains next to nothing
RESIDUAL_SHARE = 0.7
#: resting stretches shorter than this are not judged
REST_MIN_S = 45 * 60.0
#: a factor "rests" within this share of its range over the recordings
REST_SHARE = 0.02


@dataclass(frozen=True, kw_only=True)
class AxisAdequacy(AxisFigures):
    """The model's errors on one axis over the recordings it did not train on, and why it is unfit (if so)."""

    predicted_peak_um: float
    displacement_rms_um: float
    worst: str = ""  # the recording whose max error is the largest share of its peak (the figures above are its)
    reasons: tuple[str, ...] = ()

    @property
    def fit(self) -> bool:
        return not self.reasons


@dataclass(frozen=True, kw_only=True)
class RestingDrift:
    """Drift of one axis while every input rested and the model predicted no change."""

    axis: str
    stretches: int  # resting stretches judged
    drifting: int  # of them, those whose displacement moved beyond the noise
    largest_um: float  # the largest drift over one stretch
    rate_um_h: float  # its rate
    recordings: tuple[str, ...]  # where the drifting stretches are


@dataclass(frozen=True, kw_only=True)
class Adequacy:
    """The verdict before any hypothesis: per axis on unseen recordings, and drift at rest."""

    unseen: tuple[str, ...]  # the recordings judged
    axes: dict[str, AxisAdequacy]
    drift: dict[str, RestingDrift]
    training: bool = False  # no recording the model did not train on: judged on its own experiments
    # unseen recordings that seem not to start at rest (label: why, :func:`gateway.replay.starts_warm`), and the
    # verdict without them: the model is started in equilibrium with each recording's first window, so the
    # error of one that starts warm is its start's as much as the model's
    not_at_rest: dict[str, str] = field(default_factory=dict)
    without: Adequacy | None = None
    # every recording (seen or not) that seems not to start at rest, when they are a minority: a drift at rest
    # only in them may be the machine settling from its start (when all are, a disturbance is likelier)
    settling: tuple[str, ...] = ()

    @property
    def judged(self) -> bool:
        """Whether any recording the model did not train on was there to judge it."""
        return bool(self.axes) and not self.training

    @property
    def fit(self) -> bool:
        return all(a.fit for a in self.axes.values())

    @property
    def unfit_axes(self) -> list[str]:
        return [a for a, x in self.axes.items() if not x.fit]

    def summary(self) -> str:
        """Where the model is fit, how far it stays within the peak, in one sentence (see :meth:`lines`)."""
        # an axis whose peak is within the noise (probes of 0.3 um on a 1.7 um peak) is not judged by share
        judged = [x for x in self.axes.values() if x.worst] or list(self.axes.values())
        worst = max(judged, key=lambda x: x.max_error_pct_of_peak)
        where = "it was identified on" if self.training else "it did not train on"
        return (f"on {len(self.unseen)} recording(s) {where}, the model stays within "
                f"{worst.max_error_pct_of_peak:.0f} % of the peak displacement (worst: axis {worst.axis} in "
                f"{worst.worst}, max |error| {worst.max_abs_error_um:.3g} um of {worst.peak_um:.3g} um)")

    def lines(self) -> list[str]:
        """Plain sentences, the verdict first."""
        out = []
        where = (f"even on the {len(self.unseen)} recording(s) it was identified on" if self.training else
                 f"on {len(self.unseen)} recording(s) it did not train on")
        if self.axes and not self.fit:
            why = "; ".join(f"axis {a}: {', '.join(x.reasons)}" for a, x in self.axes.items() if x.reasons)
            out.append(f"this model is not fit for compensation: {where}, {why}")
            if self.not_at_rest and self.without is not None:
                which = [f"{k} ({v})" for k, v in self.not_at_rest.items()]
                several = len(which) > 1
                which = (f"{', '.join(which[:-1])}{' and ' if several else ''}{which[-1]} "
                         f"{'seem' if several else 'seems'} not to start at rest")
                if self.without.fit:
                    out.append(f"{which}; every recording is started in equilibrium with its first window, so there "
                               "the error is the start's as much as the model's; without "
                               f"{'them' if several else 'it'}: {self.without.summary()}: diagnose recordings that "
                               "start at rest (whole days, or cut where the machine had rested)")
                else:
                    out.append(f"{which}, but without {'them' if several else 'it'} the model is not fit either (axes "
                               f"{', '.join(self.without.unfit_axes)} on the other {len(self.without.unseen)})")
        elif not self.judged:
            out.append("the model's fitness for compensation cannot be judged: every recording given identified it "
                       "(there it fits); pass recordings it has not seen (production days with measured "
                       "displacement)")
        else:
            out.append(self.summary())
        for d in self.drift.values():
            if d.drifting:
                out.append(f"axis {d.axis}: the displacement drifts while every input rests and the model predicts no "
                           f"change, in {d.drifting} of {d.stretches} resting stretches (up to {d.largest_um:.3g} um, "
                           f"{d.rate_um_h:+.2g} um/h; {', '.join(d.recordings[:4])}"
                           f"{', ...' if len(d.recordings) > 4 else ''}): a disturbance no factor carries (room "
                           "temperature, coolant, a neighbouring machine), or heat slower than every mode of the model"
                           + ("; but only in recordings that seem not to start at rest, where it may be the machine "
                              "settling from its start" if self.settling and set(d.recordings) <= set(self.settling)
                              else ""))
        return out


def assess(stack: Stack, model: ThermalModel, sigma_um: dict[str, float],
           artefacts_um: Mapping[str, np.ndarray] | None = None, *,
           not_at_rest: Mapping[int, str] | None = None) -> Adequacy:
    """Judge ``model`` (its prediction is ``stack.base``) before any hypothesis; ``sigma_um``: noise per axis.

    ``artefacts_um``: per axis, the measurement artefacts found (steps within one window: a sensor knocked or
    re-zeroed), every window of the stack; they are the sensor's, not the model's, and are taken out of the
    measurement before it is judged (the report lists them).

    ``not_at_rest``: recordings (by index) that seem not to start at rest, and why. The verdict is still taken on
    every recording (a room drifting in the first hour looks like a warm start too, and must not hide an unfit
    model); where it finds the model unfit, it is also taken without them, and both are said.
    """
    y_all = stack.y.copy()
    for i, a in enumerate(stack.axes):
        if artefacts_um and a in artefacts_um:
            y_all[i] = y_all[i] - artefacts_um[a]
    unseen = [r for r, seen in enumerate(stack.identified(model)) if not seen]
    training = not unseen  # nothing else given: judged on its own experiments (if even they fail, it is unfit)
    if training:
        unseen = list(range(len(stack.bounds)))
    axes = _judge(stack, y_all, unseen, sigma_um)
    drift = {a: resting_drift(stack, i, sigma_um.get(a, 0.0), y=y_all[i]) for i, a in enumerate(stack.axes)
             if np.isfinite(stack.y[i]).any()}
    settling = tuple(stack.labels[r] for r in (not_at_rest or {})) if 2 * len(not_at_rest or {}) < len(stack.bounds) \
        else ()
    out = Adequacy(unseen=tuple(stack.labels[r] for r in unseen), axes=axes, drift=drift, training=training,
                   settling=settling)
    warm = {r: why for r, why in (not_at_rest or {}).items() if r in unseen}
    if warm and not out.fit and len(warm) < len(unseen):
        rest = [r for r in unseen if r not in warm]
        without = _judge(stack, y_all, rest, sigma_um)
        if without:
            out = replace(out, not_at_rest={stack.labels[r]: why for r, why in warm.items()},
                          without=Adequacy(unseen=tuple(stack.labels[r] for r in rest), axes=without, drift={},
                                           training=training))
    return out


def _judge(stack: Stack, y_all: np.ndarray, unseen: list[int], sigma_um: Mapping[str, float]
           ) -> dict[str, AxisAdequacy]:
    """Per axis, the model's errors on the recordings ``unseen`` (indices) and why it is unfit there (if so)."""
    axes: dict[str, AxisAdequacy] = {}
    for i, a in enumerate(stack.axes):
        parts = []  # (recording, error, measured, predicted) per unseen recording, aligned as estimate aligns
        for r in unseen:
            lo, hi = stack.bounds[r]
            y, p = y_all[i, lo:hi], stack.base[i, lo:hi]
            ok = np.isfinite(y)
            if not ok.any():
                continue
            lead = stack.lead_in(r) & ok
            if not lead.any():
                lead = np.zeros_like(ok)
                lead[int(np.flatnonzero(ok)[0])] = True
            offset = float(np.mean(y[lead] - p[lead]))
            parts.append((stack.labels[r], (y - offset - p)[ok], (y - offset)[ok], p[ok]))
        if not parts:
            continue
        err = np.concatenate([e for _, e, _, _ in parts])
        m = np.concatenate([x for _, _, x, _ in parts])
        p = np.concatenate([x for _, _, _, x in parts])
        fig = AxisFigures.of(a, err, m)
        band = 3.0 * sigma_um.get(a, 0.0)
        disp_rms = float(np.sqrt(np.mean((m - m.mean()) ** 2)))
        reasons = []
        # per recording, as a user running `cncgw estimate` on it sees it; a recording in which the axis barely
        # moved (under a fifth of its largest peak, or the noise) is not judged by its share of peak
        judged = [(name, AxisFigures.of(a, e, x)) for name, e, x, _ in parts]
        floor = max(10.0 * sigma_um.get(a, 0.0), 0.2 * fig.peak_um)
        worst = max(((name, f) for name, f in judged if f.peak_um >= floor),
                    key=lambda nf: nf[1].max_error_pct_of_peak, default=None)
        if worst is not None and worst[1].max_error_pct_of_peak > 100 * MAX_ERROR_SHARE:
            name, f = worst
            reasons.append(f"max |error| {f.max_abs_error_um:.3g} um is {f.max_error_pct_of_peak:.0f} % of the "
                           f"peak displacement {f.peak_um:.3g} um in {name} "
                           f"(fit: under {100 * MAX_ERROR_SHARE:.0f} %)")
        predicted = float(np.max(np.abs(p)))
        if predicted > PREDICTION_EXCESS * fig.peak_um + band:
            reasons.append(f"it predicts up to {predicted:.3g} um where the machine moved at most "
                           f"{fig.peak_um:.3g} um")
        if disp_rms > band and fig.rms_um >= RESIDUAL_SHARE * disp_rms:
            reasons.append(f"its error ({fig.rms_um:.3g} um RMS) is as large as the displacement itself "
                           f"({disp_rms:.3g} um RMS)")
        if worst is not None:  # the worst recording's figures, over all windows' RMS
            w = worst[1]
            fig = replace(fig, max_abs_error_um=w.max_abs_error_um, peak_um=w.peak_um,
                          max_error_pct_of_peak=w.max_error_pct_of_peak)
        axes[a] = AxisAdequacy(**asdict(fig), predicted_peak_um=predicted, displacement_rms_um=disp_rms,
                               worst=worst[0] if worst else "", reasons=tuple(reasons))
    return axes


def resting_drift(stack: Stack, axis: int, sigma_um: float, *, y: np.ndarray | None = None) -> RestingDrift:
    """Drift of the displacement over stretches where no factor moves and the model predicts no change.

    ``y``: the axis's measurement with its artefacts taken out (default: as recorded).
    """
    at_rest = np.ones(stack.n, dtype=bool)
    for f in stack.factors:
        u = stack.du[f]
        span = float(np.ptp(u)) if u.size else 0.0
        if span > 0:
            # resting: at the level the recording started from (the model's rest), within a share of the range
            at_rest &= np.abs(u) <= REST_SHARE * span
    min_len = max(3, math.ceil(REST_MIN_S / stack.dt_s))
    y, base = (stack.y[axis] if y is None else y), stack.base[axis]
    band = max(4.0 * sigma_um, 1e-9)
    judged = drifting = 0
    largest = rate = 0.0
    where: list[str] = []
    for r, (lo, hi) in enumerate(stack.bounds):
        k = lo
        while k < hi:
            if not at_rest[k]:
                k += 1
                continue
            end = k
            while end < hi and at_rest[end]:
                end += 1
            if end - k >= min_len:
                seg = slice(k, end)
                ok = np.isfinite(y[seg])
                if ok.sum() >= min_len and float(np.ptp(base[seg])) < band:
                    judged += 1
                    t_h = (stack.time_s[seg][ok] - stack.time_s[k]) / 3600.0
                    slope = float(np.polyfit(t_h, y[seg][ok], 1)[0]) if len(t_h) > 2 else 0.0
                    moved = slope * float(t_h[-1] - t_h[0])
                    if abs(moved) > band:
                        drifting += 1
                        if stack.labels[r] not in where:
                            where.append(stack.labels[r])
                        if abs(moved) > abs(largest):
                            largest, rate = moved, slope
            k = end
    return RestingDrift(axis=stack.axes[axis], stretches=judged, drifting=drifting, largest_um=abs(largest),
                        rate_um_h=rate, recordings=tuple(where))
