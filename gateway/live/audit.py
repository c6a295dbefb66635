"""The audit log and the alarms: every value written (or, in a dry run, that would have been), every event.

``DIR/audit.sqlite`` (SQLite WAL, ``synchronous=FULL``, append-only, mode 0600) beside the record store:

- ``writes``: one row per compensation write: clock and wall time, the window it follows, the mode
  (``write`` or ``dry-run``), per axis the estimate, the target (sign applied), the offset commanded after
  the limits, the offset the CNC reports applied (read back), whether they matched, the CNC's status word;
- ``events``: alarms raised and cleared, gaps filled by the gap policy, starts and stops, CNC (re)syncs.

:class:`Alarms` keeps the active alarms (thread-safe), logs each transition once and records it as an event.
"""

from __future__ import annotations

import json
import logging
import math
import sqlite3
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path

from gateway.strict_json import nan_to_none

log = logging.getLogger("gateway.live")

AUDIT_NAME = "audit.sqlite"

_SCHEMA = """
CREATE TABLE IF NOT EXISTS writes (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    t_s REAL NOT NULL,
    wall_s REAL NOT NULL,
    window INTEGER,
    mode TEXT NOT NULL,
    verified INTEGER NOT NULL,
    status INTEGER,
    body TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS events (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    t_s REAL NOT NULL,
    wall_s REAL NOT NULL,
    kind TEXT NOT NULL,
    name TEXT NOT NULL,
    message TEXT NOT NULL
);
"""


@dataclass(frozen=True, kw_only=True)
class WriteEntry:
    """One audited write (``mode`` ``"write"``: sent to the CNC and read back; ``"dry-run"``: not sent)."""

    t_s: float
    window: int | None
    mode: str
    estimate_um: Mapping[str, float]
    target_um: Mapping[str, float]
    commanded_um: Mapping[str, float]
    applied_um: Mapping[str, float]
    verified: bool
    status: int | None = None
    note: str = ""
    wall_s: float = field(default_factory=time.time)


class AuditLog:
    """The append-only audit file; see the module docstring. Thread-safe; ``path=None`` keeps it in memory."""

    def __init__(self, path: str | Path | None, *, read_only: bool = False) -> None:
        """Open (create) the audit file, or ``read_only`` an existing one.

        Read-only: nothing written, no schema (``cncgw audit`` beside a running gateway).
        """
        self.path = Path(path) if path is not None else None
        self._lock = threading.Lock()
        if read_only:
            assert self.path is not None, "a read-only audit log is a file"
            self._db: sqlite3.Connection | None = sqlite3.connect(
                f"{self.path.resolve().as_uri()}?mode=ro", uri=True, check_same_thread=False)
            return
        if self.path is not None:
            from gateway.record_store import private_file

            private_file(self.path)  # 0600: what was written to a machine is nobody else's business
        self._db = sqlite3.connect(
            ":memory:" if path is None else str(path), check_same_thread=False, isolation_level=None)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=FULL")
        self._db.executescript(_SCHEMA)

    def write(self, e: WriteEntry) -> None:
        body = json.dumps(nan_to_none({"estimate_um": dict(e.estimate_um), "target_um": dict(e.target_um),
                                  "commanded_um": dict(e.commanded_um), "applied_um": dict(e.applied_um),
                                  "note": e.note}), separators=(",", ":"), allow_nan=False)
        with self._lock:
            if self._db is None:
                return
            self._db.execute("INSERT INTO writes (t_s, wall_s, window, mode, verified, status, body) VALUES "
                             "(?, ?, ?, ?, ?, ?, ?)", (e.t_s, e.wall_s, e.window, e.mode, int(e.verified), e.status,
                                                       body))

    def event(self, t_s: float, kind: str, name: str, message: str) -> None:
        with self._lock:
            if self._db is None:
                return
            self._db.execute("INSERT INTO events (t_s, wall_s, kind, name, message) VALUES (?, ?, ?, ?, ?)",
                             (t_s, time.time(), kind, name, message))

    def writes(self) -> Iterator[WriteEntry]:
        """Every audited write, oldest first."""
        with self._lock:
            rows = [] if self._db is None else self._db.execute(
                "SELECT t_s, wall_s, window, mode, verified, status, body FROM writes ORDER BY id").fetchall()
        for t_s, wall_s, window, mode, verified, status, body in rows:
            b = json.loads(body)
            nums = {k: {a: (math.nan if v is None else v) for a, v in b[k].items()}
                    for k in ("estimate_um", "target_um", "commanded_um", "applied_um")}
            yield WriteEntry(t_s=t_s, wall_s=wall_s, window=window, mode=mode, verified=bool(verified),
                             status=status, note=b.get("note", ""), **nums)

    def events(self) -> list[tuple[float, str, str, str]]:
        """``(t_s, kind, name, message)`` of every event, oldest first."""
        with self._lock:
            if self._db is None:
                return []
            return [tuple(r) for r in self._db.execute(  # type: ignore[misc]
                "SELECT t_s, kind, name, message FROM events ORDER BY id").fetchall()]

    def close(self) -> None:
        with self._lock:
            if self._db is not None:
                self._db.close()
                self._db = None


@dataclass(frozen=True, kw_only=True, slots=True)
class Alarm:
    """An active alarm: what, since when (clock time), how often it was raised again while active."""

    name: str
    message: str
    since_s: float
    repeats: int = 0


class Alarms:
    """The gateway's active alarms; raising and clearing are logged once per transition and audited."""

    def __init__(self, *, audit: AuditLog | None = None, on_change: Callable[[], None] | None = None) -> None:
        self._lock = threading.Lock()
        self._active: dict[str, Alarm] = {}
        self._audit = audit
        self._on_change = on_change
        self.raised_total = 0

    def raise_(self, name: str, message: str, t_s: float) -> None:
        with self._lock:
            a = self._active.get(name)
            if a is not None:
                self._active[name] = replace(a, message=message, repeats=a.repeats + 1)
                if a.message == message:
                    return
            else:
                self._active[name] = Alarm(name=name, message=message, since_s=t_s)
                self.raised_total += 1
        if a is None:
            log.warning("ALARM %s: %s", name, message)
        else:
            log.info("alarm %s still active: %s", name, message)
        if self._audit is not None:
            self._audit.event(t_s, "alarm", name, message)
        if self._on_change is not None:
            self._on_change()

    def clear(self, name: str, t_s: float, message: str = "") -> None:
        with self._lock:
            a = self._active.pop(name, None)
        if a is None:
            return
        text = message or f"cleared after {t_s - a.since_s:.0f} s"
        log.warning("alarm %s cleared: %s", name, text)
        if self._audit is not None:
            self._audit.event(t_s, "clear", name, text)
        if self._on_change is not None:
            self._on_change()

    def active(self) -> list[Alarm]:
        with self._lock:
            return list(self._active.values())

    def __contains__(self, name: str) -> bool:
        with self._lock:
            return name in self._active
