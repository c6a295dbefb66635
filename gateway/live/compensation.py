"""The compensation writer: estimates in, safe offsets out to the CNC, every value audited.

Per update (one a window) the writer turns the estimate into offsets, ``offset = sign * estimate`` per axis
(the profile's ``[compensation.axes.*]``; the bundled CNC adds the offset to the position, so ``sign = -1``
cancels the estimate), and moves the commanded offsets towards them under three limits, in this order:

1. clamp to +-``limit_um`` (alarm ``clamped``);
2. at most ``max_step_um`` of change per axis and update: never a jump, whatever the estimate does;
3. a deadband: nothing is written while every axis is within ``deadband_um`` of what the CNC applies.

Nothing that is not finite, beyond the limit or beyond the register type ever reaches the wire (checked
again right before encoding). After each write the CNC's applied offsets are read back and compared count
for count with what was written (alarm ``verify`` otherwise; the writer then takes the CNC's value as the
truth and re-synchronises).

Faults. An update whose estimate rests on bad or missing windows, or no update for ``[live]
stale_after_s``, holds the offsets at once and raises an alarm (``inputs``); an estimate outside the
model's plausibility envelope (:mod:`gateway.live.plausibility`: too large, moving too fast, not finite)
holds them too and raises ``implausible``: such an estimate is never clamped and written. With
``on_fault = "ramp_to_zero"`` the offsets ramp to zero at ``max_step_um`` a window once a fault has lasted
``fault_hold_s``. A CNC that cannot be reached or refuses a write raises ``cnc``; nothing is assumed
written. On (re)connecting, the writer reads what the CNC applies and first commands exactly that, then
enables it: a restart, a CNC that tripped its watchdog (offsets ramping down) or one that was reset never
sees a jump; the limits then walk the offsets back to the estimate.

Heartbeat: written every ``heartbeat_period_s`` of clock time (a sped-up simulator's clock too) while the
writer runs, inputs good or not: holding is a decision of the gateway, dropping the offsets the CNC's
watchdog's. On stop the writer stops beating and leaves the offsets in place: back within the watchdog
time, a restarted gateway continues seamlessly; later, the CNC's watchdog ramps them out.

Audit. Every write is a row of the audit log: ``write`` (sent and read back), ``refused`` (the CNC said no:
nothing applied), ``unknown`` (no answer in time: the CNC may or may not have applied it). The first
read of the CNC that follows an unknown write (the read-back after it, a re-synchronisation, a heartbeat)
adds a ``resolved`` row with what the CNC applies, and any read showing offsets other than the last
audited ones (a write applied after its answer was lost, a watchdog ramp, a reset CNC) adds an ``observed``
row: the audited history of applied offsets follows the CNC's, value for value.

Dry run (``enabled = false``): the same computation, logged and audited as ``dry-run``; no connection.
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from types import MappingProxyType

from gateway.clock import Clock
from gateway.errors import CompensationError, DriverError
from gateway.live.audit import Alarms, AuditLog, WriteEntry
from gateway.live.cnc import CncLink, CncRejected, CncState
from gateway.live.plausibility import Plausibility
from gateway.live.tracking import EstimateUpdate
from gateway.profile.live import Compensation

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True, slots=True)
class WriterStatus:
    """The compensation writer at one moment, for health, OPC UA, MQTT and logs.

    ``mode``: ``"write"`` or ``"dry-run"``; ``synced``: connected to the CNC and holding what it applies;
    ``commanded_um``: the offsets the CNC applies as far as the writer knows (axis -> um); ``writes``,
    ``beats``, ``failures``: counters since start; ``cnc_status``: the CNC's last status word (``None``:
    not read, or not mapped); ``last_write``: the last write the CNC applies (or, dry, would apply);
    ``holding``: a fault (inputs, an implausible estimate) holds the offsets.
    """

    mode: str
    synced: bool
    commanded_um: Mapping[str, float]
    writes: int
    beats: int
    failures: int
    cnc_status: int | None
    last_write: WriteEntry | None
    holding: bool


class CompensationWriter:
    """Writes offsets to the CNC from estimate updates; see the module docstring.

    Args:
        settings: the profile's ``[compensation]``.
        clock: the shared clock (heartbeat, staleness and ramps are clock time).
        window_s: the profile's window (the ramp's pace on a fault).
        stale_after_s: no update for this long (clock s) is a fault.
        alarms: where alarms go (default: a private :class:`Alarms`).
        audit: the audit log (default: none).
        link_factory: makes the CNC link (default: :class:`CncLink` on the settings); tests pass one that
            talks to a simulator the same way.
        plausibility: the bounds an estimate must meet to move the offsets (the live gateway always passes
            the model's; ``None``: no check, for tests of the limits alone).

    Run it as a thread (:meth:`start`/:meth:`stop`), or call :meth:`service` from a stepping loop.

    """

    def __init__(self, settings: Compensation, *, clock: Clock, window_s: float, stale_after_s: float,
                 alarms: Alarms | None = None, audit: AuditLog | None = None,
                 link_factory: Callable[[], CncLink] | None = None,
                 plausibility: Plausibility | None = None) -> None:
        self.settings = settings
        self.plausibility = plausibility
        self.clock = clock
        self.window_s = float(window_s)
        self.stale_after_s = float(stale_after_s)
        self.alarms = alarms if alarms is not None else Alarms(audit=audit)
        self.audit = audit
        self.axes = tuple(a.axis for a in settings.axes)
        self._link_factory = link_factory or (lambda: CncLink(settings, clock=clock))
        self._link: CncLink | None = None
        self._lock = threading.Lock()
        self._pending: EstimateUpdate | None = None
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.commanded_um: dict[str, float] = dict.fromkeys(self.axes, 0.0)  # what the CNC applies, as far as known
        self.synced = False
        self.cnc_state: CncState | None = None
        # a restarted gateway's first beat must differ from the last one its predecessor left in the register
        self._beat = int.from_bytes(os.urandom(2), "big")
        self._next_beat_s = -math.inf
        self._next_connect_wall = 0.0
        self._inputs_from_s: float | None = None  # set by expect_inputs(): no staleness before inputs are due
        self._last_update_s: float | None = None
        self._fault_since_s: float | None = None
        self._last_ramp_s: float | None = None
        #: counters and the last write, for health and benchmarks
        self.writes = 0
        self.beats = 0
        self.failures = 0
        self.last_write: WriteEntry | None = None
        self.latencies_s: list[float] = []  # window close (update received) -> verified write, wall seconds
        self._received_wall: float | None = None
        self.hold_requested = False
        #: the thread's CPU time and wall span, known once it stopped (benchmarks)
        self.cpu_s = 0.0
        self.started_wall: float | None = None
        self.stopped_wall: float | None = None
        self._unresolved: WriteEntry | None = None  # a write whose outcome is unknown (no answer in time)
        self._audited_counts: dict[str, int] | None = None  # the CNC's applied offsets as last audited

    @property
    def writing(self) -> bool:
        return self.settings.enabled

    def expect_inputs(self, from_s: float | None = None) -> None:
        """Inputs are due from now on (the acquisition started): staleness counts from here."""
        self._inputs_from_s = self.clock.now() if from_s is None else from_s

    def request_hold(self, on: bool) -> None:
        """An operator's hold: while on, updates do not move the offsets (the heartbeat goes on)."""
        self.hold_requested = bool(on)
        self._wake.set()

    # -- input (any thread) -------------------------------------------------------------------------------
    def submit(self, update: EstimateUpdate, *, since_wall: float | None = None) -> None:
        """Hand over the newest estimate (cheap; the writer's thread acts on it).

        ``since_wall``: ``time.perf_counter()`` when the window was closed, for the latency figures.
        """
        with self._lock:
            self._pending = update
            self._received_wall = time.perf_counter() if since_wall is None else since_wall
        self._wake.set()

    # -- the thread ---------------------------------------------------------------------------------------
    def start(self) -> CompensationWriter:
        if self._thread is not None:
            raise RuntimeError("the compensation writer is already running")
        if not math.isfinite(self.clock.speedup):
            raise RuntimeError("a ManualClock has no wall time to beat on: call service() as the clock moves")
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="cncgw-compensation", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the thread and close the link (offsets stay in place: see the module docstring)."""
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        self.close()

    def close(self) -> None:
        if self._link is not None:
            self._link.close()
            self._link = None
        self.synced = False

    def _run(self) -> None:
        self.started_wall = time.monotonic()
        try:
            while not self._stop.is_set():
                try:
                    self.service()
                except Exception:  # a bug in one cycle must not stop the heartbeat for good
                    log.exception("compensation writer: cycle failed")
                self._wake.wait(self._idle_wall_s())
                self._wake.clear()
        finally:
            self.stopped_wall = time.monotonic()
            self.cpu_s = time.thread_time()

    def _idle_wall_s(self) -> float:
        """Wall seconds the thread may sleep before :meth:`service` has something to do (an update wakes it).

        At most a heartbeat period (staleness and fault ramps are checked at that pace); less while a
        beat is due sooner. Only a synced writer beats: a dry run, or a writer waiting to reconnect, sleeps
        the whole period (or until the next connection attempt) instead of spinning on a beat that will
        never be sent.
        """
        period = self.settings.heartbeat_period_s / self.clock.speedup
        if not self.writing:
            return period
        if not self.synced:
            return max(0.0, min(period, self._next_connect_wall - time.monotonic()))
        return max(0.0, min(period, (self._next_beat_s - self.clock.now()) / self.clock.speedup))

    # -- one cycle ----------------------------------------------------------------------------------------
    def service(self) -> None:
        """Connect if needed, beat if due, act on a new update or a fault ramp (one call does it all)."""
        now = self.clock.now()
        if self.writing and not self.synced:
            self._sync(now)
        if self.writing and self.synced and now >= self._next_beat_s:
            self._heartbeat(now)
        with self._lock:
            update, self._pending = self._pending, None
            received = self._received_wall
        if update is not None:
            self._on_update(update, now, received)
        else:
            self._check_stale(now)

    def _sync(self, now: float) -> None:
        wall = time.monotonic()
        if wall < self._next_connect_wall:
            return
        link = self._link or self._link_factory()
        self._link = link
        try:
            state = link.state()
            self._observe(now, state)
            # command what the CNC applies now before enabling it: enabling applies the command at once
            link.write_offsets(state.applied_counts)
            self._beat += 1
            link.beat(self._beat)
            if state.active is not True:
                link.set_enabled(True)
            state = link.state()
        except (DriverError, CompensationError) as exc:
            self._link_failed(now, f"cannot synchronise with the CNC: {exc}")
            return
        self.cnc_state = state
        self.commanded_um = dict(state.applied_um)
        self.synced = True
        self._next_beat_s = now + self.settings.heartbeat_period_s
        self.alarms.clear("cnc", now, "CNC reachable; offsets taken over as applied: " + _fmt(state.applied_um))
        self.alarms.clear("verify", now, "re-synchronised with the CNC")
        if self.audit is not None:
            self.audit.event(now, "sync", "cnc", f"synchronised: applied {_fmt(state.applied_um)}, status "
                                                 f"{state.status}")
        log.info("CNC synchronised: applied %s, status %s", _fmt(state.applied_um), state.status)

    def _link_failed(self, now: float, message: str) -> None:
        self.failures += 1
        self.synced = False
        self._next_connect_wall = time.monotonic() + self.settings.reconnect_s
        if self._link is not None:
            self._link.close()
            self._link = None
        self.alarms.raise_("cnc", message, now)

    def _heartbeat(self, now: float) -> None:
        """Beat, then check the CNC still applies what was commanded (a trip or a reset shows here)."""
        assert self._link is not None
        self._beat += 1
        try:
            self._link.beat(self._beat)
            state = self._link.state()
        except (DriverError, CompensationError) as exc:
            self._link_failed(now, f"heartbeat failed: {exc}")
            return
        self.beats += 1
        self.cnc_state = state
        self._observe(now, state)
        self._next_beat_s = now + self.settings.heartbeat_period_s
        expected = {a.axis: round(self.commanded_um[a.axis] / a.unit_um) for a in self.settings.axes}
        if state.active is False or state.applied_counts != expected:
            self.alarms.raise_("verify", f"the CNC applies {_fmt(state.applied_um)} (status {state.status}, "
                                         f"{'tripped' if state.tripped else 'active' if state.active else 'inactive'}"
                                         f"), not the {_fmt(self.commanded_um)} commanded: re-synchronising", now)
            self.commanded_um = dict(state.applied_um)
            self.synced = False

    # -- deciding what to write ---------------------------------------------------------------------------
    def _on_update(self, update: EstimateUpdate, now: float, received_wall: float | None) -> None:
        self._last_update_s = now
        estimate = {a: float(update.estimate_um.get(a, math.nan)) for a in self.axes}
        if not update.usable:
            if update.first_live and update.filled <= 1:
                return  # the gateway joined its first window part-way: hold quietly for that one window
            self._fault(now, f"holding the offsets: {update.reason}", update, estimate)
            return
        self.alarms.clear("inputs", now, f"inputs good again at window {update.index}")
        ahead = {a: float(update.next_um.get(a, math.nan)) for a in self.axes}
        use_ahead = self.settings.aim == "midpoint"
        if self.plausibility is not None:
            implausible = self.plausibility.check(update.index, estimate, ahead if use_ahead else None)
        elif not all(math.isfinite(v) for v in estimate.values()):
            implausible = f"window {update.index}: estimate not finite: {_fmt(estimate)}"
        else:
            implausible = ""
        if implausible:  # a model far outside its data, or corrupt: hold, never clamp and write
            self._fault(now, f"holding the offsets: {implausible}", update, estimate, alarm="implausible")
            return
        self.alarms.clear("implausible", now, f"estimate plausible again at window {update.index}")
        if self.hold_requested:
            self.alarms.raise_("operator_hold", "an operator asked to hold the offsets (OPC UA HoldRequest)", now)
            return
        self.alarms.clear("operator_hold", now)
        self._fault_since_s = None
        aim = estimate
        if use_ahead and all(math.isfinite(v) for v in ahead.values()):
            aim = {a: 0.5 * (estimate[a] + ahead[a]) for a in self.axes}
        target = {a.axis: a.sign * aim[a.axis] for a in self.settings.axes}
        self._move(now, update.index, estimate, target, received_wall)

    def _check_stale(self, now: float) -> None:
        since = self._last_update_s if self._last_update_s is not None else self._inputs_from_s
        if since is not None and now - since > self.stale_after_s:
            self._fault(now, f"holding the offsets: no estimate since t = {since:.0f} s (stale inputs, more than "
                             f"{self.stale_after_s:g} s)", None, None)

    def _fault(self, now: float, message: str, update: EstimateUpdate | None,
               estimate: dict[str, float] | None, *, alarm: str = "inputs") -> None:
        if self._fault_since_s is None:
            self._fault_since_s = now
        self.alarms.raise_(alarm, message, now)
        s = self.settings
        if s.on_fault != "ramp_to_zero" or now - self._fault_since_s < s.fault_hold_s:
            return
        if self._last_ramp_s is not None and now - self._last_ramp_s < self.window_s - 1e-9:
            return  # the ramp moves max_step_um a window, however often this is called
        if all(v == 0.0 for v in self.commanded_um.values()):
            return
        self._last_ramp_s = now
        self.alarms.raise_("ramp", f"{alarm} fault for {now - self._fault_since_s:.0f} s: ramping the offsets to "
                                   "zero", now)
        nan = dict.fromkeys(self.axes, math.nan)
        self._move(now, update.index if update else None, estimate or nan, dict.fromkeys(self.axes, 0.0), None,
                   note="fault ramp to zero")

    def limited(self, target_um: Mapping[str, float], now: float) -> dict[str, float]:
        """The next offsets: ``target_um`` clamped, then moved from the commanded ones by at most a step."""
        s = self.settings
        out = {}
        clamped = []
        for a in s.axes:
            t = target_um[a.axis]
            if abs(t) > s.limit_um:
                clamped.append(f"{a.axis} {t:+.2f} um")
                t = math.copysign(s.limit_um, t)
            cur = self.commanded_um[a.axis]
            step = max(-s.max_step_um, min(s.max_step_um, t - cur))
            out[a.axis] = cur + step
        if clamped:
            self.alarms.raise_("clamped", f"target beyond +-{s.limit_um:g} um: {', '.join(clamped)}", now)
        else:
            self.alarms.clear("clamped", now)
        return out

    def _move(self, now: float, window: int | None, estimate: Mapping[str, float], target: Mapping[str, float],
              received_wall: float | None, note: str = "") -> None:
        s = self.settings
        new = self.limited(target, now)
        if all(abs(new[a] - self.commanded_um[a]) < s.deadband_um for a in self.axes):
            return
        counts = {}
        for a in s.axes:
            c = round(new[a.axis] / a.unit_um)
            um = c * a.unit_um
            # the last check before the wire: finite, within the limit and the register type
            if not (math.isfinite(new[a.axis]) and abs(um) <= s.limit_um + a.unit_um / 2 and abs(c) <= a.max_counts):
                self.alarms.raise_("refused", f"axis {a.axis}: {new[a.axis]!r} um is not a value to write", now)
                return
            counts[a.axis] = c
        if all(counts[a.axis] == round(self.commanded_um[a.axis] / a.unit_um) for a in s.axes):
            return  # finer than the registers' resolution: nothing new to write
        commanded = {a.axis: counts[a.axis] * a.unit_um for a in s.axes}
        if not self.writing:
            self._record(now, window, "dry-run", estimate, target, commanded, commanded, True, None, note)
            self.commanded_um = commanded
            return
        if not self.synced or self._link is None:
            self.alarms.raise_("cnc", "CNC not reachable: offsets not written", now)
            return
        try:
            self._link.write_offsets(counts)
            state = self._link.state()
        except CncRejected as exc:  # the CNC said no: nothing of the request applies; the link is fine
            self.failures += 1
            self._record(now, window, "refused", estimate, target, commanded, dict(self.commanded_um), False, None,
                         f"refused by the CNC: {exc}")
            self.alarms.raise_("cnc", f"write of {_fmt(commanded)} refused: {exc}", now)
            self._refresh_after_failure(now)
            return
        except (DriverError, CompensationError) as exc:  # sent, no answer: applied or not, the next read says
            self._unresolved = self._record(now, window, "unknown", estimate, target, commanded,
                                            dict.fromkeys(self.axes, math.nan), False, None,
                                            f"outcome unknown ({exc}); resolved by the next read of the CNC")
            self._link_failed(now, f"write of {_fmt(commanded)} failed: {exc}")
            self._refresh_after_failure(now)
            return
        self.cnc_state = state
        verified = all(state.applied_counts.get(a) == counts[a] for a in self.axes)
        self._record(now, window, "write", estimate, target, commanded, state.applied_um, verified, state.status,
                     note)
        self._audited_counts = dict(state.applied_counts)
        self.commanded_um = dict(state.applied_um)  # the CNC's word is the truth
        if verified:
            self.alarms.clear("verify", now)
            if received_wall is not None:
                self.latencies_s.append(time.perf_counter() - received_wall)
        else:
            self.alarms.raise_("verify", f"the CNC applies {_fmt(state.applied_um)}, not the {_fmt(commanded)} "
                                         f"written (status {state.status}): re-synchronising", now)
            self.synced = False

    def _refresh_after_failure(self, now: float) -> None:
        """After a failed write: learn what the CNC applies, if it answers at all."""
        link = self._link
        try:
            if link is not None:
                state = link.state()
            else:
                link = self._link_factory()
                try:
                    state = link.state()
                finally:
                    link.close()
        except (DriverError, CompensationError):
            return
        self.cnc_state = state
        self._observe(now, state)
        self.commanded_um = dict(state.applied_um)

    def _observe(self, now: float, state: CncState) -> None:
        """Audit what the CNC applies when it is not what the audit log last said (see the module docstring)."""
        u = self._unresolved
        if u is not None:
            self._unresolved = None
            counts = {a.axis: round(u.commanded_um[a.axis] / a.unit_um) for a in self.settings.axes}
            applied = state.applied_counts == counts
            what = "applied as written" if applied else f"not applied (the CNC applies {_fmt(state.applied_um)})"
            self._record(now, u.window, "resolved", u.estimate_um, u.target_um, u.commanded_um, state.applied_um,
                         applied, state.status, f"the write of t = {u.t_s:.0f} s whose outcome was unknown: {what}")
        elif self._audited_counts is not None and dict(state.applied_counts) != self._audited_counts:
            self._record(now, None, "observed", dict.fromkeys(self.axes, math.nan), dict.fromkeys(self.axes, math.nan),
                         dict(self.commanded_um), state.applied_um, False, state.status,
                         "the CNC applies other offsets than last audited: a write applied after its answer was "
                         "lost, a watchdog ramp or a reset")
        self._audited_counts = dict(state.applied_counts)

    def _record(self, now: float, window: int | None, mode: str, estimate: Mapping[str, float],
                target: Mapping[str, float], commanded: Mapping[str, float], applied: Mapping[str, float],
                verified: bool, status: int | None, note: str) -> WriteEntry:
        entry = WriteEntry(t_s=now, window=window, mode=mode, estimate_um=MappingProxyType(dict(estimate)),
                           target_um=MappingProxyType(dict(target)), commanded_um=MappingProxyType(dict(commanded)),
                           applied_um=MappingProxyType(dict(applied)), verified=verified, status=status, note=note)
        if mode in ("write", "dry-run", "unknown", "refused"):  # sent (or, dry, computed), not observed
            self.writes += 1
        if mode in ("write", "dry-run", "resolved"):  # what the CNC applies after a write of ours
            self.last_write = entry
        if self.audit is not None:
            self.audit.write(entry)
        log.info("%s window %s: commanded %s, applied %s%s", mode, window, _fmt(commanded), _fmt(applied),
                 "" if verified or mode in ("unknown", "observed", "refused") else " (MISMATCH)")
        return entry

    def status(self) -> WriterStatus:
        """Mode, link state, offsets, counters and the last write (see :class:`WriterStatus`)."""
        return WriterStatus(mode="write" if self.writing else "dry-run", synced=self.synced,
                            commanded_um=MappingProxyType(dict(self.commanded_um)), writes=self.writes,
                            beats=self.beats, failures=self.failures,
                            cnc_status=None if self.cnc_state is None else self.cnc_state.status,
                            last_write=self.last_write, holding=self._fault_since_s is not None)


def _fmt(values: Mapping[str, float]) -> str:
    return ", ".join(f"{a} {v:+.2f} um" for a, v in values.items())
