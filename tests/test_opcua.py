"""The OPC UA server with a real asyncua client on 127.0.0.1: what it shows, who may write what.

One server for the module (asyncua's init takes about a second): ``writable = true`` with an operator
(user name and password over an encrypted policy) and anonymous reading allowed, so the operator's hold
request is the one writable node, only an authenticated session writes it, and everything else must still
refuse writes. Certificates are made for the test by asyncua's own generator.
"""

from __future__ import annotations

import asyncio
import math
import threading
import time
from dataclasses import replace
from datetime import UTC, datetime
from types import MappingProxyType

import pytest
from tests_paths import PROFILES

from gateway.clock import ManualClock
from gateway.live.audit import Alarm, WriteEntry
from gateway.live.compensation import WriterStatus
from gateway.live.health import GapStatus, Health
from gateway.live.opcua_server import OpcUaServer, unit_of
from gateway.live.tracking import EstimateUpdate
from gateway.model import load_model
from gateway.profile import load_profile
from gateway.profile.live import OpcUa
from gateway.sampler import DeviceStatus
from gateway.windows import ChannelStats, DeviceQuality, WindowRecord


def window(index: int = 42, *, factors=None, status: str = "good", reads_ok: int = 97) -> WindowRecord:
    """A window of the ADC board: 100 ticks expected, ``reads_ok`` of them read."""
    factors = {"spindle_speed": 1000.0, "z_i_sq": 13.3} if factors is None else factors
    stats = ChannelStats(count=reads_ok, coverage=reads_ok / 100, mean=1.0, mean_square=1.0, mean_abs=1.0, min=1.0,
                         max=1.0, saturated=0, bad=0)
    device = DeviceQuality(ticks_expected=100, ticks_run=100, ticks_skipped=0, reads_ok=reads_ok,
                           reads_failed=100 - reads_ok, timeouts=0, off_scan_ticks=0, largest_gap_s=0.0,
                           lateness_max_s=0.0, read_time_max_s=0.0, tick_s=0.6)
    return WindowRecord(index=index, start_s=index * 60.0, end_s=(index + 1) * 60.0, status=status,
                        factors=MappingProxyType(factors), channels=MappingProxyType({"spindle_speed": stats}),
                        devices=MappingProxyType({"adc": device}))


def estimate(index: int = 42, *, usable: bool = True, reason: str = "") -> EstimateUpdate:
    est = MappingProxyType({"x": -1.5, "y": 0.25, "z": -12.5})
    return EstimateUpdate(index=index, end_s=(index + 1) * 60.0, estimate_um=est, next_um=est,
                          factors=MappingProxyType({}), usable=usable, reason=reason)


LAST_WRITE = WriteEntry(t_s=2581.0, window=42, mode="write", verified=True,
                        estimate_um={"x": -1.5, "y": 0.25, "z": -12.5}, target_um={"x": 1.5, "y": -0.2, "z": 12.5},
                        commanded_um={"x": 1.5, "y": -0.2, "z": 12.5}, applied_um={"x": 1.5, "y": -0.2, "z": 12.5})
HEALTH = Health(
    machine="sim-vmc", clock_s=2581.0, uptime_s=12.5, windows_live=43, last_window=window(), estimate=estimate(),
    compensation=WriterStatus(mode="write", synced=True, commanded_um={"x": 1.5, "y": -0.2, "z": 12.5}, writes=7,
                              beats=40, failures=0, cnc_status=17, last_write=LAST_WRITE, holding=False),
    alarms=(Alarm(name="clamped", message="target beyond +-100 um", since_s=2500.0),),
    devices=(DeviceStatus(device="adc", state="on_scan", reads_ok=4995, reads_failed=0, timeouts=0, off_scan_ticks=0,
                          recoveries=0, ticks_run=5000, ticks_skipped=5, rate_hz=499.5),),
    gaps=GapStatus(filled_windows=2, policy="hold"), stale_after_s=150.0)

PASSWORD = "hold-me-4711"
ENCRYPTED = "Basic256Sha256_SignAndEncrypt"


@pytest.fixture(scope="module")
def pki(tmp_path_factory):
    """A server and a client certificate (asyncua's generator), and the operator's password file."""
    from asyncua.crypto.cert_gen import setup_self_signed_certificate
    from cryptography.x509.oid import ExtendedKeyUsageOID

    d = tmp_path_factory.mktemp("pki")

    async def make():
        await setup_self_signed_certificate(d / "server-key.pem", d / "server-cert.der", "urn:cncgw:test", "localhost",
                                            [ExtendedKeyUsageOID.SERVER_AUTH], {"commonName": "cncgw test"})
        await setup_self_signed_certificate(d / "client-key.pem", d / "client-cert.der", "urn:cncgw:client",
                                            "localhost", [ExtendedKeyUsageOID.CLIENT_AUTH], {"commonName": "client"})

    asyncio.run(make())
    (d / "password").write_text(PASSWORD + "\n")
    return d


def settings(pki, **kw) -> OpcUa:
    base = {"port": 0, "writable": True, "security": ("None", ENCRYPTED), "certificate": pki / "server-cert.der",
            "private_key": pki / "server-key.pem", "username": "operator", "password_file": pki / "password",
            "allow_anonymous": True}
    return OpcUa(**{**base, **kw})


@pytest.fixture(scope="module")
def server(pki):
    profile = load_profile(PROFILES / "sim-vmc.toml")
    model = load_model(PROFILES / "sim-vmc.model.toml")
    holds: list[bool] = []
    srv = OpcUaServer(settings(pki), profile=profile, model=model, on_hold=holds.append).start()
    yield srv, holds
    srv.stop()


async def client_session(endpoint, work, *, user=None, password=None, pki=None):
    from asyncua import Client

    client = Client(endpoint, timeout=10)
    if pki is not None:  # the encrypted endpoint, as an operator's client would use it
        await client.set_security_string(f"Basic256Sha256,SignAndEncrypt,{pki / 'client-cert.der'},"
                                         f"{pki / 'client-key.pem'}")
    if user is not None:
        client.set_user(user)
        client.set_password(password)
    async with client:
        ns = await client.get_namespace_index("urn:cncgw")
        return await work(client, ns)


def published(srv, n):
    for _ in range(250):
        if srv.published >= n:
            return
        threading.Event().wait(0.02)
    pytest.fail(f"the server applied {srv.published} snapshots, expected {n}")


async def try_writes(client, ns):
    """Write the hold request and three read-only nodes; the status of each (``"ok"`` or the error's name)."""
    from asyncua import ua

    out = {}
    for key, v in (("Compensation.HoldRequest", ua.Variant(True, ua.VariantType.Boolean)),
                   ("Estimate.z_um", ua.Variant(0.0, ua.VariantType.Double)),
                   ("Compensation.Commanded.z_um", ua.Variant(99.0, ua.VariantType.Double)),
                   ("Compensation.Mode", ua.Variant("write", ua.VariantType.String))):
        try:
            await client.get_node(f"ns={ns};s={key}").write_value(v)
            out[key] = "ok"
        except ua.UaStatusCodeError as exc:
            out[key] = type(exc).__name__
    return out


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
        return {k: await client.get_node(f"ns={ns};s={k}").read_data_value(raise_on_bad_status=False) for k in keys}

    dv = asyncio.run(client_session(srv.endpoint, read))
    v = {k: d.Value.Value for k, d in dv.items()}
    assert v["Machine.Name"] == "sim-vmc"
    assert v["Factors.spindle_speed"] == 1000.0
    # not in the snapshot: never shown as a number; a Bad value is null (OPC 10000-4, 7.11)
    assert (dv["Factors.x_feed"].StatusCode.name, v["Factors.x_feed"]) == ("BadNoCommunication", None)
    assert {d.StatusCode.name for k, d in dv.items() if k != "Factors.x_feed"} == {"Good"}
    assert (v["Estimate.z_um"], v["Estimate.Window"], v["Estimate.Usable"]) == (-12.5, 42, True)
    assert (v["Compensation.Mode"], v["Compensation.Commanded.z_um"], v["Compensation.Applied.y_um"]) == (
        "dry-run", 12.5, -0.2)  # the mode node shows the profile's setting (the bundled profile: dry run)
    assert (v["Compensation.Verified"], v["Compensation.Writes"]) == (True, 7)
    assert v["Health.Alarms"] == ["clamped: target beyond +-100 um"]
    assert v["Health.AlarmCount"] == 1
    assert v["Health.Devices"] == ["adc: on_scan"]
    assert (v["Health.SampleRateHz"], v["Health.MissedTicks"], v["Health.GapWindows"]) == (499.5, 3, 2)


def test_an_anonymous_session_reads_and_is_refused_every_write(server):
    srv, holds = server
    before = len(holds)
    refused = asyncio.run(client_session(srv.endpoint, try_writes))
    assert set(refused.values()) == {"BadUserAccessDenied"}  # the hold request too: anonymous never writes
    published_before = srv.published
    srv.publish(HEALTH)  # the publisher checks the hold request as it applies a snapshot
    published(srv, published_before + 1)
    assert len(holds) == before


def test_the_operator_logged_in_over_an_encrypted_channel_holds_the_offsets_and_nothing_else(server, pki):
    srv, holds = server
    result = asyncio.run(client_session(srv.endpoint, try_writes, user="operator", password=PASSWORD, pki=pki))
    assert result["Compensation.HoldRequest"] == "ok"
    assert {result[k] for k in result if k != "Compensation.HoldRequest"} <= {"BadUserAccessDenied", "BadNotWritable"}
    before = srv.published
    srv.publish(HEALTH)
    published(srv, before + 1)
    assert holds[-1:] == [True]


def test_a_wrong_password_is_refused_at_login(server, pki):
    from asyncua import ua

    srv, _ = server
    with pytest.raises(ua.UaStatusCodeError, match="BadUserAccessDenied"):
        asyncio.run(client_session(srv.endpoint, try_writes, user="operator", password="guess", pki=pki))


def test_under_encrypted_policies_anonymous_is_off_unless_allowed(pki):
    from asyncua import ua

    profile = load_profile(PROFILES / "sim-vmc.toml")
    model = load_model(PROFILES / "sim-vmc.model.toml")
    srv = OpcUaServer(settings(pki, allow_anonymous=False), profile=profile, model=model, on_hold=print).start()
    try:
        async def tokens(client, ns):
            return {(e.SecurityPolicyUri.rsplit("#", 1)[-1], t.TokenType.name) for e in await client.get_endpoints()
                    for t in e.UserIdentityTokens}

        offered = asyncio.run(client_session(srv.endpoint, tokens, user="operator", password=PASSWORD, pki=pki))
        assert {t for _, t in offered} == {"UserName"}  # no anonymous login on any endpoint
        with pytest.raises(ua.UaStatusCodeError, match="BadIdentityTokenRejected"):
            asyncio.run(client_session(srv.endpoint, tokens))
    finally:
        srv.stop()


def test_only_the_configured_security_policies_are_offered(server):
    srv, _ = server

    async def endpoints(client, ns):
        return await client.get_endpoints()

    eps = asyncio.run(client_session(srv.endpoint, endpoints))
    assert {e.SecurityPolicyUri.rsplit("#", 1)[-1] for e in eps} == {"None", "Basic256Sha256"}
    assert {t.TokenType.name for e in eps for t in e.UserIdentityTokens} == {"Anonymous", "UserName"}


def test_unit_ids_follow_the_common_codes_as_the_spec_computes_them():
    # UnitId values as the OPC Foundation's UNECE_to_OPCUA.csv lists them
    assert {k: unit_of(k).unit_id for k in ("um", "rpm", "mm/min", "degC", "%")} == {
        "um": 13384, "rpm": 5394509, "mm/min": 4732977, "degC": 4408652, "%": 20529}
    assert unit_of("um").namespace == "http://www.opcfoundation.org/UA/units/un/cefact"
    a2 = unit_of("A^2")  # Rec. 20 has no ampere squared: our own unit, not a UNECE id
    assert (a2.namespace, a2.unit_id, a2.display) == ("urn:cncgw", -1, "A\u00b2")
    assert (unit_of("furlong/min").unit_id, unit_of("furlong/min").display) == (-1, "furlong/min")


async def analog_info(client, ns, keys):
    """Per node: its type definition's name, EngineeringUnits, EURange (None when absent)."""
    out = {}
    for key in keys:
        node = client.get_node(f"ns={ns};s={key}")
        typedef = await client.get_node(await node.read_type_definition()).read_browse_name()
        props = {(await p.read_browse_name()).Name: await p.read_value() for p in await node.get_properties()}
        out[key] = (typedef.Name, props.get("EngineeringUnits"), props.get("EURange"))
    return out


def test_values_are_analog_items_with_unece_units_and_ranges_from_the_model_and_profile(server):
    srv, _ = server
    model, profile = srv.model, srv.profile
    keys = ([f"Factors.{f.name}" for f in profile.factors] + [f"Estimate.{a}_um" for a in model.axes]
            + [f"Compensation.{k}.{a.axis}_um" for k in ("Commanded", "Applied") for a in profile.compensation.axes]
            + ["Health.CoveragePct"])
    info = asyncio.run(client_session(srv.endpoint, lambda c, ns: analog_info(c, ns, keys)))
    assert {t for t, _, _ in info.values()} == {"AnalogItemType"}
    eu = {k: (u.NamespaceUri, u.UnitId, u.DisplayName.Text) for k, (_, u, _) in info.items()}
    cefact = "http://www.opcfoundation.org/UA/units/un/cefact"
    assert eu["Estimate.z_um"] == eu["Compensation.Applied.x_um"] == (cefact, 13384, "\u00b5m")
    assert eu["Factors.spindle_speed"] == (cefact, 5394509, "r/min")
    assert eu["Factors.x_feed"] == (cefact, 4732977, "mm/min")
    assert eu["Factors.z_i_sq"] == ("urn:cncgw", -1, "A\u00b2")
    assert eu["Health.CoveragePct"] == (cefact, 20529, "%")
    rng = {k: (r.Low, r.High) for k, (_, _, r) in info.items()}
    # the bundled model's envelope: z moved at most 17.04 um over the identification experiments
    assert rng["Estimate.z_um"] == pytest.approx((-17.04, 17.04), abs=0.01)
    assert all(rng[f"Estimate.{a}_um"] == (-model.envelope.axes[a].max_abs_um, model.envelope.axes[a].max_abs_um)
               for a in model.axes)
    # a factor: its reference plus the deviations identification covered (z_i_sq: 13.27 A^2 holding current)
    assert rng["Factors.z_i_sq"] == pytest.approx((13.27, 23.15), abs=0.01)
    assert rng["Factors.spindle_speed"] == pytest.approx((0.0, 1000.0))
    assert rng["Compensation.Commanded.z_um"] == (-profile.compensation.limit_um, profile.compensation.limit_um)
    assert rng["Health.CoveragePct"] == (0.0, 100.0)


def served(srv, health, keys):
    """Publish ``health``, wait until it is applied, read ``keys``: name -> (status name, value, source time)."""
    before = srv.published
    srv.publish(health)
    published(srv, before + 1)

    async def read(client, ns):
        out = {}
        for k in keys:
            d = await client.get_node(f"ns={ns};s={k}").read_data_value(raise_on_bad_status=False)
            out[k] = (d.StatusCode.name, d.Value.Value, d.SourceTimestamp)
        return out

    return asyncio.run(client_session(srv.endpoint, read))


KEYS = ("Factors.spindle_speed", "Factors.z_i_sq", "Estimate.z_um", "Health.WindowStatus")


def test_status_follows_the_window_good_held_bad_stale_and_times_are_the_windows(server):
    srv, _ = server
    t42 = datetime.fromtimestamp(43 * 60.0, UTC)
    v = served(srv, HEALTH, KEYS)
    assert v["Factors.spindle_speed"] == ("Good", 1000.0, t42)
    assert v["Estimate.z_um"] == ("Good", -12.5, t42)
    # window 43: the board did not answer; the gap policy held window 42's factors
    w43 = window(43, factors={"spindle_speed": math.nan, "z_i_sq": math.nan}, status="insufficient", reads_ok=0)
    held = replace(estimate(43, usable=False, reason="window 43 insufficient"), inputs="held",
                   held_factors=MappingProxyType({"spindle_speed": 1000.0, "z_i_sq": 13.3}))
    t43 = datetime.fromtimestamp(44 * 60.0, UTC)
    v = served(srv, replace(HEALTH, clock_s=44 * 60.0, last_window=w43, estimate=held), KEYS)
    assert v["Factors.spindle_speed"] == ("UncertainLastUsableValue", 1000.0, t43)
    assert v["Estimate.z_um"] == ("UncertainLastUsableValue", -12.5, t43)
    assert v["Health.WindowStatus"] == ("Good", "insufficient", t43)
    # window 60: held too long (gap_hold_max_s): the estimate assumes the machine idle, no factor is known
    w60 = replace(w43, index=60, start_s=60 * 60.0, end_s=61 * 60.0)
    idle = replace(estimate(60, usable=False, reason="window 60 insufficient"), inputs="reference")
    v = served(srv, replace(HEALTH, clock_s=61 * 60.0, last_window=w60, estimate=idle), KEYS)
    assert v["Factors.spindle_speed"][:2] == v["Estimate.z_um"][:2] == ("BadNoCommunication", None)
    assert v["Estimate.z_um"][2] == datetime.fromtimestamp(61 * 60.0, UTC)
    # saturated: enough samples, none valid
    v = served(srv, replace(HEALTH, clock_s=61 * 60.0, last_window=replace(w60, status="rejected"), estimate=idle),
               KEYS)
    assert v["Estimate.z_um"][:2] == ("BadSensorFailure", None)
    # no window closed for longer than stale_after_s (150 s): the last good values are not served as Good
    v = served(srv, replace(HEALTH, clock_s=43 * 60.0 + 151.0), KEYS)
    assert v["Factors.spindle_speed"][:2] == v["Estimate.z_um"][:2] == ("BadOutOfService", None)
    v = served(srv, HEALTH, KEYS)
    assert v["Estimate.z_um"] == ("Good", -12.5, t42)
    # not written (probe band too wide) is the writer's business: the estimate of good factors stays Good
    wide = estimate(usable=False, reason="95 % band z +-3.28 um wider than probes.band_limit_um = 1 um")
    v = served(srv, replace(HEALTH, estimate=wide), KEYS)
    assert v["Estimate.z_um"] == ("Good", -12.5, t42)


def test_values_turn_bad_out_of_service_on_the_servers_own_clock_when_no_snapshot_comes(server):
    """The acquisition stopped: no window closes, no snapshot arrives; the server's one-second beat sees it."""
    srv, _ = server
    clock = ManualClock(HEALTH.clock_s)
    srv.clock = clock  # what LiveGateway passes as OpcUaServer(clock=...)
    try:
        assert served(srv, HEALTH, KEYS)["Estimate.z_um"][0] == "Good"
        clock.set(43 * 60.0 + 151.0)  # stale_after_s is 150 s: past it, and nothing published

        async def status(client, ns):
            node = client.get_node(f"ns={ns};s=Estimate.z_um")
            return (await node.read_data_value(raise_on_bad_status=False)).StatusCode.name

        for _ in range(50):  # the beat is 1 s of wall time
            code = asyncio.run(client_session(srv.endpoint, status))
            if code != "Good":
                break
            time.sleep(0.1)
        assert code == "BadOutOfService"
    finally:
        srv.clock = None
        served(srv, HEALTH, KEYS)  # the module's server as the other tests expect it


def test_a_nan_is_never_served_as_good(server):
    srv, _ = server
    nan_est = replace(estimate(), estimate_um=MappingProxyType({"x": -1.5, "y": math.nan, "z": -12.5}))
    w = window(factors={"spindle_speed": math.nan, "z_i_sq": 13.3})
    v = served(srv, replace(HEALTH, last_window=w, estimate=nan_est),
               ("Estimate.y_um", "Estimate.z_um", "Factors.spindle_speed", "Factors.z_i_sq"))
    assert v["Estimate.y_um"][:2] == v["Factors.spindle_speed"][:2] == ("BadNoCommunication", None)
    assert (v["Estimate.z_um"][:2], v["Factors.z_i_sq"][:2]) == (("Good", -12.5), ("Good", 13.3))
    held = replace(estimate(usable=False, reason="window 42 insufficient"),
                   estimate_um=MappingProxyType({"x": -1.5, "y": math.nan, "z": -12.5}), inputs="held",
                   held_factors=MappingProxyType({"spindle_speed": math.nan}))
    v = served(srv, replace(HEALTH, last_window=replace(w, status="insufficient"), estimate=held),
               ("Estimate.y_um", "Estimate.z_um", "Factors.spindle_speed"))
    assert v["Estimate.y_um"][:2] == v["Factors.spindle_speed"][:2] == ("BadNoCommunication", None)  # nor Uncertain
    assert v["Estimate.z_um"][:2] == ("UncertainLastUsableValue", -12.5)


def test_before_the_first_window_every_value_waits_for_initial_data(pki):
    profile = load_profile(PROFILES / "sim-vmc.toml")
    model = load_model(PROFILES / "sim-vmc.model.toml")
    srv = OpcUaServer(settings(pki, writable=False), profile=profile, model=model).start()
    try:
        v = served(srv, Health(machine="sim-vmc", clock_s=0.0), ("Estimate.z_um", "Factors.x_feed",
                                                                 "Compensation.Commanded.z_um"))
        assert {s for s, _, _ in v.values()} == {"BadWaitingForInitialData"}
        assert {x for _, x, _ in v.values()} == {None}
    finally:
        srv.stop()
