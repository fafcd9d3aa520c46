"""``prognos`` output names and the CSV reader as an expert user loading CSVs meets them: an
output option naming a folder is refused before anything is written, ``--holdout`` reads counts
in any float notation, data messages name the command-line option too, and ``load_series``
refuses what it read wrongly (the clock's date for ``now``, a 99-hour offset, ``1_000``, a cut
through rows out of time order, a zone name without its offset)."""

from __future__ import annotations

import math
import re
import time

import numpy as np
import pytest
from _cli_helpers import healthy_csv, one_error

import prognos_torch.workflow  # noqa: F401  (imported once, at collection)
from prognos_torch.cli import _holdout, main
from prognos_torch.workflow import load_series


@pytest.mark.parametrize(
    "argv, option",
    [
        (["fit", "{d}", "--column", "v", "--learner", "elm", "--out"], "--out"),
        (["forecast", "{m}", "{d}", "--horizon", "3", "--csv"], "--csv"),
        (["forecast", "{m}", "{d}", "--horizon", "3", "--plot"], "--plot"),
        (["rul", "{d}", "--column", "v", "--time-column", "t", "--threshold", "3", "--plot"],
         "--plot"),
        (["rul", "{d}", "--column", "v", "--time-column", "t", "--threshold", "3",
          "--calibrate", "{m}", "--calibration-out"], "--calibration-out"),
    ],
)  # fmt: skip
def test_an_output_option_naming_a_folder_is_refused_before_anything_is_written(
    tmp_path, capsys, argv, option
):
    """type=Path dropped the '/': --csv new/ (no such folder) wrote a file named new, fit --out
    new/ a model file named new (as --json new/ is refused up front)."""
    data, _ = healthy_csv(tmp_path / "d.csv")
    new = str(tmp_path / "new") + "/"
    argv = [a.format(d=data, m=tmp_path / "none.pt") for a in argv] + [new]
    assert main(argv) == 2
    one_error(capsys, f"error: {option}: {new} names a folder, expected a file name")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.csv"]


def test_holdout_reads_a_whole_number_in_float_notation_as_a_count(tmp_path, capsys):
    """--holdout 1e3 was read as the fraction 1000.0 ('got 1000.0'); 2.5 is neither."""
    assert _holdout("1e1") == 10 and type(_holdout("1e1")) is int
    assert _holdout("10.0") == 10 and type(_holdout("1E3")) is int and _holdout("1E3") == 1000
    assert _holdout("0.2") == 0.2 and _holdout("50") == 50 and _holdout("0") == 0
    data, _ = healthy_csv(tmp_path / "d.csv")
    fit = ["fit", str(data), "--column", "v", "--learner", "elm", "--embedding", "2"]
    assert main(fit + ["--holdout", "1e1", "--out", str(tmp_path / "m.pt")]) == 0
    assert "rows          40 (training 30, held out 10)" in capsys.readouterr().out
    assert main(fit + ["--holdout", "1e3", "--out", str(tmp_path / "x.pt")]) == 2
    one_error(capsys, "error: --holdout: holdout=1000 leaves no training data in a series of 40")
    assert main(fit + ["--holdout", "2.5", "--out", str(tmp_path / "x.pt")]) == 2
    one_error(capsys, "error: --holdout: holdout must be a fraction in (0, 1) or a count (a "
                       "whole number; 0 for none), got '2.5'")  # fmt: skip
    assert not (tmp_path / "x.pt").exists()


@pytest.mark.parametrize(
    "extra, text",
    [
        ([], "name the value column with column=... (--column on the command line)"),
        (["--column", "v", "--until", "3"],
         "error: --until: until needs a time column (time_column=..., --time-column on the "
         "command line)"),
        (["--column", "v", "--time-format", "%d"],
         "give time_column as well (--time-column on the command line)"),
        (["--column", "v", "--time-column", "t", "--until", "-1"],
         "no data rows at or before until='-1' (--until on the command line)"),
        (["--column", "v", "--time-column", "t", "--until", "2003-01-01"],
         "error: --until: until='2003-01-01' is a date-time"),
        (["--column", "v", "--where", "chan"],
         "where: expected COLUMN=VALUE (--where COL=VALUE on the command line), got 'chan'"),
        (["--column", "v", "--time-column", "t", "--time-format", "%d/%m/%Y"],
         "does not match time_format '%d/%m/%Y' (time data '0.0' does not match format "
         "'%d/%m/%Y') (time_format: --time-format on the command line)"),
    ],
)  # fmt: skip
def test_data_messages_name_the_command_line_option(tmp_path, capsys, extra, text):
    """load_series' messages named only its Python arguments (column=..., time_column=...)."""
    data, _ = healthy_csv(tmp_path / "d.csv")
    out = tmp_path / "m.pt"
    assert main(["fit", str(data), "--learner", "elm", "--out", str(out)] + extra) == 2
    one_error(capsys, text)
    assert not out.exists()


def _load(tmp_path, text: str, **kw):
    path = tmp_path / "p.csv"
    path.write_text(text)
    return load_series(path, "v", time_column="t", **kw)


@pytest.mark.parametrize("cell", ["now", "today", "Today"])
def test_now_or_today_in_a_time_column_is_refused(tmp_path, cell):
    """NumPy reads them as the clock's date: the axis moved with the day the file was read."""
    with pytest.raises(ValueError, match=f"line 3: time column 't' value '{cell}' is neither"):
        _load(tmp_path, f"t,v\n2003-01-01,1\n{cell},2\n")


def test_zone_offsets_are_applied_and_out_of_range_ones_refused(tmp_path):
    """+99:99 shifted the time by 4 days and 3 hours without a word."""
    s = _load(tmp_path, "t,v\n2003-01-01T00:00:00+05:30,1\n2003-01-01 01:00:00 -0230,2\n")
    assert s.start == "2002-12-31T18:30:00"  # 00:00 at +05:30 is 18:30 UTC the day before
    assert s.time.tolist() == [0.0, (24 + 3.5 - 18.5) / 24]  # 01:00 at -02:30: 03:30 UTC
    for zone in ("+99:99", "+24:00", "-05:60"):
        with pytest.raises(
            ValueError, match=re.escape(f"has the offset '{zone}'; hours 00-23, minutes")
        ):
            _load(tmp_path, f"t,v\n2003-01-01T00:00:00{zone},1\n2003-01-02T00:00:00Z,2\n")


def test_digit_group_underscores_are_not_numbers(tmp_path):
    """float() reads '1_000' as 1000: a value, a numeric time or a --where value."""
    with pytest.raises(ValueError, match="line 2: column 'v' value '1_000' is not a number"):
        _load(tmp_path, "t,v\n0,1_000\n1,2\n")
    with pytest.raises(ValueError, match="line 3: time column 't' value '1_0' is not a number"):
        _load(tmp_path, "t,v\n0,1\n1_0,2\n")
    path = tmp_path / "w.csv"
    path.write_text("c,v\n1_0,1\n10,2\n10.0,3\n")
    assert load_series(path, "v", where={"c": "10"}).values.tolist() == [2.0, 3.0]


def test_missing_times_are_named_by_line(tmp_path):
    """A numeric time 'nan' gave no line; a date-time 'nan' or 'NaT' was called empty."""
    with pytest.raises(ValueError, match=r"time column 't' has non-finite values at line\(s\) 3"):
        _load(tmp_path, "t,v\n0,1\nnan,2\n2,3\n")
    for cell in ("nan", "NaT"):
        with pytest.raises(ValueError, match=f"line 3: time column 't' is missing \\('{cell}'\\)"):
            _load(tmp_path, f"t,v\n2003-01-01,1\n{cell},2\n2003-01-03,3\n")


def test_until_through_rows_out_of_time_order_is_refused(tmp_path):
    """Times 0, 1, 5, 2, 3 cut at 3 kept 0, 1, 2, 3 as if in order (5 fell out without a word);
    an array's NaN time fell out of the cut alike."""
    text = "t,v\n0,1\n1,2\n5,3\n2,4\n3,5\n"
    with pytest.raises(ValueError, match=r"line 5: time column 't' must be strictly increasing "
                                         r"\(2 follows 5\)"):  # fmt: skip
        _load(tmp_path, text, until=3)
    # a cut before the disorder keeps the first rows, as a cut before a bad cell does
    assert _load(tmp_path, text, until=1).values.tolist() == [1.0, 2.0]
    v = np.array([1.0, 2.0, 3.0, 4.0])
    with pytest.raises(ValueError, match=r"index 2: time must be strictly increasing"):
        load_series(v, time=[0.0, 5.0, 2.0, 3.0], until=3)
    with pytest.raises(ValueError, match="time has a non-finite value at index 2"):
        load_series(v, time=[0.0, 1.0, math.nan, 3.0], until=5)
    assert load_series(v, time=[0.0, 1.0, 2.0, 3.0], until=2).values.tolist() == [1.0, 2.0, 3.0]


def test_a_zone_name_without_its_offset_is_refused(tmp_path, monkeypatch):
    """strptime's %Z matches the machine's zone names but gives no offset: on a machine in New
    York, '10:00 EST' was read as 10:00 UTC, five hours off."""
    fmt = "%d/%m/%Y %H:%M %Z"
    monkeypatch.setenv("TZ", "EST5EDT")  # (strptime's zone names are this machine's)
    time.tzset()
    try:
        assert time.tzname == ("EST", "EDT")
        with pytest.raises(ValueError, match=r"the zone name 'EST' \(%Z\) gives no offset"):
            text = "t,v\n01/01/2003 10:00 EST,1\n01/01/2003 11:00 EST,2\n"
            _load(tmp_path, text, time_format=fmt)
        s = _load(tmp_path, "t,v\n01/01/2003 10:00 UTC,1\n01/01/2003 11:00 GMT,2\n",
                  time_format=fmt)  # fmt: skip
    finally:
        monkeypatch.undo()
        time.tzset()
    assert s.start == "2003-01-01T10:00:00" and s.time.tolist() == [0.0, 1 / 24]
    z = _load(tmp_path, "t,v\n01/01/2003 10:00 -0500,1\n", time_format="%d/%m/%Y %H:%M %z")
    assert z.start == "2003-01-01T15:00:00"
