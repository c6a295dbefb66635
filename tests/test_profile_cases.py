"""Golden profile cases: each folder in profile_cases/ (offline sections) and driver_cases/ (devices and
channels) holds profile.toml and either expected-summary.txt
(``cncgw profile check`` succeeds and prints exactly that) or expected-error.txt (it fails with exactly
those lines on stderr). Regenerate a case's expectation by deleting it and running with CNCGW_REGOLD=1.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from gateway.cli import main

CASES = sorted(p for folder in ("profile_cases", "driver_cases")
               for p in (Path(__file__).parent / folder).iterdir() if p.is_dir())


@pytest.mark.parametrize("case", CASES, ids=[f"{c.parent.name}/{c.name}" for c in CASES])
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


@pytest.mark.parametrize("name", ["sim-vmc.toml", "paper-vm40iii.toml", "template.toml"])
def test_bundled_profiles_are_valid(name, capsys):
    profiles = Path(__file__).resolve().parent.parent / "profiles"
    assert main(["profile", "check", str(profiles / name)]) == 0
    out = capsys.readouterr().out
    assert ": OK" in out.splitlines()[0]
    if name != "template.toml":
        assert "factors   9" in out
