"""Probes in the live gateway, over real sockets: the simulated CNC probes on a schedule, the gateway reads the
block, stores each probe with the records, updates the estimate, publishes its band, gates the writes on it,
refuses bad probes with their reason, and rebuilds all of it from the store after a restart.

A ManualClock steps the samplers, the writer and the probe reader (see tests/test_live.py).
"""

from __future__ import annotations

import asyncio
import tomllib

import pytest
import tomli_w
from tests_paths import ROOT

from gateway.clock import ManualClock
from gateway.commands._common import load_model_for
from gateway.live.audit import AUDIT_NAME, AuditLog
from gateway.live.runtime import LiveGateway
from gateway.profile import load_profile
from gateway.record_store import STORE_NAME, stored_probes
from simulators.closed_loop import live_profile
from simulators.devices import DeviceSetConfig, serve
from simulators.devices.cnc import CompensationConfig, ProbeCycles
from simulators.machine import LiveMachine

PERIOD_S = 2.9  # the ADC board's period: coarse (a fast test), not locked onto the table's strokes
PROBE_EVERY_S = 1800.0


def scenario(tmp_path):
    """The paper's spindle-and-feeds run in a room whose air swings 6 K in 8 h: a drift the model never saw."""
    doc = tomllib.loads((ROOT / "simulators" / "scenarios" / "spindle-feeds.toml").read_text())
    doc["effects"] = {"room_cycle": {"amplitude_k": 3.0, "period_h": 8.0, "peak_at_h": 4.0}}
    path = tmp_path / "spindle-feeds-room.toml"
    path.write_text(tomli_w.dumps(doc))
    return path


class ProbeRig:
    def __init__(self, tmp_path, *, probes: str, name="p", opcua_port=None):
        self.clock = ManualClock(0.0)
        self.machine = LiveMachine(scenario(tmp_path), clock=self.clock)
        # a 15 s watchdog and a beat every 4 s: fewer steps of the clock, a fast test
        cnc = CompensationConfig(probes=ProbeCycles(every_s=PROBE_EVERY_S, sd_um=0.3, seed=2), heartbeat_timeout_s=15.0)
        self.devices = serve(self.machine, self.clock, DeviceSetConfig(adc_rtu=None, can=None, dcon=None, cnc=cnc))
        try:
            path = live_profile(self.devices, tmp_path / f"{name}.toml", period_s=PERIOD_S, opcua_port=opcua_port,
                                max_step_um=5.0, heartbeat_period_s=4.0, watchdog_s=15.0)
            path.write_text(path.read_text() + f"\n[probes]\n{probes}\n")
            self.profile = load_profile(path)
        except BaseException:
            self.devices.stop()
            raise
        self.model, _ = load_model_for(self.profile, None)
        self.updates = {}

    def gateway(self, data_dir) -> LiveGateway:
        def listen(record, update):
            self.updates[record.index] = update

        return LiveGateway(self.profile, model=self.model, data_dir=data_dir, clock=self.clock, listeners=[listen])

    def close(self):
        self.devices.stop()


def events(data_dir):
    log = AuditLog(data_dir / AUDIT_NAME)
    try:
        return log.events(), list(log.writes())
    finally:
        log.close()


def test_probes_update_the_live_estimate_and_a_restart_rebuilds_it(tmp_path):
    rig = ProbeRig(tmp_path, probes="enabled = true\npoll_s = 5.0")
    data = tmp_path / "data"
    try:
        with rig.gateway(data) as gw:
            gw.run_stepped(3.5 * 3600 + 120)  # the 7th probe, at 3.5 h, read and applied
            health = gw.health()
            est = gw.tracker.adaptive.estimate()
        last = max(rig.updates)
        before = rig.updates[last]
        with rig.gateway(data) as gw2:  # a restart: the store's windows and probes replayed
            rebuilt = gw2.tracker.last
            assert gw2.tracker.rebuilt_windows == last + 1
        cnc = rig.devices.cnc
    finally:
        rig.close()
    true = rig.machine.true_displacement_um(3.5 * 3600 + 120)
    # the room moved z by several um the model cannot know; the probes taught it
    model_err = abs(true["z"] - est[2].model_um)
    updated_err = abs(true["z"] - est[2].estimate_um)
    assert model_err > 2.0
    assert updated_err < 0.5 * model_err
    assert updated_err < 1.96 * est[2].sd_um + 0.3  # inside its band (and the probe noise)
    assert set(health.estimate.sd_um) == {"x", "y", "z"}
    assert 0 < health.estimate.sd_um["z"] < 3.0
    # every probe the CNC took reached the store once, after the window it was applied in
    probes = stored_probes(data / STORE_NAME)
    assert [p.seq for _, p in probes] == list(range(1, len(cnc.probes_taken) + 1))
    assert len(probes) == 7
    evs, _ = events(data)
    applied = [m for _, k, n, m in evs if k == "probe" and n == "applied"]
    assert len(applied) == 3 * 7  # three axes a probe
    # exported with the records: sparse probe_* columns, read back as probes (stamped at their window's end)
    from gateway.adaptive.probes import read_probes
    from gateway.record_store import RecordStore, export_recording

    with RecordStore(data / STORE_NAME) as store:
        exported = export_recording(store, rig.profile, tmp_path / "export.csv")
    back = read_probes(exported)
    assert [p.seq for p in back] == [p.seq for _, p in probes]
    for (window, stored), read in zip(probes, back, strict=True):
        assert read.time_s == (window + 1) * rig.profile.sampling.window_s
        assert dict(read.values_um) == pytest.approx(dict(stored.values_um), abs=1e-12)
    # rebuilt from the store: the same estimate and band as the run had at its last window
    for a in "xyz":
        assert rebuilt.estimate_um[a] == pytest.approx(before.estimate_um[a], abs=1e-6)
        assert rebuilt.sd_um[a] == pytest.approx(before.sd_um[a], abs=1e-6)


def test_bad_probes_are_refused_live_with_their_reason(tmp_path):
    rig = ProbeRig(tmp_path, probes="enabled = true\npoll_s = 5.0")
    data = tmp_path / "data"
    try:
        cnc = rig.devices.cnc
        with rig.gateway(data) as gw:
            gw.run_stepped(2 * 3600 + 100)  # four good probes: the bank has learned the machine
            seq = cnc.probes_taken and len(cnc.probes_taken)
            z = cnc.probes_taken[-1][1]["z"]
            cnc.write_probe(values_um={"z": z + 4.0}, seq=seq)  # the same number again, other values
            gw.run_stepped(2 * 3600 + 200)
            cnc.write_probe(values_um={"z": -gw.tracker.last.estimate_um["z"]}, seq=seq + 1)  # sign reversed
            gw.run_stepped(2 * 3600 + 300)
            cnc.write_probe([seq + 2, 8, 0, 0, 0, 0, 0, 0, 3])  # axis mask with no axis of ours
            gw.run_stepped(2 * 3600 + 400)
            cnc.write_probe(values_um={"z": gw.tracker.last.estimate_um["z"] + 30.0}, seq=seq + 3)  # a chip
            gw.run_stepped(2 * 3600 + 500)
            decisions = list(gw.tracker.decisions)
    finally:
        rig.close()
    refused = [d.reason for d in decisions if not d.accepted]
    assert any(r.startswith(f"repeated sequence number {seq} with other values") for r in refused), refused
    assert any(r.startswith("wrong sign:") for r in refused), refused
    assert any(r.startswith("outlier:") for r in refused), refused
    evs, _ = events(data)
    block = [m for _, k, n, m in evs if k == "probe" and n == "refused"]
    assert any("register 11 (axis mask): 8 (0x0008): expected bits 0-2" in m for m in block), block
    assert sum("wrong sign" in m for m in block) == 1


async def read_band(endpoint):
    from asyncua import Client

    async with Client(endpoint, timeout=10) as client:
        ns = await client.get_namespace_index("urn:cncgw")
        return {a: await client.get_node(f"ns={ns};s=Estimate.{a}_band95_um").read_value() for a in "xyz"}


def test_compensation_holds_while_the_band_is_wider_than_the_limit(tmp_path):
    # no probe before 30 min: the band grows from the identification's; after the probes it is narrow again
    rig = ProbeRig(tmp_path, probes="enabled = true\npoll_s = 5.0\nband_limit_um = 1.0", opcua_port=0)
    data = tmp_path / "data"
    try:
        with rig.gateway(data) as gw:
            gw.run_stepped(2.5 * 3600)
            for _ in range(200):  # the OPC UA publisher catches up with the windows
                if gw.opcua.published >= gw.windows_live:
                    break
                asyncio.run(asyncio.sleep(0.02))
            served = asyncio.run(read_band(gw.opcua.endpoint))
    finally:
        rig.close()
    last = rig.updates[max(rig.updates)]
    for a in "xyz":  # OPC UA serves the band of the last estimate
        assert served[a] == pytest.approx(1.959963984540054 * last.sd_um[a], rel=1e-9)
    evs, writes = events(data)
    held = [m for _, k, n, m in evs if n == "inputs" and "wider than probes.band_limit_um = 1 um" in m]
    assert held, [m for _, _, n, m in evs if n == "inputs"]
    wide = [i for i, u in rig.updates.items() if max(u.sd_um.values()) * 1.96 > 1.0]
    narrow = [i for i, u in rig.updates.items() if max(u.sd_um.values()) * 1.96 <= 1.0]
    assert wide
    assert narrow
    written = {w.window for w in writes}
    assert not written & set(wide)  # nothing written on a window whose band was too wide
    assert written & set(narrow)


def test_the_mqtt_estimate_carries_the_band():
    from gateway.live.outputs import WindowSnapshot
    from gateway.live.outputs.payloads import window_payloads

    snap = WindowSnapshot(machine="m", window=7, end_s=480.0, status="good", coverage=1.0, samples_taken=10,
                          samples_expected=10, missed_ticks=0, estimate_um={"z": -12.5}, usable=True,
                          band95_um={"z": 0.8})
    estimate = dict(window_payloads(snap))["estimate"]
    assert estimate["band95"]["z"]["value"] == 0.8
    assert estimate["values"]["z"]["value"] == -12.5
    plain = dict(window_payloads(WindowSnapshot(machine="m", window=7, end_s=480.0, status="good", coverage=1.0,
                                                samples_taken=10, samples_expected=10, missed_ticks=0)))["estimate"]
    assert "band95" not in plain  # without probes the payload is as before
