"""Re-identification as a way to model a hypothesis: every path refitted beside the candidate's terms.

When the missing physics also acted during the identification experiments (the room does not stop
drifting while an experiment runs), the identified paths are wrong, and a term added on top of them cannot
repair them. Two tools here:

- :func:`path_corrections`: for the hypothesis search, columns that let every path of the model change
  (each active input through a bank of first-order lags spanning the identification's time scales). A
  hypothesis judged with them is judged by what it adds to a re-identified model, cheaply (linear).
- :func:`reidentify`: the model itself identified again by the joint identifier on all recordings given
  (identification experiments and production alike), with the accepted hypotheses' terms as inputs beside
  the factors: the model that is written.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from gateway.diagnose.data import Stack, lag, log_grid
from gateway.diagnose.extend import extend_model
from gateway.diagnose.hypotheses import Setting, identification_length_s
from gateway.diagnose.search import Term, Trial, setting_columns
from gateway.diagnose.select import BURN_IN
from gateway.errors import IdentificationError
from gateway.identify.common import Bounds, ExperimentSet
from gateway.identify.joint import AxisProblem, AxisSelection, refine_axis, select_axis
from gateway.model.model import PathTF, ThermalModel

#: lags per input in the correction bank (log-spaced over the identification's time scales)
BANK_PER_DECADE = 2.5
#: the time constants (h) of the free decays beside each recording that runs from a fitted history (see
#: :func:`history_free`)
HISTORY_DECAY_H = (0.5, 2.0, 6.0)


def history_free(stack: Stack) -> list[np.ndarray]:
    """Free decays from the own start of each recording that runs from a fitted history: nuisance of every refit.

    That history (:func:`gateway.diagnose.api.start_histories`) is the best of a few guesses, chosen on the
    axes pooled: on a small axis it can be well off, and paths refitted through it bend to put that right (the
    re-identified x paths of bench/diagnose.py --cut-days 13 predicted the whole fresh day worse in 12 of 26
    rewritten cases: none b v3 x 0.25 -> 0.96 um). Beside the paths, what the guess leaves wrong is not theirs:
    2 of 27 such cases at 13 h, 0 of 39 at 10 h; the changed cases' fresh-day pooled RMS x0.926 and x0.760
    (geometric means; 54 cases each, README: *A recording cut while the machine worked*). Fitted in the time
    constants' fit, the written gains and the held-out refits alike, and never written into the model.
    """
    return [c for tau_h in HISTORY_DECAY_H for c in stack.history_decays(tau_h * 3600.0)]


def bank_taus(stack: Stack, model: ThermalModel) -> list[float]:
    """The correction bank's time constants: from a few windows to the identification runs' length."""
    return log_grid(max(5.0 * 60.0, 2.0 * stack.dt_s), identification_length_s(model), BANK_PER_DECADE)


def path_corrections(stack: Stack, model: ThermalModel) -> list[np.ndarray]:
    """Every input that moves, through every lag of the bank: the span of the paths' possible corrections."""
    cols = []
    for name in model.input_names:
        u = stack.du.get(name)
        if u is None or not np.any(u):
            continue
        for tau in bank_taus(stack, model):
            cols.append(stack.response(u, lag(tau), lead=stack.leads.get(name)))
    return cols


def stack_experiments(stack: Stack, factors: Sequence[str], y: np.ndarray,
                      extras: Sequence[np.ndarray] = ()) -> ExperimentSet:
    """The stack's recordings as the joint identifier's experiments (each from its own initial state).

    ``y`` (axes, every window of the stack) is what is fitted; ``extras`` are stack-long columns that enter
    linearly beside the paths (a hypothesis's terms at fixed time constants, nuisance, artefacts).
    """
    lengths = np.array([b - a for a, b in stack.bounds])
    n, e = int(lengths.max()), len(stack.bounds)
    du = np.zeros((len(factors), e, n))
    yy = np.full((y.shape[0], e, n), np.nan)
    ex = np.zeros((len(extras), e, n))
    u0 = np.zeros((e, len(factors)))
    for r, (a, b) in enumerate(stack.bounds):
        for j, f in enumerate(factors):
            du[j, r, : b - a] = stack.du[f][a:b]
            u0[r, j] = stack.raw[f][a] - stack.du[f][a]
        yy[:, r, : b - a] = y[:, a:b]
        for c, col in enumerate(extras):
            ex[c, r, : b - a] = col[a:b]
    return ExperimentSet(names=stack.names, factors=tuple(factors), axes=stack.axes, dt_s=stack.dt_s, du=du, y=yy,
                         lengths=lengths, u0=u0, extra=ex if len(extras) else None,
                         extra_names=tuple(f"extra{c}" for c in range(len(extras))))


@dataclass(kw_only=True)
class Reidentified:
    """The model identified again on every recording of the stack, with the accepted hypotheses' terms."""

    model: ThermalModel
    prediction: np.ndarray  # (axes, windows of the stack): from rest at each recording's start, no offsets
    #: per axis, what it holds fixed (the paths of derived inputs the identified model already had)
    fixed: dict[str, np.ndarray]
    selections: dict[str, AxisSelection]
    terms: dict[str, list[Term]]
    #: per axis, what the joint identifier fitted beside the paths (the accepted terms, then nuisance) and how
    #: many of those are the accepted terms: the held-out scoring identifies the paths again without each fold
    extras: dict[str, list[np.ndarray]] = field(default_factory=dict)
    n_phys: dict[str, int] = field(default_factory=dict)
    bounds: Bounds | None = None
    #: per axis, what was fitted beside the paths (each term's hypothesis key and setting, the nuisance
    #: columns' count): a later re-identification with the same is refined from this one (``starts``)
    beside: dict[str, tuple] = field(default_factory=dict)
    wall_s: float = 0.0


def reidentify(stack: Stack, model: ThermalModel, accepted: Sequence[Trial], *,
               artefacts: Mapping[str, Sequence[np.ndarray]] | None = None,
               progress: Callable[[str], None] | None = None, starts: Sequence[Reidentified | None] = ()
               ) -> Reidentified:
    """Identify ``model``'s paths again on every recording, jointly with the accepted hypotheses' terms.

    Every path of the factors is refitted by the joint identifier (its structure chosen again, weak paths
    pruned again), started from the bank and from ``model``'s own time constants, its time constants held
    within the identification runs' length (what is slower is a hypothesis's to claim: a slow mode). The
    accepted hypotheses enter at the settings the search chose, their gains fitted jointly; a hypothesis's
    "gain correction" of an identified path is dropped (the path is refitted anyway); its nuisance columns
    (an initial state, a drift) and the measurement artefacts are fitted beside and left out of the model.
    Paths of derived inputs ``model`` already has stay as they are.

    ``starts``: re-identifications on nearly the same stack (diagnosis's pass before: the same recordings,
    other work before the warm ones); an axis with the same terms and artefacts beside its paths as in one of
    them is refined from the fits made there, every structure tried there from where it ended, then chosen and
    pruned again (:func:`refine_axis`), not searched again.
    """
    t0 = time.perf_counter()
    factors = model.factors
    derived = [j for j, name in enumerate(model.input_names) if name not in factors]
    frozen = stack.contributions[:, derived, :].sum(axis=1) if derived else np.zeros_like(stack.base)
    bounds = Bounds.for_data(stack.dt_s, identification_length_s(model))
    active = [bool(np.any(stack.du[f])) for f in factors]
    seeds = {a: [[t for term in model.path(a, f).terms for t in term.time_constants_s] or [3600.0] for f in factors]
             for a in model.axes}
    selections: dict[str, AxisSelection] = {}
    extras: dict[str, list[np.ndarray]] = {}
    n_phys: dict[str, int] = {}
    fixed: dict[str, np.ndarray] = {}
    terms: dict[str, list[Term]] = {}
    beside: dict[str, tuple] = {}
    free = history_free(stack)
    prediction = np.zeros_like(stack.base)
    paths: list[PathTF] = []
    for i, a in enumerate(model.axes):
        if not np.isfinite(stack.y[i]).any():
            paths += [model.path(a, f) for f in factors]
            prediction[i] = stack.base[i]
            continue
        kept: list[tuple[Trial, Setting]] = []
        phys: list[np.ndarray] = []
        nuisance: list[np.ndarray] = []
        for t in accepted:
            e = t.evidence.get(a)
            if e is None or not e.included or e.setting is None:
                continue
            p_cols, n_cols = setting_columns(stack, e.setting)
            if t.hypothesis.artefact:
                nuisance += p_cols + n_cols
                continue
            comps = tuple(c for c in e.setting.components if not c.corrects)
            setting = replace(e.setting, components=comps, signs=(), limits=())
            kept.append((t, setting))
            phys += [stack.column(c, setting.chain) for c in comps]
            nuisance += n_cols
        nuisance += list((artefacts or {}).get(a, []))
        nuisance += free
        target = stack.y - frozen
        extras[a], n_phys[a] = [*phys, *nuisance], len(phys)
        beside[a] = (tuple((t.hypothesis.key, s) for t, s in kept), len(nuisance))
        es = stack_experiments(stack, factors, target, extras[a])
        if progress:
            progress(f"re-identifying axis {a}")
        # the extra columns (terms and nuisance, 28-32 of 40-50 on the bench's room cases) factorised once, not
        # in every evaluation: the room-recorded family's diagnosis 41-60 s -> 35-46 s of CPU
        same = next((r.selections[a] for r in starts if r is not None and a in r.selections
                     and r.beside.get(a) == beside[a]), None)
        if same is not None:
            sel = refine_axis(es, i, same, input_bounds=[bounds] * len(factors), project_extra=True)
        else:
            sel = select_axis(es, i, active=active, seeds=[seeds[a]], input_bounds=[bounds] * len(factors),
                              project_extra=True)
        selections[a] = sel
        fit = sel.chosen
        # the time constants are the identifier's; the gains of what is written are fitted again without the
        # nuisance (a recording's own drift or initial state), the way the scoring and `cncgw estimate` see
        # the model: each recording from rest, a free zero per recording (and a fitted history's error)
        fitted = fit.paths(factors)
        cols = unit_columns(stack, fitted) + phys
        g = final_gains(stack.y[i] - frozen[i], cols,
                        stack.per_recording() + list((artefacts or {}).get(a, [])) + free)
        axis_paths, terms[a] = gains_into(stack, a, fitted, kept, g)
        paths += axis_paths
        prediction[i] = frozen[i] + sum((x * c for x, c in zip(g, cols, strict=True)), np.zeros(stack.n))
        fixed[a] = frozen[i]
    # the re-identified paths' gain errors go together as their fit says (an axis without one: independent)
    correlation = dict(model.gain_correlation)
    for a, sel in selections.items():
        corr = sel.chosen.gain_correlation(factors)
        if corr is None:
            correlation.pop(a, None)
        else:
            correlation[a] = corr
    base = model.with_paths(paths, gain_correlation=correlation, info={**model.info, "reidentified": {
        "recordings": list(stack.names), "structure": {a: s.chosen.structures[0] for a, s in selections.items()},
        "pruned": {a: list(s.pruned) for a, s in selections.items()}}})
    extended = extend_model(base, terms)
    return Reidentified(model=extended, prediction=prediction, fixed=fixed, selections=selections,
                        terms=terms, extras=extras, n_phys=n_phys, bounds=bounds, beside=beside,
                        wall_s=time.perf_counter() - t0)


#: at most this many folds are identified again for the held-out scoring (more held-out ids are grouped)
MAX_NESTED_FOLDS = 6


def nested_groups(folds: np.ndarray) -> list[np.ndarray]:
    """The held-out ids of ``folds`` (>= 0) in at most :data:`MAX_NESTED_FOLDS` contiguous groups."""
    ids = np.unique(folds[folds >= 0])
    return [g for g in np.array_split(ids, min(len(ids), MAX_NESTED_FOLDS)) if g.size]


def held_out_reidentified(stack: Stack, model: ThermalModel, reid: Reidentified, folds: np.ndarray,
                          block: np.ndarray, *, artefacts: Mapping[str, Sequence[np.ndarray]] | None = None
                          ) -> dict[str, np.ndarray]:
    """Per axis, the re-identified model's predictions of each held-out fold, identified without that fold.

    The re-identified model's time constants were chosen on every recording, the held-out ones too: refitting
    only its gains per fold would score a fit, not a prediction (measured: a model that scored 80 % better
    this way predicted a fresh day 70 % worse). So per fold (a group of the ids in ``folds``) the chosen
    structures are fitted again by the joint identifier, started from the chosen time constants, on the
    measurements outside it, their gains fitted as :func:`reidentify` does, and the fold predicted from its
    recording's zero (its first block, ``block == BURN_IN``, as the other candidates are). Returns the
    prediction of the measurement (the fixed part included), NaN outside the held-out folds.
    """
    factors = model.factors
    offsets = stack.per_recording()
    free = history_free(stack)
    out: dict[str, np.ndarray] = {}
    for i, a in enumerate(stack.axes):
        sel = reid.selections.get(a)
        if sel is None:
            continue
        extras = reid.extras.get(a, [])
        phys = extras[: reid.n_phys.get(a, 0)]
        target = stack.y - reid.fixed[a]
        pred = np.full(stack.n, np.nan)
        for group in nested_groups(folds):
            held = np.isin(folds, group)
            masked = target.copy()
            masked[:, held] = np.nan
            es = stack_experiments(stack, factors, masked, extras)
            try:
                # refined from the chosen time constants, not searched from several starts: the extra columns
                # (terms and nuisance) are factorised once per fold, not once per evaluation
                problem = AxisProblem(es, i, input_bounds=[reid.bounds] * len(factors), project_extra=True)
                fit = problem.fit(sel.chosen.structures, sel.chosen.thetas)
            except (ValueError, IdentificationError):
                continue  # nothing left to fit on: the fold stays unscored for this candidate
            cols = unit_columns(stack, fit.paths(factors)) + list(phys)
            g = final_gains(masked[i], cols, offsets + list((artefacts or {}).get(a, [])) + free)
            shape = sum((x * c for x, c in zip(g, cols, strict=True)), np.zeros(stack.n))
            for c in offsets:
                member = (c != 0) & held
                if not member.any():
                    continue
                first = (c != 0) & (block == BURN_IN) & np.isfinite(target[i])
                zero = float(np.mean(target[i][first] - shape[first])) if first.any() else 0.0
                pred[member] = shape[member] + zero
        out[a] = pred + reid.fixed[a]
    return out


def gains_into(stack: Stack, axis: str, paths: Sequence[PathTF], kept: Sequence[tuple[Trial, Setting]],
               g: np.ndarray) -> tuple[list[PathTF], list[Term]]:
    """The gains ``final_gains`` fitted, put back: the paths' terms first (in order), then each kept setting's."""
    out, k = [], 0
    for p in paths:
        n = len(p.terms)
        out.append(replace(p, terms=tuple(t.with_gain(float(x)) for t, x in zip(p.terms, g[k: k + n], strict=True))))
        k += n
    terms = []
    for t, setting in kept:
        gs = g[k: k + len(setting.components)]
        k += len(setting.components)
        contrib = sum((gi * stack.column(c, setting.chain) for gi, c in zip(gs, setting.components, strict=True)),
                      np.zeros(stack.n))
        terms.append(Term(trial=t, axis=axis, setting=setting, gains=np.asarray(gs), contribution=contrib))
    return out, terms


def unit_columns(stack: Stack, paths: Sequence[PathTF]) -> list[np.ndarray]:
    """Every term of ``paths`` at unit gain, each recording from rest: the regressors of their gains."""
    return [stack.response(stack.du[p.factor], (term.with_gain(1.0),), p.delay_s) for p in paths for term in p.terms]


def final_gains(target: np.ndarray, columns: Sequence[np.ndarray], free: Sequence[np.ndarray]) -> np.ndarray:
    """Least-squares gains of ``columns`` for ``target`` over its measured windows, ``free`` columns beside."""
    ok = np.isfinite(target)
    used = [c for c in free if np.any(c[ok])]
    X = np.column_stack([*(c[ok] for c in columns), *(c[ok] for c in used)])
    scale = np.linalg.norm(X, axis=0)
    scale[scale == 0] = 1.0
    Xs = X / scale
    beta = np.linalg.lstsq(Xs, target[ok], rcond=None)[0] / scale
    return beta[: len(columns)]
