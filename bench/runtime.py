"""Live gateway benchmark: estimator cost per window, latency from window close to verified write, and CPU and
memory of a gateway sampling at the full 2 ms for one simulated hour.

The simulated machine, its ADC board and its CNC run in another process (``cncgw simulate serve``), as real
devices would be other machines; the gateway (sampler thread, window closer, SQLite store, estimator,
compensation writer over Modbus TCP with read-back and heartbeat, OPC UA server) runs in this one. The ADC
board is read every 2 ms of wall time; with ``--speedup N`` a window closes every 60/N wall seconds, so the
per-window work (store, estimator, writer) runs N times more often than on a real machine: the CPU figure
is an upper bound for the same sampling in real time.

    .venv/bin/python bench/runtime.py [--hours 1] [--speedup 60] [--windows 20000]

It also runs the same gateway as a dry run (compensation off) and reports the compensation writer
thread's CPU in both (the dry run's writer once spun on a heartbeat it never sends).

``--restarts N`` instead measures what a CNC's heartbeat watchdog sees when the gateway dies: ``cncgw run``
at 1x (real time, the simulated CNC's watchdog 5 s, a beat a second) over a store holding ``--history-days``
of windows, killed with SIGKILL N times; after the systemd unit's ``RestartSec`` it is started again, as
systemd would, and a Modbus client polling the CNC's heartbeat register every 5 ms times the silence from
the last beat before the kill to the first beat after. ``--busy K`` runs K CPU-bound processes beside it
(a loaded PC); ``--gateway-root DIR`` runs another checkout's code (to compare before and after).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from gateway.clock import ScaledClock  # noqa: E402
from gateway.live.runtime import LiveGateway  # noqa: E402
from gateway.live.tracking import DisplacementTracker  # noqa: E402
from gateway.model import load_model  # noqa: E402
from gateway.profile import load_profile  # noqa: E402
from gateway.profile.live import Live  # noqa: E402
from gateway.record_store import STORE_NAME, RecordStore  # noqa: E402
from gateway.windows import WindowRecord  # noqa: E402

CNCGW = str(Path(sys.executable).with_name("cncgw"))
#: the simulated machine and devices in their own process; the CNC's watchdog is raised to 1 s of wall time
#: (5 s of clock time would be 83 ms of wall time at 60x: a starved simulator process would trip it)
SIM = """
import dataclasses, sys
from pathlib import Path
from gateway.clock import ScaledClock
from simulators.devices import DeviceSetConfig
from simulators.devices.cli import machine_source, serve_until_stopped
from simulators.devices.cnc import CompensationConfig
from simulators.devices.profile_out import profile_for
speedup, out, duration, origin = float(sys.argv[1]), Path(sys.argv[2]), float(sys.argv[3]), float(sys.argv[4])
watchdog = max(5.0, speedup)
clock = ScaledClock(speedup, origin=origin)
cnc = dataclasses.replace(CompensationConfig(), heartbeat_timeout_s=watchdog)
def on_start(devices):
    text = profile_for(devices, "adc-tcp", compensate=True, max_step_um=5.0, heartbeat_period_s=watchdog / 5,
                       watchdog_s=watchdog)
    tmp = out.with_name(out.name + ".tmp")
    tmp.write_text(text + '\\n[opcua]\\nhost = "127.0.0.1"\\nport = 0\\n')
    tmp.replace(out)
serve_until_stopped(machine_source("spindle-feeds", clock), clock,
                    DeviceSetConfig(adc_rtu=None, can=None, dcon=None, cnc=cnc), duration_s=duration,
                    on_start=on_start)
"""
MODEL = ROOT / "profiles" / "sim-vmc.model.toml"


def estimator_cost(n: int) -> None:
    """Per-window estimator cost (step + one-window prediction) and the rebuild from a long history."""
    from types import MappingProxyType

    model = load_model(MODEL)
    est = DisplacementTracker(model, window_s=60.0, live=Live())
    rng = np.random.default_rng(1)
    ref = model.reference
    times = []
    for k in range(n):
        factors = {f: ref[f] + abs(rng.normal(0, 1)) * (100 if "speed" in f or "feed" in f else 1) for f in ref}
        rec = WindowRecord(index=k, start_s=60.0 * k, end_s=60.0 * (k + 1), status="good",
                           factors=MappingProxyType(factors), channels=MappingProxyType({}),
                           devices=MappingProxyType({}))
        t0 = time.perf_counter()
        est.update(rec)
        times.append(time.perf_counter() - t0)
    t = np.array(times) * 1e6
    # baseline in the same run: the bare ModelStepper step, nothing else (no records, gap policy, prediction)
    bare, du = est.dm.stepper(), rng.normal(0, 1, (n, len(model.input_names)))
    steps = []
    for k in range(n):
        t0 = time.perf_counter()
        bare.step(du[k])
        steps.append(time.perf_counter() - t0)
    b = np.array(steps) * 1e6
    paths = sum(1 for p in model.paths.values() if p.terms)
    print(f"estimator ({len(model.axes)} axes x {len(model.factors)} factors, {paths} non-zero paths): per window "
          f"median {np.median(t):.0f} us, p99 {np.percentile(t, 99):.0f} us, max {t.max():.0f} us over {n} windows "
          f"(step + one-window prediction + record handling); the bare step alone: median {np.median(b):.0f} us "
          f"(update / bare step {np.median(t) / np.median(b):.2f}x)")
    from gateway.live.tracking import history_windows

    hist = history_windows(model, 60.0, Live())
    print(f"rebuild on start reads at most {hist} windows ({hist / 60 / 24:.1f} days: 20 x the slowest time constant)")


def proc_stat() -> tuple[float, int]:
    """(CPU seconds of this process, resident memory in bytes)."""
    t = os.times()
    rss = 0
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                rss = int(line.split()[1]) * 1024
    return t.user + t.system, rss


def live_run(hours: float, speedup: float, tmp: Path, *, dry: bool = False) -> float:
    """One live run; returns the compensation writer thread's CPU (share of one core)."""
    served = tmp / "served.toml"
    wall = hours * 3600.0 / speedup
    # from 45 min: the spindle starts at 60 min, so the hour holds heating and compensation writes
    server = subprocess.Popen([sys.executable, "-c", SIM, str(speedup), str(served), str(wall + 30), "2700"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=ROOT)
    try:
        deadline = time.monotonic() + 30
        while not served.exists():
            if time.monotonic() > deadline or server.poll() is not None:
                raise SystemExit("the simulated devices did not start")
            time.sleep(0.1)
        if dry:  # the same gateway, compensation off: a dry run
            served.write_text(served.read_text().replace("[compensation]\nenabled = true", "[compensation]\n"
                                                         "enabled = false"))
        profile = load_profile(served)
        assert profile.compensation.enabled is not dry
        model = load_model(MODEL)
        clock = ScaledClock(speedup)
        from threadpoolctl import threadpool_limits

        samples = []
        with threadpool_limits(limits=1):
            _, rss0 = proc_stat()
            t0 = time.monotonic()
            with LiveGateway(profile, model=model, data_dir=tmp / "data", clock=clock) as gw:
                started = time.monotonic() - t0
                cpu_start, _ = proc_stat()
                t_start = time.monotonic()
                while time.monotonic() - t_start < wall:
                    time.sleep(1.0)
                    samples.append((time.monotonic() - t_start, *proc_stat()))
                health = gw.health()
                cpu_end, rss_end = proc_stat()
                run_s = time.monotonic() - t_start
                lat = np.array(gw.writer.latencies_s) * 1e3
                upd = np.array(gw.update_s) * 1e6
                sampler = gw.acquisition.samplers[0]
                lateness = (sampler.lateness_quantile(0.5) * 1e3, sampler.lateness_quantile(0.99) * 1e3)
        writer = gw.writer
        writer_cpu = writer.cpu_s / (writer.stopped_wall - writer.started_wall)
        with RecordStore(tmp / "data" / STORE_NAME) as store:
            recs = list(store.windows())
    finally:
        server.terminate()
        server.wait(timeout=10)
    dev = health.devices[0]
    if dry:
        full = recs[1:]
        print(f"\ndry run (compensation off), {hours:g} h at {speedup:g}x ({run_s:.0f} s wall): compensation writer "
              f"thread {writer_cpu:.2%} of one core; {dev.reads_ok / run_s:.1f} reads/s; "
              f"{sum(r.status == 'good' for r in full)} of {len(full)} whole windows good")
        return writer_cpu
    full = recs[1:]
    print(f"\nlive: {hours:g} h of spindle-feeds at {speedup:g}x ({run_s:.0f} s wall), ADC over Modbus TCP every 2 ms "
          f"(simulator in another process), CNC over Modbus TCP, OPC UA on; {os.cpu_count()} cores; Python "
          f"{sys.version.split()[0]}")
    print(f"start (store, estimator, writer sync, OPC UA, acquisition): {started:.2f} s")
    print(f"sampling: {dev.reads_ok / run_s:.1f} reads/s, {dev.ticks_skipped} ticks skipped, "
          f"{dev.reads_failed} failed; lateness p50 {lateness[0]:.2f} ms, p99 {lateness[1]:.2f} ms; windows "
          f"{len(recs)} ({sum(r.status == 'good' for r in full)} of {len(full)} whole ones good, missed ticks at "
          f"most {max((r.missed_ticks for r in full), default=0)} a window)")
    print(f"estimator update in the closer: median {np.median(upd):.0f} us, max {upd.max():.0f} us")
    print(f"window close -> verified write (estimate, submit, limits, Modbus write, read-back): median "
          f"{np.median(lat):.2f} ms, p99 {np.percentile(lat, 99):.2f} ms, max {lat.max():.2f} ms over {len(lat)} "
          f"writes; {health.compensation.beats} heartbeats, {health.compensation.failures} failures; "
          f"alarms at the end: {[a.name for a in health.alarms] or 'none'}")
    cpu = (cpu_end - cpu_start) / run_s
    rss = np.array([s[2] for s in samples]) / 2**20
    ts = np.array([s[0] for s in samples])
    slope = np.polyfit(ts, rss, 1)[0] * 3600 / speedup if len(ts) > 2 else float("nan")
    thread = sampler.cpu_s / (sampler.stopped_wall - sampler.started_wall)
    print(f"CPU of the gateway process: {cpu:.0%} of one core (sampler thread alone {thread:.0%}, compensation "
          f"writer thread {writer_cpu:.2%}); memory: RSS "
          f"{rss0 / 2**20:.0f} MiB before start, {rss[0]:.0f} MiB after 1 s, {rss_end / 2**20:.0f} MiB at the end; "
          f"growth {slope:+.2f} MiB per simulated hour")
    return writer_cpu


BUSY = "while True:\n    pass\n"


def _unit(key: str, default: str | None = None) -> str:
    """A setting of the bundled systemd unit (``RestartSec``, ``Nice``)."""
    for line in (ROOT / "deploy" / "cncgw@.service").read_text().splitlines():
        if line.startswith(f"{key}="):
            return line.split("=", 1)[1].strip()
    if default is None:
        raise SystemExit(f"deploy/cncgw@.service has no {key}")
    return default


def _prefill(data: Path, profile: object, days: float) -> int:
    """A store of ``days`` of one-minute windows ending now (as a gateway running that long leaves it)."""
    from types import MappingProxyType

    from gateway.record_store import record_to_json
    from gateway.windows import ChannelStats, DeviceQuality

    data.mkdir(parents=True, exist_ok=True)
    n = int(days * 86400 / 60)
    last = int(time.time() // 60) - 1
    ch = ChannelStats(count=30000, coverage=1.0, mean=1.0, mean_square=1.0, mean_abs=1.0, min=0.0, max=2.0,
                      saturated=0, bad=0)
    dq = DeviceQuality(ticks_expected=30000, ticks_run=30000, ticks_skipped=0, reads_ok=30000, reads_failed=0,
                       timeouts=0, off_scan_ticks=0, largest_gap_s=0.002, lateness_max_s=0.001,
                       read_time_max_s=0.001, tick_s=0.002)
    with RecordStore(data / STORE_NAME, profile=profile) as store:  # type: ignore[arg-type]
        rows = []
        for k in range(last - n + 1, last + 1):
            factors = {f.name: 0.0 for f in profile.factors}  # type: ignore[attr-defined]
            rec = WindowRecord(index=k, start_s=60.0 * k, end_s=60.0 * (k + 1), status="good",
                               factors=MappingProxyType(factors),
                               channels=MappingProxyType({c.name: ch for c in profile.channels}),  # type: ignore
                               devices=MappingProxyType({"adc": dq}))
            rows.append((k, rec.start_s, rec.end_s, "good", 1.0, 30000, 30000, 0, 0.002, "", time.time(),
                         record_to_json(rec)))
        with store._lock:
            store._db.execute("BEGIN")
            store._db.executemany("INSERT INTO windows VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)", rows)
            store._db.execute("COMMIT")
    return n


class _BeatWatch:
    """Polls the CNC's heartbeat register (and its trip counter) every 5 ms from its own Modbus client."""

    def __init__(self, host: str, port: int) -> None:
        import threading

        from pymodbus.client import ModbusTcpClient

        self.client = ModbusTcpClient(host, port=port, timeout=0.5, retries=0)
        self.changes: list[float] = []  # wall times (monotonic) the register changed
        self.trips = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        last = None
        while not self._stop.wait(0.005):
            try:
                rr = self.client.read_holding_registers(6, count=1, device_id=1)
                st = self.client.read_input_registers(6, count=2, device_id=1)
            except Exception:
                continue
            if rr.isError() or st.isError():
                continue
            beat = rr.registers[0]
            self.trips = st.registers[1]
            if last is not None and beat != last:
                self.changes.append(time.monotonic())
            last = beat

    def first_after(self, t: float, timeout_s: float) -> float | None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            later = [c for c in self.changes if c > t]
            if later:
                return later[0]
            time.sleep(0.01)
        return None

    def last_before(self, t: float) -> float | None:
        earlier = [c for c in self.changes if c <= t]
        return earlier[-1] if earlier else None

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self.client.close()


def restart_run(n: int, tmp: Path, *, busy: int, history_days: float, gateway_root: Path,
                nice: int | None) -> None:
    """Kill -9 and restart ``cncgw run`` ``n`` times; print the silence the CNC's watchdog sees each time."""
    import random
    import re
    import signal

    restart_s = float(_unit("RestartSec").rstrip("s"))
    nice = int(_unit("Nice", "0")) if nice is None else nice
    served = tmp / "served.toml"
    server = subprocess.Popen([sys.executable, "-c", SIM, "1", str(served), str(60 + n * 30), "2700"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=ROOT)
    hogs: list[subprocess.Popen[bytes]] = []
    watch = None
    proc = None
    try:
        deadline = time.monotonic() + 30
        while not served.exists():
            if time.monotonic() > deadline or server.poll() is not None:
                raise SystemExit("the simulated devices did not start")
            time.sleep(0.1)
        profile = load_profile(served)
        watchdog = profile.compensation.watchdog_s
        data = tmp / "data"
        windows = _prefill(data, profile, history_days)
        watch = _BeatWatch(profile.compensation.host or "127.0.0.1", profile.compensation.port)
        hogs = [subprocess.Popen([sys.executable, "-c", BUSY]) for _ in range(busy)]
        env = {**os.environ, "PYTHONPATH": str(gateway_root)}
        logs = []

        def start() -> subprocess.Popen[bytes]:
            log_path = tmp / f"gateway-{len(logs)}.log"
            logs.append(log_path)
            return subprocess.Popen([sys.executable, "-m", "gateway.cli", "run", "--profile", str(served),
                                     "--data", str(data)], cwd=gateway_root, env=env,
                                    stdout=subprocess.DEVNULL, stderr=open(log_path, "wb"),
                                    preexec_fn=lambda: os.setpriority(os.PRIO_PROCESS, 0, nice))

        t0 = time.monotonic()
        proc = start()
        if watch.first_after(t0, 60.0) is None:
            raise SystemExit(f"the gateway never beat: see {logs[-1]}")
        trips0 = watch.trips
        silences, to_beat = [], []
        rng = random.Random(1)
        for _ in range(n):
            time.sleep(4.0 + rng.random())  # running, beating once a second; killed at any point of a beat
            with RecordStore(data / STORE_NAME) as store:
                committed = store.last_index
            kill = time.monotonic()
            proc.send_signal(signal.SIGKILL)
            proc.wait()
            last = watch.last_before(kill)
            time.sleep(restart_s)  # systemd's RestartSec
            proc = start()
            beat = watch.first_after(kill, 30.0)
            if beat is None or last is None:
                raise SystemExit(f"no beat after a restart: see {logs[-1]}")
            silences.append(beat - last)
            to_beat.append(beat - kill)
            with RecordStore(data / STORE_NAME) as store:
                if store.last_index is None or committed is None or store.last_index < committed:
                    raise SystemExit("committed windows lost")
        time.sleep(2.0)
        trips = watch.trips - trips0
        rebuilds = [float(m.group(1)) for p in logs
                    for m in [re.search(r"estimator rebuilt from \d+ stored windows .* in ([\d.]+) s",
                                        p.read_text(errors="replace"))] if m]
    finally:
        if proc is not None:
            proc.send_signal(signal.SIGTERM)
            proc.wait(timeout=30)
        for h in hogs:
            h.kill()
            h.wait()
        if watch is not None:
            watch.close()
        server.terminate()
        server.wait(timeout=10)
    s, b = np.array(silences), np.array(to_beat)
    print(f"restart: {n} x kill -9 of `cncgw run` at 1x (code from {gateway_root}), {busy} busy process(es) beside "
          f"it on {os.cpu_count()} cores, a store of {windows} windows ({history_days:g} days), the unit's "
          f"RestartSec {restart_s:g} s and Nice {nice}, CNC watchdog {watchdog:g} s, a beat every "
          f"{profile.compensation.heartbeat_period_s:g} s")
    print(f"kill -> first beat of the new process: median {np.median(b):.2f} s, max {b.max():.2f} s "
          f"(RestartSec included); start -> first beat {np.median(b) - restart_s:.2f} s median")
    print(f"silence the CNC saw (last beat before the kill -> first beat after): median {np.median(s):.2f} s, "
          f"max {s.max():.2f} s = {s.max() / watchdog:.0%} of the watchdog; watchdog trips: {trips}; committed "
          f"windows lost: 0")
    if rebuilds:
        print(f"history replay (logged by the gateway): median {np.median(rebuilds):.2f} s, max {max(rebuilds):.2f} s")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--hours", type=float, default=1.0)
    p.add_argument("--speedup", type=float, default=60.0)
    p.add_argument("--windows", type=int, default=20000, help="windows for the estimator cost")
    p.add_argument("--restarts", type=int, default=0, metavar="N", help="measure N kill -9 restarts instead")
    p.add_argument("--busy", type=int, default=2, metavar="K", help="--restarts: CPU-bound processes beside it")
    p.add_argument("--history-days", type=float, default=10.0, help="--restarts: stored history to replay")
    p.add_argument("--gateway-root", type=Path, default=ROOT, help="--restarts: the checkout whose code to run")
    p.add_argument("--nice", type=int, default=None, help="--restarts: the gateway's nice level (default: the unit's)")
    args = p.parse_args()
    if args.restarts:
        with tempfile.TemporaryDirectory(prefix="cncgw-bench-") as tmp:
            restart_run(args.restarts, Path(tmp), busy=args.busy, history_days=args.history_days,
                        gateway_root=args.gateway_root.resolve(), nice=args.nice)
        return 0
    estimator_cost(args.windows)
    with tempfile.TemporaryDirectory(prefix="cncgw-bench-") as tmp:
        live_run(args.hours, args.speedup, Path(tmp))
    with tempfile.TemporaryDirectory(prefix="cncgw-bench-") as tmp:
        live_run(min(args.hours, 0.25), args.speedup, Path(tmp), dry=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
