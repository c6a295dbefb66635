"""A real MQTT broker on loopback for tests, benchmarks and trials: amqtt, in-process, in a thread of its own.

>>> with LocalBroker() as broker:              # doctest: +SKIP
...     print(broker.port)                      # bound to 127.0.0.1, port 0 (any free one)
...     broker.restart()                        # down and up again on the same port (an outage)
...     broker.messages("cncgw/vmc-3/#")        # every PUBLISH the broker received, in arrival order

Not a simulation: amqtt is an MQTT 3.1.1 broker. It keeps no state across :meth:`LocalBroker.restart`
(sessions and retained messages are gone, as with a broker without persistence), so what a client lost in
an outage is what the client did not send again. The ``test`` extra installs amqtt; a plant runs its own
broker (mosquitto, EMQX, HiveMQ).
"""

from __future__ import annotations

import asyncio
import logging
import threading
from dataclasses import dataclass
from typing import Any, ClassVar

from simulators.devices.runtime import check_loopback

START_TIMEOUT_S = 20.0


@dataclass(frozen=True, slots=True)
class Received:
    """One PUBLISH as the broker received it: client, topic, payload, and the broker's receive count."""

    seq: int
    client_id: str
    topic: str
    payload: bytes
    retain: bool


class LocalBroker:
    """See the module docstring. ``record=False`` keeps no copy of the traffic (benchmarks)."""

    def __init__(self, *, host: str = "127.0.0.1", port: int = 0, record: bool = True) -> None:
        self.host = check_loopback(host)
        self.port = port
        self.record = record
        self._received: list[Received] = []
        self._lock = threading.Lock()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._broker: Any = None
        self.starts = 0

    # -- lifecycle (any thread) ---------------------------------------------------------------------------
    def start(self) -> LocalBroker:
        """Start the loop thread (once) and the broker; returns when it listens."""
        if self._thread is None:
            ready = threading.Event()

            def main() -> None:
                self._loop = asyncio.new_event_loop()
                asyncio.set_event_loop(self._loop)
                ready.set()
                self._loop.run_forever()
                self._loop.close()

            self._thread = threading.Thread(target=main, name="cncgw-mqtt-broker", daemon=True)
            self._thread.start()
            ready.wait(START_TIMEOUT_S)
        self._call(self._start())
        return self

    def stop_broker(self) -> None:
        """Stop the broker, keep the loop (an outage: :meth:`start` brings it back on the same port)."""
        if self._broker is not None:
            self._call(self._stop())

    def restart(self) -> None:
        """Stop and start again on the same port."""
        self.stop_broker()
        self.start()

    def stop(self) -> None:
        """Stop the broker and the loop thread (idempotent)."""
        self.stop_broker()
        loop, thread = self._loop, self._thread
        if loop is not None and thread is not None:
            loop.call_soon_threadsafe(loop.stop)
            thread.join(START_TIMEOUT_S)
        self._thread = self._loop = None

    def __enter__(self) -> LocalBroker:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def running(self) -> bool:
        return self._broker is not None

    def messages(self, prefix: str = "") -> list[Received]:
        """What the broker received whose topic starts with ``prefix`` (``#`` at the end is ignored)."""
        prefix = prefix.rstrip("#")
        with self._lock:
            return [m for m in self._received if m.topic.startswith(prefix)]

    # -- the loop's side ----------------------------------------------------------------------------------
    def _call(self, coro: Any) -> Any:
        assert self._loop is not None
        return asyncio.run_coroutine_threadsafe(coro, self._loop).result(START_TIMEOUT_S)

    async def _start(self) -> None:
        from amqtt.broker import Broker

        plugins: dict[str, Any] = {"amqtt.plugins.authentication.AnonymousAuthPlugin": {"allow_anonymous": True}}
        if self.record:
            plugins[f"{__name__}.RecorderPlugin"] = {}
        config = {"listeners": {"default": {"type": "tcp", "bind": f"{self.host}:{self.port}"}},
                  "plugins": plugins}
        RecorderPlugin.pending = self
        broker = Broker(config, loop=asyncio.get_running_loop())
        await broker.start()
        server = broker._servers["default"].instance  # the listening asyncio server: the port really bound
        self.port = server.sockets[0].getsockname()[1]
        self._broker = broker
        self.starts += 1

    async def _stop(self) -> None:
        broker, self._broker = self._broker, None
        await broker.shutdown()

    def _note(self, client_id: str, message: Any) -> None:
        if message is None:
            return
        with self._lock:
            self._received.append(Received(seq=len(self._received), client_id=client_id, topic=message.topic,
                                           payload=bytes(message.data), retain=bool(getattr(message, "retain", 0))))


def _plugin_base() -> type:
    from amqtt.plugins.base import BasePlugin

    return BasePlugin


class RecorderPlugin(_plugin_base()):  # type: ignore[misc]
    """amqtt plugin: hands every PUBLISH the broker receives to the :class:`LocalBroker` that started it."""

    pending: ClassVar[LocalBroker | None] = None

    def __init__(self, context: Any) -> None:
        super().__init__(context)
        self.owner = RecorderPlugin.pending

    async def on_broker_message_received(self, *, client_id: str, message: Any) -> None:
        if self.owner is not None:
            self.owner._note(client_id, message)


logging.getLogger("amqtt").setLevel(logging.WARNING)
logging.getLogger("transitions").setLevel(logging.WARNING)
