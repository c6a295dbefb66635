"""The live gateway closed loop with the simulated machine over real sockets: accuracy, faults, restart.

A ManualClock steps the samplers (the ADC board is read every 0.73 s of clock time, a period that does not
lock onto the table's strokes) and the writer's heartbeat, so a run of hours takes seconds and is exact;
the CNC's watchdog runs in the same clock.
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import math
import re
import time

import pytest

from gateway.clock import ManualClock
from gateway.commands._common import load_model_for
from gateway.live.audit import AUDIT_NAME, AuditLog
from gateway.live.runtime import LiveGateway
from gateway.profile import load_profile
from gateway.record_store import STORE_NAME, RecordStore
from simulators.closed_loop import closed_loop_errors, live_profile
from simulators.devices import DeviceSetConfig, serve
from simulators.machine import LiveMachine

PERIOD_S = 2.19  # the ADC board's period: 3 x the earlier 0.73 s, a third of the reads over the same hours
MAX_STEP_UM = 5.0
ONLY_ADC_AND_CNC = {"adc_rtu": None, "can": None, "dcon": None}


class Rig:
    """A simulated machine behind its ADC board and CNC, and a profile pointing the gateway at them."""

    def __init__(self, tmp_path, scenario="spindle-feeds", *, opcua_port=None, name="p", **comp):
        self.clock = ManualClock(0.0)
        self.machine = LiveMachine(scenario, clock=self.clock)
        self.devices = serve(self.machine, self.clock, DeviceSetConfig(**ONLY_ADC_AND_CNC))
        comp.setdefault("heartbeat_period_s", 1.6)  # within a third of the CNC's 5 s watchdog
        path = live_profile(self.devices, tmp_path / f"{name}.toml", period_s=PERIOD_S, opcua_port=opcua_port,
                            max_step_um=MAX_STEP_UM, **comp)
        self.profile = load_profile(path)
        self.model, _ = load_model_for(self.profile, None)
        self.offsets: dict[int, dict[str, float]] = {}
        self.estimates: dict[int, dict[str, float]] = {}

    def gateway(self, data_dir, **kw) -> LiveGateway:
        def listen(record, update):
            self.offsets[record.index] = dict(gw.writer.commanded_um)
            self.estimates[record.index] = dict(update.estimate_um)

        gw = LiveGateway(self.profile, model=self.model, data_dir=data_dir, clock=self.clock, listeners=[listen], **kw)
        return gw

    def close(self):
        self.devices.stop()


@pytest.fixture
def rig(tmp_path):
    r = Rig(tmp_path, opcua_port=0)
    yield r
    r.close()


def audited(data_dir):
    log = AuditLog(data_dir / AUDIT_NAME)
    try:
        return list(log.writes()), log.events()
    finally:
        log.close()


async def read_opcua(endpoint, keys):
    from asyncua import Client, ua

    async with Client(endpoint, timeout=10) as client:
        ns = await client.get_namespace_index("urn:cncgw")
        values = {k: await client.get_node(f"ns={ns};s={k}").read_value() for k in keys}
        refused = []
        for key, v in (("Compensation.HoldRequest", ua.Variant(True, ua.VariantType.Boolean)),
                       ("Estimate.z_um", ua.Variant(0.0, ua.VariantType.Double))):
            try:
                await client.get_node(f"ns={ns};s={key}").write_value(v)
            except ua.UaStatusCodeError as exc:
                refused.append((key, type(exc).__name__))
        return values, refused


def test_closed_loop_cuts_the_error_by_70_percent_and_the_cnc_applies_what_is_written(rig, tmp_path):
    end_s = 3 * 3600  # the spindle-feeds run's first working phase (its peak) and the cooling after it
    data = tmp_path / "data"
    with rig.gateway(data) as gw:
        gw.run_stepped(end_s)
        health = gw.health()
        deadline = 200
        while gw.opcua.published < gw.windows_live and deadline:  # the publisher catches up with the windows
            deadline -= 1
            asyncio.run(asyncio.sleep(0.02))
        values, refused = asyncio.run(read_opcua(gw.opcua.endpoint, [
            "Estimate.z_um", "Compensation.Commanded.z_um", "Compensation.Mode", "Health.AlarmCount",
            "Health.WindowStatus", "Health.WindowQuality", "Health.CoveragePct", "Health.SamplesTaken",
            "Health.SamplesExpected", "Health.WindowIndex"]))
    errs = closed_loop_errors(rig.machine, end_s)
    for axis in ("x", "y", "z"):
        assert errs.reduction(axis) >= 0.70, (axis, errs.max_without_um[axis], errs.max_with_um[axis])
    assert errs.max_without_um["z"] > 19.0
    assert errs.max_with_um["z"] < 3.0  # the first minute after the spindle starts: one window of lag
    writes, _ = audited(data)
    assert len(writes) > 80
    assert all(w.mode == "write" and w.verified for w in writes)
    applied = {tuple(round(v, 6) for v in offs.values()) for _, offs in rig.machine.compensation_log}
    assert all(tuple(round(w.commanded_um[a], 6) for a in "xyz") in applied for w in writes)  # written == applied
    for a, b in itertools.pairwise(writes):
        assert max(abs(b.applied_um[x] - a.applied_um[x]) for x in "xyz") <= MAX_STEP_UM + 1e-9  # never a jump
    assert health.alarms == ()
    assert health.windows_live == 180
    assert health.compensation.synced is True
    assert rig.devices.cnc.update().trips == 0
    est = health.estimate.estimate_um["z"]
    assert values["Estimate.z_um"] == pytest.approx(est)
    assert values["Compensation.Commanded.z_um"] == pytest.approx(health.compensation.commanded_um["z"])
    assert values["Compensation.Mode"] == "write"
    assert values["Health.AlarmCount"] == 0
    assert values["Health.WindowIndex"] == 179
    assert values["Health.WindowStatus"] == "good"
    assert values["Health.CoveragePct"] > 90.0
    assert values["Health.SamplesTaken"] <= values["Health.SamplesExpected"]
    assert values["Health.WindowQuality"] == (f"coverage {values['Health.CoveragePct']:.0f} % "
                                              f"({values['Health.SamplesTaken']}/{values['Health.SamplesExpected']} "
                                              "samples)")
    assert [k for k, _ in refused] == ["Compensation.HoldRequest", "Estimate.z_um"]  # read-only by default
    assert all(e in ("BadUserAccessDenied", "BadNotWritable") for _, e in refused)


def test_restart_rebuilds_the_estimate_and_changes_the_compensation_by_less_than_0_1_um(tmp_path):
    end_s, kill_s, down_s = 2.5 * 3600, 1.5 * 3600 + 25.0, 3.0  # killed while heating, back within the watchdog
    ref = Rig(tmp_path, name="ref")
    try:
        with ref.gateway(tmp_path / "ref") as gw:
            gw.run_stepped(end_s)
    finally:
        ref.close()
    rig = Rig(tmp_path, name="restart")
    try:
        data = tmp_path / "restart"
        with rig.gateway(data) as gw:
            gw.run_stepped(kill_s)
        with RecordStore(data / STORE_NAME) as store:
            stored = len(store)
        rig.clock.advance(down_s)
        with rig.gateway(data) as gw2:
            assert gw2.tracker.rebuilt_windows == stored
            gw2.run_stepped(end_s)
            health = gw2.health()
        assert rig.devices.cnc.update().trips == 0
    finally:
        rig.close()
    after = [i for i in rig.offsets if i > stored]
    assert len(after) > 50
    est_diff = max(abs(rig.estimates[i][a] - ref.estimates[i][a]) for i in after for a in "xyz")
    assert est_diff < 0.1, est_diff
    # what was written: the same 0.1 um counts, or one count apart where the estimate sits near a rounding edge
    counts = [abs(round(10 * rig.offsets[i][a]) - round(10 * ref.offsets[i][a])) for i in after for a in "xyz"]
    assert max(counts) <= 1
    assert sum(c == 0 for c in counts) / len(counts) > 0.9
    assert health.gaps.filled_windows == 1  # the window in progress at the kill, held
    assert "filled by gap policy hold" in health.gaps.last
    writes, events = audited(data)
    assert [k for _, k, n, _ in events if n == "estimator"] == ["rebuild"]
    for a, b in itertools.pairwise(writes):
        assert max(abs(b.applied_um[x] - a.applied_um[x]) for x in "xyz") <= MAX_STEP_UM + 1e-9


def test_devices_dropping_and_saturated_values_hold_the_offsets_without_a_jump(tmp_path, caplog):
    caplog.set_level(logging.INFO, logger="gateway.live")
    rig = Rig(tmp_path)
    try:
        adc = rig.devices.adc_tcp
        data = tmp_path / "data"
        with rig.gateway(data) as gw:
            gw.run_stepped(80 * 60)  # heating since 60 min
            held = dict(gw.writer.commanded_um)
            adc.faults.drop_replies = True  # the board stops answering for 4 minutes
            gw.run_stepped(84 * 60)
            assert "inputs" in gw.alarms
            assert gw.writer.commanded_um == pytest.approx(held, abs=MAX_STEP_UM)  # at most the window before
            frozen = dict(gw.writer.commanded_um)
            gw.run_stepped(86 * 60)
            assert gw.writer.commanded_um == frozen  # held while the board is down
            adc.faults.drop_replies = False
            gw.run_stepped(90 * 60)
            assert "inputs" not in gw.alarms
            adc.faults.force("spindle_i1", 1e6)  # a value far out of range: the converter saturates
            gw.run_stepped(93 * 60)
            assert "saturated" in next(a.message for a in gw.alarms.active() if a.name == "inputs")
            adc.faults.release("spindle_i1")
            gw.run_stepped(100 * 60)
            health = gw.health()
        assert health.alarms == ()
        assert health.gaps.filled_windows >= 7
        with RecordStore(data / STORE_NAME) as store:  # the store says why each window was not used
            bad = {r.index: r for r in store.windows() if r.status != "good"}
        dropped = [r for r in bad.values() if r.status == "insufficient"]
        saturated = [r for r in bad.values() if r.status == "rejected"]
        assert len(dropped) >= 3
        assert len(saturated) >= 2  # enough samples, but the converter sat at its limit: never "good"
        assert all("device adc: " in r.quality() and "samples)" in r.quality() for r in dropped)
        assert all("channel spindle_i1 (factor spindle_i1_sq) saturated in" in r.reason for r in saturated)
        # the run log explains each window that is not good: coverage, samples, the device and its error
        lines = [m for m in caplog.messages if re.match(r"window \d+ insufficient: ", m)]
        assert len(lines) >= 3
        assert all(re.match(r"window \d+ insufficient: coverage \d+ % \(\d+/\d+ samples\), device adc: ", m)
                   for m in lines), lines
        assert re.match(r'window \d+ insufficient: coverage 0 % \(0/\d+ samples\), device adc: device "adc" '
                        r"\(Modbus TCP\): no valid answer to fc4 0..8 within 0.5 s", lines[0]), lines[0]
        # every sample taken; 99-100 %: the board is read every 0.73 s, and a window's last 0-0.73 s lie after
        # its last sample
        assert any(re.match(r"window \d+ rejected: coverage (99|100) % .*channel spindle_i1 \(factor spindle_i1_sq\) "
                            r"saturated in \d+ samples", m) for m in caplog.messages)
        writes, events = audited(data)
        for a, b in itertools.pairwise(writes):
            assert max(abs(b.applied_um[x] - a.applied_um[x]) for x in "xyz") <= MAX_STEP_UM + 1e-9
        assert all(w.verified for w in writes)
        assert {n for _, k, n, _ in events if k == "alarm"} == {"inputs"}
        assert all(math.isfinite(v) for w in writes for v in w.commanded_um.values())
    finally:
        rig.close()


def test_cnc_unreachable_at_start_then_back(tmp_path):
    rig = Rig(tmp_path, scenario="spindle-1000rpm")
    try:
        cnc = rig.devices.cnc
        cnc.faults.drop_replies = True
        with rig.gateway(tmp_path / "data") as gw:
            gw.run_stepped(40 * 60)
            assert "cnc" in gw.alarms
            assert gw.writer.writes == 0
            cnc.faults.drop_replies = False
            for _ in range(200):  # reconnects are spaced by reconnect_s (0.5 s) of wall time
                gw.run_stepped(gw.clock.now() + 1.0)
                if gw.writer.synced:
                    break
                time.sleep(0.02)
            gw.run_stepped(50 * 60)
            health = gw.health()
        assert health.compensation.synced is True
        assert health.compensation.writes > 0
        assert "cnc" not in [a.name for a in health.alarms]
        assert cnc.update().applied_um["z"] > 1.0  # compensating the spindle's growth
    finally:
        rig.close()


async def read_served(endpoint, window_index, keys):
    """Wait until the gateway's OPC UA server shows window ``window_index``; then per key: (type definition,
    EngineeringUnits, EURange, status name, value, source time)."""
    from asyncua import Client

    async with Client(endpoint, timeout=10) as client:
        ns = await client.get_namespace_index("urn:cncgw")
        for _ in range(250):
            if await client.get_node(f"ns={ns};s=Health.WindowIndex").read_value() == window_index:
                break
            await asyncio.sleep(0.02)
        out = {}
        for key in keys:
            node = client.get_node(f"ns={ns};s={key}")
            typedef = (await client.get_node(await node.read_type_definition()).read_browse_name()).Name
            props = {(await p.read_browse_name()).Name: await p.read_value() for p in await node.get_properties()}
            d = await node.read_data_value(raise_on_bad_status=False)
            out[key] = (typedef, props.get("EngineeringUnits"), props.get("EURange"), d.StatusCode.name,
                        d.Value.Value, d.SourceTimestamp)
        return out


def test_an_opcua_client_sees_analog_items_and_the_status_go_good_held_bad_through_a_dropped_board(tmp_path):
    from datetime import UTC, datetime

    rig = Rig(tmp_path, opcua_port=0, live="gap_hold_max_s = 180.0")
    keys = ("Factors.spindle_speed", "Factors.z_i_sq", "Estimate.z_um", "Compensation.Commanded.z_um")
    try:
        adc = rig.devices.adc_tcp
        seen = []
        with rig.gateway(tmp_path / "data") as gw:
            for end_min, drop in ((62, False), (65, True), (70, True), (76, False)):
                adc.faults.drop_replies = drop
                gw.run_stepped(end_min * 60)
                h = gw.health()
                v = asyncio.run(read_served(gw.opcua.endpoint, h.last_window.index, keys))
                seen.append((h, v))
        for h, v in seen:
            t = datetime.fromtimestamp(h.last_window.end_s, UTC)
            assert {s[5] for s in v.values()} == {t}  # source time: the window's end (clock seconds)
            assert {s[0] for s in v.values()} == {"AnalogItemType"}
            eu, rng = v["Estimate.z_um"][1], v["Estimate.z_um"][2]
            assert (eu.UnitId, eu.DisplayName.Text) == (13384, "\u00b5m")  # UNECE 4H
            assert (rng.Low, rng.High) == (-rig.model.envelope.axes["z"].max_abs_um,
                                           rig.model.envelope.axes["z"].max_abs_um)
            assert (v["Factors.spindle_speed"][1].UnitId, v["Factors.spindle_speed"][1].DisplayName.Text) == (
                5394509, "r/min")  # UNECE RPM
            assert v["Factors.z_i_sq"][2].Low == pytest.approx(rig.model.reference["z_i_sq"])
            assert v["Compensation.Commanded.z_um"][3] == "Good"  # what the writer holds is a fact
        status = [{k: s[3] for k, s in v.items() if not k.startswith("Compensation")} for _, v in seen]
        assert [set(s.values()) for s in status] == [{"Good"}, {"UncertainLastUsableValue"}, {"BadNoCommunication"},
                                                     {"Good"}]
        (good, v_good), (held, v_held), (bad, v_bad), (back, v_back) = seen
        assert good.last_window.status == "good"
        assert held.last_window.status == bad.last_window.status == "insufficient"
        assert (held.estimate.inputs, bad.estimate.inputs) == ("held", "reference")  # gap_hold_max_s 180 s passed
        assert v_good["Estimate.z_um"][4] == pytest.approx(good.estimate.estimate_um["z"])
        assert v_good["Factors.spindle_speed"][4] == pytest.approx(good.factors["spindle_speed"])
        # held: the last good window's factors (the board has been silent since minute 62), and the estimate on them
        assert v_held["Factors.spindle_speed"][4] == pytest.approx(held.estimate.held_factors["spindle_speed"])
        # the good window seen may be an earlier one than the last before the drop: 82 reads a window at 0.73 s
        # scatter its mean speed by a few 0.01 rpm
        assert held.estimate.held_factors["spindle_speed"] == pytest.approx(good.factors["spindle_speed"], abs=0.5)
        assert v_held["Estimate.z_um"][4] == pytest.approx(held.estimate.estimate_um["z"])
        assert all(s[4] is None for k, s in v_bad.items() if not k.startswith("Compensation"))  # no number when Bad
        assert v_back["Estimate.z_um"][4] == pytest.approx(back.estimate.estimate_um["z"])
    finally:
        rig.close()
