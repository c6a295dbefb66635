"""Malformed inputs through the command line, each in a process of its own: tracebacks, hangs, memory.

    .venv/bin/python bench/fuzz.py [--inputs 2400] [--seed 1] [--keep DIR]

Generates profiles, model files and recordings with the fuzz suite's generators (``tests/fuzz_inputs.py``:
a valid file with one to four mutations) and runs each through the real entry point, ``gateway.cli.main``,
as a user would: ``cncgw profile check``, ``cncgw model show``, ``cncgw estimate`` (a fuzzed recording, and
in a third of the runs a fuzzed model) and ``cncgw identify`` (a fuzzed recording). Every run is a forked
child of this process (the imports are paid once) with an address-space limit, killed after 10 s.

Counted per command: exit codes; tracebacks (an exception other than the CLI's one-line errors, or
"Traceback" on stderr); error exits whose stderr is not all ``cncgw: error:`` lines; hangs (killed at
10 s); runs whose peak resident size exceeded 1 GiB (or that hit the address-space limit). The aims
(issue 13): >= 2000 inputs, 0 tracebacks, 0 hangs, 0 runs over 1 GiB. ``--keep DIR`` saves every input
that broke an aim with its command line and output.
"""

from __future__ import annotations

import argparse
import collections
import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # forked children must not inherit a BLAS thread pool
os.environ.setdefault("OMP_NUM_THREADS", "1")

import random
import resource
import shutil
import signal
import sys
import tempfile
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

import fuzz_inputs as fi  # noqa: E402

from gateway.cli import build_parser  # noqa: E402
from gateway.cli import main as cncgw  # noqa: E402

build_parser()  # every command module imported before forking: each child starts warm

HANG_S = 10.0
GIB_KIB = 1024 * 1024
TRACEBACK_EXIT = 70
#: command, share of the inputs
MIX = (("profile check", 0.3), ("model show", 0.25), ("estimate", 0.35), ("identify", 0.1))


@dataclass
class Tally:
    runs: int = 0
    codes: collections.Counter = field(default_factory=collections.Counter)
    tracebacks: int = 0
    bad_messages: int = 0
    hangs: int = 0
    over_memory: int = 0
    peak_kib: int = 0
    times_s: list[float] = field(default_factory=list)


def make_input(command: str, rng: random.Random, work: Path) -> list[str]:
    """Write one fuzzed input (and what it needs) into ``work``; return the cncgw arguments."""
    if command == "profile check":
        _, text = fi.profile_text(rng)
        (work / "profile.toml").write_text(text)
        return ["profile", "check", str(work / "profile.toml")]
    if command == "model show":
        _, text = fi.model_text(rng)
        (work / "m.model.toml").write_text(text)
        return ["model", "show", str(work / "m.model.toml")]
    (work / "r.csv").write_text(fi.recording_text(rng))
    if command == "estimate":
        model = fi.model_text(rng)[1] if rng.random() < 1 / 3 else fi.MODEL_BASES[rng.choice(sorted(fi.MODEL_BASES))]
        (work / "m.model.toml").write_text(model)
        return ["estimate", "--profile", str(fi.SIM_PROFILE), "--model", str(work / "m.model.toml"),
                str(work / "r.csv")]
    return ["identify", "--profile", str(fi.SIM_PROFILE), str(work / "r.csv"), "-o", str(work / "out.model.toml"),
            "--force"]


def _vm_size_bytes() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmSize:"):
            return int(line.split()[1]) * 1024
    return 0


def run_child(argv: list[str], work: Path, as_limit: int) -> tuple[int | None, int, float, str]:
    """(exit status or None when killed as hung, peak RSS KiB, wall s, stderr) of one run in a forked child."""
    out, err = work / "stdout", work / "stderr"
    t0 = time.monotonic()
    pid = os.fork()
    if pid == 0:  # the child: never returns
        try:
            resource.setrlimit(resource.RLIMIT_AS, (as_limit, as_limit))
            fd_out = os.open(out, os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
            fd_err = os.open(err, os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
            os.dup2(fd_out, 1)
            os.dup2(fd_err, 2)
            os.chdir(work)
            code = cncgw(argv)
        except SystemExit as exc:  # argparse's usage errors
            code = exc.code if isinstance(exc.code, int) else 2
        except BaseException:
            traceback.print_exc()
            code = TRACEBACK_EXIT
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    status, usage = None, None
    while time.monotonic() - t0 < HANG_S:
        done, wait_status, usage = os.wait4(pid, os.WNOHANG)
        if done:
            status = os.waitstatus_to_exitcode(wait_status)
            break
        time.sleep(0.005)
    else:
        os.kill(pid, signal.SIGKILL)
        _, _, usage = os.wait4(pid, 0)
    wall = time.monotonic() - t0
    return status, usage.ru_maxrss, wall, err.read_text(errors="replace") if err.exists() else ""


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--inputs", type=int, default=2400, help="how many inputs in all (default 2400)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--keep", type=Path, default=None, help="save the inputs that broke an aim here")
    args = ap.parse_args()

    rng = random.Random(args.seed)
    tallies = {c: Tally() for c, _ in MIX}
    as_limit = _vm_size_bytes() + 2 * 2**30  # room for 1 GiB and more: a run over 1 GiB is counted, not killed
    started = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="cncgw-fuzz-") as tmp:
        for k in range(args.inputs):
            command = rng.choices([c for c, _ in MIX], weights=[w for _, w in MIX])[0]
            work = Path(tmp) / f"{k:05d}"
            work.mkdir()
            argv = make_input(command, random.Random(rng.getrandbits(64)), work)
            status, peak_kib, wall, stderr = run_child(argv, work, as_limit)
            t = tallies[command]
            t.runs += 1
            t.times_s.append(wall)
            t.peak_kib = max(t.peak_kib, peak_kib)
            broke = []
            if status is None:
                t.hangs += 1
                broke.append("hang")
            else:
                t.codes[status] += 1
                if status == TRACEBACK_EXIT or "Traceback" in stderr:
                    if "MemoryError" in stderr:
                        t.over_memory += 1
                        broke.append("memory")
                    else:
                        t.tracebacks += 1
                        broke.append("traceback")
                elif status not in (0, 2) and not (stderr.strip() and all(
                        line.startswith("cncgw: error: ") for line in stderr.strip().splitlines())):
                    t.bad_messages += 1
                    broke.append("message")
            if peak_kib > GIB_KIB:
                t.over_memory += 1
                broke.append("memory")
            if broke and args.keep:
                dest = args.keep / f"{k:05d}-{'-'.join(broke)}"
                shutil.copytree(work, dest, dirs_exist_ok=True)
                (dest / "argv.txt").write_text(" ".join(argv) + "\n")
            shutil.rmtree(work, ignore_errors=True)
            if (k + 1) % 200 == 0:
                print(f"  {k + 1} inputs, {time.monotonic() - started:.0f} s", file=sys.stderr, flush=True)
    total = time.monotonic() - started

    print(f"bench/fuzz.py: {args.inputs} inputs (seed {args.seed}) through gateway.cli.main, one forked process "
          f"each, killed at {HANG_S:g} s; {total:.0f} s")
    print(f"{'command':<15}{'inputs':>7}  {'exit codes':<32}{'tracebacks':>11}{'bad msgs':>9}{'hangs':>6}"
          f"{'>1 GiB':>7}{'peak RSS':>10}{'median':>8}{'max':>7}")
    sums = Tally()
    for command, t in tallies.items():
        codes = ", ".join(f"{c}: {n}" for c, n in sorted(t.codes.items()))
        times = sorted(t.times_s) or [0.0]
        print(f"{command:<15}{t.runs:>7}  {codes:<32}{t.tracebacks:>11}{t.bad_messages:>9}{t.hangs:>6}"
              f"{t.over_memory:>7}{t.peak_kib / 1024:>7.0f} MiB{times[len(times) // 2]:>7.2f}s{times[-1]:>6.2f}s")
        sums.runs += t.runs
        sums.tracebacks += t.tracebacks
        sums.bad_messages += t.bad_messages
        sums.hangs += t.hangs
        sums.over_memory += t.over_memory
        sums.peak_kib = max(sums.peak_kib, t.peak_kib)
    print(f"{'all':<15}{sums.runs:>7}  {'':<32}{sums.tracebacks:>11}{sums.bad_messages:>9}{sums.hangs:>6}"
          f"{sums.over_memory:>7}{sums.peak_kib / 1024:>7.0f} MiB")
    aims = sums.runs >= 2000 and not (sums.tracebacks or sums.hangs or sums.over_memory)
    print(f"aims (>= 2000 inputs, 0 tracebacks, 0 hangs over {HANG_S:g} s, 0 runs over 1 GiB): "
          f"{'met' if aims else 'MISSED'}" + ("" if not sums.bad_messages else
                                               f"; {sums.bad_messages} error exits without one-line messages"))
    return 0 if aims else 1


if __name__ == "__main__":
    sys.exit(main())
