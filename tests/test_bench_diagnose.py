"""bench/diagnose.py's scenario builder: the concealed effect acts in the identification experiments too."""

from __future__ import annotations

import dataclasses
import importlib.util
import sys

import pytest
from tests_paths import ROOT

from simulators.machine.scenario import parse_scenario_text


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("bench_diagnose", ROOT / "bench" / "diagnose.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up
    try:
        spec.loader.exec_module(module)
        yield module
    finally:
        del sys.modules[spec.name]


def _parse(plan):
    return {name: parse_scenario_text(text, source=name) for part in (plan.experiments, plan.days, plan.fresh)
            for name, text in part.items()}


def test_the_effect_is_in_every_identification_experiment_and_day(bench):
    plan = _parse(bench.new_plan("eddy loss", 2))
    assert len(plan) == 9 + 4 + 1
    for name, sc in plan.items():
        assert sc.effects.enabled == ("eddy_loss",), name
        assert sc.effects.eddy_loss.loss_w_at_1000rpm == 15.0
        assert sc.variant == 2, name
    # the experiments keep the paper's schedules
    one = plan["exp-spindle-1000rpm"]
    assert [(s.duration_s, s.spindle_rpm) for s in one.segments] == [(3600.0, (1000.0,))]
    assert one.duration_h == 12.0


def test_the_room_keeps_its_time_of_day_in_each_experiment(bench):
    plan = _parse(bench.new_plan("room recorded", 1))
    exps = [sc for name, sc in plan.items() if name.startswith("exp-")]
    peaks = {round(sc.effects.room_cycle.peak_at_h, 3) for sc in exps}
    assert len(peaks) == 9  # each experiment starts at its own time of day
    assert all(0.0 <= p < 24.0 for p in peaks)
    for sc in plan.values():  # stamped with clock times consistent with the room: warmest at 15:00
        hour_of_start = (sc.start_time_s - bench.EPOCH0_S) % 86400 / 3600.0
        assert (hour_of_start + sc.effects.room_cycle.peak_at_h) % 24.0 == pytest.approx(15.0, abs=1e-3)
    assert all(sc.room.thermometer for sc in plan.values())
    assert plan["day1"].effects.room_cycle.peak_at_h == 15.0  # days run from midnight, warmest at 15:00
    assert plan["day1"].effects.room_cycle.drift_k_per_h == 0.02
    # the same room with the thermometer on the production days only
    days_only = _parse(bench.new_plan("room recorded on days", 1))
    assert {n for n, sc in days_only.items() if sc.room.thermometer} == {"day1", "day2", "day3", "day4", "fresh"}
    assert all(days_only[n].effects == sc.effects for n, sc in plan.items())


def test_schedules_and_noise_depend_on_the_variant_not_the_effect(bench):
    a, b = _parse(bench.new_plan("cabinet", 3)), _parse(bench.new_plan("none", 3))
    assert a.keys() == b.keys()
    for name, sc in a.items():
        assert sc.effects.enabled == ("cabinet",)
        assert b[name].effects.enabled == ()
        assert dataclasses.replace(sc, effects=b[name].effects) == b[name], name
    room, none = _parse(bench.new_plan("room not recorded", 3)), b
    for name, sc in room.items():  # the room's tables and weather aside, the same recordings
        assert dataclasses.replace(sc, effects=none[name].effects, room=none[name].room) == none[name], name
    other = _parse(bench.new_plan("none", 4))
    assert other["fresh"].segments != b["fresh"].segments
    assert other["fresh"].seed != b["fresh"].seed


def test_the_cabinet_followed_advice_case_is_the_cabinet_case_with_its_thermometer(bench):
    """The report's advice followed: the same recordings, a thermometer in the cabinet, the column allowed."""
    cab, rec = _parse(bench.new_plan("cabinet", 2)), _parse(bench.new_plan("cabinet recorded", 2))
    assert cab.keys() == rec.keys()
    for name, sc in rec.items():
        assert sc.effects.cabinet.thermometer
        assert not cab[name].effects.cabinet.thermometer
        assert dataclasses.replace(sc.effects.cabinet, thermometer=False) == cab[name].effects.cabinet
        assert dataclasses.replace(sc, effects=cab[name].effects) == cab[name], name
    assert bench.EFFECTS["cabinet recorded"].use_signals == ("cabinet_c",)
    assert bench.is_family("recorded_signal:cabinet_c on z", bench.EFFECTS["cabinet recorded"].families)


def test_the_sensor_step_is_in_one_experiment_and_two_days_never_the_fresh_day(bench):
    plan = _parse(bench.new_plan("sensor step", 1))
    stepped = sorted(n for n, sc in plan.items() if sc.effects.sensor_artefacts is not None)
    assert len([n for n in stepped if n.startswith("exp-")]) == 1
    assert len([n for n in stepped if n.startswith("day")]) == 2
    assert "fresh" not in stepped
    for n in stepped:
        sa = plan[n].effects.sensor_artefacts
        assert sa.step_um == (0.0, 0.0, 2.0)
        assert 0.0 < sa.step_at_h < plan[n].duration_h


def test_accepted_names_are_read_from_the_written_model_info(bench, tmp_path):
    (tmp_path / "m.diagnosed.model.toml").write_text(
        '[info.diagnosis]\naccepted = ["dead_time:coolant:spindle_speed on y, z", "cabinet on z"]\n'
        'artefacts_excluded = ["step on z at 3.00 h in day1"]\nindistinguishable = ["cabinet ~ spindle_i1_sq"]\n')
    (tmp_path / "report.md").write_text("## Conclusions\n\n- nothing significant is missing: ...\n")
    names = bench.diagnosis_names(tmp_path)
    assert names.accepted == ["dead_time:coolant:spindle_speed on y, z", "cabinet on z"]
    assert names.artefacts == ["step on z at 3.00 h in day1"]
    assert names.nothing_missing
    assert [bench.family(n) for n in names.accepted] == ["dead_time", "cabinet"]
    assert names.indistinguishable == ["cabinet ~ spindle_i1_sq"]


def test_the_model_complete_cases_are_the_no_effect_recordings_with_the_drag_heat_taken_out(bench):
    for name, ref in (("complete", "none"), ("complete b", "none b")):
        plan, none = _parse(bench.new_plan(name, 5)), _parse(bench.new_plan(ref, 5))
        assert plan.keys() == none.keys()
        for rec, sc in plan.items():  # every recording, experiments included; schedules and noise the same
            assert sc.viscous_drag_scale == 0.01, rec
            assert none[rec].viscous_drag_scale == 1.0, rec
            assert dataclasses.replace(sc, viscous_drag_scale=1.0) == none[rec], rec
    assert bench.EFFECTS["complete"].complete
    assert not bench.EFFECTS["none"].complete
    old = _parse(bench.old_plan("complete b", 1))
    assert {sc.viscous_drag_scale for sc in old.values()} == {0.01}


def test_more_production_days_keep_the_first_four_and_move_the_fresh_day_after_the_last(bench):
    four, seven = bench.new_plan("preload", 3), bench.new_plan("preload", 3, n_days=7)
    assert four == bench.new_plan("preload", 3, n_days=4)  # the default draws what it always did
    assert list(seven.days) == [f"day{d}" for d in range(1, 8)]
    assert {k: seven.days[k] for k in four.days} == four.days  # the first four days unchanged
    assert seven.experiments == four.experiments
    starts = {n: parse_scenario_text(t, source=n).start_time_s for n, t in {**seven.days, **seven.fresh}.items()}
    assert starts["fresh"] > max(starts[f"day{d}"] for d in range(1, 8))  # nothing fitted comes after it
    assert starts["fresh"] - starts["day7"] == 2 * 86400  # two dates after the last, as with four days


def test_the_summary_separates_what_the_signals_cannot_name_from_the_rest(bench):
    fresh = {"x": 0.2, "y": 0.5, "z": 2.0}
    none = bench.Row(protocol="new", effect="none", variant=1, before=fresh, after=fresh)
    moved = {"x": 0.2, "y": 0.5, "z": 6.0}
    cabinet = bench.Row(protocol="new", effect="cabinet", variant=1, before=moved, after=fresh,
                        indistinguishable=["cabinet ~ spindle_i1_sq"])
    slow = bench.Row(protocol="new", effect="slow mode", variant=1, before=moved, after=fresh,
                     accepted=["eddy_loss:spindle_speed on z"])
    named = bench.Row(protocol="new", effect="slow mode", variant=2, before=moved, after=fresh,
                      accepted=["slow_mode:spindle_speed on z"])
    refs = {1: none, 2: dataclasses.replace(none, variant=2)}
    verdicts = [bench.judge(r, refs[r.variant]) for r in (none, refs[2], cabinet, slow, named)]
    lines = bench.summary(verdicts, protocol="new")
    assert "named (right family) 1/3" in lines[0]
    missed = [ln for ln in lines if ln.strip().startswith("not named:")]
    assert missed == ["  not named: 2; of them said indistinguishable from a factor's path (the signals cannot name "
                      "it) 1; the rest: slow mode v1"]


@pytest.mark.plumbing
def test_a_day_without_one_axis_beside_full_days_is_diagnosed(bench, tmp_path, sim_csv_dir, capsys):
    # a production day whose file has no y_um (its sensor off): y had fewer held-out blocks than x and z, and
    # pooling their per-block figures in the check of what passes with the paths held died (ValueError:
    # operands could not be broadcast together with shapes (24,) (21,))
    import json

    from sim_shared import SIM_EXPERIMENTS

    from gateway.cli import main
    from gateway.recording import write_recording
    from simulators.machine import simulate

    text = list(bench.new_plan("none", 1, 4).days.values())[1]
    rec = simulate(parse_scenario_text(text, source="day2")).recording()
    path = tmp_path / "day2-no-y.csv"
    write_recording(path, time_s=rec.time_s, columns={**rec.factors, "x_um": rec.displacement["x"],
                                                      "z_um": rec.displacement["z"]})
    exps = [str(sim_csv_dir / f"{n}.csv") for n in SIM_EXPERIMENTS]
    assert main(["diagnose", "--profile", "sim-vmc", *exps, str(sim_csv_dir / "production-day.csv"), str(path),
                 "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    held = doc["held_out"]["before"]
    assert 0 < held["y"]["windows"] < held["x"]["windows"] == held["z"]["windows"]  # y judged where it is measured
    assert not any("nan" in c for c in doc["conclusions"])
