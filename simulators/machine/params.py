"""Parameters of the simulated vertical machining center, with where each number comes from.

The machine is a generic VMC of the paper's class (Hitachi Seiki VM40III: 40-taper spindle, table about
900 x 400 mm, X/Y/Z travels about 600/400/450 mm). Nothing here is fitted to the paper's curves except the
displacement sensitivities marked "calibrated" (spindle nose, head, column front), chosen within their
physical range (alpha x a plausible length) so that the paper's experiments land near the paper's
figures: spindle 1000 rpm for 60 min about 17 um in z, the random spindle run about 13 um (paper 12.9),
the spindle-plus-feeds run about 20 um (paper 21.9). Everything else is textbook material data and
catalogue-size guesses. The network's time constants run from 4 minutes (spindle nose) to 10 hours
(bed and column).

Material data used throughout: steel c = 460 J/(kg K), k = 45 W/(m K), alpha = 11.5e-6 /K; grey cast iron
c = 460 J/(kg K), k = 50 W/(m K), alpha = 10.5e-6 /K. Free convection h = 5..10 W/(m^2 K) (plus radiation,
about 5 W/(m^2 K) at room temperature), forced convection on fan-cooled motors h = 20..30 W/(m^2 K).
Conductances of bolted or rolling contacts are taken as 1000..3000 W/(m^2 K) over the contact area.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from types import MappingProxyType

AXES = ("x", "y", "z")
RAD_PER_RPM = 2.0 * math.pi / 60.0
G_M_S2 = 9.81


@dataclass(frozen=True, kw_only=True)
class SpindleParams:
    """Induction spindle motor (7.5 kW continuous / 11 kW 30 min class) and its speed loop.

    Field-oriented control: the stator current has a magnetising component ``magnetising_a`` (constant up to
    base speed, falling as base/n above it: field weakening) and a torque component ``iq = torque / k_T(n)``
    with ``k_T`` falling with the flux. The rotor current (referred to the stator) is ``rotor_ratio * |iq|``
    (Lm/Lr): it carries torque only, so it is near zero at constant speed and large while accelerating.
    Currents are RMS phase values, as a drive's current monitor gives them.
    """

    #: motor rotor 0.05 + spindle, coupling and tool holder 0.03 kg m^2 (7.5 kW 4-pole catalogue motors
    #: have 0.03..0.06 kg m^2)
    inertia_kg_m2: float = 0.08
    #: bearing, seal and belt-free coupling drag: two pairs of 65 mm angular contact bearings at light
    #: preload take about 0.3 Nm each pair, seals and labyrinth air about 0.2 Nm
    coulomb_nm: float = 0.8
    #: speed-proportional drag (oil-air churning): 3 W at 1000 rpm, 30 W at 3000 rpm
    viscous_nm_s: float = 0.0003
    #: closed-loop time constant of the speed loop (the paper: ~50 ms on its Z axis; spindles are similar)
    time_constant_s: float = 0.05
    #: 150 % of the rated 47.7 Nm (7.5 kW at 1500 rpm): the drive's current limit expressed as torque
    torque_limit_nm: float = 71.6
    base_speed_rpm: float = 1500.0
    max_speed_rpm: float = 8000.0
    #: no-load current of a 200 V 7.5 kW induction motor is 35..40 % of its 35 A rated current
    magnetising_a: float = 14.0
    #: rated torque 47.7 Nm at rated torque current sqrt(35^2 - 14^2) = 32 A
    torque_constant_nm_per_a: float = 1.49
    #: Lm/Lr, the share of the torque current that the rotor carries (referred to the stator)
    rotor_ratio: float = 0.96
    #: the drive switches off once a zero command has brought the speed below this
    off_below_rpm: float = 1.0
    #: stator phase resistance at working temperature; stator Joule heat = 3 R I1^2 (70 W at no load)
    stator_resistance_ohm: float = 0.12
    #: rotor resistance referred to the stator; rotor Joule heat = 3 R I2^2
    rotor_resistance_ohm: float = 0.10
    #: iron hysteresis loss, ~ speed: 30 W at 1000 rpm (about 1 % of a 7.5 kW motor's 3 kW iron-loss
    #: budget at full speed is hysteresis at low frequency); it lands in the stator
    hysteresis_w_per_rpm: float = 0.03
    #: share of the spindle's friction heat generated in the front bearings (the rest: rear bearing,
    #: which sits in the head casting)
    front_bearing_share: float = 0.7

    @property
    def omega_base(self) -> float:
        return self.base_speed_rpm * RAD_PER_RPM

    @property
    def power_limit_w(self) -> float:
        """Above base speed the current limit gives constant power."""
        return self.torque_limit_nm * self.omega_base


@dataclass(frozen=True, kw_only=True)
class FeedAxisParams:
    """A ball-screw feed axis driven by a synchronous (permanent-magnet) servo motor.

    Motor torque = J_rot * alpha + (m a + F_guides + c v) * lead / (2 pi eta) + screw drag (+ gravity on a
    vertical axis); current = torque / k_T, signed like a q-axis current feedback.
    """

    name: str
    #: moving mass: X table + fixture/workpiece; Y saddle + table; Z spindle head + motor
    mass_kg: float
    lead_mm: float = 10.0
    #: servo motor rotor (0.0012) + 40 mm x 1 m ball screw (0.0018) + coupling
    rotor_inertia_kg_m2: float = 0.0032
    efficiency: float = 0.9
    #: linear-guide friction: four medium-preload roller blocks (50..60 N each) plus seals and wipers
    guide_friction_n: float = 350.0
    #: ball-screw nut preload and support-bearing drag torque at the motor (catalogue: 0.3..0.6 Nm)
    screw_drag_nm: float = 0.45
    viscous_n_s_per_m: float = 300.0
    #: alpha-i 8 class servo motor: k_T about 1.2..1.6 Nm/A (peak current amplitude)
    torque_constant_nm_per_a: float = 1.3
    #: Joule heat = R I^2 with I the q-axis current amplitude (1.5 x the 0.6 Ohm phase resistance)
    resistance_ohm: float = 0.9
    vertical: bool = False
    max_feed_mm_min: float = 30000.0
    max_accel_m_s2: float = 5.0
    #: stroke of the axis (VM40III class: X 760, Y 410, Z 460 mm)
    travel_mm: float = 760.0
    #: the node the guide friction heats (the carriage side of the guides)
    guide_node: str = ""

    @property
    def lead_m(self) -> float:
        return self.lead_mm / 1000.0

    @property
    def force_to_torque(self) -> float:
        """Motor torque per newton of axial force, with the screw's efficiency."""
        return self.lead_m / (2.0 * math.pi * self.efficiency)

    @property
    def accel_torque_nm_per_m_s2(self) -> float:
        """Torque to accelerate the axis by 1 m/s^2 (rotor and screw, and the moving mass)."""
        return self.rotor_inertia_kg_m2 * 2.0 * math.pi / self.lead_m + self.mass_kg * self.force_to_torque

    @property
    def gravity_torque_nm(self) -> float:
        """Holding torque against gravity (no counterbalance); static, so without the screw's efficiency."""
        return self.mass_kg * G_M_S2 * self.lead_m / (2.0 * math.pi) if self.vertical else 0.0


def _axes() -> MappingProxyType[str, FeedAxisParams]:
    return MappingProxyType({
        "x": FeedAxisParams(name="x", mass_kg=450.0, guide_node="table"),
        "y": FeedAxisParams(name="y", mass_kg=800.0, rotor_inertia_kg_m2=0.0036, guide_node="saddle",
                            travel_mm=410.0),
        # head + spindle + motor 350 kg, no counterbalance: 5.5 Nm holding torque, 3.6 A
        "z": FeedAxisParams(name="z", mass_kg=350.0, torque_constant_nm_per_a=1.5, vertical=True,
                            max_feed_mm_min=24000.0, guide_node="column_front", travel_mm=460.0),
    })


@dataclass(frozen=True, kw_only=True)
class Node:
    """A lumped thermal mass.

    ``capacity_j_per_k`` is mass x specific heat, ``room_w_per_k`` its loss to the room, ``um_per_k`` its
    temperature rise's share of the tool-to-table displacement (x, y, z).
    """

    name: str
    capacity_j_per_k: float
    room_w_per_k: float
    um_per_k: tuple[float, float, float] = (0.0, 0.0, 0.0)
    note: str = ""


# Displacement convention: tool relative to table, in machine axes; +z is up (tool away from the table),
# +y is away from the column (towards the operator). Sensitivities are the thermal growth of the member
# over the length that moves the tool or the table: alpha x length, e.g. 300 mm of cast iron = 3.15 um/K.
_NODES = (
    Node(name="bearing", capacity_j_per_k=2.5e3, room_w_per_k=0.8, um_per_k=(0.0, 0.0, -2.0),
         note="front bearings, spindle nose: 5 kg steel; 175 mm of shaft, nose and tool holder below the "
              "bearings grow down (calibrated)"),
    Node(name="rotor", capacity_j_per_k=5.0e3, room_w_per_k=0.4,
         note="motor rotor and spindle shaft: 11 kg steel; grows up from the front bearing: no tool shift"),
    Node(name="stator", capacity_j_per_k=1.2e4, room_w_per_k=10.0,
         note="stator core, winding, frame: 26 kg; fan-cooled frame 0.4 m^2 at h = 25"),
    Node(name="head", capacity_j_per_k=2.0e5, room_w_per_k=6.0, um_per_k=(0.3, 2.0, -2.7),
         note="spindle head casting with quill housing and motor bracket 430 kg; 1 m^2 exposed at h = 6; "
              "grows down 260 mm from the Z nut and 190 mm forward of the guides (calibrated)"),
    Node(name="column_front", capacity_j_per_k=2.5e5, room_w_per_k=9.0, um_per_k=(0.0, -4.0, 3.0),
         note="front half of the column 540 kg; growth lifts the head, a warm front leans it back "
              "(calibrated)"),
    Node(name="column_rear", capacity_j_per_k=2.5e5, room_w_per_k=9.0, um_per_k=(0.0, 4.0, 2.5),
         note="rear half of the column 540 kg; a warm rear leans the column forward"),
    Node(name="z_screw", capacity_j_per_k=1.2e4, room_w_per_k=1.5, um_per_k=(0.0, 0.0, -2.0),
         note="Z ball screw, nut, support bearings 26 kg; fixed at the top, grows down 175 mm to the nut "
              "(mid travel; the screw's warm stretch is shorter than the nut distance)"),
    Node(name="x_screw", capacity_j_per_k=1.2e4, room_w_per_k=1.5, um_per_k=(-2.0, 0.0, 0.0),
         note="X ball screw and nut; fixed at the motor end, 175 mm of warm screw to the nut at mid travel "
              "moves the table +x"),
    Node(name="y_screw", capacity_j_per_k=1.2e4, room_w_per_k=1.5, um_per_k=(0.0, -2.0, 0.0),
         note="Y ball screw and nut; 175 mm to the nut at mid travel"),
    Node(name="table", capacity_j_per_k=1.4e5, room_w_per_k=8.0, um_per_k=(0.0, 0.0, -2.0),
         note="table 300 kg with fixture; 1 m^2 exposed; 130 mm table + 60 mm fixture plate"),
    Node(name="saddle", capacity_j_per_k=1.8e5, room_w_per_k=5.0, um_per_k=(0.0, 0.0, -2.5),
         note="saddle 400 kg; 190 mm high plus the X guide rails on it"),
    Node(name="bed", capacity_j_per_k=9.0e5, room_w_per_k=15.0, um_per_k=(0.0, 0.5, -1.0),
         note="bed 2 t; a top warmed by the Y guides bows up under the table more than under the column"),
    Node(name="x_motor", capacity_j_per_k=6.0e3, room_w_per_k=3.0, note="X servo motor 13 kg"),
    Node(name="y_motor", capacity_j_per_k=6.0e3, room_w_per_k=3.0, note="Y servo motor 13 kg"),
    Node(name="z_motor", capacity_j_per_k=6.0e3, room_w_per_k=3.0, note="Z servo motor 13 kg"),
)

# Conductances between nodes (W/K), from contact areas and conduction paths:
_LINKS = (
    ("bearing", "head", 12.0),         # outer rings and spacers in the housing: 0.006 m^2 at 2000 W/(m^2 K)
    ("bearing", "rotor", 1.0),         # through the shaft: 45 W/(m K) x 3.8e-3 m^2 / 0.17 m
    ("rotor", "stator", 5.0),          # air gap: 0.08 m^2 at h = 60
    ("stator", "head", 6.0),           # motor flange on the head
    ("head", "column_front", 8.0),     # four Z guide blocks (0.004 m^2 at 2000) and the counter plate
    ("head", "z_screw", 1.5),          # nut bracket
    ("column_front", "column_rear", 10.0),  # side walls and ribs: 50 W/(m K) x 0.1 m^2 / 0.5 m
    ("column_front", "bed", 8.0),      # bolted joint
    ("column_rear", "bed", 8.0),
    ("z_screw", "column_front", 2.0),  # support bearings
    ("z_screw", "z_motor", 1.5),       # coupling and bearing housing
    ("z_motor", "column_rear", 2.0),   # motor bracket on the column top
    ("x_screw", "table", 3.0),         # nut and nut bracket
    ("x_screw", "saddle", 2.0),        # support bearings
    ("x_screw", "x_motor", 1.5),
    ("x_motor", "saddle", 2.0),
    ("y_screw", "saddle", 3.0),        # nut and nut bracket
    ("y_screw", "bed", 2.0),
    ("y_screw", "y_motor", 1.5),
    ("y_motor", "bed", 2.0),
    ("table", "saddle", 6.0),          # X guide blocks
    ("saddle", "bed", 8.0),            # Y guide blocks
)


@dataclass(frozen=True, kw_only=True)
class MachineParams:
    """Everything that defines the simulated machine (drives, thermal network, structure)."""

    spindle: SpindleParams = field(default_factory=SpindleParams)
    axes: MappingProxyType[str, FeedAxisParams] = field(default_factory=_axes)
    nodes: tuple[Node, ...] = _NODES
    links: tuple[tuple[str, str, float], ...] = _LINKS
    #: the CNC's fast sampling period and the factor window (profile sim-vmc.toml)
    fast_period_s: float = 0.002
    window_s: float = 60.0

    @property
    def samples_per_window(self) -> int:
        return round(self.window_s / self.fast_period_s)


DEFAULT_MACHINE = MachineParams()
