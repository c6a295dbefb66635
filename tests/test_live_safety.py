"""A corrupted or absurd model never moves the CNC: plausibility bounds, and the models ``cncgw run`` refuses.

Live runs against the simulated machine over real sockets (the :class:`Rig` of ``test_live``), on a
ManualClock. The corrupted models are built in memory, so what is tested is the live path whatever a
loader would make of such a file.
"""

from __future__ import annotations

import dataclasses
import itertools

import pytest
from test_live import MAX_STEP_UM, Rig, audited

from gateway.cli import main
from gateway.live.estimator import Estimator
from gateway.live.plausibility import ABS_FACTOR, ABS_MARGIN_UM, Plausibility
from gateway.live.settings import Compensation, default_axes
from gateway.model import FirstOrder, save_model
from gateway.model.envelope import Envelope
from gateway.records import STORE_NAME, RecordStore


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
            assert gw.estimator.history.filled_total >= missing  # the windows not stored, filled by the gap policy
            live_estimate = dict(gw.estimator.last.estimate_um)
            with RecordStore(data / STORE_NAME) as store:  # a restart sees the same history: the same estimate
                again = Estimator(gw.model, window_s=gw.profile.sampling.window_s, live=gw.profile.live)
                again.rebuild(store.windows())
        assert dict(again.last.estimate_um) == pytest.approx(live_estimate, abs=1e-9)
        writes, events = audited(data)
        assert [k for _, k, n, _ in events if n == "store"] == ["alarm"] * missing + ["clear"]  # each window
        for a, b in itertools.pairwise(writes):
            assert max(abs(b.applied_um[x] - a.applied_um[x]) for x in "xyz") <= MAX_STEP_UM + 1e-9
    finally:
        rig.close()
