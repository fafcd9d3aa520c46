"""Row selection of long tables (``where``): ``read_fleet_table``, ``fleet_rul``,
``calibrate_fleet`` and the command line (``prognos rul TABLE --group-by ... --where``,
``--calibrate-where``, and ``prognos rul DATA --calibrate TABLE --calibrate-where``).

A table with one row per asset, time and channel holds several series per asset; the selected
rows must give exactly what a table of those rows alone gives, with the row numbers of the
whole table in every message."""

from __future__ import annotations

import math

import numpy as np
import pytest

from prognos_torch.cli import main
from prognos_torch.fleet import (
    FleetTable,
    calibrate_fleet,
    fleet_rul,
    read_fleet_table,
    synthetic_fleet,
    write_table,
)


def _two_channels(table: dict) -> dict:
    """``table`` as channel 5, beside a decoy channel 6 (other values, the same times), the
    channels interleaved row by row as a logger writes them."""
    n = len(table["asset"])
    out = {k: np.empty(2 * n, dtype=np.asarray(v).dtype) for k, v in table.items()}
    for k, v in table.items():
        out[k][0::2] = v
        out[k][1::2] = v
    out["value"][1::2] = 3.0 * np.asarray(table["value"]) + 1.0
    out["channel"] = np.tile(np.array([5, 6]), n)
    return out


def _csv(path, table: dict):
    write_table(path, {k: list(v) for k, v in table.items()})
    return path


def _same_table(a: FleetTable, b: FleetTable) -> None:
    assert a.assets == b.assets and a.errors == b.errors
    for x, y in zip(a.times, b.times):
        np.testing.assert_array_equal(x, y)
    for x, y in zip(a.values, b.values):
        np.testing.assert_array_equal(x, y)


@pytest.fixture(scope="module")
def fleet():
    return synthetic_fleet(5, 150, seed=2, healthy_fraction=0.2)


def test_selected_rows_read_as_the_table_of_those_rows_alone(fleet, tmp_path):
    alone = read_fleet_table(fleet.table)
    both = _two_channels(fleet.table)
    path = _csv(tmp_path / "both.csv", both)
    for source in (both, path):
        for where in ({"channel": "5"}, ["channel=5"], "channel=5.0", {"channel": 5}):
            got = read_fleet_table(source, where=where)
            _same_table(got, alone)
            # each sample keeps its row in the whole table (rows 1, 3, 5, ... are channel 5)
            for r_alone, r_got in zip(alone.rows, got.rows):
                np.testing.assert_array_equal(r_got, 2 * r_alone - 1)
    decoy = read_fleet_table(path, where="channel=6")
    np.testing.assert_array_equal(decoy.values[0], 3.0 * alone.values[0] + 1.0)
    # two conditions: both must hold; the asset column selects assets
    one = read_fleet_table(path, where=["channel=5", f"asset={fleet.assets[1]}"])
    assert one.assets == [fleet.assets[1]]
    np.testing.assert_array_equal(one.values[0], alone.values[1])
    # without where the channels mix: the decoy's rows repeat every time
    with pytest.raises(ValueError, match="duplicate timestamp"):
        read_fleet_table(path)


def test_selected_rows_of_a_dataframe_and_a_parquet_file():
    pd = pytest.importorskip("pandas")
    pytest.importorskip("pyarrow")
    import tempfile
    from pathlib import Path

    f = synthetic_fleet(3, 80, seed=4, healthy_fraction=0.0)
    alone = read_fleet_table(f.table)
    frame = pd.DataFrame(_two_channels(f.table))
    _same_table(read_fleet_table(frame, where="channel=5"), alone)
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "both.parquet"
        frame.to_parquet(path)
        _same_table(read_fleet_table(path, where={"channel": "5"}), alone)


def test_messages_give_the_rows_of_the_whole_table(fleet, tmp_path):
    both = _two_channels(fleet.table)
    both["value"] = both["value"].astype(object)
    bad = 2 * 10  # row 21 of the table (1-based), channel 5's 11th row
    both["value"][bad] = "abc"
    path = _csv(tmp_path / "bad.csv", both)
    a = fleet.assets[0]
    with pytest.raises(
        ValueError, match=rf"asset '{a}', row {bad + 1} \(line {bad + 2}\): value 'abc'"
    ):
        read_fleet_table(path, where="channel=5")
    flagged = read_fleet_table(path, where="channel=5", on_error="flag")
    assert f"row {bad + 1} (line {bad + 2})" in flagged.errors[a]
    # the same cell on channel 6's side is not read at all
    assert read_fleet_table(path, where="channel=6").errors == {}


def test_bad_selections_are_refused_by_name(fleet, tmp_path):
    path = _csv(tmp_path / "both.csv", _two_channels(fleet.table))
    cases = [
        ({"channel": "9"}, "no data rows matching channel=9 (where)"),
        (
            {"chanel": "5"},
            "no where column 'chanel'; columns found: 'asset', 't', 'value', 'channel'",
        ),
        ({"value": "1"}, "where: value=1 selects on the value (--column) column"),
        ({"t": "0"}, "where: t=0 selects on the time (--time-column) column"),
        (["channel"], "where: expected COLUMN=VALUE"),
        (["channel=5", "channel=6"], "where: column 'channel' is named twice"),
    ]
    for where, msg in cases:
        with pytest.raises(ValueError, match=msg.replace("(", r"\(").replace(")", r"\)")):
            read_fleet_table(path, where=where)
    # a missing channel cell matches nothing (it is no row of channel 5)
    both = _two_channels(fleet.table)
    both["channel"] = both["channel"].astype(object)
    both["channel"][0] = None
    got = read_fleet_table(both, where="channel=5")
    assert got.rows[0][0] == 3  # the asset's first row of channel 5 left is row 3
    assert read_fleet_table(both, where="channel=").rows[0].tolist() == [1]  # (only it)
    # a FleetTable was read already: where would be ignored, so it is refused
    tab = read_fleet_table(path, where="channel=5")
    with pytest.raises(ValueError, match="source is a FleetTable, read already"):
        fleet_rul(tab, fleet.threshold, where="channel=5")
    with pytest.raises(ValueError, match="source is a FleetTable, read already"):
        calibrate_fleet(tab, fleet.threshold, where="channel=5")


def test_fleet_rul_and_its_calibration_on_the_selected_rows(tmp_path):
    live = synthetic_fleet(6, 200, seed=6, healthy_fraction=0.0)
    failed = synthetic_fleet(4, 200, seed=5, life_fraction=(1.1, 1.3), healthy_fraction=0.0)
    kw = dict(samples=200, fractions=(0.5, 0.9))
    opts = dict(samples=200, phi="auto", min_rows=10)  # (the command line's)
    want = fleet_rul(live.table, 20.0, **opts)
    got = fleet_rul(_two_channels(live.table), 20.0, where="channel=5", **opts)
    assert got.columns["asset"] == want.columns["asset"]
    for c in ("rul_median", "rul_q05", "rul_q95", "censored_mass"):
        np.testing.assert_array_equal(np.array(got.columns[c]), np.array(want.columns[c]))
    cal, pts = calibrate_fleet(failed.table, 20.0, **kw)
    cal2, pts2 = calibrate_fleet(_two_channels(failed.table), 20.0, where="channel=5", **kw)
    assert (cal2.n, cal2.assets) == (cal.n, cal.assets) and list(pts2) == list(pts)
    for k, col in pts.items():
        if k in ("asset", "status"):
            assert pts2[k] == col
        else:
            np.testing.assert_array_equal(np.array(pts2[k]), np.array(col))
    assert (math.isnan(cal.margin) and math.isnan(cal2.margin)) or cal2.margin == cal.margin

    # the command line: --where selects the live table's rows, --calibrate-where the failed
    live_csv = _csv(tmp_path / "live.csv", _two_channels(live.table))
    failed_csv = _csv(tmp_path / "failed.csv", _two_channels(failed.table))
    out = tmp_path / "res.csv"
    base = ["rul", str(live_csv), "--group-by", "asset", "--threshold", "20", "--samples", "200",
            "--out", str(out), "--no-progress"]  # fmt: skip
    assert main([*base, "--where", "channel=5"]) == 0
    rows = out.read_text().splitlines()
    j = rows[0].split(",").index("rul_median")
    assert [float(r.split(",")[j]) for r in rows[1:]] == pytest.approx(
        want.columns["rul_median"], rel=1e-12
    )
    cal_args = ["--calibrate", str(failed_csv), "--calibrate-where", "channel=5"]
    assert main([*base, "--where", "channel=5", *cal_args]) == 0
    assert "rul_q05_calibrated" in out.read_text().splitlines()[0]


def test_command_line_options_are_named_in_their_errors(tmp_path, capsys):
    live = synthetic_fleet(3, 120, seed=6, healthy_fraction=0.0)
    live_csv = _csv(tmp_path / "live.csv", _two_channels(live.table))
    out = tmp_path / "res.csv"
    base = ["rul", str(live_csv), "--group-by", "asset", "--threshold", "20", "--out", str(out),
            "--no-progress"]  # fmt: skip
    cases = [
        (["--where", "channel"], "error: --where: expected COLUMN=VALUE (--where COL=VALUE"),
        (["--where", "channel=9"], "no data rows matching channel=9 (--where)"),
        (["--where", "value=1"], "error: --where: value=1 selects on the value"),
        (["--calibrate-where", "channel=5"], "error: --calibrate-where applies with --calibrate"),
        (["--where", "channel=5", "--calibrate", str(live_csv), "--calibrate-where", "channel"],
         "error: --calibrate-where: expected COLUMN=VALUE (--calibrate-where COL=VALUE"),
        (["--where", "channel=5", "--calibrate", str(live_csv), "--calibrate-where", "channel=7"],
         "error: --calibrate: " + str(live_csv) + ": no data rows matching channel=7 "
         "(--calibrate-where)"),
    ]  # fmt: skip
    for extra, msg in cases:
        assert main([*base, *extra]) == 2
        err = capsys.readouterr().err
        assert msg in err and err.count("\n") == 1, err
        assert not out.exists()


def test_rul_of_a_series_calibrated_on_the_selected_rows_of_histories(tmp_path, capsys):
    """``prognos rul DATA --calibrate TABLE --calibrate-where channel=5``: the calibration of
    the histories' channel-5 rows, as from a table of those rows alone."""
    from prognos_torch.prognosis.protocol import known_threshold_protocol
    from prognos_torch.systems.run_to_failure import run_to_failure_set

    records = list(run_to_failure_set(1, seed=3).items())
    new, hist = records[0][1], records[1:2]  # (one history: the selection is what is tested)
    t = np.concatenate([np.asarray(r.t) for _, r in hist])
    y = np.concatenate([np.asarray(r.y) for _, r in hist])
    unit = np.concatenate([[n.replace(" ", "_")] * len(r.t) for n, r in hist])
    one = {"unit": unit, "t": t, "value": y}
    _csv(tmp_path / "one.csv", one)
    _csv(tmp_path / "two.csv", _two_channels({"asset": unit, "t": t, "value": y}))
    two = read_fleet_table(tmp_path / "two.csv", where="channel=5")
    assert len(two.assets) == 1
    # the two-channel table names its asset column "asset"; the one-channel table "unit"
    data = tmp_path / "new.csv"
    data.write_text("t,value\n" + "".join(f"{float(a)!r},{float(b)!r}\n" for a, b in
                                          zip(new.t, new.y)))  # fmt: skip
    pc = known_threshold_protocol(new.t, new.y)
    args = ["rul", str(data), "--column", "value", "--time-column", "t", "--threshold",
            repr(pc.threshold), "--until", repr(float(pc.times[2])), "--method", "exponential",
            "--paths", "200", "--calibrate-threshold", "protocol"]  # fmt: skip
    assert main([*args, "--calibrate", str(tmp_path / "one.csv"), "--calibrate-group", "unit"]) in (
        0,
        3,
    )
    ref = capsys.readouterr().out
    assert main([*args, "--calibrate", str(tmp_path / "two.csv"), "--calibrate-where",
                 "channel=5"]) in (0, 3)  # fmt: skip
    got = capsys.readouterr().out
    row = [ln for ln in ref.splitlines() if ln.strip().startswith("calibrated 90 % interval")]
    assert row and row == [ln for ln in got.splitlines()
                           if ln.strip().startswith("calibrated 90 % interval")]  # fmt: skip
    # without --calibrate the option is refused, as the other calibration options are
    assert main([*args, "--calibrate-where", "channel=5"]) == 2
    assert "--calibrate-where, --calibrate-threshold apply with --calibrate TABLE" in \
        capsys.readouterr().err  # fmt: skip
    assert main([*args, "--calibrate", str(tmp_path / "two.csv"), "--calibrate-where",
                 "chan=5"]) == 2  # fmt: skip
    assert (
        "error: --calibrate: " in (err := capsys.readouterr().err)
        and "no where column 'chan'" in err
    )
    assert main([*args, "--calibrate", str(tmp_path / "two.csv"), "--calibrate-where",
                 "x"]) == 2  # fmt: skip
    assert "error: --calibrate-where: expected COLUMN=VALUE (--calibrate-where COL" in \
        capsys.readouterr().err  # fmt: skip
