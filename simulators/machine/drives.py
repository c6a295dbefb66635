"""The drives: spindle and X/Y/Z feed axes, as the CNC's 2 ms samples see them.

Both kinds of drive are compiled once into *pieces* on which the motion has a closed form, so a value at
any instant costs a few array operations and a one-minute window of 30 000 samples is evaluated
vectorised, never with a Python loop per 2 ms step:

- Spindle (speed loop with a ~50 ms closed-loop time constant and a current limit). Between two speed
  commands the speed is one of: an exponential approach to the command (linear region: the controller's
  torque ``J (w_c - w) / tau`` plus the friction it feeds forward), a torque-limited ramp below base speed
  (``J dw/dt = +-T_max - T_c - b w``: exponential with the long time constant J/b), a current-limited
  ramp above base speed (constant power ``P``: ``J w dw/dt = +-P - T_c w - b w^2``, whose time as a
  function of speed has a closed form, inverted by a few Newton steps), or off (a zero command has brought
  the speed below 1 rpm and the drive is disabled: no current). The compiler walks the commands once and
  stores each piece's start time and constants. A test checks all four against a brute-force integration.
- Feed axes (trapezoidal moves): every piece has constant acceleration, so ``v = v0 + a (t - t0)``; the
  Coulomb friction's sign is the piece's direction of motion (kinetic friction from the first instant of a
  move), so a sample on a piece boundary is never ambiguous.

A window whose samples all lie on one steady piece (spindle off or settled, axis at rest or at constant
velocity) is evaluated once instead of 30 000 times.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from simulators.machine.params import AXES, RAD_PER_RPM, FeedAxisParams, MachineParams, SpindleParams

#: channel names, as in profiles/sim-vmc.toml
CHANNELS = ("spindle_speed", "spindle_i1", "spindle_i2", "x_velocity", "y_velocity", "z_velocity",
            "x_current", "y_current", "z_current")
#: factor names in the profile's order, then the extra window statistics the heat model needs
FACTORS = ("spindle_speed", "spindle_i1_sq", "spindle_i2_sq", "x_feed", "x_i_sq", "y_feed", "y_i_sq",
           "z_feed", "z_i_sq")
EXTRA_STATS = ("spindle_omega_sq", "spindle_on", "x_v_sq", "y_v_sq", "z_v_sq")
STATS = FACTORS + EXTRA_STATS
STAT_INDEX = {name: i for i, name in enumerate(STATS)}

OFF, LIN, SAT_TORQUE, SAT_POWER = 0, 1, 2, 3
_SETTLED = 1e-14  # a linear piece whose transient has decayed below this fraction counts as steady


# --------------------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class SpindleTimeline:
    """The spindle's motion as pieces.

    Per piece: start ``t0`` (s), ``kind``, start speed ``w0`` and ``wt`` (the command on a linear piece, the
    asymptote on a torque-limited one), ``sign`` (+1 accelerating, -1 braking), and ``load_nm``: the cutting
    torque on the spindle (Nm, 0 without a cut).

    The cutting load: a job that cuts takes a constant cutting power ``P`` (W, the scenario's
    ``cutting_kw``) at its commanded speed, so its torque is ``P / w_c``. The tool engages once the
    spindle is in its linear region at that command (after the acceleration ramp), and the speed loop
    feeds the load's torque forward to the current loop: the motor torque is the controller's torque plus
    the load, the speed is unchanged (the 50 ms loop's speed dip at engagement is left out). The torque
    then raises ``iq = T / k_T`` and with it both currents and their Joule heat (the heat model's
    stator and rotor losses); the cutting heat at the tool and workpiece is not modelled.
    """

    params: SpindleParams
    t0: np.ndarray
    kind: np.ndarray
    w0: np.ndarray
    wt: np.ndarray
    sign: np.ndarray
    load_nm: np.ndarray | None = None

    @classmethod
    def compile(cls, params: SpindleParams, times_s: Sequence[float], commands_rpm: Sequence[float],
                cutting_w: Sequence[float] | None = None) -> SpindleTimeline:
        """Pieces for speed commands ``commands_rpm[i]`` given at ``times_s[i]`` (sorted, first at 0).

        ``cutting_w[i]``: the cutting power (W) taken while command ``i`` holds (none by default).
        """
        if params.viscous_nm_s <= 0 or params.time_constant_s <= 0:
            raise ValueError("spindle viscous drag and time constant must be > 0")
        pieces: list[tuple[float, int, float, float, float]] = []
        loads: list[float] = []
        w = 0.0
        times = [float(t) for t in times_s]
        cuts = [0.0] * len(times) if cutting_w is None else [float(c) for c in cutting_w]
        for i, (t, rpm, cut) in enumerate(zip(times, commands_rpm, cuts, strict=True)):
            t_end = times[i + 1] if i + 1 < len(times) else math.inf
            if t_end > t:
                wc = float(rpm) * RAD_PER_RPM
                first = len(pieces)
                w = _advance(params, w, wc, t, t_end, pieces)
                load = cut / wc if cut > 0.0 and wc > 0.0 else 0.0
                loads += [load if piece[1] == LIN else 0.0 for piece in pieces[first:]]
        merged, merged_loads = [pieces[0]], [loads[0]]
        for p, load in zip(pieces[1:], loads[1:], strict=True):  # consecutive "off" pieces are one
            if not (p[1] == OFF and merged[-1][1] == OFF):
                merged.append(p)
                merged_loads.append(load)
        arr = np.array(merged, dtype=float)
        load_arr = np.array(merged_loads, dtype=float)
        return cls(params=params, t0=arr[:, 0].copy(), kind=arr[:, 1].astype(np.int8), w0=arr[:, 2].copy(),
                   wt=arr[:, 3].copy(), sign=arr[:, 4].copy(), load_nm=load_arr if load_arr.any() else None)

    def evaluate(self, t: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Speed (rad/s), motor torque (Nm) and drive-on mask at times ``t`` on pieces ``idx``."""
        p = self.params
        kind = self.kind[idx]
        dt = t - self.t0[idx]
        w0, wt, sign = self.w0[idx], self.wt[idx], self.sign[idx]
        w = np.zeros_like(t)
        torque = np.zeros_like(t)
        lin = kind == LIN
        if lin.any():
            wl = wt[lin] + (w0[lin] - wt[lin]) * np.exp(-dt[lin] / p.time_constant_s)
            w[lin] = wl
            torque[lin] = p.inertia_kg_m2 * (wt[lin] - wl) / p.time_constant_s + p.coulomb_nm + p.viscous_nm_s * wl
            if self.load_nm is not None:  # without a cut nothing is added: the same sums, bit for bit
                torque[lin] += self.load_nm[idx[lin]]
        sat = kind == SAT_TORQUE
        if sat.any():
            w[sat] = w0[sat] + (w0[sat] - wt[sat]) * np.expm1(-dt[sat] * p.viscous_nm_s / p.inertia_kg_m2)
            torque[sat] = sign[sat] * p.torque_limit_nm
        pw = kind == SAT_POWER
        if pw.any():
            wp = _power_speed(p, w0[pw], sign[pw], dt[pw])
            w[pw] = wp
            torque[pw] = sign[pw] * p.power_limit_w / np.maximum(wp, p.omega_base)
        return w, torque, kind != OFF

    def currents(self, w: np.ndarray, torque: np.ndarray, on: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Stator current I1 and rotor current I2 (A RMS) from speed and torque (field-oriented control)."""
        p = self.params
        flux = np.minimum(1.0, p.omega_base / np.maximum(w, 1e-9))  # field weakening above base speed
        iq = torque / (p.torque_constant_nm_per_a * flux)
        i1 = np.where(on, np.hypot(p.magnetising_a * flux, iq), 0.0)
        i2 = np.where(on, p.rotor_ratio * np.abs(iq), 0.0)
        return i1, i2

    def steady(self, i: int, t_first: float) -> bool:
        """Whether piece ``i`` gives constant values from ``t_first`` on."""
        k = self.kind[i]
        if k == OFF:
            return True
        if k != LIN:
            return False
        decay = math.exp(-(t_first - self.t0[i]) / self.params.time_constant_s)
        return abs(self.w0[i] - self.wt[i]) * decay <= _SETTLED * (1.0 + abs(self.wt[i]))


def _demand(p: SpindleParams, w: float, wc: float) -> float:
    """Torque the linear controller asks for: the loop's correction plus the friction it feeds forward."""
    return p.inertia_kg_m2 * (wc - w) / p.time_constant_s + p.coulomb_nm + p.viscous_nm_s * w


def _limit(p: SpindleParams, w: float) -> float:
    return p.torque_limit_nm * min(1.0, p.omega_base / w) if w > 0 else p.torque_limit_nm


def _advance(p: SpindleParams, w: float, wc: float, t: float, t_end: float,
             out: list[tuple[float, int, float, float, float]]) -> float:
    """Append the pieces from ``t`` to ``t_end`` at command ``wc`` starting at speed ``w``.

    Returns the speed at ``t_end``.
    """
    J, tau, b, Tc, Tm = p.inertia_kg_m2, p.time_constant_s, p.viscous_nm_s, p.coulomb_nm, p.torque_limit_nm
    w_off = p.off_below_rpm * RAD_PER_RPM
    wb, P = p.omega_base, p.power_limit_w
    k_lin = J / tau - b
    while t < t_end:
        if wc == 0.0 and w <= w_off:
            out.append((t, OFF, 0.0, 0.0, 0.0))
            return 0.0
        demand, lim = _demand(p, w, wc), _limit(p, w)
        ramp: tuple[int, float, float, float] | None = None  # kind, end speed, asymptote, sign
        if wc > w and demand > lim * (1 + 1e-12):
            if w < wb:  # torque-limited ramp up
                ramp = (SAT_TORQUE, min((J * wc / tau + Tc - Tm) / k_lin, wb), (Tm - Tc) / b, 1.0)
            else:  # current-limited ramp up above base speed: constant power until demand = P / w
                B = J * wc / tau + Tc
                disc = B * B - 4.0 * k_lin * P
                if disc >= 0:
                    ramp = (SAT_POWER, (B + math.sqrt(disc)) / (2.0 * k_lin), 0.0, 1.0)
        elif wc < w and demand < -lim * (1 + 1e-12):
            if w > wb:  # braking at constant power down to base speed, or until demand = -P / w
                B = J * wc / tau + Tc
                ramp = (SAT_POWER, max((B + math.sqrt(B * B + 4.0 * k_lin * P)) / (2.0 * k_lin), wb), 0.0, -1.0)
            else:  # torque-limited braking (friction helps)
                ramp = (SAT_TORQUE, (J * wc / tau + Tc + Tm) / k_lin, -(Tm + Tc) / b, -1.0)
        if ramp is None or (ramp[1] - w) * ramp[3] <= 0.0:
            # linear region (also when a ramp would end where it starts: the limit is not reached)
            out.append((t, LIN, w, wc, 0.0))
            if wc == 0.0:  # the drive switches off when the speed falls below w_off
                t_off = t + tau * math.log(w / w_off)
                if t_off < t_end:
                    t, w = t_off, w_off
                    continue
            return wc + (w - wc) * math.exp(-(t_end - t) / tau) if math.isfinite(t_end) else wc
        kind, w_end, w_inf, sign = ramp
        out.append((t, kind, w, w_inf, sign))
        if kind == SAT_TORQUE:
            dur = J / b * math.log1p((w - w_end) / (w_end - w_inf))
        else:
            dur = float(_power_time(p, np.array([w_end]), sign)[0] - _power_time(p, np.array([w]), sign)[0])
        if t + dur >= t_end:  # the next command comes before the ramp ends
            if kind == SAT_TORQUE:
                return w + (w - w_inf) * math.expm1(-(t_end - t) * b / J)
            return float(_power_speed(p, np.array([w]), np.array([sign]), np.array([t_end - t]))[0])
        t, w = t + dur, w_end
    return w


def _power_time(p: SpindleParams, w: np.ndarray, sign: float | np.ndarray) -> np.ndarray:
    """Time (s, up to a constant) at which a constant-power ramp with friction passes speed ``w``.

    ``J w dw/dt = s P - T_c w - b w^2``, so ``t(w) = -J * integral w / Q(w) dw`` with ``Q = b w^2 + T_c w -
    s P``: a logarithm plus a log or arctan term depending on the sign of ``T_c^2 + 4 b s P``.
    """
    J, b, Tc, P = p.inertia_kg_m2, p.viscous_nm_s, p.coulomb_nm, p.power_limit_w
    sign = np.asarray(sign, dtype=float)
    q = b * w * w + Tc * w - sign * P
    delta = Tc * Tc + 4.0 * b * sign * P
    root = np.sqrt(np.abs(delta))
    x = 2.0 * b * w + Tc
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_q = np.where(delta > 0, np.log(np.abs((x - root) / (x + root))) / root,
                         2.0 / root * np.arctan(x / root))
    return -J * (np.log(np.abs(q)) / (2.0 * b) - Tc / (2.0 * b) * inv_q)


def _power_speed(p: SpindleParams, w0: np.ndarray, sign: np.ndarray, dt: np.ndarray) -> np.ndarray:
    """Speed ``dt`` after the start of a constant-power ramp from ``w0``.

    Newton on ``t(w)``, started from the friction-free solution (``w^2`` linear in time); it converges in a
    few steps because friction is a few per cent of the torque there.
    """
    J, b, Tc, P = p.inertia_kg_m2, p.viscous_nm_s, p.coulomb_nm, p.power_limit_w
    target = _power_time(p, w0, sign) + dt
    w = np.sqrt(np.maximum(w0 * w0 + sign * 2.0 * P * dt / J, 1e-6))
    for _ in range(8):
        slope = J * w / (sign * P - Tc * w - b * w * w)  # dt/dw
        w = w - (_power_time(p, w, sign) - target) / slope
    return w


# --------------------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class AxisTimeline:
    """One feed axis as constant-acceleration pieces.

    Per piece: start ``t0`` (s), velocity ``v0`` (m/s), acceleration ``a`` (m/s^2) and direction of motion
    ``direction`` (+1, -1, 0 at rest).
    """

    params: FeedAxisParams
    t0: np.ndarray
    v0: np.ndarray
    a: np.ndarray
    direction: np.ndarray

    def evaluate(self, t: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Velocity (m/s) and motor current (A, signed) at times ``t`` on pieces ``idx``."""
        p = self.params
        a = self.a[idx]
        direction = self.direction[idx]
        v = self.v0[idx] + a * (t - self.t0[idx])
        torque = (p.accel_torque_nm_per_m_s2 * a
                  + (p.guide_friction_n * direction + p.viscous_n_s_per_m * v) * p.force_to_torque
                  + p.screw_drag_nm * direction + p.gravity_torque_nm)
        return v, torque / p.torque_constant_nm_per_a

    def steady(self, i: int, t_first: float) -> bool:
        return self.a[i] == 0.0

    def window_sums(self, n_first: int, n_last: int, dt: float, i0: int, i1: int) -> np.ndarray:
        """Mean |v| (mm/min), mean v^2 and mean I^2 over the samples ``n_first..n_last`` in closed form.

        On a piece, ``v`` and the current are linear in time and keep their sign, so the sums over its
        samples need only the sums of ``tau`` and ``tau^2`` (tau: time since the piece's start).
        """
        p = self.params
        sl = slice(i0, i1)
        t0, v0, a, d = self.t0[sl], self.v0[sl], self.a[sl], self.direction[sl]
        # first sample on each piece: the smallest n with n * dt >= t0 (the searchsorted rule)
        k = np.ceil(t0 / dt)
        k -= (k - 1) * dt >= t0
        k += k * dt < t0
        k = np.clip(k, n_first, n_last + 1)
        k[0] = n_first
        c = np.diff(np.append(k, n_last + 1))
        e = k * dt - t0
        s1 = c * e + dt * c * (c - 1) / 2.0
        s2 = c * e * e + e * dt * c * (c - 1) + dt * dt * (c - 1) * c * (2 * c - 1) / 6.0
        alpha = (p.accel_torque_nm_per_m_s2 * a + (p.guide_friction_n * d + p.viscous_n_s_per_m * v0)
                 * p.force_to_torque + p.screw_drag_nm * d + p.gravity_torque_nm) / p.torque_constant_nm_per_a
        beta = p.viscous_n_s_per_m * a * p.force_to_torque / p.torque_constant_nm_per_a
        n = n_last - n_first + 1
        return np.array([np.sum(d * (c * v0 + a * s1)) * 60000.0 / n,
                         np.sum(c * v0 * v0 + 2 * v0 * a * s1 + a * a * s2) / n,
                         np.sum(c * alpha * alpha + 2 * alpha * beta * s1 + beta * beta * s2) / n])


# --------------------------------------------------------------------------------------------------------
def _piece_index(t0: np.ndarray, t: np.ndarray, i0: int, i1: int) -> np.ndarray:
    """Piece of every sample time ``t`` (sorted), given that pieces ``i0..i1-1`` cover them.

    The last piece starting at or before each sample (the same rule as ``searchsorted(..., side="right") -
    1``).
    """
    if i1 - i0 == 1:
        return np.full(len(t), i0)
    cuts = np.searchsorted(t, t0[i0 + 1:i1], side="left")
    counts = np.diff(np.concatenate(([0], cuts, [len(t)])))
    return np.repeat(np.arange(i0, i1), counts)


def _span(t0: np.ndarray, t_first: float, t_last: float) -> tuple[int, int]:
    """Pieces ``i0..i1-1`` that hold the samples from ``t_first`` to ``t_last``."""
    return (max(int(np.searchsorted(t0, t_first, side="right")) - 1, 0),
            int(np.searchsorted(t0, t_last, side="right")))


_SLOTS = {"spindle": [STAT_INDEX[n] for n in ("spindle_speed", "spindle_omega_sq", "spindle_i1_sq",
                                              "spindle_i2_sq", "spindle_on")]}
_SLOTS |= {a: [STAT_INDEX[n] for n in (f"{a}_feed", f"{a}_v_sq", f"{a}_i_sq")] for a in AXES}


@dataclass(frozen=True, eq=False)
class DriveTimeline:
    """The spindle and the three feed axes of one scenario, evaluable at any instant."""

    machine: MachineParams
    spindle: SpindleTimeline
    axes: Mapping[str, AxisTimeline]
    #: statistics of steady pieces, by (drive, piece): a window at rest costs a lookup
    _steady: dict[tuple[str, int], np.ndarray] = field(default_factory=dict, repr=False)

    def _drive(self, name: str) -> SpindleTimeline | AxisTimeline:
        return self.spindle if name == "spindle" else self.axes[name]

    def values(self, t: float) -> dict[str, float]:
        """Instantaneous channel values at ``t`` (rpm, A, mm/min, A)."""
        ts = np.array([float(t)])
        idx = {d: np.array([_span(self._drive(d).t0, ts[0], ts[0])[0]]) for d in _SLOTS}
        return {k: float(v[0]) for k, v in self._channels(ts, idx).items()}

    def _channels(self, t: np.ndarray, idx: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        w, torque, on = self.spindle.evaluate(t, idx["spindle"])
        i1, i2 = self.spindle.currents(w, torque, on)
        out = {"spindle_speed": w / RAD_PER_RPM, "spindle_i1": i1, "spindle_i2": i2}
        for a in AXES:
            v, i = self.axes[a].evaluate(t, idx[a])
            out[f"{a}_velocity"] = v * 60000.0
            out[f"{a}_current"] = i
        return out

    def _stats(self, name: str, t: np.ndarray, idx: np.ndarray) -> np.ndarray:
        if name == "spindle":
            w, torque, on = self.spindle.evaluate(t, idx)
            i1, i2 = self.spindle.currents(w, torque, on)
            return np.array([np.mean(w) / RAD_PER_RPM, np.mean(w * w), np.mean(i1 * i1), np.mean(i2 * i2),
                             np.mean(on)])
        v, cur = self.axes[name].evaluate(t, idx)
        return np.array([np.mean(np.abs(v)) * 60000.0, np.mean(v * v), np.mean(cur * cur)])

    def window_stats(self, n_first: int, n_last: int, *, fast: bool = True) -> np.ndarray:
        """Means over the 2 ms samples ``n_first..n_last`` (times ``n * dt``), in :data:`STATS` order.

        Fast path: a drive that stays on one steady piece for the whole window is evaluated once (and
        remembered), and a feed axis's sums come in closed form per piece. ``fast=False`` evaluates every
        sample: the reference the fast path is tested and benchmarked against.
        """
        dt = self.machine.fast_period_s
        t_first, t_last = n_first * dt, n_last * dt
        t: np.ndarray | None = None
        out = np.empty(len(STATS))
        for name, slots in _SLOTS.items():
            drive = self._drive(name)
            i0, i1 = _span(drive.t0, t_first, t_last)
            if fast and i1 - i0 == 1 and drive.steady(i0, t_first):
                vals = self._steady.get((name, i0))
                if vals is None:
                    vals = self._steady[(name, i0)] = self._stats(name, np.array([t_last]), np.array([i0]))
            elif fast and isinstance(drive, AxisTimeline):
                vals = drive.window_sums(n_first, n_last, dt, i0, i1)
            else:
                if t is None:
                    t = np.arange(n_first, n_last + 1, dtype=float) * dt
                vals = self._stats(name, t, _piece_index(drive.t0, t, i0, i1))
            out[slots] = vals
        return out

    def samples(self, n_first: int, n_last: int) -> dict[str, np.ndarray]:
        """Every channel at the 2 ms samples ``n_first..n_last`` (for plots and tests)."""
        t = np.arange(n_first, n_last + 1, dtype=float) * self.machine.fast_period_s
        idx = {d: _piece_index(self._drive(d).t0, t, *_span(self._drive(d).t0, t[0], t[-1])) for d in _SLOTS}
        return {"time_s": t} | self._channels(t, idx)
