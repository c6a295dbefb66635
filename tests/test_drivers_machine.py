"""Every driver reads the simulated machine's live values through its own simulated device."""

from __future__ import annotations

import dataclasses
import time

import pytest
from test_drivers_support import live_profile, make_driver

from drivers.base import Quality
from gateway.clock import ManualClock
from simulators.devices import DeviceSetConfig, serve
from simulators.devices.profile_out import rtu_line_boards
from simulators.machine import LiveMachine

# the coarsest step of each path: int16 counts (ADC), CAN scale, 1 mV of a DCON module
STEP = {"adc-tcp": {"spindle_speed": 0.47, "spindle_i1": 0.0032, "spindle_i2": 0.0032, "x_velocity": 1.57,
                    "y_velocity": 1.57, "z_velocity": 1.57, "x_current": 0.0016, "y_current": 0.0016,
                    "z_current": 0.0016},
        "can-slcan": {"spindle_speed": 0.25, "spindle_i1": 0.01, "spindle_i2": 0.01, "x_velocity": 0.1,
                      "y_velocity": 0.1, "z_velocity": 0.1, "x_current": 0.01, "y_current": 0.01, "z_current": 0.01},
        "dcon": {"spindle_speed": 1.5, "spindle_i1": 0.01, "spindle_i2": 0.01, "x_velocity": 5.0, "y_velocity": 5.0,
                 "z_velocity": 5.0, "x_current": 0.005, "y_current": 0.005, "z_current": 0.005}}
STEP["adc-rtu"] = STEP["adc-tcp"]
STEP["adc-rtu-line"] = STEP["adc-tcp"]  # the currents' board sends float32: finer


@pytest.mark.parametrize("via", ["adc-tcp", "adc-rtu", "adc-rtu-line", "can-slcan", "dcon"])
def test_each_driver_reads_the_machines_live_values(tmp_path, via):
    clock = ManualClock(61.5 * 60.0)  # spindle-feeds: spindle at 1000 rpm, X and Y reciprocating
    machine = LiveMachine("spindle-feeds", clock=clock)
    config = DeviceSetConfig(cnc=None)
    if via == "adc-rtu-line":  # two boards on one RS-485 line: the feed currents on the second
        first, second = rtu_line_boards(config.adc)
        config = dataclasses.replace(config, adc=first, adc_rtu_more=(second,))
    with serve(machine, clock, config) as devices:
        profile = live_profile(devices, tmp_path, via=via)
        device = profile.devices[0]
        with make_driver(profile, device.name, clock) as driver:
            deadline = time.monotonic() + 3.0
            while True:  # a CAN module's first frames arrive within 10 ms of wall time
                reading = driver.read()
                if reading.quality == (Quality.GOOD,) * 9 or time.monotonic() > deadline:
                    break
    assert reading.quality == (Quality.GOOD,) * 9
    live = machine.values(clock.now())
    got = dict(zip(driver.channel_names, reading.values, strict=True))
    assert got["spindle_speed"] == pytest.approx(1000.0, abs=2.0)
    assert abs(got["z_current"]) > 1.0  # Z holds the head against gravity
    for name, value in got.items():
        assert value == pytest.approx(live[name], abs=STEP[via][name]), name
