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

- ``Machine.Name``; ``Factors.<factor>`` (last window's factor, its unit in the description);
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

The server runs its own asyncio loop in a thread; :meth:`OpcUaServer.publish` (any thread) hands it a
health snapshot, applied by a publisher task. Both tasks run in one ``TaskGroup``; every wait has a timeout.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import threading
from collections.abc import Callable
from typing import Any

from gateway.errors import GatewayError
from gateway.live.health import Health
from gateway.model import ThermalModel
from gateway.profile import Profile
from gateway.profile.live import OpcUa

log = logging.getLogger(__name__)

NAMESPACE = "urn:cncgw"
START_TIMEOUT_S = 30.0
STOP_TIMEOUT_S = 10.0


class OpcUaServer:
    """See the module docstring. ``start()`` returns once the server listens; ``stop()`` is idempotent."""

    def __init__(self, settings: OpcUa, *, profile: Profile, model: ThermalModel,
                 on_hold: Callable[[bool], None] | None = None) -> None:
        self.settings = settings
        self.profile = profile
        self.model = model
        self.on_hold = on_hold
        self.port: int | None = None
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._queue: asyncio.Queue[Health | None] | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._nodes: dict[str, Any] = {}
        self._types: dict[str, Any] = {}
        self.published = 0

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
            raise GatewayError(f"OPC UA server on {self.settings.host}:{self.settings.port} failed to start: "
                               f"{self._error}") from self._error
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
            await server.start()
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

        async def var(folder: Any, key: str, value: Any, vtype: Any, description: str = "") -> None:
            node = await folder.add_variable(ua.NodeId(key, idx), ua.QualifiedName(key.split(".")[-1], idx),
                                             ua.Variant(value, vtype))
            if description:
                await node.write_attribute(ua.AttributeIds.Description,
                                           ua.DataValue(ua.Variant(ua.LocalizedText(description))))
            self._nodes[key] = node
            self._types[key] = vtype

        async def folder(parent: Any, key: str) -> Any:
            return await parent.add_object(ua.NodeId(key, idx), ua.QualifiedName(key.split(".")[-1], idx))

        D, S, B, I64 = ua.VariantType.Double, ua.VariantType.String, ua.VariantType.Boolean, ua.VariantType.Int64
        machine = await folder(root, "Machine")
        await var(machine, "Machine.Name", self.profile.name, S)
        factors = await folder(root, "Factors")
        for f in self.profile.factors:
            await var(factors, f"Factors.{f.name}", math.nan, D, f"{f.description} [{f.unit}]".strip())
        est = await folder(root, "Estimate")
        for a in self.model.axes:
            await var(est, f"Estimate.{a}_um", 0.0, D, f"estimated thermal displacement along {a} [um]")
        if self.profile.probes.enabled:  # the model updated by probes: every estimate has its band
            for a in self.model.axes:
                await var(est, f"Estimate.{a}_band95_um", math.nan, D,
                          f"95 % half-band of the estimate along {a}: the true displacement is within +- this [um]")
        await var(est, "Estimate.Window", -1, I64)
        await var(est, "Estimate.Usable", False, B)
        await var(est, "Estimate.Reason", "", S)
        comp = await folder(root, "Compensation")
        await var(comp, "Compensation.Mode", "write" if self.profile.compensation.enabled else "dry-run", S)
        commanded = await folder(comp, "Compensation.Commanded")
        applied = await folder(comp, "Compensation.Applied")
        for a in self.profile.compensation.axes:
            await var(commanded, f"Compensation.Commanded.{a.axis}_um", 0.0, D)
            await var(applied, f"Compensation.Applied.{a.axis}_um", math.nan, D)
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
        await var(health, "Health.CoveragePct", math.nan, D, "lowest channel coverage of the last window [%]")
        await var(health, "Health.SamplesTaken", 0, I64)
        await var(health, "Health.SamplesExpected", 0, I64)

    async def _publisher(self) -> None:
        assert self._queue is not None
        hold = False
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
            if self.on_hold is not None and self.settings.writable:
                value = bool(await self._nodes["Compensation.HoldRequest"].read_value())
                if value != hold:
                    hold = value
                    log.warning("OPC UA: hold request %s", "ON" if hold else "off")
                    self.on_hold(hold)
            if item is not ...:  # counted once the snapshot is shown and the hold request it met is passed on
                self.published += 1

    async def _apply(self, h: Health) -> None:
        values: dict[str, Any] = {}
        for name, v in h.factors.items():
            values[f"Factors.{name}"] = float(v)
        est = h.estimate
        if est is not None:
            for a, v in est.estimate_um.items():
                values[f"Estimate.{a}_um"] = float(v)
            for a, v in est.band95_um.items():
                if f"Estimate.{a}_band95_um" in self._nodes:
                    values[f"Estimate.{a}_band95_um"] = float(v)
            values["Estimate.Window"] = est.index
            values["Estimate.Usable"] = est.usable
            values["Estimate.Reason"] = est.reason
        comp = h.compensation
        if comp is not None:
            for a, v in comp.commanded_um.items():
                values[f"Compensation.Commanded.{a}_um"] = float(v)
            lw = comp.last_write
            if lw is not None:
                for a, v in lw.applied_um.items():
                    values[f"Compensation.Applied.{a}_um"] = float(v)
                values["Compensation.LastWriteTimeS"] = float(lw.t_s)
                values["Compensation.Verified"] = lw.verified
            values["Compensation.Writes"] = comp.writes
        alarms = [f"{a.name}: {a.message}" for a in h.alarms]
        values["Health.Alarms"] = alarms
        values["Health.AlarmCount"] = len(alarms)
        values["Health.Devices"] = [f"{d.device}: {d.state}" for d in h.devices]
        values["Health.SampleRateHz"] = h.sample_rate_hz
        w = h.last_window
        if w is not None:
            values["Health.MissedTicks"] = w.missed_ticks
            values["Health.WindowIndex"] = w.index
            values["Health.WindowStatus"] = w.status
            values["Health.WindowQuality"] = w.quality()
            values["Health.CoveragePct"] = 100.0 * w.coverage
            values["Health.SamplesTaken"] = w.samples_taken
            values["Health.SamplesExpected"] = w.samples_expected
        values["Health.GapWindows"] = h.gaps.filled_windows
        values["Health.UptimeS"] = h.uptime_s
        from asyncua import ua

        for key, v in values.items():
            node = self._nodes.get(key)
            if node is not None:
                await node.write_value(ua.Variant(v, self._types[key]))


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
