"""Live gateway benchmark: estimator cost per window, latency from window close to verified write, and CPU and
memory of a gateway sampling at the full 2 ms for one simulated hour.

The simulated machine, its ADC board and its CNC run in another process (``cncgw simulate serve``), as real
devices would be other machines; the gateway (sampler thread, window closer, SQLite store, estimator,
compensation writer over Modbus TCP with read-back and heartbeat, OPC UA server) runs in this one. The ADC
board is read every 2 ms of wall time; with ``--speedup N`` a window closes every 60/N wall seconds, so the
per-window work (store, estimator, writer) runs N times more often than on a real machine: the CPU figure
is an upper bound for the same sampling in real time.

    .venv/bin/python bench/runtime.py [--hours 1] [--speedup 60] [--windows 20000]
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
from gateway.live.estimator import Estimator  # noqa: E402
from gateway.live.runtime import LiveGateway  # noqa: E402
from gateway.live.settings import Live  # noqa: E402
from gateway.model import load_model  # noqa: E402
from gateway.profile import load_profile  # noqa: E402
from gateway.records import STORE_NAME, RecordStore  # noqa: E402
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
    est = Estimator(model, window_s=60.0, live=Live())
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
    # baseline in the same run: the bare LiveEstimator step, nothing else (no records, gap policy, prediction)
    bare, du = est.dm.live(), rng.normal(0, 1, (n, len(model.input_names)))
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
    from gateway.live.estimator import history_windows

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


def live_run(hours: float, speedup: float, tmp: Path) -> None:
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
        profile = load_profile(served)
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
        with RecordStore(tmp / "data" / STORE_NAME) as store:
            recs = list(store.windows())
    finally:
        server.terminate()
        server.wait(timeout=10)
    dev = health["devices"][0]
    full = recs[1:]
    print(f"\nlive: {hours:g} h of spindle-feeds at {speedup:g}x ({run_s:.0f} s wall), ADC over Modbus TCP every 2 ms "
          f"(simulator in another process), CNC over Modbus TCP, OPC UA on; {os.cpu_count()} cores; Python "
          f"{sys.version.split()[0]}")
    print(f"start (store, estimator, writer sync, OPC UA, acquisition): {started:.2f} s")
    print(f"sampling: {dev['reads_ok'] / run_s:.1f} reads/s, {dev['ticks_skipped']} ticks skipped, "
          f"{dev['reads_failed']} failed; lateness p50 {lateness[0]:.2f} ms, p99 {lateness[1]:.2f} ms; windows "
          f"{len(recs)} ({sum(r.status == 'good' for r in full)} of {len(full)} whole ones good, missed ticks at "
          f"most {max((r.missed_ticks for r in full), default=0)} a window)")
    print(f"estimator update in the closer: median {np.median(upd):.0f} us, max {upd.max():.0f} us")
    print(f"window close -> verified write (estimate, submit, limits, Modbus write, read-back): median "
          f"{np.median(lat):.2f} ms, p99 {np.percentile(lat, 99):.2f} ms, max {lat.max():.2f} ms over {len(lat)} "
          f"writes; {health['compensation']['beats']} heartbeats, {health['compensation']['failures']} failures; "
          f"alarms at the end: {[a['name'] for a in health['alarms']] or 'none'}")
    cpu = (cpu_end - cpu_start) / run_s
    rss = np.array([s[2] for s in samples]) / 2**20
    ts = np.array([s[0] for s in samples])
    slope = np.polyfit(ts, rss, 1)[0] * 3600 / speedup if len(ts) > 2 else float("nan")
    thread = sampler.cpu_s / (sampler.stopped_wall - sampler.started_wall)
    print(f"CPU of the gateway process: {cpu:.0%} of one core (sampler thread alone {thread:.0%}); memory: RSS "
          f"{rss0 / 2**20:.0f} MiB before start, {rss[0]:.0f} MiB after 1 s, {rss_end / 2**20:.0f} MiB at the end; "
          f"growth {slope:+.2f} MiB per simulated hour")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--hours", type=float, default=1.0)
    p.add_argument("--speedup", type=float, default=60.0)
    p.add_argument("--windows", type=int, default=20000, help="windows for the estimator cost")
    args = p.parse_args()
    estimator_cost(args.windows)
    with tempfile.TemporaryDirectory(prefix="cncgw-bench-") as tmp:
        live_run(args.hours, args.speedup, Path(tmp))
    return 0


if __name__ == "__main__":
    sys.exit(main())
