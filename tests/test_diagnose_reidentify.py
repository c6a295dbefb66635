"""Diagnosis where the missing physics also shaped the identification experiments.

A small synthetic plant (one axis, the spindle's speed and stator current) whose displacement also follows
the workshop's air through a 3 h lag: a daily cycle plus a weather drift that no recording carries. The room
acts in every recording, the three identification experiments (each at its own time of day) included, so the
identified paths are wrong and a term added on top of them cannot repair them. Fast (seconds), and every
figure a user gets comes from the written model through ``estimate``.
"""

from __future__ import annotations

import json
import math
import re
import shlex
from dataclasses import replace

import numpy as np
import pytest

from gateway.cli import main
from gateway.diagnose import api, diagnose, refit
from gateway.diagnose.api import start_histories, uncovered_factors, validate
from gateway.diagnose.data import build_stack
from gateway.diagnose.hypotheses import catalogue
from gateway.identify import identify
from gateway.model import FirstOrder, PathTF, ThermalModel, load_model, save_model
from gateway.recording import Recording, continued, write_recording
from gateway.replay import _held, estimate, working_history

pytestmark = pytest.mark.numeric

F = ("speed", "i_sq")
DAY_S = 86400.0
PLANT = ThermalModel(axes=("z",), factors=F, units={"speed": "rpm", "i_sq": "A^2"}, reference={}, paths={
    ("z", "speed"): PathTF(axis="z", factor="speed", terms=(FirstOrder(gain=0.012, tau_s=2400.0),
                                                           FirstOrder(gain=0.004, tau_s=9000.0))),
    ("z", "i_sq"): PathTF(axis="z", factor="i_sq", terms=(FirstOrder(gain=0.05, tau_s=900.0),)),
})
ROOM_UM_PER_K = 4.0
ROOM_LAG_S = 3 * 3600.0


def _room_um(t_s: np.ndarray, *, amplitude_k: float, drift_k_per_h: float) -> np.ndarray:
    """The displacement the room makes (um): a daily sine peaking at 15 h and a drift, through a 3 h lag."""
    room = amplitude_k * np.cos(2 * np.pi * (t_s - 15 * 3600.0) / DAY_S) + drift_k_per_h * (t_s - t_s[0]) / 3600.0
    # the machine was in the cycle's periodic steady state at the start: start the lag there
    a = np.exp(-60.0 / ROOM_LAG_S)
    w = 2 * np.pi / DAY_S
    phase = np.arctan(w * ROOM_LAG_S)
    out = np.empty_like(room)
    out[0] = amplitude_k / np.hypot(1, w * ROOM_LAG_S) * np.cos(w * (t_s[0] - 15 * 3600.0) - phase)
    for k in range(1, len(room)):
        out[k] = a * out[k - 1] + (1 - a) * room[k]
    return ROOM_UM_PER_K * out


def _record(name: str, speed: np.ndarray, *, start_s: float, seed: int, room: bool = True,
            plant: ThermalModel | None = None) -> Recording:
    """``speed`` through ``plant`` (the module's PLANT, looked up at the call: other tests swap it), noise added."""
    n = len(speed)
    i_sq = 2.0 + 60.0 * (speed / 1000.0) ** 2
    u = np.vstack([speed, i_sq])
    y = (plant or PLANT).discretize(60.0).simulate(u - u[:, :1])[0]
    t = start_s + 60.0 * np.arange(1, n + 1)
    if room:
        y = y + _room_um(t, amplitude_k=1.5, drift_k_per_h=0.02)
    rng = np.random.default_rng(seed)
    y = y + 3.0 + 0.1 * rng.standard_normal(n)
    return Recording(source=f"{name}.csv", period_s=60.0, time_s=t, present=np.ones(n, dtype=bool),
                     factors={"speed": speed, "i_sq": i_sq * (1 + 0.01 * rng.standard_normal(n))},
                     displacement={"z": y})


def _experiment(level: float, *, start_h: float, seed: int, alternating: bool = False, room: bool = True,
                plant: ThermalModel | None = None):
    speed = np.zeros(720)
    speed[30:90] = level
    if alternating:  # same mean speed, more current: the ratio of the factors differs
        speed[30:90:2] = 0.6 * level
        speed[31:90:2] = 1.4 * level
    return _record(f"exp{seed}", speed, start_s=start_h * 3600.0, seed=seed, room=room, plant=plant)


def _day(day: int, *, seed: int, room: bool = True, plant: ThermalModel | None = None) -> Recording:
    rng = np.random.default_rng(seed)
    speed = np.zeros(1440)
    k = int(rng.integers(360, 480))
    while k < 1320:
        m = int(rng.integers(20, 90))
        speed[k:k + m] = rng.choice([0.0, 800.0, 1500.0, 2500.0])
        k += m
    return _record(f"day{day}", speed, start_s=day * DAY_S, seed=seed, room=room, plant=plant)


def _bundled_day(sim_csv_dir):
    """The bundled production day as ``cncgw`` reads it."""
    from gateway.commands._common import read_recordings
    from gateway.profile import load_profile

    (day,) = read_recordings([str(sim_csv_dir / "production-day.csv")], load_profile("sim-vmc"), period_s=None,
                             require_displacement=True)
    return day


def _write_part(day: Recording, hour: float, path):
    """``day`` from ``hour`` on, written to ``path`` as a recording of its own."""
    part = day.slice(round(hour * 3600 / day.period_s), len(day))
    write_recording(path, time_s=part.time_s, columns={**part.factors, **{f"{a}_um": v for a, v in
                                                                          part.displacement.items()}})
    return path


@pytest.fixture(scope="module")
def plant_data():
    exps = [_experiment(1000.0, start_h=9.0, seed=1), _experiment(500.0, start_h=14.0, seed=2),
            _experiment(500.0, start_h=20.0, seed=3, alternating=True)]
    days = [_day(d, seed=10 + d) for d in range(1, 5)]
    fresh = _day(6, seed=99)
    base = identify(exps, factors=F, axes=("z",), units=dict(PLANT.units), machine="synthetic").model
    return exps, days, fresh, base


@pytest.fixture(scope="module")
def diagnosed(plant_data):
    exps, days, _, base = plant_data
    return diagnose(base, [*exps, *days])


def test_an_unfit_model_is_said_unfit_and_never_reassured(diagnosed):
    d = diagnosed
    # the room moves every recording early on: one note for them all, not one each
    (note,) = [n for n in d.notes if "not to start at rest" in n]
    assert re.match(r"\d+ recordings seem not to start at rest \(exp1, ", note), note
    assert note.endswith("so what they miss early on may be their start's (a machine not yet at rest) or a "
                         "disturbance no input carries"), note
    # ... and its drift at rest stays the disturbance it is: most recordings move early, no start explains that
    assert not any("settling from its start" in ln for ln in d.adequacy.lines())
    assert not d.adequacy.fit
    assert d.adequacy.lines()[0].startswith("this model is not fit for compensation")
    assert "nothing significant is missing" not in " ".join(d.conclusions)
    # the verdict goes on to the model written: judged over the held-out blocks by the same 30 % bound
    written = d.comparison.written
    worst = max(written.metrics.values(), key=lambda m: m.max_error_pct_of_peak)
    line = d.verdict()[-1]
    assert line.startswith(f"the model written ({written.title}): over the held-out blocks its max |error| is "
                           f"{worst.max_error_pct_of_peak:.0f} % of the peak displacement on axis z"), line
    assert ("within the 30 %" in line) == (worst.max_error_pct_of_peak <= 30), line
    assert d.conclusions[:len(d.verdict())] == d.verdict()


def test_a_day_cut_while_the_machine_is_warm_is_said_so_beside_the_verdict_it_spoils():
    # every recording is started in equilibrium with its first window: a day cut in a pause after three hours of
    # work cools where the model predicts nothing, and that alone made a good model "not fit for compensation"
    exps = [_experiment(1000.0, start_h=9.0, seed=1, room=False), _experiment(500.0, start_h=14.0, seed=2, room=False),
            _experiment(500.0, start_h=20.0, seed=3, alternating=True, room=False)]
    days = [_day(d, seed=10 + d, room=False) for d in range(1, 4)]
    base = identify(exps, factors=F, axes=("z",), units=dict(PLANT.units), machine="synthetic").model
    assert days[2].factors["speed"][950] == 0  # a pause ...
    assert days[2].factors["speed"][600:950].mean() > 1000  # ... after hours of work
    d = diagnose(base, [*exps, days[0], days[1], days[2].slice(950, 1440)], initial_state="rest")
    assert not d.adequacy.fit  # taken on every recording, as before: a room drifting early looks warm too
    said = d.adequacy.lines()[1]
    assert re.match(r"day3 \(axis z moves [\d.]+ um in the first hour where the model, started at rest, predicts "
                    r"[\d.e+-]+ um\) seems not to start at rest; every recording is started in equilibrium with its "
                    r"first window, so there the error is the start's as much as the model's; without it: on 2 "
                    r"recording\(s\) it did not train on, the model stays within (\d+) % of the peak", said), said
    assert int(re.search(r"stays within (\d+) %", said)[1]) <= 30, said
    assert said in d.conclusions
    (note,) = [n for n in d.notes if "not to start at rest" in n]
    assert note.startswith("day3: it seems not to start at rest (axis z moves "), note
    # its cooling while it rests is no disturbance of the room's: said where the drift is reported
    (drift,) = [ln for ln in d.adequacy.lines() if "drifts while every input rests" in ln]
    assert drift.endswith("; day3): a disturbance no factor carries (room temperature, coolant, a neighbouring "
                          "machine), or heat slower than every mode of the model; but only in recordings that seem "
                          "not to start at rest, where it may be the machine settling from its start"), drift
    # the whole day starts at rest: nothing said, and the model is fit
    whole = diagnose(base, [*exps, *days])
    assert whole.adequacy.fit, whole.adequacy.lines()
    assert not any("not to start at rest" in n for n in [*whole.notes, *whole.adequacy.lines()])
    # by default the cut day runs from the work its first hours show: the good model is fit there too, as on the
    # whole day, within the same bound
    fitted = diagnose(base, [*exps, days[0], days[1], days[2].slice(950, 1440)])
    assert fitted.adequacy.fit, fitted.adequacy.lines()
    worst = float(re.search(r"stays within (\d+) % of the peak", fitted.adequacy.lines()[0])[1])
    assert worst <= 10, fitted.adequacy.lines()
    (note,) = [n for n in fitted.notes if "not to start at rest" in n]
    assert re.match(r"day3: it seems not to start at rest \(axis z moves [\d.]+ um in the first hour .*\); it runs "
                    r"from the work its first hours show \([\d.]+ h at its (first window's|mean working) levels before "
                    r"it, from rest, as the (re-)?identified model chooses it, as windows with no displacement\)",
                    note), note
    # ... which it does not for an identification experiment: the model was fitted from that start
    assert start_histories(base, [exps[0], days[2].slice(950, 1440), *days[:2], exps[1]],
                           {0: "cut", 1: "cut"}).keys() == {1}
    # ... nor when most recordings seem not to start at rest (a disturbance in all of them is likelier)
    assert not start_histories(base, [days[2].slice(950, 1440), days[0]], {0: "cut"})


def test_a_day_cut_mid_work_runs_from_hours_of_work_like_those_before_it():
    # idle until 7 h, then jobs at 1500 and 2500 rpm; the file starts at 9 h: two hours of work before it, the
    # machine far from the equilibrium of working so for ever (its slowest mode 2.5 h)
    speed = np.zeros(1440)
    speed[420:900] = 1500.0
    speed[600:660] = 2500.0
    day = _record("day", speed, start_s=2 * DAY_S, seed=5, room=False)
    cut = day.slice(540, len(day))
    hist, said = working_history(PLANT, cut)
    hours = float(said.split(" h at ")[0])
    assert 1.0 <= hours <= 4.0, said  # hours of work, not a machine that worked so for ever
    assert len(hist) == round(hours * 60) + 1
    assert np.isnan(hist.displacement["z"]).all()
    assert hist.factors["speed"][0] == 0.0  # from rest
    assert hist.time_s[-1] == cut.time_s[0] - 60.0  # it ends one window before the recording
    # the state it leaves predicts the hours after the cut, where equilibrium with the first window does not
    rest = estimate(PLANT, cut)  # in equilibrium with its first window (working for ever)
    worked = estimate(PLANT, cut, history=hist, initial="reference")
    assert worked.metrics["z"].rms_um < 0.25 * rest.metrics["z"].rms_um, (worked.metrics["z"], rest.metrics["z"])
    # a day at rest at its start gets none
    assert working_history(PLANT, day) is None


def test_a_file_that_starts_with_a_job_on_a_cold_machine_runs_from_rest_not_from_working_for_ever():
    # idle until 9 h, then a job at 2000 rpm; the file starts as the job does: the machine was cold. Without a
    # history it would run as if it had worked at 2000 rpm for ever; the start at rest meets its hours best
    speed = np.zeros(1440)
    speed[540:900] = 2000.0
    day = _record("day", speed, start_s=2 * DAY_S, seed=6, room=False)
    cut = day.slice(540, len(day))
    # what identify records: the range each factor covered (a factor beyond a tenth of it works)
    model = replace(PLANT, info={"deviation_range": {"speed": [0.0, 2500.0], "i_sq": [0.0, 375.0]}})
    hist, said = working_history(model, cut)
    assert said == "no work", said
    assert len(hist) == 1
    assert hist.factors["speed"][0] == 0.0
    ever = estimate(model, cut)  # in equilibrium with its first window: worked at 2000 rpm for ever
    cold = estimate(model, cut, history=hist, initial="reference")
    assert cold.metrics["z"].rms_um < 0.5, cold.metrics["z"]  # the noise is 0.1 um
    assert ever.metrics["z"].rms_um > 10 * cold.metrics["z"].rms_um, (ever.metrics["z"], cold.metrics["z"])


def test_cncgw_diagnose_runs_a_day_cut_mid_work_from_its_work_or_from_rest_on_request(tmp_path, capsys):
    exps = [_experiment(1000.0, start_h=9.0, seed=1, room=False), _experiment(500.0, start_h=14.0, seed=2, room=False),
            _experiment(500.0, start_h=20.0, seed=3, alternating=True, room=False)]
    days = [_day(d, seed=10 + d, room=False) for d in range(1, 4)]
    days[2] = days[2].slice(950, 1440)  # in a pause after hours of work
    profile = tmp_path / "synthetic.toml"
    profile.write_text(_PROFILE)
    files = []
    for rec in [*exps, *days]:
        path = tmp_path / rec.source
        write_recording(path, time_s=rec.time_s, columns={**rec.factors, "z_um": rec.displacement["z"]})
        files.append(str(path))
    model = save_model(identify(exps, factors=F, axes=("z",), units=dict(PLANT.units), machine="synthetic").model,
                       tmp_path / "base.model.toml")
    docs = {}
    for how in ("fit", "rest"):
        out = tmp_path / how
        assert main(["diagnose", "--profile", str(profile), "--model", str(model), *files, "-o", str(out),
                     "--initial-state", how]) == 0
        docs[how] = json.loads((out / "report.json").read_text())
    capsys.readouterr()
    (note,) = [n for n in docs["fit"]["notes"] if n.startswith("day3: it seems not to start at rest")]
    assert "it runs from the work its first hours show (" in note
    own_h = sum(len(r) for r in [*exps, *days]) / 60.0  # the recordings' own hours, not the work run before one
    assert f"6 recording(s), {own_h:.1f} h in all (longest 24.0 h)" in " ".join(docs["fit"]["conclusions"])
    (note,) = [n for n in docs["rest"]["notes"] if n.startswith("day3: it seems not to start at rest")]
    assert "diagnose starts every recording in equilibrium with its first window" in note
    # from its work the good model is fit there; from equilibrium with its first window it was not
    assert docs["fit"]["adequacy"]["fit"] is True
    assert docs["rest"]["adequacy"]["fit"] is False
    with pytest.raises(SystemExit) as refused:  # argparse's own refusal of the value
        main(["diagnose", "--profile", str(profile), "--model", str(model), *files, "--initial-state", "warm"])
    assert refused.value.code == 2
    assert "invalid choice: 'warm' (choose from 'fit', 'rest')" in capsys.readouterr().err


def test_a_wrong_guess_of_the_work_before_days_cut_mid_work_does_not_bend_the_re_identified_paths(monkeypatch):
    # days 2 and 3 given from 15.8 h on, after 8-9 h of work (day 2 at 2500 rpm then); the guess of the work
    # before them (held at the first window's levels for some hours, as diagnosis runs them) is off. Refitted
    # through a wrong guess, the paths bent to put it right and predicted a fresh whole day 8-13x worse than
    # through the true hours; the guess's error is taken beside the paths instead, by free decays
    exps = [_experiment(1000.0, start_h=9.0, seed=1, room=False), _experiment(500.0, start_h=14.0, seed=2, room=False),
            _experiment(500.0, start_h=20.0, seed=3, alternating=True, room=False)]
    days = [_day(d, seed=10 + d, room=False) for d in range(1, 5)]
    fresh = _day(6, seed=99, room=False)
    base = identify(exps, factors=F, axes=("z",), units=dict(PLANT.units), machine="synthetic").model
    cut = 950

    def fresh_rms(guess_h: float | None) -> float:  # None: the true hours before the cut (displacement unmeasured)
        recs, lead = [], []
        for k, day in enumerate(days):
            if k not in (1, 2):
                recs.append(day)
                lead.append(0)
                continue
            part = day.slice(cut, len(day))
            if guess_h is None:
                hist = day.slice(0, cut)
                hist = replace(hist, displacement={"z": np.full(len(hist), np.nan)})
            else:
                hist = _held(part, list(F), np.array([day.factors[f][0] for f in F]),
                             np.array([part.factors[f][0] for f in F]), round(guess_h * 60))
            recs.append(continued(hist, part))
            lead.append(len(hist))
        stack = replace(build_stack(base, [*exps, *recs]), lead=(0, 0, 0, *lead))
        return estimate(refit.reidentify(stack, base, []).model, fresh).metrics["z"].rms_um

    true = fresh_rms(None)
    assert true < 0.2  # the noise is 0.1 um
    for guess_h in (0.5, 2.0, 20.0):
        assert fresh_rms(guess_h) < 1.3 * true + 0.02, guess_h
    # without the free decays, the check's own premise: the paths bend
    monkeypatch.setattr(refit, "HISTORY_DECAY_H", ())
    assert fresh_rms(0.5) > 3 * true


def test_the_work_before_a_day_cut_mid_work_is_chosen_again_by_the_re_identified_model(monkeypatch):
    # a mode of 30 h on the spindle's heat, which 12 h experiments cannot show, acts in every recording; day 3 is
    # given from 15.8 h on, after 8 h of work. The identified model lacks the mode, so the work it chooses before
    # that day is off, and so is every fit started from it; the model identified again on all recordings chooses
    # the work again, and the pass whose written model predicts the held-out blocks best is kept
    slow = replace(PLANT, paths={**PLANT.paths, ("z", "speed"): PathTF(axis="z", factor="speed", terms=(
        *PLANT.path("z", "speed").terms, FirstOrder(gain=0.03, tau_s=30 * 3600.0)))})
    exps = [_experiment(1000.0, start_h=9.0, seed=1, room=False, plant=slow),
            _experiment(500.0, start_h=14.0, seed=2, room=False, plant=slow),
            _experiment(500.0, start_h=20.0, seed=3, alternating=True, room=False, plant=slow)]
    days = [_day(d, seed=10 + d, room=False, plant=slow) for d in range(1, 5)]
    fresh = _day(6, seed=99, room=False, plant=slow)
    assert np.flatnonzero(days[2].factors["speed"])[0] / 60.0 == pytest.approx(7.8, abs=0.1)  # work from 7.8 h
    base = identify(exps, factors=F, axes=("z",), units=dict(PLANT.units), machine="synthetic").model
    recordings = [*exps, days[0], days[1], days[2].slice(950, 1440), days[3]]
    said = []
    d = diagnose(base, recordings, progress=said.append)
    assert "the work before the recordings that start warm, chosen again by the re-identified model" in said
    (note,) = [n for n in d.notes if n.startswith("day3: it seems not to start at rest")]
    hours = float(re.search(r"it runs from the work its first hours show \(([\d.]+) h at its", note)[1])
    # hours of work at a level held (8 h of jobs and pauses, through a model without the 30 h mode): not a cold
    # start, nor working so for ever
    assert 1.0 <= hours <= 10.0, note
    assert " before it, from rest, as the re-identified model chooses it, as windows with no displacement" in note
    assert "slow_mode:speed" in d.accepted_physics
    # ... where the identified model's own choice alone (one pass) is kept with a worse fit
    monkeypatch.setattr(api, "HISTORY_PASSES", 1)
    once = diagnose(base, recordings)
    assert d.comparison.written.sse < once.comparison.written.sse
    before = estimate(base, fresh).metrics["z"].rms_um
    after, after_once = (estimate(x.extended, fresh).metrics["z"].rms_um for x in (d, once))
    assert after < 0.05 * before, (before, after)
    assert after < after_once, (after_once, after)
    # with the paths refitted through that one pass's guess of the work before day 3 and nothing beside them to
    # take its error (the free decays of refit.history_free left out), the refit search took heat ~ speed^2
    # beside paths bent by it, and the paths re-identified without it predict the held-out blocks significantly
    # better: it is not written, and what more data changed is named, the slow mode
    monkeypatch.setattr(refit, "HISTORY_DECAY_H", ())
    bent = diagnose(base, recordings)
    with_terms = bent.comparison.candidates["reidentified_terms"]
    assert with_terms.title.startswith("re-identified on all recordings with heat ~ speed^2")
    assert "; the model re-identified without them predicts the held-out blocks significantly better" in \
        with_terms.verdict
    assert with_terms.verdict.endswith("): not written"), with_terms.verdict
    assert bent.accepted_physics == ["slow_mode:speed"]


def test_the_room_is_named_and_the_rewritten_model_predicts_a_fresh_day(plant_data, diagnosed):
    _, _, fresh, base = plant_data
    d = diagnosed
    assert d.accepted_physics[0] == "room_daily"
    assert d.comparison.chosen == "reidentified"
    # more data alone is scored beside the room's terms (issue 11): re-identified paths cannot absorb the room
    alone = d.comparison.candidates["reidentified_alone"]
    assert alone.title == "re-identified on all recordings (more data alone, no new term)"
    assert alone.sse > 5 * d.comparison.written.sse
    before = estimate(base, fresh).metrics["z"].rms_um
    after = estimate(d.extended, fresh).metrics["z"].rms_um
    assert after < 0.5 * before, (before, after)
    # re-identified beside the room's terms, the speed path's static gain comes back to the plant's
    assert d.extended.path("z", "speed").gain == pytest.approx(PLANT.path("z", "speed").gain, rel=0.25)
    assert [i.name for i in d.extended.inputs] == ["day_sin", "day_cos"]
    # the room of this plant is a sine: the day's harmonics are tried and not taken over it
    (harm,) = [t for t in d.result.trials if t.hypothesis.key == "room_daily:3_harmonics"]
    assert harm.verdict.startswith("passes, but room_daily predicts the held-out blocks significantly better")
    assert not any(t.rivals for t in d.result.accepted)


def test_the_rewritten_model_covers_and_bounds_the_days_it_was_fitted_on(plant_data, diagnosed):
    exps, days, _, base = plant_data
    d = diagnosed
    assert d.comparison.chosen == "reidentified"
    # the experiments ran the spindle up to 1000 rpm, the days to 2500: the identified model's coverage ends at
    # 1000, the model fitted on the days too covers them (a fresh day at 2500 rpm is no excursion for it)
    assert base.coverage.ranges["speed"][1] == pytest.approx(1000.0, rel=0.05)
    # what the report says where more data alone changed the paths: the days went beyond the experiments
    beyond = uncovered_factors(base, build_stack(base, days))
    assert any(b.startswith("speed up to 2.5x the highest covered (1") for b in beyond), beyond
    assert uncovered_factors(base, build_stack(base, exps)) == []
    assert d.extended.coverage.ranges["speed"][1] == pytest.approx(2500.0 - 0.0, rel=0.05)
    # and its plausibility envelope holds what the days measured (the live gateway would hold offsets beyond it)
    measured_span = max(float(np.ptp(r.displacement["z"])) for r in days)
    assert base.envelope.axes["z"].max_abs_um < measured_span
    assert d.extended.envelope.axes["z"].max_abs_um >= measured_span
    assert "diagnosis: 7 recordings" in d.extended.envelope.source


def test_a_room_thermometer_on_the_production_days_only_is_tried_beside_the_time_of_day():
    # the room acts in every recording, but the thermometer came with the production days: the experiments have
    # no room_c. It is tried, taken as constant where it is missing (the diagnosis ended in "exp1.csv: the model's
    # input room_c reads column room_c, which this recording does not have" once it had chosen it), and so is the
    # daily cycle, whose time of day every recording has: here the cycle predicts better and is taken
    def thermometer(rec: Recording) -> Recording:
        t = rec.time_s
        room = 20.0 + 1.5 * np.cos(2 * np.pi * (t - 15 * 3600.0) / DAY_S) + 0.02 * (t - t[0]) / 3600.0
        return replace(rec, extras={"room_c": np.round(room, 2)})

    exps = [_experiment(1000.0, start_h=9.0, seed=1), _experiment(500.0, start_h=14.0, seed=2),
            _experiment(500.0, start_h=20.0, seed=3, alternating=True)]
    days = [thermometer(_day(d, seed=10 + d)) for d in range(1, 5)]
    fresh = thermometer(_day(6, seed=99))
    base = identify(exps, factors=F, axes=("z",), units=dict(PLANT.units), machine="synthetic").model
    d = diagnose(base, [*exps, *days])
    tried = {t.hypothesis.key for t in d.result.trials}
    assert {"room_recorded:room_c", "room_daily"} <= tried
    assert d.accepted_physics == ["room_daily"]
    assert any(c.startswith("column room_c is recorded in 4 of 7 recordings") and "take it as constant in the others"
               in c for c in d.conclusions)
    # with the thermometer in every recording, it alone is tried
    full = diagnose(base, [*(thermometer(e) for e in exps), *days])
    assert "room_daily" not in {t.hypothesis.key for t in full.result.trials}
    assert full.accepted_physics[0] == "room_recorded:room_c"
    # a model that reads room_c gets its envelope and coverage from the recordings that have it, not an error
    # from the others
    from gateway.diagnose.api import _supported_region

    region = _supported_region(full.extended, [*exps, *days], reidentified=True, gap_policy="hold")
    assert region.coverage is not None
    assert region.coverage.source == "diagnosis: 4 recordings"
    before = estimate(base, fresh).metrics["z"].rms_um
    after = estimate(d.extended, fresh).metrics["z"].rms_um
    assert after < 0.2 * before, (before, after)


def test_the_daily_room_is_tried_where_the_recordings_cover_the_clock_together(plant_data):
    # days cut at 10 h (a gateway started mid-shift): none spans most of a day, but with the experiments (from 9, 14
    # and 20 h) they cover the whole clock between them, each recording's own drift fitted apart
    # (bench/diagnose.py --cut-days 10: the room not recorded, v1-v3, sine and heated hall, named in 6 of 6, was 0)
    exps, days, _, base = plant_data
    cut = [d.slice(600, len(d)) for d in days]
    stack = build_stack(base, [*exps, *cut])
    assert stack.longest_s() == pytest.approx(14 * 3600.0)
    assert stack.day_covered() > 0.95
    assert {"room_daily", "room_daily:3_harmonics"} <= {h.key for h in catalogue(stack, base, [])}
    # the same files with times that count from their own start: together they cover no more than the longest,
    # and a daily cycle cannot be told from a drift
    from_zero = [replace(r, time_s=r.time_s - r.time_s[0] + 60.0) for r in [*exps, *cut]]
    stack = build_stack(base, from_zero)
    assert stack.day_covered() == pytest.approx(14 / 24, abs=0.02)
    assert not any(h.family == "room_daily" for h in catalogue(stack, base, []))
    # nor files without a time column (read with a row period): their time of day is unknown
    stack = build_stack(base, [replace(r, clock=False) for r in [*exps, *cut]])
    assert stack.day_covered() == 0.0
    assert not any(h.family == "room_daily" for h in catalogue(stack, base, []))
    # nor two experiments run from 9 and 14 h: 9 h to 2 h the next morning is 17 of 24 h
    stack = build_stack(base, exps[:2])
    assert stack.day_covered() == pytest.approx(17 / 24, abs=0.02)
    assert not any(h.family == "room_daily" for h in catalogue(stack, base, []))


def test_without_the_room_nothing_is_named_and_the_written_model_is_no_worse():
    exps = [_experiment(1000.0, start_h=9.0, seed=1, room=False), _experiment(500.0, start_h=14.0, seed=2, room=False),
            _experiment(500.0, start_h=20.0, seed=3, alternating=True, room=False)]
    days = [_day(d, seed=10 + d, room=False) for d in range(1, 4)]
    base = identify(exps, factors=F, axes=("z",), units=dict(PLANT.units), machine="synthetic").model
    d = diagnose(base, [*exps, *days])
    assert d.adequacy.fit
    assert d.accepted_physics == []
    assert d.extended.inputs == ()
    fresh = _day(6, seed=99, room=False)
    # more data alone may pin the paths down better (three short experiments leave a slow mode loose): it is
    # written only when it predicts the held-out blocks better, and then the fresh day is no worse
    assert estimate(d.extended, fresh).metrics["z"].rms_um <= 1.05 * estimate(base, fresh).metrics["z"].rms_um
    text = " ".join(d.conclusions)
    if d.comparison.chosen == "identified":
        assert "nothing significant is missing" in text
    else:
        assert d.comparison.chosen == "reidentified"
        assert "no missing physics is named" in text
        # asked which physics explains what more data changed in the paths, it names none
        assert d.explanation is not None
        assert d.explanation.names == []
        assert "no family is named" in text
        assert d.extended.info["diagnosis"]["explained"] == []


def test_validation_starts_from_the_day_before_or_from_a_fitted_state(plant_data, diagnosed):
    _, days, _, _ = plant_data
    d = diagnosed
    after_day4 = _day(5, seed=50)
    (carried,) = validate(d, [after_day4], earlier=days)
    assert carried.start.startswith("carried from day1, day2, day3, day4")
    assert carried.settings["history"] == "day4.csv"
    # a --history that ended days before: carried, and said so (it read "ran just before it" of a day 72 h later)
    later = _day(8, seed=80)
    (gapped,) = validate(d, [later], history=days[3])
    gap_h = (later.time_s[0] - days[3].time_s[-1] - later.period_s) / 3600.0
    assert gap_h > 48
    assert gapped.start == (f"carried from day4 (--history), which ends {gap_h:.3g} h before it starts: the gap "
                            "policy hold bridges the hours between")
    # the same two days as runs of one file split by its day column (--split-by day): each starts in its own
    # equilibrium, as the diagnosis took them, though the times run on from one to the next
    run4, run5 = (replace(r, source=f"days.csv[day={k}]") for k, r in ((4, days[3]), (5, after_day4)))
    (split,) = validate(d, [run5], earlier=[run4])
    assert split.label == "day 5"
    assert split.start == ("at rest (it starts with the machine in equilibrium); a run of a --split-by file is never "
                           "carried on from the one before it (--history FILE carries)")
    assert "history" not in split.settings
    # nor does a whole file carry into a run of a split one, or a run into the file after it
    (after_run,) = validate(d, [after_day4], earlier=[run4])
    assert after_run.start.startswith(("at rest", "estimated from its first hour"))
    (into_run,) = validate(d, [run5], earlier=[days[3]])
    assert not into_run.start.startswith("carried")
    # files read with --period-s each count their times from 0: only --history carries
    (unchained,) = validate(d, [after_day4], earlier=days, chain=False)
    assert not unchained.start.startswith("carried")
    warm = after_day4.slice(600, 1440)  # starts mid-work, nothing before it
    (fitted,) = validate(d, [warm])
    assert fitted.settings["initial_state"] == "fit"
    assert "it does not start at rest (" in fitted.start
    assert any("initial state estimated from the first 1 h" in n for n in fitted.after.notes)
    # it works at its first window (2500 rpm): its state is heat since the model's reference levels, not a state on
    # top of working at 2500 rpm for ever
    assert warm.factors["speed"][0] == 2500.0
    assert fitted.settings["initial"] == "reference"
    assert fitted.start.startswith("estimated from its first hour, from the model's reference levels: it does not "
                                   "start at rest (speed is +2500 rpm from its rest level at the first window)")


def test_the_written_model_reproduces_the_reported_validation_through_cncgw_estimate(tmp_path, plant_data, capsys):
    exps, days, fresh, base = plant_data
    profile = tmp_path / "synthetic.toml"
    profile.write_text(_PROFILE)
    files = []
    for rec in [*exps, *days, fresh]:
        path = tmp_path / rec.source
        write_recording(path, time_s=rec.time_s, columns={**rec.factors, "z_um": rec.displacement["z"]})
        files.append(str(path))
    # and the fresh day cut while it works: validated from the reference levels with its state fitted
    k = int(np.flatnonzero(fresh.factors["speed"][600:] > 0)[0]) + 600
    working = fresh.slice(k, len(fresh))
    cut = tmp_path / "day6-cut.csv"
    write_recording(cut, time_s=working.time_s, columns={**working.factors, "z_um": working.displacement["z"]})
    model = save_model(base, tmp_path / "base.model.toml")
    out = tmp_path / "report"
    assert main(["diagnose", "--profile", str(profile), "--model", str(model), *files[:-1], "-o", str(out),
                 "--validate", files[-1], str(cut)]) == 0
    capsys.readouterr()
    doc = json.loads((out / "report.json").read_text())
    assert doc["written"] == "reidentified"
    written = out / "base.diagnosed.model.toml"
    assert load_model(written).info["diagnosis"]["written"] == "reidentified"
    settings = doc["validation"][0]["settings"]
    assert settings["initial_state"] == "rest"  # the fresh day starts in equilibrium: nothing to fit
    assert main(["estimate", "--profile", str(profile), "--model", str(written), files[-1], "--json"]) == 0
    est = json.loads(capsys.readouterr().out)[0]["axes"]["z"]
    reported = doc["validation"][0]["after"]["z"]
    for key in ("rms_um", "max_abs_error_um", "peak_um"):
        assert est[key] == pytest.approx(reported[key], rel=1e-6, abs=1e-9), key
    assert reported["rms_um"] < 0.5 * doc["validation"][0]["before"]["z"]["rms_um"]
    md = (out / "report.md").read_text()
    assert "## Validation: recordings never used for fitting or selection" in md
    # the table's peak: each model's own (one figure where they agree), the one its % is of
    row = next(ln for ln in md.splitlines() if ln.startswith("| day6 |"))
    before, after = (doc["validation"][0][k]["z"]["peak_um"] for k in ("before", "after"))
    shown = [float(p) for p in row.split(" | ")[7].removesuffix(" um").split(" / ")]
    assert shown[0] == pytest.approx(before, rel=5e-3)
    assert shown[-1] == pytest.approx(after, rel=5e-3)
    assert "## Models compared on held-out data" in md
    assert md.index("## Verdict") < md.index("## Conclusions")
    assert "validation.png" in {p.name for p in out.iterdir()}
    # the command the report prints for it runs as printed (from the folder diagnose ran in) and gives the same
    (cmd,) = re.findall(r"^- day6: `(cncgw estimate [^`]+)`$", md, flags=re.M)
    assert cmd == f"cncgw estimate --profile {profile} --model {written} {files[-1]}"
    assert main([*shlex.split(cmd)[1:], "--json"]) == 0
    assert json.loads(capsys.readouterr().out)[0]["axes"]["z"]["rms_um"] == pytest.approx(reported["rms_um"], rel=1e-6)
    # ... and the one cut while it works, with the options it was estimated with
    (cmd,) = re.findall(r"^- day6-cut: `(cncgw estimate [^`]+)`$", md, flags=re.M)
    assert cmd == (f"cncgw estimate --profile {profile} --model {written} --initial reference --initial-state fit "
                   f"{cut}")
    assert main([*shlex.split(cmd)[1:], "--json"]) == 0
    reported = doc["validation"][1]["after"]["z"]
    assert json.loads(capsys.readouterr().out)[0]["axes"]["z"]["rms_um"] == pytest.approx(reported["rms_um"], rel=1e-6)
    # the conclusions sum the validation up, pooled over its recordings, and say where the written model is worse
    (summary,) = [c for c in doc["conclusions"] if c.startswith("validation (2 recording(s) never fitted)")]
    pooled = [math.sqrt(sum(v[k]["z"]["windows"] * v[k]["z"]["rms_um"] ** 2 for v in doc["validation"])
                        / sum(v[k]["z"]["windows"] for v in doc["validation"])) for k in ("before", "after")]
    assert f"RMS identified -> written model: z {pooled[0]:.3g} -> {pooled[1]:.3g} um" in summary
    worse = [v for v in doc["validation"] if v["after"]["z"]["rms_um"] > 1.1 * v["before"]["z"]["rms_um"]
             and v["after"]["z"]["rms_um"] - v["before"]["z"]["rms_um"] > 0.01]
    assert ("the written model is worse on" in summary) == bool(worse), summary
    assert f"- {summary}" in md, summary


_PROFILE = """\
[machine]
name = "synthetic"
axes = ["z"]

[recording]
time_column = "time_s"
displacement_columns = { z = "z_um" }

[factors.speed]
unit = "rpm"
stat = "mean"

[factors.i_sq]
unit = "A^2"
stat = "mean_square"
"""


def _knocked(rec: Recording, *, at: int, um: float) -> Recording:
    z = np.array(rec.displacement["z"], dtype=float)
    z[at:] += um
    return replace(rec, displacement={"z": z})


def test_a_knocked_sensor_is_neither_a_model_error_nor_a_resting_drift():
    # a model that fits apart from the sensor: knocked by 25 um in a working day (40 % of its peak) and by 3 um
    # in an idle one; both are steps within one window, the sensor's, so the verdict and the resting-drift check
    # are made without them (before they were: "unfit", and "drifts while every input rests")
    exps = [_experiment(1000.0, start_h=9.0, seed=1, room=False), _experiment(500.0, start_h=14.0, seed=2, room=False),
            _experiment(500.0, start_h=20.0, seed=3, alternating=True, room=False)]
    days = [_day(d, seed=10 + d, room=False) for d in range(1, 4)]
    idle = _record("idle", np.zeros(1440), start_s=5 * DAY_S, seed=7, room=False)
    days[1] = _knocked(days[1], at=900, um=25.0)
    idle = _knocked(idle, at=700, um=3.0)
    base = identify(exps, factors=F, axes=("z",), units=dict(PLANT.units), machine="synthetic").model
    d = diagnose(base, [*exps, *days, idle])
    steps = [round(s.size_um) for s in d.findings["z"].steps]
    assert sorted(steps) == [3, 25]
    assert d.adequacy.fit, d.adequacy.lines()
    assert d.adequacy.drift["z"].drifting == 0


def test_files_of_the_same_name_in_other_folders_are_told_apart_in_the_report(tmp_path, plant_data, capsys):
    # day folders often hold files of one name: the report named both "day" and listed each note twice
    exps, days, fresh, base = plant_data
    profile = tmp_path / "synthetic.toml"
    profile.write_text(_PROFILE)
    files = [tmp_path / rec.source for rec in exps] + [tmp_path / f"d{k}" / "day.csv" for k in range(1, 6)]
    for rec, path in zip([*exps, *days, fresh], files, strict=True):
        path.parent.mkdir(exist_ok=True)
        write_recording(path, time_s=rec.time_s, columns={**rec.factors, "z_um": rec.displacement["z"]})
    model = save_model(base, tmp_path / "base.model.toml")
    assert main(["diagnose", "--profile", str(profile), "--model", str(model), *map(str, files[:-1]), "-o",
                 str(tmp_path / "report"), "--validate", str(files[-1])]) == 0
    capsys.readouterr()
    doc = json.loads((tmp_path / "report" / "report.json").read_text())
    assert doc["labels"][-4:] == ["d1/day", "d2/day", "d3/day", "d4/day"]
    assert doc["validation"][0]["label"] == "d5/day"
    md = (tmp_path / "report" / "report.md").read_text()
    assert "d1/day, d2/day, d3/day, d4/day" in md


def test_a_file_of_several_runs_is_split_alike_by_identify_diagnose_and_estimate(tmp_path, plant_data, capsys):
    # a plant's export holds runs one after the other with a run number column (the ACE lathe's 18 days in one
    # file): identify, diagnose and estimate all take --split-by, each run starting in its own equilibrium
    exps, days, fresh, _ = plant_data
    profile = tmp_path / "synthetic.toml"
    profile.write_text(_PROFILE)

    def joined(path, recs):
        cols = {k: np.concatenate([r.factors[k] for r in recs]) for k in recs[0].factors}
        cols["z_um"] = np.concatenate([r.displacement["z"] for r in recs])
        cols["run"] = np.concatenate([np.full(len(r), k + 1.0) for k, r in enumerate(recs)])
        write_recording(path, time_s=60.0 * np.arange(1, len(cols["run"]) + 1), columns=cols)
        return str(path)

    exp_file, day_file = joined(tmp_path / "exps.csv", exps), joined(tmp_path / "days.csv", [*days, fresh])
    model = tmp_path / "m.toml"
    assert main(["identify", "--profile", str(profile), exp_file, "--split-by", "run", "-o", str(model)]) == 0
    assert "from 3 experiment(s)" in capsys.readouterr().out
    assert load_model(model).info["experiments"] == ["exps[run=1]", "exps[run=2]", "exps[run=3]"]
    out = tmp_path / "report"
    assert main(["diagnose", "--profile", str(profile), "--model", str(model), exp_file, day_file,
                 "--split-by", "run", "-o", str(out), "--validate", day_file]) == 2  # the same file twice
    assert (f"--validate {day_file}[run=1]: the same data as {day_file}[run=1], which is diagnosed: validation "
            "takes recordings never used for fitting or selection") in capsys.readouterr().err
    train = joined(tmp_path / "train.csv", days)
    # the runs diagnosed from one file, validated in another that holds them and one more, neither split: it was
    # taken for "never fitted"
    assert main(["diagnose", "--profile", str(profile), "--model", str(model), exp_file, train, "-o", str(out),
                 "--validate", day_file]) == 2
    n = sum(len(d) for d in days)
    assert (f"--validate {day_file}: {n} of its windows are the same data as {train} (the same times, inputs and "
            "measured displacement), which is diagnosed") in capsys.readouterr().err
    (tmp_path / "my runs").mkdir()  # a folder with a space: the printed command quotes it
    val = joined(tmp_path / "my runs" / "val.csv", [_day(5, seed=50), fresh])  # run 2 follows run 1: not carried
    assert main(["diagnose", "--profile", str(profile), "--model", str(model), exp_file, train, "--split-by",
                 "run", "-o", str(out), "--validate", val]) == 0
    capsys.readouterr()
    doc = json.loads((out / "report.json").read_text())
    # where the identified model is the one written, the validation table says why before equals after
    assert ("the identified model is the one written, so before and after are the same" in
            (out / "report.md").read_text()) == (doc["written"] == "identified")
    (v,) = [v for v in doc["validation"] if v["recording"].endswith("val.csv[run=2]")]
    assert not v["start"].startswith("carried")
    md = (out / "report.md").read_text()
    (cmd,) = re.findall(rf"^- {re.escape(v['label'])}: `(cncgw estimate [^`]+)` \(its run 2\)$", md, flags=re.M)
    assert cmd.endswith(f"--split-by run '{val}'")
    assert main([*shlex.split(cmd)[1:], "--json"]) == 0
    runs = {e["recording"]: e for e in json.loads(capsys.readouterr().out)}
    assert set(runs) == {f"{val}[run=1]", f"{val}[run=2]"}
    assert runs[f"{val}[run=2]"]["axes"]["z"]["rms_um"] == pytest.approx(v["after"]["z"]["rms_um"], rel=1e-6)
    # each run's prediction a file of its own
    preds = tmp_path / "preds"
    assert main([*shlex.split(cmd)[1:], "-o", str(preds)]) == 0
    assert sorted(p.name for p in preds.iterdir()) == ["val[run=1].pred.csv", "val[run=2].pred.csv"]


def test_estimate_says_when_a_recording_it_starts_at_rest_seems_to_start_warm(tmp_path, plant_data, capsys):
    # diagnose --validate estimates such a recording from its first hour; plain estimate started it at rest and
    # said nothing, so its figures disagreed with the report's without a word (a real lathe's days 14 and 17)
    _, days, _, base = plant_data
    profile = tmp_path / "synthetic.toml"
    profile.write_text(_PROFILE)
    model = save_model(base, tmp_path / "base.model.toml")
    warm = days[3].slice(600, 1440)  # starts mid-work
    path = tmp_path / "warm.csv"
    write_recording(path, time_s=warm.time_s, columns={**warm.factors, "z_um": warm.displacement["z"]})
    rest = _day(3, seed=13, room=False)  # starts after a night at rest, in a steady room
    calm = tmp_path / "calm.csv"
    write_recording(calm, time_s=rest.time_s, columns={**rest.factors, "z_um": rest.displacement["z"]})
    assert main(["estimate", "--profile", str(profile), "--model", str(model), str(path), str(calm), "--json"]) == 0
    notes = {e["recording"]: e["notes"] for e in json.loads(capsys.readouterr().out)}
    (said,) = [n for n in notes[str(path)] if "seems not to start at rest" in n]
    # it works at its first window: taken in equilibrium with it by default, which is neither a machine that has
    # just started nor one warm from an unknown day; the note says what each option does instead
    assert said.startswith("it seems not to start at rest (speed is +")
    assert ("from its rest level at the first window), and is estimated in equilibrium with its first window (as if "
            "it had worked so for ever): --initial reference --initial-state fit estimates its state from its first "
            "hour, as heat since the model's reference levels (what diagnose --validate does)") in said
    assert said.endswith("--initial reference alone starts it cold at those levels, right only for a machine that has "
                         "just started")
    assert not any("seems not to start at rest" in n for n in notes[str(calm)])
    figures = {}
    for opts in ([], ["--initial", "reference"], ["--initial", "reference", "--initial-state", "fit"]):
        assert main(["estimate", "--profile", str(profile), "--model", str(model), str(path), "--json", *opts]) == 0
        (figures[len(opts)],) = json.loads(capsys.readouterr().out)
    assert figures[2]["notes"][-1].endswith("is estimated from rest: --initial-state fit estimates its initial "
                                            "state from its first hour")
    assert not any("seems not to start at rest" in n for n in figures[4]["notes"])


def test_a_recording_cut_mid_work_is_estimated_from_the_state_its_first_hour_shows(tmp_path, sim_csv_dir, capsys):
    # the bundled production day, cut while the machine works: started at rest the model misses the heat already
    # in it by tens of micrometres for hours; --initial-state fit takes the state a heat history of the inputs
    # leaves, fitted on the first hour over every axis, and carries it on (a free decay per axis fitted to the
    # hour extrapolated 28-44 % of the rest-start error here)
    day = _bundled_day(sim_csv_dir)
    cuts = [str(_write_part(day, hour, tmp_path / f"from-{hour}h.csv")) for hour in (10, 14)]
    whole = str(sim_csv_dir / "production-day.csv")
    figures = {}
    for state in ("rest", "fit"):
        assert main(["estimate", "--profile", "sim-vmc", *cuts, whole, "--json", "--initial-state", state]) == 0
        figures[state] = {e["recording"]: e for e in json.loads(capsys.readouterr().out)}
    # the whole day starts after a night at rest: fitted all the same when asked, but not called a warm start
    (said,) = [n for n in figures["fit"][whole]["notes"] if "held before the start" in n]
    assert ": yet the recording seems to start at rest (by the check estimate makes of a start at rest): the state " \
           "may only follow noise" in said, said
    for path in cuts:
        fit, rest = figures["fit"][path], figures["rest"][path]
        (said,) = [n for n in fit["notes"] if "the state the model's inputs leave when held before the start" in n]
        assert ": the recording does not start at rest; that hour scores the fit" in said, said
        for a in ("y", "z"):  # the axes the spindle's heat moves by micrometres
            assert rest["axes"][a]["rms_um"] > 5.0, (path, a, rest["axes"][a])
            assert fit["axes"][a]["rms_um"] < 0.2 * rest["axes"][a]["rms_um"], (path, a, fit["axes"][a])
        assert fit["axes"]["x"]["rms_um"] < 1.0  # x barely moves: it stays within a micrometre


def test_a_recording_that_rests_at_its_start_while_it_cools_is_said_not_to_start_at_rest(tmp_path, sim_csv_dir,
                                                                                          capsys):
    # the bundled production day cut at noon starts with 45 idle minutes in which z falls 11 um as the machine
    # cools; over the whole first hour the next job's heat hid that, and estimate said nothing (33 um RMS off)
    day = _bundled_day(sim_csv_dir)
    path = _write_part(day, 12, tmp_path / "from-noon.csv")
    assert main(["estimate", "--profile", "sim-vmc", str(path), str(sim_csv_dir / "production-day.csv"),
                 "--json"]) == 0
    notes = {e["recording"]: e["notes"] for e in json.loads(capsys.readouterr().out)}
    (said,) = [n for n in notes[str(path)] if "seems not to start at rest" in n]
    assert re.search(r"axis [xyz] moves [\d.]+ um while it rests at the start where the model, started at rest, "
                     r"predicts [\d.e+-]+ um", said), said
    # the whole day starts after a night at rest: nothing said
    assert not any("seems not to start at rest" in n for n in notes[str(sim_csv_dir / "production-day.csv")])


def test_a_recording_cut_in_a_pause_between_jobs_is_said_not_to_start_at_rest(tmp_path, sim_csv_dir, capsys):
    # the bundled production day cut at 10 h starts in a pause of three idle windows, and the next job's heat hides
    # the cooling in how far the axes move: unflagged, estimated 22 um RMS off from rest on z (1 um fitted)
    day = _bundled_day(sim_csv_dir)
    path = _write_part(day, 10, tmp_path / "from-10h.csv")
    assert main(["estimate", "--profile", "sim-vmc", str(path), "--json"]) == 0
    (rest,) = json.loads(capsys.readouterr().out)
    (said,) = [n for n in rest["notes"] if "seems not to start at rest" in n]
    m = re.search(r"axis ([xyz]): started at rest, the model misses its first hour by ([\d.]+) um RMS; the state a "
                  r"heat history leaves follows it to ([\d.]+) um", said)
    assert m, said
    assert float(m[2]) > 1.0, said
    assert float(m[3]) < float(m[2]) / 3, said
    # ... and what it points to does what it says: the fitted start follows the day on the axis it named
    assert main(["estimate", "--profile", "sim-vmc", str(path), "--json", "--initial-state", "fit"]) == 0
    (fit,) = json.loads(capsys.readouterr().out)
    assert fit["axes"][m[1]]["rms_um"] < 0.3 * rest["axes"][m[1]]["rms_um"], (fit["axes"], rest["axes"])
    # ... and so it is with a noisier sensor (0.3 um: at 6x the noise, half of such files went unflagged; now 4x)
    part = day.slice(round(10 * 3600 / day.period_s), len(day))
    for seed in (1, 2, 3):
        rng = np.random.default_rng(seed)
        noisy = tmp_path / f"from-10h-noisy-{seed}.csv"
        write_recording(noisy, time_s=part.time_s, columns={**part.factors, **{
            f"{a}_um": v + 0.3 * rng.standard_normal(len(v)) for a, v in part.displacement.items()}})
        assert main(["estimate", "--profile", "sim-vmc", str(noisy), "--json"]) == 0
        (e,) = json.loads(capsys.readouterr().out)
        assert any("seems not to start at rest" in n for n in e["notes"]), (seed, e["notes"])


def test_estimate_says_when_a_recording_follows_another_it_was_given_with(tmp_path, sim_csv_dir, capsys):
    # the day written as two files, the second starting one window after the first ends: estimated on its own,
    # from rest, as it must be without --history, but said (diagnose --validate carries such a one)
    day = _bundled_day(sim_csv_dir)
    first = day.slice(0, round(10 * 3600 / day.period_s))
    head = tmp_path / "to-10h.csv"
    write_recording(head, time_s=first.time_s, columns={**first.factors, **{f"{a}_um": v for a, v in
                                                                           first.displacement.items()}})
    tail = _write_part(day, 10, tmp_path / "from-10h.csv")
    assert main(["estimate", "--profile", "sim-vmc", str(head), str(tail), "--json"]) == 0
    notes = {e["recording"]: e["notes"] for e in json.loads(capsys.readouterr().out)}
    assert f"it starts one window after {head} ends, yet is estimated on its own: --history {head} starts it in the " \
           "state that one left" in notes[str(tail)]
    assert not any("starts one window after" in n for n in notes[str(head)])
    assert main(["estimate", "--profile", "sim-vmc", "--history", str(head), str(tail), "--json"]) == 0
    (e,) = json.loads(capsys.readouterr().out)
    assert not any("starts one window after" in n for n in e["notes"])
    assert f"started in the state {head} left (its 600 windows run first)" in e["notes"]
    # following the hint with the first file kept among the recordings: said, not "ends ... not before it starts"
    assert main(["estimate", "--profile", "sim-vmc", "--history", str(head), str(head), str(tail)]) == 2
    assert (f"--history {head}: the same data as the recording {head}: a history runs before the recordings (give "
            "it only after --history)") in capsys.readouterr().err
    # a history that ends hours before: the gap note's hours count from the history's start, said so
    early = tmp_path / "to-6h.csv"
    write_recording(early, time_s=first.time_s[:360], columns={
        **{k: v[:360] for k, v in first.factors.items()}, **{f"{a}_um": v[:360] for a, v in first.displacement.items()}})
    assert main(["estimate", "--profile", "sim-vmc", "--history", str(early), str(tail), "--json"]) == 0
    (e,) = json.loads(capsys.readouterr().out)
    assert any(n.startswith("240 missing window(s) in 1 gap(s) (the longest: 240 windows from 6 h)") for n in e["notes"])
    assert (f"started in the state {early} left (its 360 windows run first; it ends 4 h before this one starts, and "
            "the hours in the gap note count from its start)") in e["notes"]
    # ... and one that ends while the machine works: the gap policy holds that work over the gap, said
    busy = tmp_path / "to-8h.csv"
    write_recording(busy, time_s=first.time_s[:480], columns={
        **{k: v[:480] for k, v in first.factors.items()}, **{f"{a}_um": v[:480] for a, v in first.displacement.items()}})
    assert first.factors["spindle_speed"][479] > 0
    assert main(["estimate", "--profile", "sim-vmc", "--history", str(busy), str(tail), "--json"]) == 0
    (e,) = json.loads(capsys.readouterr().out)
    (said,) = [n for n in e["notes"] if n.startswith(f"started in the state {busy} left")]
    assert re.search(r"; it ends 2 h before this one starts, .*; \w+ is \+[\d.]+ \S+ from its rest level at the last "
                     r"window, and the gap policy hold keeps it so over the gap: --gap-policy reference takes the "
                     r"machine idle there\)$", said), said


def test_an_hour_of_noise_a_spike_and_a_step_at_rest_is_not_taken_for_a_warm_start(tmp_path, sim_csv_dir, capsys):
    # two windows of noise 3.5 sigma apart, one up, one down, spread the hour 7 sigma: the raw spread said "moves
    # 0.7 um in the first hour where the model predicts 0 um" of a machine that rests all along (41 of 686 bench
    # recordings that start at rest said so)
    day = _bundled_day(sim_csv_dir)
    night = day.slice(0, 300)
    assert all(np.ptp(v) == 0 for v in night.factors.values())  # the machine rests over these 5 h
    rng = np.random.default_rng(5)
    measured = {f"{a}_um": 0.05 * rng.standard_normal(len(night)) for a in night.displacement}
    measured["z_um"][[20, 40]] += (0.35, -0.35)
    measured["x_um"][30] += 3.0  # and one spike of a sensor (a running mean of 5 windows still moved 0.6 um)
    measured["y_um"][45:] += 5.0  # and a sensor knocked at 45 min: a step of 5 um in one window, not heat
    path = tmp_path / "night.csv"
    write_recording(path, time_s=night.time_s, columns={**night.factors, **measured})
    assert main(["estimate", "--profile", "sim-vmc", str(path), "--json"]) == 0
    (e,) = json.loads(capsys.readouterr().out)
    assert e["axes"]["z"]["rms_um"] > 0.05  # the spikes are there
    assert not any("seems not to start at rest" in n for n in e["notes"]), e["notes"]
