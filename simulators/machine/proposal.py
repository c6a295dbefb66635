"""A proposed experiment (``cncgw plan``) as a scenario of the simulated machine.

A proposal holds factor levels (what production showed); the simulated machine takes commands. The
spindle speed is the speed factor; each feed axis that moves reciprocates along one straight line whose
components are proportional to the axes' mean |feed| factors (the longest 300 mm, within every travel),
at a path feed that gives those feeds, within the axes' rapid traverse. The currents are the machine's
own answer to those commands: with other strokes than production's they differ somewhat (a short stroke
accelerates more often), so the plan's ratios are a target the recording can be checked against with
``cncgw estimate`` (its coverage notes). A step that cuts (plan found production cutting there: spindle
currents above their no-load level at that speed) takes the cutting power that brings the rotor current
squared to the step's level at its speed (the drive model's steady answer: the rotor carries the torque
current), within the drive's torque limit there, checked as a scenario's ``cutting_kw`` is.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import tomli_w

from simulators.machine.drives import FACTORS
from simulators.machine.params import DEFAULT_MACHINE, RAD_PER_RPM, MachineParams
from simulators.machine.scenario import cutting_limit

#: the longest stroke component (mm)
STROKE_MM = 300.0


def simulatable(factors: Sequence[str]) -> bool:
    """Whether a profile's factors are the simulated machine's (its scenarios can then be written)."""
    return set(FACTORS) <= set(factors)


def cutting_kw(rpm: float, i2_sq: float, machine: MachineParams = DEFAULT_MACHINE) -> tuple[float, bool]:
    """(cutting power in kW, whether the drive's limit capped it) for a rotor current squared ``i2_sq`` at ``rpm``.

    At steady speed I2 = rotor_ratio x iq, iq = (friction + P / w) / (k_T x flux): solved for P.
    """
    sp = machine.spindle
    w = rpm * RAD_PER_RPM
    flux = min(1.0, sp.omega_base / w)
    torque = math.sqrt(max(i2_sq, 0.0)) / sp.rotor_ratio * sp.torque_constant_nm_per_a * flux
    want = max(torque - sp.coulomb_nm - sp.viscous_nm_s * w, 0.0) * w / 1000.0
    _, most = cutting_limit(sp, rpm)
    # 95 % of the limit: the speed loop's correction at engagement needs some torque left
    return (round(min(want, 0.95 * most), 2), want > 0.95 * most)


def segment(levels: Mapping[str, float], minutes: float, machine: MachineParams = DEFAULT_MACHINE, *,
            cutting: bool = False) -> dict:
    """One scenario segment holding factor ``levels`` (absolute values) for ``minutes``.

    ``cutting``: with the cut that brings the rotor current squared to ``levels["spindle_i2_sq"]``
    (:func:`cutting_kw`).
    """
    seg: dict = {"minutes": max(1, round(minutes))}
    rpm = float(levels.get("spindle_speed", 0.0))
    if rpm >= 1.0:
        seg["spindle_rpm"] = float(min(round(rpm), machine.spindle.max_speed_rpm))
        if cutting:
            kw, _ = cutting_kw(seg["spindle_rpm"], float(levels.get("spindle_i2_sq", 0.0)), machine)
            if kw > 0.0:
                seg["cutting_kw"] = kw
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
                      hours: float, lead_in_min: float, seed: int, note: str = "",
                      cutting: Sequence[bool] = ()) -> str:
    """Scenario TOML: at rest ``lead_in_min``, each (levels, minutes) in turn, at rest to ``hours``.

    ``cutting[k]``: step ``k`` cuts (:func:`segment`). ``seed``: of the sensor noise. The scenario runs the
    nominal machine; add ``[plant] variant = N`` for another.
    """
    cuts = list(cutting) + [False] * (len(steps) - len(cutting))
    segments = {f"step{k + 1}": segment(levels, minutes, cutting=cut)
                for k, ((levels, minutes), cut) in enumerate(zip(steps, cuts, strict=True))}
    doc = {"scenario": {"name": name, "description": description, "seed": seed,
                        "initial_idle_min": round(lead_in_min), "duration_h": hours},
           "room": {"temperature_c": 20.0}, "sensors": {"noise_um": 0.1}, "segments": segments}
    head = "# proposed by cncgw plan" + (f"; {note}" if note else "") + "\n"
    return head + tomli_w.dumps(doc)
