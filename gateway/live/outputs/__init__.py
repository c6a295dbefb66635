"""Outputs beside OPC UA: what leaves the gateway once a window is done (Telegraf's outputs, small).

An output is started with the gateway (after the store and the estimator, before the samplers), handed one
:class:`WindowSnapshot` per finished window on the window closer's thread (so ``window`` must be cheap:
make the snapshot durable and return; a thread of the output's own does the network), and stopped after
the samplers. :func:`snapshot` builds the snapshot from what the live gateway knows after a window: the
record, the estimate that followed, the compensation writer's status and the active alarms.

Quality travels with every value (:class:`Quality`): ``good`` only when the number is finite and rests on
a good window; a value the gateway holds but does not trust (an estimate over a filled gap, factors of a
window with too little coverage) is ``uncertain``; no number at all is ``bad`` with ``value`` null. A NaN
is never sent as a number.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Protocol

from gateway.live.audit import Alarm
from gateway.live.compensation import WriterStatus
from gateway.live.tracking import EstimateUpdate
from gateway.profile import Profile
from gateway.windows import WindowRecord


class Quality(enum.StrEnum):
    """The quality a published value carries (OPC UA's Good / Uncertain / Bad, in words)."""

    GOOD = "good"
    UNCERTAIN = "uncertain"
    BAD = "bad"


@dataclass(frozen=True, slots=True)
class Value:
    """A number with its quality; ``value`` is ``None`` (JSON null) whenever it is not finite."""

    value: float | None
    quality: Quality

    @classmethod
    def of(cls, x: float | None, *, trusted: bool) -> Value:
        if x is None or not math.isfinite(x):
            return cls(None, Quality.BAD)
        return cls(float(x), Quality.GOOD if trusted else Quality.UNCERTAIN)

    def as_json(self) -> dict[str, Any]:
        return {"value": self.value, "quality": self.quality.value}


def _frozen(m: Mapping[str, Any] | None = None) -> MappingProxyType[str, Any]:
    return MappingProxyType(dict(m or {}))


@dataclass(frozen=True, kw_only=True, slots=True)
class WindowSnapshot:
    """What the gateway knows once window ``window`` is done (see the module docstring).

    ``end_s``: the window's end, clock seconds (epoch seconds on a real clock). ``status``: the record's
    (``good`` or ``insufficient``). ``factors``: name -> value; ``factor_units``: name -> unit.
    ``estimate_um``: axis -> um; ``usable``: the estimate may drive compensation (else ``reason``).
    ``commanded_um``/``applied_um``: the offsets commanded and read back from the CNC (empty when the
    writer has none) as the writer reports them when the window is handed over (the write that follows this
    window may still be on its way: the next window's message shows it); ``mode``: ``write`` or ``dry-run``;
    ``verified``: the last write read back equal.
    """

    machine: str
    window: int
    end_s: float
    status: str
    coverage: float
    samples_taken: int
    samples_expected: int
    missed_ticks: int
    devices_in_error: tuple[str, ...] = ()
    factors: MappingProxyType[str, float] = field(default_factory=_frozen)
    factor_units: MappingProxyType[str, str] = field(default_factory=_frozen)
    estimate_um: MappingProxyType[str, float] = field(default_factory=_frozen)
    usable: bool = False
    reason: str = ""
    filled_windows: int = 0
    mode: str = "dry-run"
    commanded_um: MappingProxyType[str, float] = field(default_factory=_frozen)
    applied_um: MappingProxyType[str, float] = field(default_factory=_frozen)
    verified: bool = False
    writes: int = 0
    alarms: tuple[str, ...] = ()
    window_reason: str = ""  # why the window is not good ("" when it is)
    #: the estimate's 95 % half-band per axis (um) when probes update the model ([probes]); empty otherwise
    band95_um: MappingProxyType[str, float] = field(default_factory=_frozen)
    source: str = "live"  # "live", or "records" for a window rebuilt from the records store after a restart


class Output(Protocol):
    """What the live gateway needs of an output (see the module docstring)."""

    name: str

    def start(self) -> Any: ...

    def window(self, snapshot: WindowSnapshot) -> None: ...

    def stop(self) -> None: ...


def snapshot(profile: Profile, record: WindowRecord, update: EstimateUpdate, writer: WriterStatus | None,
             alarms: Iterable[Alarm] = ()) -> WindowSnapshot:
    """The snapshot of ``record``, the ``update`` that followed it, the writer's status and the active alarms."""
    last = writer.last_write if writer is not None else None
    return WindowSnapshot(
        machine=profile.name, window=record.index, end_s=record.end_s, status=record.status,
        coverage=record.coverage, samples_taken=record.samples_taken, samples_expected=record.samples_expected,
        missed_ticks=record.missed_ticks, devices_in_error=tuple(record.devices_in_error),
        factors=_frozen(record.factors), factor_units=_frozen({f.name: f.unit for f in profile.factors}),
        estimate_um=_frozen(update.estimate_um), usable=update.usable, reason=update.reason,
        filled_windows=update.filled, mode=writer.mode if writer is not None else "dry-run",
        commanded_um=_frozen(writer.commanded_um if writer is not None else {}),
        applied_um=_frozen(last.applied_um if last is not None else {}),
        verified=last.verified if last is not None else False, writes=writer.writes if writer is not None else 0,
        alarms=tuple(f"{a.name}: {a.message}" for a in alarms), window_reason=record.reason,
        band95_um=_frozen(update.band95_um))


def record_snapshot(profile: Profile, record: WindowRecord) -> WindowSnapshot:
    """A window known only from the records store (the gateway stopped before an output took it).

    Factors and quality come from the record; the estimate and offsets of that moment are not stored, so
    they are left out (consumers see ``source = "records"``).
    """
    return WindowSnapshot(
        machine=profile.name, window=record.index, end_s=record.end_s, status=record.status,
        coverage=record.coverage, samples_taken=record.samples_taken, samples_expected=record.samples_expected,
        missed_ticks=record.missed_ticks, devices_in_error=tuple(record.devices_in_error),
        factors=_frozen(record.factors), factor_units=_frozen({f.name: f.unit for f in profile.factors}),
        reason="window taken from the records store after a restart: estimate and offsets not stored",
        window_reason=record.reason, source="records")
