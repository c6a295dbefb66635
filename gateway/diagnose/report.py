"""The diagnosis report: Markdown for people, JSON for machines (same content)."""

from __future__ import annotations

import math
import shlex
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from gateway.diagnose.api import Diagnosis, Validation
from gateway.diagnose.hypotheses import Setting, identification_length_s
from gateway.diagnose.locate import LAGS_S
from gateway.diagnose.search import Term, Trial
from gateway.recording import split_file
from gateway.replay import AxisFigures
from gateway.strict_json import nan_to_none


def _num(x: float, fmt: str = ".3g") -> str:
    return "-" if x is None or not math.isfinite(x) else format(x, fmt)


def _params(params: Sequence[tuple[str, object]], sd: Mapping[str, float]) -> str:
    out = []
    for k, v in params:
        if isinstance(v, float):
            text = (f"{v / 3600:.3g} h" if v >= 5400 else f"{v / 60:.3g} min") if k.endswith("_s") else f"{v:.4g}"
            if k in sd and math.isfinite(sd[k]):
                text += f" (spread over the folds: a factor {sd[k]:.2g})"
            out.append(f"{k} = {text}")
        else:
            out.append(f"{k} = {v}")
    return ", ".join(out)


def _gains(gains: np.ndarray, sd: np.ndarray, labels: Sequence[str], units: Sequence[str] = ()) -> str:
    """``label: +g +/- sd um/unit; ...``: a gain is micrometres per unit of its input (at steady state)."""
    parts = []
    for k, g in enumerate(gains):
        s = sd[k] if k < len(sd) else math.nan
        lab = labels[k] if k < len(labels) and labels[k] else f"gain {k + 1}"
        u = units[k] if k < len(units) else ""
        unit = " um" if u == "1" else (f" um/{u}" if u else "")  # "1": a flag's gain is micrometres while it is on
        parts.append(f"{lab}: {g:+.4g}" + (f" +/- {s:.2g}" if math.isfinite(s) else "") + unit)
    return "; ".join(parts)


def _input_units(d: Diagnosis, setting: Setting) -> list[str]:
    """The unit of each component's input: a factor's (the model's units), a derived input's own."""
    derived = {i.name: i.unit for i in setting.chain}
    return [derived.get(c.parts[0].input, d.model.units.get(c.parts[0].input, "")) if c.parts else ""
            for c in setting.components]


def to_json(d: Diagnosis, *, figures: Sequence[str] = (), model_file: str = "",
            validations: Sequence[Validation] = ()) -> dict[str, Any]:
    """The report as a JSON-ready dictionary."""
    def metrics(m: Mapping[str, AxisFigures]) -> dict[str, Any]:
        return {a: nan_to_none(vars(x)) for a, x in m.items()}

    def trial(t: Trial) -> dict[str, Any]:
        return {
            "hypothesis": t.hypothesis.key, "family": t.hypothesis.family, "title": t.hypothesis.title,
            "artefact": t.hypothesis.artefact, "round": t.round, "p": t.p, "p_holm": t.p_holm,
            "complexity": t.hypothesis.complexity, "score": t.score, "verdict": t.verdict,
            "axes": {a: {"included": e.included, "held_out_sse_before_um2": e.sse_before,
                         "held_out_sse_after_um2": e.sse_after, "gain_share": e.gain, "p": e.p,
                         "effect_rms_um": e.effect_rms_um, "relevance_um": e.relevance_um, "note": e.note,
                         "setting": dict(e.setting.params) if e.setting else None,
                         "gains": [float(g) for g in e.gains], "gains_sd": [_finite(g) for g in e.gains_sd],
                         "params_spread_factor": e.params_sd}
                     for a, e in t.evidence.items()},
        }

    findings = {}
    for a, f in d.findings.items():
        findings[a] = {
            "noise": vars(f.noise),
            "windows": [vars(w) | {"active": list(w.active)} for w in f.windows],
            "steps": [vars(s) for s in f.steps],
            "change_points": [vars(c) for c in f.change_points],
            "states": [vars(s) for s in f.states],
            "spectral_lines": [vars(ln) for ln in f.lines],
            "correlations": [vars(c) for c in f.correlations],
        }
    ad = d.adequacy
    ex = d.explanation
    return _plain({
        "recordings": list(d.stack.sources), "labels": d.stack.labels,
        "axes": list(d.model.axes), "wall_s": d.wall_s,
        "options": vars(d.options), "conclusions": d.conclusions, "notes": d.notes,
        "adequacy": {"judged": ad.judged, "fit": ad.fit, "unseen": list(ad.unseen),
                     "axes": {a: vars(x) for a, x in ad.axes.items()}, "resting_drift": {a: vars(x) for a, x in
                                                                                          ad.drift.items()},
                     # recordings that seem not to start at rest, and the verdict without them (when unfit)
                     "not_at_rest": dict(ad.not_at_rest),
                     "without_them": None if ad.without is None else {
                         "unseen": list(ad.without.unseen), "fit": ad.without.fit,
                         "axes": {a: vars(x) for a, x in ad.without.axes.items()}}},
        "accepted": [t.hypothesis.key for t in d.result.accepted if not t.hypothesis.artefact],
        "artefacts": d.artefacts,
        "written": d.comparison.chosen,
        "explained": d.explanation.names if d.explanation is not None else [],
        "paths_changed": d.explanation.changes if d.explanation is not None else [],
        "indistinguishable": [{"hypothesis": c.key, "title": c.title, "inputs": list(c.inputs), "factor": c.factor,
                               "unexplained_share": c.unexplained, "tell_apart": c.tell_apart}
                              for c in d.confusions],
        # "named ~ rival": passed in the same round, held-out blocks not significantly worse (search.Trial.rivals)
        "not_told_apart": list(d.extended.info.get("diagnosis", {}).get("not_told_apart", [])),
        "candidates": {k: {"title": c.title, "passes": c.passes, "verdict": c.verdict, "p": c.p, "gain_share": c.gain,
                           "held_out_sse_um2": c.sse, "metrics": metrics(c.metrics)}
                       for k, c in d.comparison.candidates.items()},
        "held_out": {"before": metrics(d.before), "after": metrics(d.after)},
        "validation": [validation_json(v) for v in validations],
        "terms": {a: [{"hypothesis": t.trial.hypothesis.key, "setting": dict(t.setting.params),
                       "gains": [float(g) for g in t.gains],
                       "components": [c.label for c in t.setting.components],
                       "contribution_rms_um": float(np.std(t.contribution))} for t in ts]
                  for a, ts in written_terms(d).items()},
        "at_search_bound": bound_flags(d),
        "findings": findings,
        "trials": [trial(t) | {"track": name} for name, r in d.results.items() for t in r.trials]
        # the search with the paths held at the identified time constants (when more data alone won): why a
        # mechanism is or is not named
        + [trial(t) | {"track": "held"} for t in (ex.result.trials if ex is not None and ex.result else [])],
        "explanation": None if ex is None else {
            "verdict": ex.verdict, "named": ex.names, "paths_changed": ex.changes,
            "held_sse_um2": _finite(ex.held_sse_um2), "free_sse_um2": _finite(ex.free_sse_um2),
            "closest": [{"hypothesis": c.key, "title": c.title, "share_of_paths_change": _finite(c.share),
                         "held_out_sse_um2": c.sse_um2, "verdict": c.verdict} for c in ex.closest]},
        "extended_model": model_file, "derived_inputs": [i.name for i in d.extended.inputs], "figures": list(figures),
    })


def validation_json(v: Validation) -> dict[str, Any]:
    """One validation recording: how it started, the settings, before/after figures per axis."""
    return {"recording": v.recording, "label": v.label, "start": v.start, "settings": v.settings,
            "before": v.before.to_json()["axes"], "after": v.after.to_json()["axes"],
            "notes": list(v.after.notes)}


def written_terms(d: Diagnosis) -> dict[str, list[Term]]:
    """The accepted terms as they are in the written model (refitted with the paths when it re-identified)."""
    if d.comparison.chosen == "reidentified" and d.reidentified is not None:
        return d.reidentified.terms
    if d.comparison.chosen == "terms":
        return d.result.terms
    if d.comparison.chosen == "explained" and d.explanation is not None:
        return d.explanation.terms
    return {}


def bound_flags(d: Diagnosis) -> list[str]:
    """Parameters that ended on the edge of what was searched: the true value may lie beyond it."""
    out = []
    for t in d.result.accepted:
        for a, e in t.evidence.items():
            if not e.included or e.setting is None:
                continue
            grid = t.hypothesis.settings.get(a, [])
            for k, v in e.setting.params:
                values = sorted({float(x) for x in (s.param(k) for s in grid) if isinstance(x, float)})
                if isinstance(v, float) and len(values) > 2 and v in (values[0], values[-1]):
                    edge = "lowest" if v == values[0] else "highest"
                    out.append(f"{t.hypothesis.key} on {a}: {k} = {_seconds(k, v)} is the {edge} value searched "
                               f"({_seconds(k, values[0])} .. {_seconds(k, values[-1])}): the true value may lie "
                               "beyond")
    if d.reidentified is not None and d.comparison.chosen == "reidentified":
        hi = identification_length_s(d.model)
        for p in d.extended.paths.values():
            if p.factor in d.model.factors and any(abs(math.log(t / hi)) < 0.01 for term in p.terms
                                                   for t in term.time_constants_s):
                out.append(f"path {p.axis}/{p.factor}: a time constant at the longest allowed ({hi / 3600:.3g} h, the "
                           "identification runs' length): slower heat is for a slow mode to claim")
    return out


def _seconds(key: str, v: float) -> str:
    if not key.endswith("_s"):
        return f"{v:.4g}"
    return f"{v / 3600:.3g} h" if v >= 5400 else f"{v / 60:.3g} min"


def _finite(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def _plain(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_plain(v) for v in x]
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.floating | float):
        v = float(x)
        return v if math.isfinite(v) else None
    if isinstance(x, np.bool_):
        return bool(x)
    return x


def to_markdown(d: Diagnosis, *, figures: Sequence[str] = (), model_file: str = "", title: str = "",
                validations: Sequence[Validation] = (), hedges: Sequence[str] = (), profile: str = "",
                model_path: str = "", recording_options: str = "") -> str:
    """The report as Markdown.

    ``profile``, ``model_path``: the paths the printed ``cncgw estimate`` commands use, as from the folder
    ``cncgw diagnose`` ran in (the recordings' paths are as given there); ``recording_options``: the options
    the recordings were read with (``--period-s 60``), which those commands need too.
    """
    q = shlex.quote  # paths with spaces (a Windows user's folders) run as printed in a POSIX shell
    estimate_cmd = (f"cncgw estimate --profile {q(profile) if profile else 'PROFILE'} "
                    f"--model {q(model_path or model_file) if model_path or model_file else 'MODEL'}"
                    + (f" {recording_options}" if recording_options else ""))
    L: list[str] = [f"# Diagnosis{': ' + title if title else ''}", ""]
    labels = d.stack.labels
    L += [f"Recordings: {', '.join(labels)}. Model axes: {', '.join(d.model.axes)}. "
          f"{len(d.hypotheses)} hypotheses, {len(d.result.trials)} trials in {d.wall_s:.1f} s.", ""]
    L += [f"> {h}" for h in hedges] + ([""] if hedges else [])
    verdict = d.verdict()
    L += ["## Verdict", ""] + [f"- {c}" for c in verdict] + [""]
    L += ["## Conclusions", ""] + [f"- {c}" for c in d.conclusions if c not in verdict] + [""]
    if d.notes:
        L += ["Notes on the data:", ""] + [f"- {n}" for n in d.notes] + [""]

    L += ["## Models compared on held-out data", "",
          f"Held out: {d.comparison.scheme}. What is held out is predicted from a fit on the rest: every "
          "candidate's gains are refitted without it (at the time constants chosen on all data; a re-identified "
          "model is identified again without it, time constants too), and each recording is predicted from its "
          "start at rest on the zero `cncgw estimate` takes (its idle lead-in). A recording's own drift or "
          "initial state is fitted while identifying and left out here, as `cncgw estimate` and `cncgw run` "
          "know nothing of it. A candidate "
          "passes when it is better consistently over the blocks (signed-rank test) and relevantly; the best that "
          "passes is written.", "",
          "| model | verdict | " + " | ".join(f"{a}: RMS / max abs / % of peak" for a in d.model.axes) + " |",
          "|---|---|" + "---|" * len(d.model.axes)]
    for c in d.comparison.candidates.values():
        cells = []
        for a in d.model.axes:
            m = c.metrics.get(a)
            cells.append("-" if m is None else f"{_num(m.rms_um)} / {_num(m.max_abs_error_um)} um / "
                                               f"{_num(m.max_error_pct_of_peak, '.1f')} %")
        L.append(f"| {c.title} | {c.verdict} | " + " | ".join(cells) + " |")
    L.append("")

    if validations:
        L += ["## Validation: recordings never used for fitting or selection", "",
              "Estimated exactly as `cncgw estimate` does with the settings given, once with the identified model "
              "and once with the written one (the written model file reproduces these figures)"
              + (": the identified model is the one written, so before and after are the same." if
                 d.comparison.chosen == "identified" else "."), "",
              "| recording | start | axis | RMS before | RMS after | max abs before | after | peak (before / after) "
              "| % of peak before "
              "| after |", "|---|---|---|---|---|---|---|---|---|---|"]
        for v in validations:
            for a, m in v.before.metrics.items():
                n = v.after.metrics.get(a)
                if n is None:
                    continue
                # each model's % is of the peak measured against its own zero (each model zeroes the recording
                # at its start): one figure where they agree, both where they do not
                peak = (f"{_num(m.peak_um)} um" if math.isclose(m.peak_um, n.peak_um, rel_tol=5e-3, abs_tol=1e-3)
                        else f"{_num(m.peak_um)} / {_num(n.peak_um)} um")
                L.append(f"| {v.label} | {v.start} | {a} | {_num(m.rms_um)} um | {_num(n.rms_um)} um | "
                         f"{_num(m.max_abs_error_um)} um | {_num(n.max_abs_error_um)} um | {peak} | "
                         f"{_num(m.max_error_pct_of_peak, '.1f')} | {_num(n.max_error_pct_of_peak, '.1f')} |")
        L.append("")
        L.append("The same with the written model, from the folder `cncgw diagnose` ran in:")
        L.append("")
        for v in validations:
            opts = " ".join(f"--{k.replace('_', '-')} {q(val)}" for k, val in v.settings.items()
                            if k in ("initial", "initial_state", "history") and val not in ("rest", "first"))
            file, part = split_file(v.recording)
            if part:  # a run of a split file: estimate splits the file the same way, this run among the others
                L.append(f"- {v.label}: `{estimate_cmd} {opts + ' ' if opts else ''}--split-by {q(part[0])} {q(file)}` "
                         f"(its {part[0]} {part[1]})")
            else:
                L.append(f"- {v.label}: `{estimate_cmd} {opts + ' ' if opts else ''}{q(v.recording)}`")
        L.append("")

    flags = bound_flags(d)
    if flags:
        L += ["Parameters on the edge of the range searched:", ""] + [f"- {f}" for f in flags] + [""]

    L += ["## Accepted", ""]
    physics = [t for t in d.result.accepted if not t.hypothesis.artefact]
    if not physics:
        L += ["Nothing: no hypothesis lowered the held-out error significantly and relevantly.", ""]
    for t in d.result.accepted:
        kind = "measurement artefact, kept out of the model" if t.hypothesis.artefact else "physics, added to the model"
        L += [f"### {t.hypothesis.title} ({kind})", "", t.hypothesis.explanation, "",
              f"Round {t.round}; Holm-adjusted p = {t.p_holm:.2g}; held-out squared error removed: "
              f"{100 * t.score:.0f} % (pooled over the axes).", ""]
        for a in t.axes:
            e = t.evidence[a]
            fin = next((x for x in written_terms(d).get(a, []) if x.trial is t), None)
            gains = fin.gains if fin is not None else e.gains
            setting = fin.setting if fin is not None else e.setting
            labels = [c.label for c in setting.components] if setting else []
            units = _input_units(d, setting) if setting else []
            L.append(f"- {a}: {_params(e.setting.params, e.params_sd) if e.setting else ''}; "
                     f"{_gains(gains, e.gains_sd, labels, units)}; held-out error down {100 * e.gain:.0f} %, "
                     f"contribution {e.effect_rms_um:.3g} um RMS")
        L.append("")
    if d.artefacts:
        L += ["Measurement artefacts (excluded from the fits, not in the model):", ""]
        L += [f"- {a}" for a in d.artefacts] + [""]

    L += ["## Located", ""]
    for a, f in d.findings.items():
        L += [f"### axis {a}", "",
              f"Noise (from first differences): {f.noise.sigma_um:.3g} um RMS"
              + (f", quantised in {f.noise.quantum_um:.3g} um steps" if f.noise.quantum_um else "")
              + f"; band +/- {f.noise.band_um:.3g} um.", ""]
        if f.windows:
            L += ["Windows outside the band (largest first):", "", "| recording | from h | to h | peak um | running | "
                  "active factors |", "|---|---|---|---|---|---|"]
            L += [f"| {w.recording} | {w.start_h:.2f} | {w.end_h:.2f} | {w.peak_um:+.3g} "
                  f"| {100 * w.running_share:.0f} % | {', '.join(w.active) or '-'} |" for w in f.windows]
            L.append("")
        else:
            L += ["The residual stays inside its noise band.", ""]
        if f.steps:
            L += ["Steps (one window, persistent): " + "; ".join(
                f"{s.size_um:+.3g} um at {s.time_h:.2f} h in {s.recording}" for s in f.steps), ""]
        if f.change_points:
            L += ["Change points of the residual's trend: " + "; ".join(
                f"{c.time_h:.1f} h into {c.recording} ({c.slope_before_um_h:+.2g} -> {c.slope_after_um_h:+.2g} um/h)"
                for c in f.change_points), ""]
        if f.states:
            L += ["Growth of the residual by operating state: " + "; ".join(
                f"{s.label} {s.growth_um_h:+.2g} um/h over {s.windows} windows" for s in f.states[:6]), ""]
        if f.lines:
            L += ["Spectral lines: " + "; ".join(f"{ln.period_h:.3g} h, amplitude {ln.amplitude_um:.2g} um "
                                                 f"({ln.ratio:.0f} x background)" for ln in f.lines), ""]
        if f.correlations:
            L += ["Correlations (largest over lags: the signal through a first-order lag of time constant 0 to "
                  f"{max(LAGS_S) / 3600:g} h, '>=' where the longest tried was best; bound: coloured-signal variance, "
                  "Bonferroni over signals and lags; the naive 1.96/sqrt(N) bound for comparison):", "",
                  "| signal | kind | lag | r | bound | naive bound | significant |", "|---|---|---|---|---|---|---|"]
            L += [f"| {c.signal} | {c.kind} | {'>= ' if c.lag_s >= max(LAGS_S) else ''}{c.lag_s / 60:.0f} min "
                  f"| {c.r:+.2f} | {c.bound:.2f} "
                  f"| {c.naive_bound:.3f} | {'yes' if c.significant else 'no'} |" for c in f.correlations[:10]]
            L.append("")

    L += ["## Every hypothesis tried", "",
          "Two searches: `frozen` judges each hypothesis as a term on the identified model; `refit` judges it with "
          "every path refitted beside it (linearly: each input through a bank of lags), what the model written by "
          "re-identification does. Ranked by evidence within a round. Per axis: share of held-out squared error "
          "removed / contribution RMS (um); * = the axis joins.", "",
          "| search | round | hypothesis | params | p (Holm) | " + " | ".join(d.model.axes) + " | verdict |",
          "|---|---|---|---|---|" + "---|" * len(d.model.axes) + "---|"]
    ranked = [(name, t) for name, r in d.results.items()
              for t in sorted(r.trials, key=lambda t: (t.round, t.p_holm, -t.score))]
    for name, t in ranked:
        cells = []
        for a in d.model.axes:
            e = t.evidence.get(a)
            mark = "*" if e is not None and e.included else ""
            cells.append("-" if e is None else f"{100 * e.gain:.0f} % / {e.effect_rms_um:.2g}{mark}")
        L.append(f"| {name} | {t.round} | {t.hypothesis.key} | {t.hypothesis.complexity} | {t.p_holm:.2g} | "
                 + " | ".join(cells) + f" | {t.verdict} |")
    L.append("")
    if figures:
        L += ["## Figures", ""] + [f"![{f}]({f})" for f in figures] + [""]
    if model_file:
        # "extended" only where something was added: a re-identified model alone is the same structure refitted
        heading = "## Extended model" if d.extended.inputs or any(not t.hypothesis.artefact
                                                                   for t in d.result.accepted) else "## Model written"
        L += [heading, "", f"Written to `{model_file}`: `{estimate_cmd} RECORDING` runs it."]
        if d.extended.inputs:
            L += ["", "Derived inputs:", ""] + [f"- `{i.name}`: {i.describe()}" + (f" ({i.note})" if i.note else "")
                                              for i in d.extended.inputs]
        L.append("")
    return "\n".join(L)
