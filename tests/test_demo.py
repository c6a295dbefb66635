"""The README's main-job command runs the workflow end to end and reports what compensation would leave."""

from __future__ import annotations

import re
from pathlib import Path

from gateway.cli import main
from gateway.model import load_model


def test_demo_runs_end_to_end(tmp_path, capsys):
    assert main(["demo", "-o", str(tmp_path / "out")]) == 0
    out = capsys.readouterr().out
    rows = re.findall(r"^\s+(spindle-feeds|production-day)\s+([xyz])\s+([\d.]+) um\s+([\d.]+) um\s+(-?\d+) %$",
                      out, flags=re.M)
    assert len(rows) == 6
    for run, axis, before, after, reduction in rows:
        assert float(after) < float(before), (run, axis)
        if run == "spindle-feeds":  # the paper's kind of run: compensation leaves a few percent
            assert int(reduction) >= 90, (run, axis, reduction)
    model = load_model(tmp_path / "out" / "sim-vmc.model.toml")
    assert model.machine == "sim-vmc"
    assert len(list((tmp_path / "out" / "experiments").glob("*.truth.csv"))) == 9
    assert Path(tmp_path / "out" / "demo.png").read_bytes()[:4] == b"\x89PNG"
