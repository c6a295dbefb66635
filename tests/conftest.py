"""Shared fixtures. Every test runs under a leak check: a test that leaves a thread running fails.

A test that samples on wall time runs alone: ``dev.py test`` runs them (marked ``realtime``, see ``REALTIME``)
in a process of their own after the 2 pytest-xdist workers; under xdist anyway each waits for the others.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
import threading
import time
import uuid
from pathlib import Path

import pytest
from sim_shared import SIM_EXPERIMENTS
from tests_paths import PROFILES, ROOT, SHARED_DATA

__all__ = ["PROFILES", "ROOT", "SHARED_DATA"]

#: tests that sample on wall time (the system clock or a ScaledClock): their timing margins (a 2 ms sampler,
#: a value within the last 0.1 s of wall time) assume the CPU is not shared with another test. Under
#: pytest-xdist each of them waits until no other worker runs a test, and the others wait for it (a failure
#: seen with 2 workers: test_drivers_opcua read a value more than 6 clock-s old at 60x). module -> test
#: names (a prefix of the id), or None: every test of the module
REALTIME: dict[str, tuple[str, ...] | None] = {
    # not the 2 ms factors nor the bursts: those step a ManualClock in lock-step with the devices
    "test_sampler.py": ("test_a_slow_device_skips_ticks", "test_a_device_dropped_mid_window"),
    "test_drivers_opcua.py": None,
    "test_link_budget_tcp.py": None,
    "test_record_store.py": ("test_cncgw_record_records_live_devices", "test_kill_9_while_recording"),
    "test_live_restart.py": ("test_kill_9_and_restart", "test_dry_run_at_10x"),
    "test_compensation.py": ("test_writer_thread_keeps_the_watchdog_alive_on_a_sped_up_clock",),
}


def pytest_configure(config):
    config.addinivalue_line("markers", "realtime: samples on wall time; under pytest-xdist it runs alone (conftest)")
    if not hasattr(config, "workerinput") and getattr(config.option, "testrunuid", "") is None:
        # the controller names the run (xdist hands it to the workers) so it can remove the run's lock files after
        # it: two files per run were left in the temporary folder (212 of them on one PC)
        config.option.testrunuid = uuid.uuid4().hex


def pytest_unconfigure(config):
    uid = getattr(config.option, "testrunuid", None)
    if uid and not hasattr(config, "workerinput"):
        for tail in (".turn", ".lock"):
            Path(f"{_lock_base(uid)}{tail}").unlink(missing_ok=True)


def _lock_base(uid: str) -> Path:
    return Path(tempfile.gettempdir()) / f"cncgw-tests-{uid}"


@pytest.hookimpl(tryfirst=True)  # before ``-m realtime`` / ``-m "not realtime"`` selects on it
def pytest_collection_modifyitems(items):
    for item in items:
        names = REALTIME.get(item.path.name, ())
        if names is None or any(item.name.startswith(n) for n in names):
            item.add_marker("realtime")


@contextlib.contextmanager
def _alone_or_shared(exclusive: bool):
    """A readers-writer lock across the xdist workers of this run (flock on two files): a realtime test
    takes it exclusively; the turnstile keeps other workers from starting tests while one waits."""
    import fcntl

    base = _lock_base(os.environ["PYTEST_XDIST_TESTRUNUID"])
    with open(f"{base}.turn", "a") as turn, open(f"{base}.lock", "a") as lock:
        fcntl.flock(turn, fcntl.LOCK_EX)
        fcntl.flock(lock, fcntl.LOCK_EX if exclusive else fcntl.LOCK_SH)
        fcntl.flock(turn, fcntl.LOCK_UN)
        try:
            yield
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    if "PYTEST_XDIST_TESTRUNUID" not in os.environ or os.name == "nt":
        yield
        return
    with _alone_or_shared(item.get_closest_marker("realtime") is not None):
        yield


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


@pytest.fixture(autouse=True)
def _no_leaked_signal_state():
    """A test that leaves this worker's SIGINT/SIGTERM handler or signal mask changed fails (and both are put
    back): every later child process would inherit an ignored or blocked Ctrl-C (a double Ctrl-C test of
    ``cncgw run`` timed out so when the whole suite ran as a background job, which ignores SIGINT from the
    start: see ``test_live_restart.dry_run``)."""
    import signal

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, [])
    yield
    changed = [f"{s.name} handler {h!r} -> {signal.getsignal(s)!r}" for s, h in handlers.items()
               if signal.getsignal(s) != h]
    now = signal.pthread_sigmask(signal.SIG_SETMASK, mask)
    if now != mask:
        changed.append(f"signal mask {sorted(m.name for m in mask)} -> {sorted(m.name for m in now)}")
    for s, h in handlers.items():
        if h is not None:
            signal.signal(s, h)
    assert not changed, f"test left this process's signal state changed: {'; '.join(changed)}"


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
