"""The simulated drives: spindle speed loop and currents, feed axes, per-window factors."""

from __future__ import annotations

import tomllib

import numpy as np
import pytest

from simulators.machine.drives import CHANNELS, FACTORS, STAT_INDEX, SpindleTimeline
from simulators.machine.params import DEFAULT_MACHINE, RAD_PER_RPM
from simulators.machine.scenario import parse_scenario_text
from simulators.machine.schedule import compile_drives
from tests.conftest import PROFILES

N = DEFAULT_MACHINE.samples_per_window


def drives_for(text: str):
    return compile_drives(parse_scenario_text(text), DEFAULT_MACHINE)


def window(drives, w: int) -> dict[str, float]:
    row = drives.window_stats(w * N + 1, (w + 1) * N)
    return {name: float(row[i]) for name, i in STAT_INDEX.items()}


def test_channels_and_factors_are_the_profiles():
    profile = tomllib.loads((PROFILES / "sim-vmc.toml").read_text())
    factors = profile["factors"]
    assert tuple(factors) == FACTORS
    assert {f["channel"] for f in factors.values()} == set(CHANNELS)


def brute_force_spindle(times, rpms, t_end, h=2e-5):
    """The same speed loop integrated with tiny explicit steps: torque = clip(feed-forward + J dw / tau)."""
    p = DEFAULT_MACHINE.spindle
    w, k_ev, wc, out = 0.0, 0, 0.0, []
    for k in range(round(t_end / h)):
        t = k * h
        while k_ev < len(times) and times[k_ev] <= t + 1e-12:
            wc, k_ev = rpms[k_ev] * RAD_PER_RPM, k_ev + 1
        if wc == 0 and w <= p.off_below_rpm * RAD_PER_RPM:
            w, torque = 0.0, 0.0
        else:
            demand = p.inertia_kg_m2 * (wc - w) / p.time_constant_s + p.coulomb_nm + p.viscous_nm_s * w
            limit = p.torque_limit_nm * min(1.0, p.omega_base / w) if w > 0 else p.torque_limit_nm
            torque = max(-limit, min(limit, demand))
            w += h * (torque - p.coulomb_nm - p.viscous_nm_s * w) / p.inertia_kg_m2
        if k % 50 == 0:
            out.append((t, w, torque))
    return np.array(out)


def test_spindle_closed_form_matches_a_brute_force_integration():
    # start, torque-limited ramp, constant-power ramp to 4000 rpm, braking through both, alternation, stop
    times = [0.0, 0.2, 1.5, 3.5, 3.6714, 3.8428, 5.0]
    rpms = [0.0, 1000.0, 4000.0, 400.0, 600.0, 400.0, 0.0]
    ref = brute_force_spindle(times, rpms, 6.0)
    tl = SpindleTimeline.compile(DEFAULT_MACHINE.spindle, times, rpms)
    t = ref[:, 0]
    idx = np.maximum(np.searchsorted(tl.t0, t, side="right") - 1, 0)
    w, torque, _ = tl.evaluate(t, idx)
    assert set(np.unique(tl.kind)) == {0, 1, 2, 3}  # off, linear, torque-limited, power-limited all used
    assert np.max(np.abs(w - ref[:, 1])) / RAD_PER_RPM < 0.5  # rpm
    assert np.max(np.abs(torque - ref[:, 2])) < 0.5  # Nm, at the switching instants the steps differ
    assert np.mean(np.abs(torque - ref[:, 2])) < 0.01


def test_spindle_currents_spike_while_accelerating():
    d = drives_for("[segments.run]\nminutes = 2\nspindle_rpm = 1000\n")
    s = d.samples(1, 2500)  # the first 5 s: at rest, then the start at t = 0
    accel = s["spindle_speed"] < 990
    steady = s["time_s"] > 3.0
    assert s["spindle_i1"][accel].max() > 45.0  # torque-limited start: about 50 A
    assert s["spindle_i2"][accel].max() > 45.0
    assert s["spindle_i1"][steady].max() < 15.0  # at speed: magnetising current and a little torque
    assert s["spindle_i2"][steady].max() < 1.0
    assert abs(s["spindle_speed"][-1] - 1000.0) < 1e-6


def test_z_holds_the_head_at_rest_and_currents_are_signed():
    d = drives_for("[segments.move]\nminutes = 1\nstroke_mm = { x = 200 }\nfeed_mm_min = 6000\n")
    rest = d.values(120.0)
    p = DEFAULT_MACHINE.axes["z"]
    assert rest["z_current"] == pytest.approx(p.gravity_torque_nm / p.torque_constant_nm_per_a, rel=1e-12)
    assert rest["z_current"] > 3.0
    assert rest["x_current"] == 0.0
    assert rest["x_velocity"] == 0.0
    s = d.samples(1, 3000)  # the first 6 s of strokes
    assert s["x_velocity"].max() == pytest.approx(6000.0)
    assert s["x_velocity"].min() == pytest.approx(-6000.0)
    assert s["x_current"].max() > 2.0
    assert s["x_current"].min() < -2.0  # braking and the return stroke: negative q-axis current


def test_diagonal_is_a_linear_interpolation():
    d = drives_for("[segments.diag]\nminutes = 1\nstroke_mm = { x = 120, y = 160 }\nfeed_mm_min = 6000\n")
    s = d.samples(1, 3000)
    assert s["x_velocity"].max() == pytest.approx(3600.0)
    assert s["y_velocity"].max() == pytest.approx(4800.0)
    np.testing.assert_allclose(s["y_velocity"], s["x_velocity"] * 160 / 120, atol=1e-9)
    assert np.all(s["z_velocity"] == 0.0)


def test_alternating_speed_raises_currents_not_mean_speed():
    alt = drives_for("[segments.a]\nminutes = 3\nspindle_rpm = [400, 600]\nchanges_per_min = 350\n")
    const = drives_for("[segments.a]\nminutes = 3\nspindle_rpm = 500\n")
    a, c = window(alt, 1), window(const, 1)
    assert a["spindle_speed"] == pytest.approx(c["spindle_speed"], abs=1.0)
    assert a["spindle_i1_sq"] > 1.25 * c["spindle_i1_sq"]
    assert a["spindle_i2_sq"] > 50.0 * c["spindle_i2_sq"]
    # mean of squares, not square of means: the samples of that window
    s = alt.samples(N + 1, 2 * N)
    assert a["spindle_i1_sq"] == pytest.approx(np.mean(s["spindle_i1"] ** 2), rel=1e-12)
    assert a["spindle_i1_sq"] > np.mean(s["spindle_i1"]) ** 2 + 5.0
    assert a["spindle_i2_sq"] > 1.5 * np.mean(s["spindle_i2"]) ** 2


@pytest.mark.parametrize("text", [
    "[segments.a]\nminutes = 3\nspindle_rpm = [400, 600]\nchanges_per_min = 350\n",
    "[segments.a]\nminutes = 3\nspindle_rpm = 2500\nstroke_mm = { x = 120, y = -160, z = 5 }\nfeed_mm_min = 5000\n",
    "[segments.a]\nminutes = 3\nstroke_mm = { z = -12 }\nfeed_mm_min = 3000\naccel_m_s2 = 5\ndwell_s = 0.3\n",
    "[segments.a]\nminutes = 2.5\nspindle_rpm = [800, 0]\nchanges_per_min = 12\n[segments.b]\nminutes = 1\n",
])
def test_fast_window_statistics_equal_every_sample(text):
    d = drives_for(text)
    for w in range(4):
        fast = d.window_stats(w * N + 1, (w + 1) * N)
        every = d.window_stats(w * N + 1, (w + 1) * N, fast=False)
        np.testing.assert_allclose(fast, every, rtol=1e-9, atol=1e-9)
