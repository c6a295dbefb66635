"""`cncgw simulate serve --profile-out`: the bundled profile with the live address of a simulated device."""

from __future__ import annotations

import pytest

from gateway.cli import main
from gateway.profile import load_profile


@pytest.mark.parametrize(("via", "driver", "period_s"), [("adc-tcp", "modbus_tcp", 0.002),
                                                         ("adc-rtu", "modbus_rtu", 0.01),
                                                         ("adc-rtu-line", "modbus_rtu", 0.02),
                                                         ("can-slcan", "can", 0.01), ("dcon", "dcon", 0.2)])
def test_profile_out_names_the_live_device(tmp_path, capsys, via, driver, period_s):
    out = tmp_path / "live.toml"
    code = main(["simulate", "serve", "spindle-1000rpm", "--speedup", "60", "--duration", "0.2",
                 "--profile-out", str(out), "--via", via])
    printed = capsys.readouterr().out
    assert code == 0
    profile = load_profile(out)
    (device,) = profile.devices
    assert (device.driver, device.period_s) == (driver, period_s)
    assert [c.name for c in profile.channels] == ["spindle_speed", "spindle_i1", "spindle_i2", "x_velocity",
                                                  "y_velocity", "z_velocity", "x_current", "y_current", "z_current"]
    o = device.options
    where = {"modbus_tcp": lambda: f"modbus-tcp://{o.host}:{o.port} ", "modbus_rtu": lambda: f"modbus-rtu:{o.port} ",
             "can": lambda: f"slcan:{o.channel} ", "dcon": lambda: f"dcon:{o.port} "}[driver]()
    assert where in printed  # the address written is the one served
    units = {c.name: c.address.unit_id for c in profile.channels} if driver == "modbus_rtu" else {}
    if via == "adc-rtu-line":  # the feed currents on the line's second board
        assert units == {c: (2 if c.endswith("_current") else None) for c in units}
        assert "adc-rtu-2" in printed
    assert profile.model_path.is_absolute()


def test_profile_out_with_displacement_reads_bursts(tmp_path, capsys):
    out = tmp_path / "live.toml"
    assert main(["simulate", "serve", "spindle-1000rpm", "--duration", "0.2", "--profile-out", str(out),
                 "--displacement"]) == 0
    capsys.readouterr()
    profile = load_profile(out)
    assert dict(profile.sampling.displacement_channels) == {"x": "x_um", "y": "y_um", "z": "z_um"}
    assert profile.sampling.burst_speed_channel == "spindle_speed"
    assert [c.address.address for c in profile.channels[-3:]] == [120, 122, 124]


def test_displacement_needs_the_adc_board(capsys):
    assert main(["simulate", "serve", "spindle-1000rpm", "--via", "dcon", "--displacement"]) == 2
    assert capsys.readouterr().err == ("cncgw: error: --displacement: the displacement sensors are on the ADC "
                                       "board, not --via dcon\n")


@pytest.mark.parametrize(("extra", "enabled", "watchdog_s"), [([], False, 30.0),
                                                             (["--compensate", "--cnc-watchdog-s", "12"], True, 12.0)])
def test_profile_out_points_compensation_at_the_simulated_cnc(tmp_path, capsys, extra, enabled, watchdog_s):
    out = tmp_path / "live.toml"
    assert main(["simulate", "serve", "spindle-1000rpm", "--speedup", "60", "--duration", "0.2",
                 "--profile-out", str(out), *extra]) == 0
    printed = capsys.readouterr().out
    comp = load_profile(out).compensation
    assert comp.enabled is enabled  # a dry run unless asked
    assert f"modbus-tcp://{comp.host}:{comp.port} " in printed  # the CNC served is the one written
    assert comp.watchdog_s == watchdog_s  # default at 60x: half a wall second, 30 s of clock time
    assert comp.heartbeat_period_s == pytest.approx(watchdog_s / 5)


def test_profile_out_via_opcua_reads_the_cncs_own_server(tmp_path, capsys):
    out = tmp_path / "live.toml"
    code = main(["simulate", "serve", "spindle-1000rpm", "--speedup", "60", "--duration", "0.2",
                 "--profile-out", str(out), "--via", "opcua"])
    printed = capsys.readouterr().out
    assert code == 0
    profile = load_profile(out)
    (device,) = profile.devices
    assert (device.driver, device.period_s, device.options.mode) == ("opcua", 0.01, "poll")
    assert f"CNC OPC UA server            {device.options.endpoint}" in printed
    assert sorted(c.name for c in profile.channels) == sorted(
        ["spindle_speed", "spindle_i1", "spindle_i2", "x_velocity", "y_velocity", "z_velocity", "x_current",
         "y_current", "z_current"])
    speed = next(c for c in profile.channels if c.name == "spindle_speed")
    assert speed.address.browse_path == ("2:CncInterface", "2:CncSpindleList", "2:Spindle", "2:ActSpeed")
    assert {c.unit for c in profile.channels} == {"rpm", "A", "mm/min"}
