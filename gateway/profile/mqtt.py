"""``[mqtt]``: the MQTT output's broker, credentials, TLS and pacing (see ``profiles/template.toml``)."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from gateway.tomlcheck import Table


@dataclass(frozen=True, kw_only=True, slots=True)
class Mqtt:
    """The profile's ``[mqtt]`` section (see ``profiles/template.toml``); off unless ``enabled``."""

    enabled: bool = False
    host: str = "127.0.0.1"
    port: int = 1883
    client_id: str = ""  # "": cncgw-<machine>
    topic_prefix: str = "cncgw"
    keepalive_s: int = 30
    username: str | None = None
    password_file: Path | None = None
    tls: bool = False
    ca_file: Path | None = None
    cert_file: Path | None = None
    key_file: Path | None = None
    backlog_windows_per_s: float = 20.0
    max_inflight_windows: int = 10
    reconnect_min_s: float = 1.0
    reconnect_max_s: float = 60.0

    def topic(self, machine: str, kind: str) -> str:
        return f"{self.topic_prefix}/{machine}/{kind}"


def parse_mqtt(root: Table, base: Path) -> Mqtt:
    """``[mqtt]``; file paths are relative to the profile's folder ``base`` and must exist."""
    t = root.table("mqtt")
    if t is None:
        return Mqtt()
    d = Mqtt()
    enabled = t.bool("enabled", default=False)
    host = t.str("host", default=None, expected="the broker's host name or IP address")
    tls = t.bool("tls", default=False)
    port = t.int("port", default=8883 if tls else 1883, min=1, max=65535)
    client_id = t.str("client_id", default="", pattern=re.compile(r"[A-Za-z0-9_.:-]{0,64}"),
                      expected="up to 64 letters, digits, _ . : - (empty: cncgw-<machine>)")
    prefix = t.str("topic_prefix", default="cncgw", pattern=re.compile(r"[^/#+\x00]+(/[^/#+\x00]+)*"),
                   expected="topic levels separated by /, without wildcards (+, #) or empty levels")
    keepalive = t.int("keepalive_s", default=30, min=5, max=3600)
    username = t.str("username", default=None, expected="the user name the broker knows this gateway by")
    wanted = {"password_file": "a file holding the password (one line), readable by the gateway only",
              "ca_file": "the CA certificate(s) that signed the broker's certificate (PEM)",
              "cert_file": "this gateway's client certificate (PEM)",
              "key_file": "the client certificate's private key (PEM)"}
    files = {key: t.str(key, default=None, expected=what) for key, what in wanted.items()}
    rate = t.float("backlog_windows_per_s", default=20.0, min=0.0, min_exclusive=True, max=10000.0)
    inflight = t.int("max_inflight_windows", default=10, min=1, max=1000)
    rmin = t.float("reconnect_min_s", default=1.0, min=0.0, min_exclusive=True, max=3600.0)
    rmax = t.float("reconnect_max_s", default=60.0, min=0.0, min_exclusive=True, max=86400.0)
    t.done()
    paths: dict[str, Path | None] = {}
    for key, name in files.items():
        paths[key] = None
        if name:
            p = base / name
            if not p.is_file():
                t.problem(key, f'file "{p}" not found: expected {wanted[key]}, relative to the profile')
            paths[key] = p
    if enabled and host is None:
        t.problem("host", "mqtt.enabled = true needs the broker's address: set mqtt.host")
    if paths["password_file"] is not None and username is None:
        t.problem("password_file", "a password needs a user name: set mqtt.username")
    if (paths["cert_file"] is None) != (paths["key_file"] is None):
        t.problem("cert_file" if paths["cert_file"] is None else "key_file",
                  "a client certificate needs both cert_file and key_file")
    tls_keys = [k for k in ("ca_file", "cert_file", "key_file") if paths[k] is not None]
    if tls_keys and not tls:
        t.problem(tls_keys[0], f"{', '.join(tls_keys)} given but mqtt.tls is false: set tls = true to use them")
    if rmin is not None and rmax is not None and rmax < rmin:
        t.problem("reconnect_max_s", f"expected a number >= reconnect_min_s ({rmin:g}), got {rmax:g}")

    def pick(value: Any, default: Any) -> Any:
        return default if value is None else value

    return Mqtt(enabled=bool(enabled), host=pick(host, d.host), port=pick(port, d.port),
                client_id=pick(client_id, ""), topic_prefix=pick(prefix, d.topic_prefix),
                keepalive_s=pick(keepalive, d.keepalive_s), username=username, password_file=paths["password_file"],
                tls=bool(tls), ca_file=paths["ca_file"], cert_file=paths["cert_file"], key_file=paths["key_file"],
                backlog_windows_per_s=pick(rate, d.backlog_windows_per_s),
                max_inflight_windows=pick(inflight, d.max_inflight_windows),
                reconnect_min_s=pick(rmin, d.reconnect_min_s), reconnect_max_s=pick(rmax, d.reconnect_max_s))
