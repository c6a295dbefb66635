"""Real signals: CNC drive signals of a real mill (umich-cnc-mill-signals, 100 ms, read in place from
../shared/data) replayed through a simulated ADC board over Modbus TCP; the factors the gateway computes
live equal those computed offline from the file."""

from __future__ import annotations

import csv

import numpy as np
import pytest
from test_drivers_support import ReplaySource

from gateway.clock import ManualClock
from gateway.profile import load_profile
from gateway.record_store import RecordStore, export_recording
from gateway.recording import read_for_profile
from gateway.sampler import Acquisition
from simulators.devices import AdcBoardConfig, DeviceSetConfig, RegisterChannel, serve

COLUMNS = {  # channel -> column of the file (velocities in mm/s, currents in A, signed)
    "spindle_speed": "S1_ActualVelocity", "spindle_current": "S1_CurrentFeedback",
    "x_velocity": "X1_ActualVelocity", "x_current": "X1_CurrentFeedback",
    "y_velocity": "Y1_ActualVelocity", "y_current": "Y1_CurrentFeedback",
    "z_velocity": "Z1_ActualVelocity", "z_current": "Z1_CurrentFeedback",
}
FACTORS = {  # factor -> (channel, stat)
    "spindle_speed": ("spindle_speed", "mean"), "spindle_i_sq": ("spindle_current", "mean_square"),
    "x_feed": ("x_velocity", "mean_abs"), "x_i_sq": ("x_current", "mean_square"),
    "y_feed": ("y_velocity", "mean_abs"), "y_i_sq": ("y_current", "mean_square"),
    "z_feed": ("z_velocity", "mean_abs"), "z_i_sq": ("z_current", "mean_square"),
}
PERIOD = 0.1  # the file's own sample period
WINDOW = 10.0  # the runs last 1-4 minutes: 10 s windows give several per run


def replay_profile(tmp_path, host, port):
    lines = ['[machine]', 'name = "umich-mill"', '[sampling]', f"fast_period_s = {PERIOD}", f"window_s = {WINDOW}",
             '[recording]', f"period_s = {WINDOW}"]
    for name, (channel, stat) in FACTORS.items():
        lines += [f"[factors.{name}]", 'unit = "-"', f'channel = "{channel}"', f'stat = "{stat}"']
    lines += ["[devices.adc]", 'driver = "modbus_tcp"', f'host = "{host}"', f"port = {port}"]
    for i, channel in enumerate(COLUMNS):
        lines += [f"[channels.{channel}]", 'device = "adc"', f"address = {2 * i}", 'data_type = "float32"']
    path = tmp_path / "umich.toml"
    path.write_text("\n".join(lines) + "\n")
    return load_profile(path)


def offline_factors(path, n_windows):
    """The factors straight from the file: window k holds rows 100 k + 1 .. 100 k + 100 (the ticks at
    k * 10 s + 0.1 s .. (k + 1) * 10 s), values as the board's float32 registers carry them."""
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    data = {ch: np.array([float(r[col]) for r in rows], dtype=np.float32).astype(float) for ch, col in COLUMNS.items()}
    per = round(WINDOW / PERIOD)
    out = {name: [] for name in FACTORS}
    for k in range(n_windows):
        for name, (channel, stat) in FACTORS.items():
            x = data[channel][k * per + 1:(k + 1) * per + 1]
            out[name].append({"mean": x.mean(), "mean_square": (x * x).mean(), "mean_abs": np.abs(x).mean()}[stat])
    return {name: np.array(v) for name, v in out.items()}


@pytest.mark.parametrize("experiment", ["experiment_01.csv", "experiment_11.csv"])
def test_live_factors_of_a_real_recording_equal_the_offline_ones(shared_data, tmp_path, experiment):
    path = shared_data / "umich-cnc-mill-signals" / experiment
    source = ReplaySource(path, COLUMNS, period_s=PERIOD)
    n_windows = int(source.n * PERIOD // WINDOW) - 1  # whole windows whose rows all exist
    board = AdcBoardConfig(channels=tuple(RegisterChannel(channel=ch, address=2 * i, encoding="float32")
                                          for i, ch in enumerate(COLUMNS)))
    clock = ManualClock(0.0)
    with serve(source, clock, DeviceSetConfig(adc=board, adc_rtu=None, can=None, dcon=None, cnc=None)) as devices:
        profile = replay_profile(tmp_path, *devices.adc_tcp.address)
        store = RecordStore(tmp_path / "records.sqlite", profile=profile)
        acq = Acquisition(profile, clock=clock, sinks=[store])
        try:
            acq.run_stepped(n_windows * WINDOW)
        finally:
            acq.stop()
    out = export_recording(store, profile, tmp_path / "umich.csv")
    records = list(store.windows())
    store.close()
    assert [r.status for r in records] == ["good"] * n_windows
    assert all(r.samples_taken == r.samples_expected == 100 for r in records)
    live = read_for_profile(out, profile, require_displacement=False)
    offline = offline_factors(path, n_windows)
    for name in FACTORS:
        np.testing.assert_allclose(live.factors[name], offline[name], rtol=1e-12, atol=1e-12, err_msg=name)
    # real, signed, noisy currents: the mean of the square is not the square of the mean
    i_sq = live.factors["x_i_sq"]
    i_mean = np.array([r.channels["x_current"].mean for r in records])
    assert np.all(i_sq > 2 * i_mean**2)
