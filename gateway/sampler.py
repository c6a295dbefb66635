"""The fast sampler: one thread per device on absolute deadlines, and a window closer beside them.

Each device is sampled by its own :class:`DeviceSampler` thread (its driver's client belongs to that
thread; a slow serial device cannot hold up a fast TCP one). Ticks are absolute wall-time deadlines
(``deadline += period``: no drift); a tick that is late by a whole period or more is skipped and counted,
never queued (Telegraf's gather loop), so a stall cannot build a backlog. The thread sleeps until shortly
before the deadline and may busy-wait the rest (``spin_s``) for sub-millisecond lateness.

The fast period is wall time (hardware cannot sample faster); window boundaries are clock time. With a
:class:`~gateway.clock.ScaledClock` of speed-up N a window lasts N times less wall time and holds N times
fewer samples, and its record says what sampling it really had. With a :class:`~gateway.clock.ManualClock`
there is no wall time to follow: :meth:`Acquisition.run_stepped` then moves the clock tick by tick
(the period read as clock time) in the calling thread, which gives exact 2 ms sampling of a simulated
machine in a test.

Per tick the sampler thread only reads and adds to running sums (:class:`gateway.windows.DeviceWindow`).
At a window boundary it hands the sums to the :class:`WindowCloser` thread, which merges the devices'
partials into a :class:`~gateway.windows.WindowRecord` and passes it to the sinks (the durable store, the
estimator): heavy Python work stays off the sampler threads.
"""

from __future__ import annotations

import logging
import math
import os
import queue
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from drivers.base import Driver
from gateway.clock import Clock, ManualClock
from gateway.profile import Profile
from gateway.runner import DeviceRunner
from gateway.windows import DevicePartial, DeviceWindow, WindowRecord, build_record, window_index

log = logging.getLogger(__name__)

Sink = Callable[[WindowRecord], None]

_HIST_BIN_S = 10e-6  # lateness histogram: 10 us bins up to 50 ms, the last bin takes the rest
_HIST_BINS = 5000


@dataclass(frozen=True, kw_only=True, slots=True)
class DeviceStatus:
    """One device's sampling since start: runner state, read counters, ticks run and skipped, first errors.

    ``rate_hz``: good reads per wall second since start, when the caller knows the wall time (the live
    gateway's health; NaN otherwise, and on a stepped clock).
    """

    device: str
    state: str  # new, on_scan, off_scan, closed
    reads_ok: int
    reads_failed: int
    timeouts: int
    off_scan_ticks: int
    recoveries: int
    ticks_run: int
    ticks_skipped: int
    errors: tuple[str, ...] = ()
    rate_hz: float = math.nan


class DeviceSampler:
    """Samples one device every ``period_s``; hands a :class:`DevicePartial` to ``sink`` per window.

    Args:
        runner: the device's runner (owns its driver).
        clock: the shared clock.
        period_s: the fast period (wall seconds; clock seconds in stepped mode).
        window_s: the window length (clock seconds).
        sink: receives each finished window's partial (called on this sampler's thread: keep it cheap).
        burst_channels: channels whose samples in the last ``burst_s`` of each window are kept.
        spin_s: busy-wait this long before each deadline (0: sleep only).
        rt_priority: run the thread under SCHED_FIFO at this priority (1-99; 0: the normal scheduler). On a
            machine shared with CPU-bound work this keeps ticks on time; it needs CAP_SYS_NICE (a warning is
            logged and the normal scheduler kept when it is refused).
        stepped: ticks are driven by :meth:`tick` from outside (no thread).

    """

    def __init__(self, *, runner: DeviceRunner, clock: Clock, period_s: float, window_s: float,
                 sink: Callable[[DevicePartial], None], burst_channels: Sequence[str] = (), burst_s: float = 0.0,
                 spin_s: float = 0.0, rt_priority: int = 0, stepped: bool = False) -> None:
        if not period_s > 0:
            raise ValueError(f"period_s must be > 0. Got {period_s!r}")
        self.runner = runner
        self.name = runner.device.name
        self.clock = clock
        self.period_s = float(period_s)
        self.window_s = float(window_s)
        self.tick_s = self.period_s if stepped else self.period_s * clock.speedup
        self._sink = sink
        self._burst_channels = tuple(burst_channels)
        self._burst_s = burst_s
        self.spin_s = spin_s
        self.rt_priority = rt_priority
        self._window: DeviceWindow | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        #: since start: ticks run and skipped, and a histogram of how late ticks started
        self.ticks_run = 0
        self.ticks_skipped = 0
        self.lateness_hist = [0] * _HIST_BINS
        self.lateness_max_s = 0.0
        self.started_wall: float | None = None
        self.stopped_wall: float | None = None
        self.cpu_s = 0.0  # CPU time of the sampler thread, known once it stopped

    # -- one tick ---------------------------------------------------------------------------------------------
    def tick(self, skipped: int = 0, lateness_s: float = 0.0) -> None:
        """Read the device once and add the reading to the current window."""
        self._roll(self.clock.now())
        window = self._window
        assert window is not None
        window.ticks_skipped += skipped
        window.ticks_run += 1
        if lateness_s > window.lateness_max_s:
            window.lateness_max_s = lateness_s
        reading = self.runner.poll()
        if reading is not None:
            if reading.t_s > window.end_s:
                self._roll(reading.t_s)
                window = self._window
                assert window is not None
            window.add(reading.t_s, reading.values, reading.quality)

    def _roll(self, t: float) -> None:
        """Hand in every window that ended before ``t`` and start the one holding ``t``."""
        k = window_index(t, self.window_s)
        current = self._window
        if current is not None and k <= current.index:
            return
        if current is not None:
            self._hand_in(current)
            for idx in range(current.index + 1, k):  # whole windows without a tick (a long stall)
                empty = self._new_window(idx, opened_s=idx * self.window_s)
                self._hand_in(empty)
            opened = k * self.window_s
        else:
            opened = t - self.tick_s  # the first sample stands for one tick
        self._window = self._new_window(k, opened_s=opened)

    def _new_window(self, index: int, *, opened_s: float) -> DeviceWindow:
        return DeviceWindow(device=self.name, channels=self.runner.channel_names, index=index,
                            window_s=self.window_s, tick_s=self.tick_s, opened_s=opened_s,
                            burst_channels=self._burst_channels, burst_s=self._burst_s)

    def _hand_in(self, window: DeviceWindow) -> None:
        c = self.runner.take_counters()
        self._sink(DevicePartial(window=window, reads_ok=c.reads_ok, reads_failed=c.reads_failed,
                                 timeouts=c.timeouts, connects_failed=c.connects_failed,
                                 off_scan_ticks=c.off_scan_ticks, recoveries=c.recoveries,
                                 read_time_max_s=c.read_time_max_s, errors=tuple(c.errors),
                                 state=self.runner.state))

    def hand_in_finished(self, t: float) -> None:
        """Hand in the current window if it ended at or before clock time ``t`` (no read)."""
        if self._window is not None and self._window.end_s <= t:
            self._roll(t + 1e-9 * max(1.0, abs(t)))

    # -- the thread -------------------------------------------------------------------------------------------
    def start(self) -> None:
        if self._thread is not None:
            raise RuntimeError(f"sampler {self.name}: already started")
        self._thread = threading.Thread(target=self._run, name=f"cncgw-sampler-{self.name}", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop the thread (it hands in windows that have ended and closes the driver)."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join()

    def _run(self) -> None:
        period = self.period_s
        spin = self.spin_s
        stop = self._stop
        hist = self.lateness_hist
        if self.rt_priority:
            try:  # Linux: pid 0 is the calling thread
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(self.rt_priority))
            except (OSError, AttributeError) as exc:
                log.warning("%s: cannot use real-time priority %d (%s); sampling under the normal scheduler",
                            self.name, self.rt_priority, exc)
        self.started_wall = deadline = time.monotonic()
        try:
            while not stop.is_set():
                now = time.monotonic()
                skipped = 0
                if now - deadline >= period:  # late by whole periods: skip them, never queue
                    skipped = int((now - deadline) // period)
                    deadline += skipped * period
                    self.ticks_skipped += skipped
                else:
                    remaining = deadline - now - spin
                    if remaining > 0.02:
                        stop.wait(remaining)  # long periods: wake at once on stop
                        if stop.is_set():
                            break
                    elif remaining > 0:
                        time.sleep(remaining)
                    while time.monotonic() < deadline:
                        pass  # spin the last spin_s: sleeping that close to a deadline wakes up late
                late = time.monotonic() - deadline
                hist[min(int(late / _HIST_BIN_S), _HIST_BINS - 1)] += 1
                if late > self.lateness_max_s:
                    self.lateness_max_s = late
                self.ticks_run += 1
                try:
                    self.tick(skipped, late)
                except Exception:  # a bug in one tick must not end months of sampling
                    log.exception("%s: sampler tick failed", self.name)
                deadline += period
        finally:
            self.stopped_wall = time.monotonic()
            self.cpu_s = time.thread_time()
            try:
                self.hand_in_finished(self.clock.now())
            finally:
                self.runner.close()

    def lateness_quantile(self, q: float) -> float:
        """Lateness (s) not exceeded by a share ``q`` of the ticks run (10 us resolution)."""
        total = sum(self.lateness_hist)
        if total == 0:
            return math.nan
        want = q * total
        run = 0
        for i, n in enumerate(self.lateness_hist):
            run += n
            if run >= want:
                return (i + 1) * _HIST_BIN_S
        return _HIST_BINS * _HIST_BIN_S


class WindowCloser:
    """Merges the devices' partials into records, in window order, and passes them to the sinks.

    A window is closed when every device has handed it in, or ``grace_s`` wall seconds after the first one
    did (a device stuck in a long read is then reported as not reporting). A partial that arrives after
    its window was closed is dropped and counted.
    """

    def __init__(self, *, profile: Profile, devices: Sequence[str], channel_order: Sequence[str],
                 sinks: Sequence[Sink], grace_s: float, nominal_tick_s: float) -> None:
        self.profile = profile
        self.devices = tuple(devices)
        self.channel_order = tuple(channel_order)
        self.sinks = list(sinks)
        self.grace_s = grace_s
        self.nominal_tick_s = nominal_tick_s
        self._queue: queue.Queue[DevicePartial | None] = queue.Queue()
        self._pending: dict[int, dict[str, DevicePartial]] = {}
        self._first_seen: dict[int, float] = {}
        self._last_closed = -math.inf
        self._thread: threading.Thread | None = None
        self.records_closed = 0
        self.late_partials = 0
        self.sink_errors = 0
        self.last_record: WindowRecord | None = None

    def put(self, partial: DevicePartial) -> None:
        """Hand in one device's window (thread-safe, cheap)."""
        self._queue.put(partial)

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="cncgw-window-closer", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Close every window all devices handed in, drop the incomplete ones, stop the thread."""
        if self._thread is not None:
            self._queue.put(None)
            self._thread.join()
            self._thread = None

    def _run(self) -> None:
        while True:
            try:
                item = self._queue.get(timeout=0.05)
            except queue.Empty:
                item = ...
            if item is None:
                self.drain()
                dropped = sorted(self._pending)
                if dropped:
                    log.info("stopping: %d incomplete window(s) not recorded: %s", len(dropped), dropped)
                self._pending.clear()
                return
            if item is not ...:
                self._accept(item)
            self._close_ready(time.monotonic())

    def drain(self) -> None:
        """Take every queued partial and close what is complete (also used inline in stepped mode)."""
        while True:
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                break
            if item is not None:
                self._accept(item)
        self._close_ready(None)

    def _accept(self, p: DevicePartial) -> None:
        idx = p.window.index
        if idx <= self._last_closed:
            self.late_partials += 1
            log.warning("%s: window %d handed in after it was closed; dropped", p.window.device, idx)
            return
        self._pending.setdefault(idx, {})[p.window.device] = p
        self._first_seen.setdefault(idx, time.monotonic())

    def _close_ready(self, now: float | None) -> None:
        while self._pending:
            idx = min(self._pending)
            got = self._pending[idx]
            complete = all(d in got for d in self.devices)
            overdue = now is not None and now - self._first_seen[idx] > self.grace_s
            if not (complete or overdue):
                return
            del self._pending[idx]
            del self._first_seen[idx]
            self._last_closed = idx
            partials: dict[str, DevicePartial | None] = {d: got.get(d) for d in self.devices}
            self._emit(build_record(self.profile, idx, partials, self.channel_order,
                                    nominal_tick_s=self.nominal_tick_s))

    def _emit(self, record: WindowRecord) -> None:
        self.records_closed += 1
        self.last_record = record
        for sink in self.sinks:
            try:
                sink(record)
            except Exception:  # one failing consumer must not stop the others or the sampling
                self.sink_errors += 1
                log.exception("window %d: a sink failed", record.index)


class Acquisition:
    """Every device of a profile sampled on its own thread, windows closed and passed to ``sinks``.

    Args:
        profile: the machine (devices, channels, sampling, factors).
        clock: the shared clock.
        sinks: called with each :class:`WindowRecord`, in window order, on the closer's thread.
        spin_s: busy-wait before each deadline (see :class:`DeviceSampler`).
        rt_priority: SCHED_FIFO priority of the sampler threads (0: normal; see :class:`DeviceSampler`).
        driver_factories: device name -> function making its driver (default: the registry's); for a
            driver that needs something the profile cannot say, e.g. a live bus object.

    Start consumers first, then producers (Telegraf's agent): :meth:`start` starts the closer, then the
    samplers; :meth:`stop` stops the samplers, then the closer (windows that ended are recorded, the
    current one is not). Use it as a context manager.

    """

    def __init__(self, profile: Profile, *, clock: Clock, sinks: Sequence[Sink] = (), spin_s: float = 0.0,
                 rt_priority: int = 0, driver_factories: dict[str, Callable[[], Driver]] | None = None) -> None:
        if not profile.devices or not profile.channels:
            raise ValueError(f"profile {profile.path} has no devices and channels to sample")
        self.profile = profile
        self.clock = clock
        self.stepped = isinstance(clock, ManualClock)
        s = profile.sampling
        bursts = (*s.displacement_channels.values(), *([s.burst_speed_channel] if s.burst_speed_channel else []))
        self.closer = WindowCloser(
            profile=profile, devices=[d.name for d in profile.devices if profile.channels_of(d.name)],
            channel_order=[c.name for c in profile.channels], sinks=sinks,
            grace_s=self._grace_s(profile), nominal_tick_s=s.fast_period_s)
        factories = driver_factories or {}
        self._driver_factories = factories
        self.link_checks: list[Any] = []  # what start() measured of the network links
        self.samplers: list[DeviceSampler] = []
        for d in profile.devices:
            channels = profile.channels_of(d.name)
            if not channels:
                continue
            runner = DeviceRunner(device=d, channels=channels, clock=clock, driver_factory=factories.get(d.name),
                                  monotonic=clock.now if self.stepped else time.monotonic)
            self.samplers.append(DeviceSampler(
                runner=runner, clock=clock, period_s=d.period_s, window_s=s.window_s, sink=self.closer.put,
                burst_channels=bursts if s.displacement_channels else (), burst_s=s.burst_s, spin_s=spin_s,
                rt_priority=rt_priority, stepped=self.stepped))
        self._state = "new"
        #: run_stepped's tick grid: the clock at its first call and the next tick number per sampler
        self._step_origin_s: float | None = None
        self._step_counts: dict[int, int] = {}

    @staticmethod
    def _grace_s(profile: Profile) -> float:
        worst = 0.0
        for d in profile.devices:
            o: Any = d.options
            worst = max(worst, d.period_s + getattr(o, "timeout_s", 1.0) * (getattr(o, "retries", 0) + 1))
        return worst + 1.0

    def start(self) -> Acquisition:
        """Start the closer, then one sampler thread per device."""
        if self.stepped:
            raise RuntimeError("with a ManualClock there is no wall time to tick on: use run_stepped()")
        if self._state != "new":
            raise RuntimeError(f"an acquisition starts once; this one is {self._state}")
        from gateway.linkcheck import check_measured_links

        # before any thread starts: a network link that cannot hold its period is refused (a bad profile)
        self.link_checks = check_measured_links(self.profile, clock=self.clock,
                                                driver_factories=self._driver_factories)
        self._state = "running"
        self.closer.start()
        try:
            for s in self.samplers:
                s.start()
        except BaseException:
            self.stop()
            raise
        return self

    def stop(self) -> None:
        """Stop the samplers, then the closer (idempotent)."""
        if self._state == "stopped":
            return
        self._state = "stopped"
        for s in self.samplers:
            s.stop()
        for s in self.samplers:
            s.runner.close()
        self.closer.stop()

    def __enter__(self) -> Acquisition:
        return self.start() if self._state == "new" else self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def run_stepped(self, until_s: float) -> None:
        """ManualClock only: tick every device in clock time up to ``until_s``, closing windows inline.

        Each device ticks at ``origin + n * period`` of clock time, ``origin`` the clock at the first call:
        the grid runs on across calls, so stepping in chunks (the live gateway steps by heartbeats) samples
        exactly as one long call would. (It restarted at each call before, so a 0.73 s period stepped by 1 s
        heartbeats read once a second at the same phase and aliased with the table's strokes.) The clock is
        set to each tick's time before the read, so the devices see exactly that instant.
        """
        clock = self.clock
        if not isinstance(clock, ManualClock):
            raise RuntimeError("run_stepped needs a ManualClock")
        if self._state == "stopped":
            raise RuntimeError("this acquisition was stopped")
        self._state = "stepping"
        if self._step_origin_s is None:
            self._step_origin_s = clock.now()
            self._step_counts = dict.fromkeys(range(len(self.samplers)), 1)
        origin, counts = self._step_origin_s, self._step_counts
        while True:
            times = {i: round(origin + n * self.samplers[i].period_s, 9) for i, n in counts.items()}
            i = min(times, key=lambda k: times[k])
            if times[i] > until_s + 1e-12:
                break
            clock.set(times[i])
            self.samplers[i].tick()
            counts[i] += 1
            self.closer.drain()
        clock.set(max(clock.now(), until_s))
        for s in self.samplers:
            s.hand_in_finished(until_s)
        self.closer.drain()

    def status(self) -> tuple[DeviceStatus, ...]:
        """Per device: state, totals since start, ticks run and skipped (for health, logs and benchmarks)."""
        return tuple(DeviceStatus(device=s.name, state=s.runner.state, reads_ok=t.reads_ok,
                                  reads_failed=t.reads_failed, timeouts=t.timeouts, off_scan_ticks=t.off_scan_ticks,
                                  recoveries=t.recoveries, ticks_run=s.ticks_run, ticks_skipped=s.ticks_skipped,
                                  errors=tuple(t.errors))
                     for s in self.samplers for t in (s.runner.total,))
