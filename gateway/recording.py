"""Per-window recordings: the CSV files that ``identify``, ``estimate`` and ``diagnose`` read.

Format (one row per window, normally one minute)::

    # cncgw recording 1                      <- optional comment lines, anywhere; "# key: value"
    # scenario: spindle-1000rpm                 lines are kept as metadata
    time_s,spindle_speed,i1_sq,...,x_um,y_um,z_um,ambient_c
    60,0,0.81,...,0.00,0.00,0.00,20.1
    120,1000,5.2,...,0.13,-0.02,0.41,20.1

- Time: a column of seconds, or of ISO 8601 stamps (``2024-05-01T08:00:00``; naive stamps are taken
  as UTC), or none at all when the caller gives the row period. A row stamped ``t`` holds the means over
  the window ``(t - period, t]``; displacement columns are samples taken at ``t``.
- Factor columns and displacement columns (um) are named by the profile; every other column is kept
  (numeric ones as numbers, others as text) for later analysis, e.g. an ambient temperature.
- Real files are messy: a UTF-8 BOM, blanks around cells, comment lines and a spreadsheet's ``;`` or tab
  with decimal commas (``_dialect``) are accepted; an empty cell
  or ``nan`` is a missing value. Time that does not increase, a non-numeric cell in a numeric column or a
  missing required column is an error naming the file, the row (file line) and the column.
- Gaps stay explicit: rows are placed on a regular grid of the nominal period, and a missing window is a
  row of NaN with ``present[k] == False``, never an interpolated value.
- Rows mostly more than one period apart are an error (the period is not the file's), not gaps.
- Bounds (each an error naming file, line and column): numbers are plain decimals with an optional
  exponent (``-1.5``, ``2e-3``; not ``1_000``, ``0x10``, ``infinity`` or non-ASCII digits) of magnitude at
  most ``MAX_ABS_VALUE``; times within +-``MAX_ABS_TIME_S``; one gap at most ``MAX_GAP_S`` and all gaps
  together at most ``MAX_MISSING_WINDOWS`` windows (a longer pause is two recordings); a cell or line at
  most ``csv.field_size_limit()`` characters; the row period from ``MIN_PERIOD_S`` to ``MAX_PERIOD_S``.
"""

from __future__ import annotations

import csv
import hashlib
import io
import math
import os
import re
import unicodedata
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING

import numpy as np

from gateway.errors import RecordingError, did_you_mean

if TYPE_CHECKING:
    from gateway.profile import Profile

FORMAT_LINE = "cncgw recording 1"
_MISSING_TOKENS = {"", "nan", "NaN", "NAN", "na", "NA", "n/a", "N/A", "null", "NULL", "-"}
#: plain decimal with an optional exponent, ASCII digits only: what a logger writes. float() also takes
#: "1_000", "infinity" and Arabic-Indic digits, which are not numbers in a recording.
_NUMBER = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_INFINITE = {"inf", "+inf", "-inf", "infinity", "+infinity", "-infinity"}

#: no sensor or CNC signal reads beyond this (in its unit); larger values overflow the fits that square them
MAX_ABS_VALUE = 1e15
#: time stamps: seconds within +-1e11 (an ISO 8601 stamp before the year 5138)
MAX_ABS_TIME_S = 1e11
#: the longest gap between two rows of one recording: longer, it is two recordings
MAX_GAP_S = 7 * 86400.0
#: missing windows a recording may hold in all (each one a row of NaN in memory)
MAX_MISSING_WINDOWS = 1_000_000
#: the row period: 0.5 ms (the fastest sampling a profile allows) to a day
MIN_PERIOD_S = 5e-4
MAX_PERIOD_S = 86400.0


@dataclass(frozen=True, slots=True)
class Gap:
    """Windows missing from a recording: ``rows`` missing windows after the row stamped ``after_s``."""

    after_s: float
    rows: int

    def __str__(self) -> str:
        return f"{self.rows} missing window{'s' if self.rows != 1 else ''} after t={self.after_s:g} s"



def split_part(source: str) -> tuple[str, str] | None:
    """(column, value) of a run of a file split by a column (``file.csv[day=7]``, see ``--split-by``), else None."""
    m = re.search(r"\[([^=\]]+)=([^\]]+)\]$", source)
    return (m.group(1), m.group(2)) if m else None


def runs_on_from(prev: Recording, rec: Recording) -> bool:
    """Whether ``rec`` starts one window after ``prev`` ends: the machine ran on from one into the other.

    A run of a file split by a column (:func:`split_part`) never runs on from another recording nor into one:
    each starts in its own equilibrium, though the times of a file of days run on across the cut.
    """
    return bool(len(prev) and len(rec) and not split_part(prev.source) and not split_part(rec.source)
                and abs(prev.period_s - rec.period_s) < 1e-9 * rec.period_s
                and 0.5 * rec.period_s < rec.time_s[0] - prev.time_s[-1] <= 1.5 * rec.period_s)


def split_file(source: str) -> tuple[str, tuple[str, str] | None]:
    """(the file, :func:`split_part`) of a source: ``file.csv[day=7]`` is ``("file.csv", ("day", "7"))``."""
    part = split_part(source)
    return (source.removesuffix(f"[{part[0]}={part[1]}]") if part else source), part


def recording_name(source: str) -> str:
    """A recording's name from its source: its file's stem, with the part for a run of a split file.

    ``file.csv[day=7]`` (see ``--split-by``) is ``file[day=7]``.
    """
    if not source:
        return "recording"
    file, _ = split_file(source)
    return Path(file).stem + source[len(file):]


@dataclass(frozen=True, kw_only=True)
class Recording:
    """A recording on a regular grid. Arrays are read-only; missing windows are NaN rows."""

    source: str
    period_s: float
    time_s: np.ndarray
    present: np.ndarray
    factors: Mapping[str, np.ndarray]
    displacement: Mapping[str, np.ndarray]
    extras: Mapping[str, np.ndarray] = field(default_factory=dict)
    text: Mapping[str, tuple[str, ...]] = field(default_factory=dict)
    meta: Mapping[str, str] = field(default_factory=dict)
    gaps: tuple[Gap, ...] = ()
    #: the time stamps are the clock's (False: a file without a time column, rows ``period_s`` apart from 0, whose
    #: time of day is unknown)
    clock: bool = True

    def __post_init__(self) -> None:
        n = len(self.time_s)
        for group in (self.factors, self.displacement, self.extras):
            for key, arr in group.items():
                if arr.shape != (n,):
                    raise ValueError(f"column {key!r}: wrong shape {arr.shape}, expected ({n},)")
        for arr in (self.time_s, self.present, *self.factors.values(), *self.displacement.values(),
                    *self.extras.values()):
            arr.flags.writeable = False

    @property
    def name(self) -> str:
        """The file's stem; for a part of a file (``file.csv[day=7]``, see ``--split-by``) with the part."""
        return recording_name(self.source)

    def fingerprint(self, factors: Sequence[str]) -> str:
        """A short hash of the values of ``factors`` and of the displacement columns (time stamps left out).

        The same run read from another file (a day cut out of a longer one, renamed) has the same
        fingerprint: diagnosis uses it to know which recordings identified a model.
        """
        h = hashlib.sha256()
        for group, names in ((self.factors, factors), (self.displacement, sorted(self.displacement))):
            for n in names:
                v = np.asarray(group[n], dtype=np.float64) if n in group else np.zeros(0)
                h.update(n.encode() + np.where(np.isfinite(v), v, 0.0).tobytes() + np.isfinite(v).tobytes())
        return h.hexdigest()[:16]

    def __len__(self) -> int:
        return len(self.time_s)

    @property
    def duration_s(self) -> float:
        return float(len(self) * self.period_s)

    def factor_matrix(self, names: Sequence[str]) -> np.ndarray:
        """Factors as an array of shape (len(names), N)."""
        return np.vstack([self.factors[n] for n in names]) if names else np.zeros((0, len(self)))

    def ending_before(self, rec: Recording) -> Recording:
        """The recording with its times moved to end one window before ``rec`` starts (its own gaps kept).

        Files read with a row period (``--period-s``) each count their times from 0: one given as another's
        history (``--history``) ran just before it, which their times cannot say.
        """
        if not len(self) or not len(rec):
            return self
        t = self.time_s + (float(rec.time_s[0]) - rec.period_s - float(self.time_s[-1]))
        return replace(self, time_s=t, gaps=_gaps_from_mask(t, self.present))

    def slice(self, start: int, stop: int) -> Recording:
        """Rows ``start:stop`` as a recording of their own (gaps recomputed)."""
        sl = slice(start, stop)
        t = self.time_s[sl]
        present = self.present[sl]
        return Recording(
            source=self.source, period_s=self.period_s, time_s=t.copy(), present=present.copy(),
            factors={k: v[sl].copy() for k, v in self.factors.items()},
            displacement={k: v[sl].copy() for k, v in self.displacement.items()},
            extras={k: v[sl].copy() for k, v in self.extras.items()},
            text={k: v[sl] for k, v in self.text.items()}, meta=self.meta,
            gaps=_gaps_from_mask(t, present), clock=self.clock,
        )


def gap_between(prev: Recording, rec: Recording) -> float:
    """The seconds between ``prev``'s last window and ``rec``'s first beyond one window (0: ``rec`` runs on from it)."""
    return float(rec.time_s[0] - prev.time_s[-1]) - rec.period_s if len(prev) and len(rec) else 0.0


def continued(history: Recording, rec: Recording) -> Recording:
    """``history`` followed by ``rec``: one recording, the windows between them explicit missing rows.

    For a recording that starts where another left off (the previous day, the stored history): a model run
    over both starts ``rec`` in the state the history left, not at rest. Columns missing from either part
    are NaN there; the window lengths must agree and ``rec`` must start after the history ends, within
    :data:`MAX_GAP_S`.
    """
    if abs(history.period_s - rec.period_s) > 1e-9 * rec.period_s:
        raise RecordingError(f"{history.source}: windows of {history.period_s:g} s, but {rec.source} has "
                             f"{rec.period_s:g} s: a history must have the recording's window length")
    if not len(history) or not len(rec):
        return rec if not len(history) else history
    gap_s = float(rec.time_s[0] - history.time_s[-1])
    if not gap_s > 0.5 * rec.period_s:
        raise RecordingError(f"{history.source} ends at t={history.time_s[-1]:g} s, not before {rec.source} starts "
                             f"(t={rec.time_s[0]:g} s): expected a history that ends before the recording")
    if gap_s > MAX_GAP_S + rec.period_s:
        raise RecordingError(f"{history.source} ends {gap_s / 86400:.1f} days before {rec.source} starts: expected a "
                             f"history that ends at most {MAX_GAP_S / 86400:g} days before")
    missing = max(0, round(gap_s / rec.period_s) - 1)
    t_gap = history.time_s[-1] + rec.period_s * np.arange(1, missing + 1)
    n_h, n_r = len(history), len(rec)

    def joined(a: Mapping[str, np.ndarray], b: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        out = {}
        for k in dict.fromkeys([*a, *b]):
            head = np.asarray(a[k], float) if k in a else np.full(n_h, np.nan)
            out[k] = np.concatenate([head, np.full(missing, np.nan),
                                     np.asarray(b[k], float) if k in b else np.full(n_r, np.nan)])
        return out

    t = np.concatenate([history.time_s, t_gap, rec.time_s])
    present = np.concatenate([history.present, np.zeros(missing, dtype=bool), rec.present])
    return Recording(source=rec.source, period_s=rec.period_s, time_s=t, present=present,
                     factors=joined(history.factors, rec.factors),
                     displacement=joined(history.displacement, rec.displacement),
                     extras=joined(history.extras, rec.extras), meta=rec.meta, gaps=_gaps_from_mask(t, present),
                     clock=rec.clock)


def _gaps_from_mask(time_s: np.ndarray, present: np.ndarray) -> tuple[Gap, ...]:
    gaps, k, n = [], 0, len(present)
    while k < n:
        if not present[k]:
            j = k
            while j < n and not present[j]:
                j += 1
            gaps.append(Gap(after_s=float(time_s[k - 1]) if k > 0 else float("nan"), rows=j - k))
            k = j
        else:
            k += 1
    return tuple(gaps)


# --------------------------------------------------------------------------------------------------------
def _parse_number(cell: str) -> float:
    """A cell as a number (plain decimal, optional exponent); ValueError otherwise."""
    if _NUMBER.fullmatch(cell) is None:
        if cell.lower() in _INFINITE:
            return math.inf
        raise ValueError(cell)
    return float(cell)


def _parse_time(cell: str) -> float:
    try:
        return _parse_number(cell)
    except ValueError:
        pass
    text = cell.strip()
    if not text.isascii():
        raise ValueError(cell)
    if text.endswith(("Z", "z")):
        text = text[:-1] + "+00:00"
    stamp = datetime.fromisoformat(text)  # raises ValueError
    if stamp.tzinfo is None:
        stamp = stamp.replace(tzinfo=UTC)
    try:
        return stamp.timestamp()
    except (OverflowError, OSError) as exc:
        raise ValueError(cell) from exc


def read_recording(
    path: str | Path,
    *,
    factor_columns: Mapping[str, str],
    displacement_columns: Mapping[str, str],
    time_column: str | None = "time_s",
    period_s: float = 60.0,
    require_displacement: bool = True,
    text: str | None = None,
    nonnegative: Mapping[str, str] | None = None,
) -> Recording:
    """Read one recording CSV.

    ``factor_columns`` maps factor name -> column, ``displacement_columns`` axis -> column (um).
    ``time_column=None`` means the file has no time column and rows are ``period_s`` apart. Missing
    displacement columns are an error only when ``require_displacement``. ``nonnegative``: factor name -> what
    it is (``"a mean of squares"``) for the factors no value below zero can be (a negative cell is an error).
    """
    try:
        return _read_recording(Path(path), factor_columns=factor_columns, displacement_columns=displacement_columns,
                               time_column=time_column, period_s=period_s,
                               require_displacement=require_displacement, text=text, nonnegative=nonnegative or {})
    except RecordingError as exc:  # one line, whatever a column name or a cell holds
        raise RecordingError(_clip(str(exc), 1000)) from None


#: the first bytes of files people pass for a recording that are no text: what each is
_MAGIC = ((b"PK\x03\x04", "a zip archive (an Excel .xlsx workbook is one)"),
          (b"\xd0\xcf\x11\xe0\xa1\xb1\x1a\xe1", "an Office document of the old format (an Excel .xls workbook)"),
          (b"%PDF", "a PDF document"), (b"\x89PNG", "a PNG image"), (b"\x1f\x8b", "a gzip archive"))


def number_or_blank(cell: str) -> bool:
    """Whether a cell reads as a number or as a missing value (a gap), as a factor's or displacement's would."""
    cell = cell.strip()
    return _blank(cell) or bool(_NUMBER.fullmatch(cell))


def _blank(cell: str) -> bool:
    """Whether a (stripped) cell is a missing value: a gap."""
    return cell in _MISSING_TOKENS or cell.lower() == "nan"


def _binary_kind(head: bytes) -> str:
    """What a file that is no text is, from its first bytes ("" when not known)."""
    return next((kind for magic, kind in _MAGIC if head.startswith(magic)), "")


def _read_recording(path: Path, *, factor_columns: Mapping[str, str], displacement_columns: Mapping[str, str],
                    time_column: str | None, period_s: float, require_displacement: bool,
                    text: str | None, nonnegative: Mapping[str, str]) -> Recording:
    if not MIN_PERIOD_S <= period_s <= MAX_PERIOD_S:
        raise RecordingError(f"{path}: the row period must be from {MIN_PERIOD_S:g} s to {MAX_PERIOD_S:g} s (a day), "
                             f"got {period_s!r}")
    if text is None:
        if path.is_dir():  # checked first: Windows opens a folder with "permission denied", not IsADirectoryError
            raise RecordingError(f"{path}: a folder, not a file: expected a recording (CSV); give its files one by "
                                 f"one (in a shell: {path}/*.csv)")
        try:
            text = path.read_text(encoding="utf-8-sig")
        except FileNotFoundError:
            raise RecordingError(f"{path}: file not found") from None
        except UnicodeDecodeError as exc:  # a spreadsheet's "CSV" in its ANSI code page (a degree sign, a mu)
            kind = _binary_kind(exc.object)
            if kind:  # the workbook itself, not a CSV saved from it
                raise RecordingError(f"{path}: {kind}, not a CSV text: expected a recording as CSV (in Excel: save "
                                     'as "CSV UTF-8")') from None
            line = exc.object[:exc.start].count(b"\n") + 1
            raise RecordingError(f"{path}:{line}: byte 0x{exc.object[exc.start]:02x} is not UTF-8: expected a UTF-8 "
                                 'text (in Excel save as "CSV UTF-8")') from None
        except OSError as exc:
            raise RecordingError(f"{path}: cannot read: {exc}") from None
    else:
        text = text.removeprefix("\ufeff")

    meta: dict[str, str] = {}
    header: list[str] | None = None
    header_line = 0
    rows: list[tuple[int, list[str]]] = []
    for lineno, cells in _csv_rows(text, path):
        first = cells[0].strip() if cells else ""
        if not any(c.strip() for c in cells):
            continue
        if first.startswith("#"):
            body = ",".join(cells).strip().lstrip("#").strip()
            key, sep, value = body.partition(":")
            if sep and key.strip() and " " not in key.strip():
                meta[key.strip()] = value.strip()
            continue
        if header is None:
            header = [c.strip() for c in cells]
            header_line = lineno
            continue
        rows.append((lineno, cells))
    if header is None:
        raise RecordingError(f"{path}: no header row: expected a line of column names such as "
                             f"{time_column or 'spindle_speed'},...")
    if header and header[0] == "" and all(h for h in header[1:]):
        header[0] = "_index"  # pandas-style unnamed index column
    named = len(header)
    while named > 1 and not header[named - 1]:
        named -= 1
    if named < len(header):
        # a spreadsheet's trailing separators (its used range wider than the data): nameless, empty columns
        for n, cells in rows:
            i = next((i for i in range(named, len(cells)) if cells[i].strip()), None)
            if i is not None:
                raise RecordingError(f'{path}:{n}: column {i + 1} holds "{_clip(cells[i].strip())}" but has no name '
                                     f"in the header on line {header_line}: expected a name for every column with "
                                     "data")
        header = header[:named]
        rows = [(n, cells[:named]) for n, cells in rows]
    for i, h in enumerate(header):
        if not h:
            raise RecordingError(f"{path}:{header_line}: column {i + 1} has an empty name")
        if header.count(h) > 1:
            raise RecordingError(f'{path}:{header_line}: column "{h}" appears {header.count(h)} times')
    col = {h: i for i, h in enumerate(header)}

    def need(name: str, what: str) -> int:
        if name not in col:
            raise RecordingError(f'{path}:{header_line}: missing column "{name}" ({what})'
                                 f"{did_you_mean(name, header)}; columns are: {', '.join(header)}")
        return col[name]

    t_idx = need(time_column, "time in seconds or ISO 8601; a file without one needs its row period: --period-s S") \
        if time_column is not None else None
    f_idx = {f: need(c, f"factor {f}") for f, c in factor_columns.items()}
    d_idx: dict[str, int] = {}
    used_names = {time_column, *factor_columns.values(), *displacement_columns.values()}
    for axis, c in displacement_columns.items():
        if c in col:
            d_idx[axis] = col[c]
        elif require_displacement:
            need(c, f"measured displacement {axis} in um")
        else:
            # optional, but a column that is it with more to its name ("x_um (um)", "x_um [um]", "x_um_um",
            # "x_um_1") or in other letters ("X_UM") would have been read as no measurement at all, without a word
            dressed = [h for h in header if h not in used_names and _words(h)[:len(_words(c))] == _words(c)]
            if dressed:
                raise RecordingError(f'{path}:{header_line}: column "{dressed[0]}" looks like the measured '
                                     f'displacement {axis} ("{c}", in um): expected the name "{c}" exactly')
    used = {i for i in (t_idx, *f_idx.values(), *d_idx.values()) if i is not None}
    extra_cols = [h for i, h in enumerate(header) if i not in used]

    n = len(rows)
    width = len(header)
    times = np.empty(n)
    numeric_needed = {i: h for i, h in enumerate(header) if i in used and i != t_idx}
    never_negative = {f_idx[f]: what for f, what in nonnegative.items() if f in f_idx}
    data = np.full((n, width), np.nan)
    text_cells: dict[str, list[str]] = {h: [] for h in extra_cols}
    non_numeric: set[str] = set()
    for r, (lineno, cells) in enumerate(rows):
        if len(cells) != width:
            if r == n - 1 and len(cells) < width and not text.endswith(("\n", "\r")):
                # a logger or a copy stopped mid-row: say so, the rows before it are whole
                raise RecordingError(f"{path}:{lineno}: the file ends in the middle of this row ({len(cells)} of "
                                     f"{width} cells, no line end): cut short while it was written or copied? "
                                     f"expected whole rows: the {n - 1} rows before it are whole; delete this line "
                                     "or copy the file again")
            raise RecordingError(f"{path}:{lineno}: row has {len(cells)} cells, expected {width} "
                                 f"(one per column of the header on line {header_line})")
        if t_idx is not None:
            cell = cells[t_idx].strip()
            try:
                times[r] = _parse_time(cell)
            except ValueError:
                raise RecordingError(f'{path}:{lineno}: column "{time_column}": "{_clip(cell)}" is not a time: '
                                     "expected seconds (a plain decimal number) or an ISO 8601 stamp") from None
            if not abs(times[r]) <= MAX_ABS_TIME_S:
                raise RecordingError(f'{path}:{lineno}: column "{time_column}": "{_clip(cell)}" is out of range: '
                                     f"expected seconds within +-{MAX_ABS_TIME_S:g} (an ISO 8601 stamp before "
                                     "the year 5138)")
        else:
            times[r] = r * period_s
        for i, h in enumerate(header):
            if i == t_idx:
                continue
            cell = cells[i].strip()
            if h in text_cells:
                text_cells[h].append(cell)
            if _blank(cell):
                continue
            if h in non_numeric:
                continue
            try:
                value = _parse_number(cell)
            except ValueError:
                if i in numeric_needed:
                    raise RecordingError(f'{path}:{lineno}: column "{h}": "{_clip(cell)}" is not a number: expected '
                                         "a plain decimal such as -12.5 or 1.2e-3") from None
                non_numeric.add(h)
                continue
            if not abs(value) <= MAX_ABS_VALUE:
                if i in numeric_needed:
                    what = ("is not a finite number" if math.isinf(value) else
                            f"is out of range: expected a magnitude of at most {MAX_ABS_VALUE:g} (in its unit)")
                    raise RecordingError(f'{path}:{lineno}: column "{h}": "{_clip(cell)}" {what}')
                non_numeric.add(h)  # an extra column of such numbers (nanosecond stamps, ids) is kept as text
                continue
            if value < 0 and i in never_negative:
                raise RecordingError(f'{path}:{lineno}: column "{h}": "{_clip(cell)}" is negative: expected a value '
                                     f">= 0, as {never_negative[i]} never is (a glitch or a sentinel value? leave the "
                                     "cell empty to make it a gap)")
            data[r, i] = value

    if n and not np.all(np.isfinite(times)):
        bad = int(np.flatnonzero(~np.isfinite(times))[0])
        raise RecordingError(f'{path}:{rows[bad][0]}: column "{time_column}": time must be finite')
    # time must increase; place rows on the nominal grid, keeping gaps explicit
    steps = np.diff(times)
    if np.any(steps <= 0):
        k = int(np.flatnonzero(steps <= 0)[0])
        raise RecordingError(
            f'{path}:{rows[k + 1][0]}: column "{time_column}": time does not increase '
            f"({times[k + 1]:g} s after {times[k]:g} s on line {rows[k][0]}); expected strictly increasing time")
    ratio = steps / period_s
    if np.any(ratio < 0.5):
        k = int(np.flatnonzero(ratio < 0.5)[0])
        raise RecordingError(
            f'{path}:{rows[k + 1][0]}: column "{time_column}": rows only {steps[k]:g} s apart, expected the '
            f"row period of {period_s:g} s (set the period to the file's own if it differs)")
    if np.any(steps > MAX_GAP_S + period_s):
        k = int(np.flatnonzero(steps > MAX_GAP_S + period_s)[0])
        raise RecordingError(
            f'{path}:{rows[k + 1][0]}: column "{time_column}": {times[k + 1]:g} s comes {steps[k]:g} s after '
            f"{times[k]:g} s on line {rows[k][0]}: expected gaps of at most {MAX_GAP_S:g} s (7 days); a longer "
            "pause is two recordings: split the file there")
    missing = float(np.sum(np.maximum(np.rint(ratio) - 1.0, 0.0))) if n else 0.0
    if missing > MAX_MISSING_WINDOWS:
        raise RecordingError(
            f'{path}: column "{time_column}": the gaps add up to {missing:.0f} missing windows of {period_s:g} s: '
            f"expected at most {MAX_MISSING_WINDOWS} (split the recording, or give the row period it really has)")
    if len(steps) >= 10 and np.median(ratio) >= 1.5:
        # most rows followed by a gap is no recording with gaps: the period is not the file's (a profile's
        # period_s of 1 s read a file of minutes as 59 missing windows after every row, filled by the gap
        # policy, and gave other figures without a word)
        raise RecordingError(
            f'{path}:{rows[1][0]}: column "{time_column}": rows are {np.median(steps):g} s apart (the median of '
            f"{len(steps)} steps), {np.median(ratio):g} times the row period of {period_s:g} s: expected rows one "
            f"period apart with occasional gaps; set the period to the file's own ({np.median(steps):g} s: "
            "[recording] period_s in the profile, or --period-s)")
    slots = np.concatenate([[0], np.cumsum(np.maximum(1, np.rint(ratio).astype(int)))]) if n else np.zeros(0, int)
    total = int(slots[-1]) + 1 if n else 0
    present = np.zeros(total, dtype=bool)
    present[slots] = True
    grid_t = times[0] + period_s * np.arange(total) if n else np.zeros(0)
    if n:
        grid_t[slots] = times  # keep each row's own stamp; missing rows sit on the nominal grid

    def column(i: int) -> np.ndarray:
        out = np.full(total, np.nan)
        out[slots] = data[:, i]
        return out

    extras = {h: column(col[h]) for h in extra_cols if h not in non_numeric}
    texts = {h: tuple(text_cells[h]) for h in extra_cols if h in non_numeric}
    return Recording(
        source=str(path), period_s=float(period_s), time_s=grid_t, present=present,
        factors={f: column(i) for f, i in f_idx.items()},
        displacement={a: column(i) for a, i in d_idx.items()},
        extras=extras, text=texts, meta=MappingProxyType(meta),
        gaps=_gaps_from_mask(grid_t, present), clock=t_idx is not None,
    )


#: a number written with a decimal comma ("-12,5", "1,2E-03"): what a spreadsheet saves in such a locale
_COMMA_NUMBER = re.compile(r"[+-]?(?:[0-9]+,[0-9]*|,[0-9]+)(?:[eE][+-]?[0-9]+)?")


def _dialect(text: str) -> tuple[str, bool]:
    """The cell separator and whether numbers carry a decimal comma.

    A spreadsheet in a locale whose decimal mark is a comma (Excel in German, French, ...) saves "CSV" with
    ``;`` between cells and ``12,5``; "Text (tab delimited)" separates by tabs. Decided by the header line
    (the first that is neither blank nor a ``#`` comment): a comma in it keeps commas; else a ``;`` or a tab
    separates, and numbers have a decimal comma if any cell of the file is one.
    """
    for line in io.StringIO(text):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        if "," in s:
            return ",", False
        sep = next((d for d in (";", "\t") if d in s), None)
        if sep is None:
            return ",", False
        pattern = rf"(?:^|{re.escape(sep)})[ ]*{_COMMA_NUMBER.pattern}[ ]*(?={re.escape(sep)}|\r?$)"
        return sep, re.search(pattern, text, re.MULTILINE) is not None
    return ",", False


def _csv_rows(text: str, path: Path) -> Iterable[tuple[int, list[str]]]:
    """The rows of ``text`` as cells, with their line numbers.

    A spreadsheet's ``;`` or tab and decimal comma are read as such (see :func:`_dialect`): a number then
    yields with a decimal point, and one written with a point, which such a file may mean as a thousands
    separator (``1.000``), is an error naming its cell.
    """
    sep, decimal_comma = _dialect(text)
    reader = csv.reader(io.StringIO(text), delimiter=sep)
    header: list[str] | None = None
    while True:
        try:
            cells = next(reader)
        except StopIteration:
            return
        except csv.Error as exc:  # a cell over the field size limit, a NUL character, a runaway quote
            line = reader.line_num
            if "field larger than field limit" in str(exc):
                raise RecordingError(f"{path}:{line}: a cell or comment longer than {csv.field_size_limit()} "
                                     "characters: expected the cells of one window") from None
            raise RecordingError(f"{path}:{line}: not readable as CSV: {exc}") from None
        if decimal_comma and cells and not cells[0].strip().startswith("#") and any(c.strip() for c in cells):
            if header is None:
                header = [c.strip() for c in cells]
            else:
                cells = [_decimal_point(c, path, reader.line_num, header, i) for i, c in enumerate(cells)]
        yield reader.line_num, cells


def _decimal_point(cell: str, path: Path, line: int, header: Sequence[str], i: int) -> str:
    """A cell of a file with a decimal comma, its number written with a point (other cells as they are)."""
    s = cell.strip()
    if _COMMA_NUMBER.fullmatch(s):
        return s.replace(",", ".")
    if "." in s and _NUMBER.fullmatch(s):
        name = header[i] if i < len(header) else f"{i + 1}"
        raise RecordingError(f'{path}:{line}: column "{_clip(name)}": "{_clip(s)}" has a "." where this file\'s '
                             "decimal mark is \",\" (its cells are separated by a semicolon or tab and it writes "
                             "numbers such as 12,5): a thousands separator? expected a number such as 1000 or "
                             "12,5") from None
    return cell


def _words(name: str) -> list[str]:
    """A column name's words, in small letters: "X_um [um]" -> ["x", "um", "um"], "x_µm" -> ["x", "um"].

    Compatibility forms are folded (full-width letters typed in another keyboard mode, the micro sign).
    """
    folded = unicodedata.normalize("NFKC", name).lower().replace("\u03bc", "u")
    return [w for w in re.split(r"[^a-z0-9]+", folded) if w]


def displacement_lookalikes(rec: Recording, displacement_columns: Mapping[str, str]) -> dict[str, list[str]]:
    """Per axis not measured in ``rec``: its unread columns that may be it.

    Those whose name's first word is the axis column's (``x_mm``, ``x``, ``x_disp_um``), or that hold the axis's
    word beside a length unit or "disp" (``disp_x_um``), or the axis's word run together with one (``dx_um``,
    ``xdisp``, ``xum``).
    """
    units = {"um", "mm", "micron", "microns", "disp", "displacement"}
    out = {}
    for axis, c in displacement_columns.items():
        if axis in rec.displacement:
            continue
        head = _words(c)[:1]
        word = head[0] if head else axis.lower()
        joined = {f"d{word}", f"{word}disp", f"disp{word}", f"{word}um", f"{word}mm"}
        # probe columns (probe_x_um, probe_sd_um: a probed day's measurement, read as such) are no look-alikes
        out[axis] = [h for h in (*rec.extras, *rec.text) if (w := _words(h)) and w[0] != "probe"
                     and (w[:1] == head or (word in w and units & set(w)) or joined & set(w))]
    return out


def unread_displacement(rec: Recording, displacement_columns: Mapping[str, str]) -> list[str]:
    """A warning for each axis not measured in ``rec`` beside unread columns that may be it.

    The columns are :func:`displacement_lookalikes`'s: ``x_mm``, ``x_disp_um`` or ``x`` beside no ``x_um`` read
    as no measurement of x, which the estimate's figures then leave out without a word; the user is told which
    columns were not read (they may be something else).
    """
    out = []
    for axis, alike in displacement_lookalikes(rec, displacement_columns).items():
        c = displacement_columns[axis]
        if alike:
            out.append(f'{rec.source}: no column "{c}" (the measured displacement {axis}, in um): axis {axis} is not '
                       f"measured in it; not read: {', '.join(alike[:4])}{', ...' if len(alike) > 4 else ''} (if one "
                       f'of them is it, in um, name it "{c}")')
    return out


def _clip(cell: str, width: int = 40) -> str:
    """A cell for a message: long ones shortened, control characters (a quoted line break) escaped."""
    shown = cell if len(cell) <= width else f"{cell[:width]}... ({len(cell)} characters)"
    return re.sub(r"[\x00-\x1f\x7f]", lambda m: repr(m.group())[1:-1], shown)


#: the factor statistics no window can make negative, in words
_NEVER_NEGATIVE = {"mean_square": "a mean of squares (stat mean_square)",
                   "mean_abs": "a mean of absolute values (stat mean_abs)"}  # profile.Stat's values (it imports us)


def read_for_profile(path: str | Path, profile: Profile, *, period_s: float | None = None,
                     require_displacement: bool = True) -> Recording:
    """Read a recording laid out as ``profile`` says. ``period_s`` set means: the file has no time column."""
    rec = profile.recording
    out = read_recording(
        path,
        factor_columns={f.name: f.column for f in profile.factors},
        displacement_columns=dict(rec.displacement_columns),
        time_column=None if period_s is not None else rec.time_column,
        period_s=period_s if period_s is not None else rec.period_s,
        require_displacement=require_displacement,
        nonnegative={f.name: _NEVER_NEGATIVE[f.stat] for f in profile.factors if f.stat in _NEVER_NEGATIVE},
    )
    written = out.extras.get(rec.time_column) if period_s is not None and rec.time_column else None
    if written is not None and np.isfinite(written).sum() > 2:
        # the rows are timed by the option, the times written beside them only carried along: where they disagree
        # every time constant found is off by their ratio (a new user's --period-s 30 on a file of minutes)
        step = float(np.median(np.diff(written[np.isfinite(written)])))
        if not abs(step - period_s) <= 0.01 * period_s:
            raise RecordingError(f'{path}: its time column "{rec.time_column}" has rows {step:g} s apart, but '
                                 f"--period-s {period_s:g} was given: expected the same period (drop --period-s to "
                                 "time the rows by the column)")
    return out


# --------------------------------------------------------------------------------------------------------
def _fmt(x: float) -> str:
    return "" if not math.isfinite(x) else repr(float(x))


def _header(names: Sequence[str], meta: Mapping[str, str] | None, time_column: str) -> str:
    lines = [f"# {FORMAT_LINE}", *(f"# {key}: {value}" for key, value in (meta or {}).items()),
             ",".join([time_column, *names])]
    return "\n".join(lines) + "\n"


def _rows(time_s: np.ndarray, columns: Mapping[str, np.ndarray], names: Sequence[str]) -> str:
    arrays = [np.asarray(columns[n], dtype=float) for n in names]
    return "".join(",".join([_fmt(t), *(_fmt(a[k]) for a in arrays)]) + "\n"
                   for k, t in enumerate(np.asarray(time_s, dtype=float)))


def format_recording(
    *,
    time_s: np.ndarray,
    columns: Mapping[str, np.ndarray],
    meta: Mapping[str, str] | None = None,
    time_column: str = "time_s",
) -> str:
    """CSV text for a recording; NaN becomes an empty cell; floats are written to round-trip exactly."""
    return _header(list(columns), meta, time_column) + _rows(time_s, columns, list(columns))


class RecordingWriter:
    """A recording CSV written chunk by chunk, atomically.

    The header goes out when the writer opens, each :meth:`write` appends rows, and the temp file replaces
    ``path`` (fsynced) only when the ``with`` block ends without an error: a failed export leaves any
    earlier file at ``path`` as it was and no partial one. Memory stays that of one chunk, however long
    the recording.
    """

    def __init__(self, path: str | Path, *, names: Sequence[str], meta: Mapping[str, str] | None = None,
                 time_column: str = "time_s") -> None:
        self.path = Path(path)
        self.names = list(names)
        self._tmp = self.path.with_name(self.path.name + ".tmp")
        self._fh = open(self._tmp, "w", encoding="utf-8", newline="")  # noqa: SIM115 (closed in __exit__)
        self._fh.write(_header(self.names, meta, time_column))

    def write(self, time_s: np.ndarray, columns: Mapping[str, np.ndarray]) -> None:
        """Append rows: ``columns`` holds every name given when the writer was opened."""
        self._fh.write(_rows(time_s, columns, self.names))

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        try:
            if exc_type is None:
                self._fh.flush()
                os.fsync(self._fh.fileno())
        finally:
            self._fh.close()
        if exc_type is None:
            self._tmp.replace(self.path)
        else:
            self._tmp.unlink(missing_ok=True)


def write_recording(path: str | Path, *, time_s: np.ndarray, columns: Mapping[str, np.ndarray],
                    meta: Mapping[str, str] | None = None, time_column: str = "time_s") -> Path:
    """Write a whole recording atomically (temp file, fsync, rename); see :class:`RecordingWriter`."""
    with RecordingWriter(path, names=list(columns), meta=meta, time_column=time_column) as writer:
        writer.write(time_s, columns)
    return writer.path
