"""``cncgw profile check PROFILE``: validate a machine profile and print a summary.

``cncgw profile new NAME``: write ``NAME.toml``, the template with every key commented, named for the machine.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

from gateway.errors import GatewayError
from gateway.profile import Profile, format_summary, load_profile


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Add ``cncgw profile``."""
    p = sub.add_parser("profile", help="check machine profiles")
    psub = p.add_subparsers(dest="profile_command", metavar="ACTION", required=True)
    check = psub.add_parser("check", help="validate a profile and print a summary",
                            description="Validate a machine profile: every problem is listed with file, "
                                        "line, key, bad value and what was expected.")
    check.add_argument("profile", metavar="PROFILE", help="profile TOML file, or a bundled profile's name (sim-vmc)")
    check.set_defaults(func=run_check)
    new = psub.add_parser("new", help="write a new profile: the commented template, named for the machine",
                          description="Write NAME.toml (or --output): the bundled template with every key, its "
                                      "default and its meaning, machine.name and the model file set to NAME. "
                                      "Then fill in the factors, devices and channels and run cncgw profile check.")
    new.add_argument("name", metavar="NAME", help="the machine's name: letters, digits, - and _ (e.g. vmc-3)")
    new.add_argument("-o", "--output", metavar="FILE", help="where to write it (default: NAME.toml here)")
    new.set_defaults(func=run_new)


def run_check(args: argparse.Namespace) -> int:
    """Check one profile and print its summary; then its model file, if there is one, against it."""
    profile = load_profile(args.profile)
    print(format_summary(profile))
    for note in _unit_slips(profile):
        print(f"cncgw: warning: {profile.path}: {note}", file=sys.stderr)
    if profile.model_path.exists():
        # a unit typed otherwise than the model was identified with (rad/s for rpm) passed here and failed at
        # `estimate` and `run` (exit 5): say it now, with the same message
        from gateway.commands._common import load_model_for

        load_model_for(profile, None)
    return 0


def _unit_slips(profile: Profile) -> list[str]:
    """Legal values that look like milliseconds typed for seconds: said, not refused (a slow OPC UA poll is real)."""
    s, out = profile.sampling, []
    if s.fast_period_s >= 1.0:
        out.append(f"sampling.fast_period_s = {s.fast_period_s:g} s: {s.samples_per_window} samples a window; the fast "
                   f"period is in seconds: if you meant {s.fast_period_s:g} ms, write {s.fast_period_s / 1000:g}")
    if s.window_s >= 3600.0:
        out.append(f"sampling.window_s = {s.window_s:g} s ({s.window_s / 3600:.3g} h): a window is normally a "
                   f"minute (60), shorter than the fastest thermal time constants; if you meant {s.window_s:g} ms, "
                   f"write {s.window_s / 1000:g}")
    return out


_MACHINE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_-]{0,63}")


def run_new(args: argparse.Namespace) -> int:
    """Write a commented copy of the template for machine ``args.name``; never overwrite a file."""
    from gateway import BUNDLED

    name = args.name
    if not _MACHINE_NAME.fullmatch(name):
        raise GatewayError(f'profile new: machine name "{name}": expected 1 to 64 letters, digits, - or _, starting '
                           "with a letter or digit (it names files, MQTT topics and the systemd instance)")
    out = Path(args.output) if args.output else Path(f"{name}.toml")
    if out.exists():
        raise GatewayError(f"{out}: already exists: choose another --output (a profile is never overwritten)")
    text = (BUNDLED / "template.toml").read_text(encoding="utf-8")
    head = f"# Profile of machine {name}, written by `cncgw profile new {name}` from the bundled template.\n"
    text = head + text.replace('name = "my-machine"', f'name = "{name}"', 1).replace(
        'file = "my-machine.model.toml"', f'file = "{name}.model.toml"', 1)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    load_profile(tmp)  # what is written is a valid profile
    tmp.replace(out)
    print(f"wrote {out}: the template for machine {name}; fill in factors, [devices.*] and [channels.*], then "
          f"`cncgw profile check {out}`")
    return 0
