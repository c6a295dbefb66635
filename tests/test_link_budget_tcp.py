"""Modbus TCP link budget: the round trip measured at start; a period the link cannot hold is refused."""

from __future__ import annotations

import pytest
from test_drivers_support import live_profile
from test_sim_devices_support import WaveSource

from gateway.clock import RealClock
from gateway.errors import ProfileError
from gateway.linkcheck import check_measured_links
from gateway.sampler import Acquisition
from simulators.devices import DeviceSetConfig, serve

DELAY_S = 0.004  # a board behind a slow gateway: every answer 4 ms late


@pytest.fixture(scope="module")
def devices():
    config = DeviceSetConfig(adc_rtu=None, can=None, dcon=None, cnc=None)
    with serve(WaveSource(), RealClock(), config) as devices:
        yield devices


@pytest.fixture
def slow(devices):
    devices.adc_tcp.faults.reply_delay_s = DELAY_S
    yield devices
    devices.adc_tcp.faults.reply_delay_s = 0.0


def test_a_period_the_link_cannot_hold_is_refused_at_start_with_what_it_can_do(slow, tmp_path):
    profile = live_profile(slow, tmp_path)  # sampling.fast_period_s = 0.002, no period of its own
    host, port = slow.adc_tcp.address
    acq = Acquisition(profile, clock=RealClock())
    with pytest.raises(ProfileError) as err:
        acq.start()
    assert acq.samplers[0]._thread is None  # refused before any sampler ran
    message = str(err.value)
    assert message.startswith(f"{profile.path}: devices.adc: a period of 2 ms (sampling.fast_period_s) is faster "
                              f"than the link can go: Modbus TCP to {host}:{port}: one scan is 1 request (fc4 0..8), "
                              "measured at start over 30 scans: median ")
    assert "so it sustains at most" in message
    suggested = float(message.rsplit(">= ", 1)[1])
    assert DELAY_S < suggested < 0.1  # what it can do: at least the board's delay, not absurdly more
    assert err.value.exit_code == 3  # a bad profile: systemd must not restart into it


def test_a_period_the_link_holds_passes_and_says_what_was_measured(slow, tmp_path):
    profile = live_profile(slow, tmp_path, device_keys={"period_s": 0.05})
    (check,) = check_measured_links(profile, clock=RealClock())
    assert check.holds
    assert DELAY_S <= check.budget.min_period_s < 0.05
    assert "measured at start over 30 scans" in check.budget.detail


def test_a_link_slow_only_at_the_first_measurement_is_measured_again_and_passes(devices, tmp_path):
    """A CPU busy at start makes a link look slower than it is; a refusal is final, so it is measured again."""
    from drivers import registry

    profile = live_profile(devices, tmp_path)  # 2 ms
    (d,) = profile.devices
    cls = registry.load(d.driver)
    made = []

    def make():  # the real driver on the real socket; the board answers late only while it is measured first
        devices.adc_tcp.faults.reply_delay_s = DELAY_S if not made else 0.0
        made.append(cls(name=d.name, options=d.options, channels=[(c.name, c.address) for c in profile.channels_of(d.name)],
                        clock=RealClock()))
        return made[-1]

    try:
        (check,) = check_measured_links(profile, clock=RealClock(), driver_factories={d.name: make}, pause_s=0.01)
    finally:
        devices.adc_tcp.faults.reply_delay_s = 0.0
    assert len(made) == 2
    assert check.holds
    assert check.budget.min_period_s < DELAY_S
    assert check.budget.detail.endswith("(the best of 2 measurements 0.01 s apart)")


def test_a_link_too_slow_every_time_is_measured_three_times_then_refused(slow, tmp_path):
    profile = live_profile(slow, tmp_path)
    with pytest.raises(ProfileError) as err:
        check_measured_links(profile, clock=RealClock(), pause_s=0.01)
    assert "median " in str(err.value)
    assert "a scan (the best of 3 measurements 0.01 s apart), so it sustains at most" in str(err.value)


def test_loopback_without_delay_measures_well_under_a_millisecond_scale(devices, tmp_path):
    profile = live_profile(devices, tmp_path, device_keys={"period_s": 0.05})
    (check,) = check_measured_links(profile, clock=RealClock())
    assert 0 < check.budget.min_period_s < DELAY_S


def test_an_unreachable_device_is_not_refused_at_start(devices, tmp_path):
    profile = live_profile(devices, tmp_path, device_keys={"port": 1, "timeout_s": 0.1})
    (check,) = check_measured_links(profile, clock=RealClock())
    assert check.budget is None
    assert check.holds
    assert "cannot connect" in check.skipped
