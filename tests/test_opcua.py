"""The OPC UA server with a real asyncua client on 127.0.0.1: what it shows, what it lets a client write.

One server for the module (asyncua's init takes about a second): configured ``writable = true``, so the
operator's hold request is the one writable node and everything else must still refuse writes.
"""

from __future__ import annotations

import asyncio
import math
import threading

import pytest
from tests_paths import PROFILES

from gateway.live.settings import OpcUa
from gateway.model import load_model
from gateway.opcua import OpcUaServer
from gateway.profile import load_profile

HEALTH = {
    "factors": {"spindle_speed": 1000.0, "z_i_sq": 13.3},
    "estimate": {"window": 42, "end_s": 2580.0, "estimate_um": {"x": -1.5, "y": 0.25, "z": -12.5}, "usable": True,
                 "reason": ""},
    "compensation": {"mode": "write", "commanded_um": {"x": 1.5, "y": -0.2, "z": 12.5}, "writes": 7,
                     "last_write": {"t_s": 2581.0, "window": 42, "mode": "write", "verified": True,
                                    "commanded_um": {"x": 1.5, "y": -0.2, "z": 12.5},
                                    "applied_um": {"x": 1.5, "y": -0.2, "z": 12.5}}},
    "alarms": [{"name": "clamped", "message": "target beyond +-100 um", "since_s": 2500.0}],
    "devices": [{"device": "adc", "state": "on_scan", "rate_hz": 499.5}],
    "last_window": {"missed_ticks": 3},
    "gaps": {"filled_windows": 2},
    "uptime_s": 12.5,
}


@pytest.fixture(scope="module")
def server():
    profile = load_profile(PROFILES / "sim-vmc.toml")
    model = load_model(PROFILES / "sim-vmc.model.toml")
    holds: list[bool] = []
    srv = OpcUaServer(OpcUa(port=0, writable=True), profile=profile, model=model, on_hold=holds.append).start()
    yield srv, holds
    srv.stop()


async def client_session(endpoint, work):
    from asyncua import Client

    async with Client(endpoint, timeout=10) as client:
        ns = await client.get_namespace_index("urn:cncgw")
        return await work(client, ns)


def published(srv, n):
    for _ in range(250):
        if srv.published >= n:
            return
        threading.Event().wait(0.02)
    pytest.fail(f"the server applied {srv.published} snapshots, expected {n}")


def test_shows_factors_estimates_compensation_and_health(server):
    srv, _ = server
    assert srv.endpoint.startswith("opc.tcp://127.0.0.1:")
    before = srv.published
    srv.publish(HEALTH)
    published(srv, before + 1)

    async def read(client, ns):
        keys = ["Machine.Name", "Factors.spindle_speed", "Estimate.z_um", "Estimate.Window", "Estimate.Usable",
                "Compensation.Mode", "Compensation.Commanded.z_um", "Compensation.Applied.y_um",
                "Compensation.Verified", "Compensation.Writes", "Health.Alarms", "Health.AlarmCount",
                "Health.Devices", "Health.SampleRateHz", "Health.MissedTicks", "Health.GapWindows",
                "Factors.x_feed"]
        return {k: await client.get_node(f"ns={ns};s={k}").read_value() for k in keys}

    v = asyncio.run(client_session(srv.endpoint, read))
    assert v["Machine.Name"] == "sim-vmc"
    assert v["Factors.spindle_speed"] == 1000.0
    assert math.isnan(v["Factors.x_feed"])  # not in the snapshot: never shown as a number
    assert (v["Estimate.z_um"], v["Estimate.Window"], v["Estimate.Usable"]) == (-12.5, 42, True)
    assert (v["Compensation.Mode"], v["Compensation.Commanded.z_um"], v["Compensation.Applied.y_um"]) == (
        "dry-run", 12.5, -0.2)  # the mode node shows the profile's setting (the bundled profile: dry run)
    assert (v["Compensation.Verified"], v["Compensation.Writes"]) == (True, 7)
    assert v["Health.Alarms"] == ["clamped: target beyond +-100 um"]
    assert v["Health.AlarmCount"] == 1
    assert v["Health.Devices"] == ["adc: on_scan"]
    assert (v["Health.SampleRateHz"], v["Health.MissedTicks"], v["Health.GapWindows"]) == (499.5, 3, 2)


def test_only_the_hold_request_is_writable(server):
    srv, holds = server

    async def write(client, ns):
        from asyncua import ua

        refused = []
        for key, v in (("Estimate.z_um", ua.Variant(0.0, ua.VariantType.Double)),
                       ("Compensation.Commanded.z_um", ua.Variant(99.0, ua.VariantType.Double)),
                       ("Compensation.Mode", ua.Variant("write", ua.VariantType.String))):
            try:
                await client.get_node(f"ns={ns};s={key}").write_value(v)
            except ua.UaStatusCodeError as exc:
                refused.append(type(exc).__name__)
        await client.get_node(f"ns={ns};s=Compensation.HoldRequest").write_value(
            ua.Variant(True, ua.VariantType.Boolean))
        return refused

    refused = asyncio.run(client_session(srv.endpoint, write))
    assert len(refused) == 3
    assert set(refused) <= {"BadUserAccessDenied", "BadNotWritable"}
    before = srv.published
    srv.publish(HEALTH)  # the publisher checks the hold request as it applies a snapshot
    published(srv, before + 1)
    assert holds == [True]


def test_only_the_configured_security_policy_is_offered(server):
    srv, _ = server

    async def endpoints(client, ns):
        return await client.get_endpoints()

    eps = asyncio.run(client_session(srv.endpoint, endpoints))
    assert {e.SecurityPolicyUri.rsplit("#", 1)[-1] for e in eps} == {"None"}
