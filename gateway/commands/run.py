"""``cncgw run``: the live gateway, the program left running on the edge PC.

Samples the profile's devices, stores one record per window in ``DATA/records.sqlite``, updates the
estimate each window, writes the compensation to the CNC (a dry run unless ``[compensation] enabled``),
serves OPC UA, and logs one line per window plus every alarm. SIGTERM (systemd's stop) or Ctrl-C stops it
cleanly; after a crash or ``kill -9`` the next start rebuilds the estimate from the stored records.
"""

from __future__ import annotations

import argparse
import faulthandler
import json
import logging
import signal
import sys
import threading
from pathlib import Path
from typing import Any

from gateway.clock import Clock, RealClock, ScaledClock
from gateway.commands._common import check_rt_priority, load_model_for, plain, positive_float
from gateway.errors import GatewayError, ModelError, ProfileError
from gateway.profile import load_profile

log = logging.getLogger("gateway.live")

_STANDARD = set(vars(logging.LogRecord("", 0, "", 0, "", None, None))) | {"message", "asctime"}


class JsonFormatter(logging.Formatter):
    """One JSON object per line: time, level, logger, message and any ``extra`` fields (structured logs)."""

    def format(self, record: logging.LogRecord) -> str:
        out: dict[str, Any] = {"ts": round(record.created, 3), "level": record.levelname, "logger": record.name,
                               "msg": record.getMessage()}
        for k, v in vars(record).items():
            if k not in _STANDARD and not k.startswith("_"):
                out[k] = v
        if record.exc_info:
            out["exc"] = self.formatException(record.exc_info)
        return json.dumps(out, default=str, allow_nan=True)


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Add ``cncgw run``."""
    p = sub.add_parser("run", help="run the live gateway: sample, estimate, compensate, serve OPC UA",
                       description=plain(__doc__), formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--profile", required=True, metavar="PROFILE", help="machine profile (TOML) with devices")
    p.add_argument("--data", required=True, metavar="DIR",
                   help="directory of records.sqlite and audit.sqlite (e.g. /var/lib/cncgw/MACHINE)")
    p.add_argument("--model", metavar="MODEL", help="model file (default: the profile's [model] file)")
    p.add_argument("--speedup", type=positive_float, default=1.0, metavar="N",
                   help="run on a clock N times faster than the wall (against simulators running as fast)")
    p.add_argument("--minutes", type=positive_float, default=None, metavar="N",
                   help="stop after N minutes of clock time (default: until SIGTERM or Ctrl-C)")
    p.add_argument("--log-format", choices=("text", "json"), default="text",
                   help="text lines (default) or one JSON object per line with the window's fields")
    p.add_argument("--no-opcua", action="store_true", help="do not serve OPC UA whatever the profile says")
    p.add_argument("--spin-us", type=float, default=0.0, metavar="US", help="sampler busy-wait before each tick")
    p.add_argument("--rt-priority", type=int, default=0, metavar="N",
                   help="sample under SCHED_FIFO at priority N (1-99; needs CAP_SYS_NICE)")
    p.set_defaults(func=run)


def _configure_logging(fmt: str, verbose: int) -> None:
    root = logging.getLogger()
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(JsonFormatter() if fmt == "json" else
                         logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    root.handlers[:] = [handler]
    root.setLevel(logging.DEBUG if verbose >= 2 else logging.INFO)
    if verbose < 2:
        logging.getLogger("pymodbus").setLevel(logging.CRITICAL)  # our runner reports device errors once
        logging.getLogger("asyncua").setLevel(logging.WARNING)


def _continue_from(profile: Any, data: Path) -> float:
    """A sped-up clock starts where the store left off, so records stay append-only."""
    from gateway.record_store import STORE_NAME, RecordStore

    if not (data / STORE_NAME).exists():
        return 0.0
    with RecordStore(data / STORE_NAME) as store:
        return 0.0 if store.last_index is None else (store.last_index + 1) * profile.sampling.window_s


def _already_stopping(*_: object) -> None:
    log.warning("already stopping: the gateway is releasing the offsets and closing its records (kill -9 "
                "would cut that short; the CNC's watchdog would then clear the offsets)")


def run(args: argparse.Namespace) -> int:
    """Run until stopped; return 0 after a clean stop."""
    profile = load_profile(args.profile)
    if not profile.devices:
        raise GatewayError(f"{profile.path}: no [devices] to sample (this is an offline profile)")
    check_rt_priority(args.rt_priority)
    model, model_path = load_model_for(profile, args.model)
    from gateway.live.plausibility import model_refusals
    from gateway.live.tracking import column_channel_problems, retention_problems

    problems = column_channel_problems(model, [c.name for c in profile.channels])
    problems += model_refusals(model, profile.name, profile.compensation)
    if problems:
        raise ModelError("\n".join(f"{model_path}: {p}" for p in problems))
    problems = retention_problems(model, profile)
    if problems:
        raise ProfileError("\n".join(problems))
    _configure_logging(args.log_format, getattr(args, "verbose", 0))
    from threadpoolctl import threadpool_limits

    from gateway.live.runtime import LiveGateway

    clock: Clock = RealClock()
    if args.speedup != 1.0:
        clock = ScaledClock(args.speedup, origin=_continue_from(profile, Path(args.data)))
    stop = threading.Event()
    previous = previous_int = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGTERM, lambda *_: stop.set())
        if getattr(args, "console", False):
            # `kill -USR1 PID` writes every thread's stack to stderr (the journal): what a hung stop is doing
            faulthandler.register(signal.SIGUSR1, all_threads=True)
            if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:  # inherited (a script's background job)
                log.warning("SIGINT is ignored (inherited from the process that started cncgw run): Ctrl-C will "
                            "not stop it; stop it with SIGTERM (kill PID)")
            # a signal mask is inherited too, and no stop signal is ever meant to stay blocked in a service
            blocked = signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})
            if blocked & {signal.SIGINT, signal.SIGTERM}:
                log.warning("%s was blocked by the process that started cncgw run: unblocked",
                            " and ".join(sorted(s.name for s in blocked & {signal.SIGINT, signal.SIGTERM})))
    end = clock.now() + args.minutes * 60.0 if args.minutes else None
    log.info("cncgw run: %s with model %s, data in %s", profile.path, model_path, args.data)
    try:
        with threadpool_limits(limits=1), LiveGateway(profile, model=model, data_dir=args.data, clock=clock,
                                                      opcua=False if args.no_opcua else None,
                                                      spin_s=args.spin_us * 1e-6, rt_priority=args.rt_priority):
            try:
                while not stop.wait(0.2):
                    if end is not None and clock.now() >= end:
                        break
            except KeyboardInterrupt:
                log.info("stopping (Ctrl-C)")
            if previous is not None:
                # closing releases the offsets, audits the stop and closes the stores: a second Ctrl-C (or
                # one a terminal sends to the whole process group) must not cut that short
                previous_int = signal.signal(signal.SIGINT, _already_stopping)
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
        if previous_int is not None:
            # a process that ends now ignores a late second Ctrl-C (Python's teardown would die of it);
            # called in-process, the caller's handler comes back
            signal.signal(signal.SIGINT, signal.SIG_IGN if getattr(args, "console", False) else previous_int)
    log.info("stopped")
    return 0
