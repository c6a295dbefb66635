"""The OPC UA client driver against the simulated CNC's OPC UA server on 127.0.0.1 (port 0): reads by node id
and browse path, polled and subscribed; the link budget; windows good at the fastest period it claims; and
the figures its docstring gives for what coarser sampling does to a mean of squares."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from test_drivers_support import live_profile, make_driver
from test_sim_devices_support import WaveSource

from drivers.base import Quality
from gateway.clock import ScaledClock
from gateway.errors import DriverError, ProfileError
from gateway.sampler import Acquisition
from simulators.devices import DeviceSetConfig, serve
from simulators.devices.opcua_cnc import OpcUaCncConfig

SPEEDUP = 60.0  # a 60 s window lasts 1 s of wall time


@pytest.fixture(scope="module")
def cnc():
    clock = ScaledClock(SPEEDUP, origin=0.0)
    source = WaveSource()
    config = DeviceSetConfig(adc_tcp_port=None, adc_rtu=None, can=None, dcon=None, cnc=None,
                             cnc_opcua=OpcUaCncConfig())
    with serve(source, clock, config) as devices:
        yield devices, source, clock


def within_recent(source, name, value, t, span_s=0.25 * SPEEDUP, after_s=0.05 * SPEEDUP):
    """The value the source had at some moment from ``span_s`` clock seconds before ``t`` to ``after_s`` after.

    Before: the server's updater samples every 10 ms of wall time, and a loaded PC holds it off longer.
    After: a reading is stamped when its request leaves, and the server may take a fresh sample before it
    answers (seen in a full-suite run: a value the source had 0.24 ms of wall time after the stamp).
    Between two points of the grid the source can go beyond both: at a crest or trough a value read there lies
    outside the grid's own extremes (seen in CI: x_velocity -18999.9994 at its trough of -19000, where the
    nearest grid points gave -18999.98). So the range is widened by half the largest step between neighbours.
    """
    seen = np.array([source.values(t - span_s + (span_s + after_s) * k / 400)[name] for k in range(401)])
    slack = 0.5 * float(np.max(np.abs(np.diff(seen)))) + 1e-6
    return seen.min() - slack <= value <= seen.max() + slack


@pytest.mark.parametrize("mode", ["poll", "subscription"])
def test_reads_node_ids_and_a_browse_path_in_engineering_units(cnc, tmp_path, mode):
    devices, source, clock = cnc
    profile = live_profile(devices, tmp_path, via="opcua", device_keys={"mode": mode})
    assert profile.channels[0].address.browse_path[0] == "2:CncInterface"  # the first channel: by browse path
    assert profile.channels[1].address.node_id == "ns=2;s=Spindle.ActCurrent"
    with make_driver(profile, "cnc", clock) as driver:
        time.sleep(0.1)  # a subscription's first report
        reading = driver.read()
    assert reading.quality == (Quality.GOOD,) * 9
    for name, value in zip(driver.channel_names, reading.values, strict=True):
        assert within_recent(source, name, value, reading.t_s), (name, value)


def test_a_node_the_server_does_not_have_is_named(cnc, tmp_path):
    devices, _, clock = cnc
    profile = live_profile(devices, tmp_path, via="opcua")
    text = profile.path.read_text().replace('node_id = "ns=2;s=Spindle.ActCurrent"', 'node_id = "ns=2;s=Spindle.Nope"')
    profile.path.write_text(text)
    from gateway.profile import load_profile

    with pytest.raises(DriverError) as err, make_driver(load_profile(profile.path), "cnc", clock):
        pass
    assert 'device "cnc" (OPC UA)' in str(err.value)
    assert f"channel spindle_i1: node ns=2;s=Spindle.Nope not found on {devices.cnc_opcua.endpoint}" in str(err.value)


def test_2_ms_is_refused_at_load_with_what_the_link_can_do(cnc, tmp_path):
    devices, _, _ = cnc
    with pytest.raises(ProfileError) as err:
        live_profile(devices, tmp_path, via="opcua", device_keys={"period_s": 0.002})
    (problem,) = err.value.problems
    assert "devices.cnc.period_s: a period of 2 ms is faster than the link can go: OPC UA (poll of 9 nodes)" in problem
    assert problem.endswith("so it sustains at most 100 Hz: set devices.cnc.period_s >= 0.01")


@pytest.mark.parametrize("mode", ["poll", "subscription"])
def test_windows_are_good_at_the_fastest_period_it_claims(cnc, tmp_path, mode):
    devices, source, clock = cnc
    profile = live_profile(devices, tmp_path, via="opcua", device_keys={"mode": mode, "period_s": 0.01})
    records = []
    with Acquisition(profile, clock=clock, sinks=[records.append]) as acq:
        deadline = time.monotonic() + 20.0
        while len(records) < 3 and time.monotonic() < deadline:
            time.sleep(0.05)
        (check,) = acq.link_checks
    assert check.budget.min_period_s <= 0.01  # measured at start: it holds 10 ms
    assert len(records) >= 3
    for r in records[1:]:  # the first window is joined part-way
        assert r.status == "good", r.notes
        assert r.coverage >= 0.9
        d = r.devices["cnc"]
        assert d.reads_ok >= 0.9 * d.ticks_expected
        assert any("the mean of squares of spindle_i1" in n and "aliases to a constant" in n for n in r.notes)
        # the window means follow the machine: the speed's mean lies between what it was in that window
        lo = min(source.values(r.start_s + k * 0.6)["spindle_speed"] for k in range(101))
        hi = max(source.values(r.start_s + k * 0.6)["spindle_speed"] for k in range(101))
        assert lo - 1.0 <= r.factors["spindle_speed"] <= hi + 1.0


def test_coarse_sampling_of_a_rectified_ripple_what_the_docstring_says():
    """Full-wave rectified 50 Hz (a 100 Hz ripple): independent phases give a relative standard error of
    0.71 / sqrt(N) on the mean of squares; sampling locked to the ripple (every 10 ms) aliases it to a constant."""
    rng = np.random.default_rng(7)
    amp = 20.0
    true_ms = amp**2 / 2
    for period_s, expected in ((0.002, 0.0041), (0.01, 0.0091), (0.1, 0.029)):
        n = round(60.0 / period_s)
        phases = rng.uniform(0.0, 2 * math.pi, size=(300, n))  # sampling not locked to the ripple
        estimates = (amp * np.abs(np.sin(phases))) ** 2
        rel = estimates.mean(axis=1) / true_ms - 1.0
        assert abs(rel.mean()) < 3 * expected / math.sqrt(300)  # unbiased
        assert rel.std() == pytest.approx(math.sqrt(0.5) / math.sqrt(n), rel=0.15)
        assert math.sqrt(0.5) / math.sqrt(n) == pytest.approx(expected, rel=0.03)
    t = np.arange(6000) * 0.01  # every 10 ms: the 100 Hz ripple is seen at one phase only
    worst = [((amp * np.abs(np.sin(2 * math.pi * 50 * t + phi))) ** 2).mean() / true_ms - 1.0
             for phi in np.linspace(0, math.pi / 2, 50)]
    assert min(worst) < -0.99
    assert max(worst) > 0.99


def test_a_dead_subscription_fails_the_read_instead_of_holding_stale_values(cnc, tmp_path):
    devices, _, clock = cnc
    profile = live_profile(devices, tmp_path, via="opcua", device_keys={"mode": "subscription", "timeout_s": 0.5})
    with make_driver(profile, "cnc", clock) as driver:
        time.sleep(0.1)
        assert driver.read().quality[0] == Quality.GOOD
        time.sleep(1.2)  # publish responses keep coming: longer than the 1 s limit, still alive
        assert driver.read().quality[0] == Quality.GOOD
        driver._subscription.last_publish_at -= 5.0  # as if the server went silent 5 s ago (a cut cable)
        with pytest.raises(DriverError, match=r"no publish response \(data or keep-alive\) from opc.tcp://127.0.0.1:"
                                               r"\d+/cnc/ for 5.\d s \(at most 1 s expected\): the subscription is dead"):
            driver.read()
