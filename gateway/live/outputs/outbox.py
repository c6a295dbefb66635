"""The MQTT output's outbox: every window's messages, durable before they are sent, and how far the broker has them.

SQLite in WAL mode beside the records (``DATA/mqtt-outbox.sqlite``): a window's messages are one row,
committed with ``synchronous=FULL`` on the window closer's thread, so a broker outage or a crash loses
nothing the records store has. ``acked_through`` is the last window whose every message the broker has
acknowledged (PUBACK), persisted as it advances: after a restart sending resumes at the next window (a
window sent but not yet acknowledged when the gateway stopped is sent again; consumers drop the duplicate
by window id). Acknowledged rows older than :data:`KEEP_ACKED` windows are pruned.
"""

from __future__ import annotations

import json
import sqlite3
import threading
from pathlib import Path

from gateway.errors import GatewayError

OUTBOX_NAME = "mqtt-outbox.sqlite"
KEEP_ACKED = 1440  # a day of one-minute windows stays readable after it was sent

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS outbox (window INTEGER PRIMARY KEY, end_s REAL NOT NULL, messages TEXT NOT NULL);
"""

Message = tuple[str, bytes]


class Outbox:
    """See the module docstring. Thread-safe: the closer appends, the sender reads and acknowledges."""

    def __init__(self, path: str | Path, *, machine: str) -> None:
        self.path = Path(path)
        self._lock = threading.Lock()
        from gateway.record_store import private_file

        private_file(self.path)  # 0600 like the records: the same machine's data
        try:
            self._db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=FULL")
            self._db.executescript(_SCHEMA)
            meta = dict(self._db.execute("SELECT key, value FROM meta").fetchall())
        except sqlite3.DatabaseError as exc:
            raise GatewayError(f"{self.path}: not a readable MQTT outbox: {exc}") from None
        self.fresh = not meta
        if self.fresh:
            self._db.execute("INSERT INTO meta VALUES ('machine', ?)", (machine,))
        elif meta.get("machine") != machine:
            raise GatewayError(f"{self.path}: this outbox is machine {meta.get('machine')!r}'s, not {machine!r}: "
                               "use the machine's own data directory")
        acked = meta.get("acked_through")
        self.acked_through: int | None = None if acked is None else int(acked)
        row = self._db.execute("SELECT MAX(window) FROM outbox").fetchone()
        self.last_window: int | None = row[0]

    def append(self, window: int, end_s: float, messages: list[Message]) -> bool:
        """Store one window's messages durably; ``False`` if that window is stored already."""
        body = json.dumps([[t, p.decode()] for t, p in messages], separators=(",", ":"))
        with self._lock:
            cur = self._db.execute("INSERT OR IGNORE INTO outbox VALUES (?, ?, ?)", (window, end_s, body))
            if cur.rowcount and (self.last_window is None or window > self.last_window):
                self.last_window = window
            return bool(cur.rowcount)

    def after(self, window: int | None, limit: int) -> list[tuple[int, list[Message]]]:
        """Up to ``limit`` stored windows after ``window`` (all when ``None``), in window order."""
        with self._lock:
            rows = self._db.execute("SELECT window, messages FROM outbox WHERE window > ? ORDER BY window LIMIT ?",
                                    (-(2**62) if window is None else window, limit)).fetchall()
        return [(w, [(t, p.encode()) for t, p in json.loads(m)]) for w, m in rows]

    def pending(self) -> int:
        """Windows stored and not yet acknowledged."""
        with self._lock:
            return int(self._db.execute("SELECT COUNT(*) FROM outbox WHERE window > ?",
                                        (-(2**62) if self.acked_through is None else self.acked_through,)
                                        ).fetchone()[0])

    def ack_through(self, window: int) -> None:
        """The broker has every message of every stored window up to ``window``: persist it, prune old rows."""
        with self._lock:
            if self.acked_through is not None and window <= self.acked_through:
                return
            self._db.execute("BEGIN IMMEDIATE")
            self._db.execute("INSERT OR REPLACE INTO meta VALUES ('acked_through', ?)", (str(window),))
            self._db.execute("DELETE FROM outbox WHERE window <= ?", (window - KEEP_ACKED,))
            self._db.execute("COMMIT")
            self.acked_through = window

    def close(self) -> None:
        """Close the file (idempotent)."""
        with self._lock:
            if self._db is not None:
                self._db.close()
                self._db = None  # type: ignore[assignment]
