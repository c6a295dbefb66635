"""Heat and structure: a lumped thermal network driven by the drives' window statistics.

``C dT/dt = -K T + q(t) + g_room * r(t)`` with T the nodes' rises above the base room temperature, C the
capacities, K the conductance matrix (links between nodes plus each node's loss to the room on the
diagonal), q the heat inputs and r the room's deviation from its base. Heat and room are constant over a
window (the window means the CNC computes), so each window is integrated exactly with one matrix
exponential (zero-order hold), computed once: ``T_{k+1} = Ad T_k + Gam q_k``. The coolant loop's dead time
is exact too, including a fraction of a window (the same split as ``gateway.model.discrete``). Three
effects depend on the state (bearing preload, chiller, the cabinet's thermostat); they are evaluated with the
temperatures at the start of each window, whose error is small because their rates are below a tenth of a
window (the thermostat switches at a window's start).

Displacement (um) is ``S (T - T0)``: the paper measures relative to the start, after > 24 h at rest, so
the reference T0 is the equilibrium at rest (the Z motor's holding current keeps a little heat flowing)
plus, with a room cycle, the cycle's periodic steady state.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.linalg

from gateway.model.discrete import split_delay
from simulators.machine.drives import STAT_INDEX, STATS
from simulators.machine.effects import Effects
from simulators.machine.params import AXES, RAD_PER_RPM, MachineParams, Node


@dataclass(frozen=True, eq=False)
class Network:
    """The thermal network.

    Nodes, capacities ``C`` (J/K), conductance matrix ``K`` (W/K), room conductances and the displacement
    sensitivities ``S`` (3 x n, um/K).
    """

    names: tuple[str, ...]
    C: np.ndarray
    K: np.ndarray
    room: np.ndarray
    S: np.ndarray

    def index(self, name: str) -> int:
        return self.names.index(name)


def build_network(machine: MachineParams, effects: Effects) -> Network:
    """The machine's network plus the nodes the switched-on effects bring."""
    nodes = list(machine.nodes)
    links = list(machine.links)
    if (sp := effects.slow_path) is not None:
        cap = sp.time_constant_h * 3600.0 * (sp.conductance_w_per_k + sp.room_w_per_k)
        nodes.append(Node(name="slow_path", capacity_j_per_k=cap, room_w_per_k=sp.room_w_per_k,
                          um_per_k=sp.um_per_k))
        links.append((sp.from_node, "slow_path", sp.conductance_w_per_k))
    if (cab := effects.cabinet) is not None:
        nodes.append(Node(name="cabinet", capacity_j_per_k=cab.capacity_kj_per_k * 1e3,
                          room_w_per_k=cab.room_w_per_k))
        links.append(("cabinet", "column_rear", cab.column_w_per_k))
    if (cd := effects.coolant_delay) is not None:
        nodes.append(Node(name="coolant_tank", capacity_j_per_k=cd.tank_capacity_kj_per_k * 1e3,
                          room_w_per_k=cd.tank_room_w_per_k))
        links.append(("coolant_tank", "column_rear", cd.tank_column_w_per_k))
    names = tuple(n.name for n in nodes)
    room = np.array([n.room_w_per_k for n in nodes])
    K = np.diag(room)
    for a, b, g in links:
        i, j = names.index(a), names.index(b)
        K[i, i] += g
        K[j, j] += g
        K[i, j] -= g
        K[j, i] -= g
    S = np.array([n.um_per_k for n in nodes]).T
    return Network(names=names, C=np.array([n.capacity_j_per_k for n in nodes]), K=K, room=room, S=S)


def zoh(net: Network, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """``(Ad, Gam)``: exact state transition and heat-input matrix for heat held constant for ``dt_s``."""
    n = len(net.names)
    M = np.zeros((2 * n, 2 * n))
    M[:n, :n] = -net.K / net.C[:, None]
    M[:n, n:] = np.diag(1.0 / net.C)
    E = scipy.linalg.expm(M * dt_s)
    return E[:n, :n], E[:n, n:]


# --------------------------------------------------------------------------------------------------------
def heat_sources(machine: MachineParams, effects: Effects) -> tuple[tuple[str, str, float], ...]:
    """``(source, node, share)`` for every heat source the window statistics drive."""
    sp = machine.spindle
    out = [("spindle_friction", "bearing", sp.front_bearing_share),
           ("spindle_friction", "head", 1.0 - sp.front_bearing_share),
           ("stator_joule", "stator", 1.0), ("iron_hysteresis", "stator", 1.0), ("rotor_joule", "rotor", 1.0)]
    for a in AXES:
        out += [(f"{a}_screw_friction", f"{a}_screw", 1.0),
                (f"{a}_guide_friction", machine.axes[a].guide_node, 1.0),
                (f"{a}_joule", f"{a}_motor", 1.0)]
    if (ed := effects.eddy_loss) is not None:
        out += [("eddy_loss", "stator", 1.0 - ed.rotor_share), ("eddy_loss", "rotor", ed.rotor_share)]
    if effects.cabinet is not None:
        out.append(("cabinet", "cabinet", 1.0))
    if effects.coolant_delay is not None:
        out.append(("coolant_removed", "stator", 1.0))
    return tuple(out)


def source_heat(machine: MachineParams, effects: Effects, stats: np.ndarray) -> dict[str, np.ndarray]:
    """Heat (W) of every source from window statistics (rows: windows, columns: :data:`STATS`)."""
    s = {name: stats[..., STAT_INDEX[name]] for name in STATS}
    sp = machine.spindle
    omega = s["spindle_speed"] * RAD_PER_RPM
    q = {
        "spindle_friction": sp.coulomb_nm * omega + sp.viscous_nm_s * s["spindle_omega_sq"],
        "stator_joule": 3.0 * sp.stator_resistance_ohm * s["spindle_i1_sq"],
        "iron_hysteresis": sp.hysteresis_w_per_rpm * s["spindle_speed"],
        "rotor_joule": 3.0 * sp.rotor_resistance_ohm * s["spindle_i2_sq"],
    }
    for a in AXES:
        ax = machine.axes[a]
        speed = s[f"{a}_feed"] / 60000.0  # mean |v|, m/s
        q[f"{a}_screw_friction"] = ax.screw_drag_nm * 2.0 * math.pi / ax.lead_m * speed
        q[f"{a}_guide_friction"] = ax.guide_friction_n * speed + ax.viscous_n_s_per_m * s[f"{a}_v_sq"]
        q[f"{a}_joule"] = ax.resistance_ohm * s[f"{a}_i_sq"]
    if (ed := effects.eddy_loss) is not None:
        q["eddy_loss"] = ed.loss_w_at_1000rpm * s["spindle_omega_sq"] / (1000.0 * RAD_PER_RPM) ** 2
    if (cab := effects.cabinet) is not None:
        q["cabinet"] = cab.w_per_a2 * (s["spindle_i1_sq"] + sum(s[f"{a}_i_sq"] for a in AXES))
    if (cd := effects.coolant_delay) is not None:
        stator = q["stator_joule"] + q["iron_hysteresis"]
        if ed is not None:
            stator = stator + q["eddy_loss"] * (1.0 - ed.rotor_share)
        q["coolant_removed"] = -cd.fraction * stator
    return q


def rest_stats(machine: MachineParams) -> np.ndarray:
    """Window statistics of the machine at rest: only a vertical axis's holding current."""
    out = np.zeros(len(STATS))
    for a in AXES:
        ax = machine.axes[a]
        out[STAT_INDEX[f"{a}_i_sq"]] = (ax.gravity_torque_nm / ax.torque_constant_nm_per_a) ** 2
    return out


# --------------------------------------------------------------------------------------------------------
class ThermalModel:
    """The network for one set of effects, discretised at the window, with its heat mapping."""

    def __init__(self, machine: MachineParams, effects: Effects) -> None:
        self.machine = machine
        self.effects = effects
        self.net = build_network(machine, effects)
        self.dt_s = machine.window_s
        self.Ad, self.Gam = zoh(self.net, self.dt_s)
        self.sources = heat_sources(machine, effects)
        self.source_names = tuple(dict.fromkeys(s for s, _, _ in self.sources))
        M = np.zeros((len(self.source_names), len(self.net.names)))
        for src, node, share in self.sources:
            M[self.source_names.index(src), self.net.index(node)] += share
        self.to_nodes = M
        self._delay = self._delay_matrices()
        self.T0 = self.initial_state()

    def _delay_matrices(self) -> tuple[int, np.ndarray, np.ndarray] | None:
        cd = self.effects.coolant_delay
        if cd is None:
            return None
        m, f = split_delay(cd.delay_s, self.dt_s)
        tank = self.net.index("coolant_tank")
        g_full = self.Gam[:, tank]
        g_recent = zoh(self.net, self.dt_s - f)[1][:, tank] if f else g_full
        return m, g_recent, g_full - g_recent

    def heat(self, stats: np.ndarray) -> tuple[dict[str, np.ndarray], np.ndarray]:
        """Source heats and the state-independent node heat (W) for window statistics ``stats``."""
        q = source_heat(self.machine, self.effects, stats)
        Q = np.stack([q[name] for name in self.source_names], axis=-1)
        return q, Q @ self.to_nodes

    def initial_state(self) -> np.ndarray:
        """Rise above the base room temperature after > 24 h at rest (and in the room's cycle)."""
        _, q_rest = self.heat(rest_stats(self.machine))
        T0 = np.linalg.solve(self.net.K, q_rest)
        if (rc := self.effects.room_cycle) is not None and rc.amplitude_k > 0:
            # periodic steady state of C dT/dt = -K T + g sum_k c_k cos(k W (t - t_peak)), taken at t = 0
            w = 2.0 * math.pi / (rc.period_h * 3600.0)
            for k, c in rc.harmonics():
                H = np.linalg.solve(1j * k * w * np.diag(self.net.C) + self.net.K,
                                    self.net.room * c * np.exp(-1j * k * w * rc.peak_at_h * 3600.0))
                T0 = T0 + H.real
        return T0

    def stepper(self) -> ThermalStepper:
        return ThermalStepper(self)


class ThermalStepper:
    """Advances one :class:`ThermalModel` window by window (shared by the offline run and the live source).

    ``step(stats_row, room_dev_k)`` integrates one window with its statistics and the room's mean deviation
    over it; ``T`` holds the rises (K) at the window's end.
    """

    def __init__(self, model: ThermalModel) -> None:
        self.model = model
        self.T = model.T0.copy()
        self.k = 0
        self._coolant: list[float] = []  # heat handed to the coolant per window (W), for the dead time
        self._gate = 0.0  # chiller build-up, 0..1
        self._cooler = False  # the cabinet's cooling unit running
        self.extra_w: dict[str, float] = {}

    def step(self, stats: np.ndarray, room_dev_k: float) -> np.ndarray:
        m = self.model
        eff = m.effects
        net = m.net
        sources, q = m.heat(stats)
        q = q + net.room * room_dev_k
        T = self.T
        self.extra_w = {}
        if (bp := eff.bearing_preload) is not None:
            b, h = net.index("bearing"), net.index("head")
            sp = m.machine.spindle
            friction = (sp.coulomb_nm * stats[STAT_INDEX["spindle_speed"]] * RAD_PER_RPM
                        + sp.viscous_nm_s * stats[STAT_INDEX["spindle_omega_sq"]])
            extra = friction * bp.gain_per_k * max(T[b] - T[h], 0.0)
            q[b] += extra * sp.front_bearing_share
            q[h] += extra * (1.0 - sp.front_bearing_share)
            self.extra_w["bearing_preload"] = extra
        if (ch := eff.chiller) is not None:
            gate = stats[STAT_INDEX["spindle_on"]]
            decay = math.exp(-m.dt_s / ch.time_constant_s)
            # mean build-up over the window of a first-order response towards the gate
            mean = gate + (self._gate - gate) * ch.time_constant_s / m.dt_s * (1.0 - decay)
            self._gate = gate + (self._gate - gate) * decay
            i = net.index(ch.node)
            removed = mean * ch.conductance_w_per_k * (T[i] - room_dev_k)
            q[i] -= removed
            self.extra_w["chiller"] = -removed
        if (cab := eff.cabinet) is not None and cab.cooler_w > 0:
            # the thermostat reads the cabinet's rise over the hall at the window's start: on above cooler_on_k,
            # off below cooler_off_k, as it was in between (a window is short against its cycle)
            i = net.index("cabinet")
            rise = T[i] - room_dev_k
            self._cooler = rise > cab.cooler_on_k or (self._cooler and rise > cab.cooler_off_k)
            removed = cab.cooler_w if self._cooler else 0.0
            q[i] -= removed
            self.extra_w["cabinet_cooler"] = -removed
        T_new = m.Ad @ T + m.Gam @ q
        if m._delay is not None:
            lag, g_recent, g_older = m._delay
            self._coolant.append(-float(sources["coolant_removed"]))
            k = len(self._coolant) - 1
            if k - lag >= 0:
                T_new += g_recent * self._coolant[k - lag]
            if k - lag - 1 >= 0:
                T_new += g_older * self._coolant[k - lag - 1]
        self.T = T_new
        self.k += 1
        return T_new

    def displacement(self, T: np.ndarray | None = None) -> np.ndarray:
        """Tool-to-table displacement (um, x y z) relative to the start."""
        return self.model.net.S @ ((self.T if T is None else T) - self.model.T0)


def room_deviation(effects: Effects, t0_s: np.ndarray | float, t1_s: np.ndarray | float) -> np.ndarray:
    """Mean deviation (K) of the room from its base temperature over ``(t0, t1]`` (exact for the cycle)."""
    t0, t1 = np.asarray(t0_s, dtype=float), np.asarray(t1_s, dtype=float)
    rc = effects.room_cycle
    if rc is None:
        return np.zeros(np.broadcast(t0, t1).shape)
    w = 2.0 * math.pi / (rc.period_h * 3600.0)
    tp = rc.peak_at_h * 3600.0
    span = np.where(t1 > t0, t1 - t0, 1.0)
    out = rc.drift_k_per_h * (t0 + t1) / 2.0 / 3600.0
    for k, c in rc.harmonics():
        kw = k * w
        out = out + c * np.where(t1 > t0, (np.sin(kw * (t1 - tp)) - np.sin(kw * (t0 - tp))) / (kw * span),
                                 np.cos(kw * (t1 - tp)))
    return out
