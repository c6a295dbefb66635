"""``cncgw``: the command line.

Each command lives in its own module exposing ``add_parser(subparsers)``; the parser it adds carries a
``run(args) -> int`` as its default ``func``. User mistakes (a :class:`~gateway.errors.GatewayError`)
become one line per problem on stderr and a non-zero exit status, never a traceback.
"""

from __future__ import annotations

import argparse
import errno
import importlib
import logging
import sys
from collections.abc import Sequence

from gateway import __version__
from gateway.errors import GatewayError, exit_codes_text

#: command modules, in the order ``cncgw --help`` lists them
COMMAND_MODULES = (
    "gateway.commands.profile",
    "gateway.commands.identify",
    "gateway.commands.plan",
    "gateway.commands.estimate",
    "gateway.commands.diagnose",
    "gateway.commands.model",
    "gateway.commands.record",
    "gateway.commands.run",
    "gateway.commands.audit",
    "simulators.cli",
    "gateway.commands.demo",
)


def _command_name(module: str) -> str:
    return "simulate" if module == "simulators.cli" else module.rsplit(".", 1)[1]


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The ``cncgw`` parser with every command module's sub-parser, or only ``command``'s.

    Only the command being run is imported: ``cncgw run`` must not pay for identification's scipy
    imports (2-3 s on a busy edge PC) before its first heartbeat reaches the CNC.
    """
    parser = argparse.ArgumentParser(
        prog="cncgw",
        description="Estimate and compensate CNC machine-tool thermal deformation from CNC signals.",
        epilog=exit_codes_text() + "\n\ncncgw COMMAND --help: each command's options.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"cncgw {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv: debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMAND_MODULES:
        if command is None or _command_name(name) == command:
            importlib.import_module(name).add_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``cncgw`` with ``argv``; return the exit status."""
    console = argv is None  # the process ends with this call (console script, python -m gateway.cli)
    argv = list(sys.argv[1:] if argv is None else argv)
    first = next((a for a in argv if not a.startswith("-")), None)  # the top level's options take no value
    known = {_command_name(m) for m in COMMAND_MODULES}
    parser = build_parser(first if first in known else None)
    args = parser.parse_args(argv)
    args.console = console
    logging.basicConfig(
        level=[logging.WARNING, logging.INFO, logging.DEBUG][min(args.verbose, 2)],
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    try:
        return int(args.func(args) or 0)
    except GatewayError as exc:
        for line in str(exc).splitlines() or [type(exc).__name__]:
            print(f"cncgw: error: {line}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print("cncgw: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        return 141
    except OSError as exc:  # an output path in a folder that does not exist, a file where a folder goes, ...
        hint = {errno.ENOENT: " (an output's folder must exist)",
                errno.EEXIST: " (a file where a directory is expected)"}.get(exc.errno, "") if exc.filename else ""
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"cncgw: error: {where}{exc.strerror or exc}{hint}", file=sys.stderr)
        logging.getLogger("gateway").debug("the error's traceback", exc_info=True)  # -vv
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
