"""Coverage: the factor region a model's identification data covered, stored in the model file, and what
estimate, the live estimator and diagnosis say when a recording leaves it."""

from __future__ import annotations

import math
from dataclasses import replace
from types import MappingProxyType

import numpy as np
import pytest

from gateway.errors import ModelError
from gateway.live.tracking import DisplacementTracker
from gateway.model import PathTF, ThermalModel, load_model, model_to_toml
from gateway.model.coverage import (
    Coverage,
    Ratio,
    beyond_coverage,
    check_coverage,
    co_varying_pairs,
    coverage_of,
    describe_coverage,
)
from gateway.model.inputs import Column
from gateway.model.terms import FirstOrder
from gateway.profile.live import Live
from gateway.recording import Recording
from gateway.replay import estimate
from gateway.windows import ChannelStats, DeviceQuality, WindowRecord

FACTORS = ("speed", "i1_sq", "feed")


def spindle_run(rpm: float, i1_per_rpm: float, *, n: int = 120, on: tuple[int, int] = (10, 70)) -> np.ndarray:
    """Deviations of a run: the spindle at ``rpm`` for windows ``on`` with the current following it."""
    du = np.zeros((3, n))
    du[0, on[0]: on[1]] = rpm
    du[1, on[0]: on[1]] = rpm * i1_per_rpm
    return du


def feed_run(mm_min: float, n: int = 120) -> np.ndarray:
    du = np.zeros((3, n))
    du[2, 10:70] = mm_min
    return du


def test_ranges_and_ratios_of_factors_that_move_together():
    cov = coverage_of([spindle_run(1000, 0.2), spindle_run(500, 0.4), feed_run(3000)], FACTORS, source="3 runs")
    assert cov.ranges == {"speed": (0.0, 1000.0), "i1_sq": (0.0, 200.0), "feed": (0.0, 3000.0)}
    # speed and current move in the same runs, the feed in another: one ratio
    assert cov.ratios == (Ratio(of="i1_sq", per="speed", low=pytest.approx(0.2), high=pytest.approx(0.4)),)
    moving = np.array([[True, True, False], [True, True, False], [False, False, True]])
    assert co_varying_pairs(FACTORS, moving) == [("i1_sq", "speed")]


def test_check_names_factor_how_far_and_how_long():
    cov = coverage_of([spindle_run(1000, 0.2), spindle_run(500, 0.4)], FACTORS)
    # 3000 rpm with the current of field weakening (a fifth of the covered current per rpm) for 40 windows
    day = spindle_run(3000, 0.04, n=200, on=(50, 90))
    check = check_coverage(cov, day, FACTORS, {"speed": "rpm", "i1_sq": "A^2"})
    assert check.windows_outside == 40
    assert check.outside[50]
    assert check.outside[89]
    assert not check.outside[49]
    assert not check.outside[90]
    by = {(e.what, e.side): e for e in check.excursions}
    speed = by[("speed", "above")]
    assert (speed.value, speed.bound, speed.windows, speed.longest, speed.first) == (3000.0, 1000.0, 40, 40, 50)
    ratio = by[("i1_sq per speed", "below")]
    assert ratio.value == pytest.approx(0.04)
    assert ratio.bound == pytest.approx(0.2)
    text = ratio.describe(60.0)
    assert "i1_sq per speed (ratio) below coverage: down to 0.04 A^2/rpm, 0.2x the lowest covered (0.2 A^2/rpm)" in text
    assert "40 windows (40 min), longest stretch 40 min, first at window 51" in text
    assert check.window_reason(60) == "speed above; i1_sq per speed below"
    # within the margin (20 % of the range, a factor 1.2 on a ratio) nothing is flagged
    near = check_coverage(cov, spindle_run(1150, 0.18), FACTORS)
    assert near.windows_outside == 0
    assert near.excursions == ()


def test_a_factor_the_identification_never_moved_leaves_coverage_as_soon_as_it_moves():
    cov = coverage_of([spindle_run(1000, 0.2)], FACTORS)
    assert cov.ranges["feed"] == (0.0, 0.0)
    check = check_coverage(cov, feed_run(100.0), FACTORS)
    assert [(e.what, e.side, e.windows) for e in check.excursions] == [("feed", "above", 60)]


def small_model(coverage: Coverage | None) -> ThermalModel:
    paths = [PathTF(axis="z", factor=f, terms=(FirstOrder(gain=-0.01, tau_s=1800.0),)) for f in FACTORS]
    return ThermalModel(axes=("z",), factors=FACTORS, units={"speed": "rpm", "i1_sq": "A^2", "feed": "mm/min"},
                        reference={"speed": 0.0, "i1_sq": 4.0, "feed": 0.0},
                        paths={(p.axis, p.factor): p for p in paths}, coverage=coverage)


def test_how_far_beyond_is_zero_inside_and_grows_in_proportion_outside():
    # covered to 1000 rpm with 0.01 A^2 per rpm; production at 3000 rpm with the current following the speed
    # (i1_sq grows as speed^2 there: 9x its covered highest); the flag is 20 % past the covered span
    cov = coverage_of([spindle_run(1000.0, 1e-2)], FACTORS)
    du = np.zeros((3, 4))
    du[0] = [500.0, 1200.0, 3000.0, 3000.0]
    du[1] = [5.0, 12.0, 30.0, 90.0]
    far = beyond_coverage(cov, du, FACTORS)
    assert far.shape == (3, 4)
    np.testing.assert_array_equal(far[:, :2], 0.0)  # inside, and at the flag itself
    assert far[0, 2] == pytest.approx(math.log(1.0 + 2.0 - 0.2))  # 3x the covered speed: 1.8 spans past the flag
    # 9x the covered current^2 lies 7.8 spans past the flag, 4.3x as far as the speed; in log 2.1x (an
    # extrapolating gain error grows in proportion, not with the span)
    assert far[1, 3] == pytest.approx(math.log(1.0 + 9.0 - 1.0 - 0.2))
    assert far[1, 3] / far[0, 2] < 2.2
    # the ratio current^2 / speed at 3x its covered value (2.5x the flag) reaches the speed too: log 2.5
    du2 = np.array([[1000.0], [30.0], [0.0]])
    assert beyond_coverage(cov, du2, FACTORS)[0, 0] == pytest.approx(math.log(2.5))
    np.testing.assert_array_equal(far[2], 0.0)  # the feed stayed where it was


def test_model_file_round_trip_and_bad_values_named_by_line_and_key(tmp_path):
    cov = coverage_of([spindle_run(1000, 0.2), spindle_run(500, 0.4), feed_run(3000)], FACTORS, source="3 runs")
    model = small_model(cov)
    text = model_to_toml(model)
    assert '"i1_sq/speed" = [' in text
    assert load_model("m.toml", text=text) == model
    bad = (text.replace("speed = [\n    0.0,\n    1000.0,\n]", "speed = [\n    1000.0,\n    0.0,\n]")
           .replace('"i1_sq/speed"', '"i1_sq/spede"').replace("on_share = 0.1", "on_share = 0.0"))
    assert bad != text
    with pytest.raises(ModelError) as err:
        load_model("m.toml", text=bad)
    msg = str(err.value)
    assert "coverage.range.speed: expected [lowest, highest] deviation" in msg
    assert "got [1000.0, 0.0]" in msg
    assert 'coverage.ratio.i1_sq/spede: expected a key "of/per" naming two different factors' in msg
    assert "coverage.on_share: expected the share of its highest deviation" in msg
    assert all(line.startswith("m.toml:") for line in msg.splitlines())
    with pytest.raises(ModelError, match=r"coverage\.range\.torque: not a factor of this model"):
        load_model("m.toml", text=text.replace("[coverage.range]\n", "[coverage.range]\ntorque = [0.0, 1.0]\n"))


def test_estimate_flags_the_windows_outside_and_says_why(tmp_path):
    cov = coverage_of([spindle_run(1000, 0.2), spindle_run(500, 0.4)], FACTORS)
    model = small_model(cov)
    n = 200
    du = spindle_run(3000, 0.04, n=n, on=(50, 90))
    rec = Recording(source="day.csv", period_s=60.0, time_s=60.0 * np.arange(1, n + 1),
                    present=np.ones(n, dtype=bool),
                    factors={"speed": du[0], "i1_sq": du[1] + 4.0, "feed": du[2]},
                    displacement={"z": np.zeros(n)})
    est = estimate(model, rec)
    assert est.coverage is not None
    assert est.coverage.windows_outside == 40
    assert any(note.startswith("outside the identification's coverage: speed above coverage: up to 3000 rpm, 3x "
                               "the highest covered (1000 rpm); 40 windows (40 min)") for note in est.notes)
    doc = est.to_json()["coverage"]
    assert doc["windows_outside"] == 40
    assert {(e["what"], e["side"], e["longest_s"]) for e in doc["excursions"]} == {
        ("speed", "above", 2400.0), ("i1_sq per speed", "below", 2400.0)}
    csv_lines = [ln for ln in est.to_csv().splitlines() if not ln.startswith("#")]
    head = csv_lines[0].split(",")
    flags = [float(ln.split(",")[head.index("outside_coverage")]) for ln in csv_lines[1:]]
    assert sum(flags) == 40
    assert flags[50] == 1.0
    assert flags[49] == 0.0
    # a model file written before coverage existed: no check, no flag
    assert estimate(small_model(None), rec).coverage is None


def _record(index: int, speed: float, i1_sq: float) -> WindowRecord:
    def stats(v: float) -> ChannelStats:
        return ChannelStats(count=100, coverage=1.0, mean=v, mean_square=v * v, mean_abs=abs(v), min=v, max=v,
                            saturated=0, bad=0)

    device = DeviceQuality(ticks_expected=100, ticks_run=100, ticks_skipped=0, reads_ok=100, reads_failed=0,
                           timeouts=0, off_scan_ticks=0, largest_gap_s=0.01, lateness_max_s=0.0,
                           read_time_max_s=0.001, tick_s=0.01)
    return WindowRecord(index=index, start_s=index * 60.0, end_s=(index + 1) * 60.0, status="good",
                        factors=MappingProxyType({"speed": speed, "i1_sq": i1_sq, "feed": 0.0}),
                        channels=MappingProxyType({"speed": stats(speed), "current": stats(math.sqrt(i1_sq))}),
                        devices=MappingProxyType({"adc": device}))


def test_live_estimator_says_which_windows_leave_coverage():
    cov = coverage_of([spindle_run(1000, 0.2), spindle_run(500, 0.4)], FACTORS)
    est = DisplacementTracker(small_model(cov), window_s=60.0, live=Live())
    inside = est.update(_record(0, 800.0, 4.0 + 800.0 * 0.3))
    outside = est.update(_record(1, 3000.0, 4.0 + 3000.0 * 0.04))
    assert inside.outside_coverage == ""
    assert outside.outside_coverage == "speed 3000 (above the covered 1000); i1_sq per speed 0.04 (below the covered 0.2)"
    assert DisplacementTracker(small_model(None), window_s=60.0, live=Live()).update(
        _record(1, 3000.0, 124.0)).outside_coverage == ""


def test_a_value_far_beyond_anything_identified_is_said_implausible_first():
    # a cell of -1e9 rpm (a glitch) gave z RMS 4e9 um with one routine coverage note among others
    cov = coverage_of([spindle_run(1000, 0.2), spindle_run(500, 0.4)], FACTORS)
    du = spindle_run(3000, 0.04, n=200, on=(50, 90))
    du[0, 120] = -1e9
    check = check_coverage(cov, du, FACTORS, {"speed": "rpm"})
    notes = check.notes(60.0)
    assert notes[0] == ("implausible value: speed reaches -1e+09 rpm (1 windows, first at window 121), 1e+06x the "
                        "width of the covered range beyond it: a glitch or a sentinel value (-9999, 32767; leave such "
                        "a cell empty to make it a gap), or a machine run far beyond anything identified? either way "
                        "the estimate from there on means little")
    # 3000 rpm where 1000 were covered is production beyond the experiments (2 widths beyond), not implausible
    assert sum(n.startswith("implausible") for n in notes) == 1
    assert any(n.startswith("outside the identification's coverage: speed above coverage: up to 3000 rpm") for n in notes)


def test_estimate_says_when_an_axis_is_missing_from_the_file_or_the_file_is_too_short():
    model = small_model(None)
    model = ThermalModel(axes=("x", "z"), factors=model.factors, units=model.units, reference=model.reference,
                         paths={**model.paths, **{("x", f): PathTF(axis="x", factor=f, terms=p.terms)
                                                  for (_, f), p in model.paths.items()}})

    def rec(n: int, axes: tuple[str, ...]) -> Recording:
        return Recording(source="r.csv", period_s=60.0, time_s=60.0 * np.arange(1, n + 1),
                         present=np.ones(n, dtype=bool),
                         factors={"speed": np.full(n, 500.0), "i1_sq": np.full(n, 6.0), "feed": np.zeros(n)},
                         displacement={a: np.zeros(n) for a in axes})

    # z's column missing (renamed, dropped) while x has one: it was estimated and left out of the figures silently
    e = estimate(model, rec(120, ("x",)))
    assert set(e.metrics) == {"x"}
    assert "axis z: not in this file (no displacement column for it, where x has one): estimated, not scored" in e.notes
    assert not any("not in this file" in n for n in estimate(model, rec(120, ("x", "z"))).notes)
    assert not any("not in this file" in n for n in estimate(model, rec(120, ())).notes)  # inputs only: no figures
    # five minutes: "max error 100 % of peak" said nothing, and nothing said so
    short = estimate(model, rec(5, ("x", "z")))
    assert ("only 5 window(s) (5 min): too short for its figures to say anything (diagnose --validate takes at least "
            "10 measured)") in short.notes
    assert not any(n.startswith("only ") for n in estimate(model, rec(10, ("x", "z"))).notes)


def test_estimate_prints_an_implausible_value_as_a_warning(tmp_path, sim_csv_dir, capsys):
    # the bundled production day with one speed cell of -1e9 rpm (a logger's glitch): said first, as a warning
    from gateway.cli import main

    lines = (sim_csv_dir / "production-day.csv").read_text().splitlines()
    head = next(k for k, ln in enumerate(lines) if not ln.startswith("#"))
    names = lines[head].split(",")
    row = head + 700
    cells = lines[row].split(",")
    cells[names.index("spindle_speed")] = "-1e9"
    lines[row] = ",".join(cells)
    glitch = tmp_path / "day.csv"
    glitch.write_text("\n".join(lines) + "\n")
    assert main(["estimate", "--profile", "sim-vmc", str(glitch)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[1].startswith("  warning: implausible value: spindle_speed reaches -1e+09 rpm (1 windows, first at "
                             "window 700)"), out[:3]
    assert all(not ln.startswith("  warning:") for ln in out[2:])


# ------------------------------------------------------------------------ recorded columns (a thermometer) ---
def room_model(room_range: tuple[float, float] | None = (17.5, 22.5)) -> ThermalModel:
    """small_model with a recorded room thermometer as an input, its covered range ``room_range``."""
    cov = coverage_of([spindle_run(1000, 0.2), spindle_run(500, 0.4)], FACTORS)
    if room_range is not None:
        cov = replace(cov, columns={"room_c": room_range})
    base = small_model(cov)
    room = PathTF(axis="z", factor="room", terms=(FirstOrder(gain=1.5, tau_s=3600.0),))
    return replace(base, inputs=(Column(name="room", column="room_c", unit="degC"),),
                   paths={**base.paths, ("z", "room"): room})


def room_day(room_c: np.ndarray) -> Recording:
    n = len(room_c)
    return Recording(source="day.csv", period_s=60.0, time_s=60.0 * np.arange(1, n + 1),
                     present=np.ones(n, dtype=bool),
                     factors={"speed": np.zeros(n), "i1_sq": np.full(n, 4.0), "feed": np.zeros(n)},
                     displacement={"z": np.zeros(n)}, extras={"room_c": np.asarray(room_c, float)})


def test_a_thermometer_in_other_units_than_the_model_was_fitted_in_is_said_implausible():
    # a helper's room thermometer in degF (68 F) on a model fitted in degC raised x's error 0.86 -> 1.24 um without a
    # word: the model takes the column's change from its first window, so the unit showed only in its level
    model = room_model()
    hours = np.arange(600) / 60.0
    celsius = 20.0 + 2.0 * np.sin(2 * np.pi * hours / 24.0)
    assert not [n for n in estimate(model, room_day(celsius)).notes if "room_c" in n]
    notes = estimate(model, room_day(32.0 + 1.8 * celsius)).notes
    assert notes[0].startswith("implausible value: room_c reaches 7"), notes
    assert "in other units than the model was fitted on (22.5 covered; degF for degC?)" in notes[0]
    assert any(n.startswith("outside the identification's coverage: room_c (column) above coverage: up to 7")
               and "above the highest covered (22.5)" in n for n in notes)
    # a summer's hall 5.5 K above anything covered (of width 5 K): outside the coverage, not implausible
    summer = estimate(model, room_day(celsius + 6.0)).notes
    assert not [n for n in summer if n.startswith("implausible")]
    assert any(n.startswith("outside the identification's coverage: room_c (column) above coverage: up to 28") and
               "28, 5.5 above the highest covered (22.5)" in n for n in summer), summer
    # gaps in the thermometer are no excursion; a model file without the column's range checks nothing
    gappy = celsius.copy()
    gappy[100:200] = np.nan
    assert not [n for n in estimate(model, room_day(gappy)).notes if "coverage" in n or "implausible" in n]
    assert not [n for n in estimate(room_model(None), room_day(32.0 + 1.8 * celsius)).notes if "room_c" in n]


def test_a_column_range_round_trips_and_a_column_no_input_reads_is_named(tmp_path):
    model = room_model()
    text = model_to_toml(model)
    assert "[coverage.column]" in text
    assert load_model("m.toml", text=text) == model
    assert any("recorded column room_c: 17.5 .. 22.5" in ln for ln in describe_coverage(model.coverage))
    bad = text.replace("[coverage.column]\n", "[coverage.column]\nhall_c = [10.0, 30.0]\n")
    with pytest.raises(ModelError) as err:
        load_model("m.toml", text=bad)
    assert ("coverage.column.hall_c: not a recorded column an input of this model reads (columns: room_c)"
            in str(err.value))
    upside = text.replace("room_c = [\n    17.5,\n    22.5,\n]", "room_c = [\n    22.5,\n    17.5,\n]")
    assert upside != text
    with pytest.raises(ModelError, match=r"coverage\.column\.room_c: expected \[lowest, highest\] value of the column"):
        load_model("m.toml", text=upside)


def test_live_estimator_says_a_thermometer_reads_implausibly():
    model = room_model()
    est = DisplacementTracker(model, window_s=60.0, live=Live(), channel_names=["speed", "current", "room_c"])

    def window(index: int, room: float) -> WindowRecord:
        rec = _record(index, 0.0, 4.0)
        stats = ChannelStats(count=100, coverage=1.0, mean=room, mean_square=room * room, mean_abs=abs(room),
                             min=room, max=room, saturated=0, bad=0)
        return replace(rec, channels=MappingProxyType({**rec.channels, "room_c": stats}))

    assert est.update(window(0, 20.0)).outside_coverage == ""
    assert est.update(window(1, 68.0)).outside_coverage == (
        "room_c 68 (above the covered 22.5, implausible: other units or a faulty sensor?)")
