"""``prognos rul DATA.csv ...``: RUL straight from a CSV, without a model file."""

from __future__ import annotations

import math
import re
from pathlib import Path

import pytest
import torch

from prognos_torch.cli import main

IMS = Path(__file__).resolve().parents[1] / "datasets" / "ims" / "test1_features.csv"


def _csv(path: Path, y: torch.Tensor) -> Path:
    lines = ["t,value"] + [f"{i},{float(v)!r}" for i, v in enumerate(y)]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_day_first_dates_with_time_format_give_the_iso_answer(capsys, tmp_path):
    """The same readings dated '%d/%m/%Y %H:%M' with --time-format, as ISO 8601: one report."""
    import numpy as np

    g = torch.Generator().manual_seed(0)
    y = 1.0 + 0.05 * torch.randn(300, generator=g, dtype=torch.float64)
    y[200:] += 0.02 * torch.exp(0.04 * torch.arange(100, dtype=torch.float64))
    stamps = np.datetime64("2024-01-30T00:00") + 10 * np.arange(300).astype("timedelta64[m]")
    outs = []
    for name, fmt, extra in (("iso", None, []), ("dmy", "%d/%m/%Y %H:%M", ["--time-format"])):
        rows = [s.astype(object).strftime(fmt) if fmt else str(s) for s in stamps]
        path = tmp_path / f"{name}.csv"
        path.write_text("t,x\n" + "".join(f"{a},{b!r}\n" for a, b in zip(rows, y.tolist())))
        argv = ["rul", str(path), "--column", "x", "--time-column", "t", "--threshold", "3"]
        assert main(argv + extra + ([fmt] if fmt else []) + ["--paths", "200"]) in (0, 3)
        outs.append(capsys.readouterr().out.split("\n", 1)[1])  # (the first line names the file)
    assert outs[0] == outs[1] and "degradation onset" in outs[0]
    # the report gives the dates a planner reads beside the day counts (the library's own)
    from prognos_torch.workflow import load_series, prognose

    res = prognose(load_series(tmp_path / "iso.csv", "x", time_column="t"), 3.0, n_paths=200)
    want = [res.failure_date(q) for q in (0.05, 0.5, 0.95)]
    assert want[1] is not None and f"failure date, median (UTC)  {want[1]}" in outs[0]
    ends = [w or "after " for w in (want[0], want[2])]
    assert f"failure dates, 90 % (UTC)   [{ends[0]}, {ends[1]}" in outs[0]
    onset = str(stamps[0] + np.timedelta64(round(res.onset.time * 86400), "s"))
    assert f"days ({onset} UTC; ksigma" in outs[0]


def test_calibrated_interval_on_date_times_comes_with_its_dates():
    """The calibrated interval's row of a dated series is followed by its dates: the last
    time plus each calibrated end (NumPy's arithmetic here)."""
    import numpy as np

    from prognos_torch.cli_prognose import calibration_rows
    from prognos_torch.prognosis.conformal import calibrate_intervals
    from prognos_torch.workflow import prognose

    g = torch.Generator().manual_seed(1)
    y = 1.0 + 0.05 * torch.randn(300, generator=g, dtype=torch.float64)
    y[200:] += 0.02 * torch.exp(0.04 * torch.arange(100, dtype=torch.float64))
    stamps = np.datetime64("2024-01-30T00:00") + 10 * np.arange(300).astype("timedelta64[m]")
    res = prognose(y, 3.0, time=stamps, method="exponential", n_paths=400)
    lo = torch.linspace(1.0, 2.0, 20, dtype=torch.float64)
    cal = calibrate_intervals(lo, 2 * lo, lo * torch.linspace(0.8, 2.4, 20, dtype=torch.float64))
    rows, _ = calibration_rows(res, cal, None, "days")
    c = cal.summary(res)["calibrated"]
    assert rows[1][0] == "calibrated failure dates (UTC)" and c["q95"] is not None

    def date(days):
        return str(stamps[0].astype("datetime64[s]") + np.timedelta64(round(days * 86400), "s"))

    assert rows[1][1] == f"[{date(res.t_last + c['q05'])}, {date(res.t_last + c['q95'])}]"
    assert len(calibration_rows(prognose(y, 3.0, method="exponential"), cal, None, "t")[0]) == 1


def test_rul_from_the_ims_table_with_until(capsys, tmp_path):
    args = ["rul", str(IMS), "--column", "rms", "--where", "channel=5", "--time-column",
            "timestamp", "--threshold", "0.45", "--until", "2003-11-25T13:00:00",
            "--plot", str(tmp_path / "rul.png")]  # fmt: skip
    assert main(args) == 0  # 1.2 % censored: below the 5 % flag, every quantile known
    cap = capsys.readouterr()
    out = cap.out
    assert cap.err == "" and re.search(r"censored mass\s+0\.012 \(RUL > ", out)
    assert "degradation onset" in out and "33.959" in out
    assert "trend model" in out and "90 % interval" in out and "censored mass" in out
    assert re.search(r"observed RUL \(days, 5-point median\)\s+0\.4392", out)
    # --within: the planner's probability, the distribution's own P(RUL <= 0.5 d)
    from prognos_torch.workflow import load_series, prognose

    s = load_series(IMS, "rms", time_column="timestamp", where={"channel": 5},
                    until="2003-11-25T13:00:00")  # fmt: skip
    p = prognose(s, 0.45).failure_probability(0.5)
    assert main(args + ["--within", "0.5"]) == 0
    got = re.search(r"P\(failure within 0\.5 days\)\s+([0-9.]+)", capsys.readouterr().out)
    assert got and float(got.group(1)) == pytest.approx(p, abs=5e-4) and 0 < p < 1
    assert (tmp_path / "rul.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # 16 days earlier 70 % of the paths are censored: exit 3 with one 'censored RUL:' line
    # (the report and the figure are still written)
    early = args[:-3] + ["2003-11-10T00:00:00", "--plot", str(tmp_path / "early.png")]
    assert main(early) == 3
    cap = capsys.readouterr()
    assert cap.err.startswith("censored RUL: ") and cap.err.count("\n") == 1
    # what is known of a median and a 95 % quantile beyond the horizon: that they are
    bound = re.search(r"censored mass\s+0\.\d+ \(RUL > ([0-9.]+) days\)", cap.out).group(1)
    assert re.search(rf"median RUL \(days\)\s+> {bound}\n", cap.out)
    assert re.search(rf"90 % interval \(days\)\s+\[[0-9.]+, > {bound}\]", cap.out)
    assert (tmp_path / "early.png").stat().st_size > 0
    # a span beyond that censored horizon: one error line, nothing printed
    assert main(early + ["--within", "500"]) == 2
    cap = capsys.readouterr()
    assert cap.out == "" and cap.err.startswith("error: --within: within = 500 days lies beyond")


def test_no_degradation_is_said_plainly(capsys, tmp_path):
    g = torch.Generator().manual_seed(0)
    y = 1.0 + 0.05 * torch.randn(400, generator=g, dtype=torch.float64)
    path = _csv(tmp_path / "flat.csv", y)
    assert main(["rul", str(path), "--column", "value", "--time-column", "t", "--threshold",
                 "2"]) == 0  # fmt: skip
    out = capsys.readouterr().out
    assert "no degradation detected yet" in out and "lower bound" in out
    assert "median RUL" not in out
    assert main(["rul", str(path), "--column", "value", "--time-column", "t", "--threshold",
                 "2", "--within", "10"]) == 0  # fmt: skip
    out = capsys.readouterr().out
    assert re.search(r"P\(failure within 10 t\)\s+n/a \(no degradation detected yet\)", out)


def test_bad_input_is_one_line_and_exit_2(capsys, tmp_path):
    y = torch.cat([torch.ones(100, dtype=torch.float64), torch.full((10,), 3.0)])
    y[::2] += 0.01
    path = _csv(tmp_path / "done.csv", y)
    assert main(["rul", str(path), "--column", "value", "--threshold", "2"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: threshold 2 already reached") and err.count("\n") == 1
    assert main(["rul", str(path), "--column", "value", "--threshold", "2", "--method",
                 "cubic"]) == 2  # fmt: skip
    assert "method must be one of" in capsys.readouterr().err
    # --filter names prognose's trend filters here; the model path's filters are refused
    assert main(["rul", str(path), "--column", "value", "--threshold", "2", "--filter",
                 "stpf"]) == 2  # fmt: skip
    err = capsys.readouterr().err
    assert (
        err.startswith("error: --filter: filter must name Gaussian filters")
        and err.count("\n") == 1
    )
    assert main(["rul", str(path), "--column", "value", "--threshold", "2", "--horizon",
                 "50"]) == 2  # fmt: skip
    assert "--horizon applies with a model file" in capsys.readouterr().err


def test_filter_pools_strong_tracking_from_the_command_line(capsys):
    args = ["rul", str(IMS), "--column", "rms", "--where", "channel=5", "--time-column",
            "timestamp", "--threshold", "0.45", "--until", "2003-11-25T13:00:00"]  # fmt: skip
    assert main(args + ["--filter", "ekf+stekf"]) == 0
    out = capsys.readouterr().out
    assert re.search(r"trend model\s+exponential\+elm \(EKF\) \+ exponential\+elm \(STEKF\)", out)
    from prognos_torch.workflow import load_series, prognose

    s = load_series(IMS, "rms", time_column="timestamp", where={"channel": 5},
                    until="2003-11-25T13:00:00")  # fmt: skip
    med = prognose(s, 0.45, filter="ekf+stekf").summary()["median"]
    got = re.search(r"median RUL \(days\)\s+([0-9.]+)", out)
    assert got and float(got.group(1)) == pytest.approx(med, rel=1e-3)


def test_epoch_times_and_small_censored_masses_are_printed_in_full(capsys, tmp_path):
    """Unix-second times keep their digits (``%g`` printed 1700021180 and 1700017580 both as
    1.70002e+09); a censored mass under 0.5 % reads as such (it read '0 %'), and the horizon is
    not described as '2 x the observed life' (it can be longer)."""
    from prognos_torch.workflow import prognose

    t = torch.arange(550, dtype=torch.float64)
    y = 1.0 + 0.05 * (-1.0) ** torch.arange(550, dtype=torch.float64)
    g = torch.Generator().manual_seed(2)
    rise = 0.05 * torch.exp(0.02 * (t - 400).clamp(min=0))
    y = torch.where(t >= 400, 1.0 + rise * torch.exp(0.05 * torch.randn(550, generator=g)), y)
    stamps = 1.7e9 + 600.0 * t[:480]
    path = tmp_path / "epoch.csv"
    path.write_text(
        "t,value\n" + "".join(f"{float(s)!r},{float(v)!r}\n" for s, v in zip(stamps, y))
    )
    res = prognose(y[:480], 3.0, time=stamps)
    code = main(["rul", str(path), "--column", "value", "--time-column", "t", "--threshold", "3"])
    cap = capsys.readouterr()
    assert f"at t = {stamps[-1]:.0f} t:" in cap.out
    assert f"{res.onset.time:.0f} t (ksigma" in cap.out
    if res.censored_mass > 0.05:
        assert code == 3 and f"{100 * res.censored_mass:.3g} % of the predicted" in cap.err
        assert "observed life" not in cap.err


def test_a_few_censored_paths_do_not_fail_the_command(capsys):
    # IMS test 3 bearing 3: 4 of 2000 paths beyond the horizon leave q05, median and q95
    # intact; only a censored mass above the 5 % of the flag (q95 unknown) exits 3
    args = ["rul", str(IMS.parent / "test3_features.csv"), "--column", "rms", "--where",
            "channel=3", "--time-column", "timestamp", "--threshold", "0.4458", "--until",
            "2004-04-17T00:00:00"]  # fmt: skip
    code = main(args)
    out = capsys.readouterr().out
    mass = float(out.split("censored mass")[1].split()[0])
    assert 0 < mass <= 0.05 and code == 0
    assert "90 % interval" in out and "n/a" not in out.split("90 % interval")[1].split("\n")[0]


def _history_table(path: Path, records) -> Path:
    lines = ["unit,t,value"] + [
        f"{name.replace(' ', '_')},{float(t)!r},{float(y)!r}"
        for name, r in records
        for t, y in zip(r.t, r.y)
    ]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_calibrate_from_a_table_of_failed_assets(capsys, tmp_path):
    from prognos_torch.prognosis.protocol import known_threshold_protocol
    from prognos_torch.systems.run_to_failure import run_to_failure_set
    from prognos_torch.workflow import calibrate_rul, load_series, prognose

    records = list(run_to_failure_set(1, seed=3).items())
    table = _history_table(tmp_path / "failed.csv", records[1:4])
    new = records[0][1]
    path = tmp_path / "new.csv"
    path.write_text("t,value\n" + "".join(f"{float(t)!r},{float(y)!r}\n" for t, y in
                                          zip(new.t, new.y)))  # fmt: skip
    pc = known_threshold_protocol(new.t, new.y)
    until = float(pc.times[2])
    args = ["rul", str(path), "--column", "value", "--time-column", "t", "--threshold",
            repr(pc.threshold), "--until", repr(until), "--method", "exponential", "--paths",
            "400", "--calibrate", str(table), "--calibrate-group", "unit",
            "--calibrate-threshold", "protocol"]  # fmt: skip
    saved = tmp_path / "cal.json"
    assert main(args + ["--calibration-out", str(saved), "--workers", "2"]) in (0, 3)
    out = capsys.readouterr().out
    assert f"calibration written to {saved}" in out
    # the same as calibrate_rul on those histories (in one process), applied to prognose's
    # result in Python
    hist = {n.replace(" ", "_"): (r.t, r.y) for n, r in records[1:4]}
    cal, points = calibrate_rul(hist, method="exponential", n_paths=400)
    s = load_series(path, "value", time_column="t", until=until)
    res = prognose(s, pc.threshold, method="exponential", n_paths=400)
    c = cal.summary(res)["calibrated"]
    hi = f"> {res.bound * math.exp(c['margin']):.4g}" if c["q95"] is None else f"{c['q95']:.4g}"
    used = len({p["name"] for p in points if "score" in p})
    assert f"[{c['q05']:.4g}, {hi}] (split conformal on {cal.n} points from {used} of 3" in out
    # fewer histories than a 90 % margin needs at one point each: said, not hidden
    assert f"warning: --calibrate: the points come from {used} histories; an asset's points " \
        "move together, and 90 % coverage for a new asset is assured from 9 histories" in out  # fmt: skip
    # the saved calibration gives the same row without the histories, under the same settings
    row = re.search(r"calibrated 90 % interval \(t\)\s+(\[[^\]]+\])", out).group(1)
    reuse = args[: args.index("--calibrate")] + ["--calibration", str(saved)]
    assert main(reuse + ["--json", str(tmp_path / "r.json")]) in (0, 3)
    assert f"{row} (split conformal on {cal.n} points from {used} histories of the " \
        "--calibration file" in (out := capsys.readouterr().out)  # fmt: skip
    # the record holds the calibrated interval of the row and its warning
    import json

    rec = json.loads((tmp_path / "r.json").read_text())["calibrated"]
    assert (rec["q05"], rec["q95"], rec["n"]) == (c["q05"], c["q95"], cal.n)
    assert rec["margin"] == (c["margin"] if math.isfinite(c["margin"]) else None)
    assert rec["warnings"] and rec["warnings"][0].startswith("--calibration: the points come")
    assert "warning" not in rec  # (it held the same sentence once more, unprefixed)
    assert f"warning: --calibration: the points come from {used} histories" in out
    for swap, msg in [(("exponential", "linear"), "was made with --method exponential, this run "
                       "has linear"), (("400", "300"), "was made with --paths 400")]:  # fmt: skip
        assert main([swap[1] if a == swap[0] else a for a in reuse]) == 2
        assert msg in capsys.readouterr().err
    # pooled seeds are another estimator: refused against a one-seed calibration (another
    # single seed is the same estimator)
    assert main(reuse + ["--seed", "0,1"]) == 2
    assert "was made with 1 pooled seed(s) (--seed), this run pools 2" in capsys.readouterr().err
    saved.write_text('{"margin": 0.1, "coverage": 1.5, "n": 3}')
    assert main(reuse) == 2
    assert "--calibration: " in (err := capsys.readouterr().err) and "coverage must lie" in err
    assert main(args + ["--calibration", str(saved)]) == 2
    assert "--calibrate and --calibration exclude each other" in capsys.readouterr().err
    # failure at the same threshold: two_phase_0's moving median (at most 0.77) never reaches it
    assert main(args[:-1] + ["same"]) in (0, 3)
    out = capsys.readouterr().out
    assert re.search(r"points from 2 of 3 histories", out)
    assert "warning: --calibrate: 1 of 3 histories gave no point with an interval (first, " \
        "'two_phase_0': protocol not usable: the moving median never reaches" in out  # fmt: skip
    # bad input: named, one line, exit 2, nothing run
    assert main(args[:-4] + ["--calibrate-group", "bearing"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: --calibrate: ") and "(--calibrate-group) column 'bearing'" in err
    assert err.count("\n") == 1
    assert main(args + ["--workers", "0"]) == 2
    assert "--workers must be >= 1 (processes), got 0" in capsys.readouterr().err
    dated = tmp_path / "dated.csv"
    dated.write_text("unit,t,value\na,2020-01-01T00:00:00,1\na,2020-01-02T00:00:00,2\n")
    assert main([str(dated) if a == str(table) else a for a in args]) == 2
    assert "holds date-times, that of" in capsys.readouterr().err
    no_clock = [a for a in args if a not in ("--time-column", "t", "--until", repr(until))]
    assert main(no_clock) == 2
    assert "--calibrate needs --time-column" in capsys.readouterr().err
    with_model = ["rul", str(tmp_path / "m.pt"), str(path), "--threshold", "1", "--calibrate",
                  str(table)]  # fmt: skip
    assert main(with_model) == 2
    assert "--calibrate and --calibration apply without a model file" in capsys.readouterr().err


def test_calibration_row_says_empty_and_too_few():
    from prognos_torch.cli_prognose import calibration_rows
    from prognos_torch.prognosis import RULCalibration
    from prognos_torch.workflow import Series

    class Result:  # the summary of a result with a finite 90 % interval [1, 1.5]
        history, t_last = Series(torch.zeros(3)), 2.0  # (numeric time: no dates)

        def summary(self):
            return {"status": "ok", "q05": 1.0, "q95": 1.5, "bound": 10.0}

    def row(margin, n):
        return calibration_rows(Result(), RULCalibration(margin, 0.9, n), None, "h")[0][0][1]

    assert row(0.5, 20).startswith("[0.6065, 2.473] (split conformal on 20 points")
    assert "ends moved out by a factor 1.65" in row(0.5, 20)
    # a margin of -0.5 shrinks both ends by e^0.5, past the interval's own width e^0.405
    assert row(-0.5, 20).startswith("empty ([1.649, 0.9098] narrowed by the margin")
    # ceil((n + 1) 0.9) <= n first holds at n = 9
    assert "too few for 90 % coverage, which needs 9" in row(math.inf, 8)
    # points from fewer histories than a finite margin needs at one point each: a warning
    warn = lambda **kw: calibration_rows(Result(), RULCalibration(0.5, 0.9, 40, **kw), None,  # noqa: E731
                                         "h")[1]  # fmt: skip
    assert warn(assets=8) == ["--calibration: " + RULCalibration(0.5, 0.9, 40, assets=8)
                              .warning("histories")]  # fmt: skip
    assert warn(assets=9) == warn() == []


def test_glitch_in_the_healthy_window_warns_and_glitch_limit_leaves_it_out(capsys, tmp_path):
    g = torch.Generator().manual_seed(0)
    t = torch.arange(480, dtype=torch.float64)
    y = 1.0 + 0.05 * torch.randn(480, generator=g, dtype=torch.float64)
    y[300:] += 0.02 * torch.exp((t[300:] - 300) / 60)
    y[40] = 3.0
    path = _csv(tmp_path / "glitch.csv", y)
    args = ["rul", str(path), "--column", "value", "--time-column", "t", "--threshold", "3"]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "no degradation detected yet" in out
    assert "warning: glitches in the healthy window: 1 isolated value" in out
    assert main([*args, "--glitch-limit", "20"]) in (0, 3)  # 3: a censored mass
    out = capsys.readouterr().out
    assert "warning: glitches left out of the healthy window" in out and "median RUL" in out
    assert main(["rul", "model.pt", str(path), "--threshold", "3", "--glitch-limit", "20"]) == 2
    assert "--glitch-limit applies without a model file" in capsys.readouterr().err


def test_json_record_holds_the_report_and_nothing_is_written_on_bad_input(capsys, tmp_path):
    """--json FILE: prognose's result as one record (RULResult.to_dict, the selection of the
    series, P(failure within), the observed RUL); '-' prints the record alone; censored and
    pre-onset answers are records too; a missing folder is refused before anything runs."""
    import json

    from prognos_torch.workflow import load_series, prognose

    rec_path = tmp_path / "r.json"
    args = ["rul", str(IMS), "--column", "rms", "--where", "channel=5", "--time-column",
            "timestamp", "--threshold", "0.45", "--until", "2003-11-25T13:00:00",
            "--within", "0.5"]  # fmt: skip
    assert main(args + ["--json", str(rec_path)]) == 0
    assert capsys.readouterr().out.rstrip().endswith(f"record written to {rec_path}")
    rec = json.loads(rec_path.read_text())
    s = load_series(IMS, "rms", time_column="timestamp", where={"channel": 5},
                    until="2003-11-25T13:00:00")  # fmt: skip
    res = prognose(s, 0.45)
    want = res.to_dict()
    assert {k: rec[k] for k in want} == want
    assert rec["where"] == {"channel": "5"} and rec["column"] == "rms"
    assert rec["p_within"] == {"within": 0.5, "p": res.failure_probability(0.5)}
    assert rec["observed_rul"] == pytest.approx(0.4392, abs=5e-5)
    assert rec["onset"]["detected"] and rec["onset"]["date"] == s.date(res.onset.time)
    assert rec["rul"]["q95"] == res.summary()["q95"] is not None
    # '-': standard output holds the record and nothing else
    assert main(args + ["--json", "-"]) == 0
    assert json.loads(capsys.readouterr().out) == rec
    # censored: exit 3 and the record, an open end as null with the horizon's date
    early = args[:-3] + ["2003-11-10T00:00:00", "--json", str(rec_path)]
    assert main(early) == 3
    rec = json.loads(rec_path.read_text())
    assert rec["rul"]["q95"] is None and rec["failure_date"]["q95"] is None
    assert rec["rul"]["censored_mass"] > 0.05
    assert rec["failure_date"]["bound"] == s.date(rec["t"] + rec["rul"]["bound"])
    capsys.readouterr()
    # a folder that does not exist: one error line, no report, nothing written
    bad = tmp_path / "no" / "r.json"
    assert main(args + ["--json", str(bad)]) == 2
    cap = capsys.readouterr()
    assert cap.out == "" and cap.err.startswith("error: --json: folder") and not bad.exists()
    # before onset the record says so and holds the lower bound
    g = torch.Generator().manual_seed(0)
    y = 1.0 + 0.05 * torch.randn(400, generator=g, dtype=torch.float64)
    flat = _csv(tmp_path / "flat.csv", y)
    assert main(["rul", str(flat), "--column", "value", "--time-column", "t", "--threshold",
                 "2", "--json", str(rec_path)]) == 0  # fmt: skip
    rec = json.loads(rec_path.read_text())
    assert rec["status"] == "no degradation detected yet" and rec["rul"]["median"] is None
    assert rec["onset"]["detected"] is False and rec["rul"]["bound"] > 0
    assert rec["date"] is None and rec["failure_date"]["bound"] is None


def test_seed_list_pools_seeds_and_a_model_file_refuses_it(capsys, tmp_path):
    """--seed 0,1: prognose(seed=(0, 1)), the same record; with a model file one seed only."""
    import json

    from prognos_torch.workflow import load_series, prognose

    args = ["rul", str(IMS), "--column", "rms", "--where", "channel=5", "--time-column",
            "timestamp", "--threshold", "0.45", "--until", "2003-11-25T13:00:00",
            "--json", "-"]  # fmt: skip
    assert main([*args, "--seed", "0,1"]) == 0
    rec = json.loads(capsys.readouterr().out)
    s = load_series(IMS, "rms", time_column="timestamp", where={"channel": 5},
                    until="2003-11-25T13:00:00")  # fmt: skip
    want = prognose(s, 0.45, seed=(0, 1)).to_dict()
    assert {k: rec[k] for k in want} == want
    assert rec["model"] == "exponential+elm (EKF, seed 0) + exponential+elm (EKF, seed 1)"
    assert main(["rul", str(tmp_path / "m.pt"), str(IMS), "--threshold", "0.45",
                 "--seed", "0,1"]) == 2  # fmt: skip
    assert "with a model file give one seed" in capsys.readouterr().err


def test_files_of_a_report_are_written_only_once_every_one_is_made(capsys, tmp_path, monkeypatch):
    """--plot, --calibration-out and --json are made first and written after: a record that
    cannot be made leaves no figure behind (the figure used to be written before the record
    was made), with and without a model file."""
    import prognos_torch.cli as cli_module
    import prognos_torch.cli_prognose as report

    g = torch.Generator().manual_seed(0)
    y = 1.0 + 0.05 * torch.randn(300, generator=g, dtype=torch.float64)
    y[200:] += 0.02 * torch.exp(0.04 * torch.arange(100, dtype=torch.float64))
    data = _csv(tmp_path / "d.csv", y)
    fig, rec = tmp_path / "f.png", tmp_path / "r.json"
    base = ["rul", str(data), "--column", "value", "--time-column", "t", "--threshold", "3",
            "--method", "exponential", "--paths", "200", "--plot", str(fig)]  # fmt: skip
    assert main([*base, "--json", str(rec)]) in (0, 3)
    out = capsys.readouterr().out
    assert fig.stat().st_size > 0 and rec.stat().st_size > 0
    assert out.index(f"figure written to {fig}") < out.index(f"record written to {rec}")
    fig.unlink()
    rec.unlink()

    def no_record(*args, **kwargs):
        raise ValueError("the record cannot be made")

    monkeypatch.setattr(report, "json_record", no_record)
    assert main([*base, "--json", str(rec)]) == 2
    assert "the record cannot be made" in capsys.readouterr().err
    assert not fig.exists() and not rec.exists()
    # with a model file
    model = tmp_path / "m.pt"
    assert main(["fit", str(data), "--column", "value", "--time-column", "t", "--learner", "elm",
                 "-m", "3", "--out", str(model)]) == 0  # fmt: skip
    monkeypatch.setattr(cli_module, "json_record", no_record)
    argv = ["rul", str(model), str(data), "--threshold", "1.5", "--particles", "50", "--plot",
            str(fig), "--json", str(rec)]  # fmt: skip
    assert main(argv) == 2
    assert "the record cannot be made" in capsys.readouterr().err
    assert not fig.exists() and not rec.exists()
    monkeypatch.undo()
    assert main(argv) in (0, 3)
    assert fig.stat().st_size > 0 and rec.stat().st_size > 0
