"""``identify``: recordings of experiments in, a :class:`~gateway.model.ThermalModel` and a report out."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime

import numpy as np
from threadpoolctl import threadpool_limits

from gateway import __version__
from gateway.errors import IdentificationError
from gateway.identify.common import ExperimentSet
from gateway.identify.joint import CANDIDATES, AxisProblem, AxisSelection, select_axis
from gateway.identify.paper import active_factors, describe_groups, identify_paper
from gateway.identify.shrink import AxisShrinkage, shrink_axis
from gateway.model.correlation import GainCorrelation
from gateway.model.coverage import coverage_of
from gateway.model.envelope import envelope_of
from gateway.model.model import ThermalModel, model_problems
from gateway.prepare import MIN_PROBE_POINTS, Prepared, prepare
from gateway.recording import Recording

METHODS = ("joint", "paper")
#: how a production run's initial thermal state is taken: at rest (a day after a night at rest), or fitted
PRODUCTION_INITIAL = ("rest", "fit")
#: a production run fitted from a warm start: free decays with these time constants (s), per run
INITIAL_DECAYS_S = (1800.0, 3 * 3600.0, 12 * 3600.0)
#: a pruned path comes back only when leaving experiments out predicts at least this share better with it
UNPRUNE_GAIN = 0.05


@dataclass(kw_only=True)
class IdentifyResult:
    """The model plus what a person needs to judge it."""

    model: ThermalModel
    method: str
    experiments: tuple[str, ...]
    wall_s: float
    report: list[str] = field(default_factory=list)
    selections: list[AxisSelection] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    #: per axis (joint method): the gain prior chosen by leaving experiments out, and each path's determination
    shrinkage: list[AxisShrinkage] = field(default_factory=list)


def identify(
    recordings: Sequence[Recording],
    *,
    factors: Sequence[str],
    axes: Sequence[str],
    units: Mapping[str, str] | None = None,
    machine: str = "",
    method: str = "joint",
    candidates: Sequence[str] = CANDIDATES,
    prune: bool = True,
    gap_policy: str = "hold",
    paper_max_iter: int = 3000,
    progress: Callable[[str], None] | None = None,
    jobs: int = 1,
    shrink: bool = True,
    production: Sequence[Recording] = (),
    production_initial: str = "rest",
) -> IdentifyResult:
    """Identify a model from experiment recordings.

    Each recording is one experiment that starts with the machine in thermal equilibrium (after a long
    idle, powered): its first window defines the experiment's initial state. The model's ``reference``
    is the mean of those initial factor levels, for live use.

    ``jobs`` > 1 (joint method): the axes are fitted in that many processes at once (forked, where the
    platform forks); the model is the same as with one. Leave it at 1 on a PC whose gateway is sampling.

    ``shrink`` (joint method): gains the experiments do not determine are pulled toward zero by a prior whose
    strength is chosen by leave-one-experiment-out prediction (:mod:`gateway.identify.shrink`); paths pruned
    by the information criterion stay zero only if leaving experiments out predicts them no worse.

    ``production`` (joint method): production runs with measured displacement, fitted with the experiments,
    each with its own offset. Their factors are deviations from the experiments' rest levels (the model's
    reference), not from their own first window (a run may start mid-work); ``production_initial="fit"``
    adds per run free decays (:data:`INITIAL_DECAYS_S`) for a run that starts warm, ``"rest"`` takes it to
    start in equilibrium like an experiment. Coverage, envelope, the gain prior and the report cover them.
    """
    if production and method != "joint":
        raise IdentificationError("production runs join the joint method only: the paper's method separates "
                                  "experiments that each change one group of factors")
    if production_initial not in PRODUCTION_INITIAL:
        raise ValueError(f"production_initial must be one of {PRODUCTION_INITIAL}. Got {production_initial!r}")
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}. Got {method!r}")
    # the matrices here are small (thousands x tens): BLAS threads only contend for the cores, and on a
    # busy 2-core edge PC that made identification 4-5x slower
    with threadpool_limits(limits=1, user_api="blas"):
        return _identify(recordings, factors=factors, axes=axes, units=units, machine=machine, method=method,
                         candidates=candidates, prune=prune, gap_policy=gap_policy, paper_max_iter=paper_max_iter,
                         progress=progress, jobs=jobs, shrink=shrink, production=production,
                         production_initial=production_initial)


def _identify(
    recordings: Sequence[Recording],
    *,
    factors: Sequence[str],
    axes: Sequence[str],
    units: Mapping[str, str] | None,
    machine: str,
    method: str,
    candidates: Sequence[str],
    prune: bool,
    gap_policy: str,
    paper_max_iter: int,
    progress: Callable[[str], None] | None,
    jobs: int,
    shrink: bool,
    production: Sequence[Recording],
    production_initial: str,
) -> IdentifyResult:
    t0 = time.perf_counter()
    notes: list[str] = []
    preps = []
    for rec in recordings:
        p = prepare(rec, factors=factors, axes=axes, initial="first", gap_policy=gap_policy)
        preps.append(p)
    # the rest levels are the experiments' (each starts in equilibrium); production runs are referred to them
    reference = {f: float(np.mean([p.u0[j] for p in preps])) for j, f in enumerate(factors)}
    prod_preps = [_probed(prepare(rec, factors=factors, axes=axes, initial="reference", reference=reference,
                                  gap_policy=gap_policy, probe_points=True), rec, axes, notes)
                  for rec in production]
    names = [p.name for p in preps]
    for p in prod_preps:
        if p.name in names:  # two recordings of one name would be one experiment in the report
            p = replace(p, name=f"{p.name} (production)")
        names.append(p.name)
        preps.append(p)
    for p in preps:
        notes += [f"{p.name}: {n}" for n in p.notes]
        for i, a in enumerate(axes):
            if not np.isfinite(p.y[i]).any():
                notes.append(f"{p.name}: no measured displacement on axis {a}; it does not inform axis {a}")
    preps = [replace(p, name=n) for p, n in zip(preps, names, strict=True)]
    es = ExperimentSet.from_prepared(preps, factors=factors, axes=axes)
    weight, sd_ref = _probe_weights(preps, production)
    if weight is not None:
        es = replace(es, weight=weight)
    if prod_preps and production_initial == "fit":
        es = _with_initial_decays(es, range(len(recordings), len(preps)))
    act = active_factors(es)
    active = act.any(axis=0)
    for j, f in enumerate(factors):
        if not active[j]:
            notes.append(f"factor {f} does not change in any experiment: its paths are set to zero "
                         "(not identifiable from these experiments)")
    for i, a in enumerate(axes):
        if not np.isfinite(es.y[i]).any():
            raise IdentificationError(f"no experiment has measured displacement on axis {a}; "
                                      "identification needs it on every axis it estimates")

    report: list[str] = []
    selections: list[AxisSelection] = []
    shrinkage: list[AxisShrinkage] = []
    paths = []
    correlation: dict[str, GainCorrelation] = {}
    info: dict[str, object] = {
        "method": method, "experiments": list(es.names[: len(recordings)]),
        "experiment_fingerprints": [r.fingerprint(factors) for r in recordings],
        "window_s": es.dt_s, "longest_experiment_s": es.longest_s,
        "identified_utc": datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ"), "cncgw_version": __version__,
    }
    if production:
        info["production_runs"] = list(es.names[len(recordings):])
        info["production_fingerprints"] = [r.fingerprint(factors) for r in production]
        info["production_initial"] = production_initial
        # how many measured points each run gave per axis: a run sampled by probes gives a few
        info["production_points"] = {p.name: {a: int(np.isfinite(p.y[i]).sum()) for i, a in enumerate(axes)}
                                     for p in preps[len(recordings):]}
        report += _production_report(preps[len(recordings):], axes, sd_ref)
    if method == "joint":
        fit_axes = _select_axes_in_processes if jobs > 1 and len(axes) > 1 and _can_fork() else _select_axes
        for i, sel in enumerate(fit_axes(es, list(active), candidates, prune, progress, jobs)):
            shr = None
            if shrink:
                if progress:
                    progress(f"axis {axes[i]}: gain prior by leaving experiments out")
                sel, shr = _shrink_selection(es, i, sel)
                shrinkage.append(shr)
            selections.append(sel)
            axis_fit = shr.fit if shr is not None else sel.chosen
            paths += axis_fit.paths(factors)
            # how the gains' errors go together (co-varying factors): the live band's prior (gateway.adaptive)
            corr = axis_fit.gain_correlation(factors)
            if corr is not None:
                correlation[axes[i]] = corr
            report += _axis_report(sel)
            info[f"axis_{axes[i]}"] = {
                "structure": _structure_name(sel.chosen.structures), "rms_um": sel.chosen.rms,
                "residual_lag1_autocorrelation": sel.rho, "effective_samples": sel.n_eff,
                "bic": {k: f.bic for k, f in sel.tried.items()}, "pruned": list(sel.pruned),
            }
            if shr is not None:
                report += _shrink_report(shr, units or {})
                info[f"axis_{axes[i]}"] |= _shrink_info(shr)
    else:
        fit = identify_paper(es, progress=progress, max_iter=paper_max_iter)
        paths = fit.paths
        report += describe_groups(es, fit.groups)
        report.append(f"steepest descent: {fit.evaluations} evaluations of E in {fit.wall_s:.2f} s")
    # the deviations the experiments covered: beyond them the model extrapolates (estimate warns)
    info["deviation_range"] = {f: [float(es.du[j].min()), float(es.du[j].max())] for j, f in enumerate(factors)}
    model = ThermalModel(axes=tuple(axes), factors=tuple(factors), units=dict(units or {}), reference=reference,
                         paths={(p.axis, p.factor): p for p in paths}, machine=machine, info=info,
                         gain_correlation=correlation)
    # what these experiments support: the live gateway holds the offsets beyond it (gateway.live.plausibility)
    what = f"{len(recordings)} experiments" + (f" and {len(production)} production runs" if production else "")
    sampled = [p for p in preps[len(recordings):] if p.sparse]
    if sampled:
        what += (f" ({sum(int(np.isfinite(p.y).any(axis=0).sum()) for p in sampled)} probe instants in "
                 f"{len(sampled)} of them)")
    envelope = envelope_of(model, ((p.du, p.y) for p in preps), window_s=es.dt_s,
                           source=f"identification: {what}")
    # where in factor space the model was fitted: estimate, run and diagnose say when a recording leaves it
    coverage = coverage_of((p.du for p in preps), factors, source=f"identification: {what}")
    model = replace(model, envelope=envelope, coverage=coverage)
    problems = model_problems(model)
    if problems:  # e.g. a factor that barely moves in the experiments: a gain of millions of um per unit
        raise IdentificationError(
            "the identified model is outside the ranges a model file may hold: the experiments do not determine "
            "it (factors that always change together, one that barely moves, or units far from the usual):\n"
            + "\n".join(problems))
    return IdentifyResult(model=model, method=method, experiments=es.names, wall_s=time.perf_counter() - t0,
                          report=report, selections=selections, notes=notes, shrinkage=shrinkage)


def _probed(p: Prepared, rec: Recording, axes: Sequence[str], notes: list[str]) -> Prepared:
    """A production run's measured points checked: some on an axis, enough where it is sampled by probes.

    A run measured only at probe cycles informs an axis with :data:`MIN_PROBE_POINTS` points or more (its own
    offset takes one); an axis with fewer is left out of it with a note, a run with fewer on every axis is an
    error naming the file and the counts.
    """
    counts = np.isfinite(p.y).sum(axis=1)
    if not counts.any():
        raise IdentificationError(
            f"{rec.source}: no measured displacement: a production run joins identification with displacement "
            f"columns ({', '.join(f'{a}_um' for a in axes)} as the profile names them) or probe columns "
            f"({', '.join(f'probe_{a}_um' for a in axes)}, probe_sd_um: cncgw record --export-only writes them "
            "from a gateway with [probes])")
    if not p.sparse:
        return p
    what = "probe columns" if p.y_source == "probes" else "sparse displacement columns"
    per_axis = ", ".join(f"{a} {int(c)}" for a, c in zip(axes, counts, strict=True))
    if counts.max() < MIN_PROBE_POINTS:
        raise IdentificationError(
            f"{rec.source}: {int(np.isfinite(p.y).any(axis=0).sum())} probe instant(s) in its {what} ({per_axis}): "
            f"a production run sampled by probes needs at least {MIN_PROBE_POINTS} on an axis (its own offset "
            "takes one, the others inform the paths); join a longer run or probe more often")
    y = p.y.copy()
    for i, a in enumerate(axes):
        if 0 < counts[i] < MIN_PROBE_POINTS:
            y[i] = np.nan
            notes.append(f"{p.name}: only {int(counts[i])} probe point(s) on axis {a} (at least {MIN_PROBE_POINTS} "
                         f"needed: its own offset takes one); it does not inform axis {a}")
    return replace(p, y=y)


def _probe_weights(preps: Sequence[Prepared], production: Sequence[Recording]
                   ) -> tuple[np.ndarray | None, float]:
    """Least-squares weights (A, E, N) from the probes' stated uncertainty, and the reference sd (um).

    A point with a stated uncertainty sd weighs (sd_ref / sd)^2, sd_ref the median stated over all points: a
    probe of typical uncertainty weighs as one window of sensor data, a better one more, a poorer one less.
    (Measured on the simulated machine, a production day probed every 1, 2 or 4 h: weighing every probe 10x
    or as the windows between probes gave no better prediction of another day, see README.)
    """
    from gateway.adaptive.probes import SD_MAX_UM

    sds = [p.y_sd[np.isfinite(p.y) & np.isfinite(p.y_sd)] for p in preps if p.y_sd is not None]
    stated = np.concatenate(sds) if sds else np.zeros(0)
    if not stated.size:
        return None, math.nan
    sources = {p.name: r.source for p, r in zip(preps[len(preps) - len(production):], production, strict=True)}
    for p in preps:
        if p.y_sd is None:
            continue
        bad = np.isfinite(p.y) & np.isfinite(p.y_sd) & ~((p.y_sd > 0) & (p.y_sd <= SD_MAX_UM))
        if bad.any():
            k = int(np.flatnonzero(bad.any(axis=0))[0])
            raise IdentificationError(
                f"{sources.get(p.name, p.name)}: column probe_sd_um at t={p.time_s[k]:g} s: "
                f"{float(p.y_sd[bad][0])!r} um: expected a probe's standard uncertainty in (0, {SD_MAX_UM:g}] um")
    sd_ref = float(np.median(stated))
    n = max(p.n for p in preps)
    weight = np.ones((preps[0].y.shape[0], len(preps), n))
    for e, p in enumerate(preps):
        if p.y_sd is not None:
            stated = np.isfinite(p.y_sd)
            weight[:, e, : p.n] = np.where(stated, (sd_ref / np.where(stated, p.y_sd, 1.0)) ** 2, 1.0)
    return weight, sd_ref


def _production_report(prods: Sequence[Prepared], axes: Sequence[str], sd_ref: float) -> list[str]:
    """Per production run: how many measured points it gave (probe points where it is sampled)."""
    lines = []
    for p in prods:
        counts = ", ".join(f"{a} {int(np.isfinite(p.y[i]).sum())}" for i, a in enumerate(axes))
        if p.sparse:
            what = "probe columns" if p.y_source == "probes" else "sparse displacement columns"
            sd = p.y_sd[np.isfinite(p.y) & np.isfinite(p.y_sd)] if p.y_sd is not None else np.zeros(0)
            weighed = (f", weighted by their stated uncertainty ({float(sd.min()):.3g}-{float(sd.max()):.3g} um; "
                       f"{sd_ref:.3g} um weighs as one window of sensor data)" if sd.size else
                       ", no uncertainty stated: each weighs as one window of sensor data")
            lines.append(f"production run {p.name}: {int(np.isfinite(p.y).any(axis=0).sum())} probe instants from its "
                         f"{what} ({counts} points){weighed}")
        else:
            lines.append(f"production run {p.name}: measured displacement on {counts} windows")
    return lines


def _with_initial_decays(es: ExperimentSet, runs: Sequence[int]) -> ExperimentSet:
    """``es`` with free decays (:data:`INITIAL_DECAYS_S`) on each of ``runs``: a warm start's unknown state."""
    cols, names = [], []
    t = es.dt_s * np.arange(es.du.shape[2])
    for e in runs:
        for tau in INITIAL_DECAYS_S:
            c = np.zeros(es.du.shape[1:])
            c[e, : es.lengths[e]] = np.exp(-t[: es.lengths[e]] / tau)
            cols.append(c)
            names.append(f"{es.names[e]}: initial decay {tau / 3600:g} h")
    extra = np.stack(cols) if es.extra is None else np.concatenate([es.extra, np.stack(cols)])
    return replace(es, extra=extra, extra_names=(*es.extra_names, *names))


def _shrink_selection(es: ExperimentSet, i: int, sel: AxisSelection) -> tuple[AxisSelection, AxisShrinkage]:
    """The prior on the chosen fit; a pruning undone when leaving experiments out predicts better without it."""
    problem = AxisProblem(es, i)
    shr = shrink_axis(problem, sel.chosen, n_eff=sel.n_eff)
    if sel.pruned:
        name = _structure_name(sel.chosen.structures)
        whole = sel.tried.get(name)
        if whole is not None:
            other = shrink_axis(problem, whole, n_eff=sel.n_eff)
            # held-out errors of two good models differ by noise: un-pruning needs a clear gain
            if other.loeo_sse[other.kappa] < (1.0 - UNPRUNE_GAIN) * shr.loeo_sse[shr.kappa]:
                if not whole.sd:
                    problem.attach_uncertainties(whole, whole.n / sel.n_eff)
                other.fit.sd, other.fit.gain_cov = whole.sd, whole.gain_cov
                sel = replace(sel, chosen=whole, pruned=(), unpruned=sel.pruned)
                shr = other
    return sel, shr


def _shrink_report(shr: AxisShrinkage, units: Mapping[str, str]) -> list[str]:
    kappa = "none" if not math.isfinite(shr.kappa) else f"kappa {shr.kappa:g}"
    if not shr.left_out:
        lines = ["    gain prior: none (it is chosen by leaving each experiment out and predicting it from the others; "
                 "with one experiment there are no others: nothing here was predicted from data it did not fit)"]
    else:
        lines = [f"    gain prior (|gain| ~ kappa x {shr.d_um:.3g} um / the factor's covered maximum): {kappa}, chosen "
                 f"by leaving each experiment out: held-out RMS {shr.loeo_rms:.3g} um (without the prior "
                 f"{shr.loeo_rms_without_prior:.3g} um)"]
    worst = sorted(shr.held_out_rms.items(), key=lambda kv: -kv[1])[:3]
    if worst:
        lines.append("    predicted from the others, worst: " + ", ".join(f"{n} {v:.3g} um" for n, v in worst))
    for p in shr.poorly_determined:
        lines.append(f"    poorly determined: {p.line(units.get(p.factor, ''))}")
    return lines


def _shrink_info(shr: AxisShrinkage) -> dict[str, object]:
    held = ({"held_out_rms_um": shr.loeo_rms, "held_out_rms_um_without_prior": shr.loeo_rms_without_prior}
            if shr.left_out else {"held_out": "one experiment: nothing left out"})
    return {"gain_prior_kappa": shr.kappa if math.isfinite(shr.kappa) else "none", **held,
            "poorly_determined": [f"{p.factor}: {p.why}" for p in shr.poorly_determined]}


def _select_axes(es: ExperimentSet, active: list[bool], candidates: Sequence[str], prune: bool,
                 progress: Callable[[str], None] | None, jobs: int) -> list[AxisSelection]:
    return [select_axis(es, i, active=active, candidates=candidates, prune=prune, progress=progress)
            for i in range(len(es.axes))]


def _select_axes_in_processes(es: ExperimentSet, active: list[bool], candidates: Sequence[str], prune: bool,
                              progress: Callable[[str], None] | None, jobs: int) -> list[AxisSelection]:
    """:func:`_select_axes` with the axes spread over ``jobs`` forked processes (progress per axis done)."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, as_completed

    out: list[AxisSelection | None] = [None] * len(es.axes)
    with ProcessPoolExecutor(max_workers=min(jobs, len(es.axes)),
                             mp_context=multiprocessing.get_context("fork")) as pool:
        futures = {pool.submit(_select_one_axis, es, i, active, candidates, prune): i for i in range(len(es.axes))}
        for future in as_completed(futures):
            i = futures[future]
            out[i] = future.result()
            if progress:
                for cand in candidates:
                    progress(f"axis {es.axes[i]}: {cand}")
    return [sel for sel in out if sel is not None]


def _select_one_axis(es: ExperimentSet, i: int, active: list[bool], candidates: Sequence[str],
                     prune: bool) -> AxisSelection:
    with threadpool_limits(limits=1, user_api="blas"):
        return select_axis(es, i, active=active, candidates=candidates, prune=prune)


def _can_fork() -> bool:
    import multiprocessing

    return "fork" in multiprocessing.get_all_start_methods()


def _structure_name(structures: Sequence[str]) -> str:
    used = sorted({s for s in structures if s != "zero"})
    return "+".join(used) if used else "zero"


def _axis_report(sel: AxisSelection) -> list[str]:
    fit = sel.chosen
    lines = [f"axis {sel.axis}: chose {_structure_name(fit.structures)} paths, fit RMS {fit.rms:.3f} um "
             f"over {fit.n} windows (residual lag-1 autocorrelation {sel.rho:.2f}, "
             f"effective samples {sel.n_eff:.0f}); {sel.wall_s:.1f} s"]
    best = min(f.bic for f in sel.tried.values())
    for name, f in sel.tried.items():
        mark = "*" if f is fit or (sel.pruned and name == _structure_name(fit.structures)) else " "
        lines.append(f"  {mark} {name:<13} RMS {f.rms:7.3f} um  parameters {f.k:3d}  "
                     f"BIC {f.bic - best:+9.1f}")
    if sel.pruned:
        lines.append(f"    zero paths after pruning (gain within 2 sd of 0): {', '.join(sel.pruned)}")
    if sel.unpruned:
        lines.append(f"    kept after all: {', '.join(sel.unpruned)} (the information criterion would zero them; "
                     "leaving each experiment out predicts better with them)")
    return lines


def identification_summary(model: ThermalModel) -> list[str]:
    """A table of every path: structure, static gain (um per unit) and K, time constants, sd."""
    lines = [f"{'axis':<4} {'factor':<16} {'kind':<13} {'gain um/unit':>13} {'sd':>9} {'K':>11}  time constants"]
    for a in model.axes:
        for f in model.input_names:  # derived inputs (added by diagnosis) after the factors
            p = model.path(a, f)
            if p.kind == "zero":
                lines.append(f"{a:<4} {f:<16} {'zero':<13} {0.0:>13.4g} {'':>9} {'inf':>11}")
                continue
            taus = ", ".join(f"{t / 60:.3g}" for term in p.terms for t in term.time_constants_s)
            sd = p.sd.get("gain", math.nan)
            lines.append(f"{a:<4} {f:<16} {p.kind:<13} {p.gain:>13.4g} {sd:>9.2g} {p.K:>11.4g}  {taus} min")
    return lines
