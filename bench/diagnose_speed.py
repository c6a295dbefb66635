"""CPU time of ``cncgw diagnose``: this tree against a baseline revision, on the same recordings, in one run.

    .venv/bin/python bench/diagnose_speed.py [--cases "room recorded:3,slow mode:1,none:1"]
                                             [--baseline REV] [--this REV] [--cache DIR] [--keep DIR]
                                             [--repeat N] [--cut-days H]

Per case (an effect and plant variant of bench/diagnose.py's new protocol: the nine identification
experiments and four production days, the effect acting in all of them), the recordings are simulated once
(cached like bench/diagnose.py's), the baseline model is identified once with the baseline revision (a
newer tree reads an older model file, not always the reverse), and then
``cncgw diagnose --model baseline exp*.csv day*.csv`` runs in a fresh process per source tree: the baseline
revision (``git archive REV``, default ``main``) and this working tree, taking turns (``--repeat``), each holding
BLAS to one thread. The CPU seconds of that process during the diagnosis (``time.process_time``) are
printed with their ratio, and what each diagnosis decided is compared: the model written, the accepted
terms, and the held-out figures of every candidate (pooled squared error, RMS per axis) as relative
differences. Timing on a shared machine is noisy: the ratio of two runs made back to back is the figure.
``--cut-days H`` gives the production days from H hours on, as bench/diagnose.py's does (a diagnosis of days
that start warm runs up to three passes).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from bench.diagnose import EFFECTS, PROFILE, cut_days_file, diagnosis_names, new_plan, record  # noqa: E402

ONE_THREAD = {v: "1" for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}
#: run in a fresh interpreter with the tree to time first on its path; prints its CPU seconds
CHILD = """
import sys, time
sys.path.insert(0, sys.argv[1])
import gateway
assert gateway.__file__.startswith(sys.argv[1]), gateway.__file__
from gateway.cli import main
c0 = time.process_time()
rc = main(sys.argv[2:])
print("CPU_S", time.process_time() - c0, rc)
"""


def baseline_tree(rev: str, into: Path) -> Path:
    """The sources of revision ``rev`` of this repository, unpacked under ``into``."""
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", rev], check=True, capture_output=True).stdout
    into.mkdir(parents=True, exist_ok=True)
    subprocess.run(["tar", "-x", "-C", str(into)], input=archive, check=True)
    return into


def timed_cli(tree: Path, args: list[str]) -> float:
    """``cncgw ARGS`` with the sources of ``tree``, in a fresh process; its CPU seconds."""
    proc = subprocess.run([sys.executable, "-c", CHILD, str(tree), *args], capture_output=True,
                          text=True, env={**os.environ, "PYTHONPATH": str(tree), **ONE_THREAD})
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("CPU_S")]
    if proc.returncode != 0 or not lines or lines[-1].split()[2] != "0":
        raise RuntimeError(f"cncgw {args[0]} with {tree} failed: {proc.stderr.strip()[-800:]}")
    return float(lines[-1].split()[1])


def decisions(out: Path) -> dict:
    """What a diagnosis decided and its held-out figures, from what it wrote."""
    doc = json.loads((out / "report.json").read_text())
    names = diagnosis_names(out)
    cands = {k: {"sse": c["held_out_sse_um2"], "passes": c["passes"],
                 "rms": {a: m.get("rms_um") for a, m in c["metrics"].items()}}
             for k, c in doc["candidates"].items()}
    return {"written": doc["written"], "accepted": names.accepted, "candidates": cands}


def rel(a: float | None, b: float | None) -> float:
    if a is None or b is None:
        return float("nan")
    return abs(b - a) / max(abs(a), 1e-12)


def compare_decisions(old: dict, new: dict) -> tuple[bool, float, list[str]]:
    """(same decisions, the largest relative difference of a held-out figure, what differs)."""
    diffs = []
    if old["written"] != new["written"]:
        diffs.append(f"written {old['written']} -> {new['written']}")
    if old["accepted"] != new["accepted"]:
        diffs.append(f"accepted {old['accepted']} -> {new['accepted']}")
    worst = 0.0
    for k in sorted(set(old["candidates"]) | set(new["candidates"])):
        o, n = old["candidates"].get(k), new["candidates"].get(k)
        if o is None or n is None:
            diffs.append(f"candidate {k} only in one")
            continue
        if o["passes"] != n["passes"]:
            diffs.append(f"{k} passes {o['passes']} -> {n['passes']}")
        worst = max(worst, rel(o["sse"], n["sse"]))
        for a in o["rms"]:
            worst = max(worst, rel(o["rms"][a], n["rms"].get(a)))
    return not diffs, worst, diffs


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", default="room recorded:3,slow mode:1,none:1",
                    help="comma-separated EFFECT:VARIANT of bench/diagnose.py's new protocol")
    ap.add_argument("--baseline", default="main", help="git revision timed against this tree (default main)")
    ap.add_argument("--this", help="time this git revision instead of the working tree (it can change meanwhile)")
    ap.add_argument("--cache", default=str(Path.home() / ".cache" / "cncgw-bench" / "diagnose"),
                    help="recordings cache (shared with bench/diagnose.py)")
    ap.add_argument("--keep", help="keep the models and both diagnoses' reports here")
    ap.add_argument("--repeat", type=int, default=1,
                    help="time each tree N times, taking turns, keep the least CPU (default 1)")
    ap.add_argument("--cut-days", type=float, metavar="H",
                    help="give the production days from H hours on (as bench/diagnose.py --cut-days)")
    args = ap.parse_args()
    cases = []
    for item in args.cases.split(","):
        effect, _, variant = item.strip().rpartition(":")
        cases.append((effect, int(variant)))
    with tempfile.TemporaryDirectory(prefix="diag-speed-") as tmp:
        work = Path(args.keep) if args.keep else Path(tmp)
        old_tree = baseline_tree(args.baseline, Path(tmp) / "baseline")
        this = baseline_tree(args.this, Path(tmp) / "this") if args.this else ROOT
        trees = {"baseline": old_tree, "this": this}
        print(f"baseline {args.baseline} vs {args.this or ROOT}; CPU s of the diagnose process (one BLAS thread)")
        print(f"{'case':24s} {'baseline':>9s} {'this':>9s} {'ratio':>6s}  same  max rel diff")
        totals = {k: 0.0 for k in trees}
        for effect, variant in cases:
            plan = new_plan(effect, variant)
            cache = Path(args.cache)
            exps = [record(t, n, cache) for n, t in plan.experiments.items()]
            days = [record(t, n, cache) for n, t in plan.days.items()]
            case_dir = work / f"{effect.replace(' ', '-')}-v{variant}"
            case_dir.mkdir(parents=True, exist_ok=True)
            if args.cut_days is not None:
                days = [cut_days_file(d, args.cut_days, case_dir / "cut") for d in days]
            model = case_dir / "sim-vmc.model.toml"
            if not model.is_file():  # a kept one is reused: both trees diagnose the same model
                # identified by the baseline: a newer tree reads an older model file, not always the reverse
                timed_cli(old_tree, ["identify", "--profile", str(PROFILE), *map(str, exps), "-o", str(model)])
            diag_args = ["diagnose", "--profile", str(PROFILE), "--model", str(model), *map(str, exps),
                         *map(str, days), *(a for col in EFFECTS[effect].use_signals for a in ("--use-signal", col)),
                         "--force", "-o"]
            cpu = {key: float("inf") for key in trees}
            # the trees take turns (baseline, this, baseline, this, ...): this PC's speed drifts over minutes
            # (the same diagnosis measured 40-72 s within a day), and N runs of one then N of the other would
            # put a drift into the ratio
            for _ in range(max(1, args.repeat)):
                for key, tree in trees.items():
                    cpu[key] = min(cpu[key], timed_cli(tree, [*diag_args, str(case_dir / key)]))
            dec = {key: decisions(case_dir / key) for key in trees}
            for key in trees:
                totals[key] += cpu[key]
            same, worst, diffs = compare_decisions(dec["baseline"], dec["this"])
            print(f"{effect + ' v' + str(variant):24s} {cpu['baseline']:9.1f} {cpu['this']:9.1f} "
                  f"{cpu['this'] / cpu['baseline']:6.2f}  {'yes' if same else 'NO':4s}  {100 * worst:.2g} %"
                  + (f"  ({'; '.join(diffs)})" if diffs else ""))
            print(f"{'':24s} written {dec['this']['written']}, accepted {dec['this']['accepted']}", flush=True)
        print(f"{'total':24s} {totals['baseline']:9.1f} {totals['this']:9.1f} "
              f"{totals['this'] / max(totals['baseline'], 1e-9):6.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
