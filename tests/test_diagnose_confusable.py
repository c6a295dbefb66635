"""A mechanism whose input one factor carries is said to be indistinguishable, not named: the cabinet case.

The control cabinet's heat is the sum of every amplifier's current squared. In a job shop's days the
spindle's current is nearly all of it (the feed axes' currents are small and follow the same jobs), so a
slower mode on the spindle current's path does what the cabinet would, and no fit can tell them apart:
diagnosis says so, and what would tell them apart. Once the feed axes run hard for hours with the spindle at
rest, the cabinet's input is no longer the spindle's, and nothing is said. Eddy loss (speed^2) stays
distinguishable from the speed on the same days. A recorded thermometer of the cabinet's air, which on those
days only follows the spindle current late, is said to be indistinguishable too; a room thermometer that
varies for reasons of its own is not. Fast (under a second).
"""

from __future__ import annotations

import numpy as np

from gateway.diagnose.confusable import CONFUSED_SHARE, confusions, unexplained_share
from gateway.diagnose.data import build_stack, lag
from gateway.diagnose.hypotheses import FactorInfo, catalogue
from gateway.model import FirstOrder, PathTF, ThermalModel
from gateway.recording import Recording

F = ("spindle_speed", "spindle_i1_sq", "x_i_sq", "y_i_sq")
INFOS = [FactorInfo(name="spindle_speed", unit="rpm"), FactorInfo(name="spindle_i1_sq", unit="A^2", stat="mean_square"),
         FactorInfo(name="x_i_sq", unit="A^2", stat="mean_square"),
         FactorInfo(name="y_i_sq", unit="A^2", stat="mean_square")]
MODEL = ThermalModel(axes=("z",), factors=F, units={f.name: f.unit for f in INFOS}, reference={}, paths={
    ("z", f): PathTF(axis="z", factor=f, terms=(FirstOrder(gain=0.01, tau_s=1800.0),)) for f in F})


def _recording(name: str, speed: np.ndarray, load: np.ndarray, x_i_sq: np.ndarray, *, seed: int) -> Recording:
    rng = np.random.default_rng(seed)
    n = len(speed)
    spindle = 2.0 + load * (speed > 0)  # the spindle's current follows the cut's torque, not its speed
    return Recording(source=f"{name}.csv", period_s=60.0, time_s=60.0 * np.arange(1, n + 1),
                     present=np.ones(n, dtype=bool),
                     factors={"spindle_speed": speed, "spindle_i1_sq": spindle, "x_i_sq": x_i_sq,
                              "y_i_sq": 0.5 * x_i_sq + 0.01 * rng.standard_normal(n)},
                     displacement={"z": 0.1 * rng.standard_normal(n)})


def _day(day: int) -> Recording:
    """A job shop's day: jobs at 800-3000 rpm; the feed axes' currents small, moving with the jobs."""
    rng = np.random.default_rng(day)
    speed, load = np.zeros(1440), np.zeros(1440)
    k = int(rng.integers(360, 480))
    while k < 1320:
        m = int(rng.integers(20, 90))
        speed[k:k + m] = rng.choice([0.0, 800.0, 1500.0, 3000.0])
        load[k:k + m] = rng.uniform(5.0, 100.0)
        k += m
    x_i_sq = 0.5 * (speed > 0) + 0.02 * rng.standard_normal(1440)
    return _recording(f"day{day}", speed, load, x_i_sq, seed=day)


def _axes_alone() -> Recording:
    """The feed axes run hard for 8 h with the spindle at rest."""
    x_i_sq = np.zeros(720)
    x_i_sq[60:540] = 40.0
    return _recording("exp-feed-x", np.zeros(720), np.zeros(720), x_i_sq, seed=7)


def _with_column(rec: Recording, name: str, values: np.ndarray) -> Recording:
    return Recording(source=rec.source, period_s=rec.period_s, time_s=rec.time_s, present=rec.present,
                     factors=rec.factors, displacement=rec.displacement, extras={name: values})


def _cabinet_thermometer(rec: Recording) -> Recording:
    """The cabinet air: 25 C plus its amplifiers' heat through a 40 min lag, read to 0.05 C."""
    stack = build_stack(MODEL, [rec])
    heat = sum(stack.du[f] for f in ("spindle_i1_sq", "x_i_sq", "y_i_sq"))
    noise = 0.05 * np.random.default_rng(11).standard_normal(len(heat))
    return _with_column(rec, "cabinet_c", 25.0 + 0.05 * stack.response(heat, lag(2400.0)) + noise)


def _room_thermometer(rec: Recording, day: int) -> Recording:
    """The hall: a daily cycle and that day's weather, whatever the machine does."""
    h = rec.time_s / 3600.0
    return _with_column(rec, "room_c", 20.0 + 2.0 * np.sin(2 * np.pi * (h - 9.0) / 24.0) + 0.3 * day + 0.05 * h)


def _confused(recordings: list[Recording]) -> dict[str, object]:
    stack = build_stack(MODEL, recordings)
    return {c.key: c for c in confusions(stack, catalogue(stack, MODEL, INFOS))}


def test_the_cabinet_is_said_indistinguishable_from_the_spindle_current_on_job_shop_days():
    found = _confused([_day(d) for d in range(1, 5)])
    assert set(found) == {"cabinet"}, found  # eddy loss, preload, chiller: their inputs are their own
    c = found["cabinet"]
    assert c.factor == "spindle_i1_sq"
    assert c.unexplained < CONFUSED_SHARE
    line = c.line()
    assert "cannot name it" in line
    assert "follows spindle_i1_sq" in line
    assert "cabinet's air temperature" in line
    assert "is not established" in c.line(accepted=True)


def test_the_feed_axes_run_alone_tell_the_cabinet_apart():
    assert _confused([*(_day(d) for d in range(1, 5)), _axes_alone()]) == {}


def test_unexplained_share():
    t = np.linspace(0.0, 10.0, 500)
    assert unexplained_share(3.0 * np.sin(t) + 2.0, np.sin(t)) < 1e-12
    assert unexplained_share(np.sin(t), np.zeros_like(t)) == 1.0  # a flat factor carries nothing
    assert 0.45 < unexplained_share(np.sin(t) + np.cos(t), np.sin(t)) < 0.55
    gap = np.sin(t)
    gap[100:120] = np.nan  # an open gap counts for neither, never as "carried"
    assert unexplained_share(3.0 * gap, np.sin(t)) < 1e-12
    assert unexplained_share(np.cos(t), gap) > 0.5
    assert unexplained_share(np.full_like(t, np.nan), np.sin(t)) == 1.0


def test_a_recorded_thermometer_that_only_follows_the_spindle_current_is_said_indistinguishable():
    found = _confused([_cabinet_thermometer(_day(d)) for d in range(1, 5)])
    assert set(found) == {"cabinet", "recorded_signal:cabinet_c"}, found
    c = found["recorded_signal:cabinet_c"]
    assert c.factor == "spindle_i1_sq"
    assert c.unexplained < CONFUSED_SHARE
    assert c.factor_lag_s > 0.0  # a temperature follows its heat late: the factor needed a further lag
    assert "recorded column cabinet_c" in c.line()
    assert "spindle_i1_sq through another" in c.line()
    assert "cannot name it" in c.line()


def test_a_room_thermometer_that_varies_on_its_own_is_not_said_indistinguishable():
    found = _confused([_room_thermometer(_day(d), d) for d in range(1, 5)])
    assert set(found) == {"cabinet"}, found


def test_a_column_some_recordings_lack_is_tried_where_two_have_it_and_the_report_says_where_it_is():
    from gateway.diagnose.hypotheses import partial_columns

    days = [_day(d) for d in range(1, 4)]
    one = [_cabinet_thermometer(days[0]), *days[1:]]
    stack = build_stack(MODEL, one)
    assert "recorded_signal:cabinet_c" not in {h.key for h in catalogue(stack, MODEL, INFOS)}
    (line,) = partial_columns(stack)
    assert line == ("column cabinet_c is recorded in 1 of 3 recordings (33 % of the windows: day1): no hypothesis on "
                    "it was tried (it needs values in at least 25 % of the windows, in 2 recordings at least); record "
                    "it in every recording, the identification experiments too, or diagnose the recordings that have "
                    "it on their own")
    # a thermometer on two of three days (on the production days, not the experiments): tried, taken as constant
    # where it is missing, and said so
    two = [_cabinet_thermometer(days[0]), _cabinet_thermometer(days[1]), days[2]]
    stack = build_stack(MODEL, two)
    assert "recorded_signal:cabinet_c" in {h.key for h in catalogue(stack, MODEL, INFOS)}
    (line,) = partial_columns(stack)
    assert line == ("column cabinet_c is recorded in 2 of 3 recordings (67 % of the windows: day1, day2): its "
                    "hypotheses take it as constant in the others, as the identified model does, and a model written "
                    "with it needs it in every recording it estimates; record it in every recording, the "
                    "identification experiments too")
    assert partial_columns(build_stack(MODEL, [_cabinet_thermometer(d) for d in days])) == []
    # ... in under half the windows too (the production days beside more hours of experiments without it)
    five = [*two, _day(4), _day(5)]
    stack = build_stack(MODEL, five)
    assert 0.25 < np.isfinite(stack.extras["cabinet_c"]).mean() < 0.5
    assert "recorded_signal:cabinet_c" in {h.key for h in catalogue(stack, MODEL, INFOS)}
