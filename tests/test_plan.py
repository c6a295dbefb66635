"""``cncgw plan``: proposals built from production's operating states, scenarios the simulator records, and
the production estimate they improve."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from sim_shared import SIM_EXPERIMENTS
from tests_paths import PROFILES

from gateway.cli import main
from gateway.identify import identify
from gateway.replay import estimate
from simulators.machine import load_scenario, simulate
from simulators.machine.scenario import parse_scenario_text

pytestmark = pytest.mark.numeric

EXPERIMENTS = SIM_EXPERIMENTS
PROFILE = PROFILES / "sim-vmc.toml"


@pytest.fixture(scope="module")
def planned(tmp_path_factory, sim_csv_dir):
    """``cncgw plan`` on the simulated runs' files (conftest: written once a session)."""
    d = sim_csv_dir
    day = simulate(load_scenario("production-day"))
    out = tmp_path_factory.mktemp("plan") / "plan"
    code = main(["plan", "--profile", str(PROFILE), *(str(d / f"{n}.csv") for n in EXPERIMENTS),
                 "--production", str(d / "production-day.csv"), "-o", str(out)])
    assert code == 0
    return d, day, json.loads((out / "plan.json").read_text())


def test_proposals_are_few_short_and_reach_what_production_uses(planned):
    _, _, doc = planned
    props = doc["proposals"]
    assert 1 <= len(props) <= 3
    assert all(p["hours"] <= 12.0 for p in props)
    # the production day runs the spindle at up to 3000 rpm in field weakening; the experiments went to 1000
    assert any("spindle_speed up to 3000 rpm" in r for p in props for r in p["reaches"])
    assert any("spindle_i1_sq per spindle_speed down to" in r for p in props for r in p["reaches"])
    # each proposal lowers the production estimate's uncertainty on every axis
    for p in props:
        for a, u in p["uncertainty_um"].items():
            assert u["after"] < u["before"], (p["name"], a)
    first = props[0]["uncertainty_um"]
    assert first["z"]["after"] < 0.7 * first["z"]["before"]


def test_scenarios_record_the_proposed_levels_on_the_simulator(planned):
    _, _, doc = planned
    for p in doc["proposals"]:
        sc = parse_scenario_text(Path(p["scenario"]).read_text(), source=p["scenario"])
        assert sc.duration_h == pytest.approx(p["hours"])
        run = simulate(sc)
        speed = run.factors["spindle_speed"]
        for step in p["steps"]:
            want = step["levels"]["spindle_speed"]
            if want > 100:  # the spindle reaches the state's speed at some point of the recording
                assert np.min(np.abs(speed - want)) < 0.02 * want
            for a in ("x", "y"):
                feed = step["levels"][f"{a}_feed"]
                if feed > 500:  # the mean |feed| of the state, within 15 %, in the windows of that step
                    assert np.any(np.abs(run.factors[f"{a}_feed"] - feed) < 0.15 * feed), (p["name"], a, feed)


def test_identification_with_the_proposals_predicts_the_production_day_better(planned, sim_identified):
    _, day, doc = planned
    profile, exps, identified = sim_identified  # the nine runs plan read, identified once a session
    extra = [simulate(parse_scenario_text(Path(p["scenario"]).read_text())).recording() for p in doc["proposals"]]
    truth = day.recording("true")
    before = identified.model
    after = identify(exps + extra, factors=profile.factor_names, axes=profile.axes).model
    e0, e1 = estimate(before, truth), estimate(after, truth)
    worst0 = max(m.max_error_pct_of_peak for m in e0.metrics.values() if m.peak_um >= 5)
    worst1 = max(m.max_error_pct_of_peak for m in e1.metrics.values() if m.peak_um >= 5)
    assert worst1 < worst0
    assert worst1 < 8.0, (worst0, worst1)
    assert e1.coverage.windows_outside < 0.2 * e0.coverage.windows_outside


def test_bad_arguments_are_named(planned, capsys):
    d, _, _ = planned
    exps = [str(d / f"{n}.csv") for n in EXPERIMENTS]
    assert main(["plan", "--profile", str(PROFILE), *exps, "--production", str(d / "production-day.csv"),
                 "--max-hours", "1"]) == 2
    assert "--max-hours 1: expected more than 1.5 h" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # argparse: --production is required
        main(["plan", "--profile", str(PROFILE), *exps])
    assert "--production" in capsys.readouterr().err


def test_a_production_day_that_cuts_gets_a_cutting_experiment_the_simulator_records(tmp_path, sim_csv_dir):
    """The bundled day with 3 kW cuts on its 2000 rpm roughing jobs: plan sees the rotor current squared above
    the no-load level at that speed, proposes cutting there (said in the text), and the scenario it writes
    records the cut: the rotor current squared reaches the cutting state's level, far beyond the experiments'."""
    text = (PROFILE.parent.parent / "simulators" / "scenarios" / "production-day.toml").read_text()
    text = text.replace("spindle_rpm = 2000\n", "spindle_rpm = 2000\ncutting_kw = 3.0\n")
    assert text.count("cutting_kw") >= 2
    from simulators.machine.run import write_run

    day = simulate(parse_scenario_text(text.replace('name = "production-day"', 'name = "cutting-day"')))
    write_run(day, tmp_path)
    out = tmp_path / "plan"
    code = main(["plan", "--profile", str(PROFILE), *(str(sim_csv_dir / f"{n}.csv") for n in EXPERIMENTS),
                 "--production", str(tmp_path / "cutting-day.csv"), "-o", str(out)])
    assert code == 0
    doc = json.loads((out / "plan.json").read_text())
    cutting_states = [s for s in doc["states"] if s["cutting"]]
    assert cutting_states
    assert all(1900 < s["levels"]["spindle_speed"] < 2100 for s in cutting_states)
    cuts = [p for p in doc["proposals"] if p["cutting"]]
    assert cuts, [p["name"] for p in doc["proposals"]]
    p = cuts[0]
    assert "cut a test piece" in p["description"]
    assert "kW at 2000 rpm" in p["simulated_cut"]
    sc = parse_scenario_text(Path(p["scenario"]).read_text(), source=p["scenario"])
    assert any(seg.cutting_w > 0 for seg in sc.segments)
    run = simulate(sc)
    i2 = run.factors["spindle_i2_sq"]
    experiments_i2 = max(float(np.max(simulate(load_scenario(n)).factors["spindle_i2_sq"]))
                         for n in ("spindle-1000rpm", "spindle-400-600rpm"))
    for step in p["steps"]:
        if step["cutting"]:  # the cut's rotor current squared, within 20 % of the state's, in the step's windows
            want = step["levels"]["spindle_i2_sq"]
            assert want > 2 * experiments_i2
            assert np.any(np.abs(i2 - want) < 0.2 * want), (want, float(i2.max()))
