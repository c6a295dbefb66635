"""What every simulated Modbus device shares: transports, fault hooks, lifecycle.

A device is a pymodbus 3.x server built from a :class:`pymodbus.simulator.SimDevice` whose ``action``
callback is the device's request handler: pymodbus calls it on every access with the register block, and
the device fills in live values, or checks a write and answers with an exception code. The fault hooks
sit in pymodbus's ``trace_pdu``/``trace_packet`` callbacks, so every fault is one a real client sees on the
wire.

Transports:

- :class:`TcpTransport`: Modbus TCP on a loopback address; port 0 picks a free port. The device answers
  any unit id (as most Modbus TCP devices do).
- :class:`RtuTransport`: Modbus RTU on a pseudo-terminal. pymodbus's serial server opens one
  pseudo-terminal; a bridge in the device loop carries the bytes between it and the client's
  pseudo-terminal (a stable link path), adding the line time at the configured baud rate. Requests for
  other device addresses are ignored, as on a shared RS-485 line. Several devices can share one line
  (:class:`RtuBus`): the client's requests reach all of them and each answers its own address.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from pymodbus import FramerType
from pymodbus.pdu import ModbusPDU
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.server.base import ModbusBaseServer
from pymodbus.simulator import SimDevice

from gateway.errors import ServeError
from simulators.devices.faults import Faults
from simulators.devices.runtime import LineTime, LineWriter, PtyPort, call_in_loop, check_loopback

log = logging.getLogger(__name__)

#: function codes that only read: the reply delay is added once per request, on these or on the write
READ_CODES = frozenset({1, 2, 3, 4})


@dataclass(frozen=True, kw_only=True)
class TcpTransport:
    """Modbus TCP on ``host`` (loopback only) and ``port`` (0: any free port)."""

    host: str = "127.0.0.1"
    port: int = 0

    def __post_init__(self) -> None:
        check_loopback(self.host)
        if not 0 <= self.port <= 65535:
            raise ValueError(f"port must be in 0..65535. Got {self.port!r}")


@dataclass(frozen=True, kw_only=True)
class RtuTransport:
    """Modbus RTU on a pseudo-terminal at ``baudrate`` (8N1: 10 bits a byte on the line)."""

    baudrate: int = 115200
    simulate_line_time: bool = True

    def __post_init__(self) -> None:
        LineTime(baudrate=self.baudrate)  # checks the rate


class RtuBus:
    """One RS-485 line: the port clients open (a stable link path) and the RTU devices on it.

    What a client writes reaches every device on the line, each through its own line-time bridge; each
    answers only requests for its own address, and every answer crosses the one line back. A device given
    a plain link path gets a line of its own. Lives in the device loop; the port opens when the first
    device joins and closes when the last one leaves.
    """

    def __init__(self, link_path: Path, transport: RtuTransport) -> None:
        self.link_path = Path(link_path)
        self.transport = transport
        self._members: list[Callable[[bytes], None]] = []
        self._client: PtyPort | None = None
        self._to_client: LineWriter | None = None

    @property
    def line(self) -> LineTime | None:
        t = self.transport
        return LineTime(baudrate=t.baudrate) if t.simulate_line_time else None

    @property
    def client_pty(self) -> PtyPort | None:
        """The clients' side of the line (``None`` while no device is on it)."""
        return self._client

    def join(self, loop: asyncio.AbstractEventLoop, to_device: Callable[[bytes], None]) -> Callable[[bytes], None]:
        """Put a device on the line: ``to_device`` gets what clients write; returns where its answers go."""
        if self._client is None:
            self._client = PtyPort(self.link_path)
            self._to_client = LineWriter(loop, self._client, self.line)
            self._client.attach(loop, self._from_client)
        self._members.append(to_device)
        assert self._to_client is not None
        return self._to_client.send

    def leave(self, to_device: Callable[[bytes], None]) -> None:
        """Take a device off the line; the last one closes the port."""
        if to_device in self._members:
            self._members.remove(to_device)
        if not self._members and self._client is not None:
            self._client.close()
            self._client = self._to_client = None

    def _from_client(self, data: bytes) -> None:
        for send in list(self._members):
            send(data)


class ModbusDevice:
    """Base of the simulated Modbus devices: one pymodbus server, its transport and its faults.

    Subclasses build the :class:`SimDevice` (:meth:`_sim_device`) and handle requests in its action.
    Call :meth:`start`/:meth:`stop` from the device loop; :meth:`disconnect_clients` from any thread.
    """

    kind = "modbus device"

    def __init__(self, *, name: str, transport: TcpTransport | RtuTransport, device_id: int,
                 serial_link: Path | RtuBus | None = None, faults: Faults | None = None) -> None:
        self._bus: RtuBus | None = None
        if isinstance(transport, RtuTransport):
            if serial_link is None:
                raise ValueError(f"{name}: a Modbus RTU device needs serial_link (the path clients open, or an "
                                 "RtuBus shared with other devices)")
            self._bus = serial_link if isinstance(serial_link, RtuBus) else RtuBus(serial_link, transport)
            if self._bus.transport != transport:
                raise ValueError(f"{name}: its transport {transport} differs from its line's {self._bus.transport}")
        self.name = name
        self.transport = transport
        self.device_id = device_id
        self.faults = faults if faults is not None else Faults()
        self._server: ModbusBaseServer | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server_pty: PtyPort | None = None
        self._to_server: Callable[[bytes], None] | None = None  # while on its line
        self._bound: tuple[str, int] | None = None

    # -- what subclasses provide ------------------------------------------------------------------------
    def _sim_device(self) -> SimDevice:
        raise NotImplementedError

    async def _started(self) -> None:
        """Hook: the server is up (e.g. start a periodic task)."""

    async def _stopping(self) -> None:
        """Hook: the server is about to stop."""

    # -- where clients find the device ------------------------------------------------------------------
    @property
    def address(self) -> tuple[str, int]:
        """``(host, port)`` of a TCP device."""
        if self._bound is None:
            raise RuntimeError(f"{self.name}: not a running TCP device")
        return self._bound

    @property
    def serial_port(self) -> str:
        """The path an RTU client opens (a stable link to the current pseudo-terminal)."""
        client = self._client_pty
        if client is None:
            raise RuntimeError(f"{self.name}: not a running RTU device")
        return client.path

    @property
    def _client_pty(self) -> PtyPort | None:
        return self._bus.client_pty if self._bus is not None and self._to_server is not None else None

    @property
    def endpoint(self) -> str:
        """Where clients find the device, for people: ``modbus-tcp://127.0.0.1:5020`` or ``modbus-rtu:...``."""
        if self._bound is not None:
            return f"modbus-tcp://{self._bound[0]}:{self._bound[1]} (unit id any)"
        client = self._client_pty
        if client is not None and isinstance(self.transport, RtuTransport):
            return (f"modbus-rtu:{client.path} (device id {self.device_id}, "
                    f"{self.transport.baudrate} baud 8N1)")
        return "not running"

    # -- lifecycle --------------------------------------------------------------------------------------
    async def start(self) -> None:
        """Start serving (in the device loop)."""
        self._loop = asyncio.get_running_loop()
        common = {"trace_packet": self._trace_packet, "trace_pdu": self._trace_pdu}
        if isinstance(self.transport, TcpTransport):
            server: ModbusBaseServer = ModbusTcpServer(
                self._sim_device(), address=(self.transport.host, self.transport.port), **common)
            try:
                await server.serve_forever(background=True)
            except (RuntimeError, OSError) as exc:
                raise ServeError(f"{self.name}: cannot listen on {self.transport.host}:{self.transport.port} "
                                      f"(is the port in use?): {exc}") from None
            sock = server.transport.sockets[0]  # type: ignore[union-attr]
            self._bound = (self.transport.host, int(sock.getsockname()[1]))
        else:
            assert self._bus is not None
            self._server_pty = PtyPort(None)
            self._to_server = LineWriter(self._loop, self._server_pty, self._bus.line).send
            self._server_pty.attach(self._loop, self._bus.join(self._loop, self._to_server))
            server = ModbusSerialServer(
                self._sim_device(), framer=FramerType.RTU, port=self._server_pty.tty_path,
                baudrate=self.transport.baudrate, reconnect_delay=0.1, **common)
            try:
                await server.serve_forever(background=True)
            except (RuntimeError, OSError) as exc:
                path = self._server_pty.tty_path
                self._close_ptys()
                raise ServeError(f"{self.name}: cannot open the pseudo-terminal {path}: {exc}") from None
        self._server = server
        await self._started()
        log.info("%s: serving on %s", self.name, self.endpoint)

    async def stop(self) -> None:
        """Stop serving and close the transport (idempotent)."""
        server, self._server = self._server, None
        if server is None:
            return
        await self._stopping()
        await server.shutdown()
        self._close_ptys()
        self._bound = None

    def _close_ptys(self) -> None:
        if self._bus is not None and self._to_server is not None:
            self._bus.leave(self._to_server)
        if self._server_pty is not None:
            self._server_pty.close()
        self._server_pty = self._to_server = None

    def disconnect_clients(self) -> None:
        """Drop every client (callable from any thread).

        TCP connections are closed; an RTU port is hung up: the client's next read fails as if the adapter
        were unplugged, and reopening the same path works.
        """
        loop = self._loop
        if loop is None or self._server is None:
            raise RuntimeError(f"{self.name}: not running")
        call_in_loop(loop, self._disconnect)

    def _disconnect(self) -> None:
        self.faults.note("disconnected")
        client = self._client_pty
        if client is not None:
            client.hang_up()  # the whole line: every device on it loses the client
            return
        assert self._server is not None
        for conn in list(self._server.active_connections.values()):
            conn.close()

    # -- fault hooks (run in the device loop) -----------------------------------------------------------
    def _trace_pdu(self, sending: bool, pdu: ModbusPDU) -> ModbusPDU | None:
        if sending:
            return pdu
        if isinstance(self.transport, RtuTransport) and pdu.dev_id != self.device_id:
            return None  # another device's request on the shared line: stay silent
        if self.faults.drop_replies:
            self.faults.note("dropped")
            return None  # pymodbus then neither handles nor answers the request
        return pdu

    def _trace_packet(self, sending: bool, data: bytes) -> bytes:
        if not sending or not data:
            return data
        faults = self.faults
        if faults.garbage_replies:
            faults.note("garbage")
            return faults.garbage(len(data))
        if faults.corrupt_replies:
            faults.note("corrupted")
            if isinstance(self.transport, RtuTransport):
                return data[:-1] + bytes([data[-1] ^ 0xFF])  # CRC no longer matches
            return data[:2] + b"\xff\xff" + data[4:]  # MBAP protocol id must be 0
        return data

    async def _reply_delay(self, function_code: int, writing: bool) -> None:
        delay = self.faults.reply_delay_s
        # a write request passes the action twice (write, then read back): delay it once
        if delay > 0 and (writing or function_code in READ_CODES):
            self.faults.note("delayed")
            await asyncio.sleep(delay)
