"""Probe data in identification and diagnosis: a production run whose displacement is measured only at the
CNC's probe cycles (probe_* columns as `cncgw record --export-only` writes them, or sparse displacement
columns) joins identification, fitted only where a probe measured, each probe weighted by its stated
uncertainty; diagnosis scores it only at those instants. All through the command line against the
simulated machine."""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_identify_production import EXPERIMENTS, HELD_OUT
from tests_paths import PROFILES

from gateway.cli import main
from gateway.identify import identify
from gateway.model import load_model
from gateway.profile import load_profile
from gateway.recording import Recording, read_for_profile, write_recording
from gateway.replay import estimate
from simulators.machine import load_scenario, simulate
from simulators.machine.scenario import parse_scenario_text

pytestmark = pytest.mark.numeric

PROFILE = PROFILES / "sim-vmc.toml"


@pytest.fixture(scope="module")
def files(tmp_path_factory, sim_identified):
    """The nine experiments (displacement sensors) and the production day probed every 2 h (no sensors); the
    experiments alone identified (conftest: once a session, the same runs in memory)."""
    d = tmp_path_factory.mktemp("probes")
    for n in EXPERIMENTS:
        assert main(["simulate", "record", n, "-o", str(d), "--no-progress"]) == 0
    assert main(["simulate", "record", "production-day", "-o", str(d / "probed"), "--probes-every-h", "2",
                 "--no-progress"]) == 0
    alone = sim_identified[2].model
    held = simulate(parse_scenario_text(HELD_OUT)).recording("true")
    return d, [str(d / f"{n}.csv") for n in EXPERIMENTS], d / "probed" / "production-day.csv", alone, held


def worst(model, rec) -> float:
    """Max error as % of peak on the worst axis with a peak of at least 5 um, against the noiseless truth."""
    return max(m.max_error_pct_of_peak for m in estimate(model, rec).metrics.values() if m.peak_um >= 5.0)


def test_the_simulated_probe_recording_has_only_probe_columns(files):
    _, _, probed, _, _ = files
    rec = read_for_profile(probed, load_profile(PROFILE), require_displacement=False)
    assert rec.displacement == {}
    seq = rec.extras["probe_seq"]
    assert np.isfinite(seq).sum() == 12  # every 2 h of 24 h
    at = np.flatnonzero(np.isfinite(seq))
    assert np.allclose(np.diff(rec.time_s[at]), 7200.0)
    assert np.all(rec.extras["probe_sd_um"][at] == 0.3)


def test_a_day_probed_every_2h_joins_identification_and_predicts_another_day_better(files, tmp_path, capsys):
    _, exps, probed, alone, held = files
    out = tmp_path / "m.toml"
    assert main(["identify", "--profile", str(PROFILE), *exps, "--production", str(probed), "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert ("production run production-day: 12 probe instants from its probe columns (x 12, y 12, z 12 points), "
            "weighted by their stated uncertainty") in text
    model = load_model(out)
    assert model.info["production_points"] == {"production-day": {"x": 12, "y": 12, "z": 12}}
    assert "(12 probe instants in 1 of them)" in model.coverage.source
    # measured: 7.2 % of peak from the experiments alone, 3.3 % with the 12 probes (2.4-4.8 % over six noise seeds)
    assert worst(model, held) <= 0.75 * worst(alone, held)
    assert estimate(model, held).coverage.windows_outside == 0
    assert estimate(alone, held).coverage.windows_outside > 0


def _probed_day(cols: dict[str, np.ndarray], run) -> Recording:
    return Recording(source="probed.csv", period_s=60.0, time_s=run.stamps_s, present=np.ones(len(run.time_s), bool),
                     factors=run.factors, displacement={}, extras=cols)


def test_each_probe_weighs_by_its_stated_uncertainty(files):
    """Six poor probes (8 um off, stated sd 20 um) between the good ones: weighted, they change nothing."""
    _, exps, _, _, held = files
    profile = load_profile(PROFILE)
    train = [read_for_profile(e, profile) for e in exps]
    run = simulate(load_scenario("production-day"))
    good = run.probe_columns(every_s=7200, sd_um=0.3)
    rows = np.arange(180, 1440, 240)
    poor = {k: v.copy() for k, v in good.items()}
    for i, a in enumerate("xyz"):
        poor[f"probe_{a}_um"][rows] = run.true_um[rows, i] + 8.0 * (-1.0) ** np.arange(len(rows))
    poor["probe_sd_um"][rows] = 20.0
    poor["probe_seq"][rows] = 0
    unstated = poor | {"probe_sd_um": np.where(np.isfinite(poor["probe_sd_um"]), 0.3, np.nan)}
    # y alone: the axis the poor probes hurt most (measured on all three axes: y 4.75 / 4.76 / 17.9 %, z 1.43 / 1.41
    # / 3.34 %, x under 5 um), the same figures as fitted with the others, in a quarter of the time
    kw = {"factors": profile.factor_names, "axes": ("y",)}
    clean = worst(identify(train, production=[_probed_day(good, run)], **kw).model, held)
    weighted = worst(identify(train, production=[_probed_day(poor, run)], **kw).model, held)
    unweighted = worst(identify(train, production=[_probed_day(unstated, run)], **kw).model, held)
    # measured: 4.75 % clean, 4.76 % with the poor probes weighted, 17.9 % with them weighted like the good ones
    assert abs(weighted - clean) < 0.5
    assert unweighted > 2.0 * weighted


def _cut(path, out, hours: float, *, rename: dict[str, str] | None = None, sd: float | None = None):
    """The first ``hours`` of a recording, columns renamed, probe_sd_um replaced."""
    profile = load_profile(PROFILE)
    rec = read_for_profile(path, profile, require_displacement=False)
    n = int(hours * 60)
    cols = {profile.factor(f).column: v[:n] for f, v in rec.factors.items()} | {k: v[:n] for k, v in rec.extras.items()}
    if sd is not None:
        cols["probe_sd_um"] = np.where(np.isfinite(cols["probe_sd_um"]), sd, np.nan)
    cols = {(rename or {}).get(k, k): v for k, v in cols.items()}
    write_recording(out, time_s=rec.time_s[:n], columns=cols)
    return out


def test_too_few_probes_and_no_measurement_are_clear_errors(files, tmp_path, capsys):
    _, exps, probed, _, _ = files
    short = _cut(probed, tmp_path / "short.csv", 5.0)  # probes at 2 h and 4 h
    assert main(["identify", "--profile", str(PROFILE), *exps, "--production", str(short)]) == 6
    err = capsys.readouterr().err
    assert f"{short}: 2 probe instant(s) in its probe columns (x 2, y 2, z 2)" in err
    assert "needs at least 3 on an axis" in err
    bare = _cut(probed, tmp_path / "bare.csv", 24.0, rename={f"probe_{a}_um": f"other_{a}" for a in "xyz"})
    assert main(["identify", "--profile", str(PROFILE), *exps, "--production", str(bare)]) == 6
    err = capsys.readouterr().err
    assert f"{bare}: no measured displacement" in err
    assert "probe_x_um" in err
    zero_sd = _cut(probed, tmp_path / "zero-sd.csv", 24.0, sd=0.0)
    assert main(["identify", "--profile", str(PROFILE), *exps, "--production", str(zero_sd)]) == 6
    err = capsys.readouterr().err
    assert f"{zero_sd}: column probe_sd_um at t=7200 s: 0.0 um: expected a probe's standard uncertainty in (0, 50] um" \
        in err


def test_sparse_displacement_columns_are_probe_points_too(files, tmp_path):
    _, _, probed, _, _ = files
    sparse = _cut(probed, tmp_path / "sparse.csv", 24.0, rename={f"probe_{a}_um": f"{a}_um" for a in "xyz"})
    profile = load_profile(PROFILE)
    from gateway.prepare import prepare

    p = prepare(read_for_profile(sparse, profile), factors=profile.factor_names, axes=profile.axes, probe_points=True)
    q = prepare(read_for_profile(probed, profile, require_displacement=False), factors=profile.factor_names,
                axes=profile.axes, probe_points=True)
    assert p.sparse
    assert q.sparse
    assert (p.y_source, q.y_source) == ("displacement", "probes")
    np.testing.assert_array_equal(p.y, q.y)
    np.testing.assert_array_equal(p.y_sd, q.y_sd)


def test_diagnose_scores_a_probed_day_at_its_probe_instants(files, tmp_path, capsys):
    _, _, probed, alone, _ = files
    from gateway.model import save_model

    model = save_model(alone, tmp_path / "alone.toml")
    assert main(["diagnose", "--profile", str(PROFILE), "--model", str(model), str(probed), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    said = " ".join(report["conclusions"])
    assert (f"{probed}: displacement measured at 12 probe instants only (its probe columns; x 12, y 12, z 12): "
            "scored at those instants, nowhere else") in said
    assert "held-out blocks of about 2.0 h" in said
    # the model's error on the day is scored at the probes (about 10 % of peak on y: 1.4 of 13.7 um)
    assert 5.0 < report["adequacy"]["axes"]["y"]["max_error_pct_of_peak"] < 20.0
    short = _cut(probed, tmp_path / "short.csv", 5.0)
    assert main(["diagnose", "--profile", str(PROFILE), "--model", str(model), str(short)]) != 0
    err = capsys.readouterr().err
    assert f"{short}: 2 probe instant(s) in its probe columns (x 2, y 2, z 2)" in err
    assert "needs at least 3 on an axis to be judged" in err
