"""Probes in the live gateway: read from the CNC, stored with the records, applied to the live estimate.

- :class:`ProbeReader` reads the CNC's probe block (``[probes]``, on the ``[compensation]`` CNC, its own
  Modbus connection) every ``poll_s`` of clock time; a block with a new sequence number or other values is
  a probe, stamped with the clock time it was read. A block that is no probe (a bad axis mask, a value
  out of range, no uncertainty) is refused with the register named, in the log and the audit log, once.
- :class:`ProbedTracker` is the live :class:`~gateway.live.tracking.DisplacementTracker` with the update of
  :mod:`gateway.adaptive.filter` on top: it steps the filter with the model's per-path contributions at every
  window the model steps (a filled gap too), then applies the probes read by that window's end. Each probe
  is stored in ``records.sqlite`` (table ``probes``, with the window after which it was applied) BEFORE it
  is applied; a probe the store cannot take is not applied. Every decision (applied, refused and why,
  re-anchored) goes to the audit log (kind ``probe``) and the log.
- The estimate it hands on is the updated one, with its band (``EstimateUpdate.sd_um``: the 95 % half-band
  / 1.96); with ``band_limit_um`` set, a window whose band on any axis is wider is not usable: the writer
  holds the offsets and says why (alarm ``inputs``, audited).
- On start, :meth:`ProbedTracker.rebuild` replays the same stored windows as the model's rebuild and the
  stored probes after the same windows, so the filter's state is a pure function of the store: a restart
  gives what an uninterrupted run had, to rounding, as long as the store holds the run from its first window
  (probes older than the replayed history, 20 x the model's slowest time constant, are forgotten).
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from collections.abc import Iterable
from dataclasses import replace
from types import MappingProxyType
from typing import Any

import numpy as np

from gateway.adaptive.filter import Z95, AdaptiveEstimator, DriftSettings
from gateway.adaptive.offline import model_beyond
from gateway.adaptive.probes import PROBE_BLOCK_WORDS, Probe, ProbeDecision, decode_probe_block
from gateway.clock import Clock
from gateway.errors import CompensationError, DriverError, RecordingError
from gateway.live.tracking import DisplacementTracker, EstimateUpdate
from gateway.profile.probes import Probes
from gateway.record_store import ProbeStore
from gateway.windows import WindowRecord

log = logging.getLogger("gateway.live.probes")


class ProbeReader:
    """Reads the CNC's probe block (see the module docstring); :meth:`take` hands over the new probes."""

    def __init__(self, settings: Probes, *, link_factory: Any, clock: Clock, audit: Any = None) -> None:
        self.settings = settings
        self.clock = clock
        self.audit = audit
        self._link_factory = link_factory
        self._link: Any = None
        self._queue: deque[Probe] = deque()
        self._lock = threading.Lock()
        self._last_words: list[int] | None = None
        self._failing = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._next_s: float | None = None
        self.reads = 0
        self.refused_blocks = 0

    def service(self, now: float | None = None) -> None:
        """Read the block if a poll is due at ``now`` (clock time); the stepped runtime calls this."""
        now = self.clock.now() if now is None else now
        if self._next_s is not None and now < self._next_s - 1e-9:
            return
        self._next_s = now + self.settings.poll_s
        self.poll(now)

    def poll(self, now: float) -> None:
        s = self.settings
        try:
            if self._link is None:
                self._link = self._link_factory()
            words = self._link.read_words(s.register, PROBE_BLOCK_WORDS, function=s.function)
        except (DriverError, CompensationError) as exc:
            if not self._failing:
                log.warning("probe block: %s (the next read is in %g s)", exc, s.poll_s)
            self._failing = True
            return
        if self._failing:
            log.info("probe block readable again")
        self._failing = False
        self.reads += 1
        if words == self._last_words:
            return
        self._last_words = list(words)
        probe, problems = decode_probe_block(words, time_s=now, unit_um=s.unit_um, first_register=s.register,
                                             source="cnc")
        if problems:
            self.refused_blocks += 1
            message = "; ".join(problems) + ": not a probe, not applied"
            log.warning("probe block refused: %s", message)
            if self.audit is not None:
                self.audit.event(now, "probe", "refused", message)
            return
        if probe is not None:
            with self._lock:
                self._queue.append(probe)

    def take(self) -> list[Probe]:
        with self._lock:
            out = list(self._queue)
            self._queue.clear()
        return out

    def start(self) -> ProbeReader:
        self._thread = threading.Thread(target=self._run, name="cncgw-probes", daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        wait = self.settings.poll_s / self.clock.speedup
        while not self._stop.is_set():
            try:
                self.poll(self.clock.now())
            except Exception:  # the probe reader never takes the gateway down
                log.exception("probe block: read failed")
            self._stop.wait(wait)

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        if self._link is not None:
            self._link.close()
            self._link = None


class ProbedTracker(DisplacementTracker):
    """The live estimator updated by probes (see the module docstring).

    Extra keyword arguments beyond :class:`~gateway.live.tracking.DisplacementTracker`'s: ``probes`` (the ``[probes]``
    settings), ``store`` (a :class:`ProbeStore`), ``source`` (a callable giving the probes read since the
    last call, e.g. :meth:`ProbeReader.take`), ``audit`` (an audit log) and ``clock``.
    """

    def __init__(self, model: Any, *, probes: Probes, store: ProbeStore, source: Any = None, audit: Any = None,
                 clock: Clock | None = None, **kw: Any) -> None:
        super().__init__(model, **kw)
        self.probe_settings = probes
        self.adaptive = AdaptiveEstimator(model, window_s=self.window_s,
                                          settings=DriftSettings(gate_sigma=probes.gate_sigma))
        self.probe_store = store
        self.source = source
        self.audit = audit
        self.clock = clock
        self._waiting: list[Probe] = []
        self.decisions: list[ProbeDecision] = []

    # -- the hooks of DisplacementTracker ---------------------------------------------------------------------------
    def _stepped(self, index: int, du: np.ndarray) -> None:
        # beyond the model's coverage the band widens (AdaptiveEstimator.step)
        beyond = model_beyond(self.model, np.asarray(du, dtype=float)[:, None])
        self.adaptive.step(self.stepper.contributions(), (index + 1) * self.window_s,
                           None if beyond is None else beyond[:, 0])

    def _rebuilt(self, first_index: int, du: np.ndarray) -> None:
        contributions = self.dm.contributions(du)
        beyond = model_beyond(self.model, du)
        stored: dict[int, list[Probe]] = {}
        for window, probe in self.probe_store.probes(since_window=first_index):
            stored.setdefault(window, []).append(probe)
        for k in range(du.shape[1]):
            self.adaptive.step(contributions[:, :, k], (first_index + k + 1) * self.window_s,
                               None if beyond is None else beyond[:, k])
            for probe in stored.get(first_index + k, []):
                self.adaptive.probe(probe)
        log.info("probe update rebuilt: %d windows, %d stored probes", du.shape[1],
                 sum(len(v) for v in stored.values()))

    # -- per window ---------------------------------------------------------------------------------------
    def update(self, record: WindowRecord) -> EstimateUpdate:
        base = super().update(record)
        self._waiting += self.source() if self.source is not None else []
        due = [p for p in self._waiting if p.time_s <= record.end_s + 1e-9]
        self._waiting = [p for p in self._waiting if p.time_s > record.end_s + 1e-9]
        for probe in due:
            self._apply(probe, record.index)
        return self._updated(base)

    def _apply(self, probe: Probe, window: int) -> None:
        now = self.clock.now() if self.clock is not None else probe.time_s
        if self.adaptive.seq.check(probe) == "":
            return  # the block read again after a restart: the probe is stored and applied already
        try:
            self.probe_store.append(probe, window)
        except RecordingError as exc:  # store first: what is not stored is not applied
            log.error("%s: not applied", exc)
            if self.audit is not None:
                self.audit.event(now, "probe", "refused", f"{exc}: not applied")
            return
        for d in self.adaptive.probe(probe):
            self.decisions.append(d)
            text = d.describe()
            (log.info if d.accepted else log.warning)("%s", text)
            if self.audit is not None:
                self.audit.event(now, "probe", "applied" if d.accepted else "refused", text)

    def _updated(self, base: EstimateUpdate) -> EstimateUpdate:
        est = self.adaptive.estimate()
        axes = self.model.axes
        estimate = {a: e.estimate_um for a, e in zip(axes, est, strict=True)}
        sd = {a: e.sd_um for a, e in zip(axes, est, strict=True)}
        ahead = {a: estimate[a] + (base.next_um[a] - base.estimate_um[a]) for a in axes}
        usable, reason = base.usable, base.reason
        limit = self.probe_settings.band_limit_um
        if usable and limit is not None:
            wide = [(a, Z95 * s) for a, s in sd.items() if not Z95 * s <= limit]
            if wide:
                usable = False
                reason = ("95 % band " + ", ".join(f"{a} +-{w:.2f} um" for a, w in wide)
                          + f" wider than probes.band_limit_um = {limit:g} um: the estimate is not trusted enough "
                          "to write (a probe narrows it)")
        upd = replace(base, estimate_um=MappingProxyType(estimate), next_um=MappingProxyType(ahead),
                      sd_um=MappingProxyType(sd), usable=usable, reason=reason)
        self.last = upd
        return upd

    def rebuild(self, records: Iterable[WindowRecord], *, origin: WindowRecord | None = None) -> int:
        n = super().rebuild(records, origin=origin)
        if n and self.last is not None:
            self.last = self._updated(self.last)
        return n
