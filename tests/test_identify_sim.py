"""Identification against the simulated machine: a physical 15-node network, not the model's own kind."""

from __future__ import annotations

import re

import numpy as np
import pytest

from gateway.identify import identify
from gateway.replay import estimate
from simulators.machine import load_scenario, simulate

pytestmark = pytest.mark.numeric


@pytest.fixture(scope="module")
def train(sim_identified):
    return sim_identified[1]


@pytest.fixture(scope="module")
def identified(sim_identified):
    """The paper's nine runs identified (conftest: once a session, shared with other modules)."""
    profile, _, result = sim_identified
    return profile, result


def test_axes_fitted_in_parallel_processes_give_the_same_model(identified, train):
    profile, serial = identified
    seen = []
    parallel = identify(train, factors=profile.factor_names, axes=profile.axes,
                        units={f.name: f.unit for f in profile.factors}, machine=profile.name, jobs=2,
                        progress=seen.append)
    assert parallel.model.paths == serial.model.paths
    def untimed(report):  # the axis lines end with their wall time
        return [re.sub(r"; [0-9.]+ s$", "", line) for line in report]

    assert untimed(parallel.report) == untimed(serial.report)
    assert sorted(seen) == sorted(f"axis {a}: {c}" for a in profile.axes
                                  for c in ("first_order", "second_order", "two_modes",
                                            "gain prior by leaving experiments out"))


@pytest.mark.parametrize("run", ["random-spindle", "spindle-feeds"])
def test_held_out_run_of_the_papers_kind_within_10_percent_of_peak(identified, run):
    """The paper reached about 28 % of peak; the aim for a truly linear plant is 10 %. The simulated machine
    is linear in its heat inputs, so its noiseless displacement is the reference; on axes whose peak is
    below 1 um the bound is the 0.1 um sensor noise instead."""
    _, result = identified
    sim = simulate(load_scenario(run))
    est = estimate(result.model, sim.recording("true"))
    for axis, m in est.metrics.items():
        assert m.max_abs_error_um <= max(0.10 * m.peak_um, 0.1), (run, axis, m)
    assert est.metrics["z"].peak_um > 10.0
    assert est.metrics["z"].max_error_pct_of_peak < 5.0


def test_measured_recording_and_truth_differ_by_the_sensor_noise_only():
    sim = simulate(load_scenario("random-spindle"))
    measured, true = sim.recording(), sim.recording("true")
    noise = measured.displacement["z"] - true.displacement["z"]
    assert 0.05 < np.std(noise) < 0.2  # the scenario's 0.1 um sensors
    np.testing.assert_array_equal(measured.factors["spindle_speed"], true.factors["spindle_speed"])
    assert measured.meta["scenario"] == "random-spindle"
    with pytest.raises(ValueError, match="which must be"):
        sim.recording("noisy")


def test_identification_reports_structure_and_reference_state(identified):
    profile, result = identified
    assert [s.axis for s in result.selections] == list(profile.axes)
    # the Z motor holds the head against gravity: its idle current squared is the reference, not zero
    assert result.model.reference["z_i_sq"] > 5.0
    assert result.model.reference["spindle_speed"] == 0.0
    assert all(s.chosen.rms < 0.3 for s in result.selections)


def test_gain_prior_predicts_left_out_experiments_better_on_the_simulated_machine(identified):
    """Two feed runs per axis and three spindle runs: leaving one out leaves a split of co-varying factors
    undetermined, which the prior settles (on y and z the held-out RMS falls to under half)."""
    _, result = identified
    by = {s.axis: s for s in result.shrinkage}
    for a in ("y", "z"):
        assert by[a].loeo_rms < 0.5 * by[a].loeo_rms_without_prior, (a, by[a].loeo_rms, by[a].loeo_rms_without_prior)
        assert by[a].loeo_rms < 1.0
    assert any("gain prior" in line for line in result.report)


def test_estimate_warns_where_the_model_extrapolates(identified):
    """The production day runs the spindle at up to 3000 rpm, where field weakening lowers the stator current
    per rpm; identification went to 1000 rpm. The model's coverage says which factor, how far, how long."""
    _, result = identified
    day = estimate(result.model, simulate(load_scenario("production-day")).recording())
    notes = [n for n in day.notes if n.startswith("outside the identification's coverage")]
    assert any("spindle_speed above coverage: up to 3000 rpm, 3x the highest covered (1000 rpm)" in n for n in notes)
    ratio = next(n for n in notes if "spindle_i1_sq per spindle_speed (ratio) below coverage" in n)
    assert re.search(r"down to 0\.01\d+ A\^2/rpm, 0\.0\d+x the lowest covered", ratio), ratio
    assert 0.3 < day.coverage.windows_outside / len(day.time_s) < 0.6  # most of both shifts
    paper_kind = estimate(result.model, simulate(load_scenario("spindle-feeds")).recording())
    assert paper_kind.coverage.windows_outside == 0
    assert not [n for n in paper_kind.notes if "coverage" in n]


@pytest.mark.plumbing
def test_identify_with_a_bundled_profile_never_writes_into_the_installed_package(sim_csv_dir, tmp_path, monkeypatch,
                                                                                  capsys):
    # a new user's first identify names the bundled profile: its model file sits inside the package
    from sim_shared import SIM_EXPERIMENTS

    from gateway import BUNDLED
    from gateway.cli import main

    bundled_model = BUNDLED / "sim-vmc.model.toml"
    before = bundled_model.read_bytes()
    monkeypatch.chdir(tmp_path)
    runs = [str(sim_csv_dir / f"{n}.csv") for n in SIM_EXPERIMENTS]
    assert main(["identify", "--profile", "sim-vmc", *runs]) == 0
    out = capsys.readouterr().out
    assert bundled_model.read_bytes() == before
    assert (tmp_path / "sim-vmc.model.toml").is_file()
    assert f"pass it on with --model {tmp_path / 'sim-vmc.model.toml'}" in out
