"""From a scenario's schedule to the drives' pieces: spindle speed commands and trapezoidal moves.

A reciprocating segment runs whole cycles only (out along the stroke, back, with ``dwell_s`` at each
end), so the axes are back where they started when the segment ends, as a part program would leave them;
what is left of the segment is spent at rest. Each move is a trapezoid along the stroke vector, or a
triangle when the stroke is too short to reach the feed rate; every axis gets its share of the path's
velocity and acceleration, so a diagonal is a true linear interpolation.
"""

from __future__ import annotations

import math

import numpy as np

from simulators.machine.drives import AxisTimeline, DriveTimeline, SpindleTimeline
from simulators.machine.params import AXES, MachineParams
from simulators.machine.scenario import Scenario, Segment


def spindle_commands(scenario: Scenario) -> tuple[list[float], list[float]]:
    """Speed command times (s) and values (rpm): 0 at the start and after every segment."""
    times, rpm, _ = spindle_commands_with_cut(scenario)
    return times, rpm


def spindle_commands_with_cut(scenario: Scenario) -> tuple[list[float], list[float], list[float]]:
    """Speed command times (s), values (rpm) and the cutting power (W) taken while each one holds."""
    times, rpm, cut = [0.0], [0.0], [0.0]
    for seg in scenario.segments:
        if seg.changes_per_min > 0:
            step = 60.0 / seg.changes_per_min
            n = max(1, math.floor(seg.duration_s / step + 1e-9))
            k = np.arange(n)
            times.extend((seg.start_s + k * step).tolist())
            rpm.extend(np.take(seg.spindle_rpm, k % len(seg.spindle_rpm)).tolist())
            cut.extend([seg.cutting_w] * n)
        else:
            times.append(seg.start_s)
            rpm.append(seg.spindle_rpm[0])
            cut.append(seg.cutting_w)
        times.append(seg.end_s)
        rpm.append(0.0)
        cut.append(0.0)
    return times, rpm, cut


def _move_pattern(seg: Segment) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    """One there-and-back cycle along the path.

    Piece offsets (s), path velocity (m/s) and acceleration at each piece's start, direction, and the
    cycle's period.
    """
    length = math.sqrt(sum(s * s for s in seg.stroke_mm)) / 1000.0
    v, a = seg.feed_mm_min / 60000.0, seg.accel_m_s2
    if length >= v * v / a:
        t_acc, t_const, v_peak = v / a, (length - v * v / a) / v, v
    else:  # too short to reach the feed rate: a triangle
        t_acc, t_const, v_peak = math.sqrt(length / a), 0.0, math.sqrt(length * a)
    t_move = 2 * t_acc + t_const
    offsets, vel, acc, direction = [], [], [], []
    for k, d in enumerate((1.0, -1.0)):
        t0 = k * (t_move + seg.dwell_s)
        offsets += [t0, t0 + t_acc]
        vel += [0.0, d * v_peak]
        acc += [d * a, 0.0]
        if t_const > 0:  # the cruise piece exists only on a trapezoid
            offsets.append(t0 + t_acc + t_const)
            vel.append(d * v_peak)
            acc.append(-d * a)
        else:
            acc[-1] = -d * a
        direction += [d] * (3 if t_const > 0 else 2)
        if seg.dwell_s > 0:
            offsets.append(t0 + t_move)
            vel.append(0.0)
            acc.append(0.0)
            direction.append(0.0)
    return (np.array(offsets), np.array(vel), np.array(acc), np.array(direction),
            2 * (t_move + seg.dwell_s))


def axis_pieces(scenario: Scenario) -> dict[str, tuple[np.ndarray, ...]]:
    """Per axis: piece start times, start velocities, accelerations, directions (all arrays)."""
    parts: dict[str, list[tuple[np.ndarray, ...]]] = {a: [] for a in AXES}
    rest = (np.zeros(1), np.zeros(1), np.zeros(1))

    def at_rest(t: float) -> tuple[np.ndarray, ...]:
        return (np.array([t]), *rest)

    for a in AXES:
        parts[a].append(at_rest(0.0))
    for seg in scenario.segments:
        if not seg.moves:
            continue
        offsets, vel, acc, direction, period = _move_pattern(seg)
        n = math.floor(seg.duration_s / period + 1e-9)
        starts = (seg.start_s + period * np.arange(n))[:, None]
        t0 = (starts + offsets[None, :]).ravel()
        length = math.sqrt(sum(s * s for s in seg.stroke_mm))
        for a, s in zip(AXES, seg.stroke_mm, strict=True):
            if s == 0.0:
                continue
            u = s / length
            parts[a].append((t0, np.tile(vel * u, n), np.tile(acc * u, n), np.tile(direction * math.copysign(1, u), n)))
            parts[a].append(at_rest(seg.start_s + n * period))
    out = {}
    for a in AXES:
        t0, v0, acc, direction = (np.concatenate(x) for x in zip(*parts[a], strict=True))
        # drop a rest piece that follows another rest piece: a window there is one steady piece
        idle = (v0 == 0) & (acc == 0)
        keep = np.ones(len(t0), dtype=bool)
        keep[1:] = ~(idle[1:] & idle[:-1])
        out[a] = (t0[keep], v0[keep], acc[keep], direction[keep])
    return out


def compile_drives(scenario: Scenario, machine: MachineParams) -> DriveTimeline:
    """The drives' pieces for a whole scenario (and at rest for ever after it)."""
    times, rpm, cut = spindle_commands_with_cut(scenario)
    spindle = SpindleTimeline.compile(machine.spindle, times, rpm, cut if any(cut) else None)
    axes = {}
    for a, (t0, v0, acc, direction) in axis_pieces(scenario).items():
        axes[a] = AxisTimeline(params=machine.axes[a], t0=t0, v0=v0, a=acc, direction=direction)
    return DriveTimeline(machine=machine, spindle=spindle, axes=axes)
