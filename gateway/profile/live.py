"""The profile's live sections, parsed into frozen typed objects: ``[live]``, ``[compensation]``, ``[opcua]``.

``[live]``: how the live estimator treats windows it has no good factors for (gaps while the gateway was
down, windows marked ``insufficient``) and when inputs count as stale.

``[compensation]``: how estimates become offsets in the CNC's registers (per axis sign, unit, register and
encoding), the limits every written value must satisfy (range, step per update, deadband), the CNC link
(Modbus TCP), its heartbeat and what to do on bad inputs. Writing stays off (a dry run: compute, log and
audit, write nothing) unless ``enabled = true``.

``[opcua]``: the read-only OPC UA server (bound to 127.0.0.1 unless configured; security policies).

``[records]``: how long the record store keeps windows (``keep_days``; default: forever).

See ``profiles/template.toml`` for every key with its meaning.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from gateway.tomlcheck import Table

GAP_POLICIES = ("hold", "reference")
ON_FAULT = ("hold", "ramp_to_zero")
AIMS = ("midpoint", "estimate")
DATA_TYPES = ("int32", "int16")
ORDERS = ("big", "little")
SECURITY_POLICIES = ("None", "Basic256Sha256_Sign", "Basic256Sha256_SignAndEncrypt",
                     "Aes128Sha256RsaOaep_Sign", "Aes128Sha256RsaOaep_SignAndEncrypt",
                     "Aes256Sha256RsaPss_Sign", "Aes256Sha256RsaPss_SignAndEncrypt")


@dataclass(frozen=True, kw_only=True, slots=True)
class Live:
    """How the live estimator fills windows without good factors, and when inputs are stale.

    ``gap_policy``: ``"hold"`` assumes the last good window's factors went on (for at most
    ``gap_hold_max_s``, then idle at the reference), ``"reference"`` assumes the machine stood idle.
    ``stale_after_s``: no good window for this long (clock seconds) and the inputs count as stale.
    ``history_max_h``: the estimator is rebuilt on start from at most this much stored history (``None``:
    twenty times the model's slowest time constant, after which older history changes nothing).
    """

    gap_policy: str = "hold"
    gap_hold_max_s: float = 600.0
    stale_after_s: float = 150.0
    history_max_h: float | None = None


@dataclass(frozen=True, kw_only=True, slots=True)
class Records:
    """The record store's retention: windows older than ``keep_days`` are deleted (``None``: kept forever)."""

    keep_days: float | None = None


@dataclass(frozen=True, kw_only=True, slots=True)
class AxisOutput:
    """Where and how one axis's offset is written: ``offset = sign * estimate``, in counts of ``unit_um``."""

    axis: str
    register: int  # holding register of the command (the first of two for int32)
    readback: int  # input register of the offset the CNC applies, same encoding
    sign: float = -1.0
    unit_um: float = 0.1
    data_type: str = "int32"
    word_order: str = "big"
    #: tighten the model's plausibility bounds (never widen them): |estimate| and change per window, in um
    plausible_um: float | None = None
    plausible_change_um: float | None = None

    @property
    def n_registers(self) -> int:
        return 2 if self.data_type == "int32" else 1

    @property
    def max_counts(self) -> int:
        return 2**31 - 1 if self.data_type == "int32" else 2**15 - 1

    def encode(self, counts: int) -> list[int]:
        """Register words for ``counts`` (refuses a value the type cannot hold)."""
        if not -self.max_counts <= counts <= self.max_counts:
            raise ValueError(f"axis {self.axis}: {counts} counts do not fit {self.data_type}")
        if self.data_type == "int16":
            return [counts & 0xFFFF]
        hi, lo = struct.unpack(">HH", struct.pack(">i", counts))
        return [hi, lo] if self.word_order == "big" else [lo, hi]

    def decode(self, words: list[int]) -> int:
        """Counts from this axis's register words."""
        if self.data_type == "int16":
            return int(struct.unpack(">h", struct.pack(">H", words[0]))[0])
        hi, lo = words if self.word_order == "big" else words[::-1]
        return int(struct.unpack(">i", struct.pack(">HH", hi, lo))[0])


@dataclass(frozen=True, kw_only=True, slots=True)
class Compensation:
    """How estimates are written back to the CNC. Writing is off (dry run) unless ``enabled``.

    Limits apply to the offset in um, before encoding: ``limit_um`` clamps it, ``max_step_um`` bounds its
    change per update (one update a window; also the ramp rate on a fault), ``deadband_um`` skips changes
    smaller than that. ``on_fault``: with stale or bad inputs the offset is held at once; ``"ramp_to_zero"``
    ramps it to zero (``max_step_um`` a window) once the fault has lasted ``fault_hold_s``.
    ``aim``: an offset written at a window's end is in force during the next window, while the machine
    keeps moving: ``"midpoint"`` aims at the middle of that window (the mean of the estimate and its
    prediction one window ahead with the factors held), which halves the lag error; ``"estimate"`` writes
    the estimate as it is.
    ``heartbeat_period_s`` and ``watchdog_s`` are clock seconds (a sped-up simulator's clock too).
    """

    enabled: bool = False
    host: str | None = None
    port: int = 502
    unit_id: int = 1
    timeout_s: float = 0.5
    retries: int = 0
    reconnect_s: float = 2.0  # wall seconds between attempts while the CNC is unreachable
    axes: tuple[AxisOutput, ...] = ()
    enable_coil: int | None = 0
    heartbeat_register: int | None = 6
    heartbeat_period_s: float = 1.0
    watchdog_s: float = 5.0
    status_register: int | None = 6
    limit_um: float = 100.0
    max_step_um: float = 1.0
    deadband_um: float = 0.1
    on_fault: str = "hold"
    fault_hold_s: float = 600.0
    aim: str = "midpoint"

    def axis(self, name: str) -> AxisOutput:
        for a in self.axes:
            if a.axis == name:
                return a
        raise KeyError(name)


@dataclass(frozen=True, kw_only=True, slots=True)
class OpcUa:
    """The OPC UA server: read-only unless ``writable`` (then only the operator's hold request).

    Writing needs an authenticated session: ``username`` with the password in ``password_file``, or a client
    certificate listed in ``user_certificates``. An anonymous session (``allow_anonymous``; default: only
    when every policy is ``"None"``) reads and never writes.
    """

    enabled: bool = True
    host: str = "127.0.0.1"
    port: int = 4840
    security: tuple[str, ...] = ("None",)
    certificate: Path | None = None
    private_key: Path | None = None
    writable: bool = False
    username: str | None = None
    password_file: Path | None = None  # read when the server starts: the password is never kept in the profile
    user_certificates: tuple[Path, ...] = ()
    allow_anonymous: bool = True

    @property
    def encrypting(self) -> tuple[str, ...]:
        """The policies that encrypt the channel (a password may cross them)."""
        return tuple(p for p in self.security if p.endswith("_SignAndEncrypt"))

    @property
    def signing(self) -> tuple[str, ...]:
        """The policies that sign (a certificate token can be verified)."""
        return tuple(p for p in self.security if p != "None")

    @property
    def endpoint(self) -> str:
        return f"opc.tcp://{self.host}:{self.port}/cncgw/"


def default_axes(axes: tuple[str, ...]) -> tuple[AxisOutput, ...]:
    """The bundled simulated CNC's map: X, Y, Z at holding 0, 2, 4 (int32, 0.1 um), sign -1."""
    return tuple(AxisOutput(axis=a, register=2 * i, readback=2 * i) for i, a in enumerate(axes))


def parse_live(root: Table, window_s: float) -> Live:
    """``[live]`` (defaults when absent)."""
    t = root.table("live")
    if t is None:
        return Live(stale_after_s=2.5 * window_s)
    policy = t.str("gap_policy", default="hold", choices=GAP_POLICIES)
    hold = t.float("gap_hold_max_s", default=600.0, min=0.0, max=7 * 86400.0,
                   expected="a number of seconds from 0 to 604800 (7 days)")
    stale = t.float("stale_after_s", default=2.5 * window_s, min=0.0, min_exclusive=True, max=86400.0,
                    expected="a number of seconds > 0 and at most 86400 (a day)")
    # the replayed history is kept in memory at start: a year of windows is the most that makes sense
    history = t.float("history_max_h", default=None, min=0.0, min_exclusive=True, max=366 * 24.0,
                      expected="a number of hours > 0 and at most 8784 (366 days)")
    t.done()
    if stale is not None and stale < window_s:
        t.problem("stale_after_s", f"expected at least one window ({window_s:g} s), got {stale:g}")
    return Live(gap_policy=policy or "hold", gap_hold_max_s=600.0 if hold is None else hold,
                stale_after_s=stale or 2.5 * window_s, history_max_h=history)


def parse_records(root: Table) -> Records:
    """``[records]`` (default: every window kept)."""
    t = root.table("records")
    if t is None:
        return Records()
    keep = t.float("keep_days", default=None, min=0.0, min_exclusive=True, max=36500.0,
                   expected="days of windows to keep in records.sqlite, > 0 (older ones are deleted)")
    t.done()
    return Records(keep_days=keep)


def parse_compensation(root: Table, axes: tuple[str, ...], window_s: float) -> Compensation:
    """``[compensation]`` and its ``[compensation.axes.AXIS]`` tables (defaults: a dry run on the bundled map)."""
    t = root.table("compensation")
    if t is None:
        return Compensation(axes=default_axes(axes))
    v: dict[str, Any] = {
        "enabled": t.bool("enabled", default=False),
        "host": t.str("host", default=None, expected="the CNC's host name or IP address"),
        "port": t.int("port", default=502, min=1, max=65535),
        "unit_id": t.int("unit_id", default=1, min=0, max=255),
        "timeout_s": t.float("timeout_s", default=0.5, min=0.0, min_exclusive=True, max=60.0),
        "retries": t.int("retries", default=0, min=0, max=10),
        "reconnect_s": t.float("reconnect_s", default=2.0, min=0.0, min_exclusive=True, max=3600.0),
        "enable_coil": _optional_address(t, "enable_coil", 0),
        "heartbeat_register": _optional_address(t, "heartbeat_register", 6),
        "heartbeat_period_s": t.float("heartbeat_period_s", default=1.0, min=0.0, min_exclusive=True),
        "watchdog_s": t.float("watchdog_s", default=5.0, min=0.0, min_exclusive=True),
        "status_register": _optional_address(t, "status_register", 6),
        "limit_um": t.float("limit_um", default=100.0, min=0.0, min_exclusive=True, max=10000.0),
        "max_step_um": t.float("max_step_um", default=1.0, min=0.0, min_exclusive=True),
        "deadband_um": t.float("deadband_um", default=0.1, min=0.0),
        "on_fault": t.str("on_fault", default="hold", choices=ON_FAULT),
        "fault_hold_s": t.float("fault_hold_s", default=600.0, min=0.0),
        "aim": t.str("aim", default="midpoint", choices=AIMS),
    }
    outputs = []
    for name, at in t.tables("axes"):
        if name not in axes:
            t.problem("axes", f'axis "{name}" is not among the machine\'s axes ({", ".join(axes)})')
            continue
        out = _parse_axis(name, at)
        if out is not None:
            outputs.append(out)
    t.done()
    defaults = Compensation()
    for k, x in v.items():  # a bad value is reported already: check the rest against the default
        if x is None and k not in ("host", "enable_coil", "heartbeat_register", "status_register"):
            v[k] = getattr(defaults, k)
    explicit = bool(outputs)
    if not outputs:
        outputs = list(default_axes(axes))
    c = Compensation(**v, axes=tuple(outputs))
    _check_compensation(t, c, explicit=explicit, window_s=window_s)
    return c


def _optional_address(t: Table, key: str, default: int) -> int | None:
    value = t.int(key, default=default, min=-1, max=65535,
                  expected="a 0-based address in 0..65535, or -1 for none")
    return None if value is None or value < 0 else value


def _parse_axis(name: str, t: Table) -> AxisOutput | None:
    register = t.int("register", min=0, max=65535, expected="the holding register of the axis's offset (0-based)")
    readback = t.int("readback", default=register, min=0, max=65535,
                     expected="the input register where the CNC shows the applied offset (0-based)")
    sign = t.float("sign", default=-1.0, expected="-1 or 1")
    unit = t.float("unit_um", default=0.1, min=0.0, min_exclusive=True, max=1000.0)
    data_type = t.str("data_type", default="int32", choices=DATA_TYPES)
    order = t.str("word_order", default="big", choices=ORDERS)
    plausible = t.float("plausible_um", default=None, min=0.0, min_exclusive=True,
                        expected="a bound on |estimate| in um > 0 (tightens the model's envelope)")
    plausible_change = t.float("plausible_change_um", default=None, min=0.0, min_exclusive=True,
                               expected="a bound on the estimate's change per window in um > 0 (tightens the "
                                        "model's envelope)")
    t.done()
    if sign is not None and sign not in (-1.0, 1.0):
        t.problem("sign", f"expected -1 or 1, got {sign:g}")
        sign = None
    if None in (register, readback, sign, unit, data_type, order):
        return None
    words = 2 if data_type == "int32" else 1  # as AxisOutput.n_registers
    for key, first in (("register", register), ("readback", readback)):
        if first + words - 1 > 65535:
            t.problem(key, f"the {data_type} value at {first} needs registers {first}..{first + words - 1}: "
                           f"expected an address in 0..{65536 - words} (the last register is 65535)")
            return None
    return AxisOutput(axis=name, register=register, readback=readback, sign=sign, unit_um=unit,
                      data_type=data_type, word_order=order, plausible_um=plausible,
                      plausible_change_um=plausible_change)


def _check_compensation(t: Table, c: Compensation, *, explicit: bool, window_s: float) -> None:
    if c.enabled and c.host is None:
        t.problem("host", "compensation.enabled = true needs the CNC's address: set compensation.host")
    if c.enabled and not explicit:
        t.problem("axes", "compensation.enabled = true needs a [compensation.axes.AXIS] table per compensated axis "
                          "(register, sign, unit_um, data_type): offsets are never written to assumed registers")
    if c.heartbeat_register is not None and c.heartbeat_period_s > c.watchdog_s / 3:
        t.problem("heartbeat_period_s", f"a beat every {c.heartbeat_period_s:g} s does not keep a {c.watchdog_s:g} s "
                                        f"watchdog alive with a margin: expected <= {c.watchdog_s / 3:g} "
                                        "(watchdog_s / 3)")
    if c.deadband_um > c.max_step_um:
        t.problem("deadband_um", f"expected at most max_step_um ({c.max_step_um:g}), got {c.deadband_um:g}: "
                                 "no change could ever be written")
    used: dict[int, str] = {}
    if c.heartbeat_register is not None:
        used[c.heartbeat_register] = "heartbeat_register"
    for a in c.axes:
        if c.limit_um / a.unit_um > a.max_counts:
            t.doc.problem((*t.path, "axes", a.axis, "unit_um"), f"limit_um {c.limit_um:g} does not fit {a.data_type} "
                                                   f"counts of {a.unit_um:g} um")
        for r in range(a.register, a.register + a.n_registers):
            if r in used:
                t.doc.problem((*t.path, "axes", a.axis, "register"), f"register {r} is already used by {used[r]}")
            used.setdefault(r, f"axes.{a.axis}")


def parse_opcua(root: Table, base: Path) -> OpcUa:
    """``[opcua]``; certificate paths are relative to the profile's folder ``base``."""
    t = root.table("opcua")
    if t is None:
        return OpcUa()
    enabled = t.bool("enabled", default=True)
    host = t.str("host", default="127.0.0.1", expected="an address to bind (127.0.0.1: this PC only)")
    port = t.int("port", default=4840, min=0, max=65535)
    security = t.str_list("security", default=("None",), choices=SECURITY_POLICIES, min_len=1)
    cert = t.str("certificate", default=None, expected="a certificate file (DER or PEM)")
    key = t.str("private_key", default=None, expected="the certificate's private key file (PEM)")
    writable = t.bool("writable", default=False)
    username = t.str("username", default=None, expected="the user name an operator's client logs in with")
    password = t.str("password_file", default=None,
                     expected="a file holding that user's password (relative to the profile; keep it 0600)")
    user_certs = t.str_list("user_certificates", default=()) or ()
    anonymous = t.bool("allow_anonymous", default=None)
    t.done()
    cert_p = (base / cert) if cert else None
    key_p = (base / key) if key else None
    password_p = (base / password) if password else None
    user_cert_ps = tuple(base / c for c in user_certs)
    secure = [s for s in (security or ()) if s != "None"]
    if secure and not (cert_p and key_p):
        t.problem("security", f"{', '.join(secure)} needs opcua.certificate and opcua.private_key")
    for key, file in (("certificate", cert_p), ("private_key", key_p), ("password_file", password_p),
                      *(("user_certificates", c) for c in user_cert_ps)):
        if file is not None and not file.is_file():  # found at start, not when the first client connects
            what = {"certificate": "the server certificate (DER or PEM)", "private_key": "its private key (PEM)",
                    "password_file": "a file holding the password",
                    "user_certificates": "a client certificate (DER or PEM)"}[key]
            t.problem(key, f'"{file}": file not found: expected {what}, a path relative to the profile\'s folder')
    if (username is None) != (password_p is None):
        t.problem("username" if username is None else "password_file",
                  "opcua.username and opcua.password_file go together (a user logs in with both)")
    if username is not None and not any(s.endswith("_SignAndEncrypt") for s in secure):
        t.problem("username", "a password would cross the network in plain text: add a *_SignAndEncrypt policy to "
                              "opcua.security (with certificate and private_key)")
    if user_cert_ps and not secure:
        t.problem("user_certificates", "a client certificate can only be verified on a signed channel: add a signed "
                                       "policy to opcua.security")
    authenticated = username is not None or bool(user_cert_ps)
    if writable and not authenticated:
        t.problem("writable", "writable = true needs an authenticated user, since an anonymous session never "
                              "writes: set opcua.username and opcua.password_file, or opcua.user_certificates")
    # anonymous reading: by default only where nothing is secured; an encrypted server asks who is there
    allow_anonymous = not secure if anonymous is None else anonymous
    if not allow_anonymous and not authenticated:
        t.problem("allow_anonymous" if anonymous is not None else "security",
                  "with anonymous sessions off (the default with signed or encrypted policies) nobody could log "
                  "in: set opcua.username and opcua.password_file, opcua.user_certificates, or allow_anonymous = "
                  "true (anonymous sessions read, never write)")
    return OpcUa(enabled=True if enabled is None else enabled, host=host or "127.0.0.1",
                 port=4840 if port is None else port, security=tuple(security or ("None",)), certificate=cert_p,
                 private_key=key_p, writable=bool(writable), username=username, password_file=password_p,
                 user_certificates=user_cert_ps, allow_anonymous=allow_anonymous)

