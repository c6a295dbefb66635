"""The model: TOML round trip, load errors, and the one discretisation (batch = live = exact ZOH)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.linalg

from gateway.errors import ModelError
from gateway.model import (
    FirstOrder,
    LiveEstimator,
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
    (lambda s: s.replace("tau_s = 900", "tau_s = -900"), "tau_s: expected a number > 0, got -900"),
])
def test_bad_model_files_are_reported(edit, message):
    with pytest.raises(ModelError) as err:
        load_model("m.toml", text=edit(good_text()))
    assert message in str(err.value)
    assert str(err.value).startswith("m.toml:")


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
    live = dm.live()
    stepped = np.array([live.step(du[:, k]) for k in range(du.shape[1])]).T
    assert np.max(np.abs(stepped - batch)) < 1e-9
    assert live.steps == 800
    np.testing.assert_allclose(live.output(), batch[:, -1], atol=1e-9)


def test_rebuilt_estimator_continues_like_an_uninterrupted_one():
    dm = rich_model().discretize(60.0)
    du = inputs(600, seed=1)
    batch = dm.simulate(du)
    rebuilt = LiveEstimator.from_history(dm, du[:, :400])
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
