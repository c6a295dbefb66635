"""``cncgw model show MODEL``: what a model file says, as a table."""

from __future__ import annotations

import argparse

from gateway.identify.api import identification_summary
from gateway.model import load_model


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Add ``cncgw model``."""
    p = sub.add_parser("model", help="inspect model files")
    msub = p.add_subparsers(dest="model_command", metavar="ACTION", required=True)
    show = msub.add_parser("show", help="print every path: structure, static gain and K, time constants")
    show.add_argument("model", metavar="MODEL", help="model file (TOML)")
    show.set_defaults(func=run_show)


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
    return 0
