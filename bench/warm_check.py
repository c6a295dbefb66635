"""How often the warm-start check flags a recording that starts at rest: bench/diagnose.py's plants, every effect.

    .venv/bin/python bench/warm_check.py [--cases none,eddy loss,...] [--variants 1,2,3] [--cache DIR]

For each case (effect and plant variant of ``bench/diagnose.py``'s new protocol, recordings from its cache or
simulated into it), the baseline model is identified on the nine experiments (``cncgw identify``), and
:func:`gateway.replay.starts_warm` is asked of every recording of the case: the nine experiments, the four
production days and the fresh day, each of which starts after a night at rest. Every flag is printed with its
reason; the summary counts them per effect. The room cases are left out by default: there the room moves every
recording in its first hour, which the check rightly reports (the default families are the other ones).
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from gateway.commands._common import read_recordings  # noqa: E402
from gateway.model import load_model  # noqa: E402
from gateway.profile import load_profile  # noqa: E402
from gateway.replay import starts_warm  # noqa: E402

DEFAULT_CASES = "none,slow mode,coolant dead time,eddy loss,viscous drag,preload,cabinet"


def _bench():
    spec = importlib.util.spec_from_file_location("bench_diagnose", ROOT / "bench" / "diagnose.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cases", default=DEFAULT_CASES, help=f"effects, comma-separated (default {DEFAULT_CASES})")
    p.add_argument("--variants", default="1,2,3,4,5,6,7")
    p.add_argument("--cache", default=str(Path.home() / ".cache" / "cncgw-bench" / "diagnose"))
    args = p.parse_args(argv)
    bench = _bench()
    cache = Path(args.cache)
    profile = load_profile(bench.PROFILE)
    flagged: dict[str, list[int]] = {}
    with tempfile.TemporaryDirectory(prefix="warm-check-") as tmp:
        for effect in args.cases.split(","):
            for variant in (int(v) for v in args.variants.split(",")):
                plan = bench.new_plan(effect, variant, 4)
                exps = [bench.record(t, n, cache) for n, t in plan.experiments.items()]
                others = [bench.record(t, n, cache) for part in (plan.days, plan.fresh) for n, t in part.items()]
                model_path = Path(tmp) / f"{effect.replace(' ', '-')}-v{variant}.model.toml"
                bench.run_cli(["identify", "--profile", bench.PROFILE, *exps, "-o", model_path, "--force"])
                model = load_model(model_path)
                count = flagged.setdefault(effect, [0, 0])
                for rec in read_recordings([str(x) for x in [*exps, *others]], profile, period_s=None,
                                           require_displacement=False):
                    count[1] += 1
                    why = starts_warm(model, rec)
                    if why:
                        count[0] += 1
                        print(f"{effect} v{variant} {Path(rec.source).name}: {why}", flush=True)
    print("recordings that start at rest flagged as not starting at rest, per effect:")
    for effect, (n, total) in flagged.items():
        print(f"  {effect:20s} {n:4d} of {total}")
    print(f"  {'all':20s} {sum(n for n, _ in flagged.values()):4d} of {sum(t for _, t in flagged.values())}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
