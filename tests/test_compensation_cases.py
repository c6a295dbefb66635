"""Golden cases of the live sections ([live], [compensation], [opcua]): each folder in compensation_cases/
holds profile.toml and either expected-summary.txt (``cncgw profile check`` prints exactly that) or
expected-error.txt (exactly those lines on stderr). Regenerate one by deleting it and running with
CNCGW_REGOLD=1.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from gateway.cli import main
from gateway.profile import load_profile

CASES = sorted(p for p in (Path(__file__).parent / "compensation_cases").iterdir() if p.is_dir())


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_compensation_case(case: Path, capsys, monkeypatch):
    monkeypatch.chdir(case)
    code = main(["profile", "check", "profile.toml"])
    out, err = capsys.readouterr()
    summary, error = case / "expected-summary.txt", case / "expected-error.txt"
    if os.environ.get("CNCGW_REGOLD") and not summary.exists() and not error.exists():
        (summary if code == 0 else error).write_text(out if code == 0 else err)
    if summary.exists():
        assert case.name.startswith("ok-")
        assert code == 0, err
        assert out == summary.read_text()
    else:
        assert case.name.startswith("err-")
        assert code == 3
        assert err == error.read_text()


def test_parsed_values_of_the_full_case():
    p = load_profile(Path(__file__).parent / "compensation_cases" / "ok-live-opcua" / "profile.toml")
    c = p.compensation
    assert (c.enabled, c.host, c.port, c.limit_um, c.max_step_um, c.aim) == (True, "10.0.0.5", 5020, 80.0, 1.5,
                                                                              "estimate")
    (z,) = c.axes
    assert (z.axis, z.register, z.readback, z.sign, z.unit_um, z.data_type) == ("z", 100, 200, -1.0, 0.5, "int16")
    assert z.encode(-3) == [0xFFFD]
    assert z.decode([0xFFFD]) == -3
    assert (p.live.gap_policy, p.live.stale_after_s, p.live.history_max_h) == ("reference", 300.0, 48.0)
    assert p.opcua.security == ("None", "Basic256Sha256_SignAndEncrypt")
    assert p.opcua.certificate == p.path.parent / "pki" / "cert.der"
    assert p.opcua.endpoint == "opc.tcp://0.0.0.0:4841/cncgw/"


def test_defaults_are_a_dry_run_on_loopback():
    p = load_profile(Path(__file__).parent / "compensation_cases" / "ok-dry-run" / "profile.toml")
    assert not p.compensation.enabled
    assert [(a.axis, a.register, a.sign, a.unit_um) for a in p.compensation.axes] == [
        ("x", 0, -1.0, 0.1), ("y", 2, -1.0, 0.1), ("z", 4, -1.0, 0.1)]
    assert (p.opcua.host, p.opcua.port, p.opcua.security, p.opcua.writable) == ("127.0.0.1", 4840, ("None",), False)
    assert (p.live.gap_policy, p.live.gap_hold_max_s, p.live.stale_after_s) == ("hold", 600.0, 150.0)
