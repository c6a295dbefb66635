"""Exporting a long record store: memory and time per window as the store grows.

    .venv/bin/python bench/export.py [--windows 5000] [--factor 10]

Builds two stores of the bundled simulated machine's profile (``--windows`` and ``--factor`` times as many
one-minute windows, with per-channel statistics as the sampler writes them), exports each to a recording CSV
and prints the peak Python memory (tracemalloc) and wall time per window of each export. The ratio of the
two peaks is the figure that matters: an export that streams stays near 1x however long the store; one
that read the whole store first grew with it. Stores are built on /dev/shm where there is one (a commit a
window is an fsync).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path
from types import MappingProxyType

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from gateway.profile import load_profile  # noqa: E402
from gateway.record_store import RecordStore, export_recording  # noqa: E402
from gateway.windows import ChannelStats, WindowRecord  # noqa: E402

PROFILE = ROOT / "profiles" / "sim-vmc.toml"


def build(path: Path, profile, n: int) -> None:
    stats = ChannelStats(count=30000, coverage=1.0, mean=1.0, mean_square=1.5, mean_abs=1.0, min=0.0, max=2.0,
                         saturated=0, bad=0)
    channels = MappingProxyType({c.name: stats for c in profile.channels})
    with RecordStore(path, profile=profile) as store:
        for k in range(n):
            factors = MappingProxyType({f.name: float(k % 97) for f in profile.factors})
            store.append(WindowRecord(index=k, start_s=60.0 * k, end_s=60.0 * (k + 1), status="good",
                                      factors=factors, channels=channels, devices=MappingProxyType({})))


def export(path: Path, profile, out: Path) -> tuple[float, float]:
    """(peak traced MiB, wall s) of one export."""
    with RecordStore(path) as store:
        tracemalloc.start()
        t0 = time.perf_counter()
        export_recording(store, profile, out)
        wall = time.perf_counter() - t0
        peak = tracemalloc.get_traced_memory()[1] / 2**20
        tracemalloc.stop()
    return peak, wall


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--windows", type=int, default=5000)
    ap.add_argument("--factor", type=int, default=10)
    args = ap.parse_args()
    profile = load_profile(PROFILE)
    shm = Path("/dev/shm")
    with tempfile.TemporaryDirectory(dir=shm if shm.is_dir() else None) as tmp:
        rows = []
        for n in (args.windows, args.windows * args.factor):
            store = Path(tmp) / f"{n}.sqlite"
            t0 = time.perf_counter()
            build(store, profile, n)
            built = time.perf_counter() - t0
            peak, wall = export(store, profile, Path(tmp) / f"{n}.csv")
            rows.append((n, peak, wall))
            print(f"{n:>8} windows ({n / 1440:6.1f} days): built in {built:5.1f} s; export peak {peak:7.2f} MiB, "
                  f"{wall:6.2f} s ({wall / n * 1e6:5.0f} us a window)")
        (n0, p0, w0), (n1, p1, w1) = rows
        print(f"\n{n1 // n0}x the windows: peak memory {p1 / p0:.2f}x, time per window {w1 / n1 / (w0 / n0):.2f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
