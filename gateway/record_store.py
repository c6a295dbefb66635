"""The durable per-window store: SQLite in WAL mode, append-only, one transaction per window.

Why SQLite: it needs no server, a committed transaction survives ``kill -9`` (and, with
``synchronous=FULL``, a power cut), and a crash in the middle of a write leaves the previous state, never
an unreadable file. One row is written a window, so the fsync costs nothing that matters. Rows are only
ever inserted; a window index at or below the last one is refused, so nothing recorded is overwritten.

Each row holds the window's summary columns (time, status, coverage, samples, missed ticks, largest gap,
devices in error) for queries, and the whole :class:`~gateway.windows.WindowRecord` as JSON (per channel
statistics, factors, per device quality, displacement bursts, notes); :meth:`RecordStore.windows` gives
the records back.

:func:`export_recording` writes the recording CSV that ``cncgw identify``, ``estimate`` and ``diagnose``
read: one row per stored window stamped at its end, factor columns as the profile names them (left empty
for an ``insufficient`` window: too little data is a gap, not a value), displacement columns when bursts
were recorded, every other channel's window mean under the channel's name (e.g. a room thermometer, for
``diagnose``), and the quality as extra ``q_*`` columns.
"""

from __future__ import annotations

import json
import logging
import math
import os
import sqlite3
import threading
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np

from gateway.adaptive.probes import Probe
from gateway.errors import GatewayError, RecordingError
from gateway.profile import Profile
from gateway.recording import RecordingWriter
from gateway.strict_json import nan_to_none
from gateway.windows import ChannelStats, DeviceQuality, WindowRecord

FORMAT = 1
STORE_NAME = "records.sqlite"
#: rows deleted per transaction when pruning: the store's lock is held for one batch at a time
PRUNE_BATCH = 500

log = logging.getLogger(__name__)

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS windows (
    idx INTEGER PRIMARY KEY,
    start_s REAL NOT NULL,
    end_s REAL NOT NULL,
    status TEXT NOT NULL,
    coverage REAL NOT NULL,
    samples_expected INTEGER NOT NULL,
    samples_taken INTEGER NOT NULL,
    missed_ticks INTEGER NOT NULL,
    largest_gap_s REAL NOT NULL,
    devices_in_error TEXT NOT NULL,
    written_s REAL NOT NULL,
    body TEXT NOT NULL
);
"""


def make_dir(path: str | Path, role: str, *, mode: int = 0o777) -> Path:
    """Create the directory ``path`` (``role``: what it is for, for the message) with its parents if missing.

    A file of that name or a folder this user may not write is one line naming it, not a traceback.
    """
    path = Path(path)
    try:
        path.mkdir(mode=mode, parents=True, exist_ok=True)
    except OSError as exc:
        reason = "a file, not a directory" if path.is_file() else exc.strerror or exc
        raise GatewayError(f"{path}: cannot be {role}: {reason}: expected a directory this user can create and "
                           "write") from None
    return path


def private_dir(path: str | Path) -> Path:
    """Create the data directory ``path`` for this user only (0700), or narrow an existing one to that.

    Records and the audit log describe a machine's work: nobody else on the PC needs to read them. A
    directory this user does not own is left as it is, with a warning.
    """
    path = make_dir(path, "the data directory", mode=0o700)
    _narrow(path, 0o700)
    return path


def private_file(path: str | Path) -> Path:
    """Make ``path`` readable by this user only (0600): created so if new, narrowed if it exists.

    An SQLite file's ``-wal`` and ``-shm`` files are created with its mode.
    """
    path = Path(path)
    if not path.exists():
        os.close(os.open(path, os.O_CREAT | os.O_WRONLY, 0o600))
    for p in (path, path.with_name(path.name + "-wal"), path.with_name(path.name + "-shm")):
        if p.exists():
            _narrow(p, 0o600)
    return path


def _narrow(path: Path, mode: int) -> None:
    if path.stat().st_mode & 0o777 & ~mode:
        try:
            os.chmod(path, mode)
        except OSError as exc:  # not ours: say so, do not stop
            log.warning("%s: cannot restrict its permissions to %o: %s", path, mode, exc)


def _num(x: Any) -> float:
    return math.nan if x is None else float(x)


def record_to_json(record: WindowRecord) -> str:
    """The record as strict JSON."""
    body = {
        "factors": dict(record.factors),
        "channels": {n: {f: getattr(c, f) for f in ChannelStats.__slots__} for n, c in record.channels.items()},
        "devices": {n: {f: getattr(d, f) for f in DeviceQuality.__slots__} for n, d in record.devices.items()},
        "displacement": dict(record.displacement),
        "burst_revolutions": dict(record.burst_revolutions),
        "notes": list(record.notes),
        "reason": record.reason,
    }
    return json.dumps(nan_to_none(body), separators=(",", ":"), allow_nan=False)


def record_from_row(idx: int, start_s: float, end_s: float, status: str, body: str) -> WindowRecord:
    """A stored row back as a :class:`WindowRecord`."""
    b = json.loads(body)
    floats = {"coverage", "mean", "mean_square", "mean_abs", "min", "max"}
    channels = {n: ChannelStats(**{k: (_num(v) if k in floats else v) for k, v in c.items()})
                for n, c in b["channels"].items()}
    devices = {}
    for n, d in b["devices"].items():
        d = dict(d)
        for k in ("largest_gap_s", "lateness_max_s", "read_time_max_s", "tick_s"):
            d[k] = _num(d[k])
        d["errors"] = tuple(d["errors"])
        devices[n] = DeviceQuality(**d)
    return WindowRecord(
        index=idx, start_s=start_s, end_s=end_s, status=status,
        factors=MappingProxyType({k: _num(v) for k, v in b["factors"].items()}),
        channels=MappingProxyType(channels), devices=MappingProxyType(devices),
        displacement=MappingProxyType({k: _num(v) for k, v in b["displacement"].items()}),
        burst_revolutions=MappingProxyType({k: _num(v) for k, v in b["burst_revolutions"].items()}),
        notes=tuple(b["notes"]), reason=b.get("reason", ""))  # stores written before reasons: ""


class RecordStore:
    """An append-only store of window records in one SQLite file; see the module docstring.

    ``RecordStore(path, profile=P)`` creates the file if needed (recording ``P``'s machine, window and
    factors in it) or opens it, refusing a store of another machine or window length;
    ``RecordStore(path)`` opens an existing store to read. Thread-safe; use as a context manager.
    """

    def __init__(self, path: str | Path, *, profile: Profile | None = None) -> None:
        self.path = Path(path)
        if profile is None and not self.path.exists():
            raise RecordingError(f"{self.path}: no record store here")
        self._lock = threading.Lock()
        if profile is not None:  # a store written to: this user's only
            private_file(self.path)
        try:
            self._db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=FULL")  # WAL + FULL: a committed window survives a power cut
            self._db.executescript(_SCHEMA)
            self.meta = dict(self._db.execute("SELECT key, value FROM meta").fetchall())
        except sqlite3.DatabaseError as exc:
            raise RecordingError(f"{self.path}: not a readable record store: {exc}") from None
        if profile is not None:
            self._claim(profile)
        elif self.meta.get("format") != str(FORMAT):
            raise RecordingError(f"{self.path}: not a cncgw record store (format {self.meta.get('format')!r})")
        row = self._db.execute("SELECT MAX(idx) FROM windows").fetchone()
        self.last_index: int | None = row[0]

    def _claim(self, profile: Profile) -> None:
        want = {"format": str(FORMAT), "machine": profile.name, "window_s": repr(profile.sampling.window_s)}
        if not self.meta:
            factors = {f.name: {"channel": f.channel, "stat": f.stat.value, "unit": f.unit, "column": f.column}
                       for f in profile.factors}
            rows = {**want, "profile": str(profile.path), "created_s": repr(time.time()),
                    "factors": json.dumps(factors)}
            with self._lock:
                self._db.execute("BEGIN IMMEDIATE")
                self._db.executemany("INSERT INTO meta (key, value) VALUES (?, ?)", rows.items())
                self._db.execute("COMMIT")
            self.meta = rows
            return
        for key, value in want.items():
            if self.meta.get(key) != value:
                raise RecordingError(f"{self.path}: this store holds {key} {self.meta.get(key)!r}, the profile "
                                     f"{profile.path} says {value!r}: record into another directory")

    def append(self, record: WindowRecord) -> None:
        """Write one window durably (committed and synced when this returns)."""
        with self._lock:
            if self.last_index is not None and record.index <= self.last_index:
                raise RecordingError(f"{self.path}: window {record.index} is not after the last one stored "
                                     f"({self.last_index}); records are append-only")
            body = record_to_json(record)
            try:
                self._insert(record, body)
            except sqlite3.Error as exc:  # SQLITE_FULL, read-only, I/O: the row is not there; say which
                raise RecordingError(f"{self.path}: window {record.index} not stored: {exc}") from None
            self.last_index = record.index

    def _insert(self, record: WindowRecord, body: str) -> None:
        self._db.execute(
            "INSERT INTO windows (idx, start_s, end_s, status, coverage, samples_expected, samples_taken, "
            "missed_ticks, largest_gap_s, devices_in_error, written_s, body) "
            "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
            (record.index, record.start_s, record.end_s, record.status, record.coverage,
             record.samples_expected, record.samples_taken, record.missed_ticks, record.largest_gap_s,
             ",".join(record.devices_in_error), time.time(), body))

    def prune(self, *, before: int, batch: int = PRUNE_BATCH) -> int:
        """Delete the windows with an index below ``before``; return how many.

        In transactions of ``batch`` rows, the lock released between them, so a window closing meanwhile is
        appended after at most one batch (the samplers never wait on the store at all). SQLite reuses the
        freed pages: the file stops growing rather than shrinking.
        """
        deleted = 0
        while True:
            with self._lock:
                cur = self._db.execute("DELETE FROM windows WHERE idx IN (SELECT idx FROM windows WHERE idx < ? "
                                       "ORDER BY idx LIMIT ?)", (before, batch))
                n = cur.rowcount
            deleted += max(0, n)
            if n < batch:
                return deleted
            time.sleep(0.002)  # a waiting append takes the lock now (threading.Lock is not fair)

    def first_index(self) -> int | None:
        """The oldest stored window's index (``None``: empty)."""
        with self._lock:
            return self._db.execute("SELECT MIN(idx) FROM windows").fetchone()[0]

    def __call__(self, record: WindowRecord) -> None:
        """A store is a sink: ``Acquisition(..., sinks=[store])``."""
        self.append(record)

    def __len__(self) -> int:
        with self._lock:
            return int(self._db.execute("SELECT COUNT(*) FROM windows").fetchone()[0])

    def windows(self, *, since: int | None = None, chunk: int = 1000) -> Iterator[WindowRecord]:
        """The stored records in window order (from index ``since`` on), read ``chunk`` rows at a time.

        The lock is held for one chunk's query only, so a long read (an export of months) neither holds
        the whole store in memory nor keeps the window closer from appending.
        """
        after = (since if since is not None else -(2**62)) - 1
        while True:
            with self._lock:
                rows = self._db.execute("SELECT idx, start_s, end_s, status, body FROM windows WHERE idx > ? "
                                        "ORDER BY idx LIMIT ?", (after, chunk)).fetchall()
            for row in rows:
                yield record_from_row(*row)
            if len(rows) < chunk:
                return
            after = rows[-1][0]

    def summary(self) -> tuple[int, int, bool]:
        """(windows, windows not good, whether any window holds displacement bursts), in one query."""
        with self._lock:
            n, bad, displacement = self._db.execute(
                "SELECT COUNT(*), TOTAL(status != 'good'), "
                "COALESCE(MAX(json_extract(body, '$.displacement') != '{}'), 0) FROM windows").fetchone()
        return int(n), int(bad), bool(displacement)

    def first(self) -> WindowRecord | None:
        """The oldest stored record (``None`` in an empty store)."""
        with self._lock:
            row = self._db.execute("SELECT idx, start_s, end_s, status, body FROM windows ORDER BY idx LIMIT 1"
                                   ).fetchone()
        return None if row is None else record_from_row(*row)

    def check(self) -> str:
        """SQLite's integrity check: ``"ok"`` for a sound file."""
        with self._lock:
            return str(self._db.execute("PRAGMA integrity_check").fetchone()[0])

    def close(self) -> None:
        """Close the file (idempotent)."""
        with self._lock:
            if self._db is not None:
                self._db.close()
                self._db = None  # type: ignore[assignment]

    def __enter__(self) -> RecordStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def export_recording(store: RecordStore, profile: Profile, out: str | Path, *, chunk: int = 2000) -> Path:
    """Write the store's windows as a recording CSV for ``profile`` (see the module docstring).

    The header's figures come from one query (:meth:`RecordStore.summary`); the rows are then read and
    written ``chunk`` windows at a time, so memory does not grow with the store.
    """
    window_s = float(store.meta.get("window_s", "nan"))
    if profile.recording.period_s != window_s:
        raise RecordingError(f"{profile.path}: recording.period_s ({profile.recording.period_s:g} s) differs from the "
                             f"recorded window ({window_s:g} s): set recording.period_s = {window_s:g}")
    stored = json.loads(store.meta.get("factors", "{}"))
    missing = [f.name for f in profile.factors if f.name not in stored]
    if missing:
        raise RecordingError(f"{store.path}: the store has no factor {', '.join(missing)} of profile {profile.path}")
    n, bad, displacement = store.summary()
    if not n:
        raise RecordingError(f"{store.path}: no windows recorded yet: nothing to export")
    meta = {"machine": store.meta.get("machine", ""), "records": str(store.path), "windows": str(n),
            "insufficient_windows": f"{bad} (factors left empty)"}
    probes = probes_by_window(store.path)  # [probes]: sparse columns at the windows they were applied after
    if probes:
        meta["probes"] = f"{len(probes)} (probe_* columns: the probe applied after that window)"
    names = list(_export_columns([], profile, displacement, probes))
    with RecordingWriter(out, names=names, meta=meta, time_column=profile.recording.time_column) as writer:
        batch: list[WindowRecord] = []
        for r in store.windows(chunk=chunk):
            batch.append(r)
            if len(batch) == chunk:
                writer.write(np.array([b.end_s for b in batch]), _export_columns(batch, profile, displacement, probes))
                batch = []
        if batch:
            writer.write(np.array([b.end_s for b in batch]), _export_columns(batch, profile, displacement, probes))
    return writer.path


def _export_columns(records: list[WindowRecord], profile: Profile, displacement: bool,
                    probes: dict[int, Any] | None = None) -> dict[str, np.ndarray]:
    """The exported columns of some windows, in the file's column order."""
    cols: dict[str, np.ndarray] = {}
    for f in profile.factors:
        cols[f.column] = np.array([r.factors.get(f.name, math.nan) if r.status == "good" else math.nan
                                   for r in records])
    if displacement:
        for axis, column in profile.recording.displacement_columns.items():
            cols[column] = np.array([r.displacement.get(axis, math.nan) for r in records])
    used = {f.channel for f in profile.factors} | set(profile.sampling.displacement_channels.values())
    for c in profile.channels:  # other channels (a room thermometer): their means, for diagnosis
        if c.name not in used and c.name not in cols:
            cols[c.name] = np.array([r.channel_mean(c.name) for r in records])
    cols["q_good"] = np.array([1.0 if r.status == "good" else 0.0 for r in records])
    cols["q_coverage"] = np.array([r.coverage for r in records])
    cols["q_samples_expected"] = np.array([float(r.samples_expected) for r in records])
    cols["q_samples_taken"] = np.array([float(r.samples_taken) for r in records])
    cols["q_missed_ticks"] = np.array([float(r.missed_ticks) for r in records])
    cols["q_largest_gap_s"] = np.array([r.largest_gap_s for r in records])
    cols["q_devices_in_error"] = np.array([float(len(r.devices_in_error)) for r in records])
    if probes:  # irregular, sparse: a probe's values on the row of the window it was applied after
        hits = [probes.get(r.index) for r in records]
        cols["probe_seq"] = np.array([math.nan if p is None else float(p.seq) for p in hits])
        for a in profile.axes:
            cols[f"probe_{a}_um"] = np.array([math.nan if p is None else p.values_um.get(a, math.nan) for p in hits])
        cols["probe_sd_um"] = np.array([math.nan if p is None else p.sd_um for p in hits])
    return cols


# -- probes ([probes]): stored in the same file, beside the windows they were applied after ------------
_PROBES_SCHEMA = """
CREATE TABLE IF NOT EXISTS probes (
    n INTEGER PRIMARY KEY AUTOINCREMENT,
    window INTEGER NOT NULL,
    seq INTEGER NOT NULL,
    time_s REAL NOT NULL,
    sd_um REAL NOT NULL,
    body TEXT NOT NULL,
    source TEXT NOT NULL
);
"""


class ProbeStore:
    """The probes applied (or refused for their values) live, in the record store's file: append-only."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._lock = threading.Lock()
        self._db: sqlite3.Connection | None = sqlite3.connect(self.path, check_same_thread=False, timeout=10.0)
        self._db.execute("PRAGMA synchronous=FULL")
        with self._db:
            self._db.executescript(_PROBES_SCHEMA)

    def append(self, probe: Probe, window: int) -> None:
        """Commit ``probe`` as applied after ``window`` (raises :class:`RecordingError` when it cannot)."""
        body = json.dumps(dict(probe.values_um))
        with self._lock:
            if self._db is None:
                raise RecordingError(f"{self.path}: the probe store is closed")
            try:
                with self._db:
                    self._db.execute("INSERT INTO probes (window, seq, time_s, sd_um, body, source) "
                                     "VALUES (?, ?, ?, ?, ?, ?)",
                                     (window, probe.seq, probe.time_s, probe.sd_um, body, probe.source))
            except sqlite3.Error as exc:
                raise RecordingError(f"{self.path}: probe {probe.seq} could not be stored: {exc}") from exc

    def probes(self, *, since_window: int | None = None) -> list[tuple[int, Probe]]:
        """``(window, probe)`` in the order they were applied."""
        with self._lock:
            if self._db is None:
                return []
            rows = self._db.execute("SELECT window, seq, time_s, sd_um, body, source FROM probes WHERE window >= ? "
                                    "ORDER BY n", (-(2**62) if since_window is None else since_window,)).fetchall()
        return [(int(w), Probe(seq=int(seq), time_s=float(t), values_um=json.loads(body), sd_um=float(sd),
                               source=str(src))) for w, seq, t, sd, body, src in rows]

    def close(self) -> None:
        with self._lock:
            if self._db is not None:
                self._db.close()
                self._db = None


def probes_by_window(path: str | Path) -> dict[int, Probe]:
    """The stored probes keyed by the window after which each was applied (the last of a window), read-only.

    ``{}`` for a store without probes (a gateway that never had ``[probes]``); nothing is written to the file.
    """
    try:
        db = sqlite3.connect(f"file:{Path(path)}?mode=ro", uri=True)
    except sqlite3.Error:
        return {}
    try:
        rows = db.execute("SELECT window, seq, time_s, sd_um, body, source FROM probes ORDER BY n").fetchall()
    except sqlite3.Error:  # no probes table
        return {}
    finally:
        db.close()
    return {int(w): Probe(seq=int(seq), time_s=float(t), values_um=json.loads(body), sd_um=float(sd),
                          source=str(src)) for w, seq, t, sd, body, src in rows}


def stored_probes(path: str | Path) -> Sequence[tuple[int, Probe]]:
    """The probes stored in a record store file (for export and tests)."""
    store = ProbeStore(path)
    try:
        return store.probes()
    finally:
        store.close()


