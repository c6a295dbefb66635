"""The models diagnosis can write, side by side on the same held-out blocks; the best that passes is written.

- ``identified``: the model as it was identified (a free offset per recording, as ``cncgw estimate``
  aligns a recording on its start).
- ``terms``: the accepted hypotheses as terms on top of the frozen identified model.
- ``reidentified``: every path identified again on all recordings given (identification experiments and
  production alike), with the accepted hypotheses' terms when there are any; without them it is "more
  data alone".

Each is scored the same way: per held-out block, its gains (path gains included) are refitted on the
other blocks at the time constants and settings chosen on all data, and the block is predicted. Nuisance
(a recording's own drift or initial state) is fitted while identifying and left out of the scoring, as
``cncgw estimate`` and ``cncgw run`` know nothing of it: the figures are what the written model does.
A candidate passes when its held-out error is lower than the identified model's consistently over the
blocks (one-sided signed-rank test at ``alpha``) and by at least ``min_gain`` of the squared error. Blocks
are judged, and figures given, on the recordings the identified model did not train on (its own
experiments are a fit for it, not a test), or on all when there are no others.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from gateway.diagnose.data import Stack
from gateway.diagnose.refit import Reidentified
from gateway.diagnose.search import Options, SearchResult, setting_columns
from gateway.diagnose.select import held_out, one_sided_p
from gateway.estimate import AxisFigures, error_figures
from gateway.model.model import ThermalModel

KEYS = ("identified", "terms", "reidentified")


@dataclass(frozen=True, kw_only=True)
class HeldMetrics(AxisFigures):
    """Held-out errors of one axis: RMS, max |error|, peak |displacement|, max error as % of peak."""


@dataclass(kw_only=True)
class Candidate:
    """One model diagnosis could write, scored on the held-out blocks."""

    key: str
    title: str
    model: ThermalModel
    prediction: dict[str, np.ndarray]  # per axis: held-out predictions of the measurement (NaN where not held out)
    block_sse: np.ndarray  # held-out SSE per judged block, pooled over the axes (um^2)
    metrics: dict[str, HeldMetrics]
    p: float = math.nan  # vs the identified model: one-sided signed-rank over the blocks
    gain: float = 0.0  # share of the identified model's pooled held-out SSE removed
    passes: bool = False
    verdict: str = ""

    @property
    def sse(self) -> float:
        return float(self.block_sse.sum())


@dataclass(kw_only=True)
class Comparison:
    """Every candidate, and the one written."""

    candidates: dict[str, Candidate]
    chosen: str

    @property
    def written(self) -> Candidate:
        return self.candidates[self.chosen]


def compare(stack: Stack, model: ThermalModel, block: np.ndarray, result: SearchResult, extended: ThermalModel,
            reid: Reidentified | None, *, artefacts: Mapping[str, Sequence[np.ndarray]],
            options: Options) -> Comparison:
    """Score the identified model, the terms on it and the re-identified model on the same held-out blocks."""
    offsets = stack.per_recording()
    physics = [t for t in result.accepted if not t.hypothesis.artefact]
    k = int(block.max()) + 1 if (block >= 0).any() else 0
    cands: dict[str, Candidate] = {}
    specs: list[tuple[str, str, ThermalModel]] = [("identified", "the identified model as it is", model)]
    if physics:
        specs.append(("terms", "the accepted terms on the frozen identified model", extended))
    if reid is not None:
        specs.append(("reidentified", "re-identified on all recordings" + (" with the accepted terms" if physics
                                                                           else " (more data alone, no new term)"),
                      reid.model))
    for key, title, m in specs:
        pred, sse, metrics = {}, np.zeros(k), {}
        for i, a in enumerate(stack.axes):
            ok = (block != -1) & np.isfinite(stack.y[i])
            rows = np.flatnonzero(ok)
            if len(rows) < 8 or k == 0:
                continue
            cols = [c[rows] for c in offsets if np.any(c[rows])] + [c[rows] for c in artefacts.get(a, [])]
            if key == "reidentified":
                assert reid is not None
                target = (stack.y[i] - reid.fixed[a])[rows]
                cols += [c[rows] for c in reid.columns.get(a, [])]
                shift = reid.fixed[a][rows]
            else:
                target = (stack.y[i] - stack.base[i])[rows]
                shift = stack.base[i][rows]
                if key == "terms":
                    for t in physics:
                        e = t.evidence.get(a)
                        if e is not None and e.included and e.setting is not None:
                            cols += [c[rows] for c in setting_columns(stack, e.setting)[0]]
            p, per_block = held_out(target, block[rows], cols)
            sse[: len(per_block)] += per_block
            full = np.full(stack.n, np.nan)
            full[rows] = p + shift
            pred[a] = full
        cands[key] = Candidate(key=key, title=title, model=m, prediction=pred, block_sse=sse, metrics=metrics)
    # judged on what the identified model did not train on: its own experiments' blocks are a fit there, not
    # a test, and would count against every other candidate; with nothing else given, on every block
    seen = set(model.info.get("experiments", []) or [])
    unseen = np.zeros(stack.n, dtype=bool)
    for name, (lo, hi) in zip(stack.names, stack.bounds, strict=True):
        unseen[lo:hi] = name not in seen
    if not (unseen & (block >= 0)).any():
        unseen[:] = True
    judged = np.zeros(k, dtype=bool)
    judged[np.unique(block[unseen & (block >= 0)])] = True
    # the peak is the measured displacement's, offset by what the identified model's scoring took as the zero
    base = cands["identified"]
    for c in cands.values():
        c.block_sse = c.block_sse[judged]
    for i, a in enumerate(stack.axes):
        if a not in base.prediction:
            continue
        held = np.isfinite(base.prediction[a]) & unseen
        zero = base.prediction[a][held] - stack.base[i][held]
        measured = stack.y[i][held] - zero
        for c in cands.values():
            err = stack.y[i][held] - c.prediction[a][held]
            c.metrics[a] = HeldMetrics(axis=a, **error_figures(err, measured))
    for c in cands.values():
        if c is base:
            c.passes, c.verdict = True, "the reference"
            continue
        c.p = one_sided_p(base.block_sse - c.block_sse)
        c.gain = 1.0 - c.sse / base.sse if base.sse > 0 else 0.0
        if not c.p < options.alpha:
            c.verdict = f"not consistently better over the blocks (p = {c.p:.2g})"
        elif c.gain < options.min_gain:
            c.verdict = f"held-out squared error down only {100 * c.gain:.0f} % (< {100 * options.min_gain:.0f} %)"
        else:
            c.passes, c.verdict = True, f"passes: held-out squared error down {100 * c.gain:.0f} % (p = {c.p:.2g})"
    chosen = "identified"
    passing = [c for c in cands.values() if c.passes and c is not base]
    if passing:
        # the fewest changes first: the frozen model with terms, unless re-identifying is significantly better
        order = sorted(passing, key=lambda c: KEYS.index(c.key))
        best = order[0]
        for c in order[1:]:
            if c.sse < best.sse and one_sided_p(best.block_sse - c.block_sse) < options.alpha:
                best = c
        chosen = best.key
    for c in cands.values():
        if c.key == chosen and c is not base:
            c.verdict += "; written"
    return Comparison(candidates=cands, chosen=chosen)
