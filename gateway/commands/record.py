"""``cncgw record``: sample the profile's live devices and store one record per window, durably.

Records go to ``DIR/records.sqlite`` (append-only, SQLite WAL: after ``kill -9`` at most the window in
progress is lost) and are exported on exit to ``DIR/<machine>.csv`` in the recording format that
``identify`` and ``estimate`` read; ``--export-only`` re-exports after a crash. Recording into a directory
that already holds records of the same machine continues them.
"""

from __future__ import annotations

import argparse
import logging
import math
import signal
import sys
import threading
from pathlib import Path

from gateway.clock import Clock, RealClock, ScaledClock
from gateway.commands._common import check_rt_priority, positive_float
from gateway.errors import DriverError, GatewayError
from gateway.profile import load_profile
from gateway.record_store import STORE_NAME, RecordStore, export_recording, make_dir
from gateway.windows import WindowRecord, window_index

log = logging.getLogger(__name__)


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Add ``cncgw record``."""
    p = sub.add_parser(
        "record", help="record per-window factors from the profile's live devices",
        description="Sample the devices of PROFILE on the fast period, store one record per window (factors, "
                    "channel statistics, displacement bursts, quality) in DIR/records.sqlite, and export them "
                    "to DIR/<machine>.csv for identify and estimate. Ctrl-C or SIGTERM stops after closing the "
                    "store; the window in progress is not recorded.")
    p.add_argument("--profile", required=True, metavar="PROFILE", help="machine profile (TOML) with devices")
    p.add_argument("--out", required=True, metavar="DIR", help="directory of the record store and the export")
    p.add_argument("--minutes", type=positive_float, default=None, metavar="N",
                   help="stop after N minutes of whole windows (default: until Ctrl-C)")
    p.add_argument("--speedup", type=positive_float, default=1.0, metavar="N",
                   help="run on a clock N times faster than the wall (against simulators running as fast); "
                        "windows then hold N times fewer samples, and the records say so")
    p.add_argument("--spin-us", type=float, default=0.0, metavar="US",
                   help="busy-wait this long before each tick's deadline (lower lateness, more CPU; default 0)")
    p.add_argument("--rt-priority", type=int, default=0, metavar="N",
                   help="sample under SCHED_FIFO at priority N (1-99; needs CAP_SYS_NICE): keeps 2 ms ticks on time "
                        "on a machine shared with CPU-bound work (default 0: the normal scheduler)")
    p.add_argument("--export-only", action="store_true", help="do not record: export the store in DIR again")
    p.add_argument("--quiet", action="store_true", help="no line per window")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Record until stopped; export; print a summary."""
    profile = load_profile(args.profile)
    out = Path(args.out)
    export_path = out / f"{profile.name}.csv"
    if args.export_only:
        with RecordStore(out / STORE_NAME) as store:
            export_recording(store, profile, export_path)
            print(f"exported {len(store)} windows to {export_path}")
        return 0
    if not profile.devices:
        raise GatewayError(f"{profile.path}: no [devices] to record from (this is an offline profile)")
    if args.verbose < 2:
        logging.getLogger("pymodbus").setLevel(logging.CRITICAL)  # our runner reports device errors once
    make_dir(out, "the output directory")
    from threadpoolctl import threadpool_limits

    from gateway.sampler import Acquisition

    with RecordStore(out / STORE_NAME, profile=profile) as store, threadpool_limits(limits=1):
        window_s = profile.sampling.window_s
        clock: Clock
        if args.speedup == 1.0:
            clock = RealClock()
        else:
            # a simulated clock starts where the store left off: records stay append-only
            origin = 0.0 if store.last_index is None else (store.last_index + 1) * window_s
            clock = ScaledClock(args.speedup, origin=origin)
        stop = threading.Event()
        start_t = clock.now()
        end_target = math.inf
        if args.minutes is not None:
            whole = math.ceil(args.minutes * 60.0 / window_s - 1e-9)
            end_target = (window_index(start_t, window_s) + 1 + whole) * window_s

        def report(record: WindowRecord) -> None:
            if not args.quiet:
                print(_line(record), flush=True)
            if record.end_s >= end_target - 1e-9:
                stop.set()

        previous = None
        if threading.current_thread() is threading.main_thread():
            previous = signal.signal(signal.SIGTERM, lambda *_: stop.set())
        check_rt_priority(args.rt_priority)
        acq = Acquisition(profile, clock=clock, sinks=[store, report], spin_s=args.spin_us * 1e-6,
                          rt_priority=args.rt_priority)
        print(f"recording {profile.name} from {len(acq.samplers)} device(s) into {store.path}"
              f"{f' at {args.speedup:g}x' if args.speedup != 1 else ''}; Ctrl-C stops", flush=True)
        try:
            with acq:
                try:
                    while not stop.wait(0.5):
                        pass
                except KeyboardInterrupt:
                    print("stopping", file=sys.stderr, flush=True)
        finally:
            if previous is not None:
                signal.signal(signal.SIGTERM, previous)
        statuses = acq.status()
        for s in statuses:
            print(f"device {s.device}: {s.reads_ok} reads, {s.reads_failed} failed ({s.timeouts} timeouts), "
                  f"{s.ticks_skipped} ticks skipped, {s.off_scan_ticks} off-scan, {s.recoveries} recoveries")
        if len(store):
            export_recording(store, profile, export_path)
            print(f"{len(store)} windows in {store.path}; exported to {export_path}")
        else:
            print(f"no whole window recorded in {store.path}")
        # a device that never answered made a recording of empty windows: a script (cron, a unit) must not take
        # it for a good one; what was recorded stays stored and exported above
        silent = [s for s in statuses if s.reads_ok == 0 and (s.reads_failed or s.off_scan_ticks)]
        if silent:
            raise DriverError("\n".join(
                f'device "{s.device}" never answered while recording ({s.reads_failed} reads failed, '
                f"{s.off_scan_ticks} ticks off-scan){': ' + s.errors[0] if s.errors else ''}: expected the "
                f"device on line (the windows it feeds are insufficient, kept in {store.path})" for s in silent))
    return 0


def _line(r: WindowRecord) -> str:
    errs = "".join(f", device {n}: {d.describe_error()}" for n, d in r.devices.items() if d.in_error)
    return (f"window {r.index} (t={r.end_s:.0f} s) {r.status}: coverage {r.coverage:.1%}, samples "
            f"{r.samples_taken}/{r.samples_expected}, missed {r.missed_ticks}, largest gap {r.largest_gap_s:.3f} s"
            f"{errs}{', ' + r.reason if r.reason else ''}")
