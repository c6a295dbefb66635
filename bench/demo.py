"""The demo's figures against the host's load: ``cncgw demo`` on this PC as it is, then with busy processes.

Runs the demo (lock-step, the default) twice, once as the PC is and once with ``--busy`` CPU-bound
processes beside it, and prints the reductions of both and their difference (the aim: within 2 points).
``--realtime`` also runs the demo's real-time mode (a sped-up clock, 2 ms sampling of wall time) the same
two ways, for comparison: there a busy PC drops samples, and the demo says when its figures are invalid.

    .venv/bin/python bench/demo.py [--hours 8] [--busy 2] [--realtime]
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
BUSY = "while True:\n    pass\n"
ROW = re.compile(r"^\s+([xyz])\s+([\d.]+) um\s+([\d.]+) um\s+(-?\d+) %$", re.M)


def demo(hours: float, busy: int, realtime: bool, out: Path) -> tuple[dict[str, int], str, float]:
    """Reductions per axis (%), the validity line, wall seconds."""
    hogs = [subprocess.Popen([sys.executable, "-c", BUSY]) for _ in range(busy)]
    try:
        t0 = time.monotonic()
        cmd = [sys.executable, "-m", "gateway.cli", "demo", "-o", str(out), "--hours", str(hours)]
        proc = subprocess.run(cmd + (["--realtime"] if realtime else []), capture_output=True, text=True, cwd=ROOT,
                              check=False)
        wall = time.monotonic() - t0
    finally:
        for h in hogs:
            h.kill()
            h.wait()
    if proc.returncode != 0:
        raise SystemExit(f"cncgw demo failed ({proc.returncode}):\n{proc.stderr[-2000:]}")
    reductions = {axis: int(red) for axis, _, _, red in ROW.findall(proc.stdout)}
    validity = next((line.strip() for line in proc.stdout.splitlines() if "figures" in line.lower()
                     and ("valid" in line.lower())), "")
    return reductions, validity, wall


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--hours", type=float, default=8.0, help="hours of the validation run (default: all 8)")
    p.add_argument("--busy", type=int, default=2, help="CPU-bound processes in the second run (default 2)")
    p.add_argument("--realtime", action="store_true", help="also the demo's real-time mode")
    args = p.parse_args()
    print(f"cncgw demo --hours {args.hours:g}: as the PC is, then with {args.busy} busy processes beside it; "
          f"{os.cpu_count()} cores, load average before: {os.getloadavg()[0]:.1f}")
    modes = [False] + ([True] if args.realtime else [])
    with tempfile.TemporaryDirectory(prefix="cncgw-bench-demo-") as tmp:
        for realtime in modes:
            name = "real time (--realtime, 480x)" if realtime else "lock-step (default)"
            runs = []
            for busy in (0, args.busy):
                red, validity, wall = demo(args.hours, busy, realtime, Path(tmp) / f"{int(realtime)}-{busy}")
                runs.append(red)
                print(f"  {name}, {busy} busy: reductions " + ", ".join(f"{a} {v} %" for a, v in red.items())
                      + f"; {wall:.0f} s wall; {validity}")
            diff = max(abs(runs[0][a] - runs[1][a]) for a in runs[0])
            print(f"  {name}: largest difference {diff} points ({'within' if diff <= 2 else 'beyond'} 2 points)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
