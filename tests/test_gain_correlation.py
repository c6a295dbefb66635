"""Identification stores how its path gains' errors go together; the probe-updated band uses it.

Two factors that always change together (a spindle's speed and its current squared) fix a combination of
their gains far better than each gain: the errors of the two are strongly negatively correlated. The model
file keeps that correlation ([gain_correlation.<axis>]), and the band of gateway.adaptive is then narrow along
the combination the experiments showed and wide against it, where the diagonal prior was the same width both
ways.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from gateway.adaptive import AdaptiveEstimator, DriftSettings
from gateway.errors import ModelError
from gateway.identify import identify
from gateway.model import FirstOrder, PathTF, ThermalModel, load_model, model_to_toml
from gateway.model.correlation import GainCorrelation
from gateway.synthetic import Segment, make_recording, schedule_inputs

F = ("speed", "i_sq")
PLANT = ThermalModel(axes=("z",), factors=F, units={}, reference={}, paths={
    ("z", "speed"): PathTF(axis="z", factor="speed", terms=(FirstOrder(gain=0.008, tau_s=2400.0),)),
    ("z", "i_sq"): PathTF(axis="z", factor="i_sq", terms=(FirstOrder(gain=0.02, tau_s=1500.0),)),
})


@pytest.fixture(scope="module")
def identified() -> ThermalModel:
    """Three spindle runs whose current squared per rpm differs by only 10-20 % (as on a real spindle)."""
    recs = []
    for k, (speed, i_sq) in enumerate([(1000.0, 100.0), (500.0, 60.0), (800.0, 88.0)]):
        segs = [Segment(minutes=30, levels={}), Segment(minutes=180, levels={"speed": speed, "i_sq": i_sq}),
                Segment(minutes=270, levels={})]
        recs.append(make_recording(PLANT, schedule_inputs(segs, F, {}), name=f"spindle{k}", noise_um=0.1, seed=k))
    return identify(recs, factors=F, axes=("z",)).model


def test_identification_stores_a_strongly_negative_correlation_of_co_varying_paths(identified):
    c = identified.gain_correlation["z"]
    assert set(c.inputs) == set(F)
    r = c.array()[c.inputs.index("speed"), c.inputs.index("i_sq")]
    assert r < -0.8, r
    # the file keeps it exactly; a model file without it reads as independent gains (the identity)
    again = load_model("m.toml", text=model_to_toml(identified))
    assert again == identified
    assert np.array_equal(again.gain_correlation_matrix("z")[np.ix_([0, 1], [0, 1])],
                          np.array(c.full(F)))
    plain = ThermalModel(axes=identified.axes, factors=F, units={}, reference=identified.reference,
                         paths=dict(identified.paths))
    assert np.array_equal(load_model("old.toml", text=model_to_toml(plain)).gain_correlation_matrix("z"), np.eye(2))


def band_sd(model: ThermalModel, c: np.ndarray, *, correlated: bool) -> float:
    """The 95 % band (as an sd) before any probe: the gains' prior alone (the disturbance starts at 0)."""
    est = AdaptiveEstimator(model, window_s=60.0, settings=DriftSettings(gain_correlation=correlated))
    est.step(c[None, :], 60.0)
    return est.estimate()[0].sd_um


def test_the_band_is_narrow_along_what_the_experiments_fixed_and_wide_against_it(identified):
    g = np.array([identified.path("z", f).gain for f in F])
    along = g * np.array([1000.0, 100.0])  # the contributions in the experiments' proportion (um)
    against = along * np.array([1.0, -1.0])  # the current falling as the speed rises: never seen
    narrow, diag = band_sd(identified, along, correlated=True), band_sd(identified, along, correlated=False)
    assert narrow < 0.3 * diag, (narrow, diag)  # measured: 0.1x
    wide, diag_against = band_sd(identified, against, correlated=True), band_sd(identified, against, correlated=False)
    assert wide > 1.3 * diag_against, (wide, diag_against)  # measured 1.41x: sqrt(2) with a correlation near -1


BASE = model_to_toml(ThermalModel(axes=("z",), factors=F, units={}, reference={}, paths=dict(PLANT.paths)))


@pytest.mark.parametrize(("table", "message"), [
    ('"speed/i_sq" = -1.5', 'gain_correlation.z.speed/i_sq: expected a correlation in [-1, 1], got -1.5'),
    ('"speed/rpm" = -0.5', 'gain_correlation.z.speed/rpm: expected a key "a/b" naming two different inputs of '
                           "this model (inputs: speed, i_sq)"),
    ('"speed/speed" = 0.5', 'gain_correlation.z.speed/speed: expected a key "a/b" naming two different inputs'),
    ('"speed/i_sq" = -0.5\n"i_sq/speed" = -0.5', 'gain_correlation.z.i_sq/speed: the pair speed/i_sq is named twice'),
    ('"speed/i_sq" = "high"', 'gain_correlation.z.speed/i_sq: expected a correlation in [-1, 1], got "high" (a string)'),
])
def test_a_bad_correlation_table_is_refused_naming_the_key_and_value(table, message):
    text = BASE.replace("[[path]]", f"[gain_correlation.z]\n{table}\n\n[[path]]", 1)
    with pytest.raises(ModelError) as exc:
        load_model("bad.model.toml", text=text)
    assert "bad.model.toml" in str(exc.value)
    assert message in str(exc.value)


def test_pairs_that_together_are_no_correlation_are_refused():
    # every pair allowed on its own, the three together impossible (a = -b, b = -c, c = -a)
    three = ThermalModel(axes=("z",), factors=("a", "b", "c"), units={}, reference={}, paths={})
    text = model_to_toml(three) + '\n[gain_correlation.z]\n"a/b" = -0.9\n"a/c" = -0.9\n"b/c" = -0.9\n'
    with pytest.raises(ModelError, match=r"gain_correlation\.z: the pairs together are not a correlation: its "
                                         r"smallest eigenvalue is -0\.8: expected a correlation matrix"):
        load_model("bad.model.toml", text=text)


def test_a_matrix_that_is_no_covariance_is_refused():
    # every pair allowed on its own, the three together impossible (x = -y, y = -z, z = -x)
    bad = [[1.0, -0.9, -0.9], [-0.9, 1.0, -0.9], [-0.9, -0.9, 1.0]]
    with pytest.raises(ValueError, match=r"smallest eigenvalue is -0\.8: expected a correlation matrix"):
        GainCorrelation(inputs=("a", "b", "c"), matrix=tuple(map(tuple, bad)))
    assert math.isclose(GainCorrelation(inputs=("a", "b"), matrix=((1.0, -1.0), (-1.0, 1.0))).array()[0, 1], -1.0)


def test_a_model_made_without_an_axis_or_input_keeps_the_correlation_of_the_rest(identified):
    from dataclasses import replace

    three = ThermalModel(axes=("y", "z"), factors=(*F, "feed"), units={}, reference={}, paths=dict(identified.paths),
                         gain_correlation={"y": GainCorrelation(inputs=F, matrix=((1.0, 0.3), (0.3, 1.0))),
                                           "z": GainCorrelation(inputs=(*F, "feed"), matrix=(
                                               (1.0, -0.9, 0.1), (-0.9, 1.0, 0.0), (0.1, 0.0, 1.0)))})
    z_only = replace(three, axes=("z",), factors=F, paths={k: v for k, v in three.paths.items()
                                                           if k[0] == "z" and k[1] != "feed"})
    assert list(z_only.gain_correlation) == ["z"]
    assert z_only.gain_correlation["z"] == GainCorrelation(inputs=F, matrix=((1.0, -0.9), (-0.9, 1.0)))
