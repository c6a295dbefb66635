"""``diagnose``: a model and recordings in; where they differ, what physics is missing, a bigger model out.

1. Residuals per axis (measured - simulated), aligned at each recording's start.
2. Locate: noise band, windows outside it, steps (measurement artefacts), change points, operating
   states, spectral lines, correlations (:mod:`gateway.diagnose.locate`).
3. Hypotheses of missing physics (:mod:`gateway.diagnose.hypotheses`).
4. Selection on held-out blocks of time with false-positive control (:mod:`gateway.diagnose.search`).
5. The extended model (:mod:`gateway.diagnose.extend`) and the figures a report needs.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from threadpoolctl import threadpool_limits

from gateway import __version__
from gateway.diagnose.adequacy import MAX_ERROR_SHARE, Adequacy, assess
from gateway.diagnose.compare import WITH_TERMS, Comparison, compare
from gateway.diagnose.confusable import Confusion, confusions
from gateway.diagnose.data import Stack, build_stack, identified_on, recording_labels
from gateway.diagnose.explain import Explanation, explain, held_corrections
from gateway.diagnose.extend import extend_model
from gateway.diagnose.hypotheses import DAY_SHOWN, FactorInfo, Hypothesis, catalogue, partial_columns, shows_the_day
from gateway.diagnose.locate import (
    ChangePoint,
    Correlation,
    Line,
    Noise,
    State,
    Step,
    Window,
    aligned_residual,
    candidate_signals,
    change_points,
    correlations,
    find_steps,
    located_windows,
    noise_level,
    operating_states,
    spectral_lines,
)
from gateway.diagnose.refit import Reidentified, path_corrections, reidentify
from gateway.diagnose.search import AxisEvidence, Options, SearchResult, Trial, search, sized
from gateway.diagnose.select import BURN_IN, blocks_to_decide, make_blocks
from gateway.errors import RecordingError
from gateway.model.coverage import check_coverage, column_ranges, coverage_of
from gateway.model.envelope import envelope_of
from gateway.model.inputs import recorded_columns
from gateway.model.model import ThermalModel
from gateway.prepare import prepare
from gateway.profile import Profile
from gateway.recording import Recording, continued, gap_between, runs_on_from, split_part
from gateway.replay import (
    INITIAL_STATES,
    AxisFigures,
    Estimate,
    estimate,
    starts_warm,
    working_history,
    works_at_start,
)


@dataclass(kw_only=True)
class AxisFindings:
    """What the residual of one axis shows before any hypothesis is fitted."""

    axis: str
    residual: np.ndarray  # aligned measured - model, every window of the stack
    noise: Noise
    windows: list[Window]
    steps: list[Step]
    change_points: list[ChangePoint]
    states: list[State]
    lines: list[Line]
    correlations: list[Correlation]


@dataclass(kw_only=True)
class Diagnosis:
    """Everything diagnosis found: findings per axis, every hypothesis tried, the extended model."""

    model: ThermalModel
    extended: ThermalModel  # the model diagnosis writes: the best candidate that passes (else the model itself)
    stack: Stack
    findings: dict[str, AxisFindings]
    hypotheses: list[Hypothesis]
    result: SearchResult  # the search whose model was written ("refit" when re-identified, else "frozen")
    results: dict[str, SearchResult]  # "frozen": terms on the identified model; "refit": every path refitted beside
    options: Options
    adequacy: Adequacy
    comparison: Comparison
    reidentified: Reidentified | None
    block: np.ndarray
    #: when more data alone won: what the re-identified paths changed, and the physics that explains it
    explanation: Explanation | None = None
    #: mechanisms whose inputs one factor carries on these recordings: no fit can name them
    confusions: list[Confusion] = field(default_factory=list)
    conclusions: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    wall_s: float = 0.0

    def verdict(self) -> list[str]:
        """The verdict: the identified model's fitness (:meth:`Adequacy.lines`), then the written model's."""
        return [*self.adequacy.lines(), *([w] if (w := written_verdict(self)) else [])]

    @property
    def before(self) -> dict[str, AxisFigures]:
        """Held-out errors of the identified model as it is."""
        return self.comparison.candidates["identified"].metrics

    @property
    def after(self) -> dict[str, AxisFigures]:
        """Held-out errors of the written model (the identified one when nothing passed)."""
        return self.comparison.written.metrics

    @property
    def accepted_physics(self) -> list[str]:
        """Keys of the accepted hypotheses that are physics (not artefacts), in order of acceptance."""
        return [t.hypothesis.key for t in self.result.accepted if not t.hypothesis.artefact]

    @property
    def artefacts(self) -> list[str]:
        """Measurement artefacts found: steps and accepted artefact hypotheses."""
        out = [f"step {s.size_um:+.3g} um on {s.axis} at {s.time_h:.2f} h ({s.recording})"
               for f in self.findings.values() for s in f.steps]
        return out + [t.hypothesis.key for t in self.result.accepted if t.hypothesis.artefact]


#: passes of the diagnosis at most: the work before warm recordings chosen again by the re-identified model
HISTORY_PASSES = 3
#: days of recordings a daily cycle needs before it can be told from the schedule and a drift
DAYS_FOR_DAILY = 3.0
#: fewer held-out blocks than this and nothing can be judged (the signed-rank test needs 3 to say anything)
MIN_HELD_BLOCKS = 3


def factor_infos(profile: Profile) -> list[FactorInfo]:
    """What diagnosis needs to know about the profile's factors."""
    return [FactorInfo(name=f.name, unit=f.unit, stat=f.stat.value, description=f.description) for f in profile.factors]


def diagnose(model: ThermalModel, recordings: Sequence[Recording], *, factors: Sequence[FactorInfo] = (),
             options: Options | None = None, gap_policy: str = "hold", families: Sequence[str] | None = None,
             initial_state: str = "fit", progress: Callable[[str], None] | None = None) -> Diagnosis:
    """Compare ``model`` with ``recordings``, locate the differences, test hypotheses, extend the model.

    ``initial_state``: "fit" runs a recording that seems not to start at rest from the hours of work its first
    hours show (:func:`start_histories`); "rest" starts every recording in equilibrium with its first window.
    """
    t0 = time.perf_counter()
    options = options or Options()
    if initial_state not in INITIAL_STATES:
        raise ValueError(f"initial_state must be one of {INITIAL_STATES}. Got {initial_state!r}")
    # many small least-squares problems: BLAS threads only contend for the cores (see identify)
    with threadpool_limits(limits=1, user_api="blas"):
        warm = {r: why for r, rec in enumerate(recordings) if (why := starts_warm(model, rec, gap_policy=gap_policy))}
        histories = start_histories(model, recordings, warm, gap_policy=gap_policy) if initial_state == "fit" else {}
        infos = list(factors) or [FactorInfo(name=f, unit=model.units.get(f, "")) for f in model.factors]
        by_name = {f.name: f for f in infos}
        signals_of = ([f for f in model.factors if f in by_name and by_name[f].is_speed],
                      [f for f in model.factors if f in by_name and by_name[f].is_current_sq
                       and not by_name[f].is_rotor])
        kw = {"infos": infos, "signals_of": signals_of, "options": options, "families": families,
              "gap_policy": gap_policy, "progress": progress}
        first = best = now = _one_pass(model, recordings, histories, warm, **kw)
        # the work before a warm recording was chosen by the identified model, which lacks the very physics sought
        # here; the model identified again on all recordings (the terms taken beside its paths) meets the data
        # better: the work it chooses is run again while the choice changes, and the pass whose written model
        # predicts the held-out blocks best is kept (bench/diagnose.py --cut-days 10: see start_histories)
        for _ in range(HISTORY_PASSES - 1):
            if not now.histories or now.chooser is None:
                break
            again = start_histories(model, recordings, warm, gap_policy=gap_policy, choose_with=now.chooser.model)
            if _choices(again) == _choices(now.histories):
                break
            if progress:
                progress("the work before the recordings that start warm, chosen again by the re-identified model")
            now = _one_pass(model, recordings, again, warm, previous=now, **kw)
            if now.comparison.written.sse >= best.comparison.written.sse:
                break  # a choice that did not predict better is not a step to build the next one on
            best = now
        histories = best.histories
        stack, findings, results, comparison = best.stack, best.findings, best.results, best.comparison
        adequacy, block, hyps, confused = best.adequacy, best.block, best.hypotheses, best.confused
        reid, explanation, missing = best.reid, best.explanation, best.missing
    refit = results.get("refit")
    if refit is not None and WITH_TERMS in comparison.candidates:  # its terms are not the model written
        refit = SearchResult(trials=refit.trials, accepted=[t for t in refit.accepted if t.hypothesis.artefact],
                             sse_rounds=refit.sse_rounds, held_of=refit.held_of)
    result = {"reidentified": refit, "explained": explanation.result if explanation else None
              }.get(comparison.chosen) or results["frozen"]
    on = [(t, f"{t.hypothesis.key} on {', '.join(t.axes)}") for t in result.accepted]
    record = {"cncgw_version": __version__, "recordings": list(stack.labels), "written": comparison.chosen,
              "accepted": [text for t, text in on if not t.hypothesis.artefact] if comparison.chosen != "identified"
              else [],
              "explained": explanation.names if explanation is not None else [],
              "paths_changed": explanation.changes if explanation is not None else [],
              "indistinguishable": [f"{c.key} ~ {c.factor}" for c in confused],
              # named mechanisms the held-out blocks do not tell apart from the one named (see search.Trial.rivals)
              "not_told_apart": list(dict.fromkeys(f"{t.hypothesis.key} ~ {r.hypothesis.key}"
                                                   for t in _named(result, explanation) for r in t.rivals)),
              "artefacts_excluded": [text for t, text in on if t.hypothesis.artefact]
              + [f"step on {s.axis} at {s.time_h:.2f} h in {s.recording}" for f in findings.values() for s in f.steps]}
    extended = comparison.written.model
    if comparison.chosen == "identified":
        extended = model
    else:
        extended = _supported_region(extended, recordings, reidentified=comparison.chosen != "terms",
                                     gap_policy=gap_policy)
    extended = replace(extended, info={**extended.info, "diagnosis": record})
    notes = [*stack.notes, *_not_at_rest_notes(stack, warm, histories, again=best is not first)]
    diag = Diagnosis(model=model, extended=extended, stack=stack, findings=findings, hypotheses=hyps, result=result,
                     results=results, options=options, adequacy=adequacy, comparison=comparison, reidentified=reid,
                     block=block, notes=notes,
                     explanation=explanation, confusions=confused)
    diag.conclusions = conclusions(diag, block)
    if options.reidentify and missing:
        which = ("the model names no identification experiments" if missing == [NONE_NAMED] else
                 "its identification experiments are not among these recordings "
                 f"({', '.join(missing[:4])}{', ...' if len(missing) > 4 else ''} missing)")
        diag.conclusions.append(f"the model was not re-identified: {which}, and its paths cannot be identified "
                                "again from production alone; pass the experiments too to let diagnosis refit "
                                "every path")
    diag.wall_s = time.perf_counter() - t0
    return diag


NONE_NAMED = "(none named)"


@dataclass(kw_only=True)
class _Pass:
    """One pass of the diagnosis: every recording run from ``histories`` (the work before warm ones)."""

    histories: Mapping[int, tuple[Recording, str]]
    stack: Stack
    findings: dict[str, AxisFindings]
    adequacy: Adequacy
    block: np.ndarray
    hypotheses: list[Hypothesis]
    confused: list[Confusion]
    results: dict[str, SearchResult]
    reid: Reidentified | None
    comparison: Comparison
    explanation: Explanation | None
    missing: list[str]
    #: the re-identified model with the terms the refit search took (``reid`` when it is the one written): what
    #: chooses the work before a warm recording again (the fullest account of the data; the one written may be
    #: the model without terms, which predicts the held-out blocks as well but not a warm start's history)
    chooser: Reidentified | None = None
    #: the model re-identified with no term beside the paths, where it was (more data alone beside the terms)
    alone: Reidentified | None = None


def _choices(histories: Mapping[int, tuple[Recording, str]]) -> dict[int, str]:
    """What each history holds, in words (by recording): two passes chose alike when these are equal."""
    return {r: said for r, (_, said) in histories.items()}


def _one_pass(model: ThermalModel, recordings: Sequence[Recording], histories: Mapping[int, tuple[Recording, str]],
              warm: Mapping[int, str], *, infos: Sequence[FactorInfo], signals_of: tuple[list[str], list[str]],
              options: Options, families: Sequence[str] | None, gap_policy: str,
              progress: Callable[[str], None] | None, previous: _Pass | None = None) -> _Pass:
    """Locate, search, re-identify and compare, with every recording run from ``histories``.

    ``previous``: the pass before (other work before the warm recordings): its re-identifications are refined
    where the same terms are beside the paths, not searched again (:func:`reidentify`'s ``starts``).
    """
    stack = build_stack(model, [continued(histories[r][0], rec) if r in histories else rec
                                for r, rec in enumerate(recordings)], gap_policy=gap_policy)
    if histories:
        stack = replace(stack, lead=tuple(len(histories[r][0]) if r in histories else 0
                                          for r in range(len(recordings))))
    signals = candidate_signals(stack, *signals_of)
    findings: dict[str, AxisFindings] = {}
    artefacts: dict[str, list[np.ndarray]] = {}
    steps_um: dict[str, np.ndarray] = {}  # per axis, the sensor steps found (um, every window)
    for i, a in enumerate(model.axes):
        if not np.isfinite(stack.y[i]).any():
            continue
        r = aligned_residual(stack, i)
        noise = noise_level(stack, i, r)
        steps = find_steps(stack, i, r, noise)
        artefacts[a] = [s.column(stack) for s in steps]
        steps_um[a] = sum((s.size_um * c for s, c in zip(steps, artefacts[a], strict=True)), np.zeros(stack.n))
        r_clean = r - steps_um[a]
        findings[a] = AxisFindings(
            axis=a, residual=r, noise=noise, windows=located_windows(stack, r_clean, noise), steps=steps,
            change_points=change_points(stack, r_clean), states=operating_states(stack, r_clean),
            lines=spectral_lines(stack, r_clean), correlations=correlations(stack, r_clean, signals))
    # a recording that starts warm (cut while the machine worked) and runs from no fitted history (most do: a
    # disturbance is likelier; or --initial-state rest) is started in equilibrium with its first window like
    # every other: its error is partly its start's, said, and the verdict taken without it too
    adequacy = assess(stack, model, {a: f.noise.sigma_um for a, f in findings.items()}, steps_um,
                      not_at_rest={r: why for r, why in warm.items() if r not in histories})
    measured = np.isfinite(stack.y).any(axis=0)
    block = make_blocks(stack.bounds, measured, options.blocks)
    held_blocks = int(block.max()) + 1 if (block >= 0).any() else 0
    if held_blocks < MIN_HELD_BLOCKS:
        # nothing can be judged on data it did not train on: a verdict would be "within inf % of a 0 um peak"
        # and "nothing significant is missing" over a single window (a new user's one-row file)
        raise RecordingError(
            f"{', '.join(stack.names)}: {int(measured.sum())} window(s) with measured displacement, "
            f"{stack.own_windows * stack.dt_s / 3600:.2g} h in all, give {held_blocks} held-out block(s); a "
            f"diagnosis judges on at least {MIN_HELD_BLOCKS} (a recording gives some from 6 measured windows "
            "on, blocks of hours from a few hours on): record longer or add recordings")
    hyps = catalogue(stack, model, infos, families=families)
    confused = confusions(stack, hyps)
    # two ways to judge a hypothesis: as a term on the frozen identified model (its paths trusted), and with
    # every path refitted beside it (the paths corrected: what the missing physics did to identification);
    # the false-positive budget is split between them
    tracks: dict[str, list[np.ndarray]] = {"frozen": []}
    # re-identifying every path needs what pinned them down first: production alone mixes the factors in
    # one schedule's ratios, and a refit of all paths on it predicts another schedule worse
    missing = missing_experiments(model, stack)
    refit = options.reidentify and not missing
    if refit:
        tracks["refit"] = path_corrections(stack, model)
    sub = replace(options, alpha=options.alpha / len(tracks), alpha_axis=options.alpha_axis / len(tracks))
    results = {}
    for name, cols in tracks.items():
        # beside free paths a term can pass by standing in for the freedom the bank lacks: the refit
        # search takes it only if it survives with the paths held at the identified time constants
        held = held_corrections(stack, model) if name == "refit" and options.held_check else None
        results[name] = search(stack, hyps, block=block, artefacts=artefacts, options=sub, corrections=cols,
                               held=held,
                               progress=(lambda m, n=name: progress(f"{n}: {m}")) if progress else None)
    def writable(t: Trial) -> bool:  # a signal of unknown meaning is named, never written unchecked
        return not t.hypothesis.signal or t.hypothesis.signal in options.use_signals

    frozen = extend_model(model, {a: [x for x in ts if writable(x.trial)]
                                  for a, ts in results["frozen"].terms.items()})
    reid = alone = None
    names = ""
    if refit:
        taken = [t for t in results["refit"].accepted if writable(t)]
        # the passes differ in the work before a few recordings: each later one refines the re-identifications
        # of the one before instead of searching their structures again (bench/diagnose.py --cut-days 13, on the
        # AMD EPYC PC of 4 Dec: cabinet recorded v1 96.7-111 -> 72-88 s of CPU; the 54 cases' max 88.4 -> 72.2 s,
        # 12 changed, fresh-day pooled RMS geometric mean x1.002)
        reid = reidentify(stack, model, taken, artefacts=artefacts, progress=progress,
                          starts=(previous.chooser, previous.alone) if previous else ())
        if any(reid.terms.values()):  # more data alone beside the terms: written where significantly better
            # searched afresh, not refined from the paths chosen beside the terms: refined, it stayed where they
            # left it (the warm-day test's slow mode: 1.43 um held-out where the search gives 1.07, and the wrong
            # term written); the search costs 1.4-1.7x the diagnosis's CPU where terms were taken
            # (bench/diagnose_speed.py: room recorded v3 1.42, slow mode v1 1.70, chiller v2 1.58)
            alone = reidentify(stack, model, [], artefacts=artefacts, progress=progress,
                               starts=(previous.alone, previous.chooser) if previous else ())
            names = "; ".join(t.hypothesis.title for t in taken if not t.hypothesis.artefact)
    comparison = compare(stack, model, block, [t for t in results["frozen"].accepted if writable(t)], frozen,
                         reid, artefacts=artefacts, options=options, alone=alone, reid_names=names)
    chooser = reid
    if WITH_TERMS in comparison.candidates:  # more data alone predicts significantly better: it is written
        reid = alone
    explanation = None
    if reid is not None and comparison.chosen == "reidentified" and not any(reid.terms.values()):
        # more data alone won: which physics reproduces what the re-identified paths changed?
        explanation = explain(stack, model, reid, comparison, hyps, block=block,
                              artefacts=artefacts, options=sub, writable=writable, progress=progress)
    return _Pass(histories=histories, stack=stack, findings=findings, adequacy=adequacy,
                 block=block, hypotheses=hyps, confused=confused, results=results, reid=reid, comparison=comparison,
                 explanation=explanation, missing=missing, chooser=chooser, alone=alone)


def _supported_region(model: ThermalModel, recordings: Sequence[Recording], *, reidentified: bool,
                      gap_policy: str) -> ThermalModel:
    """``model`` with the envelope (and, when every path was identified again, the coverage) of what it was fitted on.

    The written model was fitted on these recordings too: its plausibility envelope is the larger of the
    identification's and theirs (the live gateway holds offsets beyond it, and a production day at 3x the
    experiments' speed is now data, not an extrapolation). A re-identified model's coverage is the region all
    of them span; a model with terms on frozen paths keeps the identification's coverage (its paths saw only
    the experiments). Either way the coverage holds the range of every recorded column an input reads (a room
    thermometer), over the recordings that have it: ``estimate`` and ``run`` say when a column leaves it (a
    thermometer read in degF by a model fitted in degC).
    """
    # a recording without a column an input of the model reads (a room thermometer only on the production days)
    # is none this model can run on
    columns = recorded_columns(model.inputs)
    recordings = [r for r in recordings if all(c in r.extras and np.isfinite(r.extras[c]).any() for c in columns)]
    preps = [prepare(r, factors=model.factors, axes=model.axes, reference=model.reference, gap_policy=gap_policy,
                     inputs=model.inputs) for r in recordings]
    source = f"diagnosis: {len(recordings)} recordings"
    env = envelope_of(model, ((p.du, p.y) for p in preps), window_s=recordings[0].period_s, source=source)
    changes: dict[str, object] = {"envelope": model.envelope.merged(env) if model.envelope is not None else env}
    coverage = coverage_of((p.du for p in preps), model.factors, source=source) if reidentified else model.coverage
    if coverage is not None and columns:
        coverage = replace(coverage, columns=column_ranges({c: [r.extras[c] for r in recordings] for c in columns}))
    changes["coverage"] = coverage
    return replace(model, **changes)


def uncovered_factors(model: ThermalModel, stack: Stack) -> list[str]:
    """Factors the recordings drive beyond the identification's coverage, in words ("speed up to 3x ... (1000 rpm)").

    Where :func:`check_coverage` flags them (the notes on the data say the same per recording), the ranges only.
    """
    if model.coverage is None or not stack.n:
        return []
    du = np.vstack([stack.du[f] for f in model.factors])
    out = []
    for e in check_coverage(model.coverage, du, model.factors, model.units).excursions:
        if e.kind == "range" and e.bound != 0 and e.value / e.bound > 0:
            unit = f" {e.unit}" if e.unit else ""
            out.append(f"{e.what} {'up' if e.side == 'above' else 'down'} to {e.value / e.bound:.2g}x the "
                       f"{'highest' if e.side == 'above' else 'lowest'} covered ({e.bound:.4g}{unit})")
    return out


def missing_experiments(model: ThermalModel, stack: Stack) -> list[str]:
    """The model's identification experiments (its ``[info] experiments``) not among the recordings."""
    listed = [str(n) for n in (model.info.get("experiments", []) or [])]
    if not listed:
        return [NONE_NAMED]
    prints = list(model.info.get("experiment_fingerprints", []) or [])
    have_names, have_prints = set(stack.names), set(stack.fingerprints)
    return [n for k, n in enumerate(listed)
            if n not in have_names and not (k < len(prints) and prints[k] in have_prints)]


def written_verdict(d: Diagnosis) -> str:
    """Where another model than the identified one is written: its fitness over the held-out blocks, in words.

    The identified model's verdict judges each recording it did not train on; the written model is judged on
    the comparison's held-out blocks (each predicted from a fit without it), its max |error| against the largest
    peak displacement there, by the same 30 % bound.
    """
    written = d.comparison.written
    if written.key == "identified":
        return ""
    figures = [m for m in written.metrics.values() if np.isfinite(m.max_error_pct_of_peak)]
    if not figures:
        return ""
    worst = max(figures, key=lambda m: m.max_error_pct_of_peak)
    text = (f"the model written ({written.title}): over the held-out blocks its max |error| is "
            f"{worst.max_error_pct_of_peak:.0f} % of the peak displacement on axis {worst.axis} "
            f"({worst.max_abs_error_um:.3g} of {worst.peak_um:.3g} um)")
    if worst.max_error_pct_of_peak <= 100 * MAX_ERROR_SHARE:
        return text + f": within the {100 * MAX_ERROR_SHARE:.0f} % a model fit for compensation keeps" + _beyond(d)
    return (text + f": over the {100 * MAX_ERROR_SHARE:.0f} % a model fit for compensation keeps: better than the "
            "identified model, not fit for compensation either; validate it on recordings it never saw (--validate) "
            "and look for what is still missing before compensating with it" + _beyond(d))


#: a written mode slower than this many lengths of the longest recording is said to extrapolate
SLOW_CAUTION = 2.0


def _beyond(d: Diagnosis) -> str:
    """A caution when the written model has a mode over twice as slow as the longest recording it was judged on.

    Over a recording a mode much slower than it rises almost as a ramp (at twice its length, 39 % of the way):
    the recordings show its gain over its time constant more than where it levels off, and a machine that runs
    on for longer goes where none of them went.
    """
    longest = d.stack.longest_s()
    slow = [(t, p) for p in d.extended.paths.values() for term in p.terms for t in term.time_constants_s]
    if not slow or longest <= 0:
        return ""
    tau, path = max(slow, key=lambda s: s[0])
    if tau <= SLOW_CAUTION * longest:
        return ""
    return (f"; its slowest mode ({tau / 3600:.3g} h, {path.axis}/{path.factor}) is {tau / longest:.2g}x the longest "
            f"recording ({longest / 3600:.3g} h): over a run longer than that it predicts what no recording showed; "
            "validate it on one that long (--validate) before compensating with it over such runs")


def conclusions(d: Diagnosis, block: np.ndarray) -> list[str]:
    """What can and cannot be concluded from these recordings, in plain sentences, the verdict first."""
    st = d.stack
    out = d.verdict()
    physics = [t for t in d.result.accepted if not t.hypothesis.artefact]
    cands = d.comparison.candidates
    written = d.comparison.written
    how = {"reidentified": " with every path refitted beside it",
           "explained": " with the paths held at the identified time constants, their gains refitted"
           }.get(d.comparison.chosen, "")
    for t in physics:
        gain = ", ".join(f"{a} {100 * t.evidence[a].gain:.0f} %" for a in t.axes)
        if t.hypothesis.signal and t.hypothesis.signal not in d.options.use_signals:
            out.append(f"{t.hypothesis.title} explains part of the residual (held-out squared error down {gain}), "
                       f"but it is not written into the model: what {t.hypothesis.signal} measures is unknown, and a "
                       "signal that merely correlates in these recordings can make other days worse. Check it on "
                       f"the machine, then diagnose again with --use-signal {t.hypothesis.signal}")
        elif d.comparison.chosen == "identified":
            out.append(f"{t.hypothesis.title} passed the hypothesis search (held-out squared error down {gain}), but "
                       "no model with it predicts the recordings the identified model did not train on better: "
                       "not named as missing, not written")
        elif d.comparison.chosen == "explained" and d.explanation is not None and d.explanation.written_unexplained:
            # in the model written for predicting best, but it explains only part of what more data changed: the
            # line below says "not named", and this one said "missing physics"
            out.append(f"written, not named: {t.hypothesis.title} (held-out squared error down {gain}{how}; it "
                       "explains only part of what more data changed in the paths, see below)")
        else:
            out.append(f"missing physics: {t.hypothesis.title} (held-out squared error down {gain}{how})")
    for c in cands.values():
        if c.key == "identified":
            continue
        rms = ", ".join(f"{a} {cands['identified'].metrics[a].rms_um:.3g} -> {m.rms_um:.3g} um"
                        for a, m in c.metrics.items() if m.windows)  # an axis measured in no held-out block: none
        out.append(f"{c.title}: held-out RMS {rms}; {c.verdict}")
    if written.key == "identified":
        if not d.adequacy.fit:
            out.append("no hypothesis and no re-identification made the model fit for compensation on these "
                       "recordings: do not compensate with it; record what else acts (the room's temperature, the "
                       "coolant's), or longer, and diagnose again")
        elif not physics:
            out.append("nothing significant is missing: no physical hypothesis lowered the held-out error "
                       "significantly (family-wise) and by a relevant amount, and re-identifying on all recordings "
                       "does not predict better")
    elif not physics and not (d.explanation and d.explanation.named):
        beyond = uncovered_factors(d.model, st)
        out.append("no missing physics is named, but the model identified again on all recordings predicts the "
                   "held-out blocks better: the identification experiments did not pin its paths down ("
                   + (f"the other recordings go beyond what they covered: {'; '.join(beyond)}; or " if beyond else "")
                   + "too little excitation, or a disturbance during them); the re-identified model is written")
    ex = d.explanation
    if ex is not None:
        changed = "; ".join(ex.changes) or "its gains, no time constant by more than 25 %"
        if ex.named and written.key == "reidentified":
            out.append(f"what more data changed in the paths ({changed}) is explained by "
                       f"{'; '.join(t.hypothesis.title for t in ex.named)} (named: {ex.verdict}); the re-identified "
                       "model predicts the held-out data better and is written")
        elif ex.named:
            out.append(f"what more data changed in the paths ({changed}) is explained by "
                       f"{'; '.join(t.hypothesis.title for t in ex.named)}: {ex.verdict}")
        elif ex.written_unexplained:
            out.append(f"more data changed the paths ({changed}); with the paths held at the identified time "
                       f"constants, {'; '.join(t.hypothesis.title for t in physics)} does not explain all of it "
                       f"({ex.verdict})")
        else:
            out.append(f"more data changed the paths ({changed}); no hypothesis explains the change with the paths "
                       f"held at the identified time constants ({ex.verdict}): no family is named")
    accepted = {t.hypothesis.key for t in physics} | {t.hypothesis.key for t in (ex.named if ex else [])}
    out += [c.line(accepted=c.key in accepted) for c in d.confusions]
    out += partial_columns(st)
    span_h = st.longest_s() / 3600.0
    total_h = st.own_windows * st.dt_s / 3600.0
    k = int(block.max()) + 1 if (block >= 0).any() else 0
    # the time the held-out blocks span: from each recording's burn-in to its last scored window (probe points
    # stand for the hours between them, not a window each)
    held_s = 0.0
    for a, b in st.bounds:
        held = np.flatnonzero(block[a:b] >= 0)
        if held.size:
            burn = np.flatnonzero(block[a:b] == BURN_IN)
            held_s += float(st.time_s[a + held[-1]] - st.time_s[a + (burn[-1] if burn.size else 0)])
    block_h = held_s / max(k, 1) / 3600.0
    if not physics:
        tried = [t for t in d.result.trials if t.round == 1 and not t.hypothesis.artefact]
        # ranked by evidence; "closest" only for one that predicted the held-out blocks better than nothing,
        # pooled and in more blocks than not (its own signed-rank p under one half)
        better = [t for t in tried if sum(e.sse_after for e in t.evidence.values())
                  < sum(e.sse_before for e in t.evidence.values()) and t.p < 0.5]
        # ... first those that lacked only significance (relevant on an axis): they are what more data decides;
        # among those Holm leaves at 1, the one its own test ranks first (the real spindle's 15 thermometers)
        best = min(better, key=lambda t: (not _relevant(d, t), t.p_holm, t.p, -t.score), default=None)
        if best is not None:
            out.append(f"closest candidate: {best.hypothesis.title}: {best.verdict}"
                       + _to_decide(d, best, sum(t.round == 1 for t in d.result.trials), k, block_h))
    out.append(f"{len(st.names)} recording(s), {total_h:.1f} h in all (longest {span_h:.1f} h); judged on {k} "
               f"held-out blocks of about {block_h:.1f} h (the first block of each recording only fits the initial "
               "state)")
    # recordings measured at probe instants only, and those without any measured displacement: said up front
    out += [n for n in st.notes if ": displacement measured at " in n and "probe instants only" in n]
    out += [n for n in st.notes if ": no measured displacement (no displacement or probe_* columns" in n]
    if k < 6:
        out.append(f"only {k} held-out blocks: the tests have little power; record longer to conclude more")
    moving = [f for f in st.factors if np.nanmax(np.abs(st.du[f])) > 0] if st.factors else []
    if not moving:
        out.append("no factor varies in these recordings: the model's paths cannot be tested, only recorded "
                   "columns and time-based hypotheses (slow drift, daily cycle)")
    elif all(_monotonic(st, f) for f in moving):
        out.append("every factor rises (or falls) and settles once, like a single warm-up: the dynamics are "
                   "weakly identified, held-out blocks test extrapolation in time only, and a slow mode cannot "
                   "be told from a drift")
    if span_h < 36:
        out.append(f"the longest recording is {span_h:.0f} h: within one recording a daily cycle cannot be told apart "
                   "from a slow drift or from the work schedule; record over several days, including an idle one")
    if not shows_the_day(st) and not any(h.family == "room_recorded" for h in d.hypotheses):
        hours = 24 * st.day_covered()
        cover = (f"the recording covers {hours:.0f} h of the 24 h clock" if len(st.bounds) == 1 else
                 f"the recordings cover {hours:.0f} h of the 24 h clock between them (longest {span_h:.0f} h)")
        out.append(f"a daily cycle (the room) was not tried: {cover}; it needs {24 * DAY_SHOWN:.0f} h of it, from "
                   "recordings stamped with their time of day")
    days = total_h / 24.0
    daily = any(h.family == "room_daily" for h in d.hypotheses)
    if daily and not any(t.hypothesis.family == "room_daily" for t in physics) and days < DAYS_FOR_DAILY:
        out.append(f"these recordings span {days:.1f} day(s) in all: a daily cycle (the room) needs at least "
                   f"{DAYS_FOR_DAILY:g} days, including an idle one, to be told from the work schedule and from a "
                   "slow drift")
    for a, f in d.findings.items():
        if f.noise.quantum_um > 0:
            out.append(f"axis {a}: the displacement is quantised in steps of {f.noise.quantum_um:.3g} um "
                       f"(noise floor {f.noise.quantum_um / math.sqrt(12):.3g} um RMS)")
    seen = [st.labels[r] for r, s in enumerate(st.identified(d.model)) if s]
    if seen:
        out.append(f"{', '.join(seen)} identified the model: there its error is a fit residual, not a test; they "
                   "still inform the re-identification and the hypotheses' fits")
    taken = {id(t) for t in d.result.accepted}
    for t in _named(d.result, ex):
        if t.rivals:
            names = [r.hypothesis.title + (" (significant alone, not after the correction for the hypotheses "
                                           "tried)" if r.short_of_holm else "") for r in t.rivals[:3]]
            out.append(f"{t.hypothesis.title}: these recordings do not tell it apart from {'; '.join(names)}: "
                       f"{'they pass too and ' if not any(r.short_of_holm for r in t.rivals[:3]) else ''}"
                       "they predict the held-out blocks not significantly worse; it was taken for fewer parameters, "
                       "for passing with the paths held, for the larger held-out gain or for passing the "
                       "correction, so it is named with them, not alone")
        trials = ex.result.trials if ex is not None and ex.result and id(t) not in taken else d.result.trials
        rivals = {id(r) for r in t.rivals}
        others = [r.hypothesis.title for r in trials if r.round == t.round and r is not t and id(r) not in rivals
                  and r.verdict.startswith("passes")]
        if others:
            out.append(f"{t.hypothesis.title}: {'; '.join(others[:3])} pass too, but predict the held-out blocks "
                       "significantly worse or change a path's structure only (an extra mode, a dead time)")
    for a, f in d.findings.items():
        for s in f.steps:
            out.append(f"axis {a}: a step of {s.size_um:+.3g} um within one window at {s.time_h:.2f} h "
                       f"({s.recording}) is a measurement artefact (too fast for heat), excluded from the fits")
    for t in d.result.accepted:
        if t.hypothesis.artefact:
            out.append(f"{t.hypothesis.title} on {', '.join(t.axes)}: excluded from the model")
    return out


def _named(result: SearchResult, ex: Explanation | None) -> list[Trial]:
    """What a diagnosis named: the chosen search's accepted trials, then what explains the paths' change.

    The two are the same trials when the explanation's search is the chosen one; told apart by identity, since
    a Trial compared by value compares its evidence's arrays.
    """
    taken = {id(t) for t in result.accepted}
    return [*result.accepted, *(t for t in (ex.named if ex else []) if id(t) not in taken)]


def _relevant(d: Diagnosis, t: Trial) -> list[AxisEvidence]:
    """The axes where ``t`` would be relevant were it significant (:func:`gateway.diagnose.search.sized`)."""
    return [e for e in t.evidence.values() if e.fit.without is not None and sized(e, d.options)]


def _to_decide(d: Diagnosis, t: Trial, tried: int, k: int, block_h: float) -> str:
    """For a candidate relevant on an axis but not significant: how much more recording would decide it.

    The axis where its blocks improve most consistently, at the multiplicity its test carried (the axes, the
    ``tried`` hypotheses of the round, the two searches), against the ``k`` held-out blocks of ``block_h``
    hours there are: see :func:`gateway.diagnose.select.blocks_to_decide`.
    """
    relevant = _relevant(d, t)
    if not t.verdict.startswith("not significant") or not relevant:
        return ""
    e = min(relevant, key=lambda e: e.p)
    alpha = d.options.alpha / max(len(d.results), 1)
    m = blocks_to_decide(e.fit.without - e.fit.held, multiplicity=len(t.evidence) * tried, alpha=alpha)
    head = (f"; it removes {100 * e.gain:.0f} % of {e.axis}'s held-out squared error, but {tried} hypotheses were "
            "tried on these blocks and chance must be ruled out for all of them")
    if m is None:
        return head + (": no amount of recordings like these would decide it (its blocks do not improve consistently "
                       "enough); recordings where it acts differently from the model's factors (other speeds, other "
                       "schedules) might")
    hours = m * block_h
    # the blocks' length is what makes their sums consistent (more recording in as many blocks is another test):
    # --blocks asks for about that many, each recording gets a few at least, so the option scales with the count
    again = math.ceil(d.options.blocks * (k + m) / k)
    text = (head + f": about {m} more held-out blocks like these would decide it (80 % of the time): record about "
            f"{hours:.0f} h more ({hours / 24:.1f} days) like these and diagnose again with --blocks {again} (to keep "
            f"blocks of about {block_h:.1f} h, as here)")
    if m > 3 * k:  # its blocks scatter: the same kind of recording decides it slowly, if at all
        text += ("; that is many times what there is: recordings like these will hardly decide it, recordings where "
                 "it acts differently from the model's factors (other speeds, other schedules) might")
    return text


def _monotonic(st: Stack, factor: str) -> bool:
    """Whether a factor moves once: its total variation (smoothed over an hour) is under 3 x its range."""
    width = max(1, round(3600.0 / st.dt_s))
    tv = rng = 0.0
    for a, b in st.bounds:
        x = st.du[factor][a:b]
        if len(x) <= width:
            continue
        sm = np.convolve(x, np.ones(width) / width, mode="valid")
        tv += float(np.sum(np.abs(np.diff(sm))))
        rng += float(np.ptp(sm))
    return rng > 0 and tv < 3 * rng


# ------------------------------------------------------------------------------------------- validation --
@dataclass(kw_only=True)
class Validation:
    """A recording never used for fitting or selection, estimated with the identified and the written model.

    Both estimates are exactly what ``cncgw estimate`` gives with the same settings (``settings``): the
    report's figures can be reproduced with the written model file.
    """

    recording: str
    label: str
    start: str  # how the model's state at the start was set, in words
    settings: dict[str, str]
    before: Estimate
    after: Estimate


def validate(d: Diagnosis, recordings: Sequence[Recording], *, earlier: Sequence[Recording] = (),
             history: Recording | None = None, gap_policy: str = "hold", chain: bool = True) -> list[Validation]:
    """Estimate ``recordings`` with the identified and the written model, as ``cncgw estimate`` would.

    The model's state at each recording's start: carried from the recordings that ran just before it (any
    of ``earlier`` and ``recordings`` that ends one window before it starts, and so on back: what
    ``cncgw run`` does with its stored history), or from ``history`` for the first; else, when the
    recording starts warm (:func:`starts_warm`), fitted to its first hour; else at rest. ``chain=False``
    (times counted from ``--period-s``, each file from 0: one ending where another starts says nothing): only
    ``history`` carries.
    """
    pool = [*earlier, *recordings]
    # the diagnosed recordings as the report names them; the others (validation, history) apart from those
    label = dict(zip(d.stack.sources, d.stack.labels, strict=True))
    sources = list(dict.fromkeys([*d.stack.sources, *(r.source for r in pool),
                                  *([history.source] if history is not None else [])]))
    label = dict(zip(sources, recording_labels(sources), strict=True)) | label
    out = []
    for k, rec in enumerate(recordings):
        before_it = _preceding(rec, pool) if chain else []
        if not before_it and history is not None and k == 0:
            before_it = [history]
        hist = None
        for part in before_it:
            hist = part if hist is None else continued(hist, part)
        if hist is not None and not chain:  # files whose times each count from 0: the history ran just before
            hist = hist.ending_before(rec)
        initial_state, initial = "rest", "first"
        if hist is not None:
            start = f"carried from {', '.join(label[p.source] for p in before_it)} (ran just before it)"
            gap_s = gap_between(hist, rec)
            if gap_s > 0.5 * rec.period_s:  # a --history that ended earlier: the gap policy bridges it
                start = (f"carried from {label[before_it[0].source]} (--history), which ends {gap_s / 3600:.3g} h "
                         f"before it starts: the gap policy {gap_policy} bridges the hours between")
        else:
            warm = starts_warm(d.extended, rec, gap_policy=gap_policy)
            if warm:
                initial_state = "fit"
                start = f"estimated from its first hour: it does not start at rest ({warm})"
                if works_at_start(d.extended, rec):
                    # its first window is no equilibrium: heat since the reference levels (a machine that has just
                    # started, or a warm one), not a state on top of working at that window for ever
                    initial = "reference"
                    start = (f"estimated from its first hour, from the model's reference levels: it does not start at "
                             f"rest ({warm})")
            else:
                start = "at rest (it starts with the machine in equilibrium)"
            if split_part(rec.source):  # a user whose files follow one another saw no reason it was not carried
                start += ("; a run of a --split-by file is never carried on from the one before it (--history FILE "
                          "carries)")
        kw = {"gap_policy": gap_policy, "history": hist, "initial_state": initial_state, "initial": initial}
        before = estimate(d.model, rec, **kw)
        after = estimate(d.extended, rec, **kw)
        out.append(Validation(recording=rec.source, label=label[rec.source], start=start,
                              settings=dict(after.settings), before=before, after=after))
    return out


def start_histories(model: ThermalModel, recordings: Sequence[Recording], warm: Mapping[int, str], *,
                    gap_policy: str = "hold", choose_with: ThermalModel | None = None
                    ) -> dict[int, tuple[Recording, str]]:
    """Of ``warm`` (recordings, by index, that seem not to start at rest: why), the work each runs from, in words.

    A recording cut while the machine worked starts in a state none of its windows shows. Started in equilibrium
    with its first window (as if it had worked so for ever), it leaves a transient through the hours after that
    every fit takes for missing physics and that pulls the paths a re-identification fits. Measured
    (bench/diagnose.py --cut-days 10, plant variants 1-3: the four production days from 10 h on, two or three
    of them working then; 51 cases): the model written was the identified one, unchanged, in 44 of 51 (3 of 51 on
    the whole days); free decays of the state beside every fit took the missing physics' own signature in those
    days (2 cases changed); left out, too little was left to judge on (45 of 51). Given the true hours before
    10 h as inputs without displacement (an oracle), 3 of 51: what a known start is worth.

    So each runs from the hours of work its first hours show (:func:`gateway.replay.working_history`: its own
    levels held for some hours from rest), as unmeasured windows before it: every path, refitted or not, and
    every term a hypothesis adds starts in the state that work leaves, physics the model lacks included. Same
    bench: 31 of 51 written unchanged, the fresh day >= 30 % better in 18 (6 before, none worse).

    The identified model lacks the very physics diagnosis looks for, so the work it chooses is off where that
    physics shaped the first hours. :func:`diagnose` chooses it again with ``choose_with``, the model identified
    again on all recordings (every path refitted, the terms taken beside them), and runs another pass while the
    choice changes (at most :data:`HISTORY_PASSES`), keeping the pass whose written model predicts the held-out
    blocks best. Same bench: 21 of 51 unchanged, 28 better, none worse, the right family named in 10 of 28 (6
    with the identified model's choice alone). Choosing with the model written instead (the identified one, in
    most of these cases) gave 15 better; taking the last pass rather than the best, 24 better and three more
    wrong names.

    Only a minority, and never a recording the model was identified on (its paths were fitted from that start):
    when most recordings move early, a disturbance acting in all of them (a room drifting through every first
    hour) is likelier than as many warm starts, and it is the diagnosis's to find.
    """
    if not warm or 2 * len(warm) >= len(recordings):
        return {}
    out = {}
    for r in warm:
        rec = recordings[r]
        if identified_on(model, rec.name, rec.fingerprint(model.factors)):
            continue
        history = working_history(choose_with or model, rec, gap_policy=gap_policy)
        if history is not None:
            out[r] = history
    return out


def _not_at_rest_notes(stack: Stack, warm: dict[int, str], histories: Mapping[int, tuple[Recording, str]], *,
                       again: bool = False) -> list[str]:
    """Notes on the recordings that seem not to start at rest (by index: why): one each, or one for many.

    A room that drifts in every recording makes each of them move early: thirteen notes alike said less than one.
    Those that run from a fitted history (``histories``; ``again``: chosen by the re-identified model) are said
    so, one each.
    """
    chosen = "as the re-identified model chooses it" if again else "as the identified model chooses it"
    out = [f"{stack.labels[r]}: it seems not to start at rest ({warm[r]}); it runs from the work its first hours "
           f"show ({said} before it, from rest, {chosen}, as windows with no displacement), so every fit starts it "
           "in the state that work leaves (--initial-state rest: in equilibrium with its first window)"
           for r, (_, said) in histories.items()]
    warm = {r: why for r, why in warm.items() if r not in histories}
    if not warm:
        return out
    tail = ("diagnose starts every recording in equilibrium with its first window, so what {} early on may be "
            "{} start's (a machine not yet at rest) or a disturbance no input carries")
    if len(warm) <= 2:
        return out + [f"{stack.labels[r]}: it seems not to start at rest ({why}); {tail.format('it misses', 'its')}"
                      for r, why in warm.items()]
    first, why = next(iter(warm.items()))
    names = [stack.labels[r] for r in warm]
    listed = ", ".join(names[:6]) + (", ..." if len(names) > 6 else "")
    return [*out, f"{len(warm)} recordings seem not to start at rest ({listed}; {stack.labels[first]}: {why}); "
            f"{tail.format('they miss', 'their')}"
            + ("; all of them: more likely a disturbance than starts" if len(warm) == len(stack.labels) else "")]


def validation_summary(d: Diagnosis, validations: Sequence[Validation]) -> str:
    """The validation in one conclusion: pooled RMS per axis, identified -> written, and where the written is worse.

    The table alone left it to the reader: a written model better over the held-out blocks can be worse on a
    validation day (a warm one, a schedule the diagnosed days did not have), and the verdict did not say so.
    """
    if not validations or d.comparison.chosen == "identified":
        return ""
    pooled, worse = [], []
    for a in d.model.axes:
        pairs = [(v, v.before.metrics[a], v.after.metrics[a]) for v in validations
                 if a in v.before.metrics and a in v.after.metrics and v.before.metrics[a].windows]
        if not pairs:
            continue
        n = sum(m.windows for _, m, _ in pairs)
        rms = [math.sqrt(sum(m.windows * m.rms_um ** 2 for m in ms) / n)
               for ms in ([b for _, b, _ in pairs], [f for _, _, f in pairs])]
        pooled.append(f"{a} {rms[0]:.3g} -> {rms[1]:.3g} um")
        # worse by over a tenth and by more than a hundredth of a micrometre: a real loss, not a rounding
        worse += [f"{v.label} {a} {b.rms_um:.3g} -> {f.rms_um:.3g} um"
                  + (" (its state fitted to its first hour: the fit differs too)"
                     if v.settings.get("initial_state") == "fit" else "") for v, b, f in pairs
                  if f.rms_um > 1.1 * b.rms_um and f.rms_um - b.rms_um > 0.01]
    if not pooled:
        return ""
    text = (f"validation ({len(validations)} recording(s) never fitted), RMS identified -> written model: "
            f"{', '.join(pooled)}")
    if worse:
        text += (f"; the written model is worse on {', '.join(worse[:6])}{', ...' if len(worse) > 6 else ''}: "
                 "weigh that before compensating with it")
    return text


def _preceding(rec: Recording, pool: Sequence[Recording]) -> list[Recording]:
    """The recordings that ran just before ``rec``, each ending one window before the next starts, oldest first.

    A run of a file split by a column (``--split-by``: ``file.csv[day=7]``) never follows or precedes another
    recording: each starts in its own equilibrium, as the diagnosis took them. Their times run on across the
    cut (a file of days written one after the other, or times counted from ``--period-s``) whether or not the
    machine rested between them.
    """
    chain: list[Recording] = []
    cur = rec
    while True:
        prev = next((p for p in pool if p is not cur and p not in chain and runs_on_from(p, cur)), None)
        if prev is None:
            return chain[::-1]
        chain.append(prev)
        cur = prev
