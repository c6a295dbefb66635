"""The MQTT payloads of one window: JSON, every number with its unit and quality, keyed by window id.

Four messages a window, one per topic ``<prefix>/<machine>/<kind>``:

- ``estimate``: the estimated thermal displacement per axis (um), whether it may drive compensation; with
  ``[probes]`` also ``band95``: per axis the 95 % half-band (um) of the estimate updated by probes;
- ``offsets``: the offsets commanded to the CNC and read back (um), the writer's mode, verified or not;
- ``factors``: the window's heat-generating factors, each with its unit;
- ``health``: the window's status and why it is not good, coverage, samples, missed ticks, devices in error,
  active alarms.

Every message carries ``machine``, ``window`` (the window index: ``end_s / window_s - 1``, unique per
machine and increasing) and ``end_s`` (the window's end, epoch seconds): a consumer de-duplicates QoS 1
re-deliveries by ``(machine, window, kind)``. ``schema`` names the payload version.
"""

from __future__ import annotations

import json
import math
from typing import Any

from gateway.live.outputs import Quality, Value, WindowSnapshot

SCHEMA = "cncgw.window/1"
KINDS = ("estimate", "offsets", "factors", "health")


def _values(values: Any, *, trusted: bool) -> dict[str, Any]:
    return {k: Value.of(v, trusted=trusted).as_json() for k, v in values.items()}


def window_payloads(s: WindowSnapshot) -> list[tuple[str, dict[str, Any]]]:
    """``(kind, payload)`` for the four messages of window ``s`` (see the module docstring)."""
    head = {"schema": SCHEMA, "machine": s.machine, "window": s.window, "end_s": s.end_s, "source": s.source}
    good = s.status == "good"
    estimate = {**head, "unit": "um", "usable": s.usable and good, "reason": s.reason,
                "filled_windows": s.filled_windows,
                "values": _values(s.estimate_um, trusted=s.usable and good)}
    if s.band95_um:  # the model updated by probes: the true displacement is within +- this, 95 % of the time
        estimate["band95"] = _values(s.band95_um, trusted=s.usable and good)
    if s.source == "records":
        estimate["values"] = {}
        estimate.pop("band95", None)
    # the offsets are what the CNC was told and showed: trusted once a write was read back equal
    offsets = {**head, "unit": "um", "mode": s.mode, "verified": s.verified, "writes": s.writes,
               "commanded": _values(s.commanded_um, trusted=True),
               "applied": _values(s.applied_um, trusted=s.verified)}
    factors = {**head, "status": s.status,
               "values": {k: {**Value.of(v, trusted=good).as_json(), "unit": s.factor_units.get(k, "")}
                          for k, v in s.factors.items()}}
    coverage = s.coverage if math.isfinite(s.coverage) else None
    health = {**head, "status": s.status, "reason": s.window_reason, "coverage": coverage,
              "samples_taken": s.samples_taken, "samples_expected": s.samples_expected, "missed_ticks": s.missed_ticks,
              "devices_in_error": list(s.devices_in_error), "alarms": list(s.alarms),
              "quality": (Quality.GOOD if good and not s.alarms else Quality.UNCERTAIN if good else Quality.BAD).value}
    return [("estimate", estimate), ("offsets", offsets), ("factors", factors), ("health", health)]


def encode(payload: dict[str, Any]) -> bytes:
    """Strict JSON (a NaN or inf raises: never on the wire), compact."""
    return json.dumps(payload, separators=(",", ":"), allow_nan=False).encode()
