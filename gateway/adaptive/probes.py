"""Probe measurements: a CNC macro probes a reference artefact and reports the tool-to-table displacement.

A probe is one instant, one to three axes, each value in um relative to the same datum the model's
estimate is relative to (the machine cold, in thermal equilibrium), with the probe's own standard
uncertainty. Every probe carries the CNC's sequence number; the update in
:mod:`gateway.adaptive.filter` uses each number once, in order.

What a probe is checked for before it can reach the update (each failure is a decision with a reason,
never an exception on the live path):

- its values are finite and within the range a thermal displacement can have (:data:`VALUE_MAX_UM`);
- its uncertainty is finite and within (0, :data:`SD_MAX_UM`];
- its sequence number is new: the same number again with the same values is the same probe read twice
  (ignored without a word), with other values it is a repeated sequence number (rejected), a number behind
  the last one is stale (rejected). Numbers are 16-bit and wrap: a step of 1..32767 forward is new.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType

#: largest |value| a probe may report (um): beyond it no thermal displacement of a machine tool lies
VALUE_MAX_UM = 1000.0
#: largest probe uncertainty (1 sigma, um) the update accepts; a probe this poor teaches nothing
SD_MAX_UM = 50.0
SEQ_MODULUS = 65536


@dataclass(frozen=True, kw_only=True, slots=True)
class Probe:
    """One probe cycle's result.

    ``values_um``: axis -> measured displacement (um) for the axes probed (one to three);
    ``sd_um``: the probe's standard uncertainty (1 sigma, um), the same for each axis it reports;
    ``time_s``: when it was taken (the clock the windows are stamped with).
    """

    seq: int
    time_s: float
    values_um: Mapping[str, float]
    sd_um: float
    source: str = ""

    def __post_init__(self) -> None:
        object.__setattr__(self, "values_um", MappingProxyType(dict(self.values_um)))

    def describe(self) -> str:
        vals = ", ".join(f"{a} {v:+.2f} um" for a, v in self.values_um.items())
        return f"probe {self.seq} at t={self.time_s:.0f} s ({vals}, sd {self.sd_um:g} um)"


@dataclass(frozen=True, kw_only=True, slots=True)
class ProbeDecision:
    """What the update did with one axis of one probe (``axis`` is ``""`` for a probe refused whole)."""

    seq: int
    time_s: float
    axis: str
    accepted: bool
    reason: str  # why it was refused ("" when accepted)
    value_um: float = math.nan
    predicted_um: float = math.nan  # the estimate at the probe's instant before the update
    predicted_sd_um: float = math.nan  # its standard uncertainty, the probe's own included
    innovation_sigma: float = math.nan  # (value - predicted) / predicted_sd

    def describe(self) -> str:
        what = f"probe {self.seq}" + (f" axis {self.axis}" if self.axis else "")
        if not self.accepted:
            return f"{what} rejected: {self.reason}"
        return (f"{what} applied: {self.value_um:+.2f} um against {self.predicted_um:+.2f} +- "
                f"{self.predicted_sd_um:.2f} um ({self.innovation_sigma:+.1f} sigma)")


def probe_problems(probe: Probe, axes: tuple[str, ...]) -> list[str]:
    """Why ``probe`` cannot be used at all (``[]`` when its values and uncertainty are usable)."""
    out = []
    if not probe.values_um:
        out.append("no axis probed (the axis mask is empty)")
    for a, v in probe.values_um.items():
        if a not in axes:
            out.append(f"axis {a!r} is not one of the model's axes {', '.join(axes)}")
        elif not (math.isfinite(v) and abs(v) <= VALUE_MAX_UM):
            out.append(f"axis {a}: value {v!r} um is outside +-{VALUE_MAX_UM:g} um (no thermal displacement is "
                       "that large: a wrong unit or a failed probe cycle)")
    if not (math.isfinite(probe.sd_um) and 0 < probe.sd_um <= SD_MAX_UM):
        out.append(f"uncertainty {probe.sd_um!r} um: expected > 0 and <= {SD_MAX_UM:g} um")
    if not math.isfinite(probe.time_s):
        out.append(f"time {probe.time_s!r}: expected a finite time")
    return out


@dataclass(kw_only=True)
class SequenceCheck:
    """Which probe sequence numbers are new (see the module docstring)."""

    last_seq: int | None = None
    last_values: Mapping[str, float] = field(default_factory=dict)
    last_time_s: float = -math.inf

    def check(self, probe: Probe) -> str | None:
        """``None``: a new probe; ``""``: the last one read again (ignore it); else why it is refused."""
        if not 0 <= probe.seq < SEQ_MODULUS:
            return f"sequence number {probe.seq} is outside 0..{SEQ_MODULUS - 1}"
        if self.last_seq is None:
            return None
        step = (probe.seq - self.last_seq) % SEQ_MODULUS
        if step == 0:
            if dict(probe.values_um) == dict(self.last_values):
                return ""
            return (f"repeated sequence number {probe.seq} with other values (the last probe {probe.seq} was "
                    f"{_values(self.last_values)}, this one {_values(probe.values_um)})")
        if step >= SEQ_MODULUS // 2:
            return f"stale sequence number {probe.seq}: the last probe applied was {self.last_seq}"
        if probe.time_s < self.last_time_s:
            return (f"probe time {probe.time_s:.0f} s is before the last probe's {self.last_time_s:.0f} s "
                    "(a probe from the past)")
        return None

    def note(self, probe: Probe) -> None:
        """``probe`` was taken into account (applied, or refused for its values): its number is used."""
        self.last_seq = probe.seq
        self.last_values = dict(probe.values_um)
        self.last_time_s = probe.time_s


def _values(values: Mapping[str, float]) -> str:
    return ", ".join(f"{a} {v:+.2f} um" for a, v in values.items()) or "no axis"


# ----------------------------------------------------------------------------------- the register block ---
#: the probe block a CNC macro writes (input registers from ``probe_register``), in order:
#: sequence number (uint16, written last by the macro), axis mask (bit 0 x, 1 y, 2 z), x, y, z (int32, high
#: word first, in ``unit_um``), uncertainty (uint16, 1 sigma, in ``unit_um``)
PROBE_BLOCK_WORDS = 9
AXIS_BITS = ("x", "y", "z")


def decode_probe_block(words: Sequence[int], *, time_s: float, unit_um: float = 0.1, first_register: int = 0,
                       source: str = "cnc") -> tuple[Probe | None, list[str]]:
    """The probe in a register block read from the CNC, or ``None`` and why it cannot be one.

    Each problem names the register (``first_register`` + offset), its raw value and what was expected.
    A block of all zeros is no probe yet (a CNC that has never probed): ``(None, [])``.
    """
    if len(words) != PROBE_BLOCK_WORDS:
        return None, [f"probe block at register {first_register}: expected {PROBE_BLOCK_WORDS} registers, "
                      f"got {len(words)}"]
    if not any(words):
        return None, []
    bad = [(k, w) for k, w in enumerate(words) if not 0 <= int(w) <= 0xFFFF]
    if bad:
        return None, [f"register {first_register + k}: {w!r} is not a 16-bit register value" for k, w in bad]
    seq, mask = int(words[0]), int(words[1])
    problems = []
    if mask == 0 or mask & ~0b111:
        problems.append(f"register {first_register + 1} (axis mask): {mask} (0x{mask:04x}): expected bits 0-2 "
                        "(x, y, z), at least one set")
    values = {}
    for i, a in enumerate(AXIS_BITS):
        if mask & (1 << i):
            hi, lo = int(words[2 + 2 * i]), int(words[3 + 2 * i])
            raw = struct.unpack(">i", struct.pack(">HH", hi, lo))[0]
            um = raw * unit_um
            if abs(um) > VALUE_MAX_UM:
                problems.append(f"registers {first_register + 2 + 2 * i}-{first_register + 3 + 2 * i} ({a}): {raw} "
                                f"counts = {um:g} um: expected within +-{VALUE_MAX_UM:g} um")
            values[a] = um
    sd_raw = int(words[8])
    sd = sd_raw * unit_um
    if sd_raw == 0 or sd > SD_MAX_UM:
        problems.append(f"register {first_register + 8} (uncertainty): {sd_raw} counts = {sd:g} um: expected > 0 "
                        f"and <= {SD_MAX_UM:g} um")
    if problems:
        return None, [f"probe {seq}: {p}" for p in problems]
    return Probe(seq=seq, time_s=time_s, values_um=values, sd_um=sd, source=source), []


def encode_probe_block(*, seq: int, values_um: Mapping[str, float], sd_um: float, unit_um: float = 0.1) -> list[int]:
    """The register block for a probe (what a CNC macro writes; the simulated CNC uses it)."""
    mask = 0
    words = [0] * PROBE_BLOCK_WORDS
    for i, a in enumerate(AXIS_BITS):
        if a in values_um:
            mask |= 1 << i
            hi, lo = struct.unpack(">HH", struct.pack(">i", round(values_um[a] / unit_um)))
            words[2 + 2 * i], words[3 + 2 * i] = hi, lo
    words[0], words[1], words[8] = seq & 0xFFFF, mask, min(max(round(sd_um / unit_um), 0), 0xFFFF)
    return words


# -------------------------------------------------------------------------------------------- the CSV ---
def read_probes(path: str | Path, *, axes: Sequence[str] = AXIS_BITS) -> list[Probe]:
    """Probes from a CSV file: ``time`` (seconds or ISO 8601), ``seq``, ``x_um``/``y_um``/``z_um``, ``sd_um``.

    One row per probe cycle; an empty cell is an axis not probed (at least one per row); ``#`` lines are
    comments. A recording exported by ``cncgw record`` from a gateway with ``[probes]`` is read too: its
    ``probe_seq``, ``probe_<axis>_um``, ``probe_sd_um`` columns on the rows of the windows the probes were
    applied after (each probe then stamped with that window's end). Rows must be in time order with
    increasing sequence numbers. Every problem is raised as one :class:`~gateway.errors.RecordingError` naming
    the file, line and column.
    """
    from gateway.errors import RecordingError
    from gateway.recording import _csv_rows, _parse_number, _parse_time

    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise RecordingError(f"{path}: cannot read the probe file: {exc}") from None
    rows = [(n, [c.strip() for c in cells]) for n, cells in _csv_rows(text, path)
            if cells and not cells[0].lstrip().startswith("#")]
    if not rows:
        raise RecordingError(f"{path}: no header line: expected time, seq, {', '.join(f'{a}_um' for a in axes)}, sd_um")
    line0, head = rows[0]
    names = [h.lower() for h in head]
    # a recording exported by `cncgw record` carries its probes in sparse probe_* columns
    pre = "probe_" if "probe_seq" in names else ""
    if pre:
        names = [n[len(pre):] if n.startswith(pre) else ("time" if n in ("time", "time_s") else f"-{n}")
                 for n in names]
    need = {"time": ("time", "time_s"), "seq": ("seq",), "sd_um": ("sd_um",)}
    col: dict[str, int] = {}
    problems = []
    for key, options in need.items():
        hit = next((names.index(o) for o in options if o in names), None)
        if hit is None:
            problems.append(f"{path}:{line0}: no column {options[0]!r}: expected the columns time, seq, "
                            f"{', '.join(f'{a}_um' for a in axes)}, sd_um")
        else:
            col[key] = hit
    axis_cols = {a: names.index(f"{a}_um") for a in axes if f"{a}_um" in names}
    if not axis_cols:
        problems.append(f"{path}:{line0}: no axis column: expected at least one of "
                        f"{', '.join(f'{a}_um' for a in axes)}")
    if problems:
        raise RecordingError("\n".join(problems))
    out: list[Probe] = []
    for line, cells in rows[1:]:
        if len(cells) < len(head):
            problems.append(f"{path}:{line}: {len(cells)} cells, expected {len(head)} (the header's)")
            continue
        if pre and cells[col["seq"]] == "":
            continue  # a window without a probe

        def cell(c: int, what: str, parse, line=line, cells=cells):
            try:
                v = parse(cells[c])
            except ValueError:
                problems.append(f"{path}:{line}: column {head[c]!r}: {_clip_cell(cells[c])!r} is not {what}")
                return None
            if not math.isfinite(v):
                problems.append(f"{path}:{line}: column {head[c]!r}: {cells[c]!r} is not {what}")
                return None
            return v

        t = cell(col["time"], "a time (seconds or ISO 8601)", _parse_time)
        seq = cell(col["seq"], "a sequence number 0..65535", _parse_int)
        sd = cell(col["sd_um"], "an uncertainty in um", _parse_number)
        values = {}
        for a, c in axis_cols.items():
            if cells[c] != "":
                v = cell(c, "a displacement in um", _parse_number)
                if v is not None:
                    values[a] = v
        if None in (t, seq, sd):
            continue
        probe = Probe(seq=int(seq), time_s=float(t), values_um=values, sd_um=float(sd), source=f"{path}:{line}")
        for p in probe_problems(probe, tuple(axes)):
            problems.append(f"{path}:{line}: {p}")
        if out and probe.time_s < out[-1].time_s:
            problems.append(f"{path}:{line}: time {cells[col['time']]} is before the previous row's: expected rows in "
                            "time order")
        if out and not 0 < (probe.seq - out[-1].seq) % SEQ_MODULUS < SEQ_MODULUS // 2:
            problems.append(f"{path}:{line}: sequence number {probe.seq} does not follow {out[-1].seq}: expected "
                            "each probe's number after the previous one's")
        out.append(probe)
    if problems:
        raise RecordingError("\n".join(problems[:50]) + (f"\n{path}: ... and {len(problems) - 50} more problems"
                                                         if len(problems) > 50 else ""))
    return out


def _parse_int(cell: str) -> float:
    """A sequence number: 0..65535, written as an integer or as a whole float (an exported recording's 7.0)."""
    from gateway.recording import _parse_number

    v = _parse_number(cell)
    if not (math.isfinite(v) and v == int(v) and 0 <= v < SEQ_MODULUS):
        raise ValueError(cell)
    return float(v)


def _clip_cell(cell: str, width: int = 40) -> str:
    return cell if len(cell) <= width else f"{cell[:width]}... ({len(cell)} characters)"
