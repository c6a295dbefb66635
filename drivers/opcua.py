"""CNC signals from the CNC's own OPC UA server (asyncua client): ``driver = "opcua"``.

SINUMERIK, FANUC, Heidenhain and Okuma controls serve spindle speed, drive loads or currents and axis feeds
over OPC UA. Device keys: ``endpoint`` (``opc.tcp://host:4840/...``, required), ``mode`` (``"poll"``: one
Read of every channel's node per tick, the default; ``"subscription"``: the server samples the nodes and
reports changes, each tick takes the latest value), ``username`` (anonymous when absent; the password is
read from the file ``password_file`` names), and the common keys (``period_s``, ``timeout_s``, ...).
Channel keys: ``node_id`` (``"ns=2;s=Spindle.ActSpeed"``; ``nsu=<namespace uri>;...`` is accepted too) or
``browse_path`` (``"Objects/2:CncInterface/2:CncSpindleList/2:Spindle/2:ActSpeed"``: browse names from the
Objects folder, each ``namespace index:name``), and ``scale``/``offset`` (``value = raw * scale + offset``).

Quality: a value with a Good status code is ``GOOD``, Uncertain ``STALE`` and Bad ``BAD`` (not used); a
subscription that has not yet reported a node gives ``BAD``. A node that is not a number is ``BAD``. A
subscription holds the last value of a node that does not change, so a dead link would look like a quiet
machine: when no publish response (data or the server's keep-alive, due every 10 publishing intervals)
came for three keep-alive periods (at least 1 s), the read fails and the runner reconnects (asyncua >= 2.0).

Link budget. An OPC UA server is not a 2 ms device: a CNC updates its OPC UA variables from its own cycle,
commonly every 10 to 100 ms (the nodes' MinimumSamplingInterval says so), and the asyncua client needs
about a millisecond per Read on loopback. :data:`MIN_PERIOD_S` (10 ms) is refused below at profile load,
with what it can do; at start the measured scan (poll mode) or the server's revised sampling intervals
(subscription mode) must fit the period too (:mod:`gateway.linkcheck`).

What coarser sampling does to a mean of squares (the Joule-heat factors): for a current whose ripple is
not locked to the sampling clock, the mean of N samples of ``i**2`` is unbiased; its relative standard error
is ``sqrt(var(i**2)) / mean(i**2) / sqrt(N)``, which for a full-wave rectified ripple ``|A sin wt|`` is
``0.71 / sqrt(N)``: 0.41 % a minute at 2 ms, 0.91 % at 10 ms, 2.9 % at 100 ms (``tests/test_drivers_opcua.py``
checks these figures). A ripple locked to the sampling (a multiple of ``1 / period``: 100 Hz at 10 ms) aliases
to a constant: every sample sees the same phase and the mean of squares can be off by up to +-100 %. Windows
sampled coarser than the profile's fast period say so in their notes, with the figure for their sample count.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

from drivers.base import DeviceOptions, Driver, LinkBudget, Quality, parse_common_options, parse_scaling
from gateway.errors import DeviceTimeout, DriverError

MODES = ("poll", "subscription")
#: the shortest period refused at profile load (see the module docstring)
MIN_PERIOD_S = 0.01


@dataclass(frozen=True, kw_only=True, slots=True)
class OpcUaOptions(DeviceOptions):
    """A CNC's OPC UA server: where, how values are fetched, who we are."""

    endpoint: str
    mode: str = "poll"
    username: str | None = None
    password_file: str | None = None


@dataclass(frozen=True, kw_only=True, slots=True)
class NodeAddress:
    """Where a channel's value is: a node id, or a browse path from the Objects folder; and its scaling."""

    node_id: str | None = None
    browse_path: tuple[str, ...] = ()
    scale: float = 1.0
    offset: float = 0.0

    def describe(self) -> str:
        return f"node {self.node_id}" if self.node_id else "browse path " + "/".join(self.browse_path)


class OpcUaDriver(Driver):
    """Reads numeric nodes from an OPC UA server; see the module docstring.

    The asyncua client runs in an event loop of its own thread (``asyncua.sync.ThreadLoop``); the sampler's
    thread waits for each call with the device's ``timeout_s``.
    """

    kind: ClassVar[str] = "OPC UA"
    measured_link: ClassVar[bool] = True

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self._tloop: Any = None
        self._client: Any = None
        self._nodes: list[Any] = []
        self._latest: list[tuple[float, Quality]] = []
        self._subscription: Any = None
        self._revised_s: float | None = None
        self._stale_s = math.inf  # no publish response (data or keep-alive) for this long: the subscription is dead
        self._subscribed_at = 0.0

    # -- profile -------------------------------------------------------------------------------------------
    @classmethod
    def parse_device_options(cls, table: Any) -> OpcUaOptions | None:
        endpoint = table.str("endpoint", expected='an OPC UA endpoint such as "opc.tcp://10.0.0.7:4840"')
        if endpoint is not None and not endpoint.startswith("opc.tcp://"):
            table.problem("endpoint", f'expected an endpoint starting with "opc.tcp://", got "{endpoint}"')
            endpoint = None
        mode = table.str("mode", default="poll", choices=MODES)
        username = table.str("username", default=None, expected="the user name the server knows the gateway by")
        password_file = table.str("password_file", default=None, expected="a file holding the password")
        common = parse_common_options(table, timeout_s=1.0)
        if password_file is not None:
            from pathlib import Path

            password_file = str(Path(table.doc.path).parent / password_file)  # relative to the profile
            if not Path(password_file).is_file():
                table.problem("password_file", f'file "{password_file}" not found: expected a file holding the '
                                               "password (one line), relative to the profile")
            if username is None:
                table.problem("password_file", "a password needs a user name: set username")
        if None in (endpoint, mode):
            return None
        return OpcUaOptions(endpoint=endpoint, mode=mode, username=username, password_file=password_file, **common)

    @classmethod
    def parse_channel_address(cls, table: Any) -> NodeAddress | None:
        node_id = table.str("node_id", default=None, expected='a node id such as "ns=2;s=Spindle.ActSpeed"')
        path = table.str("browse_path", default=None,
                         expected='browse names from the Objects folder, "Objects/2:Machine/2:Speed"')
        scale, offset = parse_scaling(table, per="unit of the node's value")
        if (node_id is None) == (path is None):
            if "node_id" not in table and "browse_path" not in table:
                table.problem(None, "expected node_id or browse_path (where the value is on the server)")
            elif node_id is not None:
                table.problem("browse_path", "give node_id or browse_path, not both")
            return None
        if node_id is not None:
            try:
                from asyncua import ua

                ua.NodeId.from_string(node_id)
            except Exception:
                table.problem("node_id", f'expected a node id such as "ns=2;s=Spindle.ActSpeed" or "ns=3;i=1001", '
                                         f'got "{node_id}"')
                return None
        parts: tuple[str, ...] = ()
        if path is not None:
            parts = tuple(p for p in path.strip("/").split("/") if p)
            if parts and parts[0] == "Objects":
                parts = parts[1:]
            if not parts:
                table.problem("browse_path", f'expected at least one browse name below Objects, got "{path}"')
                return None
        if scale is None or offset is None:
            return None
        return NodeAddress(node_id=node_id, browse_path=parts, scale=scale, offset=offset)

    @classmethod
    def link_budget(cls, options: OpcUaOptions, addresses: Sequence[NodeAddress]) -> LinkBudget:
        return LinkBudget(
            min_period_s=MIN_PERIOD_S,
            detail=f"OPC UA ({options.mode} of {len(addresses)} node{'s' if len(addresses) != 1 else ''}): a CNC "
                   f"updates its OPC UA variables every 10 ms or slower and the client needs about 1 ms a Read, "
                   f"so {MIN_PERIOD_S * 1000:g} ms is the fastest period taken (checked again against the "
                   "server at start)")

    # -- the link ------------------------------------------------------------------------------------------
    def _post(self, coro: Any) -> Any:
        timeout = self.options.timeout_s
        return self._tloop.post(asyncio.wait_for(coro, timeout))

    def _connect(self) -> None:
        from asyncua import Client
        from asyncua.sync import ThreadLoop

        o: OpcUaOptions = self.options
        self._tloop = ThreadLoop(timeout=o.timeout_s * 4 + 5.0)
        self._tloop.daemon = True
        self._tloop.start()
        client = Client(o.endpoint, timeout=o.timeout_s)
        if o.username is not None:
            client.set_user(o.username)
            if o.password_file is not None:
                with open(o.password_file, encoding="utf-8") as f:
                    client.set_password(f.read().strip("\r\n"))
        self._client = client
        self._post(client.connect())
        self._nodes = [self._post(self._resolve(name, a)) for name, a in zip(self.channel_names, self.addresses,
                                                                            strict=True)]
        self._latest = [(math.nan, Quality.BAD)] * len(self._nodes)
        if o.mode == "subscription":
            self._post(self._subscribe())

    async def _resolve(self, channel: str, a: NodeAddress) -> Any:
        from asyncua import ua

        client = self._client
        try:
            if a.node_id is not None:
                node = client.get_node(a.node_id)
                await node.read_browse_name()  # the node exists
                return node
            return await client.nodes.objects.get_child(list(a.browse_path))
        except ua.UaStatusCodeError as exc:
            raise DriverError(f'device "{self.name}" ({self.kind}): channel {channel}: {a.describe()} not found on '
                              f"{self.options.endpoint}: {exc}") from None

    async def _subscribe(self) -> None:
        from asyncua import ua

        period_ms = (self.options.period_s or MIN_PERIOD_S) * 1000.0
        index = {node.nodeid: i for i, node in enumerate(self._nodes)}
        driver = self

        class Handler:
            def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
                i = index.get(node.nodeid)
                if i is not None:
                    dv = data.monitored_item.Value
                    driver._latest[i] = _decode(dv.Value.Value if dv.Value is not None else None, dv.StatusCode,
                                                driver.addresses[i])

        params = ua.CreateSubscriptionParameters(RequestedPublishingInterval=period_ms, RequestedLifetimeCount=10000,
                                                 RequestedMaxKeepAliveCount=10, MaxNotificationsPerPublish=0,
                                                 PublishingEnabled=True, Priority=0)
        sub = await self._client.create_subscription(params, Handler())
        if not hasattr(sub, "last_publish_at"):  # asyncua < 2: keep-alives cannot be seen, a dead link could not be
            raise DriverError(f'device "{self.name}" ({self.kind}): mode = "subscription" needs asyncua >= 2.0 '
                              '(to see the server\'s keep-alives); use mode = "poll" or upgrade asyncua')
        self._subscription = sub
        self._subscribed_at = time.monotonic()
        await sub.subscribe_data_change(self._nodes, sampling_interval=period_ms, queuesize=1)
        revised_pub = sub.parameters.RequestedPublishingInterval  # asyncua updates it to the revised one
        minimum = [await n.read_attribute(ua.AttributeIds.MinimumSamplingInterval) for n in self._nodes]
        mins = [m.Value.Value for m in minimum if m.Value is not None and m.Value.Value is not None]
        self._revised_s = max([revised_pub, *mins]) / 1000.0
        # the server answers a publish at least every keep-alive count x publishing interval, changes or not
        self._stale_s = max(1.0, 3.0 * params.RequestedMaxKeepAliveCount * revised_pub / 1000.0)

    def _read_raw(self) -> tuple[list[float], list[Quality]]:
        if self.options.mode == "subscription":
            last = getattr(self._subscription, "last_publish_at", None) or self._subscribed_at
            silent = time.monotonic() - last
            if silent > self._stale_s:  # the values held are stale: never hand them on as good
                raise DeviceTimeout(f'device "{self.name}" ({self.kind}): no publish response (data or keep-alive) '
                                    f"from {self.options.endpoint} for {silent:.1f} s (at most {self._stale_s:g} s "
                                    "expected): the subscription is dead")
            values = [v for v, _ in self._latest]
            return values, [q for _, q in self._latest]
        results = self._post(self._read_all())
        out = [_decode(dv.Value.Value if dv.Value is not None else None, dv.StatusCode, a)
               for dv, a in zip(results, self.addresses, strict=True)]
        return [v for v, _ in out], [q for _, q in out]

    async def _read_all(self) -> list[Any]:
        from asyncua import ua

        params = ua.ReadParameters()
        for node in self._nodes:
            rv = ua.ReadValueId()
            rv.NodeId = node.nodeid
            rv.AttributeId = ua.AttributeIds.Value
            params.NodesToRead.append(rv)
        return list(await self._client.uaclient.read(params))

    def _disconnect(self) -> None:
        client, tloop = self._client, self._tloop
        self._client = self._tloop = self._subscription = None
        if client is not None and tloop is not None:
            with contextlib.suppress(Exception):  # closing after an error must never raise
                tloop.post(asyncio.wait_for(client.disconnect(), self.options.timeout_s))
        if tloop is not None:
            tloop.stop()

    def measure_link(self, *, scans: int = 30) -> LinkBudget:
        if self.options.mode != "subscription":
            return super().measure_link(scans=scans)
        revised = self._revised_s or 0.0
        return LinkBudget(min_period_s=revised,
                          detail=f"{self._link_what()}: the server revised the publishing and sampling intervals "
                                 f"to {revised * 1000:g} ms")

    def _link_what(self) -> str:
        return (f"OPC UA {self.options.mode} of {len(self.addresses)} node{'s' if len(self.addresses) != 1 else ''} "
                f"at {self.options.endpoint}")


def _decode(value: Any, status: Any, a: NodeAddress) -> tuple[float, Quality]:
    if status is not None and not status.is_good():
        quality = Quality.STALE if status.is_uncertain() else Quality.BAD
        if quality == Quality.BAD:
            return math.nan, quality
    else:
        quality = Quality.GOOD
    if isinstance(value, bool) or not isinstance(value, int | float):
        return math.nan, Quality.BAD
    x = float(value)
    if not math.isfinite(x):
        return math.nan, Quality.BAD
    return x * a.scale + a.offset, quality
