"""``cncgw audit``: the audit log of ``cncgw run`` as CSV, to compare a dry run with measurements.

``DATA/audit.sqlite`` keeps each write's values as JSON inside SQLite: readable by the gateway, not by a
person with a spreadsheet. This prints (or writes with ``-o``) one row per audited write: the clock time,
the window, the mode, and per axis the estimate, the target, the offset commanded and the one the CNC
applied; or, with ``--events``, every event (alarms, gaps filled, starts and stops, CNC synchronisations).
The file is opened read-only, so a running gateway's log can be read beside it.
"""

from __future__ import annotations

import argparse
import csv
import io
import sqlite3
import sys
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING

from gateway.commands._common import check_output, fail_if_exists
from gateway.errors import GatewayError, UsageError

if TYPE_CHECKING:
    from gateway.live.audit import AuditLog


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Add ``cncgw audit``."""
    p = sub.add_parser("audit", help="the audit log of cncgw run as CSV (every value written, or in a dry run "
                                     "that would have been)",
                       description="Print the audit log of a cncgw run data directory as CSV: one row per "
                                   "audited write (clock time, window, mode, and per axis the estimate, the "
                                   "target, the offset commanded and the offset the CNC applied), or with "
                                   "--events every event. Compare a dry run's estimates with measurements "
                                   "taken at the same times before setting [compensation] enabled.")
    p.add_argument("--data", required=True, metavar="DIR", help="the data directory given to cncgw run")
    p.add_argument("--events", action="store_true", help="list the events (alarms, gaps, starts, stops) instead")
    p.add_argument("-o", "--output", metavar="CSV", help="write the CSV here (default: standard output)")
    p.add_argument("--force", action="store_true", help="replace the -o file if it exists")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Read the audit log; print or write it as CSV."""
    from gateway.live.audit import AUDIT_NAME, AuditLog

    path = Path(args.data) / AUDIT_NAME
    if not path.is_file():
        raise UsageError(f"{args.data}: no {AUDIT_NAME}: expected the --data directory of cncgw run (or the "
                         "demo's DIR/live)")
    out = Path(args.output) if args.output else None
    if out is not None:
        check_output("-o", args.output)
        fail_if_exists(out, args.force)
    log = None
    try:
        # read-only: never a write, nor a schema, in the file a running gateway appends to
        log = AuditLog(path, read_only=True)
        text = _events_csv(log) if args.events else _writes_csv(log)
    except (sqlite3.Error, ValueError, KeyError) as exc:
        raise GatewayError(f"{path}: not an audit log cncgw can read: {exc}") from None
    finally:
        if log is not None:
            log.close()
    if out is None:
        sys.stdout.write(text)
    else:
        out.write_text(text)
        print(f"wrote {out}", file=sys.stderr)
    return 0


def _iso(t_s: float) -> str:
    return datetime.fromtimestamp(t_s, UTC).isoformat(timespec="seconds").replace("+00:00", "Z")


#: per axis and write, in this order: the WriteEntry fields ``<name>_um``
_VALUES = ("estimate", "target", "commanded", "applied")


def _writes_csv(log: AuditLog) -> str:
    rows = list(log.writes())
    axes: list[str] = []
    for r in rows:
        for a in (*r.estimate_um, *r.commanded_um):
            if a not in axes:
                axes.append(a)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["t_s", "wall_time", "window", "mode", "verified", "status",
                *[f"{a}_{k}_um" for a in axes for k in _VALUES], "note"])
    for r in rows:
        cells = []
        for a in axes:
            cells += [_num(getattr(r, f"{k}_um").get(a)) for k in _VALUES]
        w.writerow([f"{r.t_s:.3f}", _iso(r.wall_s), "" if r.window is None else r.window, r.mode, int(r.verified),
                    "" if r.status is None else r.status, *cells, r.note])
    return buf.getvalue()


def _events_csv(log: AuditLog) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["t_s", "kind", "name", "message"])
    for t_s, kind, name, message in log.events():
        w.writerow([f"{t_s:.3f}", kind, name, message])
    return buf.getvalue()


def _num(v: float | None) -> str:
    return "" if v is None or v != v else f"{v:.4f}"
