"""CAN driver against the simulated CAN module: python-can's virtual bus in-process and slcan on a pty."""

from __future__ import annotations

import itertools
import time

import pytest
from test_drivers_support import live_profile, make_driver
from test_sim_devices_support import SIM_VMC_CHANNELS, WaveSource

from drivers.base import Quality
from drivers.can import CanSignalAddress
from gateway.clock import ManualClock
from gateway.errors import DeviceTimeout, DriverError
from gateway.runner import DeviceRunner
from simulators.devices import DeviceSetConfig, serve

RESOLUTION = {"spindle_speed": 0.25, "spindle_i1": 0.01, "spindle_i2": 0.01, "x_velocity": 0.1,
              "y_velocity": 0.1, "z_velocity": 0.1, "x_current": 0.01, "y_current": 0.01, "z_current": 0.01}
_bus_names = itertools.count()


@pytest.fixture
def module():
    clock = ManualClock(50.0)
    source = WaveSource()
    config = DeviceSetConfig(adc_tcp_port=None, adc_rtu=None, dcon=None, cnc=None,
                             can_virtual_channel=f"acq-test-{next(_bus_names)}")
    with serve(source, clock, config) as devices:
        yield source, clock, devices


def read_fresh(driver, *, want=Quality.GOOD, channels=None):
    """Read until every (named) channel has the wanted quality: frames arrive every 10 ms of wall time."""
    deadline = time.monotonic() + 3.0
    idx = [driver.channel_names.index(c) for c in channels] if channels else range(len(driver.channel_names))
    while True:
        reading = driver.read()
        if all(reading.quality[i] == want for i in idx) or time.monotonic() > deadline:
            return reading
        time.sleep(0.005)


@pytest.mark.parametrize("via", ["can-virtual", "can-slcan"])
def test_can_driver_decodes_every_signal(module, tmp_path, via):
    source, clock, devices = module
    profile = live_profile(devices, tmp_path, via=via)
    assert profile.device("can").period_s == 0.01
    with make_driver(profile, "can", clock) as driver:
        reading = read_fresh(driver)
    assert reading.quality == (Quality.GOOD,) * 9
    want = source.values(clock.now())
    got = dict(zip(driver.channel_names, reading.values, strict=True))
    assert set(got) == set(SIM_VMC_CHANNELS)
    for name in SIM_VMC_CHANNELS:
        assert got[name] == pytest.approx(want[name], abs=RESOLUTION[name] / 2 + 1e-9), name


def test_a_frame_too_short_marks_only_the_signals_it_cannot_hold(module, tmp_path):
    _, clock, devices = module
    profile = live_profile(devices, tmp_path, via="can-virtual")
    with make_driver(profile, "can", clock) as driver:
        read_fresh(driver)
        devices.can.faults.corrupt_replies = True  # virtual: every frame one byte short
        reading = read_fresh(driver, want=Quality.BAD, channels=["z_velocity"])
        devices.can.faults.corrupt_replies = False
        q = dict(zip(driver.channel_names, reading.quality, strict=True))
        assert q["z_velocity"] == Quality.BAD  # bits 40..59 need all 8 bytes
        assert q["spindle_i2"] == Quality.GOOD  # bits 32..47 fit in 7
        assert driver.short_frames > 0
        assert read_fresh(driver).quality == (Quality.GOOD,) * 9


def test_slcan_lines_with_bad_data_are_dropped_and_a_silent_bus_times_out(module, tmp_path):
    _, clock, devices = module
    profile = live_profile(devices, tmp_path, via="can-slcan")
    with make_driver(profile, "can", clock) as driver:
        read_fresh(driver)
        devices.can.faults.corrupt_replies = True  # non-hex data: python-can raises ValueError per line
        time.sleep(0.05)
        deadline = time.monotonic() + 3.0
        error = None
        while error is None and time.monotonic() < deadline:
            try:
                driver.read()
            except DeviceTimeout as exc:
                error = exc
            time.sleep(0.01)
        assert driver.bad_lines > 0
    assert error is not None
    assert str(error) == (f'device "can" (CAN slcan {devices.can.slcan_port}): no frame for the device\'s '
                              "signals for 0.2 s (timeout_s)")


def test_an_unplugged_slcan_adapter_fails_once_and_the_runner_reopens_it(module, tmp_path):
    _, clock, devices = module
    profile = live_profile(devices, tmp_path, via="can-slcan")
    runner = DeviceRunner(device=profile.device("can"), channels=profile.channels_of("can"), clock=clock)
    try:
        assert runner.poll() is not None
        devices.can.disconnect_clients()
        deadline = time.monotonic() + 3.0
        while runner.total.reads_failed == 0 and time.monotonic() < deadline:
            runner.poll()
            time.sleep(0.005)
        assert runner.total.reads_failed == 1
        assert "CAN slcan" in runner.total.errors[0]
        reading = None
        while time.monotonic() < deadline:
            reading = runner.poll()
            if reading is not None and reading.quality == (Quality.GOOD,) * 9:
                break
            time.sleep(0.005)
    finally:
        runner.close()
    assert reading is not None
    assert reading.quality == (Quality.GOOD,) * 9
    assert runner.total.recoveries == 1


def test_motorola_and_intel_signals_decode_as_a_dbc_says():
    # DBC: SG_ s : 7|12@0+ (0.5,-10) -> Motorola, MSB at bit 7 of byte 0, 12 bits
    data = bytes([0xAB, 0xC0, 0, 0, 0, 0, 0, 0])  # raw 0xABC = 2748
    moto = CanSignalAddress(frame_id=1, start_bit=7, length_bits=12, byte_order="big", scale=0.5, offset=-10.0)
    assert moto.bytes_needed() == 2
    assert moto.decode(data) == 2748 * 0.5 - 10.0
    # SG_ t : 12|8@1- -> Intel, bits 12..19, signed: 0xF0 in bits 12..19 is -16
    intel = CanSignalAddress(frame_id=1, start_bit=12, length_bits=8, signed=True)
    assert intel.decode(bytes([0x00, 0x00, 0x0F, 0, 0, 0, 0, 0])) == 0xF0 - 256
    assert intel.bytes_needed() == 3


def test_a_closed_driver_error_names_the_device(module, tmp_path):
    _, clock, devices = module
    profile = live_profile(devices, tmp_path, via="can-slcan")
    text = profile.path.read_text().replace(devices.can.slcan_port, str(tmp_path / "no-such-adapter"))
    profile.path.write_text(text)
    from gateway.profile import load_profile

    driver = make_driver(load_profile(profile.path), "can", clock)
    with pytest.raises(DriverError) as err:
        driver.open()
    assert str(err.value).startswith('device "can" (CAN): cannot connect: ')
    assert "no-such-adapter" in str(err.value)
