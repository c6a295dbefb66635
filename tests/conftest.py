"""Shared fixtures. Every test runs under a leak check: a test that leaves a thread running fails."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest
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
