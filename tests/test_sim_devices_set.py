"""The device set as the integrator uses it (serve, describe, stop) and ``cncgw simulate serve``."""

from __future__ import annotations

import socket
import struct
import threading

import can
import pytest
import serial
from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from test_sim_devices_support import WaveSource

from gateway import cli
from gateway.clock import ManualClock, ScaledClock
from gateway.errors import SimulationError
from simulators.devices import DeviceSet, DeviceSetConfig, TcpTransport, serve
from simulators.devices.cli import serve_until_stopped


def test_serve_starts_every_device_and_stop_cleans_up():
    source, clock = WaveSource(), ManualClock(5.0)
    devices = serve(source, clock)
    try:
        listing = devices.describe()
        for name in ("adc-tcp", "adc-rtu", "can", "dcon", "cnc"):
            assert name in listing
        assert "127.0.0.1:" in listing
        assert "0.0.0.0" not in listing
        expected = source.values(clock.now())

        tcp = ModbusTcpClient("127.0.0.1", port=devices.adc_tcp.address[1], timeout=2.0, retries=0)
        rtu = ModbusSerialClient(devices.adc_rtu.serial_port, baudrate=115200, timeout=1.0, retries=0)
        cnc = ModbusTcpClient("127.0.0.1", port=devices.cnc.address[1], timeout=2.0, retries=0)
        try:
            speed = tcp.read_input_registers(100, count=2, device_id=1).registers
            assert struct.unpack(">f", struct.pack(">HH", *speed))[0] == pytest.approx(expected["spindle_speed"])
            assert rtu.read_input_registers(0, count=9, device_id=1).registers == \
                tcp.read_input_registers(0, count=9, device_id=1).registers
            assert cnc.read_input_registers(6, count=1, device_id=1).registers == [0]
        finally:
            for client in (tcp, rtu, cnc):
                client.close()
        with can.Bus(interface="virtual", channel=devices.can.virtual_channel) as bus:
            assert bus.recv(timeout=2.0) is not None
        with serial.Serial(devices.dcon.serial_port, timeout=1.0) as port:
            port.write(b"$02M\r")
            assert port.read_until(b"\r") == b"!024017\r"
        links = list(devices.link_dir.iterdir())
        assert sorted(p.name for p in links) == ["adc-rtu", "dcon", "slcan"]
    finally:
        devices.stop()
    devices.stop()  # idempotent
    assert not devices.link_dir.exists()


def test_context_manager_stops_everything_when_the_body_fails():
    with pytest.raises(KeyError), DeviceSet(source=WaveSource(), clock=ScaledClock(100.0)) as devices:
        raise KeyError("boom")
    assert not devices.link_dir.exists()
    with pytest.raises(RuntimeError, match="starts once"):
        devices.start()


def test_a_port_in_use_is_a_clear_error_and_nothing_is_left_running():
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        config = DeviceSetConfig(cnc_port=port)
        with pytest.raises(SimulationError, match=f"cnc: cannot listen on 127.0.0.1:{port}"):
            serve(WaveSource(), ManualClock(), config)


def test_cli_serve_on_a_port_in_use_exits_1_as_a_server_that_cannot_start(capsys):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        rc = cli.main(["simulate", "serve", "spindle-1000rpm", "--cnc-port", str(port), "--duration", "0.3"])
    err = capsys.readouterr().err
    assert rc == 1, err  # the README's exit-code table: a server that cannot start; 7 is a bad scenario
    # one error line, the last thing said (pymodbus's own warning may come before it; in a full suite a log
    # handler an earlier test left on its closed stream can add logging's "--- Logging error ---" too)
    assert err.strip().splitlines()[-1].startswith(f"cncgw: error: cnc: cannot listen on 127.0.0.1:{port} (is the "
                                                   "port in use?)"), err


def test_only_loopback_addresses_are_accepted():
    with pytest.raises(ValueError, match="loopback"):
        DeviceSetConfig(host="0.0.0.0")
    with pytest.raises(ValueError, match="loopback"):
        TcpTransport(host="192.168.1.10")
    assert DeviceSetConfig(host="::1").host == "::1"


def test_serve_until_stopped_prints_the_addresses(capsys):
    stop = threading.Event()
    stop.set()  # serve, print, and stop at once
    assert serve_until_stopped(WaveSource(), ManualClock(), DeviceSetConfig(adc_rtu=None), stop=stop) == 0
    out = capsys.readouterr().out
    assert "modbus-tcp://127.0.0.1:" in out
    assert "slcan:" in out
    assert "devices stopped" in out


def test_cli_serve_with_a_bad_scenario_fails_clearly(capsys, tmp_path):
    scenario = tmp_path / "scenario.toml"
    scenario.write_text("[scenario]\nname = 'x'\nseed = -1\n")
    assert cli.main(["simulate", "serve", str(scenario), "--speedup", "60"]) == SimulationError.exit_code
    err = capsys.readouterr().err
    assert f"{scenario}:" in err
    assert "Traceback" not in err


def test_cli_serves_the_simulated_machine(capsys):
    assert cli.main(["simulate", "serve", "spindle-1000rpm", "--speedup", "600", "--duration", "0.3"]) == 0
    out = capsys.readouterr().out
    assert "modbus-tcp://127.0.0.1:" in out
    assert "devices stopped" in out


def test_cli_serve_checks_its_arguments(capsys):
    assert cli.main(["simulate", "serve", "x.toml", "--speedup", "0"]) == 2  # a bad argument value: usage
    assert "--speedup must be a finite number > 0" in capsys.readouterr().err
    assert cli.main(["simulate", "serve", "x.toml", "--adc-port", "70000"]) == 2
    assert "--adc-port must be in 0..65535" in capsys.readouterr().err
