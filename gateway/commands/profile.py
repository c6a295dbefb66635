"""``cncgw profile check PROFILE``: validate a machine profile and print a summary."""

from __future__ import annotations

import argparse

from gateway.profile import format_summary, load_profile


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Add ``cncgw profile``."""
    p = sub.add_parser("profile", help="check machine profiles")
    psub = p.add_subparsers(dest="profile_command", metavar="ACTION", required=True)
    check = psub.add_parser("check", help="validate a profile and print a summary",
                            description="Validate a machine profile: every problem is listed with file, "
                                        "line, key, bad value and what was expected.")
    check.add_argument("profile", metavar="PROFILE", help="profile TOML file")
    check.set_defaults(func=run_check)


def run_check(args: argparse.Namespace) -> int:
    """Check one profile and print its summary."""
    print(format_summary(load_profile(args.profile)))
    return 0
