"""How fast the simulated machine runs: simulated hours per wall second for the 24 h production day.

    .venv/bin/python bench/simulate.py [SCENARIO] [--repeat N]

Prints the figure for the fast path (closed-form sums on feed pieces, steady windows evaluated once)
and, as the baseline in the same process, the same day with every 2 ms sample of every drive evaluated
(``fast=False``: still vectorised per window, no Python loop per step). Both give the same factors; the
ratio is the speed-up. Also prints the cost of one live ``values(t)`` call. No asserts: figures only.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from simulators.machine.live import LiveMachine
from simulators.machine.run import simulate
from simulators.machine.scenario import load_scenario


def timed(fn, repeat: int) -> tuple[float, object]:
    best, out = float("inf"), None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenario", nargs="?", default="production-day")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    sc = load_scenario(args.scenario)
    hours = sc.duration_h

    fast_s, fast = timed(lambda: simulate(sc), args.repeat)
    ref_s, ref = timed(lambda: simulate(sc, fast=False), 1)
    same = np.max(np.abs(fast.stats - ref.stats) / (np.abs(ref.stats) + 1e-9))
    print(f"scenario {sc.name}: {hours:g} h, {len(fast.time_s)} windows of 30000 samples x 4 drives")
    print(f"fast path      {fast_s:7.3f} s  = {hours / fast_s:8.1f} simulated h per wall s (best of {args.repeat})")
    print(f"every sample   {ref_s:7.3f} s  = {hours / ref_s:8.1f} simulated h per wall s (baseline)")
    print(f"speed-up       {ref_s / fast_s:7.1f} x   (largest relative difference in the factors: {same:.1e})")

    live = LiveMachine(sc)
    t0 = 6 * 3600.0
    n = 20000
    start = time.perf_counter()
    for k in range(n):
        live.values(t0 + 0.002 * k)
    per_call = (time.perf_counter() - start) / n
    print(f"live values()  {per_call * 1e6:7.1f} us per call ({per_call * 500 * 100:.1f} % of a core at 500 Hz)")


if __name__ == "__main__":
    main()
