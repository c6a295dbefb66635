"""Gains the experiments do not determine: a prior chosen by leaving experiments out, and the report of
which paths are poorly determined and why."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_identify import FIRST_ORDER_PLANT, PAPER_DESIGN, F, experiment, recordings

from gateway.identify import identify
from gateway.model import load_model, model_to_toml
from gateway.replay import estimate
from gateway.synthetic import make_recording

pytestmark = pytest.mark.numeric

AXES = ("x", "z")


@pytest.fixture(scope="module")
def paper_design():
    recs = recordings(FIRST_ORDER_PLANT, noise_um=0.2)
    return identify(recs, factors=F, axes=AXES), identify(recs, factors=F, axes=AXES, shrink=False)


def test_prior_strength_is_what_predicts_left_out_experiments_best(paper_design):
    shrunk, _ = paper_design
    assert [s.axis for s in shrunk.shrinkage] == list(AXES)
    for s in shrunk.shrinkage:
        assert s.loeo_sse[s.kappa] == min(s.loeo_sse.values())
        assert s.loeo_rms <= s.loeo_rms_without_prior
        assert set(s.held_out_rms) == {f"exp{k}" for k in range(len(PAPER_DESIGN))}
        if math.isfinite(s.kappa):  # a prior is taken only when it predicts left-out runs better
            assert s.loeo_sse[s.kappa] < s.loeo_sse[math.inf]


def test_prior_leaves_determined_gains_and_held_out_accuracy(paper_design):
    shrunk, plain = paper_design
    for key, path in plain.model.paths.items():
        other = shrunk.model.paths[key]
        sd = path.sd.get("gain", 0.0)
        assert abs(other.gain - path.gain) <= max(sd, 1e-12), key
    run = make_recording(FIRST_ORDER_PLANT, experiment({"speed": 800, "i1_sq": 110, "i2_sq": 60, "x_feed": 3000,
                                                        "x_i_sq": 6}), name="held-out")
    est = estimate(shrunk.model, run)
    for m in est.metrics.values():
        assert m.max_abs_error_um <= 0.05 * m.peak_um, m


def test_report_says_which_paths_are_poorly_determined_and_why():
    # the rotor current follows the speed in one ratio in every spindle run: their split rests on shapes alone
    designs = [{"speed": 1000, "i1_sq": 100, "i2_sq": 40}, {"speed": 500, "i1_sq": 90, "i2_sq": 20},
               {"speed": 500, "i1_sq": 130, "i2_sq": 20}, {"x_feed": 6000, "x_i_sq": 4}, {"x_feed": 2000, "x_i_sq": 9}]
    result = identify(recordings(FIRST_ORDER_PLANT, designs, noise_um=0.3), factors=F, axes=AXES,
                      units={"i2_sq": "A^2"})
    z = result.shrinkage[1]
    poor = {p.factor: p for p in z.poorly_determined}
    assert "i2_sq" in poor
    assert poor["i2_sq"].why.startswith("co-varies with speed (r 1.00")
    line = next(ln for ln in result.report if "poorly determined: i2_sq" in ln)
    assert "um/A^2" in line
    info = result.model.info["axis_z"]
    assert any(t.startswith("i2_sq: co-varies with speed") for t in info["poorly_determined"])
    assert load_model("m.toml", text=model_to_toml(result.model)).info["axis_z"] == info
    # a well excited path is not listed
    assert "i1_sq" not in poor


def test_barely_excited_factor_is_named_as_such():
    designs = [*PAPER_DESIGN, {"i2_sq": 2.0}]
    plant = FIRST_ORDER_PLANT.with_paths([])
    recs = recordings(plant, designs, noise_um=0.3)
    # in this design the rotor current is also off in the spindle runs: only a weak run of its own moves it
    for r in recs[:3]:
        r.factors["i2_sq"] = np.zeros_like(r.factors["i2_sq"])
    result = identify(recs, factors=F, axes=AXES, prune=False)
    poor = {p.factor: p for s in result.shrinkage for p in s.poorly_determined}
    assert "i2_sq" in poor
    assert poor["i2_sq"].why.startswith("too little excitation (i2_sq at >= 10 % of its highest for 1 h, in 1 of 6")


def test_one_experiment_takes_no_prior_and_claims_no_held_out_error():
    # leaving each experiment out needs another to predict it from: with one, its "held-out" error was its own
    # variance (the prediction of nothing) and the report called it "predicted from the others"
    (one,) = recordings(FIRST_ORDER_PLANT, [{"speed": 1000, "i1_sq": 100, "i2_sq": 40}], noise_um=0.2)
    result = identify([one], factors=F, axes=("z",))
    (z,) = result.shrinkage
    assert not z.left_out
    assert z.kappa == math.inf
    assert z.held_out_rms == {}
    text = "\n".join(result.report)
    assert "gain prior: none (it is chosen by leaving each experiment out" in text
    assert "with one experiment there are no others" in text
    assert "predicted from the others" not in text
    assert result.model.info["axis_z"]["held_out"] == "one experiment: nothing left out"
    assert "held_out_rms_um" not in result.model.info["axis_z"]
    # two experiments: each is predicted from the other, as before
    two = identify(recordings(FIRST_ORDER_PLANT, PAPER_DESIGN[:2], noise_um=0.2), factors=F, axes=("z",))
    assert two.shrinkage[0].left_out
    assert "predicted from the others, worst: " in "\n".join(two.report)


def test_a_factor_on_in_every_recording_is_not_said_to_lack_excitation(shared_data):
    # the real lathe's front spindle temperature, high for 39.9 h in 12 of 12 days, was "too little excitation"
    from tests_paths import ROOT

    from gateway.commands._common import split_by
    from gateway.profile import load_profile
    from gateway.recording import read_for_profile

    profile = load_profile(ROOT / "bench" / "profiles" / "ace-lathe.toml")
    days = split_by(read_for_profile(shared_data / "ace-lathe-thermal" / "ace_lathe_thermal_long.csv", profile,
                                     period_s=60.0), "day")
    result = identify(days[:12], factors=profile.factor_names, axes=profile.axes)
    (poor,) = result.shrinkage[0].poorly_determined
    assert poor.why.startswith("too little change in it for its gain to show (spindle_front_c at >= 10 % of its "
                               "highest for 39.9 h, in 12 of 12 recordings: on long enough")
    assert "too little excitation" not in poor.why
