"""Golden profile cases: each folder in driver_cases/ holds profile.toml and either expected-summary.txt
(``cncgw profile check`` succeeds and prints exactly that) or expected-error.txt (it fails with exactly
those lines on stderr). Regenerate a case's expectation by deleting it and running with CNCGW_REGOLD=1.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from gateway.cli import main

CASES = sorted(p for p in (Path(__file__).parent / "driver_cases").iterdir() if p.is_dir())


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_profile_case(case: Path, capsys, monkeypatch):
    monkeypatch.chdir(case)
    code = main(["profile", "check", "profile.toml"])
    out, err = capsys.readouterr()
    summary, error = case / "expected-summary.txt", case / "expected-error.txt"
    if os.environ.get("CNCGW_REGOLD") and not summary.exists() and not error.exists():
        (summary if code == 0 else error).write_text(out if code == 0 else err)
    if summary.exists():
        assert code == 0, err
        assert out == summary.read_text()
    else:
        assert error.exists(), f"{case.name}: no expected-summary.txt or expected-error.txt"
        assert code == 3
        assert out == ""
        assert err == error.read_text()
        assert "Traceback" not in err


def test_every_case_is_named_for_its_outcome():
    for case in CASES:
        has_summary = (case / "expected-summary.txt").exists()
        assert case.name.startswith("ok-" if has_summary else "err-"), case.name

