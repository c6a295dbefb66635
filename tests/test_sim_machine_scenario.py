"""Scenario files: bundled ones load, bad ones are reported all at once with file, line, key, value, expected."""

from __future__ import annotations

from pathlib import Path

import pytest

from gateway.errors import SimulationError
from simulators.machine.scenario import bundled_scenarios, load_scenario, parse_scenario_text

BAD = """\
[scenario]
name = "bad"
seed = -1
initial_idle_min = 30
duraton_h = 12

[room]
temperature_c = "warm"

[segments.run]
minutes = -5
spindle_rmp = 1000

[segments.alternate]
minutes = 60
spindle_rpm = [400, 600]

[segments.rapid]
minutes = 10
stroke_mm = { x = 100, w = 3 }
feed_mm_min = 90000

[segments.long_stroke]
minutes = 0.01
stroke_mm = { x = 500 }
feed_mm_min = 1000

[effects.eddy_los]
loss_w_at_1000rpm = 5

[effects.room_cycle]
amplitude_k = "big"

[effects.slow_path]
from_node = "colum"
um_per_k = { z = 4, q = 1 }
"""


def test_every_problem_is_reported_with_file_line_key_value_and_expectation(tmp_path: Path):
    path = tmp_path / "bad.toml"
    path.write_text(BAD)
    with pytest.raises(SimulationError) as err:
        load_scenario(path)
    lines = str(err.value).splitlines()
    expected = [
        f"{path}:3: scenario.seed: expected an integer >= 0, got -1 (an integer)",
        f'{path}:5: scenario.duraton_h: unknown key (did you mean "duration_h"?)',
        f'{path}:8: room.temperature_c: expected a number in [-20, 60], got "warm" (a string)',
        f"{path}:11: segments.run.minutes: expected a number in (0, 1e+06], got -5 (an integer)",
        f'{path}:12: segments.run.spindle_rmp: unknown key (did you mean "spindle_rpm"?)',
        f"{path}:14: segments.alternate.changes_per_min: missing: spindle_rpm = [400, 600] alternates, so "
        "expected changes_per_min > 0 as well (the paper's 400/600 rpm run: 350)",
        f"{path}:20: segments.rapid.stroke_mm.w: unknown key (expected one of: x, y, z)",
        f"{path}:21: segments.rapid.feed_mm_min: expected a path feed rate <= 30000 mm/min on this stroke (the "
        "axes' rapid traverse), got 90000 (an integer)",
        f"{path}:24: segments.long_stroke.minutes: expected at least one stroke cycle (60.0067 s there and "
        "back), got 0.01 min",
        f'{path}:28: effects.eddy_los: unknown effect (did you mean "eddy_loss"?): expected one of room_cycle, '
        "eddy_loss, slow_path, cabinet, bearing_preload, coolant_delay, chiller, sensor_artefacts",
        f'{path}:32: effects.room_cycle.amplitude_k: expected a number in [0, 20], got "big" (a string)',
    ]
    for line in expected:
        assert line in lines
    slow = [x for x in lines if "effects.slow_path.from_node" in x]
    assert len(slow) == 1
    assert slow[0].startswith(f"{path}:35: ")
    assert 'got "colum" (a string) (did you mean "column_rear"?)' in slow[0]
    assert f"{path}:36: effects.slow_path.um_per_k.q: unknown key (expected one of: x, y, z)" in lines
    assert len(lines) == len(expected) + 2


def test_schedule_longer_than_the_run_and_partial_windows(tmp_path: Path):
    with pytest.raises(SimulationError, match=r"<scenario>:2: scenario.duration_h: expected at least the "
                                              r"schedule's 1.5 h \(idle \+ segments\), got 1"):
        parse_scenario_text("[scenario]\nduration_h = 1\ninitial_idle_min = 30\n[segments.a]\nminutes = 60\n")
    with pytest.raises(SimulationError, match=r"scenario.duration_h: expected a run of whole 60 s windows"):
        parse_scenario_text("[scenario]\nduration_h = 0.51\n")
    sc = parse_scenario_text("[segments.a]\nminutes = 2.5\nspindle_rpm = 800\n")
    assert sc.duration_s == 180.0  # rounded up to a whole window, at rest
    assert sc.segments[0].end_s == 150.0


def test_strokes_stay_within_the_travel_without_follow_up_errors():
    with pytest.raises(SimulationError) as err:
        parse_scenario_text("[segments.a]\nminutes = 5\nstroke_mm = { y = 500 }\nfeed_mm_min = 1000\n")
    assert str(err.value) == ("<scenario>:3: segments.a.stroke_mm.y: expected a stroke in mm within the Y travel "
                              "of 410 mm (either way), got 500 (an integer)")


def test_unknown_bundled_name_suggests_the_closest():
    with pytest.raises(SimulationError, match=r'no scenario "spindle-100rpm": .* \(did you mean "spindle-1000rpm"\?\)'):
        load_scenario("spindle-100rpm")
    with pytest.raises(SimulationError, match=r"nowhere/x.toml: file not found"):
        load_scenario("nowhere/x.toml")


def test_bundled_scenarios_load_and_cover_the_paper():
    names = bundled_scenarios()
    for required in ("spindle-1000rpm", "spindle-500rpm", "spindle-400-600rpm", "random-spindle",
                     "spindle-feeds", "production-day", *(f"feed-{a}-{k}" for a in "xyz" for k in ("fast", "accel"))):
        assert required in names
    for name in names:
        sc = load_scenario(name)
        assert sc.name == name
        assert sc.description
    ident = [load_scenario(n) for n in names if n.startswith(("spindle-1", "spindle-5", "spindle-4", "feed-"))]
    assert len(ident) == 9  # 9 factors, 9 identification experiments as in the paper
    for sc in ident:
        assert sc.duration_h == 12.0
        assert sc.initial_idle_s == 1800.0
        assert not sc.effects.enabled
    alt = load_scenario("spindle-400-600rpm").segments[0]
    assert alt.spindle_rpm == (400.0, 600.0)
    assert alt.changes_per_min == 350.0
    feeds = load_scenario("spindle-feeds").segments
    assert feeds[0].stroke_mm == (120.0, 160.0, 0.0)
    assert feeds[0].feed_mm_min == 6000.0
    assert feeds[2].stroke_mm == (71.0, 71.0, 0.0)
    assert load_scenario("production-day").duration_h == 24.0
    assert load_scenario("production-day").room.thermometer


def test_scenario_by_path_and_effect_switch(tmp_path: Path):
    path = tmp_path / "mine.toml"
    path.write_text("[segments.a]\nminutes = 1\n[effects.chiller]\nenabled = false\n[effects.eddy_loss]\n")
    sc = load_scenario(str(path))
    assert sc.name == "mine"
    assert sc.effects.enabled == ("eddy_loss",)
    assert sc.effects.eddy_loss.loss_w_at_1000rpm == 15.0
    assert sc.effects.cabinet is None


def test_a_thermometer_switch_that_is_not_true_or_false_is_named(tmp_path: Path):
    path = tmp_path / "cab.toml"
    path.write_text("[segments.a]\nminutes = 1\n[effects.cabinet]\nthermometer = 1\n")
    with pytest.raises(SimulationError) as err:
        load_scenario(str(path))
    assert f"{path}:4: effects.cabinet.thermometer: expected true or false, got 1 (an integer)" in str(err.value)
    path.write_text("[segments.a]\nminutes = 1\n[effects.cabinet]\nthermometer = true\n")
    assert load_scenario(str(path)).effects.cabinet.thermometer is True
