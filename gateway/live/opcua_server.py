"""The gateway's OPC UA server (asyncua): factors, estimates, compensation and health, read-only by default.

Bound to 127.0.0.1 unless ``[opcua] host`` says otherwise; security policies from ``[opcua] security``
(``"None"`` alone by default; signed or encrypted policies need ``certificate`` and ``private_key``).
Every variable is read-only, except, when ``[opcua] writable = true``, ``Compensation.HoldRequest``: an
operator (or a cell controller) can ask the writer to hold the offsets, which is always safe.

Who may do what: an anonymous session (offered only with ``allow_anonymous``, by default only when every
policy is ``"None"``) reads and is refused every write (``BadUserAccessDenied``); writing needs an
authenticated session, the profile's ``username`` with the password in ``password_file`` (over an encrypted
channel only), or a client certificate listed in ``user_certificates`` (an X509 user token, or the client's
own certificate on a signed channel). A wrong password is refused at login; a certificate not listed gets
no more than an anonymous session (refused too when anonymous sessions are off).

Address space (namespace ``urn:cncgw``, string node ids, so a client can read ``ns=2;s=Estimate.z_um``):

- ``Machine.Name``; ``Factors.<factor>`` (last window's factor, or the one held over a gap);
- ``Estimate.<axis>_um``, ``Estimate.Window``, ``Estimate.Usable``, ``Estimate.Reason``; with ``[probes]``
  also ``Estimate.<axis>_band95_um`` (the 95 % half-band of the estimate updated by probes);
- ``Compensation.Mode`` (``write``/``dry-run``), ``Compensation.Commanded.<axis>_um``,
  ``Compensation.Applied.<axis>_um`` (last read-back), ``Compensation.LastWriteTimeS``,
  ``Compensation.Verified``, ``Compensation.Writes``, ``Compensation.HoldRequest``;
- ``Health.Alarms`` (one string per active alarm), ``Health.AlarmCount``, ``Health.Devices`` (``name:
  state``), ``Health.SampleRateHz`` (lowest device), ``Health.MissedTicks`` (last window),
  ``Health.GapWindows`` (windows filled by the gap policy), ``Health.UptimeS``;
- the last window's quality: ``Health.WindowIndex``, ``Health.WindowStatus`` (``good``, ``insufficient``,
  ``rejected``), ``Health.WindowQuality`` (one line: coverage, samples, devices in error and their error,
  why it is not good), ``Health.CoveragePct``, ``Health.SamplesTaken``, ``Health.SamplesExpected``.

Factors, estimates, bands, offsets and ``Health.CoveragePct`` are ``AnalogItemType`` (``BaseAnalogType``
without a known range) with ``EngineeringUnits`` (:data:`UNITS`) and ``EURange`` (:meth:`OpcUaServer.ranges`);
their StatusCode comes from the window (:func:`estimate_status`, :func:`factor_status`), their source
timestamp is the window's end. A number that is not finite is never served Good or Uncertain.

The server runs its own asyncio loop in a thread; :meth:`OpcUaServer.publish` (any thread) hands it a
health snapshot, applied by a publisher task. Both tasks run in one ``TaskGroup``; every wait has a timeout.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import logging
import math
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from types import MappingProxyType
from typing import Any

from gateway.clock import Clock
from gateway.errors import GatewayError
from gateway.live.health import Health
from gateway.model import ThermalModel
from gateway.profile import Profile
from gateway.profile.live import OpcUa

log = logging.getLogger(__name__)


class _DropStartError(logging.Filter):
    """asyncua's own "error starting server" record (with a traceback): the caller reports the error."""

    def filter(self, record: logging.LogRecord) -> bool:
        return "error starting server" not in record.getMessage()

NAMESPACE = "urn:cncgw"
START_TIMEOUT_S = 30.0
STOP_TIMEOUT_S = 10.0
#: EUInformation.NamespaceUri of a unit from UNECE Recommendation 20 (OPC 10000-8, 5.6.3)
UNECE_NAMESPACE = "http://www.opcfoundation.org/UA/units/un/cefact"


@dataclass(frozen=True, slots=True)
class Unit:
    """An engineering unit as OPC UA's EUInformation carries it.

    ``code``: the UNECE Rec. 20 common code (``""`` when Rec. 20 has none: the unit is then ours, namespace
    ``urn:cncgw``, ``UnitId`` -1, as OPC 10000-8 says for a unit without an id).
    """

    code: str
    display: str
    description: str

    @property
    def unit_id(self) -> int:
        """OPC 10000-8, 5.6.3: the common code's characters, 8 bits each, the first the most significant."""
        if not self.code:
            return -1
        n = 0
        for c in self.code:
            n = (n << 8) | ord(c)
        return n

    @property
    def namespace(self) -> str:
        return UNECE_NAMESPACE if self.code else NAMESPACE


#: profile and model unit spellings -> UNECE Rec. 20 (codes and symbols from the OPC Foundation's
#: UNECE_to_OPCUA.csv). "rpm": RPM (level 1, rotational frequency, which a spindle speed is) rather than
#: M46 (level 2, angular velocity). "A^2" (a mean of the squared current): Rec. 20 has no ampere squared (only
#: H32, ampere squared second), so it is our own unit, never passed off as a UNECE one.
UNITS: Mapping[str, Unit] = MappingProxyType({
    "um": Unit("4H", "\u00b5m", "micrometre (micron)"),
    "mm": Unit("MMT", "mm", "millimetre"),
    "rpm": Unit("RPM", "r/min", "revolutions per minute"),
    "mm/min": Unit("H81", "mm/min", "millimetre per minute"),
    "A": Unit("AMP", "A", "ampere"),
    "A^2": Unit("", "A\u00b2", "ampere squared: the mean of the squared current over a window"),
    "degC": Unit("CEL", "\u00b0C", "degree Celsius"),
    "K": Unit("KEL", "K", "kelvin"),
    "Hz": Unit("HTZ", "Hz", "hertz"),
    "%": Unit("P1", "%", "percent"),
    "s": Unit("SEC", "s", "second"),
})


def unit_of(name: str) -> Unit:
    """The EUInformation of a profile's unit; a spelling not in :data:`UNITS` is our own unit, shown as written."""
    return UNITS.get(name) or Unit("", name, name)


#: a window-derived value's OPC UA status (see :func:`estimate_status`)
GOOD = "Good"
HELD = "UncertainLastUsableValue"
WAITING = "BadWaitingForInitialData"
STALE = "BadOutOfService"
NO_DATA = "BadNoCommunication"
REJECTED = "BadSensorFailure"


def _bad_window(status: str | None) -> str:
    """A window whose factors drive nothing: too little data (a device not answering) or data not valid."""
    return NO_DATA if status in (None, "insufficient") else REJECTED


def estimate_status(h: Health) -> str:
    """The StatusCode (name) of the estimate in ``h`` (and of its bands).

    ``Good``: the estimate rests on the window's own good factors (an estimate the writer does not follow,
    e.g. its probe band too wide, is still the model's estimate of good data). ``UncertainLastUsableValue``: the window
    had no good factors and the gap policy held the last good window's (what OPC 10000-4 calls a last usable
    value: whatever updated the inputs stopped doing so). Bad: ``BadWaitingForInitialData`` before the first
    live window, ``BadOutOfService`` when no window has closed for ``[live] stale_after_s`` (the acquisition is
    not running), ``BadNoCommunication`` for a window with too little data and nothing held (beyond
    ``gap_hold_max_s``, or gap policy ``reference``: the estimate assumes the machine idle),
    ``BadSensorFailure`` for a window whose data was not valid (saturated, not finite) and nothing held.
    """
    est, w = h.estimate, h.last_window
    if est is None or w is None:
        return WAITING
    if h.stale:
        return STALE
    if est.inputs == "window":  # the window's own good factors (``usable`` is about writing, not this)
        return GOOD
    if est.inputs == "held":
        return HELD
    return _bad_window(w.status if w.index == est.index else None)


def factor_status(h: Health) -> str:
    """The StatusCode (name) of the last window's factors.

    As :func:`estimate_status` for the window the estimate followed; a window the estimator has not taken yet
    (a snapshot taken in between) is Good only when its status is.
    """
    est, w = h.estimate, h.last_window
    if w is None:
        return WAITING
    if h.stale:
        return STALE
    if est is not None and est.index == w.index:
        return estimate_status(h)
    return GOOD if w.status == "good" else _bad_window(w.status)


class OpcUaServer:
    """See the module docstring. ``start()`` returns once the server listens; ``stop()`` is idempotent."""

    def __init__(self, settings: OpcUa, *, profile: Profile, model: ThermalModel,
                 on_hold: Callable[[bool], None] | None = None, clock: Clock | None = None) -> None:
        self.settings = settings
        self.profile = profile
        self.model = model
        self.on_hold = on_hold
        #: with a clock, the last snapshot's staleness is re-checked every second between snapshots: when the
        #: acquisition stops no window closes and no snapshot comes, yet the values must turn BadOutOfService
        self.clock = clock
        self.port: int | None = None
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._queue: asyncio.Queue[Health | None] | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._nodes: dict[str, Any] = {}
        self._types: dict[str, Any] = {}
        self.published = 0

    def ranges(self) -> dict[str, tuple[float, float]]:
        """EURange of each analog variable that has one (node key -> (low, high)); the others are BaseAnalogType.

        Estimates: +- the model's envelope (the largest displacement identification saw, per axis); their
        95 % bands: 0 to that. Factors: the model's reference plus the deviations identification covered
        (``[coverage.range]``). Offsets: +- ``[compensation] limit_um``. Coverage: 0-100 %.
        """
        out: dict[str, tuple[float, float]] = {}
        env, cov = self.model.envelope, self.model.coverage
        for a in self.model.axes:
            e = env.axes.get(a) if env is not None else None
            if e is not None:
                out[f"Estimate.{a}_um"] = (-e.max_abs_um, e.max_abs_um)
                out[f"Estimate.{a}_band95_um"] = (0.0, e.max_abs_um)
        for f in self.profile.factors:
            r = cov.ranges.get(f.name) if cov is not None else None
            if r is not None:
                ref = self.model.reference.get(f.name, 0.0)
                out[f"Factors.{f.name}"] = (ref + r[0], ref + r[1])
        limit = self.profile.compensation.limit_um
        for c in self.profile.compensation.axes:
            out[f"Compensation.Commanded.{c.axis}_um"] = (-limit, limit)
            out[f"Compensation.Applied.{c.axis}_um"] = (-limit, limit)
        out["Health.CoveragePct"] = (0.0, 100.0)
        return out

    @property
    def endpoint(self) -> str:
        return f"opc.tcp://{self.settings.host}:{self.port}/cncgw/"

    def start(self) -> OpcUaServer:
        self._thread = threading.Thread(target=self._thread_main, name="cncgw-opcua", daemon=True)
        self._thread.start()
        if not self._ready.wait(START_TIMEOUT_S):
            raise GatewayError(f"OPC UA server did not start within {START_TIMEOUT_S:g} s")
        if self._error is not None:
            self._thread.join()
            self._thread = None
            where = f"{self.settings.host}:{self.settings.port}"
            if isinstance(self._error, OSError) and self._error.errno == errno.EADDRINUSE:
                raise GatewayError(f"OPC UA server on {where} failed to start: the port is in use (another gateway "
                                   "or OPC UA server on this PC?): expected a free port: set [opcua] port in the "
                                   "profile, or run with --no-opcua") from self._error
            raise GatewayError(f"OPC UA server on {where} failed to start: {self._error}") from self._error
        return self

    def publish(self, health: Health) -> None:
        """Hand over a health snapshot (thread-safe, cheap; only the newest matters)."""
        loop, queue = self._loop, self._queue
        if loop is None or queue is None or loop.is_closed():
            return
        with contextlib.suppress(RuntimeError):  # the loop closed in between: the server is stopping
            loop.call_soon_threadsafe(queue.put_nowait, health)

    def stop(self) -> None:
        loop, queue = self._loop, self._queue
        if loop is not None and queue is not None and not loop.is_closed():
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(queue.put_nowait, None)
        if self._thread is not None:
            self._thread.join(STOP_TIMEOUT_S + 5.0)
            self._thread = None

    # -- the server's thread ------------------------------------------------------------------------------
    def _thread_main(self) -> None:
        try:
            asyncio.run(self._main())
        except BaseException as exc:  # reported to start() or logged; the gateway goes on without OPC UA
            if not self._ready.is_set():
                self._error = exc
            else:
                log.exception("OPC UA server stopped with an error")
        finally:
            self._ready.set()

    async def _main(self) -> None:
        from asyncua import Server

        self._loop = asyncio.get_running_loop()
        self._queue = asyncio.Queue()
        server = Server(user_manager=await _Users.of(self.settings))
        async with asyncio.timeout(START_TIMEOUT_S):
            await server.init()
            server.set_endpoint(f"opc.tcp://{self.settings.host}:{self.settings.port}/cncgw/")
            server.set_server_name(f"cncgw {self.profile.name}")
            await self._security(server)
            idx = await server.register_namespace(NAMESPACE)
            await self._build(server, idx)
            # asyncua logs a failed start with its traceback before it raises; start() reports it in one line
            quiet = _DropStartError()
            logging.getLogger("asyncua.server.server").addFilter(quiet)
            try:
                await server.start()
            finally:
                logging.getLogger("asyncua.server.server").removeFilter(quiet)
        try:
            assert server.bserver is not None
            self.port = server.bserver.port
            log.info("OPC UA server listening on %s", self.endpoint)
            self._ready.set()
            async with asyncio.TaskGroup() as tg:
                tg.create_task(self._publisher(), name="opcua-publisher")
        finally:
            async with asyncio.timeout(STOP_TIMEOUT_S):
                await server.stop()

    async def _security(self, server: Any) -> None:
        from asyncua import ua

        s = self.settings
        policies = [getattr(ua.SecurityPolicyType, "NoSecurity" if p == "None" else p) for p in s.security]
        server.set_security_policy(policies, permission_ruleset=_anonymous_reads_only())
        tokens = [ua.AnonymousIdentityToken] if s.allow_anonymous else []
        if s.username is not None:
            tokens.append(ua.UserNameIdentityToken)
        if s.user_certificates and s.signing:  # a certificate token is verified by a signing policy
            tokens.append(ua.X509IdentityToken)
        server.set_identity_tokens(tokens)
        if s.writable and not (s.username or s.user_certificates):
            log.warning("OPC UA: writable = true but no user is configured: nobody can write (anonymous sessions "
                        "never do)")
        if s.certificate is not None and s.private_key is not None:
            await server.load_certificate(str(s.certificate))
            await server.load_private_key(str(s.private_key))

    async def _build(self, server: Any, idx: int) -> None:
        from asyncua import ua

        root = await server.nodes.objects.add_object(ua.NodeId("cncgw", idx), ua.QualifiedName("cncgw", idx))

        ranges = self.ranges()

        async def var(folder: Any, key: str, value: Any, vtype: Any, description: str = "") -> None:
            node = await folder.add_variable(ua.NodeId(key, idx), ua.QualifiedName(key.split(".")[-1], idx),
                                             ua.Variant(value, vtype))
            if description:
                await node.write_attribute(ua.AttributeIds.Description,
                                           ua.DataValue(ua.Variant(ua.LocalizedText(description))))
            self._nodes[key] = node
            self._types[key] = vtype

        async def analog(folder: Any, key: str, unit: str, description: str = "") -> None:
            """A Double of AnalogItemType (BaseAnalogType without a range) with its EngineeringUnits and EURange.

            asyncua's add_variable always types a variable BaseDataVariableType, so the node is added with
            the type definition here; the properties are added as the type declares them (HasProperty).
            """
            item = ua.AddNodesItem()
            item.RequestedNewNodeId = ua.NodeId(key, idx)
            item.BrowseName = ua.QualifiedName(key.split(".")[-1], idx)
            item.NodeClass = ua.NodeClass.Variable
            item.ParentNodeId = folder.nodeid
            item.ReferenceTypeId = ua.NodeId(ua.ObjectIds.HasComponent)
            rng = ranges.get(key)
            item.TypeDefinition = ua.NodeId(ua.ObjectIds.AnalogItemType if rng else ua.ObjectIds.BaseAnalogType)
            attrs = ua.VariableAttributes()
            attrs.DisplayName = ua.LocalizedText(key.split(".")[-1])
            attrs.Description = ua.LocalizedText(description or key.split(".")[-1])
            attrs.DataType = ua.NodeId(ua.ObjectIds.Double)
            attrs.Value = ua.Variant(math.nan, D)
            attrs.ValueRank = ua.ValueRank.Scalar
            attrs.AccessLevel = attrs.UserAccessLevel = ua.AccessLevel.CurrentRead.mask
            item.NodeAttributes = attrs
            added = await server.iserver.isession.add_nodes([item])
            added[0].StatusCode.check()
            node = server.get_node(added[0].AddedNodeId)
            u = unit_of(unit)
            eu = ua.EUInformation(NamespaceUri=u.namespace, UnitId=u.unit_id, DisplayName=ua.LocalizedText(u.display),
                                  Description=ua.LocalizedText(u.description))
            await node.add_property(ua.NodeId(f"{key}.EngineeringUnits", idx), ua.QualifiedName("EngineeringUnits", 0),
                                    eu, datatype=ua.NodeId(ua.ObjectIds.EUInformation))
            if rng:
                await node.add_property(ua.NodeId(f"{key}.EURange", idx), ua.QualifiedName("EURange", 0),
                                        ua.Range(Low=float(rng[0]), High=float(rng[1])),
                                        datatype=ua.NodeId(ua.ObjectIds.Range))
            await node.write_value(ua.DataValue(ua.Variant(math.nan, D),
                                                StatusCode=ua.StatusCode(ua.StatusCodes.BadWaitingForInitialData)))
            self._nodes[key] = node
            self._types[key] = D

        async def folder(parent: Any, key: str) -> Any:
            return await parent.add_object(ua.NodeId(key, idx), ua.QualifiedName(key.split(".")[-1], idx))

        D, S, B, I64 = ua.VariantType.Double, ua.VariantType.String, ua.VariantType.Boolean, ua.VariantType.Int64
        machine = await folder(root, "Machine")
        await var(machine, "Machine.Name", self.profile.name, S)
        factors = await folder(root, "Factors")
        for f in self.profile.factors:
            await analog(factors, f"Factors.{f.name}", f.unit, f"{f.description} [{f.unit}]".strip())
        est = await folder(root, "Estimate")
        for a in self.model.axes:
            await analog(est, f"Estimate.{a}_um", "um", f"estimated thermal displacement along {a} [um]")
        if self.profile.probes.enabled:  # the model updated by probes: every estimate has its band
            for a in self.model.axes:
                await analog(est, f"Estimate.{a}_band95_um", "um",
                             f"95 % half-band of the estimate along {a}: the true displacement is within +- this [um]")
        await var(est, "Estimate.Window", -1, I64)
        await var(est, "Estimate.Usable", False, B)
        await var(est, "Estimate.Reason", "", S)
        comp = await folder(root, "Compensation")
        await var(comp, "Compensation.Mode", "write" if self.profile.compensation.enabled else "dry-run", S)
        commanded = await folder(comp, "Compensation.Commanded")
        applied = await folder(comp, "Compensation.Applied")
        for a in self.profile.compensation.axes:
            await analog(commanded, f"Compensation.Commanded.{a.axis}_um", "um", f"offset commanded along {a.axis}")
            await analog(applied, f"Compensation.Applied.{a.axis}_um", "um",
                         f"offset the CNC showed along {a.axis} when last read back")
        await var(comp, "Compensation.LastWriteTimeS", math.nan, D)
        await var(comp, "Compensation.Verified", False, B)
        await var(comp, "Compensation.Writes", 0, I64)
        await var(comp, "Compensation.HoldRequest", False, B, "true: hold the offsets (writable only if configured)")
        if self.settings.writable and self.on_hold is not None:
            await self._nodes["Compensation.HoldRequest"].set_writable()
        health = await folder(root, "Health")
        await var(health, "Health.Alarms", [], S)
        await var(health, "Health.AlarmCount", 0, I64)
        await var(health, "Health.Devices", [], S)
        await var(health, "Health.SampleRateHz", math.nan, D)
        await var(health, "Health.MissedTicks", 0, I64)
        await var(health, "Health.GapWindows", 0, I64)
        await var(health, "Health.UptimeS", 0.0, D)
        await var(health, "Health.WindowIndex", -1, I64)
        await var(health, "Health.WindowStatus", "", S, "good, insufficient (too little data) or rejected "
                                                       "(saturated or not finite)")
        await var(health, "Health.WindowQuality", "", S, "coverage, samples, devices in error, why not good")
        await analog(health, "Health.CoveragePct", "%", "lowest channel coverage of the last window [%]")
        await var(health, "Health.SamplesTaken", 0, I64)
        await var(health, "Health.SamplesExpected", 0, I64)

    async def _publisher(self) -> None:
        assert self._queue is not None
        hold = False
        shown: Health | None = None
        while True:
            try:
                async with asyncio.timeout(1.0):
                    item = await self._queue.get()
            except TimeoutError:
                item = ...
            items = [item]
            while not self._queue.empty():  # only the newest snapshot matters
                items.append(self._queue.get_nowait())
            if None in items:
                return
            item = items[-1]
            if item is not ...:
                await self._apply(item)
                shown = item
            elif shown is not None and self.clock is not None:
                now = replace(shown, clock_s=self.clock.now())
                if now.stale != shown.stale:  # no snapshot for stale_after_s: served Bad, not the last Good
                    log.warning("OPC UA: no window closed for %.0f s of clock time (stale_after_s %.0f s): "
                                "values served as %s", now.clock_s - now.last_window.end_s,  # type: ignore[union-attr]
                                now.stale_after_s, STALE)
                    await self._apply(now)
                    shown = now
            if self.on_hold is not None and self.settings.writable:
                value = bool(await self._nodes["Compensation.HoldRequest"].read_value())
                if value != hold:
                    hold = value
                    log.warning("OPC UA: hold request %s", "ON" if hold else "off")
                    self.on_hold(hold)
            if item is not ...:  # counted once the snapshot is shown and the hold request it met is passed on
                self.published += 1

    async def _apply(self, h: Health) -> None:
        """Show snapshot ``h``: every window-derived value with its status and the window's end as source time."""
        from asyncua import ua

        w, est, comp = h.last_window, h.estimate, h.compensation
        # (value, status name, source time in clock seconds or None for "now")
        values: dict[str, tuple[Any, str, float | None]] = {}
        f_status = factor_status(h)
        f_time = w.end_s if w is not None else None
        held = est.held_factors if est is not None else {}
        for f in self.profile.factors:
            if w is None:
                continue
            v = w.factors.get(f.name, math.nan) if f_status == GOOD else held.get(f.name, math.nan)
            values[f"Factors.{f.name}"] = (v, f_status, f_time)
        if est is not None:
            e_status, e_time = estimate_status(h), est.end_s
            for a, v in est.estimate_um.items():
                values[f"Estimate.{a}_um"] = (v, e_status, e_time)
            for a, v in est.band95_um.items():
                values[f"Estimate.{a}_band95_um"] = (v, e_status, e_time)
            values["Estimate.Window"] = (est.index, GOOD, e_time)
            values["Estimate.Usable"] = (est.usable, GOOD, e_time)
            values["Estimate.Reason"] = (est.reason, GOOD, e_time)
        if comp is not None:
            for a, v in comp.commanded_um.items():  # what the writer holds now, whatever the window
                values[f"Compensation.Commanded.{a}_um"] = (v, GOOD, f_time)
            lw = comp.last_write
            if lw is not None:  # read back from the CNC at the write's time
                for a, v in lw.applied_um.items():
                    values[f"Compensation.Applied.{a}_um"] = (v, GOOD, lw.t_s)
                values["Compensation.LastWriteTimeS"] = (lw.t_s, GOOD, lw.t_s)
                values["Compensation.Verified"] = (lw.verified, GOOD, lw.t_s)
            values["Compensation.Writes"] = (comp.writes, GOOD, None)
        alarms = [f"{a.name}: {a.message}" for a in h.alarms]
        values["Health.Alarms"] = (alarms, GOOD, None)
        values["Health.AlarmCount"] = (len(alarms), GOOD, None)
        values["Health.Devices"] = ([f"{d.device}: {d.state}" for d in h.devices], GOOD, None)
        values["Health.SampleRateHz"] = (h.sample_rate_hz, GOOD, None)
        if w is not None:
            values["Health.MissedTicks"] = (w.missed_ticks, GOOD, w.end_s)
            values["Health.WindowIndex"] = (w.index, GOOD, w.end_s)
            values["Health.WindowStatus"] = (w.status, GOOD, w.end_s)
            values["Health.WindowQuality"] = (w.quality(), GOOD, w.end_s)
            values["Health.CoveragePct"] = (100.0 * w.coverage, GOOD, w.end_s)
            values["Health.SamplesTaken"] = (w.samples_taken, GOOD, w.end_s)
            values["Health.SamplesExpected"] = (w.samples_expected, GOOD, w.end_s)
        values["Health.GapWindows"] = (h.gaps.filled_windows, GOOD, None)
        values["Health.UptimeS"] = (h.uptime_s, GOOD, None)

        now = datetime.now(UTC)
        for key, (v, status, t_s) in values.items():
            node = self._nodes.get(key)
            if node is None:
                continue
            vtype = self._types[key]
            if vtype == ua.VariantType.Double:
                v = float(v)
                if not math.isfinite(v) and not status.startswith("Bad"):
                    status = NO_DATA  # no number: never served as Good or Uncertain
            source = now if t_s is None else datetime.fromtimestamp(t_s, UTC)
            await node.write_value(ua.DataValue(ua.Variant(v, vtype),
                                                StatusCode=ua.StatusCode(getattr(ua.StatusCodes, status)),
                                                SourceTimestamp=source, ServerTimestamp=now))


def _anonymous_reads_only() -> Any:
    """asyncua's request-level permissions: an anonymous session reads, browses and subscribes, never writes."""
    from asyncua import ua
    from asyncua.crypto.permission_rules import USER_TYPES, PermissionRuleset, UserRole

    class AnonymousReadsOnly(PermissionRuleset):
        def __init__(self) -> None:
            user = {ua.NodeId(t) for t in USER_TYPES}
            no = {ua.NodeId(ua.ObjectIds.WriteRequest_Encoding_DefaultBinary),
                  ua.NodeId(ua.ObjectIds.CallRequest_Encoding_DefaultBinary)}
            self._allowed = {UserRole.Admin: user, UserRole.User: user, UserRole.Anonymous: user - no}

        def check_validity(self, user: Any, action_type_id: Any, body: Any) -> bool:
            role = getattr(user, "role", UserRole.Anonymous)
            return action_type_id in self._allowed.get(role, set())

    return AnonymousReadsOnly()


class _Users:
    """asyncua's user manager for the profile's users: who a session is, or ``None`` to refuse the login."""

    def __init__(self, settings: OpcUa, password: str | None, certificates: dict[bytes, str]) -> None:
        self.settings = settings
        self._password = password
        self._certificates = certificates

    @classmethod
    async def of(cls, settings: OpcUa) -> _Users:
        """Read the password file and the user certificates (DER or PEM) when the server starts."""
        from asyncua.crypto import uacrypto

        password = None
        if settings.password_file is not None:
            password = settings.password_file.read_text(encoding="utf-8").rstrip("\r\n")
            if not password:
                raise GatewayError(f"{settings.password_file}: the OPC UA password file is empty")
        certificates = {}
        for path in settings.user_certificates:
            cert = await uacrypto.load_certificate(path)
            certificates[uacrypto.der_from_x509(cert)] = path.name
        return cls(settings, password, certificates)

    def get_user(self, iserver: Any, username: str | None = None, password: str | None = None,
                 certificate: Any = None) -> Any:
        import hmac

        from asyncua.crypto import uacrypto
        from asyncua.crypto.permission_rules import User, UserRole

        if username is not None:  # a user name token: the password must match, whatever else
            ok = (self.settings.username is not None and self._password is not None
                  and hmac.compare_digest(username.encode(), self.settings.username.encode())
                  and hmac.compare_digest((password or "").encode(), self._password.encode()))
            if not ok:
                log.warning("OPC UA: login as %r refused (wrong user name or password)", username)
                return None
            return User(role=UserRole.User, name=username)
        if certificate is not None:  # an X509 user token, or the client's own certificate on a signed channel
            der = certificate if isinstance(certificate, bytes) else uacrypto.der_from_x509(certificate)
            name = self._certificates.get(der)
            if name is not None:
                return User(role=UserRole.User, name=f"certificate {name}")
        if self.settings.allow_anonymous:
            return User(role=UserRole.Anonymous)
        log.warning("OPC UA: an anonymous login refused (allow_anonymous is off)")
        return None
