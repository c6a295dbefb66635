"""``cncgw run``: acquisition, durable records, the live estimate, the compensation writer, OPC UA, health.

Data path per finished window, on the window closer's thread (heavy work stays off the samplers)::

    samplers -> WindowCloser -> RecordStore.append (durable first) -> DisplacementTracker.update -> writer.submit
                                                                                       -> health, OPC UA, log

Store-first by construction: the window closer has one sink, :meth:`LiveGateway._on_window`, which hands a
record to the estimator and the writer only once ``RecordStore.append`` has committed it. A window the
store could not commit (disk full, file read-only, I/O error) raises the alarm ``store`` and is not acted
on: the offsets stay where they are, and the estimator later fills it by the gap policy exactly as a
restart would, since the store does not have it either. Whatever the CNC was given can be recomputed from
the store after a crash.

Start order (Telegraf's agent): consumers before producers: the store and the audit log, the compensation
writer (its thread connects to the CNC and starts the heartbeat, holding the offsets the CNC applies), the
estimator (rebuilt from the stored history while the writer already beats), the OPC UA server, then the
acquisition (window closer, then one sampler thread per device).
Stop order is the reverse: producers first, so no window is handed to a stopped consumer.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

from drivers.base import Driver
from gateway.clock import Clock, ManualClock
from gateway.errors import ModelError, ProfileError
from gateway.live.audit import AUDIT_NAME, Alarms, AuditLog
from gateway.live.cnc import CncLink
from gateway.live.compensation import CompensationWriter
from gateway.live.health import GapStatus, Health
from gateway.live.plausibility import Plausibility, model_refusals
from gateway.live.tracking import DisplacementTracker, EstimateUpdate, history_windows, retention_problems
from gateway.model import ThermalModel
from gateway.profile import Profile
from gateway.record_store import STORE_NAME, ProbeStore, RecordStore, private_dir
from gateway.windows import WindowRecord

log = logging.getLogger("gateway.live")

Listener = Callable[[WindowRecord, EstimateUpdate], None]


class LiveGateway:
    """The gateway of one machine, live; see the module docstring.

    Args:
        profile: the machine (devices, channels, factors, ``[live]``, ``[compensation]``, ``[opcua]``).
        model: its identified model.
        data_dir: where ``records.sqlite`` and ``audit.sqlite`` live (created if needed).
        clock: the shared clock (a :class:`ManualClock` runs stepped: :meth:`run_stepped`).
        opcua: serve OPC UA (default: ``profile.opcua.enabled``).
        listeners: called with each record and the estimate that followed (closer thread; keep them cheap).
        spin_s, rt_priority: the samplers' (see :class:`gateway.sampler.Acquisition`).
        link_factory: makes the CNC link (default: from ``[compensation]``).
        driver_factories: device name -> driver factory (see :class:`~gateway.sampler.Acquisition`).

    Use as a context manager, or :meth:`start` / :meth:`stop`.

    """

    def __init__(self, profile: Profile, *, model: ThermalModel, data_dir: str | Path, clock: Clock,
                 opcua: bool | None = None, listeners: Sequence[Listener] = (), spin_s: float = 0.0,
                 rt_priority: int = 0, link_factory: Callable[[], CncLink] | None = None,
                 driver_factories: dict[str, Callable[[], Driver]] | None = None) -> None:
        self.profile = profile
        self.model = model
        self.data_dir = Path(data_dir)
        self.clock = clock
        self.stepped = isinstance(clock, ManualClock)
        self.serve_opcua = profile.opcua.enabled if opcua is None else opcua
        self.listeners = list(listeners)
        self._spin_s = spin_s
        self._rt_priority = rt_priority
        self._link_factory = link_factory
        self._driver_factories = driver_factories
        self.store: RecordStore | None = None
        self.audit: AuditLog | None = None
        self.alarms: Alarms | None = None
        self.tracker: DisplacementTracker | None = None
        self.writer: CompensationWriter | None = None
        self.plausibility: Plausibility | None = None
        self.opcua: Any = None
        self.acquisition: Any = None
        self.outputs: list[Any] = []  # outputs beside OPC UA (gateway.live.outputs): MQTT
        self.probes: Any = None  # the CNC's probe block reader ([probes], gateway.live.probes)
        self.probe_store: Any = None
        self.started_wall: float | None = None
        self.started_s: float | None = None
        self.windows_live = 0
        self._outside_since: tuple[int, ...] = ()  # first window of the current stretch outside coverage
        self.update_s: list[float] = []  # estimator step time per window (wall s)
        self.store_failures = 0  # windows the store could not commit (not acted on)
        self.last_record: WindowRecord | None = None
        self._state = "new"
        self._lock = threading.Lock()
        self._stopping = threading.Event()
        self._retention: threading.Thread | None = None
        self.pruned_windows = 0

    # -- lifecycle ----------------------------------------------------------------------------------------
    def start(self) -> LiveGateway:
        """Start consumers, then producers (see the module docstring)."""
        if self._state != "new":
            raise RuntimeError(f"a gateway starts once; this one is {self._state}")
        self._state = "starting"
        try:
            self._start()
        except BaseException:
            self.stop()
            raise
        self._state = "running"
        return self

    def _start(self) -> None:
        from gateway.sampler import Acquisition

        p = self.profile
        refusals = model_refusals(self.model, p.name, p.compensation)
        if refusals:  # before anything is created or connected
            raise ModelError("\n".join(refusals))
        if retention_problems(self.model, p):
            raise ProfileError("\n".join(retention_problems(self.model, p)))
        self.plausibility = Plausibility.for_model(self.model, p.compensation, window_s=p.sampling.window_s)
        private_dir(self.data_dir)
        self.store = RecordStore(self.data_dir / STORE_NAME, profile=p)
        self.audit = AuditLog(self.data_dir / AUDIT_NAME)
        self.alarms = Alarms(audit=self.audit, on_change=self._publish_health)
        now = self.clock.now()
        self.started_s, self.started_wall = now, time.monotonic()
        mode = "writing" if p.compensation.enabled else "dry run"
        self.audit.event(now, "start", "gateway", f"{p.name}: compensation {mode}")
        bounds = f"plausible estimates ({self.plausibility.source}): {self.plausibility.describe()}"
        self.audit.event(now, "plausibility", "model", bounds)
        log.info("%s", bounds)
        if self.model.envelope is None:
            log.warning("the model has no plausibility envelope: a dry run bounds its estimates by limit_um; "
                        "writing to the CNC will refuse it (re-run cncgw identify)")

        # the writer first: it synchronises with the CNC and beats while the history is replayed, so a restart
        # reaches the CNC's watchdog as fast as the process starts, whatever the length of the history
        self.writer = CompensationWriter(p.compensation, clock=self.clock, window_s=p.sampling.window_s,
                                         stale_after_s=p.live.stale_after_s, alarms=self.alarms, audit=self.audit,
                                         link_factory=self._link_factory, plausibility=self.plausibility)
        if not self.stepped:
            self.writer.start()
        else:
            self.writer.service()

        tracker_args: dict[str, Any] = {"window_s": p.sampling.window_s, "live": p.live,
                                          "channels": {f.name: f.channel for f in p.factors},
                                          "channel_names": [c.name for c in p.channels]}
        if p.probes.enabled:  # the model updated by the CNC's probes (gateway.adaptive)
            from gateway.live.probes import ProbedTracker, ProbeReader

            self.probe_store = ProbeStore(self.data_dir / STORE_NAME)
            self.probes = ProbeReader(p.probes, clock=self.clock, audit=self.audit, link_factory=lambda: CncLink(
                p.compensation, clock=self.clock, name="cnc-probes"))
            self.tracker = ProbedTracker(self.model, probes=p.probes, store=self.probe_store,
                                             source=self.probes.take, audit=self.audit, clock=self.clock,
                                             **tracker_args)
        else:
            self.tracker = DisplacementTracker(self.model, **tracker_args)
        if self.store.last_index is not None:
            since = self.store.last_index + 1 - history_windows(self.model, p.sampling.window_s, p.live)
            t0 = time.perf_counter()
            n = self.tracker.rebuild(self.store.windows(since=since),
                                       origin=self.store.first() if self.model.inputs else None)
            gaps = self.tracker.history.gaps
            log.info("estimator rebuilt from %d stored windows (%d filled by gap policy %s) in %.2f s", n,
                     self.tracker.history.filled_total, p.live.gap_policy, time.perf_counter() - t0)
            for g in gaps[-3:]:
                self.audit.event(now, "gap", "history", g.describe(p.sampling.window_s))
            self.audit.event(now, "rebuild", "estimator", f"{n} windows replayed up to window {self.store.last_index}")

        if self.serve_opcua:
            from gateway.live.opcua_server import OpcUaServer

            self.opcua = OpcUaServer(p.opcua, profile=p, model=self.model,
                                     on_hold=self.writer.request_hold if p.opcua.writable else None, clock=self.clock)
            self.opcua.start()

        if p.mqtt.enabled:
            from gateway.live.outputs.mqtt import MqttOutput

            self.outputs.append(MqttOutput(p.mqtt, machine=p.name, data_dir=self.data_dir,
                                           window_s=p.sampling.window_s, store=self.store, profile=p,
                                           factor_units={f.name: f.unit for f in p.factors}).start())

        if self.probes is not None and not self.stepped:
            self.probes.start()
        self.acquisition = Acquisition(p, clock=self.clock, sinks=[self._on_window], spin_s=self._spin_s,
                                       rt_priority=self._rt_priority, driver_factories=self._driver_factories)
        if not self.stepped:
            self.acquisition.start()
            if p.records.keep_days is not None:
                self._retention = threading.Thread(target=self._retention_loop, name="cncgw-retention", daemon=True)
                self._retention.start()
        self.writer.expect_inputs()
        log.info("gateway %s running: %d device(s), compensation %s%s", p.name, len(self.acquisition.samplers),
                 "WRITING to " + f"{p.compensation.host}:{p.compensation.port}" if p.compensation.enabled else
                 "dry run", f", OPC UA at {self.opcua.endpoint}" if self.opcua is not None else "")

    def stop(self) -> None:
        """Stop producers, then consumers (idempotent)."""
        if self._state in ("stopped", "new"):
            self._state = "stopped"
            return
        self._state = "stopped"
        self._stopping.set()
        if self._retention is not None:
            self._retention.join()
            self._retention = None
        if self.acquisition is not None:
            self.acquisition.stop()
        if self.probes is not None:
            self.probes.stop()
        if self.writer is not None:
            self.writer.stop()
        if self.opcua is not None:
            self.opcua.stop()
        for output in self.outputs:
            output.stop()
        if self.audit is not None:
            self.audit.event(self.clock.now(), "stop", "gateway", "stopped")
            self.audit.close()
        if self.probe_store is not None:
            self.probe_store.close()
        if self.store is not None:
            self.store.close()

    def __enter__(self) -> LiveGateway:
        return self.start() if self._state == "new" else self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def run_stepped(self, until_s: float) -> None:
        """ManualClock only: sample up to ``until_s`` in steps of the heartbeat period, servicing the writer."""
        if not self.stepped or self.acquisition is None or self.writer is None:
            raise RuntimeError("run_stepped needs a started gateway on a ManualClock")
        step = self.profile.compensation.heartbeat_period_s
        t = self.clock.now()
        while t < until_s - 1e-9:
            t = min(until_s, t + step)
            if self.probes is not None:  # the probe block is read between windows, as the thread would
                self.probes.service(t)
            self.acquisition.run_stepped(t)
            self.writer.service()
        self.prune_records()  # the retention thread's work, in step

    # -- retention ----------------------------------------------------------------------------------------
    def prune_records(self) -> int:
        """Delete the stored windows older than ``[records] keep_days`` (in batches; see ``RecordStore.prune``)."""
        keep = self.profile.records.keep_days
        store = self.store
        if keep is None or store is None or store.last_index is None:
            return 0
        window_s = self.profile.sampling.window_s
        before = store.last_index + 1 - math.ceil(keep * 86400.0 / window_s)
        first = store.first_index()
        if first is None or first >= before:
            return 0
        n = store.prune(before=before)
        self.pruned_windows += n
        message = f"{n} windows older than {keep:g} days deleted (windows {first}..{before - 1})"
        log.info("records: %s", message)
        if self.audit is not None:
            self.audit.event(self.clock.now(), "prune", "records", message)
        return n

    def _retention_loop(self) -> None:
        """Prune at start, then every hour of clock time (at least every 10 wall seconds), off the data path."""
        every_s = max(10.0, min(3600.0 / self.clock.speedup, 3600.0))
        while True:
            try:
                self.prune_records()
            except Exception:  # a full or locked disk: the next round tries again; recording goes on
                log.exception("records: pruning failed")
            if self._stopping.wait(every_s):
                return

    # -- per window ---------------------------------------------------------------------------------------
    def _on_window(self, record: WindowRecord) -> None:
        """The closer's one sink: commit the record, then (only then) estimate, write, publish."""
        assert self.store is not None
        assert self.alarms is not None
        try:
            self.store.append(record)
        except Exception as exc:  # disk full, read-only, I/O: nothing downstream may act on this window
            self.store_failures += 1
            self.alarms.raise_("store", f"window {record.index} could not be stored ({exc}): not acted on, the "
                                        "offsets are held until the store works again", self.clock.now())
            return
        self.alarms.clear("store", self.clock.now(), f"window {record.index} stored")
        self._on_record(record)

    def _on_record(self, record: WindowRecord) -> None:
        assert self.tracker is not None
        assert self.writer is not None
        t0 = time.perf_counter()
        update = self.tracker.update(record)
        self.update_s.append(time.perf_counter() - t0)
        self.writer.submit(update, since_wall=t0)
        if self.stepped:
            self.writer.service()
        with self._lock:
            self.windows_live += 1
            self.last_record = record
        if update.filled and not (update.first_live and update.filled == 1):
            gap = self.tracker.history.gaps[-1]
            if self.audit is not None:
                self.audit.event(self.clock.now(), "gap", "estimator", gap.describe(self.profile.sampling.window_s))
        self._log_window(record, update)
        self._note_coverage(record, update)
        self._publish_health(record, update)
        if self.outputs:
            from gateway.live.outputs import snapshot

            snap = snapshot(self.profile, record, update, self.writer.status(),
                            self.alarms.active() if self.alarms else ())
            for output in self.outputs:
                try:
                    output.window(snap)
                except Exception:  # an output's trouble never stops the estimate or the compensation
                    log.exception("output %s: window %d not taken", output.name, record.index)
        for listener in self.listeners:
            listener(record, update)

    def _log_window(self, record: WindowRecord, update: EstimateUpdate) -> None:
        assert self.writer is not None
        est = " ".join(f"{a}={v:+.2f}" for a, v in update.estimate_um.items())
        off = " ".join(f"{a}={v:+.2f}" for a, v in self.writer.commanded_um.items())
        alarms = [a.name for a in self.alarms.active()] if self.alarms else []
        log.info("window %d %s: %s; estimate %s um; offsets %s um%s", record.index, record.status, record.quality(),
                 est, off, f"; alarms {','.join(alarms)}" if alarms else "",
                 extra={"event": "window", "window": record.index, "status": record.status,
                        "estimate_um": dict(update.estimate_um), "offsets_um": dict(self.writer.commanded_um),
                        "usable": update.usable, "missed_ticks": record.missed_ticks,
                        "samples": record.samples_taken, "samples_expected": record.samples_expected,
                        "coverage": record.coverage, "quality": record.quality(), "reason": record.reason,
                        "devices_in_error": {n: d.describe_error() for n, d in record.devices.items()
                                             if d.in_error},
                        "alarms": alarms})

    def _note_coverage(self, record: WindowRecord, update: EstimateUpdate) -> None:
        """Log when the windows leave the identification's factor region and when they come back."""
        if update.outside_coverage and not self._outside_since:
            self._outside_since = (record.index,)
            log.warning("window %d leaves the identification's coverage: %s: the estimate extrapolates",
                        record.index, update.outside_coverage,
                        extra={"event": "coverage", "window": record.index, "outside": update.outside_coverage})
        elif not update.outside_coverage and self._outside_since and not update.reason:
            first = self._outside_since[0]
            self._outside_since = ()
            log.info("window %d back inside the identification's coverage (outside since window %d, %d windows)",
                     record.index, first, record.index - first,
                     extra={"event": "coverage", "window": record.index, "outside": ""})

    def _publish_health(self, record: WindowRecord | None = None, update: EstimateUpdate | None = None) -> None:
        if self.opcua is not None and self._state in ("running", "starting"):
            self.opcua.publish(self.health())

    # -- health -------------------------------------------------------------------------------------------
    def health(self) -> Health:
        """A frozen snapshot: sampling, the last window, the estimate, compensation, gaps, alarms."""
        with self._lock:
            rec = self.last_record
            windows = self.windows_live
        wall = time.monotonic() - self.started_wall if self.started_wall is not None else 0.0
        devices = self.acquisition.status() if self.acquisition is not None else ()
        if wall > 0 and not self.stepped:
            devices = tuple(replace(d, rate_hz=d.reads_ok / wall) for d in devices)
        est = self.tracker
        hist = est.history if est is not None else None
        live = self.profile.live
        return Health(
            machine=self.profile.name, clock_s=self.clock.now(), uptime_s=wall, windows_live=windows,
            rebuilt_windows=est.rebuilt_windows if est is not None else 0, devices=devices, last_window=rec,
            estimate=est.last if est is not None else None,
            compensation=self.writer.status() if self.writer is not None else None,
            gaps=GapStatus(filled_windows=hist.filled_total if hist else 0, policy=live.gap_policy,
                           last=hist.gaps[-1].describe(self.profile.sampling.window_s) if hist and hist.gaps else ""),
            alarms=tuple(self.alarms.active()) if self.alarms else (), stale_after_s=live.stale_after_s)
