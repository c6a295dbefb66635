"""Named mechanisms these recordings cannot tell apart from a path the model already has.

A mechanism whose input is made of the model's factors (the cabinet's sum of currents^2, eddy loss's
speed^2, a chiller's on/off flag, preload's speed times its own lag) is told apart from the identified paths
only by what of its input no single factor carries: re-identification gives a factor's path another or a
slower mode, and where that factor carries the input's whole variation, the path does what the mechanism
would. So each such input, through a thermal lag (:data:`LAG_S`), is regressed on each factor alone (with an
offset); when the best factor leaves less than :data:`CONFUSED_SHARE` of the input's variance unexplained on
these recordings, no fit can name the mechanism, and the report says so and what would tell them apart.

Measured on bench/diagnose.py's production days (96 days of the cabinet cases, 72 of the eddy-loss cases,
every variant): the cabinet's sum of currents^2 against the spindle's stator current alone left 0.06 %
(median; at most 0.53 %): the feed axes' currents carry 3 % of its heat, and their variation follows the
spindle's jobs. Against that, speed^2 against speed left 1.9-7.6 %, speed times its 1 h lag 4.3-11 %, the
spindle-on flag 3.9-18 %: mechanisms the bench names.

A recorded column (a thermometer of unknown meaning, the room) is compared the same way, with the factor
allowed a further lag (:data:`COLUMN_LAGS_S`): a temperature follows its heat late. A cabinet thermometer on
those days (bench "cabinet recorded", v1) left 0.26 % of its variation to the spindle current through a
further 1 h (7.8 % with no further lag): it names nothing a slower mode of that path would not do. The room's
thermometer, which varies for reasons of its own, is never carried.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from gateway.diagnose.data import Stack, lag
from gateway.diagnose.hypotheses import Hypothesis
from gateway.model.coverage import duration_text
from gateway.model.inputs import Column, DerivedInput, Periodic

#: the thermal lag the inputs are compared through: what a path smooths away cannot tell anything apart
LAG_S = 3600.0
#: below this share of an input's (lagged) variance left unexplained by one factor, the two are confused
CONFUSED_SHARE = 0.01
#: further lags a factor may take to be compared with a recorded column (a part's temperature lags its heat)
COLUMN_LAGS_S = (0.0, 600.0, 1800.0, 3600.0, 2 * 3600.0, 4 * 3600.0)


@dataclass(frozen=True, kw_only=True)
class Confusion:
    """A mechanism whose inputs one factor carries on these recordings."""

    key: str  # the hypothesis
    title: str
    inputs: tuple[str, ...]  # its derived inputs, described
    factor: str  # the factor that carries them
    unexplained: float  # the largest share, over its inputs, of the (lagged) variance the factor leaves
    tell_apart: str  # what would tell them apart
    factor_lag_s: float = 0.0  # the further lag the factor took (a recorded column's comparison)

    def line(self, *, accepted: bool = False) -> str:
        """The report's sentence; ``accepted``: a term of its shape passed, but its name is not established."""
        what = (f"it was taken for the shape of its response, not for its input, and a mode of that shape on the "
                f"paths of {self.factor} would do the same, so its name is not established" if accepted else
                f"another or a slower mode on the paths of {self.factor} does what it would, and no fit can tell "
                "them apart, so these recordings cannot name it")
        return (f"{self.title}: on these recordings its input ({'; '.join(self.inputs)}) follows {self.factor} "
                f"to all but {100 * self.unexplained:.2g} % of its variation (through a {LAG_S / 3600:g} h lag"
                + (f"; {self.factor} through another {duration_text(self.factor_lag_s)}" if self.factor_lag_s else "")
                + "): "
                f"{what}; to tell them apart: {self.tell_apart}")


def unexplained_share(u: np.ndarray, v: np.ndarray) -> float:
    """Share of ``u``'s variance that ``v`` (scaled, with an offset) leaves unexplained; 1 when ``v`` is flat.

    Over the windows where both are finite (a gap left open by the gap policy counts for neither).
    """
    ok = np.isfinite(u) & np.isfinite(v)
    u = u[ok] - u[ok].mean() if ok.any() else u[:0]
    v = v[ok] - v[ok].mean() if ok.any() else v[:0]
    uu, vv = float(u @ u), float(v @ v)
    if vv <= 0.0 or uu <= 0.0:
        return 1.0
    return max(0.0, 1.0 - float(u @ v) ** 2 / (uu * vv))


def confusions(stack: Stack, hypotheses: Sequence[Hypothesis]) -> list[Confusion]:
    """The hypotheses whose every derived input one factor carries on ``stack``'s recordings (see module)."""
    through = lag(LAG_S)
    lagged = {f: stack.response(stack.du[f], through) for f in stack.factors}
    further: dict[tuple[str, float], np.ndarray] = {}  # a factor through a further lag, for recorded columns

    def carried(u: np.ndarray, column: bool) -> tuple[float, str, float]:
        """(least share left, by which factor, through which further lag)."""
        best = (1.0, "", 0.0)
        for f, v in lagged.items():
            for tau in COLUMN_LAGS_S if column else (0.0,):
                if tau and (f, tau) not in further:
                    further[f, tau] = stack.response(v, lag(tau))
                share = unexplained_share(u, further[f, tau] if tau else v)
                if share < best[0]:
                    best = (share, f, tau)
        return best

    out = []
    for h in hypotheses:
        if h.artefact:
            continue
        # the derived inputs the components read, each with the chain that defines it
        inputs: dict[DerivedInput, tuple[DerivedInput, ...]] = {}
        for grid in h.settings.values():
            for s in grid:
                defined = {d.name: d for d in s.chain}
                for comp in s.components:
                    for p in comp.parts:
                        if p.input in defined:
                            inputs.setdefault(defined[p.input], s.chain)
        # inputs made of factors, or recorded columns; the time of day is no factor's to carry
        if not inputs or any(isinstance(d, Periodic) for chain in inputs.values() for d in chain):
            continue
        worst, carrier, tau_c = 0.0, "", 0.0
        for d, chain in inputs.items():
            u = stack.response(stack.input_du(d.name, chain), through)
            share, f, tau = carried(u, any(isinstance(x, Column) for x in chain))
            if share >= CONFUSED_SHARE or (carrier and f != carrier):
                break
            worst, carrier, tau_c = max(worst, share), f, max(tau_c, tau)
        else:
            out.append(Confusion(key=h.key, title=h.title, inputs=tuple(d.describe() for d in inputs),
                                 factor=carrier, unexplained=worst, factor_lag_s=tau_c,
                                 tell_apart=h.tell_apart or f"recordings where it varies while {carrier} does not"))
    return out
