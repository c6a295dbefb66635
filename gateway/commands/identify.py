"""``cncgw identify``: experiments in, model file out."""

from __future__ import annotations

import argparse
from pathlib import Path

from gateway import BUNDLED, plotting
from gateway.commands._common import (
    add_recording_options,
    add_split_option,
    check_output,
    fail_if_exists,
    positive_int,
    progress_bar,
    read_recordings,
    refuse_duplicates,
    refuse_writing_over_inputs,
    split_those_with,
)
from gateway.errors import UsageError
from gateway.identify import identify
from gateway.identify.api import identification_summary
from gateway.identify.joint import CANDIDATES
from gateway.model import save_model
from gateway.profile import Profile, load_profile


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Add ``cncgw identify``."""
    p = sub.add_parser(
        "identify", help="identify a model from experiment recordings",
        description="Identify the thermal model (axis x factor transfer functions) from experiment recordings. "
                    "Each recording must start with the machine in thermal equilibrium (idle, powered long "
                    "enough); its first window is the experiment's initial state.")
    p.add_argument("--profile", required=True, metavar="PROFILE", help="machine profile (TOML)")
    p.add_argument("experiments", nargs="+", metavar="EXPERIMENT", help="experiment recordings (CSV)")
    p.add_argument("-o", "--output", metavar="MODEL", help="model file to write (default: the profile's)")
    p.add_argument("--force", action="store_true",
                   help="replace MODEL if it exists (a gateway running with it picks the new one up at its restart)")
    p.add_argument("--method", choices=("joint", "paper"), default="joint",
                   help="joint (default): all paths of an axis at once, with structure choice and uncertainties; "
                        "paper: the paper's V^-1 separation and steepest descent, as a reference")
    p.add_argument("--structures", type=_structures, default=CANDIDATES, metavar="LIST",
                   help=f"joint method: path structures to choose from (default {','.join(CANDIDATES)})")
    p.add_argument("--no-prune", action="store_true", help="joint method: keep paths whose gain is not significant")
    p.add_argument("--max-iter", type=positive_int, default=3000, metavar="N",
                   help="paper method: steepest-descent iterations per path (default 3000)")
    p.add_argument("--jobs", type=positive_int, default=1, metavar="N",
                   help="joint method: fit the axes in N processes at once (default 1; keep 1 on a PC whose "
                        "gateway is sampling)")
    p.add_argument("--production", nargs="+", default=[], metavar="RUN",
                   help="joint method: production runs with measured displacement, fitted with the experiments "
                        "(each its own offset; factors referred to the experiments' rest levels); displacement "
                        "measured only at probe cycles counts (sparse displacement columns, or the probe_* "
                        "columns cncgw record --export-only writes), each probe weighted by its probe_sd_um")
    p.add_argument("--production-initial", choices=("rest", "fit"), default="rest",
                   help="a production run starts at rest (default: after a night at rest) or warm: fit its "
                        "initial state as free decays")
    p.add_argument("--plot", metavar="PNG", help="also draw measured vs fitted displacement of every experiment")
    add_recording_options(p)
    add_split_option(p)
    p.set_defaults(func=run)


def _structures(text: str) -> tuple[str, ...]:
    structures = tuple(s.strip() for s in text.split(",") if s.strip())
    bad = [s for s in structures if s not in CANDIDATES]
    if bad or not structures:
        raise argparse.ArgumentTypeError(f"{', '.join(bad) or 'empty'}: expected a comma-separated list from "
                                         f"{', '.join(CANDIDATES)}")
    return structures


def _output(args: argparse.Namespace, profile: Profile) -> Path:
    """Where the model goes: -o, else the profile's model file (for a bundled profile: its name, here)."""
    out = Path(args.output) if args.output else profile.model_path
    if not args.output and _inside(out, BUNDLED):
        # a bundled profile's model lives in the installed package: never overwrite it (a root-owned venv
        # would refuse, an editable one would change the repository's reference model)
        out = Path.cwd() / out.name
    return out


def run(args: argparse.Namespace) -> int:
    """Identify, write the model, print the report."""
    if args.plot:
        plotting.require("--plot")
    refuse_writing_over_inputs({"-o": args.output, "--plot": args.plot},
                               [*args.experiments, *args.production, args.profile])
    check_output("-o", args.output)
    check_output("--plot", args.plot)
    profile = load_profile(args.profile)
    out = _output(args, profile)
    # checked before the work: identification takes minutes, and the model a gateway runs is not replaced
    # by accident (a second identify with the profile's default path)
    fail_if_exists(out, args.force)
    structures = args.structures
    recs = read_recordings(args.experiments, profile, period_s=args.period_s, require_displacement=True)
    # a production run may carry its displacement as probe points only (probe_* columns): checked in identify
    prod = read_recordings(args.production, profile, period_s=args.period_s, require_displacement=False)
    if args.split_by:  # a file of several runs (days): each run an experiment or production run of its own
        recs, prod = split_those_with(recs, args.split_by, prod), split_those_with(prod, args.split_by, recs)
    refuse_duplicates([*recs, *prod], profile.factor_names,
                      counts="weighs twice in the fit, as if its conditions had been run twice")
    if prod and args.method != "joint":
        raise UsageError("--production: production runs join the joint method only (--method joint)")
    total = len(profile.axes) * (len(structures) if args.method == "joint" else len(profile.factors))
    update, close = progress_bar(total, f"identify ({args.method})")
    try:
        result = identify(recs, factors=profile.factor_names, axes=profile.axes,
                          units={f.name: f.unit for f in profile.factors}, machine=profile.name,
                          method=args.method, candidates=structures, prune=not args.no_prune,
                          gap_policy=args.gap_policy, paper_max_iter=args.max_iter, jobs=args.jobs,
                          production=prod, production_initial=args.production_initial,
                          progress=lambda m: None if "pruning" in m else update(m))
    finally:
        close()
    save_model(result.model, out)
    print(f"identified {len(result.model.axes)} axes x {len(result.model.factors)} factors from "
          f"{len(recs)} experiment(s)" + (f" and {len(prod)} production run(s)" if prod else "")
          + f" with the {args.method} method in {result.wall_s:.1f} s")
    for line in result.notes:
        print(f"note: {line}")
    for line in result.report:
        print(line)
    print()
    print("\n".join(identification_summary(result.model)))
    print(f"wrote {out}")
    if args.plot:
        from gateway.replay import estimate, plot_estimates

        ests = [estimate(result.model, r, align="offset", gap_policy=args.gap_policy) for r in [*recs, *prod]]
        plot_estimates(ests, args.plot, title=f"{profile.name}: identification fit ({args.method})")
        print(f"wrote {args.plot}")
    if not args.output and _inside(profile.model_path, BUNDLED):
        print(f"note: {profile.name} is a profile bundled with cncgw: its model was written here, not into the "
              f"installed package; pass it on with --model {out}")
    return 0


def _inside(path: Path, folder: Path) -> bool:
    try:
        return path.resolve().is_relative_to(folder.resolve())
    except OSError:
        return False
