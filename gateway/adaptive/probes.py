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
from collections.abc import Mapping
from dataclasses import dataclass, field
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
