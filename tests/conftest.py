"""Shared fixtures. Every test runs under a leak check: a test that leaves a thread running fails."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest
from sim_shared import SIM_EXPERIMENTS
from tests_paths import PROFILES, ROOT, SHARED_DATA

__all__ = ["PROFILES", "ROOT", "SHARED_DATA"]


@pytest.fixture(autouse=True)
def _no_leaked_threads():
    before = set(threading.enumerate())
    yield
    deadline = time.monotonic() + 3.0
    while True:
        leaked = [t for t in threading.enumerate() if t not in before and t.is_alive()]
        if not leaked or time.monotonic() > deadline:
            break
        time.sleep(0.02)
    assert not leaked, f"test leaked threads: {[t.name for t in leaked]}"


@pytest.fixture
def shared_data() -> Path:
    """The real recordings in ../shared/data (never copied into the repository)."""
    if not SHARED_DATA.is_dir():
        pytest.fail(f"real recordings expected at {SHARED_DATA}: the shared folder must sit beside the repository")
    return SHARED_DATA


@pytest.fixture(scope="session")
def sim_identified():
    """(profile, recordings, result): the nine identification runs of the simulated machine and the joint
    identification of them (units and machine name from the profile), made once a session. Read-only."""
    from gateway.identify import identify
    from gateway.profile import load_profile
    from simulators.machine import load_scenario, simulate

    profile = load_profile(PROFILES / "sim-vmc.toml")
    train = [simulate(load_scenario(n)).recording() for n in SIM_EXPERIMENTS]
    result = identify(train, factors=profile.factor_names, axes=profile.axes,
                      units={f.name: f.unit for f in profile.factors}, machine=profile.name)
    return profile, train, result


@pytest.fixture(scope="session")
def sim_csv_dir(tmp_path_factory) -> Path:
    """A folder with ``<name>.csv`` and ``<name>.truth.csv`` of the nine identification runs and the bundled
    production day, as ``cncgw simulate record`` writes them; written once a session. Read-only."""
    from simulators.machine import load_scenario, simulate
    from simulators.machine.run import write_run

    d = tmp_path_factory.mktemp("sim-runs")
    for n in (*SIM_EXPERIMENTS, "production-day"):
        write_run(simulate(load_scenario(n)), d)
    return d
