"""Recording, plotting and the live source of the simulated machine."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest

from gateway.cli import main
from gateway.clock import ManualClock
from gateway.errors import SimulationError
from gateway.recording import read_recording
from simulators.live import LiveSource
from simulators.machine.drives import CHANNELS, FACTORS
from simulators.machine.live import LiveMachine
from simulators.machine.params import AXES, DEFAULT_MACHINE, RAD_PER_RPM
from simulators.machine.run import simulate
from simulators.machine.scenario import load_scenario, parse_scenario_text

SMALL = """
[scenario]
name = "small"
seed = 7
initial_idle_min = 5
duration_h = 1
[room]
thermometer = true
[effects.room_cycle]
amplitude_k = 1.0
[effects.eddy_loss]
[effects.cabinet]
w_per_a2 = 2.0
thermometer = true
[segments.cut]
minutes = 20
spindle_rpm = [400, 600]
changes_per_min = 350
stroke_mm = { x = 120, y = 160 }
feed_mm_min = 6000
[segments.drill]
minutes = 10
spindle_rpm = 1500
stroke_mm = { z = -30 }
feed_mm_min = 500
dwell_s = 1
"""


def read_back(path: Path):
    return read_recording(path, factor_columns={f: f for f in FACTORS},
                          displacement_columns={a: f"{a}_um" for a in AXES})


def test_record_writes_a_recording_the_gateway_reads_and_a_truth_file(tmp_path: Path, capsys):
    scenario = tmp_path / "small.toml"
    scenario.write_text(SMALL)
    out = tmp_path / "out"
    assert main(["simulate", "record", str(scenario), "-o", str(out), "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert f"wrote {out / 'small.csv'} (60 rows of 60 s, 1 h)" in printed
    assert "peak displacement (noiseless): x " in printed
    rec = read_back(out / "small.csv")
    result = simulate(load_scenario(scenario))
    assert len(rec) == 60
    np.testing.assert_array_equal(rec.time_s, 60.0 * np.arange(1, 61))
    for name in FACTORS:
        np.testing.assert_array_equal(rec.factors[name], result.factors[name])
    for i, a in enumerate(AXES):
        np.testing.assert_array_equal(rec.displacement[a], result.measured_um[:, i])
    np.testing.assert_array_equal(rec.extras["room_c"], result.room_c)
    assert set(rec.extras) == {"room_c", "cabinet_c"}  # the thermometers only: the effects are not in the recording
    assert rec.meta["scenario"] == "small"
    text = (out / "small.csv").read_text()
    assert "eddy" not in text
    assert "room_cycle" not in text
    truth = read_recording(out / "small.truth.csv", factor_columns={},
                           displacement_columns={a: f"{a}_true_um" for a in AXES})
    np.testing.assert_array_equal(truth.displacement["z"], result.true_um[:, 2])
    assert "effect_eddy_loss_z_um" in truth.extras
    assert "effect_room_cycle_y_um" in truth.extras
    assert "temp_bearing_c" in truth.extras
    # the cabinet's thermometer reads its air: the node's temperature, warmer than the room while the spindle runs
    np.testing.assert_array_equal(rec.extras["cabinet_c"], truth.extras["temp_cabinet_c"])
    assert rec.extras["cabinet_c"].max() > rec.extras["room_c"].max() + 1.0
    assert "heat_rotor_joule_w" in truth.extras
    assert truth.meta["effects"] == "room_cycle, eddy_loss, cabinet"


def test_start_time_stamps_the_recording_and_changes_nothing_else(tmp_path: Path):
    stamped = tmp_path / "stamped.toml"
    stamped.write_text(SMALL.replace("duration_h = 1\n", "duration_h = 1\nstart_time_s = 1772409600\n"))
    plain = tmp_path / "plain.toml"
    plain.write_text(SMALL)
    for sc, d in ((stamped, "a"), (plain, "b")):
        assert main(["simulate", "record", str(sc), "-o", str(tmp_path / d), "--no-progress"]) == 0
    a, b = (read_back(tmp_path / d / "small.csv") for d in "ab")
    np.testing.assert_array_equal(a.time_s, 1772409600.0 + 60.0 * np.arange(1, 61))
    np.testing.assert_array_equal(b.time_s, 60.0 * np.arange(1, 61))
    for axis in AXES:
        np.testing.assert_array_equal(a.displacement[axis], b.displacement[axis])
    np.testing.assert_array_equal(a.extras["room_c"], b.extras["room_c"])
    assert simulate(load_scenario(stamped)).recording().time_s[0] == 1772409660.0


def test_record_is_deterministic_and_the_seed_can_be_overridden(tmp_path: Path):
    for d in ("a", "b"):
        assert main(["simulate", "record", "random-spindle", "-o", str(tmp_path / d), "--no-progress"]) == 0
    assert main(["simulate", "record", "random-spindle", "-o", str(tmp_path / "c"), "--seed", "5",
                 "--no-progress"]) == 0
    a, b, c = ((tmp_path / d / "random-spindle.csv").read_bytes() for d in "abc")
    assert a == b
    assert a != c
    assert b"# seed: 5" in c


def test_cli_errors_are_one_line_each(tmp_path: Path, capsys):
    assert main(["simulate", "record", "spindle-100rpm", "-o", str(tmp_path)]) == 7
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert err[0].startswith('cncgw: error: no scenario "spindle-100rpm"')
    bad = tmp_path / "bad.toml"
    bad.write_text("[segments.a]\nminutes = 0\nspindle_rpm = 99999\n")
    assert main(["simulate", "record", str(bad), "-o", str(tmp_path)]) == 7
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2
    assert err[0] == f"cncgw: error: {bad}:2: segments.a.minutes: expected a number in (0, 1e+06], got 0 (an integer)"
    assert err[1].startswith(f"cncgw: error: {bad}:3: segments.a.spindle_rpm: expected a speed in rpm in [0, 8000]")
    assert main(["simulate", "plot", str(tmp_path / "missing.csv"), "-o", str(tmp_path / "p.png")]) == 4
    assert "missing.csv: file not found" in capsys.readouterr().err


def test_plot_from_a_recording_and_from_a_scenario(tmp_path: Path):
    scenario = tmp_path / "small.toml"
    scenario.write_text(SMALL)
    assert main(["simulate", "record", str(scenario), "-o", str(tmp_path), "--no-progress"]) == 0
    for source, png in ((tmp_path / "small.csv", tmp_path / "rec.png"), (scenario, tmp_path / "run.png")):
        assert main(["simulate", "plot", str(source), "-o", str(png)]) == 0
        data = png.read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n"
        assert len(data) > 20_000


def test_list_names_every_bundled_scenario(capsys):
    assert main(["simulate", "list", "--effects"]) == 0
    out = capsys.readouterr().out
    assert "spindle-400-600rpm        12.0 h  identification: spindle alternating 400/600 rpm" in out
    assert "[effects.coolant_delay]" in out
    assert "  um_per_k = { x = 0.0, y = 0.0, z = 10.0 }" in out
    assert "  thermometer = false  # record the cabinet's air temperature as a column, cabinet_c" in out


# -- live ----------------------------------------------------------------------------------------------------
def test_live_source_gives_the_offline_factors_sample_by_sample():
    sc = parse_scenario_text(SMALL)
    offline = simulate(sc)
    clock = ManualClock()
    live = LiveMachine(sc, clock=clock)
    assert isinstance(live, LiveSource)
    assert live.channel_names() == (*CHANNELS, "x_um", "y_um", "z_um", "room_c", "cabinet_c")
    # a gateway sampler: every 2 ms through window 5 (the spindle starts alternating, the table starts)
    n = 30000
    w = 5
    acc = {c: [] for c in CHANNELS}
    for k in range(w * n + 1, (w + 1) * n + 1):
        clock.set(k * 0.002)
        v = live.values(clock.now())
        for c in CHANNELS:
            acc[c].append(v[c])
    f = offline.factors
    s = {c: np.array(x) for c, x in acc.items()}
    got = {"spindle_speed": s["spindle_speed"].mean(), "spindle_i1_sq": np.mean(s["spindle_i1"] ** 2),
           "spindle_i2_sq": np.mean(s["spindle_i2"] ** 2)}
    for a in AXES:
        got[f"{a}_feed"] = np.mean(np.abs(s[f"{a}_velocity"]))
        got[f"{a}_i_sq"] = np.mean(s[f"{a}_current"] ** 2)
    for name in FACTORS:
        assert got[name] == pytest.approx(f[name][w], rel=1e-9, abs=1e-9), name
    assert f["spindle_i2_sq"][w] > 10.0  # the window really has accelerations in it
    # the live machine's own windows, thermal state and sensors, up to the end of the run
    for t in np.arange(60.0, 3600.0 + 1, 60.0):
        v = live.values(t)
        k = round(t / 60.0) - 1
        for i, a in enumerate(AXES):
            assert v[f"{a}_um"] == pytest.approx(offline.measured_um[k, i], abs=1e-9)
        assert v["room_c"] == pytest.approx(offline.room_c[k], abs=1e-12)
        assert v["cabinet_c"] == pytest.approx(offline.recording_columns()["cabinet_c"][k], abs=1e-9)
    mine = live.window_factors()
    for name in FACTORS:
        np.testing.assert_allclose(mine[name], f[name], rtol=1e-12, atol=1e-12)
    true = live.true_displacement_um(1800.0)
    np.testing.assert_allclose([true[a] for a in AXES], offline.true_um[29], atol=1e-9)
    temps = live.temperatures_c(1800.0)
    assert temps["bearing"] == pytest.approx(offline.temperatures_c[29, 0], abs=1e-9)


def test_compensation_makes_the_residual_observable():
    clock = ManualClock()
    live = LiveMachine("spindle-1000rpm", clock=clock)
    clock.set(5400.0)
    d = live.true_displacement_um()
    assert d["z"] < -10.0
    assert live.residual_um() == d  # no offsets yet
    live.set_compensation({"z": -d["z"], "y": 1.0})
    r = live.residual_um()
    assert r["z"] == pytest.approx(0.0, abs=1e-12)
    assert r["y"] == pytest.approx(d["y"] + 1.0)
    assert r["x"] == d["x"]
    assert live.compensation_um == {"x": 0.0, "y": 1.0, "z": -d["z"]}
    assert live.compensation_log == [(5400.0, {"x": 0.0, "y": 1.0, "z": -d["z"]})]
    clock.set(9000.0)
    later = live.residual_um()
    assert later["z"] == pytest.approx(live.true_displacement_um()["z"] - d["z"])
    with pytest.raises(ValueError, match="unknown axis 'w'"):
        live.set_compensation({"w": 1.0})
    with pytest.raises(ValueError, match="must be finite"):
        live.set_compensation({"x": float("nan")})


def test_live_source_is_thread_safe():
    live = LiveMachine("spindle-feeds")
    reference = LiveMachine("spindle-feeds")
    times = 3600.0 + 0.05 * np.arange(2000)
    results: dict[int, list] = {}

    def reader(k: int) -> None:
        results[k] = [live.values(t)["z_um"] for t in times]

    threads = [threading.Thread(target=reader, args=(k,), name=f"reader-{k}") for k in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    expected = [reference.values(t)["z_um"] for t in times]
    for k in range(3):
        assert results[k] == expected


CUT = """
[scenario]
name = "cut"
seed = 3
duration_h = 3
[segments.job]
minutes = 120
spindle_rpm = 1000
{cut}
"""


def test_a_cutting_load_raises_the_spindle_currents_by_its_torque_and_the_displacement():
    """3 kW at 1000 rpm is 28.6 Nm on top of the friction: I1^2 = Im^2 + ((T_f + T_cut) / k_T)^2."""
    plain = simulate(parse_scenario_text(CUT.format(cut="")))
    cut = simulate(parse_scenario_text(CUT.format(cut="cutting_kw = 3.0")))
    sp = DEFAULT_MACHINE.spindle
    w = 1000 * RAD_PER_RPM
    friction = sp.coulomb_nm + sp.viscous_nm_s * w
    i1_sq = lambda t: sp.magnetising_a ** 2 + (t / sp.torque_constant_nm_per_a) ** 2  # noqa: E731
    expected = i1_sq(friction + 3000.0 / w) / i1_sq(friction)  # 2.99: the stated factor
    a, b = plain.recording_columns(), cut.recording_columns()
    steady = slice(10, 120)  # whole minutes at speed, after the first one's ramp
    ratio = b["spindle_i1_sq"][steady] / a["spindle_i1_sq"][steady]
    assert np.allclose(ratio, expected, rtol=1e-3), (ratio.min(), ratio.max(), expected)
    assert np.all(b["spindle_i2_sq"][steady] > 100 * a["spindle_i2_sq"][steady])
    # same speed, more Joule heat in the motor: every axis moves further (Z most, the spindle's own axis)
    peak_plain, peak_cut = np.abs(plain.true_um).max(axis=0), np.abs(cut.true_um).max(axis=0)
    assert np.all(peak_cut > 1.3 * peak_plain), (peak_plain, peak_cut)
    assert peak_cut[2] - peak_plain[2] > 5.0


def test_a_cut_the_spindle_cannot_take_is_refused_with_the_limit():
    with pytest.raises(SimulationError, match=r"segments.job.cutting_kw: expected a cutting power the spindle can "
                                              r"take at 1000 rpm .* at most 7.4\d kW\), got 9"):
        parse_scenario_text(CUT.format(cut="cutting_kw = 9"))
    with pytest.raises(SimulationError, match=r"segments.idle.cutting_kw: given for a segment with the spindle at "
                                              r"0 rpm"):
        parse_scenario_text(CUT.format(cut="[segments.idle]\nminutes = 5\ncutting_kw = 1"))
