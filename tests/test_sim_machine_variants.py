"""Plant variants: seeded perturbations of the simulated machine; variant 0 stays the nominal machine."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg

from gateway.cli import main
from gateway.errors import SimulationError
from simulators.machine.effects import Effects
from simulators.machine.params import DEFAULT_MACHINE
from simulators.machine.run import simulate
from simulators.machine.scenario import load_scenario, parse_scenario_text, scenario_path
from simulators.machine.thermal import build_network
from simulators.machine.variants import SPREAD, STRUCTURES, plant_variant

SHORT = """\
[scenario]
name = "short"
initial_idle_min = 10
duration_h = 4

[segments.run]
minutes = 60
spindle_rpm = 1500
stroke_mm = { x = 200 }
feed_mm_min = 4000
"""


def _time_constants_h(machine) -> np.ndarray:
    """The network's time constants (h), sorted: K x = lambda C x."""
    net = build_network(machine, Effects())
    lam = scipy.linalg.eigh(net.K, np.diag(net.C), eigvals_only=True)
    return np.sort(1.0 / lam / 3600.0)


def test_same_variant_same_recording_and_the_variant_in_the_metadata(tmp_path: Path, capsys):
    for d in ("a", "b"):
        assert main(["simulate", "record", "spindle-1000rpm", "-o", str(tmp_path / d), "--variant", "3",
                     "--no-progress"]) == 0
    assert "plant variant 3: 84 gains and losses x0." in capsys.readouterr().out
    a, b = ((tmp_path / d / "spindle-1000rpm.csv").read_bytes() for d in "ab")
    assert a == b
    assert b"# plant_variant: 3" in a
    scenario = tmp_path / "v3.toml"
    scenario.write_text(scenario_path("spindle-1000rpm").read_text() + "\n[plant]\nvariant = 3\n")
    assert main(["simulate", "record", str(scenario), "-o", str(tmp_path / "c"), "--no-progress"]) == 0
    assert (tmp_path / "c" / "spindle-1000rpm.csv").read_bytes() == a  # the scenario key = the option


def test_variant_zero_is_the_nominal_machine_unchanged(tmp_path: Path):
    assert plant_variant(0).machine is DEFAULT_MACHINE
    for d, extra in (("plain", []), ("zero", ["--variant", "0"])):
        assert main(["simulate", "record", "spindle-1000rpm", "-o", str(tmp_path / d), "--no-progress", *extra]) == 0
    plain, zero = ((tmp_path / d / "spindle-1000rpm.csv").read_bytes() for d in ("plain", "zero"))
    assert plain == zero
    assert b"plant_variant" not in plain
    nominal = simulate(parse_scenario_text(SHORT))
    keyed = simulate(parse_scenario_text(SHORT + "\n[plant]\nvariant = 0\n"))
    np.testing.assert_array_equal(nominal.measured_um, keyed.measured_um)
    assert keyed.machine is DEFAULT_MACHINE


def test_variants_perturb_every_gain_within_the_stated_spread():
    nominal_nodes = {n.name: n for n in DEFAULT_MACHINE.nodes}
    seen_structures = set()
    for v in range(1, 9):
        pv = plant_variant(v)
        factors = np.array(list(pv.factors.values()))
        assert len(factors) == 84
        assert np.all(factors >= 1 / SPREAD - 1e-12)
        assert np.all(factors <= SPREAD + 1e-12)
        assert np.std(np.log(factors)) > 0.1  # log-uniform on +-ln 1.3 has sd 0.15: spread, not a constant
        for n in pv.machine.nodes:
            if n.name not in nominal_nodes:
                continue
            ratio = n.capacity_j_per_k / nominal_nodes[n.name].capacity_j_per_k
            assert 1 / SPREAD - 1e-12 <= ratio <= SPREAD + 1e-12
            for got, nominal in zip(n.um_per_k, nominal_nodes[n.name].um_per_k, strict=True):
                assert (got == 0) == (nominal == 0)
                assert got * nominal >= 0  # signs kept
        seen_structures.add(pv.structure.split(" (")[0])
    assert seen_structures == set(STRUCTURES)


def test_time_constants_move_within_the_spread_squared_where_the_structure_is_nominal():
    nominal = _time_constants_h(DEFAULT_MACHINE)
    moved = []
    for v in range(1, 9):
        pv = plant_variant(v)
        if pv.structure != STRUCTURES[0]:
            continue
        tau = _time_constants_h(pv.machine)
        ratio = tau / nominal
        assert np.all(ratio >= 1 / SPREAD**2 - 1e-9)
        assert np.all(ratio <= SPREAD**2 + 1e-9)
        moved.append(tau)
    assert len(moved) >= 2
    assert np.max(np.abs(np.log(moved[0] / moved[1]))) > 0.05  # two variants, measurably different dynamics


def test_different_variants_give_measurably_different_responses():
    sc = parse_scenario_text(SHORT)
    peaks = {v: simulate(dataclasses.replace(sc, variant=v)).peak_um()["z"] for v in (0, 1, 2, 3)}
    values = list(peaks.values())
    for i in range(len(values)):
        for j in range(i + 1, len(values)):
            assert abs(values[i] / values[j] - 1) > 0.02, peaks
    # still the same machine class: within a factor the spread allows on a gain (S x 1/K: 1.3^2 and more)
    for v in (1, 2, 3):
        assert 1 / SPREAD**3 < peaks[v] / peaks[0] < SPREAD**3
        assert math.copysign(1, peaks[v]) == math.copysign(1, peaks[0])


def test_a_bad_variant_is_refused_naming_the_key_or_option(tmp_path: Path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text(SHORT + "\n[plant]\nvariant = -2\n")
    with pytest.raises(SimulationError) as err:
        load_scenario(bad)
    assert f"{bad}:13: plant.variant: expected an integer >= 0, got -2 (an integer)" in str(err.value)
    assert main(["simulate", "record", "spindle-1000rpm", "-o", str(tmp_path), "--variant", "-1"]) == 2  # usage
    assert "--variant: expected an integer >= 0 (0: the nominal machine), got -1" in capsys.readouterr().err


def test_viscous_drag_scale_takes_the_speed_squared_heat_and_drag_out(tmp_path: Path, capsys):
    """``[plant] viscous_drag_scale``: the drag's torque (the currents) and its ~ speed^2 heat scale together."""
    run = SHORT.replace("spindle_rpm = 1500", "spindle_rpm = 3000")
    full = simulate(parse_scenario_text(run + "\n[plant]\nvariant = 2\n"))
    low = simulate(parse_scenario_text(run + "\n[plant]\nvariant = 2\nviscous_drag_scale = 0.01\n"))
    sp = full.machine.spindle
    assert low.machine.spindle.viscous_nm_s == pytest.approx(0.01 * sp.viscous_nm_s)
    for a in "xyz":
        assert low.machine.axes[a].viscous_n_s_per_m == pytest.approx(0.01 * full.machine.axes[a].viscous_n_s_per_m)
    at_speed = full.stats[:, 0] > 2990  # windows at a steady 3000 rpm
    omega = 3000 * 2 * math.pi / 60
    drop = (full.heat_w["spindle_friction"] - low.heat_w["spindle_friction"])[at_speed]
    np.testing.assert_allclose(drop, 0.99 * sp.viscous_nm_s * omega**2, rtol=0.02)  # b w^2, 15-50 W
    assert np.all(low.stats[at_speed, 1] < full.stats[at_speed, 1])  # less drag: less stator current^2
    path = tmp_path / "low.toml"
    path.write_text(run + "\n[plant]\nviscous_drag_scale = 0.01\n")
    assert main(["simulate", "record", str(path), "-o", str(tmp_path / "o"), "--no-progress"]) == 0
    assert "viscous drag x0.01" in capsys.readouterr().out
    assert b"# plant_viscous_drag_scale: 0.01" in (tmp_path / "o" / "short.csv").read_bytes()
    path.write_text(run + "\n[plant]\nviscous_drag_scale = 0\n")
    with pytest.raises(SimulationError) as err:
        load_scenario(path)
    assert "plant.viscous_drag_scale: expected a number in [0.001, 10], got 0 (an integer)" in str(err.value)
    assert str(err.value).startswith(f"{path}:")
