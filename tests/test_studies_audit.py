"""Audit of the study infrastructure (prognos_torch.studies): options, result files, per-run
rows, aggregation, table writers, the RUL protocol's points and bad input. Tiny inputs only;
no study is run."""

from __future__ import annotations

import json
import math
import statistics
from dataclasses import asdict
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from prognos_torch import studies
from prognos_torch.prognosis.protocol import known_threshold_protocol
from prognos_torch.studies import (
    Stat,
    Study,
    StudyConfig,
    StudyResult,
    fmt_value,
    format_table,
    lowest_counts,
    markdown_table,
    run_errors,
    run_rows,
    summarize,
    write_outputs,
)
from prognos_torch.studies import indicator_protocol as ip
from prognos_torch.studies import rul_protocol as rp

F64 = torch.float64


# ------------------------------------------------------------------------------ options
def test_study_config_numpy_ints_are_ints_and_bad_seed_or_flags_are_refused():
    cfg = StudyConfig(runs=np.int64(3), seed=np.int64(2))
    assert type(cfg.runs) is int and type(cfg.seed) is int
    rec = json.loads(json.dumps(asdict(cfg), default=str))  # as run.json records it
    assert rec["runs"] == 3 and rec["seed"] == 2  # (was "3" and "2": strings)
    a, b = cfg.generator(1), torch.Generator().manual_seed(3)
    assert torch.equal(torch.rand(3, generator=a), torch.rand(3, generator=b))
    with pytest.raises(TypeError, match="seed must be an int, got 1.5"):
        StudyConfig(seed=1.5)  # (was accepted; manual_seed failed later)
    with pytest.raises(TypeError, match="quick must be a bool, got 'no'"):
        StudyConfig(quick="no")  # (was read as True: the quick protocol ran)
    with pytest.raises(TypeError, match="progress must be a bool"):
        StudyConfig(progress=None)
    assert StudyConfig(quick=np.bool_(True)).quick is True


# ------------------------------------------------------------------------- result files
def _toy():
    st = Study("toy", "000", "Toy", run=lambda cfg, out: None, default_runs=2)
    res = StudyResult(rows=[{"run": 0, "method": "A", "MAE": 1.0}], metrics=["MAE"])
    return st, res


def test_write_outputs_writes_nothing_when_a_file_cannot_be_built(tmp_path):
    st, res = _toy()
    res.config = {"a": 1}
    res.config["self"] = res.config  # run.json cannot be built
    out = tmp_path / "toy"
    with pytest.raises(ValueError, match="[Cc]ircular"):
        write_outputs(st, StudyConfig(out=tmp_path), res, out, 0.1)
    assert not out.exists()  # (was: table.md and results.csv written, no run.json)
    res.config = {"a": 1}
    text = write_outputs(st, StudyConfig(out=tmp_path), res, out, 0.1)
    assert sorted(p.name for p in out.iterdir()) == ["results.csv", "run.json", "table.md"]
    assert (out / "table.md").read_text(encoding="utf-8") == text
    assert json.loads((out / "run.json").read_text())["study_config"] == {"a": 1}


def test_a_failed_run_removes_every_folder_it_made(tmp_path):
    def fail(cfg, out):
        raise RuntimeError("boom")

    st = Study("toy", "000", "Toy", run=fail)
    with pytest.raises(RuntimeError, match="boom"):
        studies.run_study(st, StudyConfig(out=tmp_path / "new" / "out"))
    assert list(tmp_path.iterdir()) == []  # (was: new/out left behind, empty)
    (tmp_path / "keep").mkdir()
    (tmp_path / "keep" / "x.txt").write_text("x")
    with pytest.raises(RuntimeError, match="boom"):
        studies.run_study(st, StudyConfig(out=tmp_path / "keep"))
    assert [p.name for p in (tmp_path / "keep").iterdir()] == ["x.txt"]


# ------------------------------------------------------------------------------- rows
def test_run_rows_numpy_arrays_are_per_run_and_matrices_are_refused():
    rows = run_rows("A", {"x": np.array([1.0, 2.5]), "s": np.float64(0.5), "z": np.array(4.0)})
    assert rows == [
        {"run": 0, "method": "A", "x": 1.0, "s": 0.5, "z": 4.0},
        {"run": 1, "method": "A", "x": 2.5, "s": 0.5, "z": 4.0},
    ]  # (was: the whole array in every row, and runs required)
    with pytest.raises(ValueError, match=r"values\['e'\] must be \(R,\).*\(2, 3\)"):
        run_rows("A", {"e": torch.ones(2, 3)})  # (was: "only one element tensors ...")
    with pytest.raises(ValueError, match="runs must be a non-negative int, got 2.5"):
        run_rows("A", {"x": 1.0}, runs=2.5)
    assert len(run_rows("A", {"x": 1.0}, runs=np.int64(2))) == 2


# ------------------------------------------------------------------------ aggregation
def test_summarize_and_format_table_against_brute_force():
    vals = {"A": [1.0, 2.0, math.nan, 7.0, math.inf], "B": [0.25]}
    rows = [{"run": i, "method": m, "e": v} for m, vs in vals.items() for i, v in enumerate(vs)]
    s = summarize(rows, ["e"])
    fin = [1.0, 2.0, 7.0]
    assert s["A"]["e"].n == 3
    assert s["A"]["e"].mean == pytest.approx(sum(fin) / 3, abs=1e-15)
    assert s["A"]["e"].std == pytest.approx(statistics.stdev(fin), abs=1e-15)
    assert s["B"]["e"] == Stat(0.25, 0.0, 1)
    line = format_table(StudyResult(rows, ["e"])).splitlines()[2]
    assert line == f"| A | 5 | {sum(fin) / 3:.4f} ± {statistics.stdev(fin):.4f} (3 of 5 finite) |"


def test_lowest_counts_never_counts_a_nan_run_as_lowest():
    scores = {
        "a": torch.tensor([math.nan, 1.0, 2.0, math.nan], dtype=F64),
        "b": torch.tensor([0.5, 2.0, 2.0, math.nan], dtype=F64),
        "c": torch.tensor([0.7, 0.1, math.nan, math.nan], dtype=F64),
    }
    want = dict.fromkeys(scores, 0)  # brute force: first method with the lowest finite score
    for r in range(4):
        fin = [(float(v[r]), k) for k, v in scores.items() if not math.isnan(float(v[r]))]
        if fin:
            low = min(x for x, _ in fin)
            want[next(k for x, k in fin if x == low)] += 1
    assert want == {"a": 1, "b": 1, "c": 1}
    assert lowest_counts(scores) == want  # (was a 2: its NaN runs 0 and 3 counted as lowest)
    with pytest.raises(ValueError, match="one length"):
        lowest_counts({"a": torch.zeros(2), "b": torch.zeros(3)})


def test_run_errors_brute_force_and_a_target_of_another_length_is_refused():
    pred = torch.tensor([[0.0, 1.0, 3.0], [1.0, 1.0, 1.0]], dtype=F64)
    y = torch.tensor([1.0, 1.0, 1.0], dtype=F64)
    e = run_errors(pred, y)
    for r in range(2):
        d = [float(pred[r, i] - y[i]) for i in range(3)]
        assert float(e["MAE"][r]) == pytest.approx(sum(map(abs, d)) / 3, abs=1e-15)
        assert float(e["RMSE"][r]) == pytest.approx(math.sqrt(sum(x * x for x in d) / 3))
        assert float(e["MSE"][r]) == pytest.approx(sum(x * x for x in d) / 3)
    with pytest.raises(ValueError, match=r"target must be \(N,\).*\(1,\).*\(2, 3\)"):
        run_errors(pred, y[:1])  # (was broadcast over the three samples)


# --------------------------------------------------------------------------- tables
def test_fmt_value_numpy_and_tensor_nan_is_missing():
    assert fmt_value(np.float32("nan")) == "—"  # (was "nan")
    assert fmt_value(torch.tensor(math.nan)) == "—"
    assert fmt_value(np.float32(0.5)) == "0.5000" and fmt_value(3) == "3.0000"


def test_markdown_table_keeps_a_name_with_a_line_break_on_one_row():
    lines = markdown_table(["method", "n"], [["a\nb | c", 1]]).splitlines()
    assert lines == ["| method | n |", "|---|---|", "| a<br>b \\| c | 1 |"]  # (was 4 lines)


def test_threshold_census_refuses_a_nan_threshold():
    assert studies.threshold_census([0.5, 2.0], np.float32(1.0)) == (
        "1 lie below 1 (0.500), 1 lie above 1 (2.000)"
    )
    with pytest.raises(ValueError, match="threshold must be a real number, got nan"):
        studies.threshold_census([0.5, 2.0], math.nan)  # (was "": neither side)


# ---------------------------------------------------------------------- RUL protocol
def _lower_median(v):
    s = sorted(v)
    return s[(len(s) - 1) // 2]


def _ramp():
    t = torch.arange(40, dtype=F64)
    k = t.tolist()
    y = [1.0 + 0.1 * (i % 2) if i < 20 else 1.05 + 0.15 * (i - 19) for i in range(40)]
    return t, torch.tensor(y, dtype=F64), k, y


def test_protocol_points_against_a_direct_computation():
    t, y_t, k, y = _ramp()
    mm = [_lower_median(y[max(0, i - 4) : i + 1]) for i in range(40)]  # trailing 5-point
    thr = 0.9 * max(mm)
    i_eol = next(i for i in range(40) if mm[i] >= thr)
    t_eol = k[i_eol]
    base = [y[i] for i in range(i_eol + 1) if k[i] <= 0.3 * t_eol]  # first 30 % of life
    limit = statistics.mean(base) + 4 * statistics.stdev(base)
    above = [i >= 4 and mm[i] > limit for i in range(i_eol + 1)]
    i_on = next(i for i in range(i_eol - 3) if all(above[i : i + 5]))
    times = [k[i_on] + f * (t_eol - k[i_on]) for f in (0.2, 0.4, 0.6, 0.8, 0.9)]
    pc = known_threshold_protocol(t, y_t)
    assert pc.valid and pc.threshold == pytest.approx(thr, abs=1e-12)
    assert (pc.i_eol, pc.t_eol, pc.i_onset) == (i_eol, t_eol, i_on)
    rows, _, per, _ = rp.protocol_rows({"s": (t, y_t, False)}, ["linear slope"])
    assert [r["t"] for r in rows] == pytest.approx(times, abs=1e-12)
    assert [r["true_rul"] for r in rows] == pytest.approx([t_eol - x for x in times], abs=1e-12)
    assert len(per) == 1
    # (was "step must be ...")
    with pytest.raises(ValueError, match="every must be a positive int, got -1"):
        rp.protocol_rows({"s": (t, y_t, False)}, ["linear slope"], every=-1)
    with pytest.raises(ValueError, match="every must be a positive int, got 0"):
        rp.protocol_rows({"s": (t, y_t, False)}, ["linear slope"], every=0)
    with pytest.raises(ValueError, match="'linear slope' has no intervals"):
        rp.conformal_rows(rows, "linear slope", lambda name: name)  # (was a TypeError on None)


def test_fit_series_baseline_interval_is_clamped_at_zero_from_tp(monkeypatch):
    import prognos_torch.workflow as wf

    summ = {"median": 1.0, "q05": 0.1, "q95": 0.15}
    res = SimpleNamespace(summary=lambda: summ, censored_mass=0.0)
    monkeypatch.setattr(wf, "fit_series", lambda series, seed: None)
    monkeypatch.setattr(wf, "rul", lambda *a, **k: res)
    t = torch.arange(10, dtype=F64)
    y = 0.1 * t
    # the last sample at 9: the prediction time 9.5 lies 0.5 after it
    p = rp.predict_rul("fit_series + rul(stpf)", t, y, SimpleNamespace(threshold=2.0), 9.5, 0)
    assert (p["pred"], p["lo"], p["hi"]) == (0.5, 0.0, 0.0)  # (hi was 0.15 - 0.5 = -0.35)


# ------------------------------------------------------------------------- training
def test_outcome_rows_online_without_the_online_reading_is_refused():
    out = studies.TrainTest(torch.zeros(2, 3, dtype=F64), torch.zeros(2, 4, dtype=F64), 1.0, 0.5)
    y, yt = torch.zeros(4, dtype=F64), torch.ones(3, dtype=F64)
    assert [r["MAE"] for r in studies.outcome_rows("A", out, y, yt)] == [1.0, 1.0]
    with pytest.raises(ValueError, match="online=True needs the online reading"):
        studies.outcome_rows("A", out, y, yt, online=True)  # (was an AttributeError on None)


# ------------------------------------------------------------------ indicator protocol
def test_indicator_case_bad_input_is_named():
    t = 0.5 * torch.arange(12, dtype=F64)
    z = 0.125 * torch.arange(12, dtype=F64)  # reaches 0.8 at t = 3.5
    kw = dict(threshold=0.8, rul_start=1.2, rul_every=0.5, horizon=2.2)
    assert ip.indicator_case(z, t, np.int64(2), **kw).rul_idx == [2, 3, 4, 5, 6]
    cases = [
        (dict(threshold=5.0), "never reaches the threshold 5.0"),  # (was "arange: ...")
        (dict(start=100.0), "start 100.0 lies after the last sample"),  # (was an IndexError)
        (dict(rul_every=0.0), "rul_every must be a finite positive number"),  # (ZeroDivisionError)
        (dict(rul_every=-1.0), "rul_every must be a finite positive number"),  # (stack of nothing)
        (dict(rul_start=3.6), "no RUL prediction time"),  # (stack of nothing)
    ]
    for bad, msg in cases:
        with pytest.raises(ValueError, match=msg):
            ip.indicator_case(z, t, 2, **(kw | bad))
    with pytest.raises(ValueError, match="m must be a positive int"):
        ip.indicator_case(z, t, 0, **kw)


# ---------------------------------------------------------------------- forecasters
def test_forecast_problem_rul_times_outside_the_test_are_refused():
    z = torch.linspace(0.0, 1.0, 12, dtype=F64)
    X, Y = torch.zeros(4, 2, dtype=F64), torch.zeros(4, 1, dtype=F64)
    days = torch.arange(12, dtype=F64)
    kw = dict(days=days, threshold=0.9, t_eol=11.0)
    p = studies.ForecastProblem("p", 2, X, Y, z, 6, 1, rul_idx=(5, 10), **kw)
    assert p.rul_index() == [0, 5]  # the first: the belief before the first test target
    for bad in ((2,), (11,)):  # rul_index -3 (read from the end) and 6 (past the last belief)
        with pytest.raises(ValueError, match=r"rul_idx must hold indices of z in .* = \[5, 10\]"):
            studies.ForecastProblem("p", 2, X, Y, z, 6, 1, rul_idx=bad, **kw)


def test_protocol_coverage_compares_the_bounds_in_float64(monkeypatch):
    """An interval [q05, q95] that equals the true RUL at both ends covers it: the bounds were
    built in the default float32, where one of them rounded past the float64 truth (covered 0;
    the pronostia-rul run's q05 of one sampling step)."""
    t, y_t, _, _ = _ramp()
    pc = known_threshold_protocol(t, y_t)
    times = [pc.t_onset + f * (pc.t_eol - pc.t_onset) for f in (0.2, 0.4, 0.6, 0.8, 0.9)]
    truth = [pc.t_eol - x for x in times]

    def at_truth(method, t, y, case, tp, seed, unit):  # q05 = q95 = the true RUL, to the bit
        r = case.t_eol - tp
        return {"pred": r, "lo": r, "hi": r, "censored": 0.0, "model": "m"}

    monkeypatch.setattr(rp, "predict_rul", at_truth)
    rows, _, _, _ = rp.protocol_rows({"s": (t, y_t, False)}, ["m"])
    assert [r["true_rul"] for r in rows] == pytest.approx(truth, abs=1e-12)
    assert any(float(torch.tensor(r["q05"], dtype=torch.float32)) != r["q05"] for r in rows)
    assert [r["covered"] for r in rows] == [1.0] * 5
