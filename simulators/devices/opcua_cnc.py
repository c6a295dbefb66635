"""The CNC's own OPC UA server: the machine's signals as a control serves them (umati / OPC 40502-like names).

Address space (namespace ``urn:cncgw:sim-cnc``, index 2 on a fresh server), the drive signals under the
CNC Systems companion specification's folders, each a Double with its EngineeringUnits and a string node id::

    Objects/CncInterface/CncSpindleList/Spindle/ActSpeed          spindle_speed   rpm     ns=2;s=Spindle.ActSpeed
                                               /ActCurrent        spindle_i1      A       ns=2;s=Spindle.ActCurrent
                                               /ActRotorCurrent   spindle_i2      A       (vendor extension)
    Objects/CncInterface/CncAxisList/X/ActSpeed                   x_velocity      mm/min  ns=2;s=X.ActSpeed
                                      /ActCurrent                 x_current       A       ns=2;s=X.ActCurrent
                                     (Y, Z alike)

A control refreshes its OPC UA variables from its own cycle, not per request: an updater task samples the
machine every ``update_period_s`` of wall time (10 ms by default, the nodes' MinimumSamplingInterval) and
writes every node, so a client reading faster sees the same value twice. Faults: ``reply_delay_s`` delays
the updates (values go stale), ``drop_replies`` stops them (the variables keep their last value, as a
control's server does while its PLC task stalls) and ``freeze``/``force`` per channel;
``disconnect_clients()`` closes the clients' sessions.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from dataclasses import dataclass

from gateway.clock import Clock
from simulators.devices.faults import Faults
from simulators.devices.runtime import check_loopback
from simulators.devices.sources import require_channels
from simulators.live import LiveSource

log = logging.getLogger(__name__)

NAMESPACE = "urn:cncgw:sim-cnc"


@dataclass(frozen=True, slots=True)
class CncNode:
    """One served signal: the machine's channel, where it sits (folders below CncInterface), its unit."""

    channel: str
    folder: tuple[str, ...]
    name: str
    unit: str

    @property
    def string_id(self) -> str:
        return f"{self.folder[-1]}.{self.name}"

    def browse_path(self, ns: int) -> str:
        return "/".join(["Objects", f"{ns}:CncInterface", *(f"{ns}:{p}" for p in self.folder), f"{ns}:{self.name}"])


def _drive_nodes() -> tuple[CncNode, ...]:
    spindle = ("CncSpindleList", "Spindle")
    nodes = [CncNode("spindle_speed", spindle, "ActSpeed", "rpm"), CncNode("spindle_i1", spindle, "ActCurrent", "A"),
             CncNode("spindle_i2", spindle, "ActRotorCurrent", "A")]
    for axis in "XYZ":
        where = ("CncAxisList", axis)
        nodes += [CncNode(f"{axis.lower()}_velocity", where, "ActSpeed", "mm/min"),
                  CncNode(f"{axis.lower()}_current", where, "ActCurrent", "A")]
    return tuple(nodes)


DEFAULT_NODES = _drive_nodes()


@dataclass(frozen=True, kw_only=True)
class OpcUaCncConfig:
    """The CNC's OPC UA server: what it serves and how often it refreshes (wall seconds)."""

    nodes: tuple[CncNode, ...] = DEFAULT_NODES
    update_period_s: float = 0.01
    host: str = "127.0.0.1"
    port: int = 0

    def __post_init__(self) -> None:
        check_loopback(self.host)
        if not self.update_period_s > 0:
            raise ValueError(f"update_period_s must be > 0. Got {self.update_period_s!r}")


class OpcUaCnc:
    """A CNC's OPC UA server fed by a :class:`LiveSource` (see the module docstring)."""

    kind = "CNC OPC UA server"

    def __init__(self, *, source: LiveSource, clock: Clock, config: OpcUaCncConfig | None = None,
                 faults: Faults | None = None, name: str = "cnc-opcua") -> None:
        self.config = config or OpcUaCncConfig()
        require_channels(source, [n.channel for n in self.config.nodes], device=name)
        self.name = name
        self.faults = faults or Faults()
        self._source = source
        self._clock = clock
        self._server = None
        self._task: asyncio.Task[None] | None = None
        self._nodes: list[tuple[CncNode, object]] = []
        self.port: int | None = None
        self.ns: int | None = None
        self.updates = 0

    @property
    def endpoint(self) -> str:
        return f"opc.tcp://{self.config.host}:{self.port}/cnc/"

    @property
    def address(self) -> tuple[str, int]:
        assert self.port is not None
        return self.config.host, self.port

    async def start(self) -> None:
        from asyncua import Server, ua

        server = Server()
        await server.init()
        server.set_endpoint(f"opc.tcp://{self.config.host}:{self.config.port}/cnc/")
        server.set_server_name("cncgw simulated CNC")
        server.set_security_policy([ua.SecurityPolicyType.NoSecurity])
        ns = await server.register_namespace(NAMESPACE)
        self.ns = ns
        objects = server.nodes.objects
        folders: dict[tuple[str, ...], object] = {}

        async def folder(path: tuple[str, ...]) -> object:
            if path not in folders:
                parent = objects if len(path) == 1 else await folder(path[:-1])
                folders[path] = await parent.add_folder(ua.NodeId(".".join(path), ns),  # type: ignore[attr-defined]
                                                        ua.QualifiedName(path[-1], ns))
            return folders[path]

        values = self._source.values(self._clock.now())
        for n in self.config.nodes:
            parent = await folder(("CncInterface", *n.folder))
            var = await parent.add_variable(ua.NodeId(n.string_id, ns), ua.QualifiedName(n.name, ns),  # type: ignore[attr-defined]
                                            ua.Variant(float(values[n.channel]), ua.VariantType.Double))
            await var.write_attribute(ua.AttributeIds.MinimumSamplingInterval,
                                      ua.DataValue(ua.Variant(self.config.update_period_s * 1000.0,
                                                              ua.VariantType.Double)))
            eu = ua.EUInformation()
            eu.DisplayName = ua.LocalizedText(n.unit)
            eu.Description = ua.LocalizedText(n.unit)
            prop = await var.add_property(ua.NodeId(f"{n.string_id}.EngineeringUnits", ns),
                                          ua.QualifiedName("EngineeringUnits", 0), eu)
            del prop
            self._nodes.append((n, var))
        await server.start()
        assert server.bserver is not None
        self.port = server.bserver.port
        self._server = server
        self._task = asyncio.get_running_loop().create_task(self._update(), name=f"{self.name}-updater")

    async def _update(self) -> None:
        from asyncua import ua

        period = self.config.update_period_s
        loop = asyncio.get_running_loop()
        server = self._server
        assert server is not None
        deadline = loop.time()
        while True:
            deadline += period
            delay = deadline - loop.time()
            if delay < -period:  # fell behind: skip, never queue
                deadline = loop.time()
            await asyncio.sleep(max(0.0, delay))
            if self.faults.drop_replies:
                continue
            if self.faults.reply_delay_s:
                await asyncio.sleep(self.faults.reply_delay_s)
            values = self.faults.apply(self._source.values(self._clock.now()))
            for n, var in self._nodes:
                await server.write_attribute_value(var.nodeid,  # type: ignore[attr-defined]
                                                   ua.DataValue(ua.Variant(float(values[n.channel]),
                                                                           ua.VariantType.Double)))
            self.updates += 1

    async def stop(self) -> None:
        task, self._task = self._task, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        server, self._server = self._server, None
        if server is not None:
            await server.stop()

    def disconnect_clients(self) -> None:
        server = self._server
        if server is None or server.bserver is None:
            return
        for protocol in list(getattr(server.bserver, "clients", [])):
            with contextlib.suppress(Exception):
                protocol.transport.close()
