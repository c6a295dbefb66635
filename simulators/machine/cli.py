"""``cncgw simulate`` actions of the simulated machine: ``record``, ``plot``, ``list``."""

from __future__ import annotations

import argparse
import dataclasses

from gateway.errors import SimulationError, UsageError


def add_actions(actions: argparse._SubParsersAction) -> None:
    """Add this part's actions to ``cncgw simulate``."""
    rec = actions.add_parser(
        "record", help="run a scenario offline and write its recording and ground truth",
        description="Run a scenario as fast as possible and write DIR/<run>.csv (the recording the gateway "
                    "reads: time_s, the nine factors, measured displacement x_um y_um z_um with sensor noise, "
                    "room_c and cabinet_c when the scenario has those thermometers) and DIR/<run>.truth.csv (noiseless "
                    "displacement, node temperatures, heat per source, each effect's contribution; the "
                    "gateway never reads it).")
    rec.add_argument("scenario", metavar="SCENARIO", help="a bundled scenario's name or a scenario TOML file")
    rec.add_argument("-o", "--out", metavar="DIR", required=True, help="output directory (created if missing)")
    rec.add_argument("--seed", type=int, default=None, help="sensor-noise seed instead of the scenario's")
    rec.add_argument("--variant", type=int, default=None, metavar="N",
                     help="plant variant instead of the scenario's [plant] variant: 0 the nominal machine, N > 0 "
                          "its gains and time constants perturbed by seed N (+-30 %%; cncgw simulate list --variant N "
                          "shows them)")
    rec.add_argument("--probes-every-h", type=float, default=None, metavar="H",
                     help="write the recording a gateway without displacement sensors exports from a CNC probing "
                          "every H hours: no displacement columns, the probes in probe_* columns")
    rec.add_argument("--probe-sd-um", type=float, default=0.3, metavar="UM",
                     help="with --probes-every-h: the probes' noise and stated uncertainty (default 0.3 um)")
    rec.add_argument("--no-progress", action="store_true", help="no progress bar")
    rec.set_defaults(func=run_record)

    plot = actions.add_parser(
        "plot", help="plot factors and displacement of a scenario or a recording",
        description="Plot the per-minute factors and the displacement over time: of a recording "
                    "(*.csv, with its truth file when it lies beside it) or of a scenario run on the spot.")
    plot.add_argument("source", metavar="SCENARIO_OR_CSV", help="a recording CSV, a scenario name or TOML file")
    plot.add_argument("-o", "--out", metavar="FILE.png", required=True, help="the PNG to write")
    plot.set_defaults(func=run_plot)

    lst = actions.add_parser("list", help="list the bundled scenarios (and the switchable effects)",
                             description="List the bundled scenarios with their length and description.")
    lst.add_argument("--effects", action="store_true", help="also list every switchable effect's parameters")
    lst.add_argument("--variant", type=int, default=None, metavar="N",
                     help="also list plant variant N's structure and the factor drawn for every parameter")
    lst.set_defaults(func=run_list)


def run_record(args: argparse.Namespace) -> int:
    """Run one scenario offline and write its two files."""
    from simulators.machine.run import simulate, write_run
    from simulators.machine.scenario import load_scenario

    scenario = load_scenario(args.scenario)
    if args.seed is not None:
        if args.seed < 0:
            raise UsageError(f"--seed: expected an integer >= 0, got {args.seed}")
        scenario = dataclasses.replace(scenario, seed=args.seed)
    if args.variant is not None:
        if args.variant < 0:
            raise UsageError(f"--variant: expected an integer >= 0 (0: the nominal machine), got {args.variant}")
        scenario = dataclasses.replace(scenario, variant=args.variant)
    every_h = args.probes_every_h
    if every_h is not None and not (0 < every_h <= scenario.duration_h and 0 < args.probe_sd_um <= 50):
        raise UsageError(f"--probes-every-h {every_h:g} --probe-sd-um {args.probe_sd_um:g}: expected an interval "
                         f"in (0, {scenario.duration_h:g}] h (the run's length) and an uncertainty in (0, 50] um")
    result = simulate(scenario, progress=not args.no_progress)
    try:
        rec, truth = write_run(result, args.out, probe_every_s=None if every_h is None else every_h * 3600.0,
                               probe_sd_um=args.probe_sd_um)
    except OSError as exc:
        raise SimulationError(f"{args.out}: cannot write the recording: {exc}") from None
    peak = result.peak_um()
    print(f"wrote {rec} ({len(result.time_s)} rows of {result.machine.window_s:g} s, "
          f"{scenario.duration_h:g} h)")
    print(f"wrote {truth} (ground truth: not for the gateway)")
    print("peak displacement (noiseless): " + ", ".join(f"{a} {v:+.2f} um" for a, v in peak.items()))
    if scenario.variant:
        from simulators.machine.variants import plant_variant

        print(plant_variant(scenario.variant).summary())
    if scenario.viscous_drag_scale != 1.0:
        print(f"viscous drag x{scenario.viscous_drag_scale:g} (spindle and feed axes: torque and heat)")
    return 0


def run_plot(args: argparse.Namespace) -> int:
    """Plot a recording or a scenario."""
    from simulators.machine.plot import load_plot_data, plot

    print(f"wrote {plot(load_plot_data(args.source), args.out)}")
    return 0


def run_list(args: argparse.Namespace) -> int:
    """Print the bundled scenarios."""
    from simulators.machine.effects import describe_effects
    from simulators.machine.scenario import bundled_scenarios, load_scenario

    names = bundled_scenarios()
    width = max(len(n) for n in names)
    for name in names:
        sc = load_scenario(name)
        print(f"{name:<{width}}  {sc.duration_h:5.1f} h  {sc.description}")
    if args.effects:
        print()
        print(describe_effects())
    if args.variant is not None:
        from simulators.machine.variants import plant_variant

        if args.variant < 0:
            raise UsageError(f"--variant: expected an integer >= 0 (0: the nominal machine), got {args.variant}")
        print()
        print("\n".join(plant_variant(args.variant).describe()))
    return 0
