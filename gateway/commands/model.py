"""``cncgw model``: ``show`` what a model file says; ``envelope`` computes its plausibility envelope.

``envelope`` is for a model written before identification recorded one, or one checked on more recordings.
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

from gateway.commands._common import add_recording_options, load_model_for, read_recordings
from gateway.identify.api import identification_summary
from gateway.model import load_model, save_model
from gateway.model.correlation import describe_correlation
from gateway.model.coverage import describe_coverage
from gateway.model.envelope import describe_envelope, envelope_of
from gateway.prepare import prepare
from gateway.profile import load_profile


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Add ``cncgw model``."""
    p = sub.add_parser("model", help="inspect model files")
    msub = p.add_subparsers(dest="model_command", metavar="ACTION", required=True)
    show = msub.add_parser("show", help="print every path: structure, static gain and K, time constants")
    show.add_argument("model", metavar="MODEL", help="model file (TOML)")
    show.set_defaults(func=run_show)
    env = msub.add_parser("envelope", help="compute the model's plausibility envelope from recordings and write it",
                          description="Compute the range of displacement the given recordings support (per axis "
                                      "the largest |displacement| measured or predicted, the largest predicted "
                                      "change per window) and write it as the model's [envelope]; cncgw run "
                                      "holds the offsets beyond it. Give the identification experiments (each "
                                      "starting in thermal equilibrium), and any recording the model was "
                                      "checked on; the envelope is computed over all of them and replaces the "
                                      "model's.")
    env.add_argument("--profile", required=True, metavar="PROFILE", help="machine profile (TOML)")
    env.add_argument("model", metavar="MODEL", help="model file (TOML)")
    env.add_argument("recordings", nargs="+", metavar="RECORDING", help="recordings with measured displacement")
    env.add_argument("-o", "--output", metavar="OUT", help="file to write (default: MODEL, replaced atomically)")
    add_recording_options(env)
    env.set_defaults(func=run_envelope)


def run_show(args: argparse.Namespace) -> int:
    """Print the model's paths."""
    model = load_model(args.model)
    print(f"model {args.model}: machine {model.machine or '?'}, axes {', '.join(model.axes)}, "
          f"{len(model.factors)} factors" + (f", {len(model.inputs)} derived inputs" if model.inputs else ""))
    for inp in model.inputs:  # added by diagnosis: computed from recorded columns
        print(f"derived input {inp.name}: {inp.describe()}" + (f" ({inp.note})" if inp.note else ""))
    info = dict(model.info)
    if info.get("method"):
        print(f"identified with the {info['method']} method from {', '.join(info.get('experiments', []))}")
    print("reference (idle) levels: " + ", ".join(f"{f} {v:.4g} {model.units.get(f, '')}".rstrip()
                                                 for f, v in model.reference.items()))
    print("\n".join(identification_summary(model)))
    print("\n".join(describe_envelope(model.envelope)))
    print("\n".join(describe_coverage(model.coverage, model.units)))
    print("\n".join(describe_correlation(dict(model.gain_correlation))))
    return 0


def run_envelope(args: argparse.Namespace) -> int:
    """Compute the envelope over the recordings, write the model with it."""
    profile = load_profile(args.profile)
    model, path = load_model_for(profile, args.model)
    recs = read_recordings(args.recordings, profile, period_s=args.period_s, require_displacement=True)
    windows = {r.period_s for r in recs}
    if len(windows) != 1:
        from gateway.errors import RecordingError

        raise RecordingError("the recordings have different window lengths: "
                             + ", ".join(f"{r.source} {r.period_s:g} s" for r in recs))
    preps = [prepare(r, factors=model.factors, axes=model.axes, initial="first", gap_policy=args.gap_policy,
                     inputs=model.inputs) for r in recs]
    env = envelope_of(model, ((p.du, p.y) for p in preps), window_s=windows.pop(),
                      source=f"cncgw model envelope: {len(recs)} recordings")
    out = Path(args.output) if args.output else path
    save_model(replace(model, envelope=env), out)
    for line in ["before: " + x for x in describe_envelope(model.envelope)] + describe_envelope(env):
        print(line)
    print(f"wrote {out}")
    return 0
