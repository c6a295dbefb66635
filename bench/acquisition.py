"""Acquisition benchmark: 8 channels over Modbus TCP on loopback at 500 Hz, the gateway's sampler against a
naive read-then-sleep(2 ms) loop, in the same run.

The simulated machine and its ADC board run in another process (``cncgw simulate serve``), as a real board
would be another machine: the figures are the gateway's. The gateway side runs what it runs in production:
the sampler thread, the window closer, the durable SQLite store and the live estimator (one
``ModelStepper.step()`` per window, with a model identified from the simulator by ``cncgw demo``).

Printed per run: achieved rate, missed ticks, lateness of ticks against their deadlines (p50/p99/max),
CPU of the process and of each core. Aims (issue 4): >= 499.5 Hz, <= 0.1 % missed, p99 lateness <= 0.5 ms.

    .venv/bin/python bench/acquisition.py [--seconds 60] [--window-s 10] [--spin-us 0] [--model M]
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from gateway.clock import RealClock  # noqa: E402
from gateway.model import load_model  # noqa: E402
from gateway.profile import load_profile  # noqa: E402
from gateway.record_store import RecordStore  # noqa: E402
from gateway.sampler import Acquisition  # noqa: E402
from gateway.windows import WindowRecord  # noqa: E402

CNCGW = str(Path(sys.executable).with_name("cncgw"))


def cpu_times() -> list[tuple[int, int]]:
    """(busy, total) jiffies per core from /proc/stat."""
    out = []
    with open("/proc/stat") as fh:
        for line in fh:
            if re.match(r"cpu\d+ ", line):
                v = [int(x) for x in line.split()[1:]]
                idle = v[3] + v[4]
                out.append((sum(v) - idle, sum(v)))
    return out


class CpuMeter:
    def __enter__(self):
        self.cores0, self.proc0, self.t0 = cpu_times(), os.times(), time.monotonic()
        return self

    def __exit__(self, *exc):
        cores1, proc1 = cpu_times(), os.times()
        self.wall = time.monotonic() - self.t0
        self.process = (proc1.user - self.proc0.user + proc1.system - self.proc0.system) / self.wall
        self.cores = [(b1 - b0) / max(1, t1 - t0) for (b0, t0), (b1, t1) in zip(self.cores0, cores1, strict=True)]

    def line(self) -> str:
        cores = ", ".join(f"{c:.0%}" for c in self.cores)
        return f"CPU: gateway process {self.process:.0%} of one core; per core (whole machine) {cores}"


def eight_channel_profile(served: Path, out: Path, window_s: float) -> Path:
    """The served profile with spindle_i2 (and its factor) left out: 8 channels, registers 0-1 and 3-8."""
    text = served.read_text()
    text = re.sub(r"\[factors\.spindle_i2_sq\]\n(?:[^\[\n].*\n)*\n?", "", text)
    text = re.sub(r"\[channels\.spindle_i2\]\n(?:[^\[\n].*\n)*\n?", "", text)
    text = re.sub(r"window_s = [0-9.]+", f"window_s = {window_s!r}", text)
    text = re.sub(r"(\[recording\][^\[]*?)period_s = [0-9.]+", rf"\g<1>period_s = {window_s!r}", text)
    out.write_text(text)
    return out


class EstimatorSink:
    """Steps the live estimator once per window, as the gateway will (factor deviations from the reference)."""

    def __init__(self, model_path: Path) -> None:
        self.model = load_model(model_path)
        self.window_s: float | None = None
        self.stepper = None
        self.steps = 0
        self.step_s: list[float] = []
        self.last = None

    def __call__(self, record: WindowRecord) -> None:
        if self.stepper is None:
            self.stepper = self.model.discretize(record.end_s - record.start_s).stepper()
        ref = self.model.reference
        du = [record.factors.get(f, ref[f]) - ref[f] for f in self.model.factors]
        du = [0.0 if d != d else d for d in du]  # a gap: hold the reference (bench only)
        t0 = time.perf_counter()
        self.last = self.stepper.step(du)
        self.step_s.append(time.perf_counter() - t0)
        self.steps += 1


def realtime(pid: int, priority: int) -> None:
    """Every thread of process ``pid`` under SCHED_FIFO ``priority``."""
    for task in Path(f"/proc/{pid}/task").iterdir():
        os.sched_setscheduler(int(task.name), os.SCHED_FIFO, os.sched_param(priority))


def run_sampler(profile_path: Path, seconds: float, spin_us: float, model: Path, tmp: Path,
                rt_priority: int = 0) -> None:
    from threadpoolctl import threadpool_limits

    profile = load_profile(profile_path)
    store = RecordStore(tmp / f"records-spin{spin_us:g}.sqlite", profile=profile)
    estimator = EstimatorSink(model)
    records: list[WindowRecord] = []
    acq = Acquisition(profile, clock=RealClock(), sinks=[store, estimator, records.append], spin_s=spin_us * 1e-6,
                      rt_priority=rt_priority)
    with threadpool_limits(limits=1), CpuMeter() as cpu:
        acq.start()
        time.sleep(seconds)
        acq.stop()
    store.close()
    s = acq.samplers[0]
    run_s = s.stopped_wall - s.started_wall
    t = s.runner.total
    expected = s.ticks_run + s.ticks_skipped  # deadlines that passed
    extra = (f", spin {spin_us:g} us" if spin_us else "") + (f", SCHED_FIFO {rt_priority}" if rt_priority else "")
    print(f"\n== gateway sampler (thread, absolute deadlines, skip rule{extra})")
    print(f"run {run_s:.1f} s: {t.reads_ok} reads = {t.reads_ok / run_s:.2f} Hz; ticks run {s.ticks_run}, "
          f"skipped {s.ticks_skipped}; failed reads {t.reads_failed}")
    print(f"missed ticks: {expected - t.reads_ok} of {expected} = {(expected - t.reads_ok) / expected:.3%}")
    p50, p99 = s.lateness_quantile(0.5) * 1e3, s.lateness_quantile(0.99) * 1e3
    print(f"lateness vs deadline: p50 {p50:.3f} ms, p99 {p99:.3f} ms, max {s.lateness_max_s * 1e3:.3f} ms "
          "(10 us bins)")
    print(cpu.line() + f"; the sampler thread {s.cpu_s / run_s:.1%} of one core")
    full = records[1:]  # the first window started mid-way
    if full:
        print(f"windows: {len(records)} closed ({len(full)} whole): status {sorted({r.status for r in full})}, "
              f"samples {min(r.samples_taken for r in full)}..{max(r.samples_taken for r in full)} of "
              f"{full[0].samples_expected}, missed {max(r.missed_ticks for r in full)} at most, largest gap "
              f"{max(r.largest_gap_s for r in full) * 1e3:.1f} ms")
    if estimator.steps:
        est = ", ".join(f"{a} {v:+.2f} um" for a, v in zip(estimator.model.axes, estimator.last, strict=True))
        print(f"estimator: {estimator.steps} steps, {max(estimator.step_s) * 1e6:.0f} us at most; last {est}")


def run_naive(profile_path: Path, seconds: float) -> None:
    from drivers import registry

    profile = load_profile(profile_path)
    d = profile.devices[0]
    driver = registry.load(d.driver)(name=d.name, options=d.options,
                                     channels=[(c.name, c.address) for c in profile.channels_of(d.name)])
    period = d.period_s
    late = []
    with driver, CpuMeter() as cpu:
        start = time.monotonic()
        n = 0
        while (now := time.monotonic()) - start < seconds:
            late.append(now - (start + n * period))  # where the n-th read should have started
            driver.read()
            n += 1
            time.sleep(period)
    run_s = time.monotonic() - start
    expected = run_s / period
    lat = np.array(late)
    print("\n== naive loop (read, then sleep 2 ms)")
    print(f"run {run_s:.1f} s: {n} reads = {n / run_s:.2f} Hz")
    print(f"missed ticks: {expected - n:.0f} of {expected:.0f} = {(expected - n) / expected:.3%}")
    print(f"drift behind the 2 ms schedule: after 1 s {np.interp(1.0, np.arange(n) * period, lat) * 1e3:.0f} ms, "
          f"at the end {lat[-1]:.2f} s (it never catches up)")
    print(cpu.line())


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=60.0)
    p.add_argument("--window-s", type=float, default=10.0, help="window length (default 10 s: six estimator steps)")
    p.add_argument("--spin-us", type=float, default=0.0, help="the sampler's busy-wait before each deadline")
    p.add_argument("--model", type=Path, help="model file (default: identified by `cncgw demo` first)")
    p.add_argument("--rt-priority", type=int, default=0,
                   help="also run the sampler under SCHED_FIFO at this priority (a second run)")
    p.add_argument("--skip-naive", action="store_true")
    args = p.parse_args()
    with tempfile.TemporaryDirectory(prefix="cncgw-bench-") as tmpdir:
        tmp = Path(tmpdir)
        model = args.model
        if model is None:
            print("identifying a model of the simulated machine (cncgw demo) ...", flush=True)
            subprocess.run([CNCGW, "demo", "-o", str(tmp / "demo")], check=True, capture_output=True)
            model = tmp / "demo" / "sim-vmc.model.toml"
        served = tmp / "served.toml"
        total = args.seconds * (1 + (not args.skip_naive) + (args.rt_priority > 0)) + 30
        server = subprocess.Popen([CNCGW, "simulate", "serve", "spindle-feeds", "--profile-out", str(served),
                                   "--duration", str(total)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            deadline = time.monotonic() + 30
            while not served.exists():
                if time.monotonic() > deadline or server.poll() is not None:
                    raise SystemExit("the simulated devices did not start")
                time.sleep(0.1)
            profile_path = eight_channel_profile(served, tmp / "bench.toml", args.window_s)
            prof = load_profile(profile_path)
            print(f"{len(prof.channels)} channels over Modbus TCP on loopback ({prof.devices[0].options.host}:"
                  f"{prof.devices[0].options.port}, simulator in another process), period "
                  f"{prof.devices[0].period_s * 1e3:g} ms, {args.seconds:g} s per run, window {args.window_s:g} s, "
                  f"{os.cpu_count()} cores; Python {sys.version.split()[0]}")
            print(f"threads in this process while sampling: sampler, window closer, main "
                  f"(+ store and estimator on the closer); active now: {threading.active_count()}")
            run_sampler(profile_path, args.seconds, args.spin_us, model, tmp)
            if not args.skip_naive:
                run_naive(profile_path, args.seconds)
            if args.rt_priority:
                # the simulated board stands in for a board with a CPU of its own: on a machine shared with
                # CPU-bound work it gets real-time priority too, one below the sampler's
                realtime(server.pid, max(1, args.rt_priority - 1))
                print("\n(the simulator process's threads now run under SCHED_FIFO "
                      f"{max(1, args.rt_priority - 1)} too)")
                run_sampler(profile_path, args.seconds, args.spin_us, model, tmp, args.rt_priority)
        finally:
            server.terminate()
            server.wait(timeout=10)
    return 0


if __name__ == "__main__":
    sys.exit(main())
