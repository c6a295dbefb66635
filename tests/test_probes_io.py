"""Probe input: the register block the CNC writes (read over a real socket from the simulated CNC), the CSV."""

from __future__ import annotations

import pytest
from tests_paths import ROOT

from gateway.adaptive.probes import PROBE_BLOCK_WORDS, decode_probe_block, encode_probe_block, read_probes
from gateway.clock import ManualClock
from gateway.errors import RecordingError
from gateway.live.cnc import CncLink
from gateway.profile.live import Compensation, default_axes
from simulators.devices import DeviceSet, DeviceSetConfig
from simulators.devices.cnc import CompensationConfig, ProbeCycles
from simulators.machine.live import LiveMachine

ONLY_CNC = {"adc_tcp_port": None, "adc_rtu": None, "can": None, "dcon": None}
SCENARIO = ROOT / "simulators" / "scenarios" / "spindle-1000rpm.toml"


@pytest.fixture
def rig():
    clock = ManualClock(0.0)
    machine = LiveMachine(SCENARIO, clock=clock)
    # a watchdog longer than the test: the clock jumps hours at a time
    cfg = CompensationConfig(probes=ProbeCycles(every_s=1800.0, sd_um=0.3, seed=4), heartbeat_timeout_s=1e6)
    devices = DeviceSet(source=machine, clock=clock, config=DeviceSetConfig(**ONLY_CNC, cnc=cfg)).start()
    link = CncLink(Compensation(host="127.0.0.1", port=devices.cnc.address[1], axes=default_axes(("x", "y", "z"))),
                   clock=clock)
    yield clock, machine, devices.cnc, link
    link.close()
    devices.stop()


def read(link, clock):
    return decode_probe_block(link.read_words(10, PROBE_BLOCK_WORDS), time_s=clock.now(), first_register=10)


def test_the_simulated_cnc_probes_on_schedule_and_the_link_reads_it(rig):
    clock, machine, cnc, link = rig
    assert read(link, clock) == (None, [])  # never probed: all zeros
    clock.set(2 * 3600.0 + 100.0)  # the spindle ran 30..90 min: z has grown
    probe, problems = read(link, clock)
    assert problems == []
    assert probe.seq == 4
    assert probe.sd_um == pytest.approx(0.3)
    t_last, written = cnc.probes_taken[-1]
    assert t_last == 7200.0
    assert len(cnc.probes_taken) == 4
    true = machine.true_displacement_um(7200.0)
    for a in "xyz":
        assert probe.values_um[a] == pytest.approx(written[a], abs=0.051)  # 0.1 um registers
        assert probe.values_um[a] == pytest.approx(true[a], abs=4 * 0.3 + 0.05)
    assert abs(true["z"]) > 5.0  # a displacement worth probing


def test_the_probe_is_the_thermal_displacement_with_the_compensation_taken_out(rig):
    clock, machine, _cnc, link = rig
    link.write_offsets({"z": -100})  # -10 um commanded
    link.set_enabled(True)
    clock.set(1800.0)
    link.beat(1)
    probe, _ = read(link, clock)
    true = machine.true_displacement_um(1800.0)
    assert machine.residual_um(1800.0)["z"] == pytest.approx(true["z"] - 10.0)
    assert probe.values_um["z"] == pytest.approx(true["z"], abs=4 * 0.3 + 0.05)


@pytest.mark.parametrize(("words", "message"), [
    ([7, 8, 0, 0, 0, 0, 0, 0, 3], "register 11 (axis mask): 8 (0x0008): expected bits 0-2 (x, y, z), at least one set"),
    ([7, 0, 0, 0, 0, 0, 0, 0, 3], "register 11 (axis mask): 0 (0x0000)"),
    (encode_probe_block(seq=7, values_um={"z": 1500.0}, sd_um=0.3),
     "probe 7: registers 16-17 (z): 15000 counts = 1500 um: expected within +-1000 um"),
    (encode_probe_block(seq=7, values_um={"x": 1.0}, sd_um=0.0),
     "probe 7: register 18 (uncertainty): 0 counts = 0 um: expected > 0 and <= 50 um"),
])
def test_bad_register_values_are_named(rig, words, message):
    clock, _, cnc, link = rig
    cnc.write_probe(words)
    probe, problems = read(link, clock)
    assert probe is None
    assert any(message in p for p in problems), problems


def test_a_wrong_sign_and_a_repeated_number_reach_the_gateway_as_written(rig):
    clock, _, cnc, link = rig
    clock.set(1900.0)
    first, _ = read(link, clock)
    cnc.write_probe(values_um={"z": -first.values_um["z"]}, seq=first.seq)  # a macro that writes twice
    again, problems = read(link, clock)
    assert problems == []
    assert again.seq == first.seq
    assert again.values_um["z"] == pytest.approx(-first.values_um["z"])


def test_the_probe_csv_is_read(tmp_path):
    f = tmp_path / "probes.csv"
    f.write_text("# probes of vmc-3\ntime,seq,x_um,y_um,z_um,sd_um\n"
                 "2026-03-02T08:00:00Z,1,0.5,,-3.25,0.3\n1772445600,2,,,-4.0,0.5\n")
    p1, p2 = read_probes(f)
    assert p1.time_s == 1772438400.0
    assert p1.values_um == {"x": 0.5, "z": -3.25}
    assert p1.sd_um == 0.3
    assert p2.seq == 2
    assert dict(p2.values_um) == {"z": -4.0}


@pytest.mark.parametrize(("text", "message"), [
    ("time,seq,z_um\n1,1,2\n", "no column 'sd_um'"),
    ("time,seq,sd_um\n1,1,0.3\n", "no axis column: expected at least one of x_um, y_um, z_um"),
    ("time,seq,z_um,sd_um\n1,1,abc,0.3\n", ":2: column 'z_um': 'abc' is not a displacement in um"),
    ("time,seq,z_um,sd_um\n1,1.5,2,0.3\n", ":2: column 'seq': '1.5' is not a sequence number 0..65535"),
    ("time,seq,z_um,sd_um\n1,1,2,0\n", ":2: uncertainty 0.0 um: expected > 0"),
    ("time,seq,z_um,sd_um\n1,1,,0.3\n", ":2: no axis probed"),
    ("time,seq,z_um,sd_um\n1,1,2,0.3\n2,1,2,0.3\n", ":3: sequence number 1 does not follow 1"),
    ("time,seq,z_um,sd_um\n5,1,2,0.3\n2,2,2,0.3\n", ":3: time 2 is before the previous row's"),
    ("time,seq,z_um,sd_um\n1,1,2000,0.3\n", ":2: axis z: value 2000.0 um is outside +-1000 um"),
    ("time,seq,z_um,sd_um\n1,1,2\n", ":2: 3 cells, expected 4"),
])
def test_bad_probe_csv_names_file_line_and_column(tmp_path, text, message):
    f = tmp_path / "probes.csv"
    f.write_text(text)
    with pytest.raises(RecordingError) as err:
        read_probes(f)
    assert message in str(err.value)
    assert str(f) in str(err.value)


@pytest.fixture(scope="module")
def room_run(tmp_path_factory):
    """The paper's spindle-and-feeds run in a room swinging 6 K in 8 h, recorded; probes of its truth every 30 min."""
    import tomllib

    import numpy as np
    import tomli_w

    from simulators.machine.run import simulate, write_run
    from simulators.machine.scenario import parse_scenario_text

    out = tmp_path_factory.mktemp("room")
    doc = tomllib.loads((ROOT / "simulators" / "scenarios" / "spindle-feeds.toml").read_text())
    doc["effects"] = {"room_cycle": {"amplitude_k": 3.0, "period_h": 8.0, "peak_at_h": 4.0}}
    result = simulate(parse_scenario_text(tomli_w.dumps(doc), source="room"))
    rec, _ = write_run(result, out)
    rng = np.random.default_rng(3)
    rows = ["time_s,seq,x_um,y_um,z_um,sd_um"]
    for q, k in enumerate(range(29, len(result.time_s), 30)):
        vals = result.true_um[k] + 0.3 * rng.standard_normal(3)
        rows.append(f"{result.time_s[k]:g},{q + 1},{vals[0]:.3f},{vals[1]:.3f},{vals[2]:.3f},0.3")
    probes = out / "probes.csv"
    probes.write_text("\n".join(rows) + "\n")
    return rec, probes


def cli(args, capsys):
    from gateway.cli import main

    code = main([str(a) for a in args])
    return code, capsys.readouterr()


def test_estimate_with_probes_from_a_csv(room_run, capsys, tmp_path):
    import json

    rec, probes = room_run
    code, out = cli(["estimate", "--profile", "sim-vmc", rec, "--json", "--align", "none"], capsys)
    assert code == 0
    alone = json.loads(out.out)[0]["axes"]["z"]["rms_um"]
    code, out = cli(["estimate", "--profile", "sim-vmc", rec, "--probes", probes, "--json", "--align", "none", "-o",
                     tmp_path / "p.csv"],
                    capsys)
    assert code == 0, out.err
    doc = json.loads(out.out)[0]
    assert doc["probes_applied"] == 16 * 3  # every 30 min of the 8 h run, three axes each
    assert doc["refused"] == []
    assert alone > 1.0  # the room the model does not know
    assert doc["axes"]["z"]["rms_um"] < 0.3 * alone
    assert doc["axes"]["z"]["band_coverage"] > 0.85
    head = next(ln for ln in (tmp_path / "p.csv").read_text().splitlines() if not ln.startswith("#"))
    assert head == "time_s,x_um,x_sd_um,x_model_um,y_um,y_sd_um,y_model_um,z_um,z_sd_um,z_model_um"


def test_estimate_with_a_bad_probe_file_names_the_line(room_run, capsys, tmp_path):
    rec, _ = room_run
    bad = tmp_path / "bad.csv"
    bad.write_text("time_s,seq,z_um,sd_um\n7200,1,2.0,0.3\n10800,1,2.5,0.3\n")
    code, out = cli(["estimate", "--profile", "sim-vmc", rec, "--probes", bad], capsys)
    assert code == 4
    assert f"{bad}:3: sequence number 1 does not follow 1" in out.err
    code, out = cli(["estimate", "--profile", "sim-vmc", rec, "--probes", bad, "--initial-state", "fit"], capsys)
    assert code == 2
    assert "--initial-state fit is not used with them" in out.err
