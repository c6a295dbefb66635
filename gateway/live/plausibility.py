"""Is an estimate plausible? Bounds from the model's envelope, and the checks ``cncgw run`` makes at start.

A model can be wrong in ways no loader catches: a gain or a reference level that is finite but absurd
(a corrupted file, a hand edit), or a machine run far outside what the identification experiments
covered. Its estimate is then finite and large, and clamping it to ``limit_um`` would still walk the
offsets there at ``max_step_um`` a window. So the compensation writer holds the offsets and raises the
alarm ``implausible`` when an estimate leaves the model's plausibility envelope; it never clamps and
writes such an estimate.

Bounds per axis, from the envelope identification stored in the model file
(:mod:`gateway.model.envelope`):

- ``|estimate| <= 1.5 x max_abs_um + 5 um``;
- ``|change| <= (1.5 x max_change_um + 1 um) x max(1, window_s / envelope window)`` per window, measured
  from the last estimate that passed (n windows later: n times that), so an absurd level is not accepted
  because it stopped moving.

Why these margins: the held-out runs of the simulated machine within the identified speeds reach 1.18x
the identified peak (spindle-and-feeds, z: 20.0 um vs 17.0 um) and 1.02x its fastest change per window
(2.61 vs 2.55 um); 1.5x leaves room for work moderately harder than any experiment, and the additive
terms keep an axis the experiments barely moved (an identified peak near the sensor noise) from alarming
on noise. Beyond that the model extrapolates far from its data (a 3000 rpm production day on a model
identified up to 1000 rpm reaches 87 um in z, 5x the identified peak): the remedy is identification
experiments that cover that work, not a write. A profile may tighten a bound
(``[compensation.axes.AXIS] plausible_um``, ``plausible_change_um``), never widen it.

A model without an envelope (written before identification recorded one) is refused when the profile
writes to the CNC; in a dry run it gets bounds derived from the profile, ``|estimate| <= limit_um`` and a
change of at most ``limit_um / 10`` a window, and the start is logged as such.

The start checks (:func:`model_refusals`): the model names this machine (its ``machine`` equals the
profile's ``[machine] name``), estimates every axis the profile compensates, and has an envelope covering
them when writing.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from gateway.model import ThermalModel
from gateway.profile.live import Compensation

ABS_FACTOR = 1.5
ABS_MARGIN_UM = 5.0
CHANGE_FACTOR = 1.5
CHANGE_MARGIN_UM = 1.0
#: a dry run's bounds for a model without an envelope: |estimate| <= limit_um, change <= limit_um / this
DERIVED_CHANGE_DIVISOR = 10.0


@dataclass(frozen=True, kw_only=True, slots=True)
class AxisBound:
    """One axis's bound on the estimate (``abs_um``) and on its change in one live window (``change_um``)."""

    axis: str
    abs_um: float
    change_um: float
    origin: str  # where the numbers come from, for messages


class Plausibility:
    """Checks estimates against per-axis bounds; remembers the last estimate that passed.

    Build it with :meth:`for_model`. :meth:`check` returns ``""`` for a plausible estimate (and remembers
    it as the base of the next change) or the reason it is not.
    """

    def __init__(self, bounds: Mapping[str, AxisBound], *, source: str) -> None:
        self.bounds = dict(bounds)
        self.source = source
        self._last: tuple[int, dict[str, float]] | None = None

    @classmethod
    def for_model(cls, model: ThermalModel, settings: Compensation, *, window_s: float) -> Plausibility:
        """Bounds for the axes ``settings`` compensates, from ``model``'s envelope (see the module docstring)."""
        env = model.envelope
        bounds = {}
        for out in settings.axes:
            a = out.axis
            if env is not None and a in env.axes:
                e = env.axes[a]
                scale = max(1.0, window_s / env.window_s)
                abs_um = ABS_FACTOR * e.max_abs_um + ABS_MARGIN_UM
                change_um = (CHANGE_FACTOR * e.max_change_um + CHANGE_MARGIN_UM) * scale
                origin = (f"the model's envelope: {e.max_abs_um:.3g} um and {e.max_change_um:.3g} um a window "
                          f"identified, x{ABS_FACTOR:g} + {ABS_MARGIN_UM:g} um and x{CHANGE_FACTOR:g} + "
                          f"{CHANGE_MARGIN_UM:g} um")
            else:
                abs_um = settings.limit_um
                change_um = settings.limit_um / DERIVED_CHANGE_DIVISOR
                origin = "derived from limit_um (the model has no envelope)"
            tightened = []
            if out.plausible_um is not None and out.plausible_um < abs_um:
                abs_um = out.plausible_um
                tightened.append("plausible_um")
            if out.plausible_change_um is not None and out.plausible_change_um < change_um:
                change_um = out.plausible_change_um
                tightened.append("plausible_change_um")
            if tightened:
                origin += f", tightened by the profile's {' and '.join(tightened)}"
            bounds[a] = AxisBound(axis=a, abs_um=abs_um, change_um=change_um, origin=origin)
        source = env.source if env is not None else "no envelope in the model: bounds derived from limit_um"
        return cls(bounds, source=source)

    def describe(self) -> str:
        return "; ".join(f"{b.axis} |estimate| <= {b.abs_um:.3g} um, change <= {b.change_um:.3g} um a window"
                         for b in self.bounds.values())

    def check(self, index: int, estimate: Mapping[str, float], ahead: Mapping[str, float] | None = None) -> str:
        """``""`` when ``estimate`` (window ``index``) and the prediction ``ahead`` one window on are plausible.

        A plausible estimate becomes the base of the next change check; an implausible one does not.
        """
        problems = []
        windows = 1 if self._last is None else max(1, index - self._last[0])
        for a, b in self.bounds.items():
            v = estimate.get(a, math.nan)
            if not math.isfinite(v):
                problems.append(f"{a} estimate {v!r} is not finite")
                continue
            if abs(v) > b.abs_um:
                problems.append(f"{a} estimate {v:+.4g} um is beyond +-{b.abs_um:.3g} um ({b.origin})")
                continue
            if self._last is not None:
                prev = self._last[1][a]
                if abs(v - prev) > windows * b.change_um:
                    problems.append(f"{a} estimate moved {v - prev:+.4g} um in {windows} window(s) from "
                                    f"{prev:+.4g} um at window {self._last[0]}, more than {windows} x "
                                    f"{b.change_um:.3g} um ({b.origin})")
                    continue
            if ahead is not None:
                n = ahead.get(a, math.nan)
                if not math.isfinite(n) or abs(n) > b.abs_um or abs(n - v) > b.change_um:
                    problems.append(f"{a} prediction one window ahead {n:+.4g} um is beyond +-{b.abs_um:.3g} um "
                                    f"or {b.change_um:.3g} um from the estimate ({b.origin})")
        if problems:
            return f"window {index}: implausible estimate: " + "; ".join(problems)
        self._last = (index, {a: float(estimate[a]) for a in self.bounds})
        return ""


def model_refusals(model: ThermalModel, profile_name: str, settings: Compensation,
                   model_path: str | Path | None = None) -> list[str]:
    """Why ``cncgw run`` must not start with this model on this machine (empty: it may)."""
    where = f"{model_path}: " if model_path else ""
    out = []
    if model.machine != profile_name:
        named = f'names machine "{model.machine}"' if model.machine else "names no machine"
        out.append(f'{where}the model {named}, but this profile is machine "{profile_name}": a model is only '
                   f"valid for the machine it was identified on (identify this machine, or set [model] machine "
                   f"if the file was renamed)")
    missing = [o.axis for o in settings.axes if o.axis not in model.axes]
    if missing:
        out.append(f"{where}the model does not estimate axis {', '.join(missing)}, which the profile compensates "
                   f"(model axes: {', '.join(model.axes)}): identify the model on every compensated axis or "
                   "remove the axis from [compensation.axes]")
    if settings.enabled and model.envelope is None:
        out.append(f"{where}the model has no [envelope] (the range of displacement its identification data "
                   "support; models written before it was recorded lack it): nothing would bound its estimates, "
                   "so compensation.enabled = true refuses it; re-run `cncgw identify`, or add it with `cncgw "
                   "model envelope`, or run with compensation.enabled = false (a dry run)")
    elif model.envelope is not None:
        lacking = [o.axis for o in settings.axes if o.axis in model.axes and o.axis not in model.envelope.axes]
        if lacking:
            out.append(f"{where}the model's [envelope] has no bound for axis {', '.join(lacking)}")
    return out
