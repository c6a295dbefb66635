"""The plausibility envelope of a model: the displacements its identification data support.

Identification records, per axis, the largest displacement the experiments showed (the span of the
measured displacement, which does not depend on the sensor's zero, or the model's prediction of the same
experiments, whichever is larger) and the largest change of the predicted displacement in one window.
The live gateway derives from it a bound on the estimate and on its change per window
(:mod:`gateway.live.plausibility`): an estimate beyond it is the model extrapolating far outside what it
was fitted on, or a corrupted model, and is never written.

In the model file::

    [envelope]
    window_s = 60.0          # the identification's window: max_change_um is per window of this length
    source = "identification: 9 experiments"
    [envelope.z]
    max_abs_um = 19.9        # largest |displacement| measured (span) or predicted over the experiments
    max_change_um = 1.02     # largest change of the predicted displacement in one window
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from gateway.model.model import ThermalModel
    from gateway.tomlcheck import Table

#: an envelope value beyond this (10 mm) is no thermal displacement of a machine tool: the file is corrupt
MAX_ENVELOPE_UM = 10000.0


@dataclass(frozen=True, kw_only=True, slots=True)
class AxisEnvelope:
    """One axis: the largest |displacement| and the largest change per window the experiments showed."""

    max_abs_um: float
    max_change_um: float


@dataclass(frozen=True, kw_only=True)
class Envelope:
    """Per axis, what the identification data support; ``max_change_um`` is per window of ``window_s``."""

    window_s: float
    axes: Mapping[str, AxisEnvelope]
    source: str = ""

    def __post_init__(self) -> None:
        object.__setattr__(self, "axes", MappingProxyType(dict(self.axes)))

    def merged(self, other: Envelope) -> Envelope:
        """The larger of both per axis (``other``'s changes rescaled to this window length)."""
        scale = self.window_s / other.window_s
        axes = dict(self.axes)
        for a, e in other.axes.items():
            mine = axes.get(a)
            change = e.max_change_um * max(1.0, scale)
            axes[a] = e if mine is None else AxisEnvelope(max_abs_um=max(mine.max_abs_um, e.max_abs_um),
                                                          max_change_um=max(mine.max_change_um, change))
        return Envelope(window_s=self.window_s, axes=axes, source=f"{self.source}; {other.source}")


def envelope_of(model: ThermalModel, experiments: Iterable[tuple[np.ndarray, np.ndarray]], *, window_s: float,
                source: str) -> Envelope:
    """The envelope of ``model`` over experiments given as ``(du, y)``.

    ``du``: input deviations (inputs, N) from the experiment's initial equilibrium; ``y``: the measured
    displacement (axes, N; NaN where not measured).
    """
    dm = model.discretize(window_s)
    peak = np.zeros(len(model.axes))
    change = np.zeros(len(model.axes))
    for du, y in experiments:
        du = np.nan_to_num(np.asarray(du, dtype=float), nan=0.0)
        if du.shape[1] == 0:
            continue
        pred = dm.simulate(du)
        # the prediction starts from the equilibrium (0): its first window's change counts too
        steps = np.abs(np.diff(pred, axis=1, prepend=0.0))
        peak = np.maximum(peak, np.abs(pred).max(axis=1))
        change = np.maximum(change, steps.max(axis=1))
        y = np.asarray(y, dtype=float)
        for i in range(len(model.axes)):
            finite = y[i][np.isfinite(y[i])]
            if finite.size:
                peak[i] = max(peak[i], float(finite.max() - finite.min()))
    axes = {a: AxisEnvelope(max_abs_um=float(peak[i]), max_change_um=float(change[i]))
            for i, a in enumerate(model.axes)}
    return Envelope(window_s=float(window_s), axes=axes, source=source)


def envelope_to_toml(env: Envelope) -> dict[str, Any]:
    """The ``[envelope]`` table."""
    out: dict[str, Any] = {"window_s": float(env.window_s)}
    if env.source:
        out["source"] = env.source
    for a, e in env.axes.items():
        out[a] = {"max_abs_um": float(e.max_abs_um), "max_change_um": float(e.max_change_um)}
    return out


def parse_envelope(t: Table, axes: Sequence[str]) -> Envelope | None:
    """Read ``[envelope]`` (every model axis must be there); ``None`` after reporting a problem."""
    window = t.float("window_s", min=0.0, min_exclusive=True, max=86400.0)
    source = t.str("source", default="")
    ok = window is not None
    per_axis = {}
    for a in axes:
        at = t.table(a, required=True, expected=f"a table [envelope.{a}] (max_abs_um, max_change_um)")
        if at is None:
            ok = False
            continue
        peak = at.float("max_abs_um", min=0.0, max=MAX_ENVELOPE_UM,
                        expected=f"the largest |displacement| the identification showed, in um, in [0, "
                                 f"{MAX_ENVELOPE_UM:g}]")
        change = at.float("max_change_um", min=0.0, max=MAX_ENVELOPE_UM,
                          expected=f"the largest change per window the identification showed, in um, in [0, "
                                   f"{MAX_ENVELOPE_UM:g}]")
        at.done()
        if peak is None or change is None:
            ok = False
            continue
        per_axis[a] = AxisEnvelope(max_abs_um=peak, max_change_um=change)
    t.done()
    if not ok or window is None:
        return None
    return Envelope(window_s=window, axes=per_axis, source=source or "")


def describe_envelope(env: Envelope | None) -> list[str]:
    """Lines for ``cncgw model show``."""
    if env is None:
        return ["plausibility envelope: none (a model written before cncgw recorded one; `cncgw run` will not "
                "write offsets from it: re-identify, or add one with `cncgw model envelope`)"]
    lines = [f"plausibility envelope ({env.source or 'source not stated'}; changes per {env.window_s:g} s window):"]
    for a, e in env.axes.items():
        lines.append(f"  {a}: |displacement| up to {e.max_abs_um:.3g} um, change up to {e.max_change_um:.3g} um "
                     "a window")
    return lines


__all__ = ["MAX_ENVELOPE_UM", "AxisEnvelope", "Envelope", "describe_envelope", "envelope_of",
           "envelope_to_toml", "parse_envelope"]
