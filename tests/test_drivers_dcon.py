"""DCON (ADAM-4000 style) driver against the simulated modules on a pseudo-terminal at 9600 baud."""

from __future__ import annotations

import dataclasses

import pytest
from test_drivers_support import live_profile, make_driver
from test_sim_devices_support import SIM_VMC_CHANNELS, WaveSource

from drivers.base import Quality
from gateway.clock import ManualClock
from gateway.errors import DeviceTimeout
from simulators.devices import DeviceSetConfig, serve
from simulators.devices.dcon import DEFAULT_DCON_CONFIG

# one count of +dd.ddd is 1 mV; in engineering units that is the scale of each channel's volts
RESOLUTION = {"spindle_speed": 1.5, "spindle_i1": 0.01, "spindle_i2": 0.01, "x_velocity": 5.0,
              "y_velocity": 5.0, "z_velocity": 5.0, "x_current": 0.005, "y_current": 0.005, "z_current": 0.005}


def dcon_line(checksum: bool):
    if not checksum:
        return DEFAULT_DCON_CONFIG
    return dataclasses.replace(DEFAULT_DCON_CONFIG, modules=tuple(
        dataclasses.replace(m, checksum=True) for m in DEFAULT_DCON_CONFIG.modules))


@pytest.fixture(params=[False, True], ids=["plain", "checksum"])
def line(request):
    clock = ManualClock(20.0)
    source = WaveSource()
    config = DeviceSetConfig(adc_tcp_port=None, adc_rtu=None, can=None, cnc=None, dcon=dcon_line(request.param))
    with serve(source, clock, config) as devices:
        yield source, clock, devices, request.param


def test_dcon_driver_reads_every_input_in_engineering_units(line, tmp_path):
    source, clock, devices, checksum = line
    profile = live_profile(devices, tmp_path, via="dcon")
    assert profile.device("dcon").options.checksum is checksum
    with make_driver(profile, "dcon", clock) as driver:
        reading = driver.read()
    assert reading.quality == (Quality.GOOD,) * 9
    want = source.values(clock.now())
    got = dict(zip(driver.channel_names, reading.values, strict=True))
    assert set(got) == set(SIM_VMC_CHANNELS)
    for name in SIM_VMC_CHANNELS:
        assert got[name] == pytest.approx(want[name], abs=RESOLUTION[name] / 2 + 1e-9), name


def test_a_corrupted_answer_makes_its_modules_values_bad(line, tmp_path):
    _, clock, devices, _checksum = line
    profile = live_profile(devices, tmp_path, via="dcon")
    with make_driver(profile, "dcon", clock) as driver:
        devices.dcon.faults.corrupt_replies = True  # checksum modules: wrong checksum; plain: a digit -> "?"
        reading = driver.read()
        devices.dcon.faults.corrupt_replies = False
        assert reading.quality == (Quality.BAD,) * 9
        assert driver.bad_answers == 2
        assert driver.read().quality == (Quality.GOOD,) * 9


def test_a_value_that_does_not_fit_reads_saturated(line, tmp_path):
    _, clock, devices, _ = line
    profile = live_profile(devices, tmp_path, via="dcon")
    devices.dcon.faults.force("spindle_speed", 200000.0)  # 133 V: the module prints +99.999
    with make_driver(profile, "dcon", clock, channels=["spindle_speed", "x_current"]) as driver:
        reading = driver.read()
    assert reading.quality == (Quality.SATURATED, Quality.GOOD)
    assert reading.values[0] == pytest.approx(99.999 * 1500.0)


def test_a_silent_module_times_out_naming_the_device_and_the_module(line, tmp_path):
    _, clock, devices, checksum = line
    profile = live_profile(devices, tmp_path, via="dcon", device_keys={"timeout_s": 0.2})
    devices.dcon.faults.drop_replies = True
    driver = make_driver(profile, "dcon", clock)
    with driver, pytest.raises(DeviceTimeout) as err:
        driver.read()
    command = "#0184" if checksum else "#01"
    assert str(err.value) == (f'device "dcon" (DCON {devices.dcon.serial_port}): module 01 did not answer '
                              f"'{command}' within 0.2 s")


def test_a_dead_module_goes_off_scan_alone_and_the_other_is_read_on(line, tmp_path):
    source, clock, devices, _ = line
    # the live module's answer must come within timeout_s on a loaded PC too (0.2 s failed once at load 10)
    profile = live_profile(devices, tmp_path, via="dcon", device_keys={"timeout_s": 0.6, "backoff_s": 2.0})
    devices.dcon.silent_modules.add(0x02)  # the currents' module dies
    driver = make_driver(profile, "dcon", clock)
    with driver:
        reading = driver.read()
        names = driver.channel_names
        good = {n for n, q in zip(names, reading.quality, strict=True) if q == Quality.GOOD}
        assert good == {"spindle_speed", "spindle_i1", "spindle_i2", "x_velocity", "y_velocity", "z_velocity"}
        want = source.values(reading.t_s)
        for n, v in zip(names, reading.values, strict=True):
            if n in good:
                assert v == pytest.approx(want[n], abs=RESOLUTION[n]), n
        assert len(reading.errors) == 1
        assert "module 02 did not answer" in reading.errors[0]
        assert reading.errors[0].endswith("(module 02 off-scan; the line's other units are read on)")
        clock.advance(1.0)  # within its back-off: not asked
        asked = devices.dcon.faults.counts["dropped"]
        assert driver.read().errors[0].startswith("module 02 off-scan: ")
        assert devices.dcon.faults.counts["dropped"] == asked
        devices.dcon.silent_modules.clear()
        clock.advance(1.5)
        back = driver.read()
    assert set(back.quality) == {Quality.GOOD}
    assert back.errors == ()
