"""The report's figures: fit with located windows, residual before and after, spectrum, contributions."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gateway.diagnose.api import Diagnosis
from gateway.diagnose.locate import spectrum


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


def write_figures(d: Diagnosis, out_dir: Path) -> list[str]:
    """Write the PNGs into ``out_dir``; return their file names."""
    plt = _plt()
    st = d.stack
    h = _hours(d)
    axes = [a for a in d.model.axes if a in d.findings]
    names = []
    after = {a: sum((t.contribution for t in d.result.terms.get(a, [])), np.zeros(st.n)) for a in axes}

    fig, grid = plt.subplots(len(axes), 1, figsize=(11, 2.8 * len(axes)), sharex=True, squeeze=False)
    for k, a in enumerate(axes):
        ax = grid[k, 0]
        i = d.model.axes.index(a)
        f = d.findings[a]
        meas = st.base[i] + f.residual
        ax.plot(h, meas, color="0.3", lw=0.8, label="measured (zero at each start)")
        ax.plot(h, st.base[i], color="C0", lw=1.2, label="model before")
        if after[a].any():
            ax.plot(h, st.base[i] + after[a], color="C3", lw=1.2, ls="--", label="model after")
        for w in f.windows:
            ax.axvspan(h[w.start], h[w.stop - 1], color="C1", alpha=0.15, lw=0)
        for s in f.steps:
            ax.axvline(h[s.index], color="C4", lw=1.0)
        _separators(ax, d, h)
        ax.set_ylabel(f"{a} (um)")
    grid[0, 0].legend(fontsize=7, loc="best")
    grid[0, 0].set_title("measured vs model before and after; shaded: residual outside its noise band; "
                         "violet: sensor steps", fontsize=9)
    grid[-1, 0].set_xlabel("time (h, recordings end to end)")
    fig.tight_layout()
    fig.savefig(out_dir / "fit.png", dpi=100)
    plt.close(fig)
    names.append("fit.png")

    fig, grid = plt.subplots(len(axes), 1, figsize=(11, 2.4 * len(axes)), sharex=True, squeeze=False)
    for k, a in enumerate(axes):
        ax = grid[k, 0]
        held = d.result.held.get(a)
        if held is not None:
            i = d.model.axes.index(a)
            r = st.y[i][held.rows] - st.base[i][held.rows]
            ax.plot(h[held.rows], r - held.before, color="C0", lw=0.8, label="before (held out)")
            ax.plot(h[held.rows], r - held.after, color="C3", lw=0.8, label="after (held out)")
        ax.axhline(0, color="k", lw=0.5)
        band = d.findings[a].noise.band_um
        ax.axhspan(-band, band, color="0.85", lw=0)
        _separators(ax, d, h)
        ax.set_ylabel(f"{a} residual (um)")
    grid[0, 0].legend(fontsize=7, loc="best")
    grid[0, 0].set_title("held-out residual (each block predicted from the others; grey: noise band)", fontsize=9)
    grid[-1, 0].set_xlabel("time (h)")
    fig.tight_layout()
    fig.savefig(out_dir / "residual.png", dpi=100)
    plt.close(fig)
    names.append("residual.png")

    fig, grid = plt.subplots(1, len(axes), figsize=(4 * len(axes), 3.2), squeeze=False)
    for k, a in enumerate(axes):
        ax = grid[0, k]
        f = d.findings[a]
        for label, r, color in (("before", f.residual, "C0"), ("after", f.residual - after[a], "C3")):
            fr, p = spectrum(st, r)
            if fr.size > 1:
                ax.loglog(1.0 / fr[1:], p[1:], color=color, lw=0.8, label=label)
        for ln in f.lines:
            ax.axvline(ln.period_h, color="C2", lw=0.8, ls="--")
        ax.set_xlabel("period (h)")
        ax.set_title(f"{a} residual spectrum", fontsize=9)
    grid[0, 0].set_ylabel("power (um^2)")
    grid[0, 0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out_dir / "spectrum.png", dpi=100)
    plt.close(fig)
    names.append("spectrum.png")

    if any(d.result.terms.get(a) for a in axes):
        fig, grid = plt.subplots(len(axes), 1, figsize=(11, 2.2 * len(axes)), sharex=True, squeeze=False)
        for k, a in enumerate(axes):
            ax = grid[k, 0]
            for t in d.result.terms.get(a, []):
                if not t.trial.hypothesis.artefact:
                    ax.plot(h, t.contribution, lw=1.0, label=t.trial.hypothesis.key)
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
    return names
