"""The MQTT output (paho-mqtt 2.x): per window, estimates, offsets, factors and health at QoS 1, store-and-forward.

Topics, for machine ``M`` and ``[mqtt] topic_prefix`` ``P`` (payloads: :mod:`gateway.live.outputs.payloads`)::

    P/M/estimate   P/M/offsets   P/M/factors   P/M/health     one message each per window, QoS 1
    P/M/status     retained: {"state": "online", ...} on connect (birth); the broker publishes
                   {"state": "offline", "clean": false} if the gateway vanishes (last will); a clean stop
                   publishes {"state": "offline", "clean": true}

Store and forward: :meth:`MqttOutput.window` (the closer's thread) commits the window's four messages to
the :class:`~gateway.live.outputs.outbox.Outbox` and returns; the output's sender thread hands stored windows to
paho in window order while the broker is connected, at most ``max_inflight_windows`` unacknowledged and at
most ``backlog_windows_per_s`` a second (a token bucket: a backlog after an outage drains at that rate,
while live windows, one a minute, never wait). A window counts as delivered once the broker acknowledged
all its messages (PUBACK); the outbox persists the last window delivered in order. While the broker is
away nothing new is handed over; paho re-sends what was in flight (DUP) when it reconnects. On start, a
window the records store has and the outbox lacks (the gateway stopped between the two commits) is
taken from the store: factors and quality, without the estimate of that moment (``source = "records"``).

TLS (``tls = true``, ``ca_file``, and ``cert_file``/``key_file`` for client certificates) and credentials
(``username``, the password read from ``password_file``) come from the profile's ``[mqtt]`` section.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from gateway import __version__
from gateway.live.outputs import WindowSnapshot, record_snapshot
from gateway.live.outputs.outbox import OUTBOX_NAME, Message, Outbox
from gateway.live.outputs.payloads import encode, window_payloads
from gateway.profile.mqtt import Mqtt

log = logging.getLogger(__name__)

QOS = 1
STOP_TIMEOUT_S = 5.0


@dataclass(frozen=True, kw_only=True, slots=True)
class MqttStatus:
    """The output's state: connected, windows stored / delivered in order / pending, reconnects."""

    connected: bool
    stored_through: int | None
    delivered_through: int | None
    pending_windows: int
    connects: int
    disconnects: int
    messages_sent: int


class MqttOutput:
    """See the module docstring.

    Args:
        settings: the profile's ``[mqtt]``.
        machine: the machine's name (topics, client id).
        data_dir: where the outbox lives (the gateway's data directory).
        window_s: the window length (the birth message says it).
        factor_units: factor -> unit (the birth message lists them).
        store: the records store, to take windows the outbox missed (``None``: none).
        profile: needed with ``store`` to rebuild snapshots from records.

    """

    name = "mqtt"

    def __init__(self, settings: Mqtt, *, machine: str, data_dir: str | Path, window_s: float,
                 factor_units: dict[str, str] | None = None, store: Any = None, profile: Any = None) -> None:
        self.settings = settings
        self.machine = machine
        self.data_dir = Path(data_dir)
        self.window_s = window_s
        self.factor_units = dict(factor_units or {})
        self._store = store
        self._profile = profile
        self.outbox: Outbox | None = None
        self._client: Any = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._acks: queue.SimpleQueue[int] = queue.SimpleQueue()
        self._connected = threading.Event()
        self._mids: dict[int, int | None] = {}  # paho message id -> window (None: a status message)
        self._open: dict[int, int] = {}  # window -> messages not yet acknowledged
        self._order: deque[int] = deque()  # windows handed to paho, in order
        self._sent_through: int | None = None
        self._tokens = float(settings.max_inflight_windows)
        self._last_refill = time.monotonic()
        self._idle_s = 0.1  # how long the sender sleeps when nothing wakes it
        self.connects = self.disconnects = self.messages_sent = 0
        self.delivered: list[int] = []  # windows delivered, in order, since start (tests and benchmarks)

    # -- lifecycle ----------------------------------------------------------------------------------------
    def start(self) -> MqttOutput:
        """Open the outbox (taking windows the records store has and it lacks), connect in the background."""
        import paho.mqtt.client as paho

        s = self.settings
        from gateway.record_store import private_dir

        private_dir(self.data_dir)
        self.outbox = Outbox(self.data_dir / OUTBOX_NAME, machine=self.machine)
        self._catch_up_from_store()
        self._sent_through = self.outbox.acked_through
        client = paho.Client(callback_api_version=paho.CallbackAPIVersion.VERSION2,
                             client_id=s.client_id or f"cncgw-{self.machine}", clean_session=True,
                             protocol=paho.MQTTv311)
        # paho's own logger is left off: it logs every failed reconnect; _on_disconnect says it once
        client.max_inflight_messages_set(4 * s.max_inflight_windows + 4)
        client.reconnect_delay_set(min_delay=s.reconnect_min_s, max_delay=s.reconnect_max_s)  # type: ignore[arg-type]
        client.will_set(s.topic(self.machine, "status"), encode({"state": "offline", "clean": False,
                                                                  "machine": self.machine}), qos=QOS, retain=True)
        if s.username is not None:
            password = None
            if s.password_file is not None:
                password = s.password_file.read_text(encoding="utf-8").strip("\r\n")
            client.username_pw_set(s.username, password)
        if s.tls:
            client.tls_set(ca_certs=str(s.ca_file) if s.ca_file else None,
                           certfile=str(s.cert_file) if s.cert_file else None,
                           keyfile=str(s.key_file) if s.key_file else None)
        client.on_connect = self._on_connect
        client.on_disconnect = self._on_disconnect
        client.on_publish = self._on_publish
        self._client = client
        client.connect_async(s.host, s.port, keepalive=s.keepalive_s)
        client.loop_start()
        self._thread = threading.Thread(target=self._run, name=f"cncgw-mqtt-{self.machine}", daemon=True)
        self._thread.start()
        log.info("MQTT: publishing %s/%s/* to %s:%d%s; %d window(s) waiting", s.topic_prefix, self.machine, s.host,
                 s.port, " (TLS)" if s.tls else "", self.outbox.pending())
        return self

    def stop(self) -> None:
        """Stop sending, say a clean goodbye if connected, disconnect (idempotent). Unsent windows stay stored."""
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(STOP_TIMEOUT_S)
            self._thread = None
        client, self._client = self._client, None
        if client is not None:
            if self._connected.is_set():
                with contextlib.suppress(Exception):
                    info = client.publish(self.settings.topic(self.machine, "status"),
                                          encode({"state": "offline", "clean": True, "machine": self.machine}),
                                          qos=QOS, retain=True)
                    info.wait_for_publish(timeout=STOP_TIMEOUT_S)  # a loaded PC: the goodbye is worth seconds
            client.disconnect()
            client.loop_stop()
        self._drain_acks()
        if self.outbox is not None:
            self.outbox.close()
            self.outbox = None

    def __enter__(self) -> MqttOutput:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- the closer's call ----------------------------------------------------------------------------------
    def window(self, snapshot: WindowSnapshot) -> None:
        """Commit one window's messages to the outbox and wake the sender (cheap; no network here)."""
        assert self.outbox is not None, "start() the output first"
        self.outbox.append(snapshot.window, snapshot.end_s, self._messages(snapshot))
        self._wake.set()

    def _messages(self, snapshot: WindowSnapshot) -> list[Message]:
        return [(self.settings.topic(self.machine, kind), encode(p)) for kind, p in window_payloads(snapshot)]

    def status(self) -> MqttStatus:
        ob = self.outbox
        return MqttStatus(connected=self._connected.is_set(), stored_through=None if ob is None else ob.last_window,
                          delivered_through=None if ob is None else ob.acked_through,
                          pending_windows=0 if ob is None else ob.pending(), connects=self.connects,
                          disconnects=self.disconnects, messages_sent=self.messages_sent)

    # -- paho's thread ------------------------------------------------------------------------------------
    def _on_connect(self, client: Any, userdata: Any, flags: Any, reason_code: Any, properties: Any) -> None:
        if reason_code.is_failure:
            log.error("MQTT: broker %s:%d refused the connection: %s", self.settings.host, self.settings.port,
                      reason_code)
            return
        self.connects += 1
        log.info("MQTT: connected to %s:%d", self.settings.host, self.settings.port)
        birth = {"state": "online", "machine": self.machine, "version": __version__, "since_s": time.time(),
                 "window_s": self.window_s, "units": {"estimate": "um", "offsets": "um", **self.factor_units},
                 "schema": "cncgw.window/1"}
        client.publish(self.settings.topic(self.machine, "status"), encode(birth), qos=QOS, retain=True)
        self._connected.set()
        self._wake.set()

    def _on_disconnect(self, client: Any, userdata: Any, flags: Any, reason_code: Any, properties: Any) -> None:
        if self._connected.is_set():
            self.disconnects += 1
            if not self._stop.is_set():
                log.warning("MQTT: lost the broker (%s); windows are kept and sent when it is back", reason_code)
        self._connected.clear()

    def _on_publish(self, client: Any, userdata: Any, mid: int, reason_code: Any, properties: Any) -> None:
        # paho may call this holding its own lock: only hand the id over, the sender thread does the rest
        self._acks.put(mid)
        self._wake.set()

    # -- the sender thread --------------------------------------------------------------------------------
    def _run(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(self._idle_s)
            self._wake.clear()
            self._idle_s = 0.1
            try:
                self._drain_acks()
                if self._connected.is_set():
                    self._send()
            except Exception:  # never let the sender die: the outbox keeps everything for the next round
                log.exception("MQTT: sender error")
                time.sleep(0.5)

    def _send(self) -> None:
        assert self.outbox is not None
        s = self.settings
        now = time.monotonic()
        self._tokens = min(float(s.max_inflight_windows),
                           self._tokens + (now - self._last_refill) * s.backlog_windows_per_s)
        self._last_refill = now
        room = min(s.max_inflight_windows - len(self._open), int(self._tokens))
        if room <= 0:
            if len(self._open) < s.max_inflight_windows:  # waiting for a token: come back when one is due
                self._idle_s = min(0.1, max(0.001, (1.0 - self._tokens) / s.backlog_windows_per_s))
            return
        client = self._client
        for window, messages in self.outbox.after(self._sent_through, room):
            if not self._connected.is_set() or client is None:
                return
            self._open[window] = len(messages)
            self._order.append(window)
            for topic, payload in messages:
                info = client.publish(topic, payload, qos=QOS)
                self._mids[info.mid] = window
                self.messages_sent += 1
            self._sent_through = window
            self._tokens -= 1.0

    def _drain_acks(self) -> None:
        advanced = None
        while True:
            try:
                mid = self._acks.get_nowait()
            except queue.Empty:
                break
            window = self._mids.pop(mid, None)
            if window is None or window not in self._open:
                continue
            self._open[window] -= 1
            if self._open[window] == 0:
                del self._open[window]
        while self._order and self._order[0] not in self._open:
            advanced = self._order.popleft()
            self.delivered.append(advanced)
        if advanced is not None and self.outbox is not None:
            self.outbox.ack_through(advanced)

    def _catch_up_from_store(self) -> None:
        """Windows the records store has after the outbox's last one (none for a fresh outbox)."""
        ob = self.outbox
        assert ob is not None
        if self._store is None or self._profile is None or ob.fresh or ob.last_window is None:
            return
        n = 0
        for record in self._store.windows(since=ob.last_window + 1):
            ob.append(record.index, record.end_s, self._messages(record_snapshot(self._profile, record)))
            n += 1
        if n:
            log.warning("MQTT: %d window(s) taken from the records store (stored while no output ran)", n)


def describe_payload_sizes(snapshot: WindowSnapshot, settings: Mqtt | None = None) -> dict[str, int]:
    """Bytes of each message of ``snapshot`` on the wire (payload + topic), for sizing a broker."""
    s = settings or Mqtt()
    return {kind: len(encode(p)) + len(s.topic(snapshot.machine, kind))
            for kind, p in window_payloads(snapshot)}


