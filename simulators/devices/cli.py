"""``cncgw simulate serve SCENARIO``: the simulated machine behind its devices, until Ctrl-C.

The devices are served on loopback (see :mod:`simulators.devices.deviceset`); the addresses are printed
on start. The machine is :class:`simulators.machine.LiveMachine` running the scenario (a bundled name or a
TOML path) on a clock sped up ``--speedup`` times.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import math
import signal
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, TextIO

from gateway.clock import Clock, ScaledClock
from gateway.errors import UsageError
from simulators.live import LiveSource

if TYPE_CHECKING:
    from simulators.devices.deviceset import DeviceSet, DeviceSetConfig

def add_actions(actions: argparse._SubParsersAction) -> None:
    """Add this part's actions to ``cncgw simulate``."""
    p = actions.add_parser(
        "serve", help="serve the simulated machine's devices on loopback until Ctrl-C",
        description="Run the simulated machine through SCENARIO and serve its devices on 127.0.0.1: an "
                    "ADC board over Modbus TCP and RTU, a CAN module (slcan), DCON modules, and the CNC's "
                    "compensation registers over Modbus TCP. Their addresses are printed on start.")
    p.add_argument("scenario", metavar="SCENARIO", help="scenario the machine runs: a bundled name or a TOML file")
    p.add_argument("--speedup", type=float, default=1.0, metavar="N",
                   help="simulated seconds per wall second (default 1)")
    p.add_argument("--adc-port", type=int, default=0, metavar="PORT",
                   help="TCP port of the Modbus ADC board (default: any free port)")
    p.add_argument("--cnc-port", type=int, default=0, metavar="PORT",
                   help="TCP port of the CNC's compensation registers (default: any free port)")
    p.add_argument("--duration", type=float, default=None, metavar="S",
                   help="stop after S wall seconds (default: run until Ctrl-C)")
    p.add_argument("--profile-out", metavar="FILE",
                   help="write the bundled profile with the live address of the device --via to FILE once serving "
                        "(ports are chosen at start and pseudo-terminal paths are temporary)")
    p.add_argument("--via", choices=("adc-tcp", "adc-rtu", "adc-rtu-line", "can-slcan", "dcon", "opcua"),
                   default="adc-tcp",
                   help="the device the --profile-out profile reads the channels from (default adc-tcp; opcua: "
                        "the CNC's own OPC UA server, started only then)")
    p.add_argument("--cnc-watchdog-s", type=float, default=None, metavar="S",
                   help="the CNC's heartbeat watchdog in clock seconds (default 5 s, raised to 0.5 s of wall time "
                        "at high --speedup so a busy machine does not trip it)")
    p.add_argument("--compensate", action="store_true",
                   help="the --profile-out profile writes offsets to the simulated CNC (default: a dry run)")
    p.add_argument("--displacement", action="store_true",
                   help="also serve the displacement sensors x_um, y_um, z_um on the ADC board (float32 um at input "
                        "registers 120-125) and read them as bursts in the --profile-out profile")
    p.set_defaults(func=run_serve)


def run_serve(args: argparse.Namespace) -> int:
    """Serve the devices of the machine running ``args.scenario``."""
    if not (args.speedup > 0 and math.isfinite(args.speedup)):
        raise UsageError(f"--speedup must be a finite number > 0. Got {args.speedup!r}")
    for flag, port in (("--adc-port", args.adc_port), ("--cnc-port", args.cnc_port)):
        if not 0 <= port <= 65535:
            raise UsageError(f"{flag} must be in 0..65535. Got {port!r}")
    from simulators.devices.deviceset import DeviceSetConfig  # here: keeps `cncgw --help` light

    clock = ScaledClock(args.speedup)
    source = machine_source(args.scenario, clock)
    from simulators.devices.cnc import CompensationConfig

    watchdog_s = args.cnc_watchdog_s if args.cnc_watchdog_s is not None else max(5.0, 0.5 * args.speedup)
    if not (watchdog_s > 0 and math.isfinite(watchdog_s)):
        raise UsageError(f"--cnc-watchdog-s must be a finite number > 0. Got {watchdog_s!r}")
    config = DeviceSetConfig(adc_tcp_port=args.adc_port, cnc_port=args.cnc_port,
                             cnc=dataclasses.replace(CompensationConfig(), heartbeat_timeout_s=watchdog_s))
    on_start = None
    if args.displacement and not args.via.startswith("adc"):
        raise UsageError(f"--displacement: the displacement sensors are on the ADC board, not --via {args.via}")
    if args.displacement:
        from simulators.devices.profile_out import adc_with_displacement

        config = dataclasses.replace(config, adc=adc_with_displacement(config.adc))
    if args.via == "adc-rtu-line":
        from simulators.devices.profile_out import rtu_line_boards

        first, second = rtu_line_boards(config.adc)
        config = dataclasses.replace(config, adc=first, adc_rtu_more=(second,))
    if args.via == "opcua":
        from simulators.devices.opcua_cnc import OpcUaCncConfig

        config = dataclasses.replace(config, cnc_opcua=OpcUaCncConfig())
    if args.profile_out:
        from simulators.devices.profile_out import profile_for

        def on_start(devices: DeviceSet) -> None:
            path = Path(args.profile_out)
            tmp = path.with_name(path.name + ".tmp")
            tmp.write_text(profile_for(devices, args.via, displacement=args.displacement,
                                       compensate=args.compensate), encoding="utf-8")
            tmp.replace(path)  # a reader polling for the file never sees half of it

    return serve_until_stopped(source, clock, config, duration_s=args.duration, on_start=on_start)


def machine_source(scenario: str | Path, clock: Clock) -> LiveSource:
    """The simulated machine running ``scenario`` (bundled name or TOML path) against ``clock``."""
    from simulators.machine import LiveMachine

    return LiveMachine(scenario, clock=clock)


def serve_until_stopped(source: LiveSource, clock: Clock, config: DeviceSetConfig | None = None, *,
                        duration_s: float | None = None, stop: threading.Event | None = None,
                        out: TextIO | None = None, on_start: Callable[[DeviceSet], None] | None = None) -> int:
    """Serve until ``stop`` is set, ``duration_s`` wall seconds pass, Ctrl-C or SIGTERM; returns 0.

    ``on_start`` is called with the running devices before their addresses are printed.
    """
    from simulators.devices.deviceset import serve

    out = out or sys.stdout
    stop = stop or threading.Event()
    restore = None
    if threading.current_thread() is threading.main_thread():
        # a service manager stops us with SIGTERM: shut the devices down as cleanly as on Ctrl-C
        restore = signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:
        with serve(source, clock, config) as devices:
            if on_start is not None:
                on_start(devices)
            print(devices.describe(), file=out, flush=True)
            print(f"serving at {clock.speedup:g}x; Ctrl-C stops", file=out, flush=True)
            with contextlib.suppress(KeyboardInterrupt):
                stop.wait(duration_s)
    finally:
        if restore is not None:
            signal.signal(signal.SIGTERM, restore)
    print("devices stopped", file=out, flush=True)
    return 0
