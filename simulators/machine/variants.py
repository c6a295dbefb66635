"""Plant variants: the simulated machine with its gains and time constants perturbed by a seed.

One nominal machine (:data:`~simulators.machine.params.DEFAULT_MACHINE`) makes a poor test of a method
tuned on it. Variant ``N > 0`` draws, from its own seed, an independent factor for every parameter below,
log-uniform in ``[1 / SPREAD, SPREAD]`` (SPREAD = 1.3, i.e. +-30 %); variant 0 is the nominal machine,
unchanged. Perturbed:

- thermal network: every node's capacity and its conductance to the room, every link's conductance
  (so every time constant of the network moves, by at most SPREAD^2 = 1.69 in either direction while the
  structure is unchanged: Courant-Fischer on ``K x = lambda C x``);
- structure: every non-zero displacement sensitivity (um/K per node and axis; the sign is kept);
- drive losses: spindle coulomb and viscous drag, stator and rotor resistance, iron hysteresis; per feed
  axis guide friction, screw drag, viscous drag and motor resistance (drag also changes the currents the
  CNC reports, as on a real machine).

Structure, drawn from a second stream of the same seed: a third of the variants keep the nominal network,
a third get an extra conductance from the head to the rear column (covers and the cable carrier,
1..4 W/K), a third an extra node: a motor bracket (20 kJ/K x the spread) between stator and head, with
its own loss to the room and its own growth that tilts the head (y +0.8, z -0.8 um/K x the spread).

Left alone: masses, inertias, leads, torque constants and travel (the drives' kinematics and the
scenario checks stay those of the nominal machine), the share of friction heat in the front bearing.
A scenario chooses a variant with ``[plant] variant = N``; ``cncgw simulate record --variant N`` overrides it.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from functools import lru_cache
from types import MappingProxyType

import numpy as np

from simulators.machine.params import DEFAULT_MACHINE, MachineParams, Node

SPREAD = 1.3
#: the seed stream of plant variants (kept apart from sensor noise and bench schedules)
_STREAM = 0x9E1A27

SPINDLE_LOSSES = ("coulomb_nm", "viscous_nm_s", "stator_resistance_ohm", "rotor_resistance_ohm",
                  "hysteresis_w_per_rpm")
AXIS_LOSSES = ("guide_friction_n", "screw_drag_nm", "viscous_n_s_per_m", "resistance_ohm")
STRUCTURES = ("nominal structure", "head-rear column link", "motor bracket node")


@dataclass(frozen=True, kw_only=True)
class PlantVariant:
    """A drawn variant: the machine and what was done to it (for ``describe``)."""

    variant: int
    machine: MachineParams
    structure: str
    #: parameter label -> factor applied (1.0 for variant 0)
    factors: MappingProxyType[str, float]

    def describe(self) -> list[str]:
        """One line per parameter: label, factor."""
        lines = [f"plant variant {self.variant}: {self.structure}; factors log-uniform in "
                 f"[{1 / SPREAD:.3f}, {SPREAD:.3f}]"]
        lines += [f"  {k:<40} x{v:.3f}" for k, v in self.factors.items()]
        return lines

    def summary(self) -> str:
        """One line: structure and the range of factors drawn."""
        if not self.factors:
            return f"plant variant {self.variant}: the nominal machine"
        v = np.array(list(self.factors.values()))
        return (f"plant variant {self.variant}: {len(v)} gains and losses x{v.min():.2f}..x{v.max():.2f}, "
                f"structure: {self.structure}")


def _draw(rng: np.random.Generator) -> float:
    return float(math.exp(rng.uniform(-math.log(SPREAD), math.log(SPREAD))))


@lru_cache(maxsize=64)
def _nominal_variant(variant: int) -> PlantVariant:
    return _variant(variant, DEFAULT_MACHINE)


def _variant(variant: int, machine: MachineParams) -> PlantVariant:
    if variant == 0:
        return PlantVariant(variant=0, machine=machine, structure=STRUCTURES[0], factors=MappingProxyType({}))
    rng = np.random.default_rng([_STREAM, variant, 0])
    factors: dict[str, float] = {}

    def f(label: str) -> float:
        factors[label] = _draw(rng)
        return factors[label]

    nodes = []
    for n in machine.nodes:
        um = tuple(v * f(f"{n.name}.um_per_k.{a}") if v else 0.0 for a, v in zip("xyz", n.um_per_k, strict=True))
        nodes.append(dataclasses.replace(n, capacity_j_per_k=n.capacity_j_per_k * f(f"{n.name}.capacity"),
                                         room_w_per_k=n.room_w_per_k * f(f"{n.name}.room_w_per_k"),
                                         um_per_k=um))
    links = [(a, b, g * f(f"link {a}-{b}")) for a, b, g in machine.links]
    spindle = dataclasses.replace(machine.spindle, **{k: getattr(machine.spindle, k) * f(f"spindle.{k}")
                                                       for k in SPINDLE_LOSSES})
    axes = MappingProxyType({a: dataclasses.replace(p, **{k: getattr(p, k) * f(f"{a}_axis.{k}") for k in AXIS_LOSSES})
                             for a, p in machine.axes.items()})
    srng = np.random.default_rng([_STREAM, variant, 1])
    kind = int(srng.integers(0, len(STRUCTURES)))
    structure = STRUCTURES[kind]
    if kind == 1:
        g = float(math.exp(srng.uniform(0.0, math.log(4.0))))
        links.append(("head", "column_rear", g))
        structure += f" ({g:.2f} W/K)"
    elif kind == 2:
        s = [_draw(srng) for _ in range(6)]
        nodes.append(Node(name="motor_bracket", capacity_j_per_k=2.0e4 * s[0], room_w_per_k=2.0 * s[1],
                          um_per_k=(0.0, 0.8 * s[2], -0.8 * s[3]),
                          note="plant variant: a motor bracket between stator and head"))
        links += [("stator", "motor_bracket", 4.0 * s[4]), ("motor_bracket", "head", 4.0 * s[5])]
        structure += f" ({2.0e4 * s[0] / 1e3:.1f} kJ/K)"
    out = dataclasses.replace(machine, nodes=tuple(nodes), links=tuple(links), spindle=spindle, axes=axes)
    return PlantVariant(variant=variant, machine=out, structure=structure, factors=MappingProxyType(factors))


def plant_variant(variant: int, machine: MachineParams = DEFAULT_MACHINE) -> PlantVariant:
    """Variant ``variant`` (>= 0) of ``machine``: the same number gives the same plant on any run."""
    if isinstance(variant, bool) or not isinstance(variant, int) or variant < 0:
        raise ValueError(f"plant variant must be an integer >= 0. Got {variant!r}")
    # MachineParams holds mappings (unhashable): cache the variants of the default machine only
    return _nominal_variant(variant) if machine is DEFAULT_MACHINE else _variant(variant, machine)


def variant_machine(variant: int, machine: MachineParams = DEFAULT_MACHINE, *,
                    viscous_drag_scale: float = 1.0) -> MachineParams:
    """The machine of variant ``variant`` (``machine`` itself for 0), every viscous drag times the scale.

    ``viscous_drag_scale`` (``[plant] viscous_drag_scale``) multiplies the spindle's and every feed axis's
    speed-proportional drag after the variant's draw: its torque (so the currents the CNC reports) and its
    heat (~ speed^2, which no factor of a profile carries) together. A scale near 0 gives a plant whose heat
    is linear in the speeds and the currents squared, which the identified model's structure describes
    entirely (bench/diagnose.py measures false alarms on it).
    """
    out = plant_variant(variant, machine).machine
    if viscous_drag_scale == 1.0:
        return out
    if not (math.isfinite(viscous_drag_scale) and viscous_drag_scale > 0):
        raise ValueError(f"viscous drag scale must be a number > 0. Got {viscous_drag_scale!r}")
    spindle = dataclasses.replace(out.spindle, viscous_nm_s=out.spindle.viscous_nm_s * viscous_drag_scale)
    axes = MappingProxyType({a: dataclasses.replace(p, viscous_n_s_per_m=p.viscous_n_s_per_m * viscous_drag_scale)
                             for a, p in out.axes.items()})
    return dataclasses.replace(out, spindle=spindle, axes=axes)
