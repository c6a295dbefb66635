"""The report's figures: fit with located windows, residual before and after, spectrum, contributions."""

from __future__ import annotations

import textwrap
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from gateway.diagnose.api import Diagnosis, Validation
from gateway.diagnose.locate import spectrum
from gateway.diagnose.report import written_terms
from gateway.replay import INITIAL_FIT_S


def _legend(grid, **kw) -> None:
    """The legend on the first panel that has labelled lines (none where no panel has: no empty legend)."""
    for ax in grid[:, 0]:
        if ax.get_legend_handles_labels()[0]:
            ax.legend(**kw)
            return


def _hours(d: Diagnosis) -> np.ndarray:
    """Hours on one axis for all recordings end to end (each recording continues after the previous)."""
    st = d.stack
    out = np.empty(st.n)
    offset = 0.0
    for a, b in st.bounds:
        t = (st.time_s[a:b] - st.time_s[a] + st.dt_s) / 3600.0
        out[a:b] = offset + t
        offset = out[b - 1]
    return out


def _plt():
    from gateway.plotting import pyplot

    plt = pyplot()

    return plt


def _separators(ax, d: Diagnosis, h: np.ndarray) -> None:
    for a, _ in d.stack.bounds[1:]:
        ax.axvline(h[a], color="k", lw=0.6, ls=":")


def write_figures(d: Diagnosis, out_dir: Path, *, validations: Sequence[Validation] = (), hedge: str = "") -> list[str]:
    """Write the PNGs into ``out_dir``; return their file names. ``hedge``: a caveat every figure carries."""
    plt = _plt()
    st = d.stack
    h = _hours(d)
    axes = [a for a in d.model.axes if a in d.findings]
    names = []
    terms = written_terms(d)
    written = d.comparison.written
    before = d.comparison.candidates["identified"]
    tail = f"\n{hedge}" if hedge else ""

    fig, grid = plt.subplots(len(axes), 1, figsize=(11, 2.8 * len(axes)), sharex=True, squeeze=False)
    for k, a in enumerate(axes):
        ax = grid[k, 0]
        i = d.model.axes.index(a)
        f = d.findings[a]
        meas = st.base[i] + f.residual
        ax.plot(h, meas, color="0.3", lw=0.8, label="measured (zero at each start)")
        ax.plot(h, st.base[i], color="C0", lw=1.2, label="identified model")
        if written is not before and d.reidentified is not None and written.key == "reidentified":
            shift = _zero_at_start(st, d.reidentified.prediction[i], meas)
            ax.plot(h, d.reidentified.prediction[i] + shift, color="C3", lw=1.2, ls="--", label="written model")
        elif written is not before:
            extra = sum((t.contribution for t in terms.get(a, [])), np.zeros(st.n))
            ax.plot(h, st.base[i] + extra, color="C3", lw=1.2, ls="--", label="written model")
        for w in f.windows:
            ax.axvspan(h[w.start], h[w.stop - 1], color="C1", alpha=0.15, lw=0)
        for s in f.steps:
            ax.axvline(h[s.index], color="C4", lw=1.0)
        _separators(ax, d, h)
        ax.set_ylabel(f"{a} (um)")
    _legend(grid, fontsize=7, loc="best")
    grid[0, 0].set_title("measured vs the identified and the written model; shaded: residual outside its noise band; "
                         "violet: sensor steps" + tail, fontsize=9)
    # wrapped: a dozen recordings' names made a label wider than the figure, cut off at both ends
    grid[-1, 0].set_xlabel(textwrap.fill("time (h), recordings end to end: " + ", ".join(_labels(d)), 150),
                           fontsize=8)
    fig.tight_layout()
    fig.savefig(out_dir / "fit.png", dpi=100)
    plt.close(fig)
    names.append("fit.png")

    fig, grid = plt.subplots(len(axes), 1, figsize=(11, 2.4 * len(axes)), sharex=True, squeeze=False)
    for k, a in enumerate(axes):
        ax = grid[k, 0]
        i = d.model.axes.index(a)
        # the identified model's residual, and the written model's beside it when another model is written
        for c, color in ((before, "C0"), *(((written, "C3"),) if written is not before else ())):
            p = c.prediction.get(a)
            if p is None:
                continue
            ax.plot(h, st.y[i] - p, color=color, lw=0.8, label=f"{c.key} (held out)")
        ax.axhline(0, color="k", lw=0.5)
        band = d.findings[a].noise.band_um
        ax.axhspan(-band, band, color="0.85", lw=0)
        _separators(ax, d, h)
        ax.set_ylabel(f"{a} residual (um)")
    _legend(grid, fontsize=7, loc="best")
    grid[0, 0].set_title("held-out residual (each block predicted from the others; grey: noise band)" + tail,
                         fontsize=9)
    grid[-1, 0].set_xlabel("time (h)")
    fig.tight_layout()
    fig.savefig(out_dir / "residual.png", dpi=100)
    plt.close(fig)
    names.append("residual.png")
    after = {}
    for a in axes:
        i = d.model.axes.index(a)
        p = written.prediction.get(a)
        q = before.prediction.get(a)
        after[a] = np.nan_to_num(p - q) if p is not None and q is not None else np.zeros(st.n)

    fig, grid = plt.subplots(1, len(axes), figsize=(4 * len(axes), 3.2), squeeze=False)
    for k, a in enumerate(axes):
        ax = grid[0, k]
        f = d.findings[a]
        for label, r, color in (("before", f.residual, "C0"), ("after", f.residual - after[a], "C3")):
            fr, p = spectrum(st, r)
            if fr.size > 1:  # after dashed: where nothing was removed it lies on before, which still shows
                ax.loglog(1.0 / fr[1:], p[1:], color=color, lw=0.8, label=label, ls="--" if label == "after" else "-")
        for n, ln in enumerate(f.lines):
            ax.axvline(ln.period_h, color="C2", lw=0.8, ls=":", label="spectral line found" if n == 0 else None)
        ax.set_xlabel("period (h)")
        ax.set_title(f"{a} residual spectrum", fontsize=9)
    grid[0, 0].set_ylabel("power (um^2)")
    _legend(grid, fontsize=7)
    fig.tight_layout()
    fig.savefig(out_dir / "spectrum.png", dpi=100)
    plt.close(fig)
    names.append("spectrum.png")

    if any(terms.get(a) for a in axes):
        fig, grid = plt.subplots(len(axes), 1, figsize=(11, 2.2 * len(axes)), sharex=True, squeeze=False)
        for k, a in enumerate(axes):
            ax = grid[k, 0]
            mine = [t for t in terms.get(a, []) if not t.trial.hypothesis.artefact]
            for t in mine:  # named as the report names it
                ax.plot(h, t.contribution, lw=1.0, label=t.trial.hypothesis.title)
            if not mine:
                ax.text(0.5, 0.5, f"no accepted term acts on {a}", transform=ax.transAxes, ha="center",
                        va="center", fontsize=8, color="0.4")
            ax.axhline(0, color="k", lw=0.5)
            _separators(ax, d, h)
            ax.set_ylabel(f"{a} (um)")
            if ax.get_legend_handles_labels()[0]:
                ax.legend(fontsize=7, loc="best")
        grid[0, 0].set_title("contribution of each accepted term", fontsize=9)
        grid[-1, 0].set_xlabel("time (h)")
        fig.tight_layout()
        fig.savefig(out_dir / "contributions.png", dpi=100)
        plt.close(fig)
        names.append("contributions.png")
    if validations:
        names.append(_validation_figure(plt, validations, out_dir, tail))
    return names


def _validation_figure(plt, validations: Sequence[Validation], out_dir: Path, tail: str) -> str:
    axes = list(validations[0].after.axes)
    fig, grid = plt.subplots(len(axes), len(validations), figsize=(min(4 * len(validations), 16) + 2, 2.4 * len(axes)),
                             squeeze=False, sharey="row")
    for c, v in enumerate(validations):
        h = (v.after.time_s - v.after.time_s[0]) / 3600.0
        for r, a in enumerate(axes):
            ax = grid[r, c]
            i = axes.index(a)
            if v.settings.get("initial_state") == "fit":  # the hour its initial state is fitted on
                ax.axvspan(0.0, min(INITIAL_FIT_S / 3600.0, float(h[-1]) if h.size else 0.0), color="0.9", lw=0,
                           label="initial state fitted here")
            ax.plot(h, v.after.measured[i], color="0.3", lw=0.8, label="measured")
            ax.plot(h, v.before.estimated[i], color="C0", lw=1.0, label="identified")
            ax.plot(h, v.after.estimated[i], color="C3", lw=1.0, ls="--", label="written")
            if r == 0:
                ax.set_title(v.label, fontsize=8)
            if c == 0:
                ax.set_ylabel(f"{a} (um)")
            if r == len(axes) - 1:
                ax.set_xlabel("hours from its start")
    _legend(grid, fontsize=6)
    fig.suptitle("validation: recordings never fitted, as cncgw estimate gives them" + tail, fontsize=9)
    fig.tight_layout()
    fig.savefig(out_dir / "validation.png", dpi=100)
    plt.close(fig)
    return "validation.png"


def _labels(d: Diagnosis) -> list[str]:
    return list(d.stack.labels)


def _zero_at_start(st, pred: np.ndarray, meas: np.ndarray) -> np.ndarray:
    """Per recording, the constant that puts ``pred`` on the measured zero of its first windows."""
    out = np.zeros(st.n)
    for a, b in st.bounds:
        ok = np.flatnonzero(np.isfinite(meas[a:b]))[:10]
        if ok.size:
            out[a:b] = float(np.mean(meas[a:b][ok] - pred[a:b][ok]))
    return out
