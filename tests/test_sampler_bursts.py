"""Displacement bursts for identification runs: read at the end of each window and averaged over a whole
number of spindle revolutions, which cancels runout (the paper's method); recorded and exported with the
factors."""

from __future__ import annotations

import math
import random

import pytest
from test_drivers_support import RunoutSource, live_profile

from gateway.clock import ManualClock
from gateway.record_store import RecordStore, export_recording
from gateway.recording import read_for_profile
from gateway.sampler import Acquisition
from gateway.windows import revolution_average
from simulators.devices import DeviceSetConfig, serve
from simulators.devices.analog import DEFAULT_ADC_CONFIG
from simulators.devices.profile_out import adc_with_displacement
from simulators.machine import LiveMachine

START = 31 * 60.0  # spindle-1000rpm: one minute into the 1000 rpm run


def test_bursts_average_whole_revolutions_and_cancel_runout(tmp_path):
    clock = ManualClock(START)
    machine = LiveMachine("spindle-1000rpm", clock=clock)
    source = RunoutSource(machine, amplitude_um=20.0)  # exaggerated: 20 um once per revolution
    config = DeviceSetConfig(adc=adc_with_displacement(DEFAULT_ADC_CONFIG), adc_rtu=None, can=None, dcon=None,
                             cnc=None)
    with serve(source, clock, config) as devices:
        profile = live_profile(devices, tmp_path, displacement=True, sampling={"window_s": 5.0, "burst_s": 2.9})
        profile.path.write_text(profile.path.read_text().replace("period_s = 60.0", "period_s = 5.0"))
        from gateway.profile import load_profile

        profile = load_profile(profile.path)
        store = RecordStore(tmp_path / "records.sqlite", profile=profile)
        records = []
        acq = Acquisition(profile, clock=clock, sinks=[store, records.append])
        try:
            acq.run_stepped(START + 10.0)
        finally:
            acq.stop()
    assert [r.index for r in records] == [372, 373]
    for r in records:
        # 1000 rpm: a revolution is 60 ms; 2.9 s of burst hold 48 whole ones (2.88 s, 1440 samples)
        assert dict(r.burst_revolutions) == {"x": 48.0, "y": 48.0, "z": 48.0}
        ticks = [round(r.end_s - k * 0.002, 9) for k in range(1440)]
        plain_errors = []
        for axis in "xyz":
            truth = sum(machine.values(t)[f"{axis}_um"] for t in ticks) / len(ticks)  # without runout
            plain = [source.values(round(r.end_s - k * 0.002, 9))[f"{axis}_um"] for k in range(1450)]
            plain_errors.append(abs(sum(plain) / len(plain) - truth))
            # a read missed under load (the driver's timeout is wall time) moves it by ~3e-4 um at most
            assert r.displacement[axis] == pytest.approx(truth, abs=1e-3), axis
        # the plain mean of the 2.9 s keeps a part of the runout (how much depends on its phase)
        assert max(plain_errors) > 0.02
    out = export_recording(store, profile, tmp_path / "burst.csv")
    store.close()
    rec = read_for_profile(out, profile)  # displacement columns are required by identify
    assert list(rec.displacement["z"]) == [r.displacement["z"] for r in records]


def test_revolution_average_without_speed_or_at_rest_is_the_plain_mean():
    samples = [(k * 0.01, float(k)) for k in range(1, 11)]
    assert revolution_average(samples, None) == (5.5, 0.0)
    assert revolution_average(samples, 0.0) == (5.5, 0.0)
    assert revolution_average(samples, 100.0) == (5.5, 0.0)  # 0.1 s at 100 rpm: less than one revolution
    # 0.1 s at 1500 rpm (40 ms a revolution): two whole revolutions, the last 8 samples
    assert revolution_average(samples, 1500.0) == (pytest.approx(6.5), 2.0)
    assert math.isnan(revolution_average([], 1000.0)[0])


def test_revolution_average_cancels_runout_over_missed_and_late_reads():
    """A loaded PC skips ticks and reads late (here 0.1 ms rms, 5 % of a tick): the burst is averaged over
    time, so it still spans whole revolutions (counting samples left a part of a revolution in for every
    missed read: up to 0.22 um of this 20 um runout with 5 % missed, worst of 200 bursts)."""
    rng = random.Random(7)

    def burst(missed: float, jitter_s: float) -> list[tuple[float, float]]:
        phase = rng.uniform(0.0, 2 * math.pi)
        out = []
        for k in range(1450):  # 2.9 s at 2 ms, 1000 rpm: a revolution every 60 ms, runout of 20 um
            t = 100.0 + k * 0.002 + rng.gauss(0.0, jitter_s)
            if k == 1449 or rng.random() >= missed:
                out.append((t, 3.0 + 20.0 * math.sin(2 * math.pi * t / 0.06 + phase)))
        return out

    for missed, jitter_s, tolerance in ((0.0, 0.0, 1e-9), (0.0, 1e-4, 1e-3), (0.01, 1e-4, 6e-3),
                                        (0.05, 1e-4, 0.02)):
        for _ in range(30):
            samples = burst(missed, jitter_s)
            mean, revolutions = revolution_average(samples, 1000.0)
            assert revolutions == 48.0
            assert mean == pytest.approx(3.0, abs=tolerance), (missed, jitter_s)
    one_gap = burst(0.0, 0.0)
    del one_gap[700]
    assert revolution_average(one_gap, 1000.0)[0] == pytest.approx(3.0, abs=1e-3)
