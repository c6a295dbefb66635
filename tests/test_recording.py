"""Recording CSV: messy but valid files are read, bad ones fail naming file, line and column."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gateway.errors import RecordingError
from gateway.recording import RecordingWriter, format_recording, read_recording, write_recording

F = {"speed": "speed_rpm", "i1": "i1_sq"}
D = {"z": "z_um"}


def read(text, **kw):
    kw = {"factor_columns": F, "displacement_columns": D, **kw}
    return read_recording("rec.csv", text=text, **kw)


def test_messy_but_valid_file_is_read():
    text = ("\ufeff# cncgw recording 1\n# scenario: warm-up\n"
            " time_s , speed_rpm , i1_sq , z_um , room_c , note\n"
            "60, 0, 1.5, 0.0, 20.1, idle\n"
            "# a comment between rows\n"
            "120 ,1000,5.25 , 0.5 ,20.2, run \n"
            "\n"
            "180,1000,5.0,,20.2,run\n")
    rec = read(text)
    assert rec.meta == {"scenario": "warm-up"}
    np.testing.assert_array_equal(rec.time_s, [60, 120, 180])
    np.testing.assert_array_equal(rec.factors["i1"], [1.5, 5.25, 5.0])
    assert math.isnan(rec.displacement["z"][2])  # empty cell: missing, not zero
    np.testing.assert_array_equal(rec.extras["room_c"], [20.1, 20.2, 20.2])  # extra numeric column kept
    assert rec.text["note"] == ("idle", "run", "run")  # extra text column kept
    assert rec.gaps == ()


def test_iso_time_and_gap_kept_explicit():
    text = ("time,speed_rpm,i1_sq,z_um\n"
            "2024-05-01T08:01:00Z,0,1,0\n"
            "2024-05-01T08:02:00Z,0,1,0.1\n"
            "2024-05-01T08:05:00Z,500,2,0.4\n")
    rec = read(text, time_column="time")
    assert len(rec) == 5  # two missing minutes inserted as explicit NaN rows
    np.testing.assert_array_equal(rec.present, [True, True, False, False, True])
    assert np.isnan(rec.factors["speed"][2:4]).all()
    assert rec.time_s[4] - rec.time_s[0] == 240.0
    assert rec.clock
    assert len(rec.gaps) == 1
    assert rec.gaps[0].rows == 2
    assert str(rec.gaps[0]) == f"2 missing windows after t={rec.time_s[1]:g} s"


def test_no_time_column_needs_period():
    rec = read("speed_rpm,i1_sq,z_um\n0,1,0\n10,2,0.5\n", time_column=None, period_s=30)
    np.testing.assert_array_equal(rec.time_s, [0, 30])
    assert rec.period_s == 30
    # its time of day is unknown (diagnosis tries no daily cycle on it), and so is that of its parts
    assert not rec.clock
    assert not rec.slice(1, 2).clock


@pytest.mark.parametrize(("text", "message"), [
    ("time_s,speed_rpm,i1_sq,z_um\n60,0,1,0\n60,0,1,0\n",
     'rec.csv:3: column "time_s": time does not increase (60 s after 60 s on line 2); expected strictly increasing time'),
    ("time_s,speed_rpm,i1_sq,z_um\n60,0,1,0\n120,fast,1,0\n",
     'rec.csv:3: column "speed_rpm": "fast" is not a number: expected a plain decimal such as -12.5 or 1.2e-3'),
    ("time_s,speed_rpm,i_sq,z_um\n60,0,1,0\n",
     'rec.csv:1: missing column "i1_sq" (factor i1) (did you mean "i_sq"?); columns are: time_s, speed_rpm, i_sq, z_um'),
    ("time_s,speed_rpm,i1_sq\n60,0,1\n",
     'rec.csv:1: missing column "z_um" (measured displacement z in um); columns are: time_s, speed_rpm, i1_sq'),
    ("time_s,speed_rpm,i1_sq,z_um\n60,0,1\n",
     "rec.csv:2: row has 3 cells, expected 4 (one per column of the header on line 1)"),
    ("time_s,speed_rpm,i1_sq,z_um\nyesterday,0,1,0\n",
     'rec.csv:2: column "time_s": "yesterday" is not a time: expected seconds (a plain decimal number) or an ISO '
     "8601 stamp"),
    ("time_s,speed_rpm,i1_sq,z_um\n60,0,1,0\n70,0,1,0\n",
     'rec.csv:3: column "time_s": rows only 10 s apart, expected the row period of 60 s '
     "(set the period to the file's own if it differs)"),
    ("time_s,speed_rpm,i1_sq,z_um\n60,inf,1,0\n", 'rec.csv:2: column "speed_rpm": "inf" is not a finite number'),
    ("# only comments\n", "rec.csv: no header row: expected a line of column names such as time_s,..."),
    ("time_s,speed_rpm,speed_rpm,i1_sq,z_um\n", 'rec.csv:1: column "speed_rpm" appears 2 times'),
])
def test_bad_files_name_file_line_and_column(text, message):
    with pytest.raises(RecordingError) as err:
        read(text)
    assert str(err.value) == message


H = "time_s,speed_rpm,i1_sq,z_um\n"


@pytest.mark.parametrize(("text", "message"), [
    # each was read as a number, or ended in a traceback, a MemoryError or millions of gap windows
    (H + "60,1_000,1,0\n", 'rec.csv:2: column "speed_rpm": "1_000" is not a number: expected a plain decimal such as '
                           "-12.5 or 1.2e-3"),
    (H + "60,\u0661\u0662\u0663,1,0\n", 'rec.csv:2: column "speed_rpm": "\u0661\u0662\u0663" is not a number: '
                                        "expected a plain decimal such as -12.5 or 1.2e-3"),
    (H + "60,0x10,1,0\n", 'rec.csv:2: column "speed_rpm": "0x10" is not a number: expected a plain decimal such as '
                          "-12.5 or 1.2e-3"),
    (H + "60,0,1,0\n1_20,0,1,0\n", 'rec.csv:3: column "time_s": "1_20" is not a time: expected seconds (a plain '
                                   "decimal number) or an ISO 8601 stamp"),
    (H + "60,1e308,1,0\n", 'rec.csv:2: column "speed_rpm": "1e308" is out of range: expected a magnitude of at most '
                           "1e+15 (in its unit)"),
    (H + "60,-Infinity,1,0\n", 'rec.csv:2: column "speed_rpm": "-Infinity" is not a finite number'),
    (H + "60,0,1,0\n1e12,0,1,0\n", 'rec.csv:3: column "time_s": "1e12" is out of range: expected seconds within '
                                   "+-1e+11 (an ISO 8601 stamp before the year 5138)"),
    (H + "60,0,1,0\n1e300,0,1,0\n", 'rec.csv:3: column "time_s": "1e300" is out of range: expected seconds within '
                                    "+-1e+11 (an ISO 8601 stamp before the year 5138)"),
    (H + "-1e9,0,1,0\n60,0,1,0\n120,0,1,0\n",
     'rec.csv:3: column "time_s": 60 s comes 1e+09 s after -1e+09 s on line 2: expected gaps of at most 604800 s '
     "(7 days); a longer pause is two recordings: split the file there"),
    (H + "60,0,1,0\n" + "".join(f"{k * 600000},0,1,0\n" for k in range(1, 120)),
     'rec.csv: column "time_s": the gaps add up to 1189880 missing windows of 60 s: expected at most 1000000 (split '
     "the recording, or give the row period it really has)"),
    (H + "60," + "1" * 200_000 + ",1,0\n", "rec.csv:2: a cell or comment longer than 131072 characters: expected the "
                                          "cells of one window"),
    ("# " + "x" * 200_000 + "\n" + H, "rec.csv:1: a cell or comment longer than 131072 characters: expected the cells "
                                      "of one window"),
])
def test_values_beyond_what_a_recording_holds_name_file_line_and_column(text, message):
    with pytest.raises(RecordingError) as err:
        read(text)
    assert str(err.value) == message


def test_the_largest_gap_allowed_is_read_as_explicit_missing_windows():
    rec = read(H + "60,0,1,0\n" + f"{60 + 7 * 86400},0,1,0\n")
    assert len(rec) == 7 * 1440 + 1
    assert rec.gaps[0].rows == 7 * 1440 - 1


@pytest.mark.parametrize("period_s", [1e-300, 1e-4, 86401.0, math.inf])
def test_a_row_period_out_of_range_is_refused(period_s):
    with pytest.raises(RecordingError, match=r"the row period must be from 0.0005 s to 86400 s \(a day\), got "):
        read("speed_rpm,i1_sq,z_um\n0,1,0\n", time_column=None, period_s=period_s)


def test_other_nan_spellings_are_missing_and_huge_extra_numbers_are_kept_as_text():
    rec = read("time_s,speed_rpm,i1_sq,z_um,stamp_ns\n60,Nan,1,0,1716000000000000000\n120,1,1,0,1716000060000000000\n")
    assert math.isnan(rec.factors["speed"][0])
    assert rec.text["stamp_ns"] == ("1716000000000000000", "1716000060000000000")
    assert "stamp_ns" not in rec.extras


def test_displacement_optional_when_not_required():
    rec = read("time_s,speed_rpm,i1_sq\n60,0,1\n", require_displacement=False)
    assert rec.displacement == {}
    # ... but a column that is it with more to its name is not silently read as no measurement at all
    for name in ("z_um (um)", "z_um [um]", "Z_UM", "z_um_um", "z-um.1"):
        with pytest.raises(RecordingError) as exc:
            read(f"time_s,speed_rpm,i1_sq,{name}\n60,0,1,0.5\n", require_displacement=False)
        assert str(exc.value) == (f'rec.csv:1: column "{name}" looks like the measured displacement z ("z_um", in um): '
                                  'expected the name "z_um" exactly')
    # ... and only such a one: words that merely hold the name's letters are other columns
    for name in ("xz_um", "z", "az_um_max", "z_mm"):
        assert read(f"time_s,speed_rpm,i1_sq,{name}\n60,0,1,0.5\n", require_displacement=False).displacement == {}


def test_columns_that_may_be_a_missing_axis_are_found_and_others_are_not():
    from gateway.recording import displacement_lookalikes

    maybe = ["x", "X", "x_mm", "x_disp_um", "disp_x_um", "dx_um", "xdisp", "xum", "x_micron", "x_displacement"]
    other = ["xz_um", "max_load", "y_pos", "index", "x2", "probe_x_um", "probe_sd_um"]
    rec = read(f"time_s,speed_rpm,i1_sq,z_um,{','.join(maybe + other)}\n60,0,1,0.5,{','.join(['1'] * 17)}\n",
               require_displacement=False)
    found = displacement_lookalikes(rec, {"x": "x_um", "z": "z_um"})
    assert found == {"x": maybe}  # z is measured: nothing looked for


def test_write_read_round_trip_is_exact(tmp_path):
    rng = np.random.default_rng(3)
    t = 60.0 * np.arange(1, 51)
    cols = {"speed_rpm": rng.random(50) * 1000, "i1_sq": rng.random(50) / 7, "z_um": rng.standard_normal(50)}
    cols["z_um"][7] = np.nan
    path = write_recording(tmp_path / "r.csv", time_s=t, columns=cols, meta={"seed": "3"})
    rec = read_recording(path, factor_columns=F, displacement_columns=D)
    np.testing.assert_array_equal(rec.factors["speed"], cols["speed_rpm"])
    np.testing.assert_array_equal(rec.factors["i1"], cols["i1_sq"])
    np.testing.assert_array_equal(rec.displacement["z"], cols["z_um"])
    assert rec.meta == {"seed": "3"}
    assert not (tmp_path / "r.csv.tmp").exists()


def test_format_writes_missing_as_empty_cells():
    text = format_recording(time_s=np.array([60.0]), columns={"a": np.array([np.nan])})
    assert text.splitlines()[-1] == "60.0,"


def test_real_spindle_file_without_time_column(shared_data):
    """SJTU motorized spindle: UTF-8 BOM, no time column, coarse displacement steps, 16 temperatures."""
    path = shared_data / "sjtu-spindle-thermal" / "thermal_expansion_error_original.csv"
    rec = read_recording(path, factor_columns={}, displacement_columns={"z": "delta L"}, time_column=None,
                         period_s=60.0)
    assert len(rec) == 4683  # SOURCE.md says 4682: its count misses the last row (no final newline)
    assert set(rec.extras) == {f"T{k}" for k in range(16)}
    z = rec.displacement["z"]
    assert z[0] == 0.0
    assert 17.0 < z.max() < 17.6
    # coarse resolution: steps of ~0.13 and ~0.26 um, so few distinct levels over 78 h
    assert len(np.unique(np.round(z, 6))) < 250
    assert np.min(np.abs(np.diff(z))[np.diff(z) != 0]) > 0.008


def test_real_cnc_signal_file_keeps_every_column(shared_data):
    """UMich CNC drive signals: unnamed index column, text columns, 100 ms rows."""
    path = shared_data / "umich-cnc-mill-signals" / "experiment_01.csv"
    rec = read_recording(path, factor_columns={"s": "S1_ActualVelocity", "i": "S1_CurrentFeedback"},
                         displacement_columns={}, time_column=None, period_s=0.1)
    assert len(rec) > 400
    assert "Machining_Process" in rec.text
    assert "X1_CurrentFeedback" in rec.extras
    assert np.isfinite(rec.factors["i"]).all()


def test_a_recording_written_in_chunks_equals_one_written_whole_and_a_failed_one_changes_nothing(tmp_path):
    t = np.arange(1.0, 8.0) * 60.0
    cols = {"a": np.linspace(0.0, 1.0, 7), "b": np.array([1.0, np.nan, 3.0, 4.0, 5.0, 6.0, 7.0])}
    whole = write_recording(tmp_path / "whole.csv", time_s=t, columns=cols, meta={"m": "1"}).read_text()
    with RecordingWriter(tmp_path / "parts.csv", names=["a", "b"], meta={"m": "1"}) as w:
        for part in (slice(0, 3), slice(3, 7)):
            w.write(t[part], {k: v[part] for k, v in cols.items()})
    assert (tmp_path / "parts.csv").read_text() == whole
    with pytest.raises(KeyError), RecordingWriter(tmp_path / "parts.csv", names=["a", "c"]) as w:
        w.write(t, cols)  # no column "c": the export fails half way
    assert (tmp_path / "parts.csv").read_text() == whole  # the earlier file is untouched
    assert not (tmp_path / "parts.csv.tmp").exists()


def test_a_negative_mean_square_or_mean_abs_is_refused_by_line_and_a_negative_speed_is_not(tmp_path):
    # a glitch or a sentinel in a current's column (-50 A^2) was read as heat taken out of the motor
    from tests_paths import PROFILES

    from gateway.profile import load_profile
    from gateway.recording import read_for_profile

    profile = load_profile(PROFILES / "sim-vmc.toml")
    names = ["time_s", *(f.column for f in profile.factors), "x_um", "y_um", "z_um"]
    rows = [[60.0 * (k + 1), *([0.0] * len(profile.factors)), 0.0, 0.0, 0.0] for k in range(5)]
    i1, feed, speed = (names.index(c) for c in ("spindle_i1_sq", "x_feed", "spindle_speed"))

    def file(col: int, value: str) -> str:
        lines = [",".join(names)] + [",".join(f"{v:g}" for v in r) for r in rows]
        cells = lines[3].split(",")
        cells[col] = value
        lines[3] = ",".join(cells)
        path = tmp_path / f"{names[col]}.csv"
        path.write_text("\n".join(lines) + "\n")
        return str(path)

    with pytest.raises(RecordingError) as err:
        read_for_profile(file(i1, "-50"), profile)
    assert str(err.value) == (f'{tmp_path}/spindle_i1_sq.csv:4: column "spindle_i1_sq": "-50" is negative: expected '
                              "a value >= 0, as a mean of squares (stat mean_square) never is (a glitch or a sentinel "
                              "value? leave the cell empty to make it a gap)")
    with pytest.raises(RecordingError, match=r'x_feed.csv:4: column "x_feed": "-3" is negative: expected a value >= 0, '
                                             r"as a mean of absolute values \(stat mean_abs\) never is"):
        read_for_profile(file(feed, "-3"), profile)
    rec = read_for_profile(file(speed, "-800"), profile)  # a spindle turning backwards (M04)
    assert rec.factors["spindle_speed"][2] == -800.0
