"""A fleet through one broker: 200 gateways' windows, end-to-end latency, CPU, and a broker outage replayed.

    .venv/bin/python bench/mqtt.py [--gateways 200] [--speedup 60] [--minutes 30] [--outage-min 10]
                                   [--workers 2] [--broker mosquitto]

Each simulated gateway is the real publish path: an :class:`gateway.live.outputs.mqtt.MqttOutput` with its own
outbox (SQLite, one synchronous commit a window) and its own paho client, handed the bundled simulated
machine's window snapshot (9 factors, 3 axes) at the end of every window of an accelerated clock (``--speedup``
60: a one-minute window every wall second). The gateways run in ``--workers`` processes; the broker is
mosquitto (``apt-get install mosquitto``; with persistence, as a plant's broker would run) in its own process;
one consumer (a historian: a paho client with a persistent session, QoS 1, ``cncgw/+/+``) counts every
message and drops QoS 1 re-deliveries by (machine, kind, window).

Phases: ``--minutes`` of steady publishing (latency from the window's close to the consumer's receipt, p50 /
p99 / max; CPU of the gateway processes and of the broker), then the broker is stopped for ``--outage-min``
simulated minutes while windows keep closing, started again, and publishing goes on for 5 more minutes. At
the end every window of every gateway must have reached the consumer exactly once after de-duplication:
the figures printed are the windows expected, received, lost and duplicated (raw and after de-duplication).
Message sizes are measured on the payloads the gateway sends.
"""

from __future__ import annotations

import argparse
import contextlib
import getpass
import hashlib
import json
import math
import multiprocessing as mp
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from types import MappingProxyType

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from gateway.live.outputs import WindowSnapshot  # noqa: E402
from gateway.live.outputs.mqtt import MqttOutput, describe_payload_sizes  # noqa: E402
from gateway.profile.mqtt import Mqtt  # noqa: E402

WINDOW_S = 60.0
PROFILE = ROOT / "profiles" / "sim-vmc.toml"


def factor_units() -> dict[str, str]:
    from gateway.profile import load_profile

    return {f.name: f.unit for f in load_profile(PROFILE).factors}


def snapshot(machine: str, k: int, units: dict[str, str]) -> WindowSnapshot:
    factors = {name: 1000.0 + (k % 60) + i * 0.123456789 for i, name in enumerate(units)}
    return WindowSnapshot(
        machine=machine, window=k, end_s=(k + 1) * WINDOW_S, status="good", coverage=0.99967,
        samples_taken=29990, samples_expected=30000, missed_ticks=10, factors=MappingProxyType(factors),
        factor_units=MappingProxyType(units),
        estimate_um=MappingProxyType({"x": 1.234567, "y": -0.345678, "z": -14.456789 - k % 7}), usable=True,
        mode="write", commanded_um=MappingProxyType({"x": -1.2, "y": 0.3, "z": 14.5}),
        applied_um=MappingProxyType({"x": -1.2, "y": 0.3, "z": 14.5}), verified=True, writes=k)


# -- the broker ----------------------------------------------------------------------------------------------
class Mosquitto:
    """mosquitto on 127.0.0.1 with persistence in a temp dir; stop/start keep the port and the sessions."""

    def __init__(self, workdir: Path) -> None:
        exe = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
        if not Path(exe).exists():
            sys.exit("bench/mqtt.py: mosquitto not found (apt-get install mosquitto)")
        self.exe = exe
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            self.port = s.getsockname()[1]
        self.conf = workdir / "mosquitto.conf"
        (workdir / "db").mkdir()
        self.conf.write_text(f"listener {self.port} 127.0.0.1\nallow_anonymous true\npersistence true\n"
                             f"persistence_location {workdir / 'db'}/\nmax_queued_messages 1000000\n"
                             f"max_inflight_messages 100\nlog_type error\nuser {getpass.getuser()}\n")
        self.proc: subprocess.Popen | None = None
        self.cpu_s = 0.0

    def start(self) -> None:
        self.proc = subprocess.Popen([self.exe, "-c", str(self.conf)], stdout=subprocess.DEVNULL)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            with socket.socket() as s, contextlib.suppress(OSError):  # refused while it starts
                s.connect(("127.0.0.1", self.port))
                return
            time.sleep(0.05)
        raise RuntimeError("mosquitto did not start")

    def cpu_now(self) -> float:
        if self.proc is None:
            return self.cpu_s
        return self.cpu_s + proc_cpu_s(self.proc.pid)

    def stop(self) -> None:
        if self.proc is not None:
            self.cpu_s += proc_cpu_s(self.proc.pid)
            self.proc.send_signal(signal.SIGTERM)  # saves the persistent sessions
            self.proc.wait(20)
            self.proc = None


def proc_cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


# -- gateways (worker processes) ----------------------------------------------------------------------------
def worker(names: list[str], port: int, workdir: str, speedup: float, n_windows: int, conn) -> None:
    import logging

    logging.basicConfig(level=logging.ERROR)
    units = factor_units()
    outs = []
    for name in names:
        settings = Mqtt(enabled=True, host="127.0.0.1", port=port, backlog_windows_per_s=20.0,
                        max_inflight_windows=10, reconnect_min_s=0.5, reconnect_max_s=2.0)
        outs.append(MqttOutput(settings, machine=name, data_dir=Path(workdir) / name, window_s=WINDOW_S,
                               factor_units=units).start())
    while not all(o.status().connected for o in outs):
        time.sleep(0.05)
    conn.send("ready")
    t0 = conn.recv()
    cpu0 = time.process_time()
    late = []
    for k in range(n_windows):
        due = t0 + (k + 1) * WINDOW_S / speedup
        time.sleep(max(0.0, due - time.time()))
        late.append(time.time() - due)
        for o in outs:
            o.window(snapshot(o.machine, k, units))
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and not all(o.status().delivered_through == n_windows - 1 for o in outs):
        time.sleep(0.1)
    cpu = time.process_time() - cpu0
    delivered = sum(1 for o in outs if o.status().delivered_through == n_windows - 1)
    sent = sum(o.messages_sent for o in outs)
    for o in outs:
        o.stop()
    late.sort()
    conn.send({"cpu_s": cpu, "delivered_all": delivered, "messages_sent": sent,
               "late_p99_s": late[int(0.99 * (len(late) - 1))]})


# -- the consumer --------------------------------------------------------------------------------------------
class Historian:
    """A paho subscriber with a persistent session: first receipt time per (machine, kind, window)."""

    def __init__(self, port: int) -> None:
        import paho.mqtt.client as paho

        self.first: dict[tuple[str, str, int], float] = {}
        self.digest: dict[tuple[str, str, int], bytes] = {}
        self.raw = 0
        self.conflicts = 0  # a re-delivery whose content differs from the first copy
        self.lock = threading.Lock()
        c = paho.Client(callback_api_version=paho.CallbackAPIVersion.VERSION2, client_id="historian",
                        clean_session=False)
        c.on_message = self._on_message
        c.on_connect = lambda cl, u, f, rc, p: cl.subscribe("cncgw/+/+", qos=1)
        c.reconnect_delay_set(0.2, 1)
        c.connect("127.0.0.1", port, keepalive=30)
        c.loop_start()
        self.client = c

    def _on_message(self, client, userdata, msg) -> None:
        now = time.time()
        kind = msg.topic.rsplit("/", 1)[1]
        if kind == "status":
            return
        p = json.loads(msg.payload)
        key = (p["machine"], kind, p["window"])
        digest = hashlib.blake2b(msg.payload, digest_size=8).digest()
        with self.lock:
            self.raw += 1
            if self.first.setdefault(key, now) != now and self.digest[key] != digest:
                self.conflicts += 1
            self.digest.setdefault(key, digest)

    def stop(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()


def run(*, gateways: int, workers: int, speedup: float, minutes: int, outage_min: int, outbox_dir: str | None,
        quiet: bool = False) -> dict:
    """One fleet through a fresh mosquitto: steady phase, outage (if ``outage_min``), replay; the figures."""
    say = (lambda *a: None) if quiet else print
    work = Path(tempfile.mkdtemp(prefix="cncgw-bench-mqtt-", dir=outbox_dir))
    broker = Mosquitto(work)
    broker.start()
    hist = Historian(broker.port)
    n_windows = minutes + outage_min + (5 if outage_min else 0)
    names = [f"vmc-{i:04d}" for i in range(gateways)]
    ctx = mp.get_context("spawn")
    procs, pipes = [], []
    for w in range(min(workers, gateways)):
        parent, child = ctx.Pipe()
        p = ctx.Process(target=worker, args=(names[w::workers], broker.port, str(work), speedup, n_windows, child))
        p.start()
        procs.append(p)
        pipes.append(parent)
    for p in pipes:
        assert p.recv() == "ready"
    t0 = time.time() + 0.5
    for p in pipes:
        p.send(t0)
    worker_cpu0, broker_cpu0 = sum(proc_cpu_s(p.pid) for p in procs), broker.cpu_now()  # start-up left out
    say(f"{gateways} gateways in {len(procs)} processes connected; {n_windows} windows each at {speedup:g}x, "
        f"outboxes in {work} ({gateways * speedup / WINDOW_S:.0f} windows/s, "
        f"{4 * gateways * speedup / WINDOW_S:.0f} messages/s through the broker)")

    def due(k: int) -> float:  # wall time window k closes
        return t0 + (k + 1) * WINDOW_S / speedup

    steady_end = due(minutes - 1) + 0.8 * WINDOW_S / speedup  # the last steady window has been delivered
    time.sleep(max(0.0, steady_end - time.time()))
    broker_cpu_steady = broker.cpu_now() - broker_cpu0
    worker_cpu_steady = sum(proc_cpu_s(p.pid) for p in procs) - worker_cpu0
    steady_wall = time.time() - (t0 - 0.5)
    t_back = math.nan
    if outage_min:
        broker.stop()
        say(f"broker stopped after window {minutes - 1}: {outage_min} simulated minutes of outage "
            f"({outage_min * WINDOW_S / speedup:.1f} s)")
        time.sleep(max(0.0, due(minutes + outage_min - 1) + 0.1 - time.time()))
        t_back = time.time()
        broker.start()
    kinds = ("estimate", "offsets", "factors", "health")
    expected = {(n, kind, k) for n in names for kind in kinds for k in range(n_windows)}
    results = [p.recv() for p in pipes]
    for p in procs:
        p.join(30)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and len(hist.first) < len(expected):
        time.sleep(0.1)
    hist.stop()
    backlog = [hist.first[(n, "estimate", k)] for n in names for k in range(minutes, minutes + outage_min)
               if (n, "estimate", k) in hist.first]
    lat = sorted(t - due(k) for (_, _, k), t in hist.first.items() if k < minutes)
    broker.stop()
    shutil.rmtree(work, ignore_errors=True)
    got = set(hist.first)
    n = len(lat)
    return {"p50_ms": lat[n // 2] * 1000, "p99_ms": lat[int(0.99 * (n - 1))] * 1000, "max_ms": lat[-1] * 1000,
            "n_lat": n, "gateway_cpu": worker_cpu_steady / steady_wall, "broker_cpu": broker_cpu_steady / steady_wall,
            "steady_wall": steady_wall, "late_p99_ms": max(r["late_p99_s"] for r in results) * 1000,
            "backlog_s": (max(backlog) - t_back) if backlog else math.nan, "expected": len(expected),
            "received": len(got), "lost": sorted(expected - got), "raw": hist.raw, "conflicts": hist.conflicts,
            "delivered_all": sum(r["delivered_all"] for r in results)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gateways", type=int, default=200)
    ap.add_argument("--speedup", type=float, default=60.0)
    ap.add_argument("--minutes", type=int, default=30, help="simulated minutes of steady publishing")
    ap.add_argument("--outage-min", type=int, default=10, help="simulated minutes the broker is down")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--outbox-dir", default=None,
                    help="where the gateways' outboxes live (default: a temp dir; /dev/shm leaves out the fsyncs)")
    args = ap.parse_args()

    units = factor_units()
    sizes = describe_payload_sizes(snapshot("vmc-0001", 1234, units))
    per_window = sum(sizes.values())
    print(f"message sizes (payload + topic, bytes): {sizes}; {per_window} B a window, "
          f"{per_window * 1440 / 1e6:.2f} MB a machine-day at one window a minute")
    base = run(gateways=1, workers=1, speedup=args.speedup, minutes=10, outage_min=0, outbox_dir=args.outbox_dir,
               quiet=True)
    print(f"baseline, one gateway alone ({base['n_lat']} messages): latency window close -> historian p50 "
          f"{base['p50_ms']:.1f} ms, p99 {base['p99_ms']:.1f} ms; {base['gateway_cpu']:.2%} of a core at "
          f"{args.speedup:g}x")
    r = run(gateways=args.gateways, workers=args.workers, speedup=args.speedup, minutes=args.minutes,
            outage_min=args.outage_min, outbox_dir=args.outbox_dir)
    print(f"steady ({args.minutes} windows x {args.gateways} gateways, {r['n_lat']} messages): latency window close "
          f"-> historian p50 {r['p50_ms']:.1f} ms, p99 {r['p99_ms']:.1f} ms, max {r['max_ms']:.1f} ms "
          f"(p99 {r['p99_ms'] / base['p99_ms']:.1f}x the lone gateway's)")
    print(f"CPU during the steady phase ({r['steady_wall']:.1f} s wall): gateways {r['gateway_cpu']:.0%} of a core "
          f"for {args.gateways} ({r['gateway_cpu'] / args.gateways:.2%} of a core each at {args.speedup:g}x; "
          f"{r['gateway_cpu'] / args.gateways / base['gateway_cpu']:.2f}x the lone gateway's), broker (mosquitto) "
          f"{r['broker_cpu']:.1%} of a core; worker scheduling lateness p99 {r['late_p99_ms']:.1f} ms")
    if args.outage_min:
        print(f"outage: the backlog of {args.outage_min} windows per gateway reached the historian "
              f"{r['backlog_s']:.1f} s after the broker was back")
    print(f"windows x kinds expected {r['expected']}, received {r['received']}, lost {len(r['lost'])}, raw messages "
          f"{r['raw']} ({r['raw'] - r['received']} QoS 1 re-deliveries dropped by window id, {r['conflicts']} of them "
          f"differing from the first copy); gateways whose every window was acknowledged: "
          f"{r['delivered_all']}/{args.gateways}")
    if r["lost"]:
        print(f"LOST (first 5): {r['lost'][:5]}")


if __name__ == "__main__":
    main()
