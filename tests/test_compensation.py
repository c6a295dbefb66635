"""The compensation writer against the simulated CNC over Modbus TCP: what it writes, what it refuses, faults.

Time is a ManualClock: the writer is serviced by hand (no thread) and the CNC's watchdog runs in the same
clock, so every expectation is exact and no test waits for wall time.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import time
from types import MappingProxyType

import pytest
from test_sim_devices_support import WaveSource

from gateway.clock import ManualClock
from gateway.live.audit import AuditLog
from gateway.live.compensation import CompensationWriter
from gateway.live.plausibility import AxisBound, Plausibility
from gateway.live.tracking import EstimateUpdate
from gateway.profile.live import Compensation, default_axes
from simulators.devices import CompensationConfig, DeviceSet, DeviceSetConfig

ONLY_CNC = {"adc_tcp_port": None, "adc_rtu": None, "can": None, "dcon": None}
AXES = ("x", "y", "z")


@pytest.fixture
def clock():
    return ManualClock(1000.0)


@pytest.fixture
def source():
    return WaveSource()


def start_cnc(source, clock, **cnc):
    cfg = {"drop_ramp_s": 10.0, "heartbeat_timeout_s": 5.0, "limit_um": 500.0, **cnc}
    return DeviceSet(source=source, clock=clock, config=DeviceSetConfig(**ONLY_CNC, cnc=CompensationConfig(**cfg))).start()


@pytest.fixture
def cnc(source, clock):
    devices = start_cnc(source, clock)
    yield devices.cnc
    devices.stop()


def settings(cnc, **kw) -> Compensation:
    base = {"enabled": True, "host": "127.0.0.1", "port": cnc.address[1], "axes": default_axes(AXES),
            "max_step_um": 2.0, "deadband_um": 0.1, "limit_um": 100.0, "aim": "estimate", "reconnect_s": 0.01,
            # the CNC's answer can take more than 0.3 s of wall time on a loaded PC (a full suite beside two
            # benches: an implausible-estimate test failed so); tests of late answers set their own
            "timeout_s": 1.0}
    return Compensation(**{**base, **kw})


def update(i, *, usable=True, reason="", **est):
    e = MappingProxyType({a: float(est.get(a, 0.0)) for a in AXES})
    return EstimateUpdate(index=i, end_s=(i + 1) * 60.0, estimate_um=e, next_um=e, factors=MappingProxyType({}),
                          usable=usable, reason=reason)


@pytest.fixture
def audit():
    log = AuditLog(None)
    yield log
    log.close()


def make_writer(s, clock, audit=None, **kw):
    return CompensationWriter(s, clock=clock, window_s=60.0, stale_after_s=150.0, audit=audit, **kw)


def feed(writer, clock, *updates, dt=60.0):
    """One update a window; the writer beats every second in between, as its thread would."""
    for u in updates:
        writer.submit(u)
        writer.service()
        for _ in range(int(dt)):
            clock.advance(1.0)
            writer.service()


def test_writes_sign_times_estimate_reads_back_and_the_machine_gets_it(cnc, source, clock, audit):
    w = make_writer(settings(cnc), clock, audit)
    try:
        feed(w, clock, update(0, x=-0.5, y=0.3, z=-1.26))
        assert w.synced
        assert w.commanded_um == pytest.approx({"x": 0.5, "y": -0.3, "z": 1.3})  # sign -1, 0.1 um counts
        status = cnc.update()
        assert status.enabled
        assert not status.tripped
        assert status.heartbeat_ok
        assert status.applied_um == pytest.approx({"x": 0.5, "y": -0.3, "z": 1.3})
        assert source.last_compensation() == pytest.approx({"x": 0.5, "y": -0.3, "z": 1.3})
        (entry,) = list(audit.writes())
        assert entry.mode == "write"
        assert entry.verified
        assert entry.window == 0
        assert dict(entry.commanded_um) == pytest.approx(dict(entry.applied_um))
        assert dict(entry.estimate_um) == {"x": -0.5, "y": 0.3, "z": -1.26}
        assert w.beats >= 59  # one a second of clock time
    finally:
        w.stop()


def test_step_limit_clamp_and_deadband_never_a_jump(cnc, clock, audit):
    w = make_writer(settings(cnc, max_step_um=2.0, limit_um=5.0, deadband_um=0.3), clock, audit)
    try:
        feed(w, clock, *(update(i, z=-100.0) for i in range(4)))
        zs = [e.commanded_um["z"] for e in audit.writes()]
        assert zs == pytest.approx([2.0, 4.0, 5.0])  # 2 um a window, then the 5 um limit: no more writes
        assert "clamped" in w.alarms
        assert cnc.update().applied_um["z"] == pytest.approx(5.0)
        feed(w, clock, update(4, z=-4.8))  # 0.2 um away: inside the deadband, nothing written
        assert len(list(audit.writes())) == 3
        assert "clamped" not in w.alarms
        feed(w, clock, update(5, z=-4.6))
        assert [e.commanded_um["z"] for e in audit.writes()][-1] == pytest.approx(4.6)
    finally:
        w.stop()


def test_bad_or_nan_inputs_hold_the_last_value_with_an_alarm_then_resume_without_a_jump(cnc, clock, audit):
    w = make_writer(settings(cnc, max_step_um=1.0), clock, audit)
    try:
        feed(w, clock, update(0, z=-0.8))
        assert cnc.update().applied_um["z"] == pytest.approx(0.8)
        feed(w, clock, update(1, usable=False, reason="window 1 insufficient; devices in error: adc", z=-7.0))
        assert [a.message for a in w.alarms.active()] == ["holding the offsets: window 1 insufficient; devices in "
                                                          "error: adc"]
        feed(w, clock, update(2, z=math.nan), update(3, x=math.inf))  # good inputs, a model gone wrong
        assert "inputs" not in w.alarms
        assert [a.message for a in w.alarms.active()] == ["holding the offsets: window 3: estimate not finite: "
                                                          "x +inf um, y +0.00 um, z +0.00 um"]
        assert len(list(audit.writes())) == 1  # nothing written while inputs or estimates were bad
        assert cnc.update().applied_um["z"] == pytest.approx(0.8)  # held
        feed(w, clock, update(4, z=-7.0))
        assert w.alarms.active() == []
        assert cnc.update().applied_um["z"] == pytest.approx(1.8)  # one step from the held value
        events = [(k, n) for _, k, n, _ in audit.events() if n in ("inputs", "implausible")]
        assert events == [("alarm", "inputs"), ("clear", "inputs"), ("alarm", "implausible"),
                          ("alarm", "implausible"), ("clear", "implausible")]  # each new reason audited
    finally:
        w.stop()


def test_an_implausible_estimate_holds_the_offsets_and_is_never_clamped_and_written(cnc, clock, audit):
    bounds = {a: AxisBound(axis=a, abs_um=30.0, change_um=4.0, origin="test bounds") for a in AXES}
    w = make_writer(settings(cnc, max_step_um=1.0, limit_um=100.0), clock, audit,
                    plausibility=Plausibility(bounds, source="test"))
    try:
        feed(w, clock, *(update(i, z=-0.8 * (i + 1)) for i in range(3)))  # -0.8, -1.6, -2.4 um
        assert cnc.update().applied_um["z"] == pytest.approx(2.4)
        writes = len(list(audit.writes()))
        feed(w, clock, update(3, z=-1e6))  # finite, absurd: once this was clamped to 100 um and walked there
        assert [a.name for a in w.alarms.active()] == ["implausible"]
        assert "z estimate -1e+06 um is beyond +-30 um (test bounds)" in w.alarms.active()[0].message
        feed(w, clock, update(4, z=-12.0))  # within +-30 um, but 9.6 um from the last plausible in 2 windows
        assert "moved -9.6 um in 2 window(s) from -2.4 um at window 2" in w.alarms.active()[0].message
        assert len(list(audit.writes())) == writes  # held: nothing written
        assert cnc.update().applied_um["z"] == pytest.approx(2.4)
        feed(w, clock, update(5, z=-5.0))  # 2.6 um in 3 windows: plausible again, one step on
        assert w.alarms.active() == []
        assert cnc.update().applied_um["z"] == pytest.approx(3.4)
        names = [n for _, k, n, _ in audit.events() if k == "alarm"]
        assert "clamped" not in names
        assert names.count("implausible") == 2
    finally:
        w.stop()


def test_stale_inputs_ramp_to_zero_when_configured(cnc, clock, audit):
    w = make_writer(settings(cnc, max_step_um=1.0, on_fault="ramp_to_zero", fault_hold_s=120.0), clock, audit)
    try:
        w.expect_inputs()
        feed(w, clock, *(update(i, z=-3.0) for i in range(3)))
        assert cnc.update().applied_um["z"] == pytest.approx(3.0)
        for _ in range(600):  # ten minutes without an estimate
            clock.advance(1.0)
            w.service()
        assert "inputs" in w.alarms
        assert "ramp" in w.alarms
        zs = [e.commanded_um["z"] for e in audit.writes()]
        assert zs == pytest.approx([1.0, 2.0, 3.0, 2.0, 1.0, 0.0])  # held 150 + 120 s, then 1 um a window
        assert all(abs(b - a) <= 1.0 + 1e-9 for a, b in itertools.pairwise(zs))
        assert cnc.update().applied_um["z"] == 0.0
        assert cnc.update().enabled  # the heartbeat went on all along: the CNC never tripped
    finally:
        w.stop()


def test_cnc_unreachable_raises_an_alarm_writes_nothing_and_resynchronises(cnc, clock, audit):
    w = make_writer(settings(cnc), clock, audit)
    try:
        feed(w, clock, update(0, z=-1.0))
        cnc.faults.drop_replies = True  # the CNC stops answering: requests time out
        feed(w, clock, update(1, z=-2.0), dt=3.0)
        assert "cnc" in w.alarms
        assert not w.synced
        assert [e.mode for e in audit.writes()] == ["write", "unknown"]  # sent, never answered
        cnc.faults.drop_replies = False
        for _ in range(200):  # reconnect attempts are spaced by reconnect_s of wall time
            if w.synced:
                break
            time.sleep(0.01)
            w.service()
        assert w.synced
        assert "cnc" not in w.alarms
        feed(w, clock, update(2, z=-3.0), dt=1.0)
        feed(w, clock, update(3, z=-3.0))
        rows = [(e.mode, e.commanded_um["z"], e.applied_um["z"], e.verified) for e in audit.writes()]
        assert math.isnan(rows[1][2])  # unknown: nothing known applied
        # the read at re-synchronisation resolves it (the silent CNC never applied it); then, from what the CNC
        # applied (1.0), one step of 2 um
        assert [r for i, r in enumerate(rows) if i != 1] == [("write", 1.0, 1.0, True), ("resolved", 2.0, 1.0, False),
                                                             ("write", 3.0, 3.0, True)]
        kinds = [k for _, k, n, _ in audit.events() if n == "cnc"]
        assert kinds[0] == "sync"
        assert "alarm" in kinds
        assert kinds[-2:] == ["clear", "sync"]
    finally:
        w.stop()


def test_a_write_answered_too_late_is_audited_unknown_then_resolved_and_the_audit_follows_the_cnc(
        cnc, source, clock, audit):
    w = make_writer(settings(cnc, max_step_um=1.0, timeout_s=0.3), clock, audit)
    try:
        feed(w, clock, update(0, z=-1.0))
        cnc.faults.reply_delay_s = 0.8  # the CNC answers after the gateway gave up, and applies the write anyway
        w.submit(update(1, z=-2.0))
        w.service()
        assert [e.mode for e in audit.writes()] == ["write", "unknown"]
        assert "cnc" in w.alarms
        for _ in range(300):  # the late request lands in the CNC
            if cnc.update().applied_um["z"] == pytest.approx(2.0):
                break
            time.sleep(0.01)
        assert cnc.update().applied_um["z"] == pytest.approx(2.0)  # "failed", yet applied: the audit gap of old
        cnc.faults.reply_delay_s = 0.0
        for _ in range(200):
            if w.synced:
                break
            time.sleep(0.01)
            w.service()
        assert w.synced
        feed(w, clock, update(2, z=-3.0), update(3, z=-3.0))
        rows = list(audit.writes())
        assert [e.mode for e in rows] == ["write", "unknown", "resolved", "write"]
        resolved = rows[2]
        assert resolved.verified  # read back: applied as written
        assert resolved.applied_um["z"] == pytest.approx(2.0)
        assert resolved.window == 1
        assert "whose outcome was unknown: applied as written" in resolved.note
        # the audited history of applied offsets is the CNC's, value for value, and never a jump
        audited = [e.applied_um["z"] for e in rows if math.isfinite(e.applied_um["z"])]
        audited = [z for i, z in enumerate(audited) if i == 0 or z != audited[i - 1]]
        cnc_history = [c["z"] for c in source.compensation]
        assert cnc_history[0] == 0.0  # before the first write: what the writer took over (a "sync" event)
        assert audited == pytest.approx(cnc_history[1:])
        assert audited == pytest.approx([1.0, 2.0, 3.0])
        assert all(abs(b - a) <= 1.0 + 1e-9 for a, b in itertools.pairwise(audited))
    finally:
        w.stop()


def test_a_write_the_cnc_refuses_is_not_assumed_applied(source, clock, audit):
    devices = start_cnc(source, clock, limit_um=2.0)  # the CNC's own limit is tighter than the gateway's
    w = make_writer(settings(devices.cnc, max_step_um=5.0), clock, audit)
    try:
        feed(w, clock, update(0, z=-1.5))
        feed(w, clock, update(1, z=-4.0))  # 4 um: the CNC answers exception 3 and applies nothing
        assert "cnc" in w.alarms
        assert "refused with exception 3 (illegal data value)" in next(a.message for a in w.alarms.active())
        assert w.commanded_um["z"] == pytest.approx(1.5)  # read back from the CNC, not assumed
        assert devices.cnc.update().applied_um["z"] == pytest.approx(1.5)
        assert [(e.mode, e.commanded_um["z"], e.applied_um["z"]) for e in audit.writes()] == [
            ("write", 1.5, 1.5), ("refused", 4.0, 1.5)]
    finally:
        w.stop()
        devices.stop()


def test_after_a_watchdog_trip_the_writer_resumes_from_the_ramped_offsets(cnc, clock, audit):
    w = make_writer(settings(cnc, max_step_um=2.0), clock, audit)
    try:
        feed(w, clock, *(update(i, z=-6.0) for i in range(3)))
        assert cnc.update().applied_um["z"] == pytest.approx(6.0)
        clock.advance(10.0)  # the gateway stalls: no beat for 10 s, the CNC trips at 5 s and ramps (10 s)
        status = cnc.update()
        assert status.tripped
        assert status.applied_um["z"] == pytest.approx(3.0)
        w.service()  # the next beat finds the CNC tripped
        assert "verify" in w.alarms
        assert not w.synced
        assert "tripped" in next(a.message for a in w.alarms.active() if a.name == "verify")
        w.service()  # re-synchronises: commands what the CNC applies, then enables it
        status = cnc.update()
        assert w.synced
        assert status.enabled
        assert not status.tripped
        assert status.applied_um["z"] == pytest.approx(3.0)  # taken over from the ramp, no jump back to 6
        feed(w, clock, update(4, z=-6.0), update(5, z=-6.0))
        rows = [(e.mode, e.applied_um["z"]) for e in audit.writes()]
        assert rows == [("write", 2.0), ("write", 4.0), ("write", 6.0), ("observed", 3.0), ("write", 5.0),
                        ("write", 6.0)]  # the CNC's ramp is audited as what it did, not as a write of ours
        assert all(abs(b - a) <= 2.0 + 1e-9 for (ma, a), (mb, b) in itertools.pairwise(rows) if mb == "write")
        assert cnc.update().applied_um["z"] == pytest.approx(6.0)
        assert not cnc.update().tripped
    finally:
        w.stop()


def test_dry_run_computes_and_audits_but_never_connects(cnc, clock, audit):
    w = make_writer(settings(cnc, enabled=False), clock, audit)
    try:
        feed(w, clock, update(0, z=-1.0), update(1, z=-1.0))
        assert [(e.mode, e.commanded_um["z"]) for e in audit.writes()] == [("dry-run", 1.0)]
        status = cnc.update()
        assert not status.enabled
        assert status.applied_um["z"] == 0.0
        assert status.command_um["z"] == 0.0
        assert w.beats == 0
        assert not w.synced
    finally:
        w.stop()


def test_writer_thread_keeps_the_watchdog_alive_on_a_sped_up_clock(source):
    from gateway.clock import ScaledClock

    clock = ScaledClock(100.0)  # heartbeat 1 s of clock time = 10 ms of wall time
    devices = start_cnc(source, clock, heartbeat_timeout_s=50.0)
    w = make_writer(settings(devices.cnc), clock)
    try:
        with pytest.raises(RuntimeError, match="ManualClock"):
            make_writer(settings(devices.cnc), ManualClock()).start()
        w.start()
        w.submit(update(0, z=-1.0))
        start = clock.now()
        while clock.now() - start < 60.0:  # a minute of clock time
            clock.sleep_until(clock.now() + 5.0)
        status = devices.cnc.update()
        assert status.enabled
        assert status.heartbeat_ok
        assert status.trips == 0
        assert status.applied_um["z"] == pytest.approx(1.0)
        assert w.beats >= 10
    finally:
        w.stop()
        devices.stop()
    assert w._thread is None


def test_int16_little_endian_variant_and_sign_plus(source, clock, audit):
    devices = start_cnc(source, clock, offset_encoding="int16", offset_unit_um=1.0, heartbeat_address=3,
                        status_address=3)
    axes = tuple(dataclasses.replace(a, register=i, readback=i, data_type="int16", unit_um=1.0, sign=1.0)
                 for i, a in enumerate(default_axes(AXES)))
    w = make_writer(settings(devices.cnc, axes=axes, heartbeat_register=3, status_register=3, deadband_um=0.5),
                    clock, audit)
    try:
        feed(w, clock, update(0, x=1.2, y=-1.6, z=0.4))
        assert devices.cnc.update().applied_um == {"x": 1.0, "y": -2.0, "z": 0.0}  # sign +1, whole um
        assert all(e.verified for e in audit.writes())
    finally:
        w.stop()
        devices.stop()
