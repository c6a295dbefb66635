"""The command line: identify -> estimate on files, and user mistakes as one-line errors."""

from __future__ import annotations

import argparse
import dataclasses
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gateway.cli import build_parser, main
from gateway.errors import EXIT_CODES, GatewayError
from gateway.model import FirstOrder, PathTF, SecondOrder, ThermalModel, load_model, save_model
from gateway.profile import load_profile
from gateway.recording import read_for_profile, read_recording, write_recording
from gateway.replay import estimate
from gateway.synthetic import Segment, make_recording, schedule_inputs

PROFILE = """
[machine]
name = "bench-lathe"
axes = ["x", "z"]

[factors.speed]
unit = "rpm"
stat = "mean"

[factors.i_sq]
unit = "A^2"
channel = "spindle_current"
stat = "mean_square"
"""

TRUTH = ThermalModel(
    axes=("x", "z"), factors=("speed", "i_sq"), units={"speed": "rpm", "i_sq": "A^2"}, reference={},
    paths={("z", "speed"): PathTF(axis="z", factor="speed",
                                  terms=(SecondOrder.from_time_constants(gain=0.01, tau1_s=500, tau2_s=2500),)),
           ("z", "i_sq"): PathTF(axis="z", factor="i_sq", terms=(FirstOrder(gain=0.05, tau_s=1200),)),
           ("x", "i_sq"): PathTF(axis="x", factor="i_sq", terms=(FirstOrder(gain=-0.02, tau_s=3000),))})


def write(path: Path, levels: list[tuple[int, dict]], seed: int) -> Path:
    u = schedule_inputs([Segment(minutes=m, levels=lv) for m, lv in levels], TRUTH.factors, {})
    rec = make_recording(TRUTH, u, name=path.stem, noise_um=0.05, seed=seed, zero_um={"x": 1.0, "z": 4.0})
    cols = {"speed": rec.factors["speed"], "i_sq": rec.factors["i_sq"], "x_um": rec.displacement["x"],
            "z_um": rec.displacement["z"]}
    return write_recording(path, time_s=rec.time_s, columns=cols)


@pytest.fixture
def workdir(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    Path("lathe.toml").write_text(PROFILE)
    write(Path("exp1.csv"), [(30, {}), (60, {"speed": 2000, "i_sq": 40}), (510, {})], 1)
    write(Path("exp2.csv"), [(30, {}), (60, {"speed": 800, "i_sq": 60}), (510, {})], 2)
    write(Path("val.csv"), [(20, {}), (40, {"speed": 1500, "i_sq": 50}), (30, {}), (90, {"speed": 600, "i_sq": 30}),
                            (180, {})], 3)
    return tmp_path


def test_identify_never_replaces_a_model_unless_forced(workdir, capsys):
    assert main(["identify", "--profile", "lathe.toml", "exp1.csv", "exp2.csv", "-o", "model.toml"]) == 0
    first = Path("model.toml").read_bytes()
    capsys.readouterr()
    # refused before any work (exit 1: an output exists without --force), the model a gateway may be running
    # untouched
    assert main(["identify", "--profile", "lathe.toml", "exp1.csv", "-o", "model.toml"]) == 1
    assert "cncgw: error: model.toml exists: pass --force to replace it, or -o another file" in capsys.readouterr().err
    assert Path("model.toml").read_bytes() == first
    assert main(["identify", "--profile", "lathe.toml", "exp1.csv", "-o", "model.toml", "--force"]) == 0
    assert Path("model.toml").read_bytes() != first


def test_identify_then_estimate_on_files(workdir, capsys):
    assert main(["identify", "--profile", "lathe.toml", "exp1.csv", "exp2.csv", "-o", "model.toml",
                 "--plot", "fit.png"]) == 0
    out = capsys.readouterr().out
    assert "identified 2 axes x 2 factors from 2 experiment(s) with the joint method" in out
    assert "wrote model.toml" in out
    model = load_model("model.toml")
    assert model.machine == "bench-lathe"
    assert model.path("z", "speed").gain == pytest.approx(0.01, rel=0.05)
    assert Path("fit.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    assert main(["estimate", "--profile", "lathe.toml", "--model", "model.toml", "val.csv", "-o", "pred.csv",
                 "--json", "--plot", "val.png"]) == 0
    report = json.loads(capsys.readouterr().out)
    z = report[0]["axes"]["z"]
    assert z["peak_um"] > 10.0
    assert z["max_error_pct_of_peak"] < 5.0  # held-out run, plant of the model's own kind
    assert report[0]["settings"] == {"initial": "first", "gap_policy": "hold", "align": "start", "initial_state": "rest"}
    pred = read_recording("pred.csv", factor_columns={}, displacement_columns={"z": "z_est_um"})
    assert len(pred) == 360
    assert {"x_resid_um", "z_meas_um"} <= set(pred.extras)
    assert np.nanmax(np.abs(pred.extras["z_resid_um"])) == pytest.approx(z["max_abs_error_um"])
    assert Path("val.png").read_bytes()[:4] == b"\x89PNG"

    assert main(["model", "show", "model.toml"]) == 0
    shown = capsys.readouterr().out
    assert "z    speed" in shown
    assert "identified with the joint method from exp1, exp2" in shown


def test_model_envelope_adds_what_the_recordings_support_to_an_older_model(workdir, capsys):
    old = dataclasses.replace(TRUTH, machine="bench-lathe")  # as written before envelopes: none
    save_model(old, "old.model.toml")
    assert main(["model", "show", "old.model.toml"]) == 0
    assert "plausibility envelope: none" in capsys.readouterr().out
    assert main(["model", "envelope", "--profile", "lathe.toml", "old.model.toml", "exp1.csv", "exp2.csv",
                 "-o", "new.model.toml"]) == 0
    env = load_model("new.model.toml").envelope
    profile = load_profile("lathe.toml")
    preds = [estimate(TRUTH, read_for_profile(f, profile)).estimated for f in ("exp1.csv", "exp2.csv")]
    for i, a in enumerate(TRUTH.axes):  # the true peak, up to the measurement's noise (0.05 um)
        assert env.axes[a].max_abs_um == pytest.approx(max(np.max(np.abs(p[i])) for p in preds), abs=0.3), a
        change = max(np.max(np.abs(np.diff(p[i], prepend=0.0))) for p in preds)  # the model's own, exactly
        assert env.axes[a].max_change_um == pytest.approx(change, rel=1e-9), a
    assert env.axes["z"].max_abs_um > 10.0
    assert load_model("old.model.toml").envelope is None  # -o leaves the original as it was
    assert main(["model", "show", "new.model.toml"]) == 0
    assert "z: |displacement| up to" in capsys.readouterr().out


def test_paper_method_from_the_cli(workdir, capsys):
    write(Path("exp3.csv"), [(30, {}), (60, {"speed": 1600, "i_sq": 20}), (510, {})], 4)
    # two co-varying factors need two experiments in different ratios; a third in another ratio breaks (1)
    code = main(["identify", "--profile", "lathe.toml", "exp1.csv", "exp2.csv", "exp3.csv", "--method", "paper",
                 "-o", "paper.toml"])
    err = capsys.readouterr().err
    assert code == 6
    assert "condition (1) fails for the factors {speed, i_sq}: they change together in 3 experiment(s)" in err
    assert main(["identify", "--profile", "lathe.toml", "exp1.csv", "exp2.csv", "--method", "paper",
                 "--max-iter", "200", "-o", "paper.toml"]) == 0
    assert "group {speed, i_sq} from exp1, exp2" in capsys.readouterr().out
    assert load_model("paper.toml").path("z", "speed").kind == "second_order"


@pytest.mark.parametrize(("argv", "code", "message"), [
    (["identify", "--profile", "lathe.toml", "nope.csv"], 4, "cncgw: error: nope.csv: file not found"),
    (["identify", "--profile", "missing.toml", "exp1.csv"], 3, "cncgw: error: missing.toml: file not found"),
    (["estimate", "--profile", "lathe.toml", "val.csv"], 5,
     "cncgw: error: lathe.model.toml: model file not found; create it with `cncgw identify --profile lathe.toml "
     "EXPERIMENTS... -o lathe.model.toml`"),
    (["estimate", "--profile", "lathe.toml", "--model", "lathe.toml", "val.csv"], 5,
     "cncgw: error: lathe.toml: a machine profile (it has [machine]), not a model file: expected a model written by "
     "cncgw identify; pass the profile with --profile (its [model] file is the default model)"),
    (["identify", "--profile", "lathe.toml", "exp1.csv", "--period-s", "-3"], 2,
     "argument --period-s: expected a number > 0, got '-3'"),
    (["identify", "--profile", "lathe.toml", "exp1.csv", "--structures", "third_order"], 2,
     "argument --structures: third_order: expected a comma-separated list from first_order, second_order, two_modes"),
    (["demo", "-o", "d", "--hours", "1"], 2,
     "cncgw: error: --hours 1: the validation run 'spindle-feeds' rests for its first 1 h (the spindle starts then)"
     " and needs at least 10 min of work after it: expected more than 1 h 10 min, e.g. --hours 3"),
])
def test_user_mistakes_are_one_line_errors(workdir, capsys, argv, code, message):
    try:
        got = main(argv)
    except SystemExit as exc:  # argparse's own errors
        got = exc.code
    err = capsys.readouterr().err
    assert got == code
    assert message in err
    assert "Traceback" not in err


def test_estimate_refuses_a_model_of_another_machine(workdir, capsys):
    other = ThermalModel(axes=("z",), factors=("spindle_power",), units={}, reference={}, paths={})
    from gateway.model import save_model

    save_model(other, "other.toml")
    assert main(["estimate", "--profile", "lathe.toml", "--model", "other.toml", "val.csv"]) == 5
    assert ('other.toml: factor "spindle_power" is not in profile lathe.toml (its factors: speed, i_sq)'
            in capsys.readouterr().err)


def test_estimate_warns_when_the_model_names_another_machine(workdir, capsys):
    # the same factors and axes, but identified on another machine: offline figures, with a warning
    from gateway.model import FirstOrder, PathTF, save_model

    twin = ThermalModel(axes=("z",), factors=("speed", "i_sq"), units={}, reference={}, machine="lathe-2", paths={
        ("z", "speed"): PathTF(axis="z", factor="speed", terms=(FirstOrder(gain=0.01, tau_s=1800.0),))})
    save_model(twin, "twin.toml")
    assert main(["estimate", "--profile", "lathe.toml", "--model", "twin.toml", "val.csv"]) == 0
    err = capsys.readouterr().err
    assert 'twin.toml: the model names machine "lathe-2", this profile is machine' in err
    assert "`cncgw run` refuses it" in err


def test_estimate_warns_of_an_axis_not_measured_beside_a_column_that_may_be_it(workdir, capsys):
    # x_mm beside no x_um: read as no measurement of x, which the figures then left out without a word
    assert main(["identify", "--profile", "lathe.toml", "exp1.csv", "exp2.csv", "-o", "model.toml"]) == 0
    text = Path("val.csv").read_text().replace(",x_um,", ",x_mm,")
    Path("val-mm.csv").write_text(text)
    capsys.readouterr()
    assert main(["estimate", "--profile", "lathe.toml", "--model", "model.toml", "val-mm.csv"]) == 0
    out, err = capsys.readouterr()
    assert ('cncgw: warning: val-mm.csv: no column "x_um" (the measured displacement x, in um): axis x is not '
            'measured in it; not read: x_mm (if one of them is it, in um, name it "x_um")') in err
    assert "  x: RMS" not in out
    assert "  z: RMS" in out
    # diagnose does not try it as a signal for z (a displacement explains another axis only by the same heat);
    # nor does an axis measured in no recording it judges on break the joint choice of a machine-wide setting
    # (an IndexError: the axes' folds differed) or print "held-out RMS x nan -> nan um"
    assert main(["diagnose", "--profile", "lathe.toml", "--model", "model.toml", "exp1.csv", "exp2.csv",
                 "val-mm.csv", "--json"]) == 0
    out, err = capsys.readouterr()
    doc = json.loads(out)
    assert not any("nan" in c for c in doc["conclusions"]), doc["conclusions"]
    assert doc["held_out"]["before"]["x"]["windows"] == 0
    assert doc["held_out"]["before"]["z"]["windows"] > 0
    assert "not read: x_mm" in err
    assert any(c.startswith("not tried as signals: x_mm (each may be a measured displacement") for c in
               doc["conclusions"]), doc["conclusions"]
    assert not any("x_mm" in t["hypothesis"] for t in doc["trials"])
    # the one spelled in a micro sign or in full-width letters is it: refused, named
    for name in ("x_\u00b5m", "\uff58_um"):
        Path("val-u.csv").write_text(text.replace(",x_mm,", f",{name},"))
        assert main(["estimate", "--profile", "lathe.toml", "--model", "model.toml", "val-u.csv"]) != 0
        assert f'column "{name}" looks like the measured displacement x ("x_um", in um)' in capsys.readouterr().err


def test_a_mistyped_model_file_is_named_with_the_model_file_beside_it(workdir, capsys):
    Path("vmc.model.toml").write_text("")  # only its name matters: the error comes before any reading
    assert main(["estimate", "--profile", "lathe.toml", "--model", "vmc.modle.toml", "val.csv"]) == 5
    assert ('cncgw: error: vmc.modle.toml: model file not found (did you mean "vmc.model.toml"?); create it with '
            "`cncgw identify --profile lathe.toml EXPERIMENTS... -o vmc.modle.toml`") in capsys.readouterr().err


def test_console_script_exits_without_traceback(workdir):
    bad = Path("bad.csv")
    bad.write_text("time_s,speed,i_sq,x_um,z_um\n60,0,0,0,0\n120,0,zero,0,0\n")
    proc = subprocess.run([sys.executable, "-m", "gateway.cli", "estimate", "--profile", "lathe.toml",
                           "--model", "nothing.toml", "bad.csv"], capture_output=True, text=True, check=False)
    assert proc.returncode == 5
    assert proc.stderr.strip() == ("cncgw: error: nothing.toml: model file not found; create it with `cncgw identify "
                                   "--profile lathe.toml EXPERIMENTS... -o nothing.toml`")


def test_estimate_with_an_absurd_model_is_an_error_not_a_memory_error(workdir, capsys):
    from gateway.model import save_model

    save_model(TRUTH, "lathe.model.toml")
    text = Path("lathe.model.toml").read_text()
    Path("late.toml").write_text(text.replace('factor = "i_sq"\n', 'factor = "i_sq"\ndelay_s = 1e12\n', 1))
    assert main(["estimate", "--profile", "lathe.toml", "--model", "late.toml", "val.csv"]) == 5
    err = capsys.readouterr().err
    assert "late.toml:" in err
    assert "delay_s: expected a dead time from 0 to 86400 s (1 day), got 1000000000000.0" in err
    assert "Traceback" not in err


def _all_parsers(parser):
    yield parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                yield from _all_parsers(sub)


def test_help_texts_show_no_rest_markup():
    parsers = list(_all_parsers(build_parser()))
    assert len(parsers) > 15
    for p in parsers:
        text = p.format_help()
        assert "`" not in text, f"{p.prog}: {[line for line in text.splitlines() if '`' in line]}"
        assert ":mod:" not in text, p.prog


def _error_classes(cls=GatewayError):
    for sub in cls.__subclasses__():
        yield sub
        yield from _error_classes(sub)


def test_every_exit_code_is_in_help_and_readme_and_every_error_has_one():
    build_parser()  # imports every command module, and so every error class
    codes = dict(EXIT_CODES)
    assert {GatewayError.exit_code, *(c.exit_code for c in _error_classes())} <= set(codes)
    epilog = build_parser().format_help()
    for code, meaning in EXIT_CODES:
        assert f"{code:>3}  {meaning}" in epilog
    readme = (Path(__file__).resolve().parent.parent / "README.md").read_text()
    table = readme[readme.index("## Exit codes"):readme.index("## Layout")]
    rows = {int(m[0]): m[1].replace("\\|", "|") for m in re.findall(r"^\| (\d+) \| (.+?) \|$", table, re.M)}
    assert rows == codes


@pytest.mark.parametrize("value", ["0", "1", "1.5", "-0.1", "nan", "x"])
def test_a_share_option_out_of_0_1_names_both_bounds(workdir, capsys, value):
    with pytest.raises(SystemExit) as refused:
        main(["diagnose", "--profile", "sim-vmc", "day1.csv", "--alpha", value])
    assert refused.value.code == 2
    assert (f"argument --alpha: expected a number between 0 and 1 (exclusive), got '{value}'"
            in capsys.readouterr().err)


def test_diagnose_history_without_validate_is_a_usage_error_not_ignored(workdir, capsys):
    assert main(["diagnose", "--profile", "sim-vmc", "day1.csv", "--history", "day0.csv"]) == 2
    assert capsys.readouterr().err == ("cncgw: error: --history day0.csv: it carries the machine's state into the first "
                                       "--validate recording, and no --validate was given (expected --validate "
                                       "RECORDING with it)\n")


def test_a_bad_argument_value_found_after_parsing_is_a_usage_error(workdir, capsys):
    from tests_paths import PROFILES

    assert main(["run", "--profile", str(PROFILES / "sim-vmc.toml"), "--data", "d", "--rt-priority", "200"]) == 2
    assert capsys.readouterr().err == "cncgw: error: --rt-priority must be 0 (the normal scheduler) or 1-99 (SCHED_FIFO). Got 200\n"
    assert not Path("d").exists()


def test_identify_on_fewer_windows_than_parameters_says_so(workdir, capsys):
    write(Path("short.csv"), [(2, {}), (2, {"speed": 1000, "i_sq": 40})], 4)  # found by bench/fuzz.py: an IndexError
    assert main(["identify", "--profile", "lathe.toml", "short.csv", "-o", "short.model.toml"]) == 6
    err = capsys.readouterr().err
    assert err.startswith("cncgw: error: axis x: 4 windows with measured displacement cannot fix the 5 parameters of "
                          "the simplest structure (first_order, 2 paths, 1 experiment offsets): expected at least 6")


def test_a_workbook_or_a_folder_given_for_a_recording_is_named_as_such(workdir, capsys):
    # an Excel workbook was "byte 0xd6 is not UTF-8 ... save as CSV UTF-8" at line 1; a folder was a raw OS error
    Path("ACE_X.xlsx").write_bytes(b"PK\x03\x04\x14\x00\x06\x00\x08\x00\xd6\xff" + bytes(range(256)))
    Path("runs").mkdir()
    for given, message in (("ACE_X.xlsx", "ACE_X.xlsx: a zip archive (an Excel .xlsx workbook is one), not a CSV "
                                          'text: expected a recording as CSV (in Excel: save as "CSV UTF-8")'),
                           ("runs", "runs: a folder, not a file: expected a recording (CSV); give its files one "
                                    "by one (in a shell: runs/*.csv)")):
        assert main(["identify", "--profile", "lathe.toml", given, "-o", "m.toml"]) != 0
        err = capsys.readouterr().err
        assert message in err
        assert "Traceback" not in err
        assert "Errno" not in err


def test_a_file_of_days_with_a_time_column_splits_into_days_without_the_nights_between(workdir, capsys):
    # a new user's file: two days of 180 rows with the time of day, nothing recorded over the night between them;
    # each day's run ran on over the night's empty windows to the next day's start (1440 windows, "1233 missing
    # window(s)", recorded columns said to be in 15 % of the windows)
    from gateway.commands._common import split_by
    from gateway.profile import load_profile
    from gateway.recording import read_for_profile

    lines = Path("val.csv").read_text().splitlines()
    head = [ln for ln in lines if ln.startswith("#")]
    body = [ln for ln in lines if not ln.startswith("#")]
    rows = [ln.split(",") for ln in body[1:]]
    night_s = 20 * 3600.0
    days = [",".join([f"{float(r[0]) + (night_s if k >= 180 else 0.0):.6g}", *r[1:], "1" if k < 180 else "2"])
            for k, r in enumerate(rows)]
    Path("days.csv").write_text("\n".join([*head, body[0] + ",day", *days]) + "\n")
    runs = split_by(read_for_profile("days.csv", load_profile("lathe.toml")), "day")
    assert [(r.source, len(r)) for r in runs] == [("days.csv[day=1]", 180), ("days.csv[day=2]", len(rows) - 180)]
    assert all(r.present.all() and not r.gaps for r in runs)
    assert main(["identify", "--profile", "lathe.toml", "exp1.csv", "exp2.csv", "-o", "m.toml"]) == 0
    capsys.readouterr()
    assert main(["estimate", "--profile", "lathe.toml", "--model", "m.toml", "days.csv", "--split-by", "day",
                 "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert [e["axes"]["z"]["windows"] for e in out] == [180, len(rows) - 180]
    assert not any("missing window" in n for e in out for n in e["notes"])


def test_a_blank_stretch_of_factor_cells_is_said_where_it_is(workdir, capsys):
    # a new user's file with half an hour of blank CNC cells: the estimate (and a diagnosis) over it and for hours
    # after rests on the gap policy; the note said how many rows, not where
    lines = Path("val.csv").read_text().splitlines()
    k = next(i for i, ln in enumerate(lines) if not ln.startswith("#"))
    header = lines[k].split(",")
    cols = [header.index("speed"), header.index("i_sq")]
    for i in range(k + 1 + 100, k + 1 + 130):
        cells = lines[i].split(",")
        for c in cols:
            cells[c] = ""
        lines[i] = ",".join(cells)
    Path("blank.csv").write_text("\n".join(lines) + "\n")
    assert main(["identify", "--profile", "lathe.toml", "exp1.csv", "exp2.csv", "-o", "m.toml"]) == 0
    capsys.readouterr()
    assert main(["estimate", "--profile", "lathe.toml", "--model", "m.toml", "blank.csv", "--json"]) == 0
    (e,) = json.loads(capsys.readouterr().out)
    (note,) = [n for n in e["notes"] if "empty factor cells" in n]
    assert note.startswith("30 row(s) with empty factor cells (the longest: 30 windows from 1.67 h); gap policy hold")


def test_a_history_read_with_a_row_period_ran_just_before_the_recording(workdir, capsys):
    # files without a time column each count from 0: --history was refused ("ends at t=5940 s, not before ...
    # starts (t=0 s)"), which the user could not mend; it is taken to end one window before, as times would say
    lines = Path("val.csv").read_text().splitlines()
    k = next(i for i, ln in enumerate(lines) if not ln.startswith("#"))
    body = lines[k + 1:]
    for name, rows in (("am", body[:150]), ("pm", body[150:])):
        Path(f"{name}_t.csv").write_text("\n".join([lines[k], *rows]) + "\n")
        Path(f"{name}.csv").write_text("\n".join(",".join(ln.split(",")[1:]) for ln in [lines[k], *rows]) + "\n")
    assert main(["identify", "--profile", "lathe.toml", "exp1.csv", "exp2.csv", "-o", "m.toml"]) == 0
    capsys.readouterr()
    runs = {}
    for tag, args in (("timed", ["--history", "am_t.csv", "pm_t.csv"]),
                      ("period", ["--period-s", "60", "--history", "am.csv", "pm.csv", "pm.csv"])):
        assert main(["estimate", "--profile", "lathe.toml", "--model", "m.toml", *args, "--json"]) == 0
        runs[tag] = json.loads(capsys.readouterr().out)
    timed, (period, again) = runs["timed"][0], runs["period"]
    assert any(n.startswith("started in the state am.csv left") for n in period["notes"])
    for a in ("x", "z"):
        assert period["axes"][a]["rms_um"] == pytest.approx(timed["axes"][a]["rms_um"], rel=1e-9)
    # a second file carries on from the first (it ran just after it, times counted from 0 again)
    assert any(n.startswith("started in the state pm.csv left") for n in again["notes"])


def test_a_file_split_by_a_date_keeps_its_dates_and_two_runs_of_one_name_are_not_written_over(workdir, capsys):
    from gateway.commands._common import split_by
    from gateway.recording import read_for_profile

    assert main(["identify", "--profile", "lathe.toml", "exp1.csv", "exp2.csv", "-o", "m.toml"]) == 0
    lines = Path("val.csv").read_text().splitlines()
    head = [ln for ln in lines if ln.startswith("#")]
    body = [ln for ln in lines if not ln.startswith("#")]
    half = (len(body) - 1) // 2
    dated = [body[0] + ",date"] + [f"{ln},{20240105 if k < half else 20240106}" for k, ln in enumerate(body[1:])]
    Path("dated.csv").write_text("\n".join([*head, *dated]) + "\n")
    from gateway.profile import load_profile

    runs = split_by(read_for_profile("dated.csv", load_profile("lathe.toml")), "date")
    assert [r.source for r in runs] == ["dated.csv[date=20240105]", "dated.csv[date=20240106]"]  # not 2.02401e+07
    for d in ("a", "b"):
        Path(d).mkdir()
        Path(d, "val.csv").write_text(Path("val.csv").read_text())
    capsys.readouterr()
    assert main(["estimate", "--profile", "lathe.toml", "--model", "m.toml", "a/val.csv", "b/val.csv", "-o", "out"]) == 2
    err = capsys.readouterr().err
    assert "-o out: a/val.csv and b/val.csv would both be written to out/val.pred.csv" in err
    assert not Path("out").exists()
    assert main(["estimate", "--profile", "lathe.toml", "--model", "m.toml", "dated.csv", "--split-by", "date", "-o",
                 "out"]) == 0
    assert sorted(p.name for p in Path("out").iterdir()) == ["dated[date=20240105].pred.csv",
                                                           "dated[date=20240106].pred.csv"]
    # a second run (other options) never replaces the first one's files without --force: refused before the work
    first = Path("out", "dated[date=20240105].pred.csv").read_text()
    capsys.readouterr()
    assert main(["estimate", "--profile", "lathe.toml", "--model", "m.toml", "dated.csv", "--split-by", "date", "-o",
                 "out", "--align", "none"]) == 1
    assert capsys.readouterr().err == ("cncgw: error: out/dated[date=20240105].pred.csv exists (and 1 more of the 2 "
                                       "it would write): pass --force to replace it, or -o another directory\n")
    assert Path("out", "dated[date=20240105].pred.csv").read_text() == first
    assert main(["estimate", "--profile", "lathe.toml", "--model", "m.toml", "dated.csv", "--split-by", "date", "-o",
                 "out", "--align", "none", "--force"]) == 0
    assert Path("out", "dated[date=20240105].pred.csv").read_text() != first
    # one recording, one file: the same
    assert main(["estimate", "--profile", "lathe.toml", "--model", "m.toml", "val.csv", "-o", "val.pred.csv"]) == 0
    capsys.readouterr()
    assert main(["estimate", "--profile", "lathe.toml", "--model", "m.toml", "val.csv", "-o", "val.pred.csv"]) == 1
    assert capsys.readouterr().err == ("cncgw: error: val.pred.csv exists: pass --force to replace it, or -o another "
                                       "file\n")
