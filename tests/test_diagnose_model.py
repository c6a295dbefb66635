"""Derived model inputs (what diagnosis adds to the core): model files, checked loading, batch = live."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from gateway.errors import ModelError, RecordingError
from gateway.model import FirstOrder, ModelStepper, PathTF, ThermalModel, load_model, model_to_toml, save_model
from gateway.model.inputs import (
    Column,
    Flag,
    InputStepper,
    Periodic,
    Product,
    Same,
    Sum,
    evaluate_inputs,
    initial_values,
)
from gateway.prepare import prepare
from gateway.recording import Recording
from gateway.replay import estimate

FACTORS = ("speed", "i1_sq", "z_i_sq")
INPUTS = (
    Product(name="speed_sq", of=("speed", "speed"), unit="rpm^2", note="eddy loss"),
    Product(name="speed_x_lag", of=("speed", "speed"), lag_s=(0.0, 300.0), unit="rpm^2"),
    Sum(name="amps_sq", of=("i1_sq", "z_i_sq"), unit="A^2"),
    Flag(name="running", of="speed", above=1.0),
    Product(name="on_x_i1_lag", of=("running", "i1_sq"), lag_s=(0.0, 1200.0), unit="A^2"),
    Column(name="room", column="room_c", unit="degC"),
    Periodic(name="day_sin", period_s=86400.0, phase="sin"),
    Periodic(name="day_cos", period_s=86400.0, phase="cos"),
    Same(name="i1_sq_delay900s", of="i1_sq"),
)

pytestmark = pytest.mark.numeric


def extended_model() -> ThermalModel:
    paths = [
        PathTF(axis="z", factor="speed", terms=(FirstOrder(gain=0.01, tau_s=1800.0),)),
        PathTF(axis="z", factor="speed_sq", terms=(FirstOrder(gain=2e-6, tau_s=3600.0),)),
        PathTF(axis="z", factor="speed_x_lag", terms=(FirstOrder(gain=-1e-6, tau_s=600.0),)),
        PathTF(axis="y", factor="amps_sq", terms=(FirstOrder(gain=0.004, tau_s=3000.0),
                                                  FirstOrder(gain=0.002, tau_s=40000.0))),
        PathTF(axis="y", factor="on_x_i1_lag", terms=(FirstOrder(gain=-0.003, tau_s=900.0),)),
        PathTF(axis="x", factor="room", terms=(FirstOrder(gain=1.5, tau_s=20000.0),)),
        PathTF(axis="x", factor="day_sin", terms=(FirstOrder(gain=0.7, tau_s=1.0),)),
        PathTF(axis="x", factor="day_cos", terms=(FirstOrder(gain=-0.4, tau_s=1.0),)),
        PathTF(axis="z", factor="i1_sq_delay900s", terms=(FirstOrder(gain=0.003, tau_s=2400.0),), delay_s=900.0),
    ]
    return ThermalModel(axes=("x", "y", "z"), factors=FACTORS, units={"speed": "rpm", "i1_sq": "A^2", "z_i_sq": "A^2"},
                        reference={"z_i_sq": 13.0}, paths={(p.axis, p.factor): p for p in paths}, machine="t",
                        inputs=INPUTS)


def recording(n: int = 600, *, seed: int = 0, room: bool = True) -> Recording:
    rng = np.random.default_rng(seed)
    speed = np.repeat(rng.choice([0.0, 800.0, 2000.0, 3000.0], size=n // 30), 30)[:n]
    speed[:20] = 0.0
    i1 = np.where(speed > 0, 200.0 + 0.05 * speed, 0.0) + rng.uniform(0, 5, n)
    z = 13.0 + rng.uniform(0, 3, n)
    extras = {}
    if room:
        r = 20.0 + np.sin(np.arange(n) / 200.0)
        r[[50, 51, 300]] = np.nan  # gaps in the thermometer: the last value holds
        extras["room_c"] = r
    t = 60.0 * np.arange(1, n + 1) + 3600.0 * 5
    return Recording(source="r.csv", period_s=60.0, time_s=t, present=np.ones(n, dtype=bool),
                     factors={"speed": speed, "i1_sq": i1, "z_i_sq": z}, displacement={"z": np.zeros(n)}, extras=extras)


def test_model_with_derived_inputs_round_trips_exactly(tmp_path):
    m = extended_model()
    path = save_model(m, tmp_path / "m.toml")
    text = path.read_text()
    assert "[inputs.speed_sq]" in text
    assert 'kind = "product"' in text
    back = load_model(path)
    assert back == m
    assert model_to_toml(back) == text
    assert back.input_names == FACTORS + tuple(d.name for d in INPUTS)
    assert back.units["speed_sq"] == "rpm^2"
    assert back.path("z", "i1_sq_delay900s").delay_s == 900.0


def test_a_model_without_derived_inputs_keeps_its_file_format():
    m = ThermalModel(axes=("z",), factors=("speed",), units={"speed": "rpm"}, reference={},
                     paths={("z", "speed"): PathTF(axis="z", factor="speed", terms=(FirstOrder(gain=0.01, tau_s=900.0),))})
    text = model_to_toml(m)
    assert "inputs" not in text
    assert load_model("m.toml", text=text) == m


def test_bad_derived_inputs_are_reported_with_file_line_and_key():
    text = model_to_toml(extended_model())
    bad = text.replace('kind = "product"', 'kind = "prodcut"', 1).replace('of = "speed"', 'of = "sped"', 1)
    with pytest.raises(ModelError) as err:
        load_model("bad.model.toml", text=bad)
    lines = str(err.value).splitlines()
    kind_line = next(k + 1 for k, line in enumerate(bad.splitlines()) if "prodcut" in line)
    assert (f'bad.model.toml:{kind_line}: inputs.speed_sq.kind: expected one of "product", "sum", "flag", "column", '
            f'"periodic", "same", got "prodcut" (a string) (did you mean "product"?)') in lines
    assert any('input running: "sped" is neither a factor nor an input declared before it' in line for line in lines)


def test_inputs_must_reference_factors_or_earlier_inputs():
    with pytest.raises(ValueError, match='input early: "later" is neither a factor nor an input declared before it'):
        ThermalModel(axes=("z",), factors=("speed",), units={}, reference={}, paths={},
                     inputs=(Same(name="early", of="later"), Same(name="later", of="speed")))


def test_batch_and_live_derived_inputs_agree():
    rec = recording()
    n = len(rec)
    sig = {f: np.asarray(rec.factors[f]) for f in FACTORS}
    cols = {"room_c": np.asarray(rec.extras["room_c"])}
    initial = {f: float(v[0]) for f, v in sig.items()} | {"room_c": 20.0 + math.sin(1 / 200.0)}
    batch = evaluate_inputs(INPUTS, sig, time_s=rec.time_s, dt_s=60.0, columns=cols, initial=initial)
    live = InputStepper(INPUTS, dt_s=60.0, initial=initial, time0_s=float(rec.time_s[0]))
    for k in range(n):
        out = live.step({f: sig[f][k] for f in FACTORS}, time_s=float(rec.time_s[k]),
                        columns={"room_c": cols["room_c"][k]})
        for name, v in out.items():
            assert v == pytest.approx(batch[name][k], rel=1e-12, abs=1e-9), (name, k)
    assert batch["room"][51] == batch["room"][49]  # a missing reading holds the last one
    assert batch["running"].max() == 1.0
    assert batch["running"][0] == 0.0


def test_a_lag_starts_settled_at_the_initial_equilibrium():
    sig = {"speed": np.full(50, 1000.0)}
    inp = (Product(name="p", of=("speed", "speed"), lag_s=(0.0, 600.0)),)
    out = evaluate_inputs(inp, sig, time_s=60.0 * np.arange(50), dt_s=60.0)
    assert np.allclose(out["p"], 1e6)
    assert initial_values(inp, {"speed": 1000.0}, time0_s=0.0)["p"] == 1e6


def test_prepare_and_estimate_run_a_model_with_derived_inputs():
    m = extended_model()
    rec = recording()
    prep = prepare(rec, factors=m.factors, axes=m.axes, inputs=m.inputs)
    assert prep.du.shape == (len(m.input_names), len(rec))
    j = m.input_names.index("speed_sq")
    assert np.allclose(prep.du[j], rec.factors["speed"] ** 2 - rec.factors["speed"][0] ** 2)
    assert np.all(prep.du[:, 0] == 0.0)  # every input starts at its initial equilibrium
    est = estimate(m, rec, align="none")
    assert np.allclose(est.estimated, m.discretize(60.0).simulate(prep.du))
    assert np.abs(est.estimated[2]).max() > 1.0


def test_live_estimator_agrees_with_batch_replay_on_derived_inputs():
    m = extended_model()
    rec = recording()
    prep = prepare(rec, factors=m.factors, axes=m.axes, inputs=m.inputs)
    dm = m.discretize(60.0)
    batch = dm.simulate(prep.du)
    sig = {f: np.asarray(rec.factors[f]) for f in FACTORS}
    initial = {f: float(v[0]) for f, v in sig.items()} | {"room_c": float(rec.extras["room_c"][0])}
    start = initial_values(m.inputs, initial, time0_s=float(rec.time_s[0]))
    stepper = InputStepper(m.inputs, dt_s=60.0, initial=initial, time0_s=float(rec.time_s[0]))
    live = ModelStepper(dm)
    for k in range(len(rec)):
        values = stepper.step({f: sig[f][k] for f in FACTORS}, time_s=float(rec.time_s[k]),
                              columns={"room_c": rec.extras["room_c"][k]})
        du = [sig[f][k] - initial[f] for f in FACTORS] + [values[d.name] - start[d.name] for d in m.inputs]
        y = live.step(du)
        assert np.allclose(y, batch[:, k], atol=1e-9)


def test_a_recording_without_the_column_an_input_reads_is_rejected_by_name():
    with pytest.raises(RecordingError, match='the model\'s input room reads column "room_c", which this recording '
                                             r"does not have \(numeric extra columns: none\)"):
        prepare(recording(room=False), factors=FACTORS, axes=("z",), inputs=(Column(name="room", column="room_c"),))


def test_a_column_an_input_reads_that_holds_text_or_nothing_is_said_so_not_missing(tmp_path):
    # one "ERR" cell made the thermometer a text column, and the message said the file had no such column
    from gateway.recording import read_recording

    n = 30
    rows = ["time_s,speed,i1_sq,z_i_sq,z_um,room_c"] + [f"{60 * (k + 1)},0,0,13,0,{20 + 0.01 * k:g}" for k in range(n)]
    inputs = (Column(name="room", column="room_c"),)

    def prepared(cells: dict[int, str]) -> None:
        lines = list(rows)
        for k, cell in cells.items():
            lines[k + 1] = lines[k + 1].rsplit(",", 1)[0] + "," + cell
        path = tmp_path / "r.csv"
        path.write_text("\n".join(lines) + "\n")
        rec = read_recording(path, factor_columns={f: f for f in FACTORS}, displacement_columns={"z": "z_um"})
        prepare(rec, factors=FACTORS, axes=("z",), inputs=inputs)

    prepared({3: ""})  # an empty cell is a gap
    with pytest.raises(RecordingError) as err:
        prepared({7: "ERR"})
    assert str(err.value) == (f'{tmp_path}/r.csv: the model\'s input room reads column "room_c", which holds text: "ERR" '
                              "in its data row 8 (expected numbers; leave a cell empty to make it a gap)")
    with pytest.raises(RecordingError, match='reads column "room_c", which has no value in any row of this recording'):
        prepared(dict.fromkeys(range(n), ""))


# -- a room thermometer's paths start in the room's daily cycle ----------------------------------------------
DAY = 86400.0


def room_model(start: str) -> ThermalModel:
    """x follows the room through a casting's lag (6 h, 1.5 um/K); z has a spindle path beside it."""
    paths = [PathTF(axis="x", factor="room", terms=(FirstOrder(gain=1.5, tau_s=6 * 3600.0),)),
             PathTF(axis="z", factor="speed", terms=(FirstOrder(gain=0.01, tau_s=1800.0),))]
    return ThermalModel(axes=("x", "z"), factors=("speed",), units={"speed": "rpm"}, reference={},
                        paths={(p.axis, p.factor): p for p in paths}, machine="t",
                        inputs=(Column(name="room", column="room_c", unit="degC", start=start),))


def room_days(days: float, *, drift_k_per_h: float = 0.02, amplitude_k: float = 1.5, t0: float = 1.7e9) -> Recording:
    """A machine at rest in a room cycling a day (warmest at 15 h) and drifting, recorded every minute."""
    t = t0 + 60.0 * np.arange(1, round(days * DAY / 60.0) + 1)
    room = 20.0 + amplitude_k * np.cos(2 * math.pi * (t - 15 * 3600.0) / DAY) + drift_k_per_h * (t - t[0]) / 3600.0
    n = len(t)
    return Recording(source="room.csv", period_s=60.0, time_s=t, present=np.ones(n, dtype=bool),
                     factors={"speed": np.zeros(n)}, displacement={"x": np.zeros(n)}, extras={"room_c": room})


def heated_hall(rec: Recording) -> Recording:
    """The same days in a hall heated from 6 to 18 h (19 -> 21 C within an hour or two), drifting 0.01 K/h."""
    t = rec.time_s - rec.time_s[0]
    h = (t / 3600.0) % 24
    room = 19.0 + 2.0 / (1 + np.exp(-2 * (h - 6))) - 2.0 / (1 + np.exp(-2 * (h - 18))) + 0.01 * t / 3600.0
    return replace(rec, extras={"room_c": room})


@pytest.mark.parametrize("hall", ["sine", "heated"])
def test_a_room_thermometer_s_paths_start_in_the_daily_cycle_the_days_before_left(hall):
    # the truth: four days of the cycle from a settled start (the lag forgets it within a day); the last day alone
    # is what a user estimates. Settled at its first reading, x is off by most of the room's swing through the lag
    whole = room_days(4) if hall == "sine" else heated_hall(room_days(4))
    truth = estimate(room_model("settled"), whole, align="none").estimated[0][-1440:]
    truth = truth - truth[0]
    day = whole.slice(len(whole) - 1440, len(whole))
    swing = float(np.ptp(truth))
    errors = {}
    for start in ("settled", "daily"):
        est = estimate(room_model(start), day, align="none")
        x = est.estimated[0] - est.estimated[0][0]
        errors[start] = float(np.max(np.abs(x - truth))) / swing
        if start == "daily":
            assert any("column room_c: its paths start as if it had cycled daily before the recording" in note
                       for note in est.notes), est.notes
    # the drift of the days before is not known (the mean before the start is the first reading's), and a day
    # is fitted with three harmonics: a few % of the swing
    assert errors["daily"] < 0.08, errors
    assert errors["settled"] > 0.3, errors


def test_a_daily_start_needs_half_a_day_and_adds_no_cycle_to_a_room_that_only_drifts():
    short = room_days(0.4)
    est = estimate(room_model("daily"), short, align="none")
    settled = estimate(room_model("settled"), short, align="none")
    assert np.array_equal(est.estimated, settled.estimated)
    assert any("column room_c (a daily start): 9.58 h of values, 12 h needed to tell a daily cycle from a drift: "
               "started settled at its first value" in note for note in est.notes), est.notes
    # a steady rise over a day: the drift is fitted beside the sine, and the mean before the start is the first
    # reading's, so the days before are flat: the same start as settled
    ramp = room_days(0.9, drift_k_per_h=0.3, amplitude_k=0.0)
    got = estimate(room_model("daily"), ramp, align="none").estimated
    assert np.allclose(got, estimate(room_model("settled"), ramp, align="none").estimated, rtol=0, atol=1e-6)


def test_a_daily_start_round_trips_and_a_misspelt_one_is_named(tmp_path):
    m = room_model("daily")
    path = save_model(m, tmp_path / "m.toml")
    assert 'start = "daily"' in path.read_text()
    assert load_model(path) == m
    assert 'start' not in model_to_toml(room_model("settled")).split("[inputs.room]")[1].split("\n\n")[0]
    with pytest.raises(ModelError) as err:
        load_model("bad.model.toml", text=path.read_text().replace('start = "daily"', 'start = "dialy"'))
    assert ('inputs.room.start: expected one of "settled", "daily", got "dialy" (a string) (did you mean "daily"?)'
            in str(err.value))
