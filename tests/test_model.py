"""The model: TOML round trip, load errors, and the one discretisation (batch = live = exact ZOH)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.linalg

from gateway.errors import ModelError
from gateway.model import (
    FirstOrder,
    ModelStepper,
    PathTF,
    SecondOrder,
    ThermalModel,
    load_model,
    model_to_toml,
    save_model,
)
from gateway.model.model import paper_convolution

pytestmark = pytest.mark.numeric

FACTORS = ("speed", "i1_sq", "z_i_sq")


def rich_model() -> ThermalModel:
    paths = [
        PathTF(axis="z", factor="speed", terms=(SecondOrder.from_time_constants(gain=0.012, tau1_s=600, tau2_s=3000),),
               sd={"gain": 0.0004, "tau_slow_s": 120.0}),
        PathTF(axis="z", factor="i1_sq", terms=(FirstOrder(gain=0.05, tau_s=900), FirstOrder(gain=-0.02, tau_s=9000))),
        PathTF(axis="x", factor="i1_sq", terms=(SecondOrder(gain=-0.01, zeta=0.45, omega_rad_s=1 / 1500),),
               delay_s=150.0),
        PathTF(axis="x", factor="z_i_sq", terms=(FirstOrder(gain=0.2, tau_s=1200),), delay_s=120.0),
        PathTF(axis="y", factor="speed", terms=(FirstOrder(gain=1e-3 / 3, tau_s=1800.0000000001),)),
    ]
    return ThermalModel(axes=("x", "y", "z"), factors=FACTORS, units={"speed": "rpm", "i1_sq": "A^2", "z_i_sq": "A^2"},
                        reference={"z_i_sq": 2.25}, paths={(p.axis, p.factor): p for p in paths}, machine="test",
                        info={"method": "joint", "experiments": ["a", "b"], "axis_z": {"rms_um": 0.1}})


def test_round_trip_is_exact(tmp_path):
    m = rich_model()
    path = save_model(m, tmp_path / "m.toml")
    back = load_model(path)
    assert back == m
    assert model_to_toml(back) == path.read_text()
    assert back.path("z", "speed").sd["gain"] == 0.0004
    assert back.path("y", "z_i_sq").kind == "zero"
    assert math.isinf(back.path("y", "z_i_sq").K)


def test_gain_and_paper_K_are_both_reported():
    p = rich_model().path("z", "speed")
    assert p.gain == pytest.approx(0.012)
    assert p.K == pytest.approx(1 / 0.012)
    assert p.terms[0].K == pytest.approx(1 / 0.012)
    assert p.kind == "second_order"
    assert rich_model().path("z", "i1_sq").kind == "two_modes"


def good_text() -> str:
    return model_to_toml(rich_model())


@pytest.mark.parametrize(("edit", "message"), [
    (lambda s: s.replace('K = 83.33333333333333\nzeta', 'K = 80.0\nzeta'), "K"),
    (lambda s: s.replace("format = 1", "format = 7"), "format: expected 1, got 7: this model was written by another version"),
    (lambda s: s.replace('kind = "first_order", gain = 0.05', 'kind = "first_ordr", gain = 0.05'),
     'expected one of "first_order", "second_order", got "first_ordr" (a string) (did you mean "first_order"?)'),
    (lambda s: s.replace('axis = "z"\nfactor = "speed"', 'axis = "w"\nfactor = "speed"', 1), '"w" (a string)'),
    (lambda s: s.replace("[model]", "[model]\nowner = 1"), "model.owner: unknown key"),
    (lambda s: s.replace("tau_s = 900", "tau_s = -900"),
     "tau_s: expected a time constant from 1 s to 7.776e+06 s (90 days), got -900.0 (a number)"),
])
def test_bad_model_files_are_reported(edit, message):
    with pytest.raises(ModelError) as err:
        load_model("m.toml", text=edit(good_text()))
    assert message in str(err.value)
    assert str(err.value).startswith("m.toml:")


TAU_RANGE = "expected a time constant from 1 s to 7.776e+06 s (90 days)"
K_RANGE = ("expected the paper's K = 1/gain with |K| >= 1e-06 (a gain within +-1e+06 um per factor unit), or inf "
           "for a zero path")
DELAY_RANGE = "expected a dead time from 0 to 86400 s (1 day)"
INPUTS = """
[inputs.speed_sq]
kind = "product"
of = ["speed", "speed"]
lag_s = [0.0, 3600.0]

[inputs.day_sin]
kind = "periodic"
period_s = 86400.0
phase = "sin"
"""


@pytest.mark.parametrize(("old", "new", "message"), [
    # each of these ended in a traceback (ZeroDivisionError, MemoryError, ValueError) or in NaN estimates
    ("gain = 0.012\nK = 83.33333333333333\nzeta", "K = 0.0\nzeta", f"path.7.term.1.K: {K_RANGE}, got 0.0"),
    ("gain = 0.012\nK = 83.33333333333333\nzeta", "K = 5e-324\nzeta", f"path.7.term.1.K: {K_RANGE}, got 5e-324"),
    ("delay_s = 150.0", "delay_s = 1e12", f"path.2.delay_s: {DELAY_RANGE}, got 1000000000000.0 (a number)"),
    ("delay_s = 150.0", "delay_s = 1e300", f"path.2.delay_s: {DELAY_RANGE}, got 1e+300 (a number)"),
    ("zeta = 0.45", "zeta = 1e300", "path.2.term.1.zeta: expected a damping ratio > 0 and <= 10000, got 1e+300 (a number)"),
    ("omega_rad_s = 0.0006666666666666666", "omega_rad_s = 1e300",
     "path.2.term.1.omega_rad_s: expected a natural frequency from 1.286e-07 to 1 rad/s (1/(90 days) to 1/(1 s)), "
     "got 1e+300 (a number)"),
    ("zeta = 0.45", "zeta = 5000.0",
     "path.2.term.1.zeta: zeta = 5000.0 with omega_rad_s = 0.0006666666666666666 gives time constants 0.15 s and "
     "1.5e+07 s: expected both to be a time constant from 1 s to 7.776e+06 s (90 days)"),
    ("tau_s = 900.0", "tau_s = 5e-324", f"path.8.term.1.tau_s: {TAU_RANGE}, got 5e-324 (a number)"),
    ("tau_s = 9000.0", "tau_s = 1e9", f"path.8.term.2.tau_s: {TAU_RANGE}, got 1000000000.0 (a number)"),
    ("gain = 0.05, tau_s", "gain = 1e300, tau_s",
     "path.8.term.1.gain: expected a static gain within +-1e+06 um per factor unit, got 1e+300 (a number)"),
    ("z_i_sq = 2.25", "z_i_sq = 1e12",
     "reference.z_i_sq: expected a factor level within +-1e+09 (in the factor's unit), got 1000000000000.0 (a number)"),
    ("lag_s = [0.0, 3600.0]", "lag_s = [0.0, 1e-300]",
     "inputs.speed_sq.lag_s: expected an array of two lags in s, each 0 (none) or from 1 s to 7.776e+06 s (90 days), "
     "got [0.0, 1e-300]"),
    ("period_s = 86400.0", "period_s = 1e-300",
     "inputs.day_sin.period_s: expected a period from 1 s to 3.16224e+07 s (366 days), got 1e-300 (a number)"),
])
def test_values_out_of_physical_range_are_refused_at_their_line(old, new, message):
    text = good_text() + INPUTS
    assert text.count(old) == 1
    bad = text.replace(old, new)
    line = bad[: bad.index(new)].count("\n") + 1  # the key is on the first line of the edit
    with pytest.raises(ModelError) as err:
        load_model("m.toml", text=bad)
    assert str(err.value).splitlines() == [f"m.toml:{line}: {message}"]


def test_the_model_with_derived_inputs_used_above_loads():
    model = load_model("m.toml", text=good_text() + INPUTS)
    assert [d.name for d in model.inputs] == ["speed_sq", "day_sin"]


def test_identification_searches_only_time_constants_a_model_file_may_hold():
    from gateway.identify.common import Bounds
    from gateway.model import limits

    for dt_s, longest_s in ((60.0, 43200.0), (0.5, 600.0), (3600.0, 400 * 86400.0)):
        b = Bounds.for_data(dt_s, longest_s)
        assert limits.TAU_MIN_S <= math.exp(b.log_tau_min) < math.exp(b.log_tau_max) <= limits.TAU_MAX_S * (1 + 1e-12)


def test_second_order_K_only_is_accepted():
    text = good_text().replace('gain = 0.012\nK = 83.33333333333333\nzeta', 'K = 83.33333333333333\nzeta')
    assert load_model("m.toml", text=text).path("z", "speed").gain == pytest.approx(0.012)


# ------------------------------------------------------------------------------------ discretisation ---
def inputs(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    u = rng.random((3, n)) * np.array([[1000.0], [30.0], [4.0]])
    u[:, rng.random(n) < 0.3] = 0.0  # on/off like a machine
    return u


def test_live_estimator_equals_batch_replay():
    dm = rich_model().discretize(60.0)
    du = inputs(800)
    batch = dm.simulate(du)
    live = dm.stepper()
    stepped = np.array([live.step(du[:, k]) for k in range(du.shape[1])]).T
    assert np.max(np.abs(stepped - batch)) < 1e-9
    assert live.steps == 800
    np.testing.assert_allclose(live.output(), batch[:, -1], atol=1e-9)


def test_rebuilt_estimator_continues_like_an_uninterrupted_one():
    dm = rich_model().discretize(60.0)
    du = inputs(600, seed=1)
    batch = dm.simulate(du)
    rebuilt = ModelStepper.from_history(dm, du[:, :400])
    after = np.array([rebuilt.step(du[:, k]) for k in range(400, 600)]).T
    assert np.max(np.abs(after - batch[:, 400:])) < 1e-9


def fine_solution(path: PathTF, u_windows: np.ndarray, dt_s: float, sub: int) -> np.ndarray:
    """Integrate the continuous path exactly on a fine grid with the input held per window and delayed."""
    h = dt_s / sub
    u_fine = np.repeat(u_windows, sub)
    shift = round(path.delay_s / h)
    assert abs(shift * h - path.delay_s) < 1e-9, "choose sub so the delay is a whole number of fine steps"
    u_fine = np.concatenate([np.zeros(shift), u_fine])[: u_fine.size]
    y = np.zeros(u_fine.size)
    for term in path.terms:
        A, B, C = term.unit_state_space()
        n = A.shape[0]
        M = np.zeros((n + 1, n + 1))
        M[:n, :n], M[:n, n] = A * h, B * h
        E = scipy.linalg.expm(M)
        x = np.zeros(n)
        for k, uk in enumerate(u_fine):
            x = E[:n, :n] @ x + E[:n, n] * uk
            y[k] += term.gain * (C @ x)
    return y[sub - 1 :: sub]  # samples at the end of every window


@pytest.mark.parametrize(("axis", "factor"), [("z", "speed"), ("z", "i1_sq"), ("x", "i1_sq"), ("x", "z_i_sq")])
def test_zoh_discretisation_is_exact_for_window_means(axis, factor):
    model = rich_model()
    j = model.factors.index(factor)
    du = inputs(120, seed=2)
    y = model.discretize(60.0).contributions(du)[model.axes.index(axis), j]
    exact = fine_solution(model.path(axis, factor), du[j], 60.0, sub=20)  # 3 s fine step: delays are multiples
    scale = np.max(np.abs(exact))
    assert scale > 0
    assert np.max(np.abs(y - exact)) < 1e-9 * scale + 1e-12


def test_a_window_acts_on_the_displacement_sampled_at_its_end():
    """Row k holds the mean over (t_k - dt, t_k] and the displacement at t_k: no one-window lag."""
    m = ThermalModel(axes=("z",), factors=("speed",), units={}, reference={},
                     paths={("z", "speed"): PathTF(axis="z", factor="speed", terms=(FirstOrder(gain=1.0, tau_s=60.0),))})
    du = np.zeros((1, 5))
    du[0, 2] = 1.0
    y = m.discretize(60.0).simulate(du)[0]
    assert y[1] == 0.0
    assert y[2] == pytest.approx(1 - math.exp(-1))
    assert y[3] == pytest.approx((1 - math.exp(-1)) * math.exp(-1))


def test_static_gain_of_a_step():
    dm = rich_model().discretize(60.0)
    du = np.zeros((3, 3000))
    du[0] = 1000.0
    y = dm.simulate(du)
    assert y[2, -1] == pytest.approx(1000 * 0.012, rel=1e-6)


def test_paper_convolution_agrees_within_its_own_discretisation_error():
    """Eq. 5 is a rectangle rule on the convolution integral: its error is bounded by the rule's error on g."""
    model = rich_model()
    du = inputs(400, seed=3)
    exact = model.discretize(60.0).simulate(du)
    for dt, sub in ((60.0, 1), (15.0, 4), (3.0, 20)):
        u_fine = np.repeat(du, sub, axis=1)
        paper = paper_convolution(model, u_fine, dt, n_terms=u_fine.shape[1])[:, sub - 1 :: sub]
        diff = np.max(np.abs(paper - exact), axis=1)
        # bound: max|u| * sum_l |int_{l dt}^{(l+1) dt} g - g(l dt) dt|, per axis over its paths
        for i, a in enumerate(model.axes):
            bound = 0.0
            for j, f in enumerate(model.factors):
                p = model.path(a, f)
                if p.kind == "zero":
                    continue
                t = np.arange(0, 40 * 3600, dt / 50)
                g = p.impulse_response(t)
                exact_int = np.add.reduceat(g * (dt / 50), np.arange(0, t.size, 50))
                rect = p.impulse_response(np.arange(exact_int.size) * dt) * dt
                bound += np.max(np.abs(du[j])) * np.sum(np.abs(exact_int - rect))
            assert diff[i] <= 1.05 * bound + 1e-9, (a, dt, diff[i], bound)
        if dt == 60.0:
            coarse = diff
    assert np.all(diff < coarse / 10)  # 20x finer steps: the paper's error shrinks ~linearly


@pytest.mark.parametrize("delay_s", [0.0, 60.0, 150.0])
def test_first_order_fast_path_equals_the_general_section(delay_s):
    from gateway.model.discrete import Section, first_order_coefficients

    term = FirstOrder(gain=1.0, tau_s=700.0)
    sec = Section.from_state_space(*term.unit_state_space(), 60.0, delay_s)
    num, den = first_order_coefficients(700.0, 60.0, delay_s)
    np.testing.assert_allclose(num, sec.num, rtol=1e-13, atol=1e-16)
    np.testing.assert_allclose(den, sec.den, rtol=1e-13)


def test_a_model_the_loader_would_refuse_is_never_written(tmp_path):
    m = rich_model().with_paths([PathTF(axis="y", factor="i1_sq", terms=(FirstOrder(gain=9.5e6, tau_s=600.0),))])
    with pytest.raises(ModelError) as err:
        save_model(m, tmp_path / "m.toml")
    assert str(err.value) == (f"{tmp_path / 'm.toml'}: not written: path y/i1_sq.term.1.gain: expected a static gain "
                              "within +-1e+06 um per factor unit, got 9500000.0 (a number)")
    assert not (tmp_path / "m.toml").exists()
    assert not (tmp_path / "m.toml.tmp").exists()
