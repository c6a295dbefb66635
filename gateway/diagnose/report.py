"""The diagnosis report: Markdown for people, JSON for machines (same content)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from gateway.diagnose.api import Diagnosis, HeldMetrics
from gateway.diagnose.search import Trial


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


def _gains(gains: np.ndarray, sd: np.ndarray, labels: Sequence[str]) -> str:
    parts = []
    for k, g in enumerate(gains):
        s = sd[k] if k < len(sd) else math.nan
        lab = labels[k] if k < len(labels) and labels[k] else f"gain {k + 1}"
        parts.append(f"{lab}: {g:+.4g}" + (f" +/- {s:.2g}" if math.isfinite(s) else ""))
    return "; ".join(parts)


def to_json(d: Diagnosis, *, figures: Sequence[str] = (), model_file: str = "") -> dict[str, Any]:
    """The report as a JSON-ready dictionary."""
    def metrics(m: Mapping[str, HeldMetrics]) -> dict[str, Any]:
        return {a: {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                    for k, v in vars(x).items()} for a, x in m.items()}

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
    return _plain({
        "recordings": list(d.stack.sources), "axes": list(d.model.axes), "wall_s": d.wall_s,
        "options": vars(d.options), "conclusions": d.conclusions, "notes": d.notes,
        "accepted": [t.hypothesis.key for t in d.result.accepted if not t.hypothesis.artefact],
        "artefacts": d.artefacts,
        "held_out": {"before": metrics(d.before), "after": metrics(d.after),
                     "after_physics_only": metrics(d.after_physics)},
        "terms": {a: [{"hypothesis": t.trial.hypothesis.key, "setting": dict(t.setting.params),
                       "gains": [float(g) for g in t.gains],
                       "components": [c.label for c in t.setting.components],
                       "contribution_rms_um": float(np.std(t.contribution))} for t in ts]
                  for a, ts in d.result.terms.items()},
        "findings": findings, "trials": [trial(t) for t in d.result.trials],
        "extended_model": model_file, "derived_inputs": [i.name for i in d.extended.inputs], "figures": list(figures),
    })


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


def to_markdown(d: Diagnosis, *, figures: Sequence[str] = (), model_file: str = "", title: str = "") -> str:
    """The report as Markdown."""
    L: list[str] = [f"# Diagnosis{': ' + title if title else ''}", ""]
    L += [f"Recordings: {', '.join(d.stack.sources)}. Model axes: {', '.join(d.model.axes)}. "
          f"{len(d.hypotheses)} hypotheses, {len(d.result.trials)} trials in {d.wall_s:.1f} s.", ""]
    L += ["## Conclusions", ""] + [f"- {c}" for c in d.conclusions] + [""]
    if d.notes:
        L += ["Notes on the data:", ""] + [f"- {n}" for n in d.notes] + [""]

    L += ["## Held-out error, before and after", "",
          "Each block of time is predicted from a fit on the other blocks (the first block of each recording "
          "only fits the initial state). Before: the model as it is (a free offset per recording: sensors are "
          "zeroed anywhere). After: with the accepted physics, and measurement artefacts removed.", "",
          "| axis | windows | RMS before | RMS after | max abs error before | after | peak | % of peak before | after "
          "| RMS, physics only |", "|---|---|---|---|---|---|---|---|---|---|"]
    for a, b in d.before.items():
        af, ph = d.after[a], d.after_physics[a]
        L.append(f"| {a} | {b.windows} | {_num(b.rms_um)} um | {_num(af.rms_um)} um | {_num(b.max_abs_error_um)} um "
                 f"| {_num(af.max_abs_error_um)} um | {_num(b.peak_um)} um | {_num(b.max_error_pct_of_peak, '.1f')} "
                 f"| {_num(af.max_error_pct_of_peak, '.1f')} | {_num(ph.rms_um)} um |")
    L.append("")

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
            fin = next((x for x in d.result.terms.get(a, []) if x.trial is t), None)
            gains = fin.gains if fin is not None else e.gains
            labels = [c.label for c in e.setting.components] if e.setting else []
            L.append(f"- {a}: {_params(e.setting.params, e.params_sd) if e.setting else ''}; "
                     f"{_gains(gains, e.gains_sd, labels)}; held-out error down {100 * e.gain:.0f} %, "
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
                f"{c.time_h:.1f} h ({c.slope_before_um_h:+.2g} -> {c.slope_after_um_h:+.2g} um/h)"
                for c in f.change_points), ""]
        if f.states:
            L += ["Growth of the residual by operating state: " + "; ".join(
                f"{s.label} {s.growth_um_h:+.2g} um/h over {s.windows} windows" for s in f.states[:6]), ""]
        if f.lines:
            L += ["Spectral lines: " + "; ".join(f"{ln.period_h:.3g} h, amplitude {ln.amplitude_um:.2g} um "
                                                 f"({ln.ratio:.0f} x background)" for ln in f.lines), ""]
        if f.correlations:
            L += ["Correlations (largest over lags; bound: coloured-signal variance, Bonferroni over signals and lags; "
                  "the naive 1.96/sqrt(N) bound for comparison):", "",
                  "| signal | kind | lag | r | bound | naive bound | significant |", "|---|---|---|---|---|---|---|"]
            L += [f"| {c.signal} | {c.kind} | {c.lag_s / 60:.0f} min | {c.r:+.2f} | {c.bound:.2f} "
                  f"| {c.naive_bound:.3f} | {'yes' if c.significant else 'no'} |" for c in f.correlations[:10]]
            L.append("")

    L += ["## Every hypothesis tried", "",
          "Per axis: share of held-out squared error removed / contribution RMS (um); * = the axis joins.", "",
          "| round | hypothesis | params | p (Holm) | " + " | ".join(d.model.axes) + " | verdict |",
          "|---|---|---|---|" + "---|" * len(d.model.axes) + "---|"]
    for t in sorted(d.result.trials, key=lambda t: (t.round, t.p_holm, -t.score)):
        cells = []
        for a in d.model.axes:
            e = t.evidence.get(a)
            mark = "*" if e is not None and e.included else ""
            cells.append("-" if e is None else f"{100 * e.gain:.0f} % / {e.effect_rms_um:.2g}{mark}")
        L.append(f"| {t.round} | {t.hypothesis.key} | {t.hypothesis.complexity} | {t.p_holm:.2g} | "
                 + " | ".join(cells) + f" | {t.verdict} |")
    L.append("")
    if figures:
        L += ["## Figures", ""] + [f"![{f}]({f})" for f in figures] + [""]
    if model_file:
        L += ["## Extended model", "", f"Written to `{model_file}`: `cncgw estimate --model {model_file}` runs it."]
        if d.extended.inputs:
            L += ["", "Derived inputs:", ""] + [f"- `{i.name}`: {i.describe()}" + (f" ({i.note})" if i.note else "")
                                              for i in d.extended.inputs]
        L.append("")
    return "\n".join(L)
