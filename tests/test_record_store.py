"""The durable record store: append-only SQLite, round trip, export to the recording format, `cncgw record`,
and kill -9 in the middle of a recording."""

from __future__ import annotations

import math
import os
import re
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from test_drivers_support import live_profile

from gateway.cli import main
from gateway.clock import ManualClock
from gateway.errors import RecordingError
from gateway.record_store import STORE_NAME, RecordStore, export_recording
from gateway.recording import read_for_profile
from gateway.sampler import Acquisition
from simulators.devices import DeviceSetConfig, serve
from simulators.machine import LiveMachine

MINUTE = 60.0


@pytest.fixture
def recorded(tmp_path):
    """Six 10 s windows of spindle-1000rpm sampled every 20 ms over Modbus TCP; the board is silent in the 4th."""
    clock = ManualClock(31 * MINUTE)
    machine = LiveMachine("spindle-1000rpm", clock=clock)
    config = DeviceSetConfig(adc_rtu=None, can=None, dcon=None, cnc=None)
    with serve(machine, clock, config) as devices:
        profile = live_profile(devices, tmp_path, sampling={"window_s": 10.0},
                               device_keys={"period_s": 0.02, "timeout_s": 0.05, "backoff_s": 0.5,
                                            "backoff_max_s": 0.5})
        profile.path.write_text(profile.path.read_text().replace("period_s = 60.0", "period_s = 10.0"))
        from gateway.profile import load_profile

        profile = load_profile(profile.path)
        store = RecordStore(tmp_path / STORE_NAME, profile=profile)
        records = []
        acq = Acquisition(profile, clock=clock, sinks=[store, records.append])
        try:
            acq.run_stepped(31 * MINUTE + 30.0)
            devices.adc_tcp.faults.drop_replies = True
            acq.run_stepped(31 * MINUTE + 40.0)
            devices.adc_tcp.faults.drop_replies = False
            acq.run_stepped(31 * MINUTE + 60.0)
        finally:
            acq.stop()
        yield profile, store, records
        store.close()


def test_the_store_gives_back_exactly_what_was_written(recorded):
    _profile, store, records = recorded
    assert [r.index for r in records] == list(range(186, 192))
    assert [r.status for r in records] == ["good", "good", "good", "insufficient", "good", "good"]
    back = list(store.windows())
    assert len(store) == 6
    for a, b in zip(records, back, strict=True):
        assert (a.index, a.start_s, a.end_s, a.status, a.notes) == (b.index, b.start_s, b.end_s, b.status, b.notes)
        for name in a.factors:
            assert a.factors[name] == b.factors[name] or (math.isnan(a.factors[name]) and math.isnan(b.factors[name]))
        assert a.devices == b.devices
        assert a.channels.keys() == b.channels.keys()
        assert a.channels["spindle_i1"] == b.channels["spindle_i1"]
    silent = back[3]
    assert silent.devices_in_error == ("adc",)
    assert silent.devices["adc"].timeouts >= 1
    assert silent.devices["adc"].errors[0].startswith('device "adc" (Modbus TCP): no valid answer to fc4 0..8')
    assert [r.index for r in store.windows(since=190)] == [190, 191]
    assert store.check() == "ok"


def test_records_are_append_only_and_a_store_belongs_to_one_machine(recorded, tmp_path):
    profile, store, records = recorded
    with pytest.raises(RecordingError) as err:
        store.append(records[2])
    assert str(err.value) == (f"{store.path}: window 188 is not after the last one stored (191); records are "
                              "append-only")
    assert len(store) == 6  # nothing recorded was touched
    other = profile.path.read_text().replace("window_s = 10.0", "window_s = 20.0")
    (tmp_path / "other.toml").write_text(other)
    from gateway.profile import load_profile

    with pytest.raises(RecordingError) as err:
        RecordStore(store.path, profile=load_profile(tmp_path / "other.toml"))
    assert str(err.value) == (f"{store.path}: this store holds window_s '10.0', the profile {tmp_path / 'other.toml'} "
                              "says '20.0': record into another directory")


def test_a_file_that_is_not_a_store_is_refused(tmp_path):
    bad = tmp_path / "records.sqlite"
    bad.write_text("time_s,x\n1,2\n")
    with pytest.raises(RecordingError, match=r"records.sqlite: not a readable record store: file is not a database"):
        RecordStore(bad)
    with pytest.raises(RecordingError, match=r"nothing.sqlite: no record store here"):
        RecordStore(tmp_path / "nothing.sqlite")


def test_export_is_a_recording_identify_and_estimate_read_with_insufficient_windows_as_gaps(recorded, tmp_path):
    profile, store, records = recorded
    out = export_recording(store, profile, tmp_path / "export.csv")
    rec = read_for_profile(out, profile, require_displacement=False)
    assert list(rec.time_s) == [r.end_s for r in records]
    assert rec.period_s == 10.0
    speed = rec.factors["spindle_speed"]
    assert np.isnan(speed[3])  # the silent window is a gap, not a value
    assert speed[[0, 1, 2, 4, 5]] == pytest.approx(1000.0, abs=0.5)
    assert rec.factors["spindle_i1_sq"][0] == records[0].factors["spindle_i1_sq"]
    assert list(rec.extras["q_good"]) == [1, 1, 1, 0, 1, 1]
    assert rec.extras["q_coverage"][3] < 0.9
    assert rec.extras["q_devices_in_error"][3] == 1
    assert rec.meta["insufficient_windows"] == "1 (factors left empty)"


def test_export_and_reading_back_in_chunks_give_the_same_file(recorded, tmp_path):
    # a store of months is read and written a chunk at a time: the chunk boundaries must not show
    profile, store, records = recorded
    whole = export_recording(store, profile, tmp_path / "whole.csv").read_text()
    for chunk in (1, 3, 4):  # 6 windows: one a chunk, two full chunks, a full and a partial one
        assert [r.index for r in store.windows(chunk=chunk)] == [r.index for r in records]
        assert [r.index for r in store.windows(since=189, chunk=chunk)] == [189, 190, 191]
        assert export_recording(store, profile, tmp_path / f"c{chunk}.csv", chunk=chunk).read_text() == whole
    assert sorted(p.name for p in tmp_path.glob("*.tmp")) == []


def test_cncgw_record_records_live_devices_for_n_minutes(tmp_path, capsys):
    from gateway.clock import ScaledClock

    clock = ScaledClock(60.0)
    machine = LiveMachine("spindle-1000rpm", clock=clock)
    config = DeviceSetConfig(adc_rtu=None, can=None, dcon=None, cnc=None)
    with serve(machine, clock, config) as devices:
        profile = live_profile(devices, tmp_path)
        code = main(["record", "--profile", str(profile.path), "--out", str(tmp_path / "rec"), "--speedup", "60",
                     "--minutes", "2"])
    out = capsys.readouterr().out
    assert code == 0
    lines = out.splitlines()
    assert lines[0] == f"recording sim-vmc from 1 device(s) into {tmp_path / 'rec' / STORE_NAME} at 60x; Ctrl-C stops"
    windows = [ln for ln in lines if ln.startswith("window ")]
    assert len(windows) == 3  # the window it started in, then two whole ones
    # good on a quiet PC; on a loaded one the 2 ms sampler may miss samples, and the line says how many
    assert re.match(r"window 2 \(t=180 s\) (good: coverage [\d.]+%|insufficient: coverage [\d.]+%, samples \d+/500)",
                    windows[-1]), windows[-1]
    assert lines[-1] == f"3 windows in {tmp_path / 'rec' / STORE_NAME}; exported to {tmp_path / 'rec' / 'sim-vmc.csv'}"
    rec = read_for_profile(tmp_path / "rec" / "sim-vmc.csv", profile, require_displacement=False)
    assert list(rec.time_s) == [60.0, 120.0, 180.0]
    assert main(["record", "--profile", str(profile.path), "--out", str(tmp_path / "rec"), "--export-only"]) == 0
    assert capsys.readouterr().out == f"exported 3 windows to {tmp_path / 'rec' / 'sim-vmc.csv'}\n"


def test_kill_9_while_recording_loses_at_most_the_window_in_progress(tmp_path):
    from gateway.clock import ScaledClock

    clock = ScaledClock(60.0)
    machine = LiveMachine("spindle-1000rpm", clock=clock)
    config = DeviceSetConfig(adc_rtu=None, can=None, dcon=None, cnc=None)
    out = tmp_path / "rec"
    with serve(machine, clock, config) as devices:
        profile = live_profile(devices, tmp_path)
        cmd = [sys.executable, "-m", "gateway.cli", "record", "--profile", str(profile.path), "--out", str(out),
               "--speedup", "60"]
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        printed = []
        try:
            deadline = time.monotonic() + 30.0
            while len(printed) < 3 and time.monotonic() < deadline:
                line = proc.stdout.readline()
                if line.startswith("window "):
                    printed.append(line)
            time.sleep(0.5)  # into the next window
            proc.send_signal(signal.SIGKILL)
            proc.wait(timeout=10)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
            proc.stdout.close()
            proc.stderr.close()
        assert proc.returncode == -signal.SIGKILL
        assert len(printed) == 3
        with RecordStore(out / STORE_NAME) as store:
            assert store.check() == "ok"
            kept = [r.index for r in store.windows()]
        # every window reported as written is there (it is printed only after its commit); the one in
        # progress at the kill is the only one that can be missing
        assert kept[:3] == [0, 1, 2]
        assert kept == list(range(len(kept)))
        assert len(kept) <= 4
        # recording again continues the store after the last window it holds
        code = subprocess.run([*cmd, "--minutes", "1", "--quiet"], capture_output=True, text=True, timeout=60)
        assert code.returncode == 0, code.stderr
    with RecordStore(out / STORE_NAME) as store:
        after = [r.index for r in store.windows()]
    assert after[: len(kept)] == kept
    assert after[len(kept)] == kept[-1] + 1
    assert os.path.exists(out / "sim-vmc.csv")
