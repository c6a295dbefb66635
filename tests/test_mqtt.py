"""The MQTT output against a real broker (amqtt, in-process) on 127.0.0.1, port 0: payloads, birth and will,
store-and-forward through a broker restart and a gateway restart, and the ``[mqtt]`` profile section."""

from __future__ import annotations

import json
import math
import time
from types import MappingProxyType

import pytest
from tests_paths import PROFILES

from gateway.errors import ProfileError
from gateway.live.outputs import WindowSnapshot
from gateway.live.outputs.mqtt import MqttOutput
from gateway.live.outputs.outbox import OUTBOX_NAME, Outbox
from gateway.profile import load_profile
from gateway.profile.mqtt import Mqtt
from simulators.mqtt_broker import LocalBroker

WINDOW_S = 60.0
KINDS = ("estimate", "offsets", "factors", "health")


@pytest.fixture
def broker():
    with LocalBroker() as b:
        yield b


def snap(k: int, **kw) -> WindowSnapshot:
    base = dict(machine="vmc-3", window=k, end_s=(k + 1) * WINDOW_S, status="good", coverage=0.999,
                samples_taken=29990, samples_expected=30000, missed_ticks=10,
                factors=MappingProxyType({"spindle_speed": 1000.0 + k, "spindle_i1_sq": 40.5}),
                factor_units=MappingProxyType({"spindle_speed": "rpm", "spindle_i1_sq": "A^2"}),
                estimate_um=MappingProxyType({"x": 0.5, "y": -0.25, "z": -14.0 - k}), usable=True, mode="write",
                commanded_um=MappingProxyType({"z": 14.0 + k}), applied_um=MappingProxyType({"z": 14.0 + k}),
                verified=True, writes=k)
    base.update(kw)
    return WindowSnapshot(**base)


def output(broker, tmp_path, **kw) -> MqttOutput:
    kw = {"reconnect_min_s": 0.2, "reconnect_max_s": 0.5, **kw}
    settings = Mqtt(enabled=True, host="127.0.0.1", port=broker.port, **kw)
    return MqttOutput(settings, machine="vmc-3", data_dir=tmp_path, window_s=WINDOW_S,
                      factor_units={"spindle_speed": "rpm", "spindle_i1_sq": "A^2"})


def wait_for(predicate, timeout_s=20.0, what="condition"):
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out waiting for {what}")
        time.sleep(0.02)


def windows_received(broker, kind):
    return [json.loads(m.payload)["window"] for m in broker.messages(f"cncgw/vmc-3/{kind}")]


def test_payloads_carry_units_quality_and_the_window_id(broker, tmp_path):
    with output(broker, tmp_path) as out:
        out.window(snap(7))
        nan_estimate = dict(snap(8).estimate_um, y=math.nan)
        out.window(snap(8, estimate_um=MappingProxyType(nan_estimate)))
        out.window(snap(9, status="insufficient", usable=False, reason="window 9 insufficient",
                        factors=MappingProxyType({"spindle_speed": math.nan, "spindle_i1_sq": 12.0})))
        wait_for(lambda: out.status().delivered_through == 9, what="3 windows acknowledged")
    got = {(m.topic, json.loads(m.payload)["window"]): json.loads(m.payload)
           for m in broker.messages("cncgw/vmc-3/") if not m.topic.endswith("status")}
    est = got[("cncgw/vmc-3/estimate", 7)]
    assert est["unit"] == "um"
    assert est["values"]["z"] == {"value": -21.0, "quality": "good"}
    assert est["usable"] is True
    assert got[("cncgw/vmc-3/factors", 7)]["values"]["spindle_speed"] == {"value": 1007.0, "quality": "good",
                                                                           "unit": "rpm"}
    assert got[("cncgw/vmc-3/offsets", 7)]["applied"]["z"] == {"value": 21.0, "quality": "good"}
    # a NaN is never a number, and never good
    assert got[("cncgw/vmc-3/estimate", 8)]["values"]["y"] == {"value": None, "quality": "bad"}
    # an insufficient window: nothing in it is good
    assert got[("cncgw/vmc-3/estimate", 9)]["values"]["z"]["quality"] == "uncertain"
    assert got[("cncgw/vmc-3/estimate", 9)]["usable"] is False
    assert got[("cncgw/vmc-3/factors", 9)]["values"]["spindle_speed"] == {"value": None, "quality": "bad",
                                                                           "unit": "rpm"}
    assert got[("cncgw/vmc-3/factors", 9)]["values"]["spindle_i1_sq"]["quality"] == "uncertain"
    assert got[("cncgw/vmc-3/health", 9)]["quality"] == "bad"
    # a clean stop says so: the goodbye is acknowledged before stop() returns, but the broker files what it
    # received on its own loop, which on a loaded PC can come a moment after its acknowledgement
    wait_for(lambda: json.loads(broker.messages("cncgw/vmc-3/status")[-1].payload)["state"] == "offline",
             timeout_s=5.0, what="the clean goodbye at the broker")
    status = [json.loads(m.payload) for m in broker.messages("cncgw/vmc-3/status")]
    assert status[0]["state"] == "online"  # birth
    assert status[0]["units"]["spindle_speed"] == "rpm"
    assert status[-1] == {"state": "offline", "clean": True, "machine": "vmc-3"}
    assert all(m.retain for m in broker.messages("cncgw/vmc-3/status"))


def test_a_broker_restart_loses_nothing_and_the_backlog_arrives_in_order(broker, tmp_path):
    with output(broker, tmp_path, backlog_windows_per_s=50.0) as out:
        for k in range(5):
            out.window(snap(k))
        wait_for(lambda: out.status().delivered_through == 4, what="windows 0-4 acknowledged")
        broker.stop_broker()  # the outage: windows 5-24 close while the broker is away
        wait_for(lambda: not out.status().connected, what="the output to notice")
        for k in range(5, 25):
            out.window(snap(k))
        time.sleep(0.3)
        assert out.status().pending_windows == 20
        broker.start()  # back on the same port, empty
        wait_for(lambda: out.status().delivered_through == 24, what="the backlog acknowledged")
        for k in range(25, 28):  # live again
            out.window(snap(k))
        wait_for(lambda: out.status().delivered_through == 27, what="live windows acknowledged")
        assert out.status().connects == 2
    for kind in KINDS:
        got = windows_received(broker, kind)
        first_seen = list(dict.fromkeys(got))  # a consumer drops QoS 1 re-deliveries by window id
        assert first_seen == list(range(28)), kind
    assert out.delivered == list(range(28))


def test_a_gateway_restart_resumes_after_the_last_window_the_broker_acknowledged(broker, tmp_path):
    with output(broker, tmp_path) as out:
        for k in range(3):
            out.window(snap(k))
        wait_for(lambda: out.status().delivered_through == 2, what="windows 0-2")
        broker.stop_broker()
        wait_for(lambda: not out.status().connected, what="the output to notice")
        for k in range(3, 6):
            out.window(snap(k))
    outbox = Outbox(tmp_path / OUTBOX_NAME, machine="vmc-3")
    assert outbox.acked_through == 2  # persisted
    assert outbox.pending() == 3
    outbox.close()
    broker.start()
    with output(broker, tmp_path) as out:  # a new process: the outbox is all it knows
        out.window(snap(6))
        wait_for(lambda: out.status().delivered_through == 6, what="windows 3-6 after the restart")
    assert list(dict.fromkeys(windows_received(broker, "estimate"))) == list(range(7))


def test_the_last_will_says_offline_when_the_gateway_vanishes(broker, tmp_path):
    import paho.mqtt.client as paho

    seen = []
    sub = paho.Client(callback_api_version=paho.CallbackAPIVersion.VERSION2, client_id="historian")
    sub.on_message = lambda c, u, m: seen.append(json.loads(m.payload))
    sub.connect("127.0.0.1", broker.port)
    sub.subscribe("cncgw/+/status", qos=1)
    sub.loop_start()
    out = output(broker, tmp_path, reconnect_min_s=30.0, reconnect_max_s=30.0).start()
    try:
        wait_for(lambda: any(p["state"] == "online" for p in seen), what="the birth message")
        out._client._sock.close()  # a vanished gateway: its connection ends without DISCONNECT
        wait_for(lambda: any(p["state"] == "offline" for p in seen), what="the will")
        assert seen[-1] == {"state": "offline", "clean": False, "machine": "vmc-3"}
    finally:
        out.stop()
        sub.disconnect()
        sub.loop_stop()


def test_the_mqtt_section_is_checked_like_the_rest_of_the_profile(tmp_path):
    text = (PROFILES / "sim-vmc.toml").read_text()
    bad = tmp_path / "bad.toml"
    bad.write_text(text + '\n[mqtt]\nenabled = true\nport = 70000\ntopic_prefix = "plant/#"\n'
                   'password_file = "nope.txt"\nca_file = "ca.pem"\nqos = 2\n')
    with pytest.raises(ProfileError) as err:
        load_profile(bad)
    problems = err.value.problems
    at = len(text.splitlines()) + 2  # the [mqtt] line
    assert f"{bad}:{at + 2}: mqtt.port: expected an integer in [1, 65535], got 70000 (an integer)" in problems
    assert (f'{bad}:{at + 3}: mqtt.topic_prefix: expected topic levels separated by /, without wildcards (+, #) or '
            'empty levels, got "plant/#" (a string)') in problems
    assert any(p.startswith(f"{bad}:{at + 6}: mqtt.qos: unknown key") for p in problems)
    assert (f'{bad}:{at + 4}: mqtt.password_file: file "{tmp_path / "nope.txt"}" not found: expected a file holding '
            "the password (one line), readable by the gateway only, relative to the profile") in problems
    assert f"{bad}:{at}: mqtt.host: mqtt.enabled = true needs the broker's address: set mqtt.host" in problems
    assert f"{bad}:{at + 4}: mqtt.password_file: a password needs a user name: set mqtt.username" in problems
    assert (f"{bad}:{at + 5}: mqtt.ca_file: ca_file given but mqtt.tls is false: set tls = true to use them"
            in problems)
    good = tmp_path / "good.toml"
    (tmp_path / "pw").write_text("s3cret\n")
    (tmp_path / "ca.pem").write_text("-----BEGIN CERTIFICATE-----\n")
    good.write_text(text + '\n[mqtt]\nenabled = true\nhost = "broker.plant"\ntls = true\nca_file = "ca.pem"\n'
                    'username = "vmc3"\npassword_file = "pw"\n')
    m = load_profile(good).mqtt
    assert (m.enabled, m.host, m.port, m.tls, m.ca_file, m.username) == (True, "broker.plant", 8883, True,
                                                                         tmp_path / "ca.pem", "vmc3")
    assert load_profile(PROFILES / "sim-vmc.toml").mqtt.enabled is False


def test_the_live_gateway_publishes_every_window_beside_opc_ua(broker, tmp_path):
    """Stepped run of the simulated machine behind its ADC board and CNC: each window's four messages arrive."""
    from gateway.clock import ManualClock
    from gateway.commands._common import load_model_for
    from gateway.live.runtime import LiveGateway
    from simulators.closed_loop import live_profile
    from simulators.devices import DeviceSetConfig, serve
    from simulators.machine import LiveMachine

    clock = ManualClock(3600.0)  # the spindle starts in the second hour of spindle-feeds
    machine = LiveMachine("spindle-feeds", clock=clock)
    with serve(machine, clock, DeviceSetConfig(adc_rtu=None, can=None, dcon=None)) as devices:
        path = live_profile(devices, tmp_path / "p.toml", period_s=0.73, opcua_port=None, heartbeat_period_s=1.6,
                            max_step_um=5.0)
        path.write_text(path.read_text() + f'\n[mqtt]\nenabled = true\nhost = "127.0.0.1"\nport = {broker.port}\n'
                                           'topic_prefix = "plant1/cncgw"\n')
        profile = load_profile(path)
        model, _ = load_model_for(profile, None)
        with LiveGateway(profile, model=model, data_dir=tmp_path / "data", clock=clock) as gw:
            gw.run_stepped(3600.0 + 5 * 60.0)
            out = gw.outputs[0]
            wait_for(lambda: out.status().delivered_through == 64, what="windows 60-64")
    name = profile.name
    factors = [json.loads(m.payload) for m in broker.messages(f"plant1/cncgw/{name}/factors")]
    assert [f["window"] for f in factors] == [60, 61, 62, 63, 64]
    last = factors[-1]["values"]
    assert last["spindle_speed"]["unit"] == "rpm"
    assert last["spindle_speed"]["quality"] == "good"
    assert 100.0 < last["spindle_speed"]["value"] < 5000.0  # the spindle runs in that hour
    estimates = [json.loads(m.payload) for m in broker.messages(f"plant1/cncgw/{name}/estimate")]
    assert [e["window"] for e in estimates] == [60, 61, 62, 63, 64]
    assert all(math.isfinite(v["value"]) for v in estimates[-1]["values"].values())
    offsets = json.loads(broker.messages(f"plant1/cncgw/{name}/offsets")[-1].payload)
    assert offsets["mode"] == "write"
    assert set(offsets["commanded"]) == {"x", "y", "z"}


def test_the_outbox_is_readable_by_the_gateway_only(broker, tmp_path):
    data = tmp_path / "data"
    with output(broker, data) as out:
        out.window(snap(1))
        wait_for(lambda: out.status().delivered_through == 1, what="window 1")
    assert (data / OUTBOX_NAME).stat().st_mode & 0o777 == 0o600
    assert data.stat().st_mode & 0o777 == 0o700


def test_a_broker_down_at_start_gets_every_window_once_it_is_up(broker, tmp_path):
    broker.stop_broker()
    with output(broker, tmp_path) as out:
        for k in range(4):
            out.window(snap(k, status="rejected", usable=False, window_reason="channel spindle_i1 saturated"))
        time.sleep(0.5)
        assert not out.status().connected
        broker.start()
        wait_for(lambda: out.status().delivered_through == 3, what="windows 0-3")
    health = [json.loads(m.payload) for m in broker.messages("cncgw/vmc-3/health")]
    assert [h["window"] for h in health] == [0, 1, 2, 3]
    assert health[0]["reason"] == "channel spindle_i1 saturated"
    assert health[0]["quality"] == "bad"
    est = json.loads(broker.messages("cncgw/vmc-3/estimate")[0].payload)
    assert est["values"]["z"]["quality"] == "uncertain"  # a rejected window's estimate is never good
