"""calibrate_fleet: a fleet's intervals calibrated on its failed assets (split conformal)."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
import torch

from prognos_torch.fleet import calibrate_fleet, fleet_rul, synthetic_fleet
from prognos_torch.prognosis.conformal import conformal_margin
from prognos_torch.prognosis.protocol import known_threshold_protocol


def _failed(n: int, seed: int):
    """A synthetic fleet observed past every failure (life fraction > 1)."""
    return synthetic_fleet(n, 300, seed=seed, life_fraction=(1.1, 1.3), healthy_fraction=0.0)


def _subset(table: dict, assets) -> dict:
    keep = np.isin(table["asset"], list(assets))
    return {k: v[keep] for k, v in table.items()}


def test_replayed_points_are_fleet_rows_of_the_truncated_assets():
    f = _failed(6, seed=4)
    cal, pts = calibrate_fleet(f.table, 20.0, fractions=(0.5, 0.9))
    assert pts["asset"][:2] == [f"{f.assets[0]}@0.5", f"{f.assets[0]}@0.9"]
    # point 2 is fleet_rul on asset 0's rows up to its 90 % protocol time, under that name
    t, y = (f.table[k][f.table["asset"] == f.assets[0]] for k in ("t", "value"))
    pc = known_threshold_protocol(torch.from_numpy(t), torch.from_numpy(y), fractions=(0.5, 0.9),
                                  threshold=20.0)  # fmt: skip
    keep = t <= float(pc.times[1])
    alone = fleet_rul({"asset": np.full(int(keep.sum()), pts["asset"][1]), "t": t[keep],
                       "value": y[keep]}, 20.0).row(pts["asset"][1])  # fmt: skip
    assert (pts["rul_q05"][1], pts["rul_q95"][1]) == (alone["rul_q05"], alone["rul_q95"])
    assert pts["true_rul"][1] == pc.t_eol - float(t[keep][-1])
    # the margin is the conformal quantile of the points' scores
    scores = torch.tensor([s for s in pts["score"] if not math.isnan(s)], dtype=torch.float64)
    assert cal.n == scores.numel() == 12 and cal.margin == conformal_margin(scores, 0.9)
    assert (cal.settings["method"], cal.settings["threshold"]) == ("exponential", 20.0)


@pytest.mark.parametrize("bins", [1, "auto"])
def test_calibrated_intervals_cover_held_out_failed_assets(bins):
    # calibrate on 200 failed assets, check on the replayed points of 200 others: the fleet's
    # own intervals under-cover there (truth above q95), the calibrated ones cover 0.9 within
    # the Monte-Carlo spread of 200 assets x 5 correlated points. One margin leaves the last
    # points (90 % of the life: the shortest RULs) under-covered; bins of the predicted median
    # (5 here: 1,000 points) cover them too
    f = _failed(400, seed=1)
    cal, _ = calibrate_fleet(_subset(f.table, f.assets[:200]), 20.0, bins=bins)
    _, pts = calibrate_fleet(_subset(f.table, f.assets[200:]), 20.0)
    lo, hi, tr, med = (torch.tensor(pts[k], dtype=torch.float64)
                       for k in ("rul_q05", "rul_q95", "true_rul", "rul_median"))  # fmt: skip
    ok = ~torch.isnan(lo)
    raw = ((lo <= tr) & (tr <= hi))[ok].double().mean()
    new_lo, new_hi = cal.interval(lo[ok], hi[ok], med[ok])
    covered = (new_lo <= tr[ok]) & (tr[ok] <= new_hi)
    last = torch.tensor([a.endswith("@0.9") for a in pts["asset"]])[ok]
    assert cal.margin > 0 and float(raw) < 0.8
    assert 0.84 <= float(covered.double().mean()) <= 0.97
    assert len(cal.margins) == (0 if bins == 1 else 5)
    late = float(covered[last].double().mean())
    assert late < 0.75 if bins == 1 else late >= 0.8


def test_fleet_result_calibrated_columns_and_settings_check():
    f = _failed(40, seed=2)
    cal, _ = calibrate_fleet(f.table, 20.0)
    live = synthetic_fleet(30, 300, seed=3)
    res = fleet_rul(live.table, 20.0)
    out = res.calibrated(cal)
    lo = torch.tensor(res.columns["rul_q05"], dtype=torch.float64)
    hi = torch.tensor(res.columns["rul_q95"], dtype=torch.float64)
    cm = torch.tensor(res.columns["censored_mass"], dtype=torch.float64)
    hi = torch.where(torch.isnan(hi) & ~torch.isnan(lo) & (cm > 0.05), math.inf, hi)
    med = torch.tensor(res.columns["rul_median"], dtype=torch.float64)
    want_lo, want_hi = cal.interval(lo, hi, torch.where(torch.isnan(med), math.inf, med))
    got_lo = torch.tensor(out.columns["rul_q05_calibrated"], dtype=torch.float64)
    got_hi = torch.tensor(out.columns["rul_q95_calibrated"], dtype=torch.float64)
    assert torch.equal(torch.isnan(got_lo), torch.isnan(lo))
    ok = ~torch.isnan(lo)
    assert torch.equal(got_lo[ok], want_lo[ok]) and torch.equal(got_hi[ok], want_hi[ok])
    assert out.columns["rul_median"] == res.columns["rul_median"]
    assert not any("date" in c for c in out.columns)  # numeric time: no dates
    # on a date-time axis (days since epoch) the calibrated ends also come as dates
    from dataclasses import replace

    dated = replace(res, epoch="2024-01-01T00:00:00").calibrated(cal)
    day0, t_last = np.datetime64("2024-01-01T00:00:00"), np.array(res.columns["t_last"])
    for end, got in (("q05", got_lo), ("q95", got_hi)):
        want = [
            str(day0 + np.timedelta64(round(d * 86400), "s")) if np.isfinite(d) else ""
            for d in t_last + got.numpy()
        ]
        assert dated.columns[f"failure_date_{end}_calibrated"] == want
    with pytest.raises(ValueError, match="made with threshold=20.0, this result has threshold=25"):
        fleet_rul(live.table, 25.0).calibrated(cal)
    with pytest.raises(ValueError, match="this result has samples=500"):
        cal2, _ = calibrate_fleet(f.table, 20.0, samples=300)
        fleet_rul(live.table, 20.0, samples=500).calibrated(cal2)
    # every option is compared with the defaults filled in: a calibration under the defaults
    # refuses another phi, onset rule or sample count (they passed: only the options the
    # calibration named were read), and the defaults written out are the defaults
    for kw, named in ((dict(phi="baseline"), "phi='auto', this result has phi='baseline'"),
                      (dict(k=1.0), "k=4.0, this result has k=1.0"),
                      (dict(samples=5), "samples=1000, this result has samples=5")):  # fmt: skip
        with pytest.raises(ValueError, match=re.escape(named)):
            fleet_rul(live.table, 20.0, **kw).calibrated(cal)
    fleet_rul(live.table, 20.0, samples=1000, phi="auto", k=4.0).calibrated(cal)
    cal3, _ = calibrate_fleet(f.table, 20.0, samples=1000, phi="auto")
    res.calibrated(cal3)


def test_bad_failed_tables_are_refused_by_name():
    with pytest.raises(ValueError, match="direction must be 'above' or 'below'"):
        calibrate_fleet(_failed(3, 0).table, 20.0, direction="auto")
    healthy = synthetic_fleet(4, 300, seed=0, healthy_fraction=1.0)
    with pytest.raises(ValueError, match="no failed asset gives a prediction point .*never "
                       "reaches the threshold 20"):  # fmt: skip
        calibrate_fleet(healthy.table, 20.0)
    short = {"asset": np.array(["a"] * 10), "t": np.arange(10.0), "value": np.ones(10)}
    with pytest.raises(ValueError, match="10 observed values, the protocol needs 20"):
        calibrate_fleet(short, 20.0)


def test_cli_calibrate_adds_the_calibrated_columns(tmp_path, capsys):
    from prognos_torch.cli import main
    from prognos_torch.fleet import read_fleet_table, write_table

    failed = _failed(30, seed=5)
    live = synthetic_fleet(20, 300, seed=6)
    write_table(tmp_path / "failed.csv", {k: list(v) for k, v in failed.table.items()})
    write_table(tmp_path / "live.csv", {k: list(v) for k, v in live.table.items()})
    out = tmp_path / "res.csv"
    args = ["rul", str(tmp_path / "live.csv"), "--group-by", "asset", "--threshold", "20",
            "--calibrate", str(tmp_path / "failed.csv"), "--out", str(out), "--no-progress"]  # fmt: skip
    assert main(args) == 0
    cal, _ = calibrate_fleet(read_fleet_table(tmp_path / "failed.csv"), 20.0, samples=1000,
                             phi="auto", min_rows=10)  # fmt: skip
    assert f"calibrated on {cal.n} points of 30 failed assets" in (said := capsys.readouterr().out)
    assert "warning: the points come from" not in said and cal.assets == 30  # 30 >= 9 assets
    want = fleet_rul(read_fleet_table(tmp_path / "live.csv"), 20.0, samples=1000, phi="auto",
                     min_rows=10).calibrated(cal)  # fmt: skip
    got = out.read_text().splitlines()
    head = got[0].split(",")
    j = head.index("rul_q05_calibrated")
    first = [float(v) for v in got[1].split(",")[j : j + 2]]
    assert first == pytest.approx(
        [want.columns["rul_q05_calibrated"][0], want.columns["rul_q95_calibrated"][0]], rel=1e-12
    )
    # a threshold no failed asset reached: one error line, nothing written
    out.unlink()
    assert main([a if a != "20" else "2000" for a in args]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: --calibrate: no failed asset gives a prediction point")
    assert not out.exists()
    # three failed assets: a finite margin from their points, and a warning that it is loose
    few = _subset(failed.table, sorted(set(failed.table["asset"]))[:3])
    write_table(tmp_path / "few.csv", {k: list(v) for k, v in few.items()})
    assert main([str(tmp_path / "few.csv") if a.endswith("failed.csv") else a for a in args]) == 0
    said = capsys.readouterr().out
    assert "points of 3 failed assets" in said and "margin" in said
    assert "warning: the points come from 3 failed assets; an asset's points move together, " \
        "and 90 % coverage for a new asset is assured from 9 failed assets on" in said  # fmt: skip


def test_replayed_truth_counts_from_the_replayed_rows_and_run_options_are_not_settings():
    """A failed asset with missing values (every other row after t = 40): a replayed point
    whose last rows had no value took its true RUL from the last observed time, while the
    fleet row's RUL counts from its last row (t_last), so its score was off by the gap.
    shard_size/progress/on_error passed to calibrate_fleet became settings that every live
    result was refused against; on_error was not applied to the failed table."""
    f = synthetic_fleet(1, 120, seed=2, life_fraction=(1.1, 1.3), healthy_fraction=0.0)
    t, y = f.table["t"], f.table["value"].copy()
    y[(t > 40) & (t % 2 == 1)] = np.nan
    bad = {"asset": np.array(["z"] * 3), "t": np.arange(3.0), "value": np.array(["1", "x", "2"])}
    tab = {k: np.concatenate([f.table[k] if k == "asset" else (t if k == "t" else y), bad[k]])
           for k in ("asset", "t", "value")}  # fmt: skip
    cal, pts = calibrate_fleet(tab, 20.0, samples=50, fractions=(0.5, 0.9), shard_size=1,
                               progress=False, on_error="flag")  # fmt: skip
    ok = ~np.isnan(y)
    pc = known_threshold_protocol(torch.from_numpy(t[ok]), torch.from_numpy(y[ok]), threshold=20.0)
    last = [float(t[t <= tp].max()) for tp in pts["t_pred"][:-1]]  # the replayed rows' t_last
    assert pts["t_last"][:-1] == last and any(np.isnan(y[t == v][0]) for v in last)
    assert pts["true_rul"][:-1] == [pc.t_eol - v for v in last]
    assert pts["asset"][-1] == "z" and "value 'x' in column 'value'" in pts["status"][-1]
    assert not {"shard_size", "progress", "on_error"} & set(cal.settings)
    fleet_rul(f.table, 20.0, samples=50).calibrated(cal)  # the same method: accepted


def test_cli_calibrate_takes_on_error_and_names_assets_without_a_point(tmp_path, capsys):
    """`prognos rul LIVE --calibrate FAILED --on-error flag` read the failed table with
    on_error='raise': one bad cell in a failed asset stopped the run."""
    from prognos_torch.cli import main
    from prognos_torch.fleet import write_table

    failed = _failed(3, seed=5).table
    bad = {"asset": ["z"] * 3, "t": [0.0, 1.0, 2.0], "value": ["1", "x", "2"]}
    write_table(tmp_path / "failed.csv", {k: list(failed[k]) + bad[k] for k in bad})
    write_table(tmp_path / "live.csv", {k: list(v) for k, v in _failed(2, seed=6).table.items()})
    out = tmp_path / "res.csv"
    args = ["rul", str(tmp_path / "live.csv"), "--group-by", "asset", "--threshold", "20",
            "--calibrate", str(tmp_path / "failed.csv"), "--out", str(out), "--no-progress",
            "--samples", "50"]  # fmt: skip
    assert main(args) == 2 and not out.exists()
    assert "error: --calibrate: " in (err := capsys.readouterr().err) and "'x'" in err
    assert main([*args, "--on-error", "flag"]) == 0 and out.exists()
    said = capsys.readouterr()
    assert "points of 3 failed assets" in said.out
    assert "1 failed asset(s) gave no calibration point (first, 'z': " in said.err
