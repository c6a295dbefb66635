"""``cncgw demo``: the whole workflow on the bundled simulated machine, closed loop, in about a minute.

1. Simulate the paper's nine identification experiments (12 h each) on the simulated machining center.
2. Identify the model from those recordings (the joint method), as ``cncgw identify`` does.
3. Run it live: the simulated machine plays the paper's spindle-and-feeds validation run (8 h) behind its
   devices on 127.0.0.1 (the ADC board and the CNC's compensation registers over Modbus TCP); the gateway
   reads the board, closes a window a simulated minute, updates the estimate, writes offsets to the CNC
   (limits, read-back, heartbeat with the CNC's 5 s watchdog) and serves OPC UA. A table follows the run;
   at the end, the max tool-to-table thermal error without and with compensation per axis (the machine's
   ground truth, with the offsets the CNC really applied) and a plot.

The simulated clock moves in lock-step with the gateway (by default): the demo advances it a heartbeat at
a time and the gateway reads the board every 0.73 s of simulated time (a period that does not lock onto
the table's strokes; about what 2 ms of wall time is at 480x), so every window has all its samples and the
figures are the same on an idle or a busy PC; only the wall time changes. ``--realtime`` runs it on a
clock sped up ``--speedup`` times instead, the gateway's threads sampling every 2 ms of wall time, as on a
machine: then a busy PC drops samples, and when windows lack data the demo says its figures are invalid.
At a speed-up of N the CNC's watchdog (5 s) would be 5/N wall seconds: a real-time demo gives the
simulated CNC a watchdog of ``max(5 s, N x 0.5 s)`` of clock time and the gateway a heartbeat five times
faster.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import logging
import queue
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

from gateway import BUNDLED
from gateway.commands._common import plain, positive_float
from gateway.errors import UsageError
from gateway.identify import identify
from gateway.model import save_model
from gateway.profile import load_profile

PROFILE = BUNDLED / "sim-vmc.toml"
IDENTIFICATION = ("spindle-1000rpm", "spindle-500rpm", "spindle-400-600rpm", "feed-x-fast", "feed-x-accel",
                  "feed-y-fast", "feed-y-accel", "feed-z-fast", "feed-z-accel")
VALIDATION = "spindle-feeds"


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Add ``cncgw demo``."""
    p = sub.add_parser("demo", help="the workflow end to end on the bundled simulated machine, closed loop",
                       description=plain(__doc__), formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("-o", "--out", default="demo-out", metavar="DIR",
                   help="where the recordings, the model, the records, the audit log and the plot go "
                        "(default: demo-out)")
    p.add_argument("--realtime", action="store_true",
                   help="run the live part on a sped-up clock with the gateway sampling every 2 ms of wall time "
                        "(figures then depend on how busy this PC is) instead of in lock-step")
    p.add_argument("--speedup", type=positive_float, default=480.0, metavar="N",
                   help="--realtime: simulated seconds per wall second (default 480: 8 h in a minute)")
    p.add_argument("--hours", type=positive_float, default=8.0, metavar="H",
                   help="how much of the 8 h validation run to play (default: all of it)")
    p.add_argument("--table-every-min", type=positive_float, default=30.0, metavar="M",
                   help="a table row every M simulated minutes (default 30)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Simulate, identify, run closed loop; print the tables; write the plot."""
    from gateway.commands._common import progress_bar
    from simulators.machine import load_scenario, simulate, write_run

    rest_s = load_scenario(VALIDATION).initial_idle_s
    if args.hours * 3600.0 <= rest_s + 600.0:
        # the machine rests first: a run that ends there compensates nothing and would print 0 % as a result
        raise UsageError(f"--hours {args.hours:g}: the validation run '{VALIDATION}' rests for its first "
                         f"{rest_s / 3600:g} h (the spindle starts then) and needs at least 10 min of work after it: "
                         f"expected more than {_h(rest_s + 600.0)}, e.g. --hours 3 (the default 8 plays all of it)")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    profile = load_profile(PROFILE)
    print(f"cncgw demo: the bundled simulated machining center ({PROFILE.name}: "
          f"{len(profile.factors)} factors, axes {', '.join(profile.axes)})\n")

    t0 = time.perf_counter()
    update, close = progress_bar(len(IDENTIFICATION), "simulating")
    train = []
    try:
        for name in IDENTIFICATION:
            result = simulate(load_scenario(name))
            write_run(result, out / "experiments")
            train.append(result.recording())
            update(name)
    finally:
        close()
    hours = sum(len(r) for r in train) / 60
    print(f"1/3 simulated the paper's {len(train)} identification experiments ({hours:.0f} machine hours) in "
          f"{time.perf_counter() - t0:.1f} s -> {out / 'experiments'}/")

    t0 = time.perf_counter()
    ident = identify(train, factors=profile.factor_names, axes=profile.axes,
                     units={f.name: f.unit for f in profile.factors}, machine=profile.name)
    model_path = save_model(ident.model, out / "sim-vmc.model.toml")
    print(f"2/3 identified {len(profile.axes)} x {len(profile.factors)} transfer functions (joint method) in "
          f"{time.perf_counter() - t0:.1f} s -> {model_path}")
    for line in ident.report:
        if line.startswith("axis"):
            print(f"    {line.split(';')[0]}")
    return _live(args, out, ident.model)


#: lock-step: the board is read every this many simulated seconds (not a divisor of the strokes' periods)
LOCKSTEP_PERIOD_S = 0.73
#: more windows than this share without their data and the figures say nothing about the method
INVALID_SHARE = 0.01


def _live(args: argparse.Namespace, out: Path, model: object) -> int:
    from gateway.clock import Clock, ManualClock, ScaledClock
    from gateway.live.runtime import LiveGateway
    from simulators.closed_loop import closed_loop_errors, live_profile, plot_closed_loop
    from simulators.devices import DeviceSetConfig, serve
    from simulators.devices.cnc import CompensationConfig
    from simulators.machine import LiveMachine

    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    speedup, end_s = args.speedup, args.hours * 3600.0
    lockstep = not args.realtime
    watchdog_s = 5.0 if lockstep else max(5.0, 0.5 * speedup)
    clock: Clock = ManualClock(0.0) if lockstep else ScaledClock(speedup)
    machine = LiveMachine(VALIDATION, clock=clock)
    config = DeviceSetConfig(adc_rtu=None, can=None, dcon=None,
                             cnc=dataclasses.replace(CompensationConfig(), heartbeat_timeout_s=watchdog_s))
    data = out / "live"
    if (data / "records.sqlite").exists():  # a fresh run each time: the simulated clock starts at 0 again
        for f in data.iterdir():
            f.unlink()
    rows: queue.Queue[tuple] = queue.Queue()
    every_s = args.table_every_min * 60.0

    def listen(record, update) -> None:
        if round(record.end_s) % round(every_s) == 0:
            rows.put((record, update, gw.writer.commanded_um if gw.writer else {}))

    pace = (f"in lock-step with the gateway, which reads the board every {LOCKSTEP_PERIOD_S:g} s of simulated time"
            if lockstep else f"at {speedup:g}x; the gateway samples every 2 ms of wall time")
    print(f"3/3 closed loop: the simulated machine runs '{VALIDATION}' ({args.hours:g} h) behind Modbus TCP devices "
          f"on 127.0.0.1, {pace}, estimates each simulated minute and writes offsets to the CNC (watchdog "
          f"{watchdog_s:g} s of clock time)\n")
    t0 = time.perf_counter()
    with _warnings_held() as warned, tempfile.TemporaryDirectory(prefix="cncgw-demo-") as tmp, \
            serve(machine, clock, config) as devices:
        path = live_profile(devices, Path(tmp) / "sim-vmc-live.toml", opcua_port=0, max_step_um=5.0,
                            period_s=LOCKSTEP_PERIOD_S if lockstep else None,
                            heartbeat_period_s=watchdog_s / 5, watchdog_s=watchdog_s)
        profile = load_profile(path)
        gw = LiveGateway(profile, model=model, data_dir=data, clock=clock, listeners=[listen])  # type: ignore[arg-type]
        with gw:
            if gw.opcua is not None:
                print(f"    OPC UA (read-only): {gw.opcua.endpoint}  e.g. ns=2;s=Estimate.z_um\n")
            print(f"    {'time':>6} {'spindle':>8} {'estimate z':>11} {'offset z':>9} {'error without':>14} "
                  f"{'error with':>11}  alarms")
            while clock.now() < end_s or not rows.empty():
                if lockstep and clock.now() < end_s:
                    gw.run_stepped(min(end_s, clock.now() + every_s))  # the clock moves as the gateway works
                try:
                    record, update, offsets = rows.get(timeout=0.0 if lockstep else 0.2)
                except queue.Empty:
                    continue
                _row(machine, record, update, offsets, gw)
            health = gw.health()
            windows, not_good, _ = gw.store.summary()
        wall = time.perf_counter() - t0
        audit_ok, audit_n = _audit_matches(data, machine)
    print(f"\n    {end_s / 3600:g} simulated hours in {wall:.0f} s; {health.windows_live} windows, "
          f"{health.compensation.writes} verified writes, {health.compensation.beats} heartbeats, "
          f"{audit_n} audited writes: {'every one applied as written' if audit_ok else 'MISMATCHES (see audit)'}")
    print(_validity(windows, not_good, lockstep=lockstep, speedup=speedup))
    if warned:  # held during the table, where they read like a failure between its rows
        print(f"    the gateway warned {len(warned)} time(s) (in its log as they come when it runs as a service):")
        for message in warned:
            print(f"      {message}")
    errs = closed_loop_errors(machine, end_s)
    print("\n    tool-to-table thermal error over the run (machine's ground truth, offsets the CNC applied):\n")
    print(f"    {'axis':<4} {'max error without':>18} {'with compensation':>18} {'reduction':>10}")
    for a in machine.true_displacement_um(0.0):
        before, after = errs.max_without_um[a], errs.max_with_um[a]
        print(f"    {a:<4} {before:>15.2f} um {after:>15.2f} um {100 * (1 - after / before):>9.0f} %")
    from gateway import plotting

    if plotting.available():
        png = plot_closed_loop(errs, out / "demo.png", title=f"{VALIDATION}, closed loop at {speedup:g}x")
        print(f"\nplot: {png}\nrecords and audit log: {data}/")
    else:  # an edge PC's install: the run is what matters there
        print(f"\nplot: skipped (matplotlib is not installed: {plotting.INSTALL_HINT})\n"
              f"records and audit log: {data}/")
    return 0


def _validity(windows: int, not_good: int, *, lockstep: bool, speedup: float) -> str:
    """Whether the figures below measure the method, or a PC that could not keep up."""
    if windows and not_good / windows > INVALID_SHARE:
        why = (f"this PC did not keep up with sampling every 2 ms of wall time at {speedup:g}x (other programs "
               "took the CPU)" if not lockstep else "the simulated devices did not answer")
        return (f"    FIGURES INVALID: {not_good} of {windows} windows lacked their data (coverage below the 90 % "
                f"minimum: {why}); the gateway held the offsets through them, so the reductions below say more "
                f"about this run than about the method. Run it again "
                + ("without --realtime (lock-step: the same figures on any PC)." if not lockstep else "."))
    return (f"    figures valid: {windows - not_good} of {windows} windows had their data"
            + ("" if lockstep else f" (real time at {speedup:g}x)"))


def _row(machine, record, update, offsets, gw) -> None:
    t = record.end_s
    true = machine.true_displacement_um(t)["z"]
    left = machine.residual_um(t)["z"]
    alarms = ",".join(a.name for a in gw.alarms.active()) if gw.alarms else ""
    rpm = record.factors.get("spindle_speed", float("nan"))
    est, offset = _um(update.estimate_um["z"]), _um(offsets.get("z", 0.0))
    print(f"    {t / 3600:>5.1f}h {rpm:>5.0f}rpm {est:>8} um {offset:>6} um {_um(true):>11} um {_um(left):>8} um  "
          f"{alarms}", flush=True)


def _um(x: float) -> str:
    """Two decimals, without the minus of a value that rounds to zero ("-0.00")."""
    text = f"{x:.2f}"
    return text[1:] if text == "-0.00" else text


class _Held(logging.Filter):
    """Keeps the gateway's warnings and errors back from the handlers it is on; lets everything else through."""

    def __init__(self) -> None:
        super().__init__()
        self.messages: list[str] = []

    def filter(self, record: logging.LogRecord) -> bool:
        if record.name.split(".")[0] == "gateway" and record.levelno >= logging.WARNING:
            text = record.getMessage()
            self.messages.append(text if record.levelno == logging.WARNING else f"{record.levelname}: {text}")
            return False
        return True


@contextlib.contextmanager
def _warnings_held() -> Iterator[list[str]]:
    """The gateway's warnings kept, not printed, while the block runs: their messages, for after it.

    Held at the root logger's handlers (where ``cncgw`` prints), so ``-v``'s info and debug lines still go
    out as they come. Should the block fail, what was held is printed before the error goes on.
    """
    held, handlers = _Held(), list(logging.getLogger().handlers)
    for h in handlers:
        h.addFilter(held)
    try:
        yield held.messages
    except BaseException:
        for message in held.messages:
            print(f"cncgw demo: gateway warned: {message}", file=sys.stderr)
        raise
    finally:
        for h in handlers:
            h.removeFilter(held)


def _audit_matches(data: Path, machine) -> tuple[bool, int]:
    """Every audited write was verified, and the CNC's offsets log holds each value written."""
    from gateway.live.audit import AUDIT_NAME, AuditLog

    audit = AuditLog(data / AUDIT_NAME)
    try:
        writes = [w for w in audit.writes() if w.mode == "write"]
    finally:
        audit.close()
    applied = {tuple(round(v, 6) for v in offs.values()) for _, offs in machine.compensation_log}
    ok = all(w.verified and tuple(round(w.commanded_um[a], 6) for a in ("x", "y", "z")) in applied for w in writes)
    return ok, len(writes)


def _h(seconds: float) -> str:
    """``1 h 10 min``: hours and minutes as a person writes them."""
    h, m = divmod(round(seconds / 60.0), 60)
    return " ".join(p for p in (f"{h} h" if h else "", f"{m} min" if m else "") if p) or "0 min"
