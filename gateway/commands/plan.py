"""``cncgw plan``: the next experiments that most reduce the uncertainty of what production uses."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from gateway.commands._common import (
    add_recording_options,
    check_output,
    positive_float,
    positive_int,
    read_recordings,
)
from gateway.errors import UsageError
from gateway.identify import identify
from gateway.plan import LEAD_IN_MIN, plan
from gateway.prepare import prepare
from gateway.profile import load_profile


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Add ``cncgw plan``."""
    p = sub.add_parser(
        "plan", help="propose the next identification experiments for a production schedule",
        description="Identify the experiments, then propose up to --max-experiments more (each at most --max-hours "
                    "long, built from the operating states the production recordings show) that most reduce the "
                    "uncertainty of the production estimate; says how long each runs, what it must reach beyond "
                    "the experiments' coverage, and the uncertainty before and after. With -o DIR on the simulated "
                    "machine's profile, each proposal is also written as a scenario (cncgw simulate record).")
    p.add_argument("--profile", required=True, metavar="PROFILE", help="machine profile (TOML)")
    p.add_argument("experiments", nargs="+", metavar="EXPERIMENT",
                   help="the identification experiments recorded so far (CSV, with displacement)")
    p.add_argument("--production", nargs="+", required=True, metavar="RECORDING",
                   help="production recordings (CSV; factors are enough, e.g. cncgw record --export-only)")
    p.add_argument("--max-experiments", type=positive_int, default=3, metavar="N",
                   help="propose at most N experiments (default 3)")
    p.add_argument("--max-hours", type=positive_float, default=12.0, metavar="H",
                   help="each experiment at most H hours long, rest after it included (default 12)")
    p.add_argument("-o", "--output", metavar="DIR", help="write plan.json (and scenarios on the simulated machine)")
    p.add_argument("--json", action="store_true", help="print the plan as JSON")
    add_recording_options(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Identify, plan, print (and write) the proposals."""
    if args.max_hours * 60.0 <= LEAD_IN_MIN + 60.0:
        raise UsageError(f"--max-hours {args.max_hours:g}: expected more than {(LEAD_IN_MIN + 60.0) / 60:g} h "
                         "(the rest before an experiment and an hour of it)")
    check_output("-o", args.output, directory=True)
    profile = load_profile(args.profile)
    exps = read_recordings(args.experiments, profile, period_s=args.period_s, require_displacement=True)
    prod = read_recordings(args.production, profile, period_s=args.period_s, require_displacement=False)
    factors, axes = profile.factor_names, profile.axes
    result = identify(exps, factors=factors, axes=axes, units={f.name: f.unit for f in profile.factors},
                      machine=profile.name, gap_policy=args.gap_policy)
    model = result.model
    preps = [prepare(r, factors=factors, axes=axes, initial="first", gap_policy=args.gap_policy) for r in exps]
    prods = [prepare(r, factors=factors, axes=axes, initial="reference", reference=model.reference,
                     gap_policy=args.gap_policy) for r in prod]
    out = plan(result, preps, prods, max_experiments=args.max_experiments, max_hours=args.max_hours)
    scenarios = _write_scenarios(out, profile, Path(args.output)) if args.output else {}
    doc = _json(out, scenarios)
    if args.output:
        (Path(args.output) / "plan.json").write_text(json.dumps(doc, indent=2), encoding="utf-8")
    if args.json:
        print(json.dumps(doc, indent=2))
        return 0
    hours = sum(p.n for p in prods) * prods[0].dt_s / 3600.0
    print(f"plan for {profile.name}: {len(exps)} experiments, {len(prod)} production recordings ({hours:.3g} h), "
          f"{len(out.states)} operating states, {out.candidates} candidate experiments")
    print("production estimate's uncertainty from these experiments (gains; RMS over the production windows): "
          + ", ".join(f"{a} {v:.3g} um" for a, v in out.sd_before_um.items()))
    if not out.proposals:
        print("no experiment lowers it by 5 % or more: the experiments cover what production uses")
    for k, p in enumerate(out.proposals):
        print(p.describe())
        if p.reaches:
            print("  must reach: " + "; ".join(p.reaches))
        print("  uncertainty after: " + ", ".join(f"{a} {b:.3g} -> {c:.3g} um" for a, (b, c) in p.sd_um.items()))
        if k in scenarios:
            path, cuts = scenarios[k]
            print(f"  scenario: {path}" + (f" (on the simulated machine {cuts})" if cuts else ""))
    print("operating states of production:")
    for i, s in enumerate(out.states):
        print(f"  state {i + 1}: {s.label} ({s.hours:.3g} h)")
    for n in out.notes:
        print(f"note: {n}")
    if args.output and not scenarios and out.proposals:
        print(f"note: no scenarios written: profile {profile.path} does not read the simulated machine's factors")
    if args.output:
        print(f"wrote {Path(args.output) / 'plan.json'}")
    return 0


def _write_scenarios(out, profile, directory: Path) -> dict[int, Path]:
    directory.mkdir(parents=True, exist_ok=True)
    from simulators.machine.proposal import proposal_scenario, simulatable

    if not simulatable(profile.factor_names):
        return {}
    written = {}
    ref = {f: 0.0 for f in profile.factor_names}
    for k, p in enumerate(out.proposals):
        steps = [({f: v + ref[f] for f, v in s.levels.items()}, minutes) for s, minutes in p.steps]
        text = proposal_scenario(f"plan-{k + 1}", p.describe(), steps, hours=p.hours, lead_in_min=LEAD_IN_MIN,
                                 seed=9100 + k, note="reaches " + ("; ".join(p.reaches) or "nothing beyond coverage"),
                                 cutting=[s.cutting for s, _ in p.steps])
        path = directory / f"plan-{k + 1}.toml"
        path.write_text(text, encoding="utf-8")
        written[k] = (path, _cuts(steps, [s.cutting for s, _ in p.steps]))
    return written


def _cuts(steps, cutting) -> str:
    """The simulated machine's cutting power for each cutting step, for the printed proposal."""
    from simulators.machine.proposal import cutting_kw

    parts = []
    for k, ((levels, _), cut) in enumerate(zip(steps, cutting, strict=True)):
        if cut:
            rpm = levels.get("spindle_speed", 0.0)
            kw, capped = cutting_kw(rpm, levels.get("spindle_i2_sq", 0.0))
            parts.append(f"step {k + 1} cuts {kw:.3g} kW at {rpm:.4g} rpm"
                         + (" (the drive's torque limit there; production's level is beyond it)" if capped else ""))
    return "; ".join(parts)


def _json(out, scenarios) -> dict:
    return {"uncertainty_before_um": out.sd_before_um,
            "proposals": [{"name": p.name, "hours": p.hours, "description": p.describe(),
                           "steps": [{"levels": dict(s.levels), "minutes": m, "label": s.label, "cutting": s.cutting}
                                     for s, m in p.steps],
                           "reaches": list(p.reaches),
                           "uncertainty_um": {a: {"before": b, "after": c} for a, (b, c) in p.sd_um.items()},
                           "cutting": p.cuts,
                           "scenario": str(scenarios[k][0]) if k in scenarios else None,
                           "simulated_cut": scenarios[k][1] if k in scenarios else None}
                          for k, p in enumerate(out.proposals)],
            "states": [{"label": s.label, "hours": s.hours, "levels": dict(s.levels), "cutting": s.cutting}
                       for s in out.states],
            "notes": out.notes}
