"""Heat, structure and the switchable effects: magnitudes, exact integration, each effect's direction and size."""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest
import scipy.integrate

from gateway.errors import SimulationError
from simulators.machine.drives import STAT_INDEX
from simulators.machine.effects import Effects
from simulators.machine.params import AXES, DEFAULT_MACHINE, RAD_PER_RPM
from simulators.machine.run import simulate
from simulators.machine.scenario import load_scenario, parse_scenario_text
from simulators.machine.thermal import ThermalModel, build_network

X, Y, Z = range(3)
SPINDLE_2000 = """
[scenario]
initial_idle_min = 30
duration_h = 12
[sensors]
noise_um = 0
[segments.run]
minutes = 60
spindle_rpm = 2000
"""


@cache
def run(text: str):
    return simulate(parse_scenario_text(text))


@cache
def bundled(name: str):
    return simulate(load_scenario(name))


def row(minutes: float) -> int:
    """Index of the row stamped ``minutes`` after the start."""
    return round(minutes) - 1


def test_paper_magnitudes():
    spindle = bundled("spindle-1000rpm").peak_um()
    assert spindle["z"] < 0  # the head and spindle nose grow down towards the table
    assert 8.0 <= abs(spindle["z"]) <= 18.0  # paper: several um to ~15 um
    assert abs(spindle["y"]) < abs(spindle["z"])
    assert abs(spindle["x"]) < abs(spindle["y"])
    random_run = bundled("random-spindle").peak_um()
    assert abs(random_run["z"]) == pytest.approx(12.9, abs=2.0)  # paper: 12.9 um
    with_feeds = bundled("spindle-feeds").peak_um()
    assert abs(with_feeds["z"]) == pytest.approx(21.9, abs=3.5)  # paper: 21.9 um
    assert abs(with_feeds["z"]) > abs(spindle["z"])


def test_a_slow_component_remains_after_the_spindle_stops():
    r = bundled("spindle-1000rpm")
    z = r.true_um[:, Z]
    peak = np.max(np.abs(z))
    assert abs(z[row(120)]) < 0.6 * peak  # the fast part (spindle nose, minutes) has gone 30 min after
    assert abs(z[row(300)]) > 0.08 * peak  # 3.5 h after the stop the head and column still hold heat
    assert abs(z[-1]) < 0.05 * peak  # and after 10.5 h the machine is back near its start


def test_network_has_the_nodes_and_time_constants_the_docs_claim():
    net = build_network(DEFAULT_MACHINE, Effects())
    assert len(net.names) >= 8
    for name in ("bearing", "stator", "rotor", "head", "column_front", "z_screw", "table", "bed"):
        assert name in net.names
    tau_min = np.sort(1.0 / np.linalg.eigvals(net.K / net.C[:, None]).real) / 60.0
    assert 1.0 < tau_min[0] < 10.0  # minutes
    assert tau_min[-1] > 5 * 60.0  # hours
    assert np.count_nonzero(net.S[Z] > 0) >= 2  # mixed signs: the column lifts what the head lowers
    assert np.count_nonzero(net.S[Z] < 0) >= 2


def test_window_integration_is_exact_for_constant_heat():
    model = ThermalModel(DEFAULT_MACHINE, Effects())
    stats = np.zeros(len(STAT_INDEX))
    stats[STAT_INDEX["spindle_speed"]] = 1000.0
    stats[STAT_INDEX["spindle_omega_sq"]] = (1000.0 * RAD_PER_RPM) ** 2
    stats[STAT_INDEX["spindle_i1_sq"]] = 196.0
    stats[STAT_INDEX["z_i_sq"]] = 13.27
    stepper = model.stepper()
    for _ in range(120):
        stepper.step(stats, 0.0)
    _, q = model.heat(stats)
    net = model.net
    sol = scipy.integrate.solve_ivp(lambda t, T: (q - net.K @ T) / net.C, (0.0, 7200.0), model.T0,
                                    method="LSODA", rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(stepper.T, sol.y[:, -1], rtol=1e-6, atol=1e-8)


def test_determinism_with_a_seed():
    sc = load_scenario("random-spindle")
    a, b = simulate(sc), simulate(sc)
    np.testing.assert_array_equal(a.measured_um, b.measured_um)
    np.testing.assert_array_equal(a.stats, b.stats)
    import dataclasses

    c = simulate(dataclasses.replace(sc, seed=sc.seed + 1))
    np.testing.assert_array_equal(a.true_um, c.true_um)
    assert np.max(np.abs(a.measured_um - c.measured_um)) > 0.05
    noise = a.measured_um - a.true_um
    assert np.std(noise) == pytest.approx(sc.noise_um, rel=0.15)


# -- switchable effects ------------------------------------------------------------------------------------
def test_eddy_loss_is_speed_squared_and_linear_in_its_parameter():
    r15 = run(SPINDLE_2000 + "[effects.eddy_loss]\nloss_w_at_1000rpm = 15\n")
    r30 = run(SPINDLE_2000 + "[effects.eddy_loss]\nloss_w_at_1000rpm = 30\n")
    steady = row(60)
    assert r15.heat_w["eddy_loss"][steady] == pytest.approx(15.0 * 2.0**2, rel=1e-9)
    assert r15.heat_w["eddy_loss"][row(10)] == 0.0
    c15, c30 = r15.contributions_um["eddy_loss"], r30.contributions_um["eddy_loss"]
    np.testing.assert_allclose(c30, 2.0 * c15, rtol=1e-9, atol=1e-12)
    assert c15[row(90), Z] < -1.0  # more heat in the motor: the head grows further down
    assert "eddy_loss" not in run(SPINDLE_2000).contributions_um


def test_room_cycle_acts_through_the_structure():
    cyc = run("[scenario]\nduration_h = 48\n[room]\nthermometer = true\n[sensors]\nnoise_um = 0\n"
              "[effects.room_cycle]\namplitude_k = 2.0\npeak_at_h = 15\n")
    assert cyc.room_c.max() == pytest.approx(22.0, abs=0.01)
    assert cyc.room_c.min() == pytest.approx(18.0, abs=0.01)
    assert cyc.time_s[np.argmax(cyc.room_c)] / 3600.0 == pytest.approx(15.0, abs=0.05)
    d = cyc.true_um
    np.testing.assert_allclose(d[row(24 * 60)], d[row(48 * 60)], atol=0.05)  # periodic steady state
    assert np.ptp(d[:, Z]) > 5.0  # a daily swing of several um
    # a heated hall: warm from 9 to 21 h, cold otherwise, the same swing; the machine starts in its cycle too
    hall = run("[scenario]\nduration_h = 48\n[room]\nthermometer = true\n[sensors]\nnoise_um = 0\n"
               "[effects.room_cycle]\namplitude_k = 2.0\npeak_at_h = 15\nheated_h = 12\n")
    hours = hall.time_s / 3600.0 % 24.0
    warm = (hours > 11.0) & (hours < 19.0)
    cold = (hours < 7.0) | (hours > 23.0)
    np.testing.assert_allclose(hall.room_c[warm], 22.0, atol=0.02)
    np.testing.assert_allclose(hall.room_c[cold], 18.0, atol=0.02)
    np.testing.assert_allclose(hall.true_um[row(24 * 60)], hall.true_um[row(48 * 60)], atol=0.05)
    assert np.ptp(hall.true_um[:, Z]) > 5.0
    ramp = run("[scenario]\nduration_h = 72\n[sensors]\nnoise_um = 0\n"
               "[effects.room_cycle]\namplitude_k = 0\ndrift_k_per_h = 0.1\n")
    # warmed uniformly, the tool moves by the sum of the sensitivities per kelvin
    slope = (ramp.true_um[-1] - ramp.true_um[-361]) / (0.1 * 6.0)
    total = np.array([n.um_per_k for n in DEFAULT_MACHINE.nodes]).sum(axis=0)
    np.testing.assert_allclose(slope, total, rtol=0.01)


def test_slow_path_leaves_a_slow_offset():
    r = run(SPINDLE_2000 + "[effects.slow_path]\ntime_constant_h = 24\num_per_k = { z = 10.0 }\n")
    c = r.contributions_um["slow_path"][:, Z]
    assert c.max() > 1.0  # the slow part's rise lifts the tool (+z, as its parameter says)
    assert c[-1] > 0.5 * c.max()  # 10.5 h after the stop most of it is still there
    slow = r.temperatures_c[:, r.node_names.index("slow_path")] - 20.0
    k_peak = int(np.argmax(slow))
    assert r.time_s[k_peak] > 3 * 3600  # it peaks hours after the heat stopped
    flipped = run(SPINDLE_2000 + "[effects.slow_path]\ntime_constant_h = 24\num_per_k = { z = -10.0 }\n")
    assert flipped.contributions_um["slow_path"][-1, Z] < -0.5 * c.max()


def test_cabinet_heat_follows_the_currents_squared():
    r = run(SPINDLE_2000 + "[effects.cabinet]\nw_per_a2 = 2.0\n")
    f = r.factors
    expected = 2.0 * (f["spindle_i1_sq"] + f["x_i_sq"] + f["y_i_sq"] + f["z_i_sq"])
    np.testing.assert_allclose(r.heat_w["cabinet"], expected, rtol=1e-12)
    c = r.contributions_um["cabinet"]
    assert c[row(120), Y] > 0.3  # a warm column back leans the column forward: +y
    assert c[row(120), Z] > 0.0


def test_a_cabinet_cooler_holds_the_cabinet_between_its_thermostat_points():
    """The cooling unit saws the cabinet between off and on over the hall while the spindle runs hard, never at rest."""
    hard = SPINDLE_2000.replace("minutes = 60\nspindle_rpm = 2000", "minutes = 240\nspindle_rpm = 3000")
    cab = "[effects.cabinet]\nw_per_a2 = 2.0\nthermometer = true\n"
    free = run(hard + cab)
    cooled = run(hard + cab + "cooler_w = 150.0\ncooler_on_k = 4.0\ncooler_off_k = 2.5\n")
    i = free.node_names.index("cabinet")
    during = slice(row(60), row(30 + 240))  # the spindle runs from 30 to 270 min
    assert free.temperatures_c[during, i].max() > 20.0 + 6.0  # without it the cabinet would pass 26 C
    hall = 20.0
    on = cooled.heat_w["cabinet_cooler"] < 0
    assert set(np.unique(cooled.heat_w["cabinet_cooler"])) == {-150.0, 0.0}
    # it starts only above +4 K and stops only below +2.5 K (read at a window's start: within a window's change)
    rise = cooled.temperatures_c[:, i] - hall
    before = np.concatenate([[rise[0]], rise[:-1]])  # the rise at each window's start
    started = on & ~np.concatenate([[False], on[:-1]])
    stopped = ~on & np.concatenate([[False], on[:-1]])
    assert started.sum() >= 3
    assert stopped.sum() >= 3
    assert np.all(before[started] > 4.0)
    assert np.all(before[stopped] < 2.5)
    assert rise[during].max() < 4.5
    assert not on[: row(30)].any()  # at rest (the Z holding current only) it never runs
    assert not on[row(30 + 240 + 60):].any()
    np.testing.assert_array_equal(cooled.thermometers()["cabinet_c"], cooled.temperatures_c[:, i])
    # the column feels less of the cabinet: the effect on y is held down with it
    assert cooled.contributions_um["cabinet"][during, Y].max() < 0.7 * free.contributions_um["cabinet"][during, Y].max()


def test_a_cooler_that_stops_above_where_it_starts_is_refused():
    with pytest.raises(SimulationError) as err:
        parse_scenario_text(SPINDLE_2000 + "[effects.cabinet]\ncooler_w = 100.0\ncooler_on_k = 3.0\ncooler_off_k = 5.0\n")
    assert "effects.cabinet.cooler_off_k: expected below cooler_on_k (3 K" in str(err.value)
    assert "got 5" in str(err.value)


def test_bearing_preload_feeds_back_on_friction_heat():
    peaks = [abs(run(SPINDLE_2000 + (f"[effects.bearing_preload]\ngain_per_k = {g}\n" if g else ""))
                 .peak_um()["z"]) for g in (0.0, 0.01, 0.02)]
    assert peaks[0] < peaks[1] < peaks[2]
    r = run(SPINDLE_2000 + "[effects.bearing_preload]\ngain_per_k = 0.01\n")
    k = row(60)
    T = r.temperatures_c[k - 1]  # the state at the window's start sets the extra heat
    sp = DEFAULT_MACHINE.spindle
    friction = r.heat_w["spindle_friction"][k]
    dT = T[r.node_names.index("bearing")] - T[r.node_names.index("head")]
    assert r.heat_w["bearing_preload"][k] == pytest.approx(friction * 0.01 * dT, rel=1e-12)
    assert dT > 5.0
    assert 0 < sp.front_bearing_share < 1
    assert r.contributions_um["bearing_preload"][row(90), Z] < -0.5


def test_coolant_loop_carries_heat_with_a_dead_time():
    def tank_rise(delay_s: float) -> np.ndarray:
        r = run(SPINDLE_2000 + f"[effects.coolant_delay]\nfraction = 0.5\ndelay_s = {delay_s}\n")
        tank = r.temperatures_c[:, r.node_names.index("coolant_tank")]
        return tank - tank[row(30)]

    now, late = tank_rise(0.0), tank_rise(1800.0)
    start = row(30)
    assert now[start + 29] > 0.05  # 30 min into the run the tank has warmed
    assert abs(late[start + 29]) < 0.05 * now[start + 29]  # with a 30 min dead time it has not yet
    assert late[start + 59] > 0.3 * now[start + 29]  # and then it does
    between = tank_rise(90.0)
    assert tank_rise(60.0)[start + 10] > between[start + 10] > tank_rise(120.0)[start + 10]
    r = run(SPINDLE_2000 + "[effects.coolant_delay]\nfraction = 0.5\ndelay_s = 0\n")
    stator = r.heat_w["stator_joule"] + r.heat_w["iron_hysteresis"]
    np.testing.assert_allclose(r.heat_w["coolant_removed"], -0.5 * stator, rtol=1e-12)
    assert r.contributions_um["coolant_delay"][row(90), Z] > 0.5  # a cooler motor: less growth


def test_chiller_runs_with_the_spindle_and_builds_up():
    r = run(SPINDLE_2000 + "[effects.chiller]\nconductance_w_per_k = 20\ntime_constant_s = 300\n")
    sink = r.heat_w["chiller"]
    assert np.all(sink[: row(30)] == 0.0)  # nothing before the spindle starts
    assert sink[row(32)] < 0.0
    assert abs(sink[row(31)]) < 0.5 * abs(sink[row(40)])  # its own build-up (5 min)
    plain = run(SPINDLE_2000)
    stator = r.node_names.index("stator")
    assert r.temperatures_c[row(90), stator] < plain.temperatures_c[row(90), stator] - 1.0
    assert r.contributions_um["chiller"][row(90), Z] > 0.5
    assert abs(r.peak_um()["z"]) < abs(plain.peak_um()["z"])


def test_sensor_artefacts_step_and_drift():
    r = run("[scenario]\nduration_h = 4\n[sensors]\nnoise_um = 0\n[effects.sensor_artefacts]\nstep_at_h = 2\n"
            "step_um = { z = 3.0 }\ndrift_um_per_h = { x = 0.5, y = -0.25 }\n")
    err = r.measured_um - r.true_um
    t_h = r.time_s / 3600.0
    np.testing.assert_allclose(err[:, X], 0.5 * t_h, atol=1e-12)
    np.testing.assert_allclose(err[:, Y], -0.25 * t_h, atol=1e-12)
    np.testing.assert_allclose(err[:, Z], np.where(t_h >= 2.0, 3.0, 0.0), atol=1e-12)
    np.testing.assert_allclose(r.contributions_um["sensor_artefacts"], err, atol=1e-12)
    np.testing.assert_allclose(r.true_um, 0.0, atol=1e-9)  # nothing moved: the artefacts are the sensor's
    assert set(AXES) == {"x", "y", "z"}
