"""A corrupted or absurd model never moves the CNC: plausibility bounds, and the models ``cncgw run`` refuses.

Live runs against the simulated machine over real sockets (the :class:`Rig` of ``test_live``), on a
ManualClock. The corrupted models are built in memory, so what is tested is the live path whatever a
loader would make of such a file.
"""

from __future__ import annotations

import dataclasses
import itertools
import subprocess
import sys
import threading

import pytest
from test_live import MAX_STEP_UM, Rig, audited

from gateway.cli import main
from gateway.live.plausibility import ABS_FACTOR, ABS_MARGIN_UM, Plausibility
from gateway.live.tracking import DisplacementTracker
from gateway.model import FirstOrder, save_model
from gateway.model.envelope import Envelope
from gateway.profile import load_profile
from gateway.profile.live import Compensation, default_axes
from gateway.record_store import STORE_NAME, RecordStore


def gain_1e300(model):
    path = model.path("z", "spindle_speed")
    return model.with_paths([dataclasses.replace(path, terms=(FirstOrder(gain=1e300, tau_s=600.0),))])


def reference_1e12(model):
    return dataclasses.replace(model, reference={**model.reference, "spindle_speed": 1e12})


@pytest.mark.parametrize("corrupt", [gain_1e300, reference_1e12])
def test_an_absurd_model_holds_the_offsets_with_an_alarm_and_writes_nothing(tmp_path, corrupt):
    rig = Rig(tmp_path, name=corrupt.__name__)
    try:
        data = tmp_path / "data"
        with rig.gateway(data) as gw:
            gw.run_stepped(75 * 60)  # heating since 60 min: the offsets are compensating
            before = len(audited(data)[0])
        held = rig.devices.cnc.update().applied_um
        assert held["z"] > 3.0
        rig.model = corrupt(rig.model)  # the file replaced by a corrupted one, then a restart
        rig.clock.advance(2.0)
        with rig.gateway(data) as gw:
            gw.run_stepped(95 * 60)
            alarms = {a.name: a.message for a in gw.alarms.active()}
            commanded = dict(gw.writer.commanded_um)
        writes, events = audited(data)
        assert "implausible" in alarms
        assert "z estimate" in alarms["implausible"]
        assert "envelope" in alarms["implausible"]
        assert "clamped" not in alarms
        assert len(writes) == before  # not one write beyond the good run's
        assert rig.devices.cnc.update().applied_um == pytest.approx(held)  # held, to the count
        assert commanded == pytest.approx(held)
        assert rig.devices.cnc.update().trips == 0  # held means the heartbeat went on
        assert ("alarm", "implausible") in [(k, n) for _, k, n, _ in events]
        for a, b in itertools.pairwise(writes):
            assert max(abs(b.applied_um[x] - a.applied_um[x]) for x in "xyz") <= MAX_STEP_UM + 1e-9
    finally:
        rig.close()


def test_a_model_beyond_its_envelope_is_held_from_the_start_in_a_dry_run_too(tmp_path):
    rig = Rig(tmp_path, enabled=False)
    try:
        rig.model = reference_1e12(rig.model)
        with rig.gateway(tmp_path / "data") as gw:
            gw.run_stepped(10 * 60)
            assert "implausible" in gw.alarms
            assert gw.writer.writes == 0  # not even a dry-run value
            assert gw.writer.commanded_um == {"x": 0.0, "y": 0.0, "z": 0.0}
    finally:
        rig.close()


def run_cli(rig, tmp_path, model, capsys):
    path = save_model(model, tmp_path / "other.model.toml")
    data = tmp_path / "never"
    code = main(["run", "--profile", str(rig.profile.path), "--model", str(path), "--data", str(data),
                 "--minutes", "1"])
    err = capsys.readouterr().err
    assert not data.exists()  # refused before the data directory is touched
    return code, err


def test_run_refuses_a_model_of_another_machine_or_lacking_a_compensated_axis(tmp_path, capsys):
    rig = Rig(tmp_path)
    try:
        code, err = run_cli(rig, tmp_path, dataclasses.replace(rig.model, machine="vmc-7"), capsys)
        assert code == 5
        assert 'the model names machine "vmc-7", but this profile is machine "sim-vmc"' in err
        env = rig.model.envelope
        xy = dataclasses.replace(rig.model, axes=("x", "y"), paths={k: v for k, v in rig.model.paths.items()
                                                                     if k[0] != "z"},
                                 envelope=Envelope(window_s=env.window_s, axes={a: env.axes[a] for a in "xy"}))
        code, err = run_cli(rig, tmp_path, xy, capsys)
        assert code == 5
        assert "the model does not estimate axis z, which the profile compensates" in err
        code, err = run_cli(rig, tmp_path, dataclasses.replace(rig.model, envelope=None), capsys)
        assert code == 5
        assert "the model has no [envelope]" in err
        assert "compensation.enabled = true refuses it" in err
    finally:
        rig.close()


def test_bounds_come_from_the_envelope_a_profile_tightens_them_and_without_one_from_limit_um(tmp_path):
    rig = Rig(tmp_path)
    rig.close()
    model = rig.model
    env = model.envelope.axes["z"]
    axes = tuple(dataclasses.replace(a, plausible_um=10.0) if a.axis == "x" else
                 dataclasses.replace(a, plausible_um=1e6) for a in default_axes(model.axes))
    check = Plausibility.for_model(model, Compensation(axes=axes, limit_um=80.0), window_s=60.0)
    assert check.bounds["z"].abs_um == pytest.approx(ABS_FACTOR * env.max_abs_um + ABS_MARGIN_UM)  # never widened
    assert check.bounds["x"].abs_um == 10.0
    assert "tightened by the profile's plausible_um" in check.bounds["x"].origin
    derived = Plausibility.for_model(dataclasses.replace(model, envelope=None), Compensation(
        axes=default_axes(model.axes), limit_um=80.0), window_s=60.0)
    assert derived.bounds["z"].abs_um == 80.0
    assert derived.bounds["z"].change_um == 8.0


def test_a_window_the_store_cannot_commit_is_not_acted_on_and_the_offsets_hold(tmp_path):
    """Store-first by construction: SQLite's own "database or disk is full" (the file capped at its size)."""
    rig = Rig(tmp_path, name="full")
    try:
        data = tmp_path / "data"
        with rig.gateway(data) as gw:
            gw.run_stepped(70 * 60)  # heating since 60 min: every window moves the offsets
            held = rig.devices.cnc.update().applied_um
            writes, stored, live = gw.writer.writes, len(gw.store), gw.windows_live
            with gw.store._lock:  # the disk is full from here on
                pages = gw.store._db.execute("PRAGMA page_count").fetchone()[0]
                gw.store._db.execute(f"PRAGMA max_page_count = {pages}")
            gw.run_stepped(76 * 60)
            assert "store" in gw.alarms
            message = next(a.message for a in gw.alarms.active() if a.name == "store")
            assert "records.sqlite: window" in message
            assert "database or disk is full" in message
            assert gw.store_failures >= 5
            assert gw.windows_live == live  # the estimator never saw an uncommitted window
            assert gw.writer.writes == writes  # nor did the writer
            assert rig.devices.cnc.update().applied_um == pytest.approx(held)
            assert rig.devices.cnc.update().trips == 0  # held, the heartbeat went on
            with gw.store._lock:
                gw.store._db.execute("PRAGMA max_page_count = 1073741823")  # space again
            gw.run_stepped(85 * 60)
            assert "store" not in gw.alarms
            assert gw.writer.writes > writes  # compensating again
            missing = gw.store_failures
            assert len(gw.store) == stored + gw.windows_live - live
            assert gw.tracker.history.filled_total >= missing  # the windows not stored, filled by the gap policy
            live_estimate = dict(gw.tracker.last.estimate_um)
            with RecordStore(data / STORE_NAME) as store:  # a restart sees the same history: the same estimate
                again = DisplacementTracker(gw.model, window_s=gw.profile.sampling.window_s, live=gw.profile.live)
                again.rebuild(store.windows())
        assert dict(again.last.estimate_um) == pytest.approx(live_estimate, abs=1e-9)
        writes, events = audited(data)
        assert [k for _, k, n, _ in events if n == "store"] == ["alarm"] * missing + ["clear"]  # each window
        for a, b in itertools.pairwise(writes):
            assert max(abs(b.applied_um[x] - a.applied_um[x]) for x in "xyz") <= MAX_STEP_UM + 1e-9
    finally:
        rig.close()


def test_windows_older_than_keep_days_are_pruned_and_files_are_private(tmp_path):
    rig = Rig(tmp_path, name="keep", live="history_max_h = 1.0")
    try:
        rig.profile.path.write_text(rig.profile.path.read_text() + "\n[records]\nkeep_days = 0.05\n")  # 72 windows
        rig.profile = load_profile(rig.profile.path)
        data = tmp_path / "data"
        data.mkdir(mode=0o755)
        with rig.gateway(data) as gw:
            gw.run_stepped(150 * 60)
            first, last = gw.store.first_index(), gw.store.last_index
            assert last == 149
            assert first == last + 1 - 72  # 0.05 days of one-minute windows kept, the rest deleted
            assert len(gw.store) == 72
            assert gw.pruned_windows > 70
            modes = {p.name: p.stat().st_mode & 0o777 for p in data.iterdir()}
        assert data.stat().st_mode & 0o777 == 0o700  # narrowed from 0755
        assert modes["records.sqlite"] == modes["audit.sqlite"] == 0o600
        assert modes["records.sqlite-wal"] == modes["audit.sqlite-wal"] == 0o600
        _, events = audited(data)
        assert any(k == "prune" and "older than 0.05 days deleted" in m for _, k, _, m in events)
        rig.clock.advance(2.0)
        with rig.gateway(data) as gw:  # a restart replays what was kept: 1 h of history
            assert gw.tracker.rebuilt_windows == 60
            gw.run_stepped(155 * 60)
            assert "inputs" not in gw.alarms
    finally:
        rig.close()


def test_keep_days_shorter_than_the_history_a_restart_needs_is_refused(tmp_path, capsys):
    rig = Rig(tmp_path, name="short")
    try:
        rig.profile.path.write_text(rig.profile.path.read_text() + "\n[records]\nkeep_days = 2\n")
        code = main(["run", "--profile", str(rig.profile.path), "--data", str(tmp_path / "never")])
        err = capsys.readouterr().err
        assert code == 3
        assert "records.keep_days = 2 keeps less than the" in err
        assert "days of history the estimator replays on start" in err
        assert not (tmp_path / "never").exists()
    finally:
        rig.close()


def test_pruning_in_batches_lets_windows_be_appended_meanwhile(tmp_path):
    rig = Rig(tmp_path, name="batch")
    rig.close()
    with RecordStore(tmp_path / "s.sqlite", profile=rig.profile) as store:
        bodies = []
        for k in range(3000):  # one transaction: the test needs many rows, not a durable each
            bodies.append((k, 60.0 * k, 60.0 * (k + 1), "good", 1.0, 1, 1, 0, 0.0, "", 0.0, "{\"factors\":{},"
                           "\"channels\":{},\"devices\":{},\"displacement\":{},\"burst_revolutions\":{},\"notes\":[]}"))
        with store._lock:
            store._db.execute("BEGIN")
            store._db.executemany("INSERT INTO windows VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)", bodies)
            store._db.execute("COMMIT")
            store.last_index = 2999
        template = store.first()
        appended = []

        def append_more():
            for k in range(3000, 3040):
                store.append(dataclasses.replace(template, index=k, start_s=60.0 * k, end_s=60.0 * (k + 1)))
                appended.append(k)

        t = threading.Thread(target=append_more)
        t.start()
        deleted = store.prune(before=2900, batch=100)
        t.join()
        assert deleted == 2900
        assert appended == list(range(3000, 3040))
        assert store.first_index() == 2900
        assert len(store) == 140
        assert [r.index for r in store.windows()][:3] == [2900, 2901, 2902]


def test_a_restart_beats_before_it_replays_the_history_and_run_imports_no_identification(tmp_path):
    rig = Rig(tmp_path, name="order")
    try:
        data = tmp_path / "data"
        with rig.gateway(data) as gw:
            gw.run_stepped(10 * 60)
        rig.clock.advance(2.0)
        with rig.gateway(data) as gw:
            assert gw.tracker.rebuilt_windows >= 9
        _, events = audited(data)
        second = [(k, n) for _, k, n, _ in events][[k for _, k, _, _ in events].index("stop") + 1:]
        assert second.index(("sync", "cnc")) < second.index(("rebuild", "estimator"))  # the CNC hears it first
    finally:
        rig.close()
    # `cncgw run` builds its own parser only: identification's scipy is not imported before the first beat
    code = ("import sys; from gateway.cli import build_parser; build_parser('run'); "
            "import gateway.commands.run, gateway.live.runtime, gateway.live.compensation; "
            "print(sorted(m for m in ('scipy', 'gateway.identify', 'asyncua') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
