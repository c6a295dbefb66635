"""What a plant engineer trips on at first contact: the README's commands on an install without extras,
from outside the repository, and the files a user really makes (spreadsheets, wrong settings)."""

from __future__ import annotations

import json
import re
import sys

import pytest

from gateway.cli import main


@pytest.fixture(scope="module")
def random_spindle(tmp_path_factory):
    """The paper's random spindle run (6 h) recorded by the simulated machine."""
    out = tmp_path_factory.mktemp("rec")
    assert main(["simulate", "record", "random-spindle", "-o", str(out), "--no-progress"]) == 0
    return out / "random-spindle.csv"


@pytest.fixture
def no_matplotlib(monkeypatch):
    """An install without the [engineering] extra: matplotlib cannot be imported (find_spec says so too)."""
    for name in [m for m in sys.modules if m == "matplotlib" or m.startswith("matplotlib.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "matplotlib", None)


# ------------------------------------------------------------------------------ installs without matplotlib ---
@pytest.mark.parametrize("command", ["identify", "estimate"])
def test_plot_without_matplotlib_is_refused_before_any_work(command, no_matplotlib, tmp_path, capsys):
    # recordings that do not exist: the refusal comes first, not after minutes of identification
    out = tmp_path / "m.model.toml"
    args = [command, "--profile", "sim-vmc", str(tmp_path / "none.csv"), "--plot", str(tmp_path / "f.png")]
    assert main(args + (["-o", str(out)] if command == "identify" else [])) == 1
    err = capsys.readouterr().err
    assert "--plot: plots need matplotlib" in err
    assert "pip install 'cncgw[engineering]'" in err
    assert "none.csv" not in err
    assert not out.exists()


def test_diagnose_without_matplotlib_writes_its_report_and_model(random_spindle, no_matplotlib, tmp_path, capsys):
    out = tmp_path / "diag"
    assert main(["diagnose", "--profile", "sim-vmc", str(random_spindle), "-o", str(out), "--no-reidentify"]) == 0
    captured = capsys.readouterr()
    assert "figures: skipped (matplotlib is not installed" in captured.err
    assert f"wrote {out / 'report.md'}" in captured.out
    assert (out / "sim-vmc.diagnosed.model.toml").exists()
    doc = json.loads((out / "report.json").read_text())
    assert doc["figures"] == []
    assert not list(out.glob("*.png"))


# ------------------------------------------------------------------------------------- diagnose --split-by ---
def _moved_rows(rec, um_by_row):
    """``rec``'s header and rows (split on commas), each displacement moved by ``um_by_row(row index)`` um."""
    lines = [ln for ln in rec.read_text().splitlines() if not ln.startswith("#")]
    um = [k for k, name in enumerate(lines[0].split(",")) if name.endswith("_um")]
    rows = [[f"{float(v) + um_by_row(i):g}" if k in um and v else v for k, v in enumerate(ln.split(","))]
            for i, ln in enumerate(lines[1:])]
    return lines[0], rows


def _two_days(rec, path):
    """``rec`` twice, one after the other, with a day column: a logger's file of several days.

    Each day's displacement is moved (0.2 and 0.3 um): two runs, not one given three times (refused).
    """
    header, one = _moved_rows(rec, lambda i: 0.2)
    _, two = _moved_rows(rec, lambda i: 0.3)
    last = float(one[-1][0])
    out = [header + ",day"]
    out += [",".join(r) + ",1" for r in one]
    out += [",".join([f"{float(r[0]) + last:g}", *r[1:]]) + ",2" for r in two]
    path.write_text("\n".join(out) + "\n")
    return path


def _other_run(rec, path, um_by_row=lambda i: 0.5):
    """``rec`` with its displacement moved (0.5 um higher): another run (diagnose refuses to validate on one it fits)."""
    header, rows = _moved_rows(rec, um_by_row)
    path.write_text("\n".join([header, *(",".join(r) for r in rows)]) + "\n")
    return path


def test_split_by_splits_the_files_that_have_the_column_and_keeps_the_others_whole(random_spindle, tmp_path,
                                                                                   capsys):
    days = _two_days(random_spindle, tmp_path / "days.csv")
    other = _other_run(random_spindle, tmp_path / "other.csv")
    # the README's workflow: the experiments (here one recording without a day column), a file of several
    # days, and a validation run without one: it had failed on the first file without the column (exit 1)
    assert main(["diagnose", "--profile", "sim-vmc", str(random_spindle), str(days), "--split-by", "day",
                 "--validate", str(other), "--no-reidentify", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["recordings"] == [str(random_spindle), f"{days}[day=1]", f"{days}[day=2]"]
    assert len(doc["validation"]) == 1


def test_split_by_a_column_no_recording_has_is_a_usage_error_naming_the_files(random_spindle, tmp_path, capsys):
    days = _two_days(random_spindle, tmp_path / "days.csv")
    assert main(["diagnose", "--profile", "sim-vmc", str(random_spindle), str(days), "--split-by", "shift"]) == 2
    err = capsys.readouterr().err
    assert 'no recording has a numeric column "shift"' in err
    assert f"{days}: day" in err
    assert f"{random_spindle}: none" in err


def test_a_recording_too_short_to_hold_out_anything_is_refused_not_reassured(random_spindle, tmp_path, capsys):
    # a new user's one-row file: "within inf % of the peak displacement" and "nothing significant is missing"
    lines = random_spindle.read_text().splitlines()
    k = next(i for i, ln in enumerate(lines) if not ln.startswith("#"))
    short = tmp_path / "short.csv"
    short.write_text("\n".join(lines[: k + 2]) + "\n")
    assert main(["diagnose", "--profile", "sim-vmc", str(short)]) == 4  # a bad recording
    err = capsys.readouterr().err
    assert err.startswith("cncgw: error: short: 1 window(s) with measured displacement")
    assert "give 0 held-out block(s); a diagnosis judges on at least 3" in err
    assert main(["estimate", "--profile", "sim-vmc", str(short)]) == 0
    out = capsys.readouterr().out
    assert "no displacement to take a share of (1 windows)" in out
    assert "inf %" not in out


def test_a_new_users_slips_get_one_line_that_says_what_to_do(random_spindle, tmp_path, capsys):
    from tests_paths import ROOT

    # another machine's model: one line saying so first, not eleven lines of factors
    assert main(["estimate", "--profile", str(ROOT / "bench" / "profiles" / "ace-lathe.toml"), "--model",
                 str(ROOT / "profiles" / "sim-vmc.model.toml"), str(random_spindle)]) != 0
    first = capsys.readouterr().err.splitlines()[0]
    assert re.search(r'sim-vmc.model.toml: a model of machine "sim-vmc", but profile .*ace-lathe.toml is machine '
                     r'"[^"]+" \(\d+ of its \d+ factors are not in the profile\)', first), first
    # --split-by with the column's name in another case
    days = _two_days(random_spindle, tmp_path / "days.csv")
    assert main(["diagnose", "--profile", "sim-vmc", str(days), "--split-by", "Day"]) == 2
    assert 'no recording has a numeric column "Day" (did you mean "day"?)' in capsys.readouterr().err
    # a file without a time column: the option that reads it is named
    lines = random_spindle.read_text().splitlines()
    k = next(i for i, ln in enumerate(lines) if not ln.startswith("#"))
    untimed = tmp_path / "untimed.csv"
    untimed.write_text("\n".join(",".join(ln.split(",")[1:]) for ln in lines[k:]) + "\n")
    assert main(["estimate", "--profile", "sim-vmc", str(untimed)]) != 0
    assert 'a file without one needs its row period: --period-s S' in capsys.readouterr().err
    # a history of several runs: which one ran just before is the user's to say
    before = tmp_path / "before.csv"
    before.write_text(days.read_text())
    assert main(["estimate", "--profile", "sim-vmc", str(days), "--split-by", "day", "--history", str(before)]) == 2
    assert f"--history {before}: 2 runs of --split-by day (" in capsys.readouterr().err
    # --split-by a measurement (it changes in every row) rather than a run label
    body = [ln for ln in lines[k + 1:] if ln and not ln.startswith("#")]
    wobbly = tmp_path / "wobbly.csv"
    wobbly.write_text("\n".join([lines[k] + ",hall_c", *(f"{ln},{20 + 0.01 * i:.2f}" for i, ln in enumerate(body))])
                      + "\n")
    assert main(["estimate", "--profile", "sim-vmc", str(wobbly), "--split-by", "hall_c"]) == 2
    assert (f"--split-by hall_c: {len(body)} runs, {len(body)} of them under 10 rows: the column changes value in "
            "most rows") in capsys.readouterr().err
    # a validation recording of one row
    one = tmp_path / "one.csv"
    one.write_text("\n".join(lines[: k + 2]) + "\n")
    assert main(["diagnose", "--profile", "sim-vmc", str(random_spindle), "--validate", str(one)]) == 2
    assert (f'--validate {one}: 1 window(s) with measured displacement ("x_um", "y_um", "z_um"): a validation '
            "needs at least 10") in capsys.readouterr().err
    # one without any displacement column: refused the same way (it may lack one axis, not all)
    blind = tmp_path / "blind.csv"
    cols = lines[k].split(",")
    keep = [i for i, c in enumerate(cols) if not c.endswith("_um")]
    blind.write_text("\n".join([",".join(cols[i] for i in keep), *(",".join(ln.split(",")[i] for i in keep)
                                                                  for ln in body)]) + "\n")
    assert main(["diagnose", "--profile", "sim-vmc", str(random_spindle), "--validate", str(blind)]) == 2
    assert f"--validate {blind}: 0 window(s) with measured displacement" in capsys.readouterr().err


def test_files_of_one_name_in_two_folders_are_told_apart_wherever_the_report_names_a_recording(random_spindle,
                                                                                               tmp_path, capsys):
    n = sum(not ln.startswith("#") for ln in random_spindle.read_text().splitlines())
    for day, drift in (("d1", 4.0), ("d2", -3.0)):  # a sensor drifting by some um over the run: windows to locate
        (tmp_path / day).mkdir()
        _other_run(random_spindle, tmp_path / day / "log.csv", lambda i, drift=drift: drift * i / n)
    out = tmp_path / "diag"
    assert main(["diagnose", "--profile", "sim-vmc", str(tmp_path / "d1" / "log.csv"), str(tmp_path / "d2" / "log.csv"),
                 "--no-reidentify", "-o", str(out), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["labels"] == ["d1/log", "d2/log"]
    named = {w["recording"] for f in doc["findings"].values() for w in f["windows"]}
    named |= {c["recording"] for f in doc["findings"].values() for c in f["change_points"]}
    assert named, "nothing located: the test shows nothing"
    assert named <= {"d1/log", "d2/log"}, named
    from gateway.model import load_model

    assert load_model(out / "sim-vmc.diagnosed.model.toml").info["diagnosis"]["recordings"] == ["d1/log", "d2/log"]


# ------------------------------------------------------------------------------ diagnose: what it refuses ---
def test_a_recording_given_twice_is_refused_by_its_content(random_spindle, tmp_path, capsys):
    copy = tmp_path / "copy.csv"
    copy.write_bytes(random_spindle.read_bytes())
    for twice, said in (([random_spindle, random_spindle], "given twice"),
                        ([random_spindle, copy], f"the same data as {random_spindle}")):
        assert main(["diagnose", "--profile", "sim-vmc", *map(str, twice), "--no-reidentify"]) == 2
        err = capsys.readouterr().err
        assert f"{twice[1]}: {said}" in err
        assert "doubles its evidence" in err


def test_identify_refuses_an_experiment_given_twice(random_spindle, tmp_path, capsys):
    out = tmp_path / "m.model.toml"
    assert main(["identify", "--profile", "sim-vmc", str(random_spindle), str(random_spindle), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"{random_spindle}: given twice: a recording given twice weighs twice in the fit" in err
    assert not out.exists()


def test_use_signal_of_a_column_no_recording_has_is_refused_naming_the_columns_there(random_spindle, capsys):
    assert main(["diagnose", "--profile", "sim-vmc", str(random_spindle), "--use-signal", "roomc"]) == 2
    err = capsys.readouterr().err
    assert "--use-signal roomc: no recording has a column 'roomc'" in err
    assert "(recorded columns: " in err


@pytest.mark.parametrize(("blocks", "said"), [("1", "expected an integer >= 3 (held-out blocks of time), got '1'"),
                                              ("abc", "expected an integer >= 3 (held-out blocks of time), got 'abc'"),
                                              ("100000", "--blocks 100000: these recordings hold 6 h, so the blocks "
                                                         "would be 6e-05 h long")])
def test_held_out_blocks_too_few_or_shorter_than_an_hour_are_refused(random_spindle, blocks, said, capsys):
    try:
        code = main(["diagnose", "--profile", "sim-vmc", str(random_spindle), "--blocks", blocks])
    except SystemExit as e:  # argparse's own refusal of the value
        code = e.code
    assert code == 2
    err = capsys.readouterr().err
    assert said in err


def test_a_model_of_another_machine_is_diagnosed_with_a_warning_the_report_keeps(random_spindle, capsys):
    from gateway import BUNDLED

    assert main(["diagnose", "--profile", "paper-vm40iii", "--model", str(BUNDLED / "sim-vmc.model.toml"),
                 str(random_spindle), "--no-reidentify", "--json"]) == 0
    captured = capsys.readouterr()
    said = 'the model names machine "sim-vmc", this profile is machine "paper-vm40iii"'
    assert f"cncgw: warning: {BUNDLED / 'sim-vmc.model.toml'}: {said}" in captured.err
    assert any(said in c for c in json.loads(captured.out)["conclusions"])


# ---------------------------------------------------------------------------------- wrong units, bad files ---
def _profile(tmp_path, old, new):
    """The bundled profile with one line changed, its model the bundled one."""
    from gateway import BUNDLED

    text = (BUNDLED / "sim-vmc.toml").read_text()
    assert old in text
    text = text.replace(old, new).replace('file = "sim-vmc.model.toml"',
                                          f'file = "{(BUNDLED / "sim-vmc.model.toml").as_posix()}"')
    path = tmp_path / "p.toml"
    path.write_text(text)
    return path


def test_a_row_period_that_is_not_the_files_is_an_error_not_gaps(random_spindle, tmp_path, capsys):
    # period_s = 1 typed for a file of minutes: read as 59 missing windows after every row, filled by the
    # gap policy, it gave other figures (z max error 3.5 -> 12.5 % of peak on spindle-feeds) without a word
    profile = _profile(tmp_path, "period_s = 60.0", "period_s = 1.0")
    assert main(["estimate", "--profile", str(profile), str(random_spindle)]) == 4
    err = capsys.readouterr().err
    assert f"{random_spindle}:" in err
    assert "rows are 60 s apart (the median of 359 steps), 60 times the row period of 1 s" in err
    assert "[recording] period_s in the profile, or --period-s" in err
    # the file's own period reads it
    assert main(["estimate", "--profile", str(profile), "--period-s", "60", str(random_spindle)]) == 0
    capsys.readouterr()
    # another one is not taken over the times written in the file (every time constant would be off by 2)
    assert main(["estimate", "--profile", str(profile), "--period-s", "30", str(random_spindle)]) == 4
    assert (f'{random_spindle}: its time column "time_s" has rows 60 s apart, but --period-s 30 was given'
            in capsys.readouterr().err)


def _excel(text: str, sep: str = ";") -> bytes:
    """``text`` as Excel saves "CSV" where the decimal mark is a comma: a BOM, CRLF, ';' and '12,5'."""
    lines = [ln if ln.startswith("#") else ln.replace(",", sep).replace(".", ",") for ln in text.splitlines()]
    return ("\ufeff" + "\r\n".join(lines) + "\r\n").encode("utf-8")


@pytest.mark.parametrize("sep", [";", "\t"])
def test_a_recording_saved_by_a_spreadsheet_reads_as_the_original(random_spindle, tmp_path, sep):
    from gateway.profile import load_profile
    from gateway.recording import read_for_profile

    profile = load_profile("sim-vmc")
    excel = tmp_path / "excel.csv"
    excel.write_bytes(_excel(random_spindle.read_text(), sep))
    a, b = read_for_profile(random_spindle, profile), read_for_profile(excel, profile)
    assert b.meta == a.meta
    assert list(b.factors) == list(a.factors)
    for name in a.factors:
        assert b.factors[name].tolist() == a.factors[name].tolist()
    for axis in a.displacement:
        assert b.displacement[axis].tolist() == a.displacement[axis].tolist()
    assert b.time_s.tolist() == a.time_s.tolist()


def test_a_point_in_a_file_with_decimal_commas_is_an_error_naming_the_cell(random_spindle, tmp_path, capsys):
    # "1.000" in such a file may be a thousands separator: never read as 1
    text = _excel(random_spindle.read_text()).decode("utf-8").splitlines()
    row = next(i for i, ln in enumerate(text) if ln.startswith("600,0;"))
    cells = text[row].split(";")
    cells[1] = "1.000"
    text[row] = ";".join(cells)
    bad = tmp_path / "bad.csv"
    bad.write_text("\n".join(text) + "\n")
    assert main(["estimate", "--profile", "sim-vmc", str(bad)]) == 4
    err = capsys.readouterr().err
    assert f'{bad}:{row + 1}: column "spindle_speed": "1.000" has a "." where this file\'s decimal mark is ","' in err


def test_a_probe_file_saved_by_a_spreadsheet_reads_as_the_original(tmp_path):
    from gateway.adaptive.probes import read_probes

    plain = tmp_path / "probes.csv"
    plain.write_text("time,seq,x_um,y_um,z_um,sd_um\n7200,1,0.5,-0.6,2.0,0.3\n14400,2,,-0.3,3.25,0.3\n")
    excel = tmp_path / "probes-excel.csv"
    excel.write_bytes(_excel(plain.read_text()))
    got = read_probes(excel)
    want = read_probes(plain)
    assert [(p.seq, p.time_s, p.values_um, p.sd_um) for p in got] == \
        [(p.seq, p.time_s, p.values_um, p.sd_um) for p in want]
    assert got[1].values_um == {"y": -0.3, "z": 3.25}


def test_a_recording_in_a_spreadsheets_code_page_names_the_line(tmp_path, capsys):
    path = tmp_path / "ansi.csv"
    path.write_bytes("time_s,spindle_speed\n# room in \u00b0C\n".encode("cp1252"))
    assert main(["estimate", "--profile", "sim-vmc", str(path)]) == 4
    assert f'{path}:2: byte 0xb0 is not UTF-8: expected a UTF-8 text (in Excel save as "CSV UTF-8")' in \
        capsys.readouterr().err


def test_a_recording_cut_short_mid_row_says_so(random_spindle, tmp_path, capsys):
    text = random_spindle.read_text()
    lines = text.splitlines(keepends=True)
    k = len(lines) // 2
    cut = tmp_path / "cut.csv"
    cut.write_text("".join(lines[:k]) + ",".join(lines[k].split(",")[:3]))  # a copy stopped mid-row
    assert main(["estimate", "--profile", "sim-vmc", str(cut)]) == 4
    err = capsys.readouterr().err
    assert f"{cut}:{k + 1}: the file ends in the middle of this row (3 of 13 cells, no line end)" in err


# --------------------------------------------------------------------------- the README's paths, installed ---
def test_the_readmes_profile_path_outside_a_checkout_names_the_bundled_profile(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)  # no profiles/ folder here, as after `pip install cncgw`
    assert main(["profile", "check", "profiles/sim-vmc.toml"]) == 3
    assert capsys.readouterr().err.strip() == ("cncgw: error: profiles/sim-vmc.toml: file not found; sim-vmc is a "
                                               "profile bundled with cncgw: from any directory, --profile sim-vmc")


def test_a_missing_model_of_a_bundled_profile_says_to_identify_with_its_name(tmp_path, capsys):
    model = tmp_path / "m.model.toml"
    assert main(["estimate", "--profile", "sim-vmc", "--model", str(model), str(tmp_path / "r.csv")]) == 5
    err = capsys.readouterr().err
    assert f"create it with `cncgw identify --profile sim-vmc EXPERIMENTS... -o {model}`" in err


def test_a_model_file_given_as_the_profile_is_one_line(capsys):
    from gateway import BUNDLED

    model = BUNDLED / "sim-vmc.model.toml"
    assert main(["profile", "check", str(model)]) == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"cncgw: error: {model}: a model file (it has [[path]] tables), not a profile: expected a "
                   "machine profile with [machine] and [factors.*]; pass the model with --model"]


# ------------------------------------------------------------------------------------------------ cncgw run ---
def test_an_opc_ua_port_in_use_is_one_line_saying_what_to_do(caplog):
    import logging
    import socket

    from gateway import BUNDLED
    from gateway.errors import GatewayError
    from gateway.live.opcua_server import OpcUaServer
    from gateway.model import load_model
    from gateway.profile import load_profile
    from gateway.profile.live import OpcUa

    # another gateway (or the CNC's own OPC UA server) already listens on the profile's port
    with socket.socket() as other:
        other.bind(("127.0.0.1", 0))
        other.listen()
        port = other.getsockname()[1]
        caplog.set_level(logging.INFO)
        server = OpcUaServer(OpcUa(port=port), profile=load_profile("sim-vmc"),
                             model=load_model(BUNDLED / "sim-vmc.model.toml"))
        with pytest.raises(GatewayError) as err:
            server.start()
    assert str(err.value) == (f"OPC UA server on 127.0.0.1:{port} failed to start: the port is in use (another "
                              "gateway or OPC UA server on this PC?): expected a free port: set [opcua] port in the "
                              "profile, or run with --no-opcua")
    assert err.value.exit_code == 1
    # asyncua's own record of it, with its traceback, is not printed before that line
    assert not [r for r in caplog.records if r.exc_info or "error starting server" in r.getMessage()]


# ------------------------------------------------------------------------------------ probes, offline ---
def test_probes_on_another_clock_than_the_recording_are_said_to_change_nothing(random_spindle, tmp_path, capsys):
    probes = tmp_path / "probes.csv"
    # stamped on the shop's clock (seconds since some epoch) while the recording counts from its start
    probes.write_text("time,seq,x_um,y_um,z_um,sd_um\n1007200,1,0.5,-0.6,2.0,0.3\n1014400,2,0.9,-0.3,3.0,0.3\n")
    assert main(["estimate", "--profile", "sim-vmc", "--probes", str(probes), str(random_spindle)]) == 0
    captured = capsys.readouterr()
    assert (f"cncgw: warning: {probes}: none of its 2 probes (time 1007200-1014400 s) falls within a recording "
            f"({random_spindle}: 60-21600 s): the estimates below are the model's alone") in captured.err
    assert "0 probe-axes applied, 0 refused, 2 probes outside this recording" in captured.out
    # probes within it: no warning
    probes.write_text("time,seq,x_um,y_um,z_um,sd_um\n7200,1,0.5,-0.6,2.0,0.3\n")
    assert main(["estimate", "--profile", "sim-vmc", "--probes", str(probes), str(random_spindle)]) == 0
    assert "warning" not in capsys.readouterr().err


# ------------------------------------------------- Workflow step 6: compare a dry run's audit log with measurements ---
def test_audit_prints_a_dry_runs_log_as_csv_without_touching_it(tmp_path, capsys):
    import csv
    import io

    from gateway.live.audit import AUDIT_NAME, AuditLog, WriteEntry

    log = AuditLog(tmp_path / AUDIT_NAME)  # a running gateway holds it open
    log.event(0.0, "start", "gateway", "vmc-3: compensation dry run")
    log.write(WriteEntry(t_s=3660.0, window=60, mode="dry-run", estimate_um={"x": -0.17, "z": -2.6181},
                         target_um={"x": 0.25, "z": 3.57}, commanded_um={"x": 0.2, "z": 3.6},
                         applied_um={"x": float("nan"), "z": float("nan")}, verified=False, wall_s=1.8e9))
    before = (tmp_path / AUDIT_NAME).read_bytes()
    assert main(["audit", "--data", str(tmp_path)]) == 0
    rows = list(csv.DictReader(io.StringIO(capsys.readouterr().out)))
    assert rows == [{"t_s": "3660.000", "wall_time": "2027-01-15T08:00:00Z", "window": "60", "mode": "dry-run",
                     "verified": "0", "status": "", "x_estimate_um": "-0.1700", "x_target_um": "0.2500",
                     "x_commanded_um": "0.2000", "x_applied_um": "", "z_estimate_um": "-2.6181",
                     "z_target_um": "3.5700", "z_commanded_um": "3.6000", "z_applied_um": "", "note": ""}]
    assert main(["audit", "--data", str(tmp_path), "--events"]) == 0
    assert capsys.readouterr().out == "t_s,kind,name,message\n0.000,start,gateway,vmc-3: compensation dry run\n"
    assert (tmp_path / AUDIT_NAME).read_bytes() == before
    log.close()
    assert main(["audit", "--data", str(tmp_path / "nope")]) == 2
    assert "no audit.sqlite: expected the --data directory of cncgw run" in capsys.readouterr().err


# ------------------------------------------------------------------------------- never lose recorded data ---
@pytest.mark.parametrize(("command", "option"), [("estimate", "-o"), ("estimate", "--plot"), ("identify", "--plot"),
                                                 ("identify", "-o")])
def test_an_output_naming_an_input_recording_is_refused_before_it_is_touched(command, option, random_spindle,
                                                                              tmp_path, capsys):
    rec = tmp_path / "day.csv"
    rec.write_bytes(random_spindle.read_bytes())
    extra = ["--force"] if command == "identify" else []  # identify -o: even with --force
    assert main([command, "--profile", "sim-vmc", str(rec), option, str(rec), *extra]) == 2
    assert f"{option} {rec}: that is an input of this command ({rec}): expected a new file" in capsys.readouterr().err
    assert rec.read_bytes() == random_spindle.read_bytes()


@pytest.mark.parametrize("args", [["--seed", "-3"], ["--variant", "-1"], ["--probes-every-h", "0"],
                                  ["--probes-every-h", "13"]])
def test_a_bad_simulate_record_option_value_is_a_usage_error(args, tmp_path, capsys):
    # exit 2 as the README's table says for a bad argument value (7 is a bad scenario file)
    assert main(["simulate", "record", "spindle-1000rpm", "-o", str(tmp_path), *args]) == 2
    assert f"cncgw: error: {args[0]}" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


def test_record_with_a_device_that_never_answers_exits_8_and_keeps_what_it_recorded(tmp_path, capsys):
    import socket

    with socket.socket() as s:  # a port nothing listens on: the board is off or the address is wrong
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    profile = _profile(tmp_path, "port = 5020", f"port = {port}")
    out = tmp_path / "rec"
    # it exited 0 after a run of empty windows: a script or a unit took that for a recording
    assert main(["record", "--profile", str(profile), "--out", str(out), "--speedup", "60", "--minutes", "1",
                 "--quiet"]) == 8
    captured = capsys.readouterr()
    assert 'cncgw: error: device "adc" never answered while recording' in captured.err
    assert f"cannot connect to 127.0.0.1:{port}" in captured.err
    assert f"exported to {out / 'sim-vmc.csv'}" in captured.out
    text = (out / "sim-vmc.csv").read_text()
    windows = int(re.search(r"# windows: (\d+)", text).group(1))
    assert windows >= 1
    assert f"# insufficient_windows: {windows} (factors left empty)" in text


def test_a_spreadsheets_trailing_empty_columns_are_ignored_and_a_nameless_column_with_data_is_not(random_spindle,
                                                                                                   tmp_path, capsys):
    from gateway.profile import load_profile
    from gateway.recording import read_for_profile

    lines = [ln if ln.startswith("#") else ln + ";;" for ln in _excel(random_spindle.read_text()).decode("utf-8")
             .removeprefix("\ufeff").splitlines()]
    wide = tmp_path / "wide.csv"
    wide.write_text("\r\n".join(lines) + "\r\n")
    profile = load_profile("sim-vmc")
    a, b = read_for_profile(random_spindle, profile), read_for_profile(wide, profile)
    assert b.factors["spindle_speed"].tolist() == a.factors["spindle_speed"].tolist()
    assert b.displacement["z"].tolist() == a.displacement["z"].tolist()
    assert set(b.extras) == set(a.extras)
    # a value under a nameless column is data without a name: still an error naming the column
    row = next(i for i, ln in enumerate(lines) if ln.startswith("600,0;"))
    lines[row] += "7"
    wide.write_text("\r\n".join(lines) + "\r\n")
    assert main(["estimate", "--profile", "sim-vmc", str(wide)]) == 4
    assert (f'{wide}:{row + 1}: column 15 holds "7" but has no name in the header on line 7: expected a name for '
            "every column with data") in capsys.readouterr().err


def test_an_audit_csv_that_exists_is_not_replaced_without_force_exit_1(tmp_path, capsys):
    from gateway.live.audit import AUDIT_NAME, AuditLog

    AuditLog(tmp_path / AUDIT_NAME).close()
    out = tmp_path / "audit.csv"
    out.write_text("mine\n")
    assert main(["audit", "--data", str(tmp_path), "-o", str(out)]) == 1  # the table: an output exists
    assert f"{out} exists: pass --force to replace it" in capsys.readouterr().err
    assert out.read_text() == "mine\n"
    assert main(["audit", "--data", str(tmp_path), "-o", str(out), "--force"]) == 0
    assert out.read_text().startswith("t_s,wall_time,window,mode")


@pytest.mark.parametrize("command", ["run", "record"])
def test_a_data_directory_that_is_a_file_is_one_line_not_a_traceback(command, tmp_path, capsys):
    target = tmp_path / "data"
    target.write_text("a file the user had there\n")
    option = "--data" if command == "run" else "--out"
    assert main([command, "--profile", "sim-vmc", option, str(target), "--minutes", "1", "--speedup", "60"]) == 1
    err = capsys.readouterr().err
    what = "data" if command == "run" else "output"
    assert f"cncgw: error: {target}: cannot be the {what} directory: a file, not a directory" in err
    assert "Traceback" not in err
    assert target.read_text() == "a file the user had there\n"


def test_an_output_in_a_missing_folder_is_one_line_and_refused_before_the_work_where_it_is_slow(random_spindle,
                                                                                                 tmp_path, capsys):
    missing = tmp_path / "nodir"
    # estimate (seconds): written at the end, one line naming the file (it was a FileNotFoundError traceback)
    assert main(["estimate", "--profile", "sim-vmc", str(random_spindle), "-o", str(missing / "p.csv")]) == 1
    assert capsys.readouterr().err == (f"cncgw: error: {missing / 'p.csv'}: No such file or directory (an output's "
                                       "folder must exist)\n")
    # identify, diagnose, plan (minutes): refused before the work; identify had fitted, then failed on its .tmp
    assert main(["identify", "--profile", "sim-vmc", str(tmp_path / "none.csv"), "-o", str(missing / "m.toml")]) == 2
    assert f"-o {missing / 'm.toml'}: the folder {missing} does not exist" in capsys.readouterr().err
    afile = tmp_path / "afile"
    afile.write_text("x\n")
    none = str(tmp_path / "none.csv")
    for command in (["diagnose", "--profile", "sim-vmc", none], ["plan", "--profile", "sim-vmc", none,
                                                                 "--production", none]):
        assert main([*command, "-o", str(afile)]) == 2
        assert f"-o {afile}: a file, not a directory" in capsys.readouterr().err
    assert not missing.exists()
    assert afile.read_text() == "x\n"


def test_a_profile_made_by_profile_new_is_found_by_its_name_as_the_bundled_ones_are(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["profile", "new", "vmc-3"]) == 0
    capsys.readouterr()
    # `--profile sim-vmc` works from anywhere, so a newcomer types `--profile vmc-3` for the one just made
    assert main(["profile", "check", "vmc-3"]) == 0
    assert capsys.readouterr().out.startswith("profile   vmc-3.toml: OK")


def test_a_profile_given_as_the_model_is_one_line(random_spindle, capsys):
    from gateway import BUNDLED

    profile = BUNDLED / "sim-vmc.toml"
    assert main(["estimate", "--profile", "sim-vmc", "--model", str(profile), str(random_spindle)]) == 5
    assert capsys.readouterr().err.splitlines() == [
        f"cncgw: error: {profile}: a machine profile (it has [machine]), not a model file: expected a model written "
        "by cncgw identify; pass the profile with --profile (its [model] file is the default model)"]


def test_profile_check_checks_the_model_file_it_names_against_the_profile(tmp_path, capsys):
    from gateway import BUNDLED

    # a unit typed otherwise than the model was identified with: profile check said OK, estimate and run exit 5
    profile = _profile(tmp_path, 'unit = "rpm"', 'unit = "rad/s"')
    assert main(["profile", "check", str(profile)]) == 5
    captured = capsys.readouterr()
    assert captured.out.startswith(f"profile   {profile}: OK")
    assert captured.err == (f'cncgw: error: {BUNDLED / "sim-vmc.model.toml"}: factor "spindle_speed" is in rpm but '
                            f"profile {profile} says rad/s\n")
    assert main(["profile", "check", str(_profile(tmp_path, 'unit = "rpm"', 'unit = "rpm"'))]) == 0


@pytest.mark.parametrize(("old", "new", "said"), [
    ("fast_period_s = 0.002", "fast_period_s = 2", "sampling.fast_period_s = 2 s: 30 samples a window; the fast "
                                                   "period is in seconds: if you meant 2 ms, write 0.002"),
    ("window_s = 60.0", "window_s = 60000", "sampling.window_s = 60000 s (16.7 h): a window is normally a minute "
                                            "(60), shorter than the fastest thermal time constants; if you meant "
                                            "60000 ms, write 60"),
])
def test_profile_check_says_when_a_period_looks_like_milliseconds(old, new, said, tmp_path, capsys):
    profile = _profile(tmp_path, old, new)
    assert main(["profile", "check", str(profile)]) == 0  # legal (a slow OPC UA poll is real): said, not refused
    assert capsys.readouterr().err == f"cncgw: warning: {profile}: {said}\n"
    assert main(["profile", "check", str(_profile(tmp_path, old, old))]) == 0
    assert capsys.readouterr().err == ""
