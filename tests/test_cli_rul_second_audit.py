"""``prognos rul`` as a planner runs it: the report and the ``--json`` record against the
library's own result and brute force (dates of a zone-aware time column, ``--within``, the
observed RUL after ``--until``), ``--calibration`` files, and the fleet command line's outputs
and option errors."""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest
import torch
from _cli_helpers import one_error

from prognos_torch.cli import main


def _dated_csv(path):
    """60 hourly readings stamped in local time (+02:00) that degrade from row 20; the path and
    the UTC stamps."""
    g = torch.Generator().manual_seed(0)
    t = torch.arange(60, dtype=torch.float64)
    y = 1.0 + 0.05 * torch.randn(60, generator=g, dtype=torch.float64)
    y[20:] += 0.05 * torch.exp(0.08 * (t[20:] - 20))
    local = np.datetime64("2024-03-30T22:00") + np.arange(60) * np.timedelta64(1, "h")
    path.write_text("timestamp,rms\n" + "".join(f"{s}+02:00,{v!r}\n" for s, v in
                                                zip(local, y.tolist())))  # fmt: skip
    return path, (local - np.timedelta64(2, "h")).astype("datetime64[s]"), y


def test_json_record_agrees_with_brute_force_on_a_zone_aware_clock(tmp_path, capsys):
    """The record's dates are UTC stamps of t_last + the RUL quantile, p_within the share of
    the still-running paths that cross within W, the observed RUL the first crossing of the
    trailing 5-point median after the cut; strict JSON (no NaN token)."""
    from prognos_torch.workflow import load_series, prognose

    path, utc, y = _dated_csv(tmp_path / "d.csv")
    until = "2024-04-01T20:00:00+02:00"  # = 18:00 UTC, row 46
    argv = ["rul", str(path), "--column", "rms", "--time-column", "timestamp", "--threshold",
            "1.8", "--paths", "100", "--method", "exponential", "--until", until, "--within",
            "0.2", "--json", "-"]  # fmt: skip
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "NaN" not in text and "Infinity" not in text
    rec = json.loads(text)
    res = prognose(load_series(path, "rms", time_column="timestamp", until=until), 1.8,
                   method="exponential", n_paths=100)  # fmt: skip
    assert res.status == "ok" and {k: rec[k] for k in res.to_dict()} == res.to_dict()
    assert rec["t"] == pytest.approx(46 / 24, abs=1e-12) and rec["date"] == "2024-04-01T18:00:00"
    for key in ("q05", "median", "q95"):
        days = rec["rul"][key]
        want = utc[0] + np.timedelta64(round((46 / 24 + days) * 86400), "s")
        assert rec["failure_date"][key] == str(want)
    x = res.rul_samples[~torch.isnan(res.rul_samples)]
    assert rec["p_within"] == {"within": 0.2, "p": float((x <= 0.2).double().mean())}
    med = [float(np.median(y[max(0, i - 4) : i + 1].numpy())) for i in range(60)]
    first = next(i for i in range(47, 60) if med[i] >= 1.8)
    assert rec["observed_rul"] == pytest.approx((first - 46) / 24, abs=1e-12)


def test_a_calibration_file_made_with_filter_ekf_in_capitals_serves_the_default(tmp_path):
    """--filter EKF runs the filter ekf, but a calibration made with it was refused by a run
    with the default filter ('was made with --filter EKF, this run has ekf'), and vice versa."""
    from prognos_torch.cli_prognose import _check_settings
    from prognos_torch.prognosis import RULCalibration

    run = {"method": "exponential", "filter": "ekf", "n_paths": 100, "direction": "above",
           "threshold": 1.8, "glitch_limit": None, "seed": 0}  # fmt: skip
    for made in ("EKF", " ekf", "ekf"):
        cal = RULCalibration(0.5, 0.9, 20, settings=dict(run, filter=made))
        _check_settings(cal, "c.json", run)
    _check_settings(RULCalibration(0.5, 0.9, 20, settings=dict(run, filter="Ekf+STEKF")),
                    "c.json", dict(run, filter="ekf+stekf"))  # fmt: skip
    for made in ("stekf", "stekf+ekf", "unknown"):
        cal = RULCalibration(0.5, 0.9, 20, settings=dict(run, filter=made))
        with pytest.raises(ValueError, match=re.escape(f"with --filter {made}, this run has ekf")):
            _check_settings(cal, "c.json", run)


def test_a_calibration_path_that_is_a_folder_is_named(tmp_path, capsys):
    """--calibration DIR: 'error: [Errno 21] Is a directory: ...', without the option."""
    path, _, _ = _dated_csv(tmp_path / "d.csv")
    folder = tmp_path / "cal"
    folder.mkdir()
    argv = ["rul", str(path), "--column", "rms", "--time-column", "timestamp", "--threshold",
            "1.8", "--calibration", str(folder)]  # fmt: skip
    assert main(argv) == 2
    one_error(capsys, f"error: --calibration: {folder} cannot be read (Is a directory)")


# --------------------------------------------------------------------------- fleet
def _table(path, n_assets: int = 2, rows: int = 12):
    t = np.arange(float(rows))
    lines = ["asset,t,value"] + [f"a{a},{float(v)!r},{1.0 + 0.1 * a + 0.01 * float(v)!r}"
                                 for a in range(n_assets) for v in t]  # fmt: skip
    path.write_text("\n".join(lines) + "\n")
    return path


def test_fleet_out_naming_an_input_or_a_folder_is_refused_before_the_run(tmp_path, capsys):
    """--out TABLE replaced the table with the results (exit 0); --out naming the --calibrate
    table likewise; --out on a folder failed after the whole run ('give a file name, e.g.
    .../model.pt')."""
    table = _table(tmp_path / "f.csv")
    failed = _table(tmp_path / "failed.csv", 3)
    before = table.read_bytes(), failed.read_bytes()
    base = ["rul", str(table), "--group-by", "asset", "--threshold", "20", "--no-progress"]
    assert main([*base, "--out", str(table)]) == 2
    one_error(capsys, f"error: --out: {table} is the table, which this run reads")
    other = tmp_path / "." / "failed.csv"  # (the same file by another name)
    assert main([*base, "--calibrate", str(failed), "--out", str(other)]) == 2
    one_error(capsys, f"error: --out: {other} is the --calibrate table, which this run reads")
    assert (table.read_bytes(), failed.read_bytes()) == before
    folder = tmp_path / "out.csv"
    folder.mkdir()
    assert main([*base, "--out", str(folder)]) == 2
    one_error(capsys, f"error: --out: {folder} is a folder, expected a file name")
    assert list(folder.iterdir()) == []
    slash = f"{tmp_path / 'new.csv'}/"  # (a folder by its name: Path() dropped the slash and
    assert main([*base, "--out", slash]) == 2  # the results were written to new.csv)
    one_error(capsys, f"error: --out: {slash} names a folder, expected a file name")
    assert not (tmp_path / "new.csv").exists()


def test_fleet_command_restores_the_callers_thread_count(tmp_path, capsys):
    """The fleet command left torch at one thread in a caller's process."""
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(3)
        argv = ["rul", str(tmp_path / "none.csv"), "--group-by", "asset", "--threshold", "20",
                "--out", str(tmp_path / "o.csv")]  # fmt: skip
        assert main(argv) == 2
        capsys.readouterr()
        assert torch.get_num_threads() == 3
    finally:
        torch.set_num_threads(before)


@pytest.mark.parametrize(
    "extra, text",
    [
        (["--samples", "0"], "error: --samples: samples must be a positive int, got 0"),
        (["--shard-size", "0"], "error: --shard-size: shard_size must be a positive int, got 0"),
        (["--horizon", "nan"], "error: --horizon: horizon must be a finite number, got nan"),
        (["--seed", str(2**70)], "error: --seed: seed must lie in [-2**63, 2**64)"),
        (["--backend", "dask"], "error: --backend: backend must be 'local' or 'ray'"),
        (["--method", "cubic"], "error: --method: unknown method 'cubic'"),
        (["--method", "prognose", "--samples", "3"],
         "error: --samples: n_paths must be an int >= 10, got 3"),
    ],
)  # fmt: skip
def test_fleet_bad_option_is_named_in_its_error(tmp_path, capsys, extra, text):
    """'error: samples must be a positive int' named the Python argument, not --samples;
    --method prognose --samples 3 exited 0 with every asset's prognose_error."""
    out = tmp_path / "o.csv"
    argv = ["rul", str(_table(tmp_path / "f.csv")), "--group-by", "asset", "--threshold", "20",
            "--no-progress", "--min-rows", "20", "--out", str(out)]  # fmt: skip
    assert main(argv + extra) == 2
    one_error(capsys, text)
    assert not out.exists()


def test_fleet_setting_refused_in_the_calibration_replay_is_not_blamed_on_the_table(
    tmp_path, capsys
):
    """With --calibrate, --threshold nan read 'error: --calibrate: threshold must be ...', as if
    the failed table were at fault."""
    table = _table(tmp_path / "f.csv")
    argv = ["rul", str(table), "--group-by", "asset", "--calibrate", str(table), "--out",
            str(tmp_path / "o.csv"), "--no-progress"]  # fmt: skip
    assert main(argv + ["--threshold", "nan"]) == 2
    one_error(capsys, "error: --threshold: threshold must be a finite number, got nan")
    assert main(argv + ["--threshold", "20", "--direction", "up"]) == 2
    one_error(capsys, "error: --direction: direction must be 'above' or 'below', got 'up'")


def test_prognose_rul_refuses_a_bad_prognose_option_as_an_argument():
    """n_paths=3 or an unknown filter was every asset's prognose_error (a table of flags), not
    the call's error; a valid option set still gives each asset's row."""
    from prognos_torch.fleet import pad_batch, prognose_rul

    t = np.arange(12.0)
    batch = pad_batch(["a", "b"], [t, t], [1.0 + 0.01 * t, 1.0 + 0.02 * t], 0)
    with pytest.raises(ValueError, match=r"^n_paths must be an int >= 10, got 3$"):
        prognose_rul(batch, 20.0, n_paths=3)
    with pytest.raises(ValueError, match=r"^filter must name Gaussian filters"):
        prognose_rul(batch, 20.0, filter="kalman")
    with pytest.raises(ValueError, match=r"^method must be one of"):
        prognose_rul(batch, 20.0, method="cubic")
    with pytest.raises(TypeError, match="n_path"):  # a name prognose does not take
        prognose_rul(batch, 20.0, n_path=100)
    res = prognose_rul(batch, 20.0, min_rows=20, n_paths=10)
    assert res["flags"] == ["too_few_rows", "too_few_rows"]
    assert math.isnan(res["rul_median"][0])
