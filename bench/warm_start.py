"""How well ``cncgw estimate --initial-state fit`` carries a warm start: a simulated day cut while the machine works.

    .venv/bin/python bench/warm_start.py [--scenario production-day] [--cuts 8,10,12,14] [--plot PNG]

The scenario is simulated (the bundled plant) and cut at each hour of ``--cuts``; each part, which starts warm
with nothing before it, is estimated with the bundled model started at rest and with its initial state fitted
to its first hour (:func:`gateway.replay.estimate`). Printed per cut and axis: the RMS error over the part
(the first hour included, where the fit is scored on what it was fitted to) and over the hours after the first
(what the fitted state carried into), and the fit's share of the rest start's error (same run, same data); last,
the same with the inputs taken from the model's reference levels (``--initial reference --initial-state fit``,
what ``diagnose --validate`` does with a part that works at its first window).
``--plot``: the error of both estimates on the axis that moves most, for every cut.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from gateway.model import load_model  # noqa: E402
from gateway.replay import INITIAL_FIT_S, estimate  # noqa: E402
from simulators.machine import load_scenario, simulate  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenario", default="production-day")
    p.add_argument("--cuts", default="8,10,12,14", help="hours into the scenario where each part starts")
    p.add_argument("--plot", type=Path, help="write a figure of the estimates here (PNG)")
    args = p.parse_args(argv)
    cuts = [float(c) for c in args.cuts.split(",")]
    model = load_model(ROOT / "profiles" / "sim-vmc.model.toml")
    rec = simulate(load_scenario(args.scenario)).recording()
    rows, curves = [], []
    print(f"{args.scenario}, bundled model; RMS um over the part / over the hours after the first")
    print(f"{'cut':>5} {'axis':>4} {'at rest':>16} {'fitted':>16} {'fitted/rest':>12} {'ref. + fitted':>16}")
    for cut in cuts:
        part = rec.slice(round(cut * 3600.0 / rec.period_s), len(rec))
        runs = {state: estimate(model, part, initial_state=state) for state in ("rest", "fit")}
        # a part that works at its first window: what diagnose --validate does (from the reference levels, fitted)
        ref = estimate(model, part, initial="reference", initial_state="fit")
        later = (part.time_s - part.time_s[0]) >= INITIAL_FIT_S
        for i, a in enumerate(model.axes):
            figs = {}
            for state, e in runs.items():
                err = e.measured[i] - e.estimated[i]
                figs[state] = (e.metrics[a].rms_um, float(np.sqrt(np.nanmean(err[later] ** 2))))
            ratio = figs["fit"][1] / figs["rest"][1] if figs["rest"][1] > 0 else float("nan")
            rows.append(ratio)
            err = ref.measured[i] - ref.estimated[i]
            print(f"{cut:5g} {a:>4} {figs['rest'][0]:7.2f} / {figs['rest'][1]:6.2f} "
                  f"{figs['fit'][0]:7.2f} / {figs['fit'][1]:6.2f} {ratio:12.2f} "
                  f"{ref.metrics[a].rms_um:7.2f} / {float(np.sqrt(np.nanmean(err[later] ** 2))):6.2f}")
        curves.append((cut, part, runs))
    print(f"fitted / at rest after the first hour: median {np.nanmedian(rows):.2f} over {len(rows)} cuts x axes")
    if args.plot:
        from gateway.plotting import pyplot

        plt = pyplot()
        i = int(np.argmax([np.nanmax(np.abs(curves[0][2]["rest"].measured[k])) for k in range(len(model.axes))]))
        fig, grid = plt.subplots(1, len(curves), figsize=(4.0 * len(curves), 3.4), squeeze=False, sharey=True)
        for ax, (cut, part, runs) in zip(grid[0], curves, strict=True):
            h = cut + (part.time_s - part.time_s[0]) / 3600.0
            # each run's measured zero is taken against its own estimate (align="start"): errors compare
            ax.plot(h, runs["rest"].residual[i], color="C3", ls="--", label="started at rest")
            ax.plot(h, runs["fit"].residual[i], color="C0", label="state fitted to the first hour")
            ax.axhline(0.0, color="k", lw=0.5)
            ax.axvspan(cut, cut + INITIAL_FIT_S / 3600.0, color="0.9")
            ax.set_title(f"cut at {cut:g} h", fontsize=9)
            ax.set_xlabel("time of day (h)")
        grid[0, 0].set_ylabel(f"{model.axes[i]} measured - estimated (um)")
        grid[0, 0].legend(fontsize=7)
        fig.suptitle(f"{args.scenario} cut while working: error of the estimate started at rest and from a state "
                     "fitted to the first hour (grey: the hour it is fitted on)", fontsize=9)
        fig.tight_layout()
        fig.savefig(args.plot, dpi=110)
        print(f"wrote {args.plot}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
