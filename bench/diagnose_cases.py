"""Concealed effects through the internal API: the case generator tests/test_diagnose.py uses.

This is the earlier bench/diagnose.py, kept as it was for the diagnosis tests (bench/diagnose.py re-exports
``CASES``, ``baseline``, ``simulate_case``, ``located``, ``fresh_rms`` and ``run_case``); the benchmark
itself is bench/diagnose.py, through the command line. Run alone it prints the earlier table:

    .venv/bin/python bench/diagnose_cases.py [--seeds N] [--first-seed S] [--cases a,b,...] [--min-effect SHARE]
                                             [--report DIR]

For every seed: the baseline model is identified on the paper's 9 identification runs with every effect
off (a controlled shop; sensor noise drawn from the seed). For every case and seed: a multi-day production
recording with that one effect on (days of different kinds: two shifts, a day shift, a late shift, an idle
day, in an order drawn from the seed; jobs drawn from the seed) is given to ``diagnose`` with the profile
and the baseline model, never the ground truth. A second recording of the same kind (another schedule,
other noise) is never shown to diagnose: the model before and after is estimated on it.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from gateway.diagnose import Diagnosis, Options, diagnose, factor_infos, write_report
from gateway.identify import identify
from gateway.model import ThermalModel
from gateway.profile import load_profile
from gateway.recording import Recording

ROOT = Path(__file__).resolve().parent.parent
PROFILE = ROOT / "profiles" / "sim-vmc.toml"
IDENTIFICATION_SCENARIOS = ("spindle-1000rpm", "spindle-500rpm", "spindle-400-600rpm", "feed-x-fast", "feed-x-accel",
                            "feed-y-fast", "feed-y-accel", "feed-z-fast", "feed-z-accel")
BURN_IN_H = 6.0


@dataclass(frozen=True)
class Case:
    """One concealed effect (or none): the scenario's effect tables and what diagnosis should name."""

    effects: str
    expected: str  # hypothesis family, "artefact" (the step) or "" (nothing)
    thermometer: bool = False
    days: int = 4
    note: str = ""


CASES: dict[str, Case] = {
    "room recorded": Case("[effects.room_cycle]\namplitude_k = 1.5\ndrift_k_per_h = 0.02\n", "room_recorded",
                          thermometer=True, note="daily 3 K swing and a 0.02 K/h weather drift; room_c recorded"),
    "room not recorded": Case("[effects.room_cycle]\namplitude_k = 1.5\n", "room_daily",
                              note="daily 3 K swing, no thermometer"),
    "eddy loss": Case("[effects.eddy_loss]\nloss_w_at_1000rpm = 15.0\n", "eddy_loss", note="15 W at 1000 rpm"),
    "slow mode": Case("[effects.slow_path]\ntime_constant_h = 24.0\num_per_k = { z = 10.0 }\n", "slow_mode",
                      note="a 24 h part fed by the head, 10 um/K in z"),
    "cabinet": Case("[effects.cabinet]\nw_per_a2 = 2.0\n", "cabinet", note="2 W per A^2 of amplifier current"),
    "preload": Case("[effects.bearing_preload]\ngain_per_k = 0.01\n", "bearing_preload",
                    note="1 % more friction per K of bearing over head"),
    "dead time": Case("[effects.coolant_delay]\nfraction = 0.5\ndelay_s = 5400.0\ntank_capacity_kj_per_k = 20.0\n"
                      "tank_room_w_per_k = 2.0\ntank_column_w_per_k = 15.0\n", "dead_time",
                      note="coolant takes half the motor heat to a 10 l tank on the column, 90 min later"),
    "coolant switching": Case("[effects.chiller]\nconductance_w_per_k = 15.0\n", "chiller",
                              note="chiller on the stator while the spindle runs"),
    "sensor step": Case("", "artefact", note="a 2 um step on z at a random time"),
    "none": Case("", "", note="production days, no effect"),
    "none 1 day": Case("", "", days=1, note="one production day, no effect"),
}


# ------------------------------------------------------------------------------------------ scenarios ---
def _jobs(rng: np.random.Generator, minutes: float, prefix: str) -> list[tuple[str, float, dict[str, object]]]:
    """Jobs and pauses filling ``minutes``: speeds 800..3000 rpm, strokes and feeds of a job shop."""
    out: list[tuple[str, float, dict[str, object]]] = []
    t = 0.0
    while t < minutes - 5:
        m = float(min(rng.integers(15, 90), max(5.0, minutes - t)))
        if rng.random() < 0.25:
            out.append((f"{prefix}pause{len(out)}", float(min(rng.integers(5, 45), max(5.0, minutes - t))), {}))
        else:
            lv: dict[str, object] = {"spindle_rpm": float(rng.choice([800, 1000, 1500, 2000, 2500, 3000]))}
            if rng.random() < 0.8:
                axes = str(rng.choice(["x", "y", "xy", "z", "xyz"]))
                lv["stroke_mm"] = {a: float(rng.integers(20, {"x": 500, "y": 300, "z": 150}[a])) for a in axes}
                lv["feed_mm_min"] = float(rng.integers(5, 80) * 100)
            if rng.random() < 0.1:  # positioning and chip clearing without the spindle
                lv = {"stroke_mm": {"x": 400.0, "y": 250.0}, "feed_mm_min": 10000.0}
            out.append((f"{prefix}job{len(out)}", m, lv))
        t += out[-1][1]
    return out


DAY_KINDS = {"two shifts": (6.0, 21.5), "day shift": (7.0, 16.0), "late shift": (13.0, 23.5), "idle": None}


def scenario_text(seed: int, *, days: int, effects: str = "", thermometer: bool = False, name: str = "run",
                  step_um: float = 0.0) -> str:
    """A production scenario over ``days`` days (TOML), kinds of day and jobs drawn from ``seed``."""
    rng = np.random.default_rng(seed)
    kinds = list(DAY_KINDS) if days >= len(DAY_KINDS) else list(rng.choice(["two shifts", "day shift"], size=1))
    order = [kinds[i] for i in rng.permutation(len(kinds))] if days >= len(DAY_KINDS) else kinds
    while len(order) < days:
        order.append(str(rng.choice(["two shifts", "day shift", "late shift"])))
    lines = [f'[scenario]\nname = "{name}"\nseed = {seed}\nduration_h = {24 * days}\n',
             f"[room]\ntemperature_c = 20.0\nthermometer = {'true' if thermometer else 'false'}\n",
             "[sensors]\nnoise_um = 0.1\n"]
    for d, kind in enumerate(order[:days]):
        span = DAY_KINDS[kind]
        if span is None:
            lines.append(f"[segments.d{d}_idle]\nminutes = 1440\n")
            continue
        start = (span[0] + rng.uniform(-0.5, 0.5)) * 60
        end = (span[1] + rng.uniform(-0.5, 0.5)) * 60
        lines.append(f"[segments.d{d}_before]\nminutes = {start:.0f}\n")
        used = round(start)
        for nm, m, lv in _jobs(rng, end - start, f"d{d}_"):
            if used + m > 1440 - 5:
                break
            lines.append(f"[segments.{nm}]\nminutes = {m:.0f}")
            for k, v in lv.items():
                lines.append(f"{k} = {{ " + ", ".join(f"{a} = {x}" for a, x in v.items()) + " }"
                             if isinstance(v, dict) else f"{k} = {v}")
            lines.append("")
            used += round(m)
        lines.append(f"[segments.d{d}_after]\nminutes = {1440 - used}\n")
    text = "\n".join(lines) + "\n" + effects
    if step_um:
        at = float(rng.uniform(0.3, 0.8) * 24 * days)
        text += f"\n[effects.sensor_artefacts]\nstep_at_h = {at:.2f}\nstep_um = {{ z = {step_um} }}\n"
    return text


def simulate_case(case: Case, seed: int, *, fresh: bool = False):
    """The recording diagnosis sees (``fresh=False``) or the one it never sees, with the case's effect on."""
    from simulators.machine import parse_scenario_text, simulate

    s = 10_000 + 97 * seed + (5000 if fresh else 0)
    step = 2.0 if case.expected == "artefact" else 0.0
    text = scenario_text(s, days=case.days, effects=case.effects, thermometer=case.thermometer,
                         name=f"{'fresh' if fresh else 'seen'}-{seed}", step_um=step)
    return simulate(parse_scenario_text(text, source=f"bench seed {s}"))


def baseline(seed: int) -> ThermalModel:
    """The model a careful engineer identifies in a controlled shop: the 9 runs, effects off, noise from ``seed``."""
    from simulators.machine import load_scenario, simulate

    profile = load_profile(PROFILE)
    recs = [simulate(replace(load_scenario(n), seed=1000 * seed + k)).recording()
            for k, n in enumerate(IDENTIFICATION_SCENARIOS)]
    return identify(recs, factors=profile.factor_names, axes=profile.axes,
                    units={f.name: f.unit for f in profile.factors}, machine=profile.name).model


# ------------------------------------------------------------------------------------------- scoring ---
@dataclass
class Row:
    """One case and seed."""

    case: str
    seed: int
    accepted: list[str]
    artefacts: list[str]
    named_first: bool
    named_any: bool
    located: str
    cv_before_um: float
    cv_after_um: float
    fresh_before_um: float
    fresh_after_um: float
    wall_s: float
    true_um: float = math.nan  # RMS of the hidden effect on its main axis (ground truth, for scoring only)
    relevance_um: float = math.nan  # the relevance bound diagnosis used

    @property
    def relevant(self) -> bool:
        """Whether the hidden effect reaches the bound diagnosis calls relevant (by design not named below)."""
        return not self.true_um < self.relevance_um

    @property
    def fresh_gain(self) -> float:
        return 1 - self.fresh_after_um / self.fresh_before_um if self.fresh_before_um > 0 else math.nan


def fresh_rms(model: ThermalModel, rec: Recording) -> float:
    """RMS over all axes after the burn-in, best constant offset per axis removed (before and after alike)."""
    from gateway.replay import estimate

    e = estimate(model, rec, align="none")
    keep = (e.time_s - e.time_s[0]) >= BURN_IN_H * 3600
    errs = []
    for i in range(len(e.axes)):
        err = (e.measured[i] - e.estimated[i])[keep]
        err = err[np.isfinite(err)]
        errs.append(err - err.mean())
    return float(np.sqrt(np.mean(np.concatenate(errs) ** 2)))


def located(case: Case, d: Diagnosis, sim) -> tuple[str, int]:
    """How well diagnosis located the effect; returns (text, main axis index)."""
    axes = d.model.axes
    if case.expected == "artefact":
        sa = sim.scenario.effects.sensor_artefacts
        steps = [s for f in d.findings.values() for s in f.steps]
        ok = any(s.axis == "z" and abs(s.time_h - sa.step_at_h) <= 3 / 60 for s in steps)
        return ("step at the true time" if ok else "step missed"), axes.index("z")
    if not sim.contributions_um:
        return "-", axes.index("z")
    contrib = next(iter(sim.contributions_um.values()))
    i = int(np.argmax(np.sqrt(np.mean(contrib ** 2, axis=0))))
    f = d.findings.get(axes[i])
    if f is None:
        return "-", i
    true = np.abs(contrib[:, i] - contrib[0, i]) > f.noise.band_um
    loc = np.zeros(len(true), dtype=bool)
    for w in f.windows:
        loc[w.start:w.stop] = True
    recall = float((loc & true).sum() / max(true.sum(), 1))
    text = f"{100 * recall:.0f} % of {axes[i]}"
    if case.expected in ("room_daily", "room_recorded"):
        text += ", 24 h line" if any(abs(ln.period_h - 24) < 3 for ff in d.findings.values() for ln in ff.lines) \
            else ", no 24 h line"
    return text, i


def run_case(name: str, seed: int, model: ThermalModel, *, report: Path | None = None,
             options: Options | None = None) -> Row:
    """Diagnose one case blind and score it against the truth it never saw."""
    case = CASES[name]
    profile = load_profile(PROFILE)
    seen = simulate_case(case, seed)
    fresh = simulate_case(case, seed, fresh=True)
    t0 = time.perf_counter()
    d = diagnose(model, [seen.recording()], factors=factor_infos(profile), options=options)
    wall = time.perf_counter() - t0
    families = [t.hypothesis.family for t in d.result.accepted if not t.hypothesis.artefact]
    text, i = located(case, d, seen)
    if case.expected == "artefact":
        named_first = named_any = bool([s for f in d.findings.values() for s in f.steps]) and not families
    elif case.expected:
        named_first, named_any = bool(families) and families[0] == case.expected, case.expected in families
    else:
        named_first = named_any = not families and not d.artefacts
    a = d.model.axes[i]
    if report is not None:
        write_report(d, report / f"{name.replace(' ', '-')}-{seed}", model_name="baseline",
                     title=f"{name}, seed {seed}")
    fresh_rec = fresh.recording()
    true_um = math.nan
    if seen.contributions_um:
        contrib = next(iter(seen.contributions_um.values()))[:, i]
        true_um = float(np.std(contrib))
    trial = next((t for t in d.result.trials if a in t.evidence), None)
    return Row(case=name, seed=seed, accepted=d.accepted_physics, artefacts=d.artefacts, named_first=named_first,
               named_any=named_any, located=text, cv_before_um=d.before[a].rms_um, cv_after_um=d.after[a].rms_um,
               fresh_before_um=fresh_rms(model, fresh_rec), fresh_after_um=fresh_rms(d.extended, fresh_rec),
               wall_s=wall, true_um=true_um,
               relevance_um=trial.evidence[a].relevance_um if trial is not None else math.nan)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--first-seed", type=int, default=1)
    ap.add_argument("--cases", default=",".join(CASES), help="comma-separated case names")
    ap.add_argument("--report", help="write every diagnosis report under this folder")
    ap.add_argument("--min-effect", type=float, default=Options().min_effect_share,
                    help="relevance bound as a share of the largest peak (diagnose's --min-effect)")
    args = ap.parse_args()
    names = [c.strip() for c in args.cases.split(",") if c.strip()]
    bad = [n for n in names if n not in CASES]
    if bad:
        ap.error(f"unknown case(s) {bad}; cases: {', '.join(CASES)}")
    report = Path(args.report) if args.report else None
    rows: list[Row] = []
    print(f"{'case':<18} {'seed':>4}  {'named':<6} {'accepted (first = the name given)':<58} {'located':<24} "
          f"{'CV RMS main axis um':<20} {'fresh RMS um (gain)':<22} {'effect/bound um':<16} {'s':>5}")
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        model = baseline(seed)
        for name in names:
            r = run_case(name, seed, model, report=report, options=Options(min_effect_share=args.min_effect))
            rows.append(r)
            acc = ", ".join(r.accepted) or "nothing"
            if r.artefacts:
                acc += " | artefacts: " + "; ".join(r.artefacts)
            print(f"{r.case:<18} {r.seed:>4}  {('yes' if r.named_first else 'any' if r.named_any else 'no'):<6} "
                  f"{acc[:58]:<58} {r.located[:24]:<24} {r.cv_before_um:6.3f} -> {r.cv_after_um:6.3f}     "
                  f"{r.fresh_before_um:6.3f} -> {r.fresh_after_um:6.3f} ({100 * r.fresh_gain:+4.0f} %) "
                  f"{r.true_um:5.2f} / {r.relevance_um:4.2f}   {r.wall_s:5.1f}", flush=True)
    print()
    print("summary per case (n seeds):")
    for name in names:
        rs = [r for r in rows if r.case == name]
        case = CASES[name]
        if case.expected in ("", "artefact"):
            what = "nothing accepted" if not case.expected else "step classified as an artefact, no physics accepted"
            ok = sum(r.named_first for r in rs)
            aim = 0.95 if not case.expected else 0.9
            print(f"  {name:<18} {what}: {ok}/{len(rs)}  (aim >= {100 * aim:.0f} %)")
            continue
        first = sum(r.named_first for r in rs)
        anyn = sum(r.named_any for r in rs)
        both = sum(r.named_first and r.fresh_gain >= 0.3 for r in rs)
        gains = [100 * r.fresh_gain for r in rs]
        big = [r for r in rs if r.relevant]
        print(f"  {name:<18} named first {first}/{len(rs)}, named at all {anyn}/{len(rs)}, named first with fresh RMS "
              f"-30 % or better {both}/{len(rs)}; fresh RMS gain median {np.median(gains):+.0f} % "
              f"(min {min(gains):+.0f} %); where the hidden effect reaches the relevance bound: named first "
              f"{sum(r.named_first for r in big)}/{len(big)}  (aim: >= 90 % named, >= 30 % gain)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
