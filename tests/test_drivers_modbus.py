"""Modbus TCP and RTU drivers against the simulated ADC board over a real socket and a pseudo-terminal."""

from __future__ import annotations

import dataclasses
import struct

import pytest
from test_drivers_support import live_profile, make_driver
from test_sim_devices_support import SIM_VMC_CHANNELS, WaveSource

from drivers.base import Quality, unpack_words
from drivers.modbus_common import RegisterAddress, describe_requests, plan_requests
from gateway.clock import ManualClock
from gateway.errors import DeviceTimeout, DriverError
from gateway.profile import Device, load_profile
from gateway.runner import DeviceRunner
from simulators.devices import AdcBoardConfig, DeviceSetConfig, RegisterChannel, serve
from simulators.devices.analog import DEFAULT_ADC_CONFIG
from simulators.devices.profile_out import adc_with_displacement

RESOLUTION = {"spindle_speed": 0.469, "spindle_i1": 0.0032, "spindle_i2": 0.0032, "x_velocity": 1.57,
              "y_velocity": 1.57, "z_velocity": 1.57, "x_current": 0.0016, "y_current": 0.0016, "z_current": 0.0016}


@pytest.fixture
def board(tmp_path):
    """The default ADC board plus displacement sensors, over TCP and RTU, fed by sines; clock at 100 s."""
    clock = ManualClock(100.0)
    source = WaveSource((*SIM_VMC_CHANNELS, "x_um", "y_um", "z_um"))
    config = DeviceSetConfig(adc=adc_with_displacement(DEFAULT_ADC_CONFIG), can=None, dcon=None, cnc=None)
    with serve(source, clock, config) as devices:
        yield source, clock, devices


def test_tcp_driver_reads_every_channel_in_engineering_units(board, tmp_path):
    source, clock, devices = board
    profile = live_profile(devices, tmp_path, displacement=True)
    with make_driver(profile, "adc", clock) as driver:
        assert describe_requests(driver.requests) == "2 requests (fc4 0..8, fc4 120..125)"
        reading = driver.read()
    want = source.values(clock.now())
    assert reading.t_s == 100.0
    assert reading.quality == (Quality.GOOD,) * 12
    got = dict(zip(driver.channel_names, reading.values, strict=True))
    for name in SIM_VMC_CHANNELS:  # int16 counts: within one count
        assert got[name] == pytest.approx(want[name], abs=RESOLUTION[name]), name
    for name in ("x_um", "y_um", "z_um"):  # float32
        assert got[name] == pytest.approx(want[name], rel=1e-6), name


def test_rtu_driver_reads_over_the_serial_line(board, tmp_path):
    source, clock, devices = board
    profile = live_profile(devices, tmp_path, via="adc-rtu")
    assert profile.device("adc").period_s == 0.01
    with make_driver(profile, "adc", clock) as driver:
        first = driver.read()
        clock.advance(7.0)
        second = driver.read()
    for reading in (first, second):
        want = source.values(reading.t_s)
        for name, value in zip(driver.channel_names, reading.values, strict=True):
            assert value == pytest.approx(want[name], abs=RESOLUTION.get(name, 1e-5)), name
    assert second.values != first.values


def test_word_and_byte_orders_and_holding_registers(tmp_path):
    clock = ManualClock(10.0)
    source = WaveSource()
    chans = (RegisterChannel(channel="spindle_speed", address=10, encoding="float32", word_order="little"),
             RegisterChannel(channel="spindle_i1", address=12, encoding="float32", byte_order="little"),
             RegisterChannel(channel="spindle_i2", address=14, encoding="float32", word_order="little",
                             byte_order="little"),
             RegisterChannel(channel="x_current", address=16, encoding="uint16", eng_range=(-50.0, 50.0),
                             counts_range=(0, 64000)))
    adc = dataclasses.replace(DEFAULT_ADC_CONFIG, channels=chans, holding_mirror=True)
    config = DeviceSetConfig(adc=adc, adc_rtu=None, can=None, dcon=None, cnc=None)
    with serve(source, clock, config) as devices:
        host, port = devices.adc_tcp.address
        path = tmp_path / "orders.toml"
        path.write_text(f"""
[machine]
name = "orders"
[factors.spindle_speed]
unit = "rpm"
stat = "mean"
[devices.adc]
driver = "modbus_tcp"
host = "{host}"
port = {port}
[channels.spindle_speed]
device = "adc"
address = 10
data_type = "float32"
word_order = "little"
[channels.spindle_i1]
device = "adc"
address = 12
data_type = "float32"
byte_order = "little"
[channels.spindle_i2]
device = "adc"
address = 14
data_type = "float32"
word_order = "little"
byte_order = "little"
[channels.x_current]
device = "adc"
address = 16
function = 3
data_type = "uint16"
scale = {100 / 64000!r}
offset = -50.0
""")
        with make_driver(load_profile(path), "adc", clock) as driver:
            assert describe_requests(driver.requests) == "2 requests (fc3 16..16, fc4 10..15)"
            reading = driver.read()
    want = source.values(10.0)
    got = dict(zip(driver.channel_names, reading.values, strict=True))
    for name in ("spindle_speed", "spindle_i1", "spindle_i2"):
        assert got[name] == pytest.approx(want[name], rel=1e-6), name
    assert got["x_current"] == pytest.approx(want["x_current"], abs=0.0016)


def test_int32_and_uint32_decode_like_struct():
    for fmt, data_type in ((">i", "int32"), (">I", "uint32"), (">f", "float32")):
        value = -123456 if data_type == "int32" else 3_000_000_000 if data_type == "uint32" else -1.5
        hi, lo = struct.unpack(">HH", struct.pack(fmt, value))
        assert unpack_words([hi, lo], data_type, word_order="big", byte_order="big") == value
        assert unpack_words([lo, hi], data_type, word_order="little", byte_order="big") == value
        swapped = [int.from_bytes(w.to_bytes(2, "big")[::-1], "big") for w in (hi, lo)]
        assert unpack_words(swapped, data_type, word_order="big", byte_order="little") == value


def test_contiguous_registers_merge_into_one_request_and_gaps_split():
    a = [RegisterAddress(address=n) for n in (3, 0, 1, 2)] + [RegisterAddress(address=5, data_type="float32"),
                                                             RegisterAddress(address=4, function=3)]
    reqs = plan_requests(a)
    assert describe_requests(reqs) == "3 requests (fc3 4..4, fc4 0..3, fc4 5..6)"
    assert reqs[1].members == ((1, 0), (2, 1), (3, 2), (0, 3))
    many = [RegisterAddress(address=n) for n in range(200)]
    assert describe_requests(plan_requests(many)) == "2 requests (fc4 0..124, fc4 125..199)"


def test_a_converter_at_its_limit_is_flagged_saturated(board, tmp_path):
    _, clock, devices = board
    profile = live_profile(devices, tmp_path)
    devices.adc_tcp.faults.force("spindle_i1", 500.0)  # beyond the +/-100 A range: counts sit at 32767
    with make_driver(profile, "adc", clock, channels=["spindle_speed", "spindle_i1"]) as driver:
        reading = driver.read()
    assert reading.quality == (Quality.GOOD, Quality.SATURATED)
    assert reading.values[1] == 32767 * 0.003125


def test_an_exception_answer_names_the_device_and_the_registers(board, tmp_path):
    _, clock, devices = board
    profile = live_profile(devices, tmp_path)
    text = profile.path.read_text().replace("address = 8\n", "address = 50\n")
    profile.path.write_text(text)
    driver = make_driver(load_profile(profile.path), "adc", clock)
    with driver, pytest.raises(DriverError) as err:
        driver.read()
    assert str(err.value) == 'device "adc" (Modbus TCP): fc4 50..50 answered with exception 2 (illegal data address)'
    assert not driver.is_open  # closed on error: the next read starts with a fresh connection


def test_a_silent_device_times_out_naming_the_device_and_the_timeout(board, tmp_path):
    _, clock, devices = board
    profile = live_profile(devices, tmp_path, device_keys={"timeout_s": 0.2})
    devices.adc_tcp.faults.drop_replies = True
    driver = make_driver(profile, "adc", clock)
    with driver, pytest.raises(DeviceTimeout) as err:
        driver.read()
    assert str(err.value).startswith('device "adc" (Modbus TCP): no valid answer to fc4 0..8 within 0.2 s x 1 '
                                     "attempt: ")


def test_rtu_corrupted_replies_fail_and_the_next_read_recovers(board, tmp_path):
    _, clock, devices = board
    profile = live_profile(devices, tmp_path, via="adc-rtu")
    device: Device = profile.device("adc")
    runner = DeviceRunner(device=device, channels=profile.channels_of("adc"), clock=clock)
    try:
        assert runner.poll() is not None
        devices.adc_rtu.faults.corrupt_replies = True
        assert runner.poll() is None  # bad CRC: no valid answer
        devices.adc_rtu.faults.corrupt_replies = False
        reading = runner.poll()  # the first failure of a working device is retried at the next tick
        assert reading is not None
    finally:
        runner.close()
    c = runner.total
    assert (c.reads_ok, c.reads_failed, c.recoveries) == (2, 1, 1)
    assert c.errors[0].startswith('device "adc" (Modbus RTU): ')
    assert devices.adc_rtu.faults.counts["corrupted"] >= 1


def test_tcp_disconnect_is_one_failed_read_then_a_reconnect(board, tmp_path):
    _, clock, devices = board
    profile = live_profile(devices, tmp_path)
    runner = DeviceRunner(device=profile.device("adc"), channels=profile.channels_of("adc"), clock=clock)
    try:
        assert runner.poll() is not None
        devices.adc_tcp.disconnect_clients()
        results = [runner.poll() for _ in range(3)]
    finally:
        runner.close()
    assert [r is not None for r in results] in ([False, True, True], [True, True, True])
    assert runner.state == "closed"
    assert runner.total.reads_ok >= 3


@pytest.fixture
def line(tmp_path):
    """Two simulated boards sharing one pseudo-terminal line (each answers its own address) and a profile
    whose one RTU device reads unit 1 (the device's) and unit 5; clock at 50 s."""
    clock = ManualClock(50.0)
    source = WaveSource()
    second = AdcBoardConfig(device_id=5, channels=(
        RegisterChannel(channel="x_current", address=0, encoding="float32"),
        RegisterChannel(channel="z_current", address=2, encoding="float32")))
    config = DeviceSetConfig(adc_tcp_port=None, adc_rtu_more=(second,), can=None, dcon=None, cnc=None)
    with serve(source, clock, config) as devices:
        path = tmp_path / "line.toml"
        path.write_text(f"""
[machine]
name = "line"
[factors.spindle_speed]
unit = "rpm"
stat = "mean"
[devices.rs485]
driver = "modbus_rtu"
port = "{devices.adc_rtu.serial_port}"
baudrate = 115200
period_s = 0.01
timeout_s = 0.2
[channels.spindle_speed]
device = "rs485"
address = 100
data_type = "float32"
[channels.x_current]
device = "rs485"
address = 0
data_type = "float32"
unit_id = 5
[channels.z_current]
device = "rs485"
address = 2
data_type = "float32"
unit_id = 5
""")
        yield source, clock, devices, load_profile(path)


def test_several_boards_on_one_rs485_line_are_one_device_whose_channels_name_their_unit(line):
    # the gateway opens the port once and reads unit 1, then unit 5
    source, clock, devices, profile = line
    assert devices.adc_rtu_more[0].serial_port == devices.adc_rtu.serial_port
    assert "adc-rtu-5" in devices.describe()
    driver = make_driver(profile, "rs485", clock)
    with driver:
        assert describe_requests(driver.requests) == "2 requests (unit 1 fc4 100..101, unit 5 fc4 0..3)"
        reading = driver.read()
        want = source.values(reading.t_s)
        assert reading.quality == (Quality.GOOD,) * 3
        for name, value in zip(driver.channel_names, reading.values, strict=True):
            assert value == pytest.approx(want[name], rel=1e-6), name
        # the second board stops answering: it goes off-scan alone, the first one is read on
        devices.adc_rtu_more[0].faults.drop_replies = True
        clock.advance(1.0)
        partial = driver.read()
        assert partial.quality == (Quality.GOOD, Quality.BAD, Quality.BAD)
        assert partial.values[0] == pytest.approx(source.values(partial.t_s)["spindle_speed"], rel=1e-6)
        assert len(partial.errors) == 1
        assert partial.errors[0].startswith('device "rs485" (Modbus RTU): no valid answer to unit 5 fc4 0..3 '
                                            "within 0.2 s x 1 attempt: ")
        assert partial.errors[0].endswith("(unit 5 off-scan; the line's other units are read on)")
        dropped = devices.adc_rtu_more[0].faults.counts["dropped"]
        clock.advance(0.5)  # within backoff_s (1 s): not asked, no timeout spent on it
        skipped = driver.read()
        assert skipped.quality == partial.quality
        assert skipped.errors == (f"unit 5 off-scan: {partial.errors[0].split(' (unit 5')[0]}",)
        assert devices.adc_rtu_more[0].faults.counts["dropped"] == dropped
        devices.adc_rtu_more[0].faults.drop_replies = False
        clock.advance(1.0)
        again = driver.read()  # its back-off is over: asked again, and it answers
        assert again.quality == (Quality.GOOD,) * 3
        assert again.errors == ()
        # the whole line silent: that is the device failing, as any device does
        devices.adc_rtu.faults.drop_replies = devices.adc_rtu_more[0].faults.drop_replies = True
        with pytest.raises(DeviceTimeout, match=r"no valid answer to unit 1 fc4 100..101"):
            driver.read()
    assert again.values != reading.values


def test_a_silent_unit_is_reported_in_the_window_while_the_device_reads_on(line):
    _, clock, devices, profile = line
    runner = DeviceRunner(device=profile.device("rs485"), channels=profile.channels_of("rs485"), clock=clock)
    try:
        assert runner.poll() is not None
        devices.adc_rtu_more[0].faults.drop_replies = True
        clock.advance(1.0)
        reading = runner.poll()
        state = runner.state
    finally:
        runner.close()
    assert reading is not None
    assert reading.quality[0] == Quality.GOOD
    c = runner.take_counters()
    assert (c.reads_ok, c.reads_failed, state) == (2, 0, "on_scan")
    assert c.in_error  # the window will list the line among the devices in error, with the reason
    assert c.errors[0].startswith('device "rs485" (Modbus RTU): no valid answer to unit 5 fc4 0..3')


def test_boards_on_one_line_need_distinct_addresses():
    with pytest.raises(ValueError, match=r"the boards on one RS-485 line need distinct device ids. Got \[1, 1\]"):
        DeviceSetConfig(adc_rtu_more=(DEFAULT_ADC_CONFIG,))
