"""The README's main-job command: simulate, identify, then the closed loop against the simulated devices."""

from __future__ import annotations

import re
from pathlib import Path

from gateway.cli import main
from gateway.model import load_model


def test_demo_runs_closed_loop_and_cuts_the_error(tmp_path, capsys):
    # the first 3 h of the validation run: the 1000 rpm phase with its peak, then cooling
    assert main(["demo", "-o", str(tmp_path / "out"), "--hours", "3"]) == 0
    out, err = capsys.readouterr()
    assert "3/3 closed loop" in out
    # the gateway's coverage warnings (the y feed's current per feed below the experiments' in windows 60-109)
    # come after the table, not on stderr between its rows
    assert "leaves the identification's coverage" not in err
    warned = out.index("the gateway warned")
    assert out.index("window 60 leaves the identification's coverage: y_i_sq per y_feed") > warned
    *_, last_row = re.finditer(r"^\s+\d+\.\dh\s+\d+rpm .*$", out, flags=re.M)
    assert warned > last_row.end()
    assert "-0.00" not in out
    table = re.findall(r"^\s+\d+\.\dh\s+\d+rpm\s+(-?[\d.]+) um\s+(-?[\d.]+) um\s+(-?[\d.]+) um\s+(-?[\d.]+) um", out,
                       flags=re.M)
    assert len(table) >= 4  # a row every 30 simulated minutes once the gateway runs (it starts during the idle hour)
    rows = re.findall(r"^\s+([xyz])\s+([\d.]+) um\s+([\d.]+) um\s+(-?\d+) %$", out, flags=re.M)
    assert [r[0] for r in rows] == ["x", "y", "z"]
    for axis, before, after, reduction in rows:
        assert float(after) < float(before), axis
        assert int(reduction) >= 70, (axis, reduction)
    assert float(rows[2][1]) > 19.0  # z peaks near 20 um at 2 h
    assert "every one applied as written" in out
    assert "figures valid: 180 of 180 windows had their data" in out  # lock-step: whatever else the PC does
    model = load_model(tmp_path / "out" / "sim-vmc.model.toml")
    assert model.machine == "sim-vmc"
    assert len(list((tmp_path / "out" / "experiments").glob("*.truth.csv"))) == 9
    assert Path(tmp_path / "out" / "demo.png").read_bytes()[:4] == b"\x89PNG"
    assert (tmp_path / "out" / "live" / "records.sqlite").exists()


def test_a_demo_whose_windows_lack_data_says_its_figures_are_invalid_and_why():
    from gateway.commands.demo import _validity

    line = _validity(367, 181, lockstep=False, speedup=480.0)
    assert line.strip().startswith("FIGURES INVALID: 181 of 367 windows lacked their data")
    assert "did not keep up with sampling every 2 ms of wall time at 480x" in line
    assert "without --realtime" in line
    assert _validity(461, 4, lockstep=False, speedup=480.0).strip().startswith("figures valid: 457 of 461")
