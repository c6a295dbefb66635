"""The simulated DCON (ADAM-4000 style) modules on a pseudo-terminal, against a pyserial client."""

from __future__ import annotations

import re

import pytest
import serial
from test_sim_devices_support import WaveSource

from gateway.clock import ManualClock
from simulators.devices import (
    DEFAULT_DCON_CONFIG,
    SIM_VMC_ANALOG,
    DconChannel,
    DconLineConfig,
    DconModuleConfig,
    DeviceSet,
    DeviceSetConfig,
)
from simulators.devices.dcon import checksum

ONLY_DCON = {"adc_tcp_port": None, "adc_rtu": None, "can": None, "cnc": None}
VALUE = re.compile(r"[+-]\d+(?:\.\d+)?")


@pytest.fixture
def clock():
    return ManualClock(33.0)


@pytest.fixture
def source():
    return WaveSource()


def line_with(source, clock, config=DEFAULT_DCON_CONFIG):
    return DeviceSet(source=source, clock=clock, config=DeviceSetConfig(**ONLY_DCON, dcon=config))


@pytest.fixture
def devices(source, clock):
    with line_with(source, clock) as devs:
        yield devs


def ask(port, command: str) -> bytes:
    """Send a command, return the answer with its CR (b"" if the module stays silent within the timeout)."""
    port.reset_input_buffer()
    port.write(command.encode("ascii") + b"\r")
    return port.read_until(b"\r")


def volts(name, value):
    return SIM_VMC_ANALOG[name].volts(value)


@pytest.fixture
def port(devices):
    with serial.Serial(devices.dcon.serial_port, baudrate=9600, timeout=0.5) as port:
        yield port


def test_all_inputs_read_live_voltages(devices, port, source, clock):
    for _ in range(2):
        expected = source.values(clock.now())
        answer = ask(port, "#01")
        assert answer.startswith(b">")
        assert answer.endswith(b"\r")
        fields = VALUE.findall(answer[1:-1].decode())
        assert len(fields) == 8
        assert all(len(f) == 7 for f in fields)  # +dd.ddd
        names = ("spindle_speed", "spindle_i1", "spindle_i2", "x_velocity", "y_velocity", "z_velocity")
        for name, text in zip(names, fields, strict=False):
            assert float(text) == pytest.approx(volts(name, expected[name]), abs=0.0005 + 1e-9), name
        assert fields[6:] == ["+00.000", "+00.000"]  # unwired inputs
        currents = VALUE.findall(ask(port, "#02").decode())
        for name, text in zip(("x_current", "y_current", "z_current"), currents, strict=False):
            assert float(text) == pytest.approx(volts(name, expected[name]), abs=0.0005 + 1e-9), name
        clock.advance(9.0)


def test_single_input_name_firmware_config_and_invalid_commands(port, source, clock):
    expected = source.values(clock.now())
    one = ask(port, "#023")  # module 02, input 3: unwired
    assert one == b">+00.000\r"
    z = ask(port, "#012")
    assert float(z[1:-1]) == pytest.approx(volts("spindle_i2", expected["spindle_i2"]), abs=0.0005 + 1e-9)
    assert ask(port, "$01M") == b"!014017\r"
    assert ask(port, "$02F") == b"!02A2.10\r"
    assert ask(port, "$012") == b"!01080600\r"  # +/-10 V, 9600 baud, no checksum
    assert ask(port, "#019") == b"?01\r"  # no input 9
    assert ask(port, "$01Q") == b"?01\r"
    assert ask(port, "%01ZZ") == b"?01\r"


def test_other_addresses_get_no_answer(port):
    assert ask(port, "#07") == b""
    assert ask(port, "$FFM") == b""
    assert ask(port, "#01").startswith(b">")


def test_checksum_mode_and_engineering_units(source, clock):
    inputs = (DconChannel(channel="spindle_speed", scaling="engineering", int_digits=5, decimals=1),
              DconChannel(channel="z_current", scaling="engineering", int_digits=3, decimals=2))
    config = DconLineConfig(baudrate=115200, modules=(
        DconModuleConfig(address=0x1A, checksum=True, name="4018", inputs=inputs),))
    with line_with(source, clock, config) as devs, \
            serial.Serial(devs.dcon.serial_port, baudrate=115200, timeout=0.5) as port:
        expected = source.values(clock.now())
        answer = ask(port, "#1A" + checksum("#1A")).decode()
        body, given = answer[:-3], answer[-3:-1]
        assert given == checksum(body)
        speed, current = VALUE.findall(body[1:])
        assert len(speed) == 8  # +ddddd.d
        assert float(speed) == pytest.approx(expected["spindle_speed"], abs=0.05 + 1e-9)
        assert float(current) == pytest.approx(expected["z_current"], abs=0.005 + 1e-9)
        assert ask(port, "$1a2" + checksum("$1a2")).decode()[:-3] == "!1A080A40"  # 115200, checksum on
        assert ask(port, "#1A00") == b""  # a wrong checksum gets no answer at all
        assert ask(port, "#1A") == b""  # nor does a missing one


def test_out_of_range_value_shows_all_nines(devices, port):
    devices.dcon.faults.force("x_velocity", 1e9)
    devices.dcon.faults.force("y_velocity", -1e9)
    assert VALUE.findall(ask(port, "#01").decode())[3:5] == ["+99.999", "-99.999"]


def test_frozen_input_stops_moving(devices, port, clock):
    before = VALUE.findall(ask(port, "#01").decode())
    devices.dcon.faults.freeze("spindle_speed")
    clock.advance(50.0)
    after = VALUE.findall(ask(port, "#01").decode())
    assert after[0] == before[0]
    assert after[1:6] != before[1:6]


def test_dropped_and_delayed_answers(devices, port):
    devices.dcon.faults.drop_replies = True
    assert ask(port, "#01") == b""
    devices.dcon.faults.drop_replies = False
    devices.dcon.faults.reply_delay_s = 1.0
    assert ask(port, "$01M") == b""  # not within the client's 0.5 s...
    port.timeout = 5.0
    assert port.read_until(b"\r") == b"!014017\r"  # ...but it comes
    assert devices.dcon.faults.counts["dropped"] == 1
    assert devices.dcon.faults.counts["delayed"] == 1


def test_corrupt_answers_fail_their_checksum_or_their_format(source, clock):
    config = DconLineConfig(baudrate=115200, modules=(
        DconModuleConfig(address=1, checksum=True, inputs=(DconChannel(channel="x_current"),)),
        DconModuleConfig(address=2, inputs=(DconChannel(channel="y_current"),)),
    ))
    with line_with(source, clock, config) as devs, \
            serial.Serial(devs.dcon.serial_port, baudrate=115200, timeout=0.5) as port:
        devs.dcon.faults.corrupt_replies = True
        with_sum = ask(port, "#01" + checksum("#01")).decode()
        assert with_sum[-3:-1] != checksum(with_sum[:-3])
        plain = ask(port, "#02").decode()
        assert VALUE.fullmatch(plain[1:-1]) is None
        devs.dcon.faults.corrupt_replies = False
        devs.dcon.faults.garbage_replies = True
        garbage = ask(port, "#02")
        assert not re.fullmatch(rb">[+-]\d\d\.\d{3}\r", garbage)


def test_disconnect_is_seen_and_the_same_path_works_again(devices, port):
    path = devices.dcon.serial_port
    assert ask(port, "$01M") == b"!014017\r"
    devices.dcon.disconnect_clients()
    with pytest.raises(serial.SerialException, match="Input/output error"):
        port.write(b"$01M\r")  # as when a USB adapter is pulled
    assert devices.dcon.serial_port == path
    with serial.Serial(path, baudrate=9600, timeout=0.5) as again:
        assert ask(again, "$02M") == b"!024017\r"


def test_line_config_is_checked():
    with pytest.raises(ValueError, match="unique"):
        DconLineConfig(modules=(DconModuleConfig(address=1, inputs=(DconChannel(channel="a"),)),) * 2)
    with pytest.raises(ValueError, match="baudrate"):
        DconLineConfig(baudrate=1000, modules=DEFAULT_DCON_CONFIG.modules)
    with pytest.raises(ValueError, match="scaling"):
        DconChannel(channel="a", scaling="percent")
