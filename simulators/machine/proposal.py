"""A proposed experiment (``cncgw plan``) as a scenario of the simulated machine.

A proposal holds factor levels (what production showed); the simulated machine takes commands. The
spindle speed is the speed factor; each feed axis that moves reciprocates along one straight line whose
components are proportional to the axes' mean |feed| factors (the longest 300 mm, within every travel),
at a path feed that gives those feeds, within the axes' rapid traverse. The currents are the machine's
own answer to those commands: with other strokes than production's they differ somewhat (a short stroke
accelerates more often), so the plan's ratios are a target the recording can be checked against with
``cncgw estimate`` (its coverage notes). The simulator has no cutting load: a state whose currents came
from one is reached in speed and feed only, and the scenario says so.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import tomli_w

from simulators.machine.drives import FACTORS
from simulators.machine.params import DEFAULT_MACHINE, MachineParams

#: the longest stroke component (mm)
STROKE_MM = 300.0


def simulatable(factors: Sequence[str]) -> bool:
    """Whether a profile's factors are the simulated machine's (its scenarios can then be written)."""
    return set(FACTORS) <= set(factors)


def segment(levels: Mapping[str, float], minutes: float, machine: MachineParams = DEFAULT_MACHINE) -> dict:
    """One scenario segment holding factor ``levels`` (absolute values) for ``minutes``."""
    seg: dict = {"minutes": max(1, round(minutes))}
    rpm = float(levels.get("spindle_speed", 0.0))
    if rpm >= 1.0:
        seg["spindle_rpm"] = float(min(round(rpm), machine.spindle.max_speed_rpm))
    feeds = {a: max(float(levels.get(f"{a}_feed", 0.0)), 0.0) for a in ("x", "y", "z")}
    top = max(feeds.values())
    if top >= 1.0:
        scale = min(STROKE_MM, *(0.8 * machine.axes[a].travel_mm for a, v in feeds.items() if v > 0)) / top
        stroke = {a: round(v * scale, 1) for a, v in feeds.items() if v * scale >= 1.0}
        length = math.sqrt(sum(s * s for s in stroke.values()))
        # each axis cruises at its feed when the path runs at |feeds|; accelerations make the mean a little lower
        path = math.sqrt(sum(v * v for a, v in feeds.items() if a in stroke)) * 1.05
        limit = min(machine.axes[a].max_feed_mm_min * length / abs(s) for a, s in stroke.items())
        seg["stroke_mm"] = stroke
        seg["feed_mm_min"] = float(round(min(path, 0.95 * limit)))
    return seg


def proposal_scenario(name: str, description: str, steps: Sequence[tuple[Mapping[str, float], float]], *,
                      hours: float, lead_in_min: float, seed: int, note: str = "") -> str:
    """Scenario TOML: at rest ``lead_in_min``, each (levels, minutes) in turn, at rest to ``hours``.

    ``seed``: of the sensor noise. The scenario runs the nominal machine; add ``[plant] variant = N`` for
    another.
    """
    segments = {f"step{k + 1}": segment(levels, minutes) for k, (levels, minutes) in enumerate(steps)}
    doc = {"scenario": {"name": name, "description": description, "seed": seed,
                        "initial_idle_min": round(lead_in_min), "duration_h": hours},
           "room": {"temperature_c": 20.0}, "sensors": {"noise_um": 0.1}, "segments": segments}
    head = "# proposed by cncgw plan" + (f"; {note}" if note else "") + "\n"
    return head + tomli_w.dumps(doc)
