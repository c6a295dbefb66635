"""``cncgw demo``: the whole workflow on the bundled simulated machine, in about ten seconds.

1. Simulate the paper's nine identification experiments (12 h each) on the simulated machining center.
2. Identify the model from those recordings (the joint method), as ``cncgw identify`` does.
3. Play validation runs the identification never saw (the paper's spindle-and-feeds run, a 24 h
   production day) and compare the tool-to-table thermal error without compensation with what would be
   left if the CNC applied offsets of minus the estimate.

Today the third step runs offline on the same model and discretisation the live estimator uses; the live
loop (drivers, 2 ms sampler, Modbus compensation writer) is the acquisition and live-gateway work.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from gateway.estimate import estimate
from gateway.identify import identify
from gateway.model import save_model
from gateway.profile import load_profile

PROFILE = Path(__file__).resolve().parents[2] / "profiles" / "sim-vmc.toml"
IDENTIFICATION = ("spindle-1000rpm", "spindle-500rpm", "spindle-400-600rpm", "feed-x-fast", "feed-x-accel",
                  "feed-y-fast", "feed-y-accel", "feed-z-fast", "feed-z-accel")
VALIDATION = ("spindle-feeds", "production-day")


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Add ``cncgw demo``."""
    p = sub.add_parser("demo", help="the workflow end to end on the bundled simulated machine",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("-o", "--out", default="demo-out", metavar="DIR",
                   help="where the recordings, the model and the plot go (default: demo-out)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Simulate, identify, validate; print the table; write the plot."""
    from gateway.commands._common import progress_bar
    from simulators.machine import load_scenario, simulate, write_run

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    profile = load_profile(PROFILE)
    print(f"cncgw demo: the bundled simulated machining center ({PROFILE.name}: "
          f"{len(profile.factors)} factors, axes {', '.join(profile.axes)})\n")

    t0 = time.perf_counter()
    update, close = progress_bar(len(IDENTIFICATION), "simulating")
    train = []
    try:
        for name in IDENTIFICATION:
            result = simulate(load_scenario(name))
            write_run(result, out / "experiments")
            train.append(result.recording())
            update(name)
    finally:
        close()
    hours = sum(len(r) for r in train) / 60
    print(f"1/3 simulated the paper's {len(train)} identification experiments ({hours:.0f} machine hours) in "
          f"{time.perf_counter() - t0:.1f} s -> {out / 'experiments'}/")

    t0 = time.perf_counter()
    ident = identify(train, factors=profile.factor_names, axes=profile.axes,
                     units={f.name: f.unit for f in profile.factors}, machine=profile.name)
    model_path = save_model(ident.model, out / "sim-vmc.model.toml")
    print(f"2/3 identified {len(profile.axes)} x {len(profile.factors)} transfer functions (joint method) in "
          f"{time.perf_counter() - t0:.1f} s -> {model_path}")
    for line in ident.report:
        if line.startswith("axis"):
            print(f"    {line.split(';')[0]}")

    print("3/3 validation runs the identification never saw; error = tool-to-table thermal displacement; "
          "with compensation the CNC applies offsets of minus the estimate\n")
    print(f"    {'run':<16} {'axis':<4} {'max error without':>18} {'with compensation':>18} {'reduction':>10}")
    estimates = []
    for name in VALIDATION:
        sim = simulate(load_scenario(name))
        est = estimate(ident.model, sim.recording("true"))
        estimates.append((name, sim, est))
        for i, a in enumerate(profile.axes):
            true = est.measured[i]
            left = true - est.estimated[i]
            before, after = float(np.max(np.abs(true))), float(np.max(np.abs(left)))
            print(f"    {name:<16} {a:<4} {before:>15.2f} um {after:>15.2f} um {100 * (1 - after / before):>9.0f} %")
    png = out / "demo.png"
    _plot(estimates, png)
    print(f"\nplot: {png}")
    print("offline for now: the live loop (devices, 2 ms sampler, Modbus writer) replaces step 3 when built")
    return 0


def _plot(estimates: list, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, grid = plt.subplots(len(estimates), 1, figsize=(10, 3.6 * len(estimates)), squeeze=False)
    for row, (name, _, est) in zip(grid[:, 0], estimates, strict=True):
        hours = (est.time_s - est.time_s[0]) / 3600
        for i, a in enumerate(est.axes):
            row.plot(hours, est.measured[i], color=f"C{i}", lw=1.2, label=f"{a} without compensation")
            row.plot(hours, est.measured[i] - est.estimated[i], color=f"C{i}", lw=1.2, ls="--",
                     label=f"{a} with compensation")
        row.axhline(0, color="k", lw=0.5)
        row.set_title(f"{name}: tool-to-table thermal error", fontsize=10)
        row.set_ylabel("um")
        row.set_xlabel("time (h)")
        row.legend(fontsize=7, ncol=3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
