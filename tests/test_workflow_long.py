"""Long series in the workflow: the LS-SVR size policy, the fixed-size LS-SVR end to end, the
memory budget (``PROGNOS_MEMORY_BUDGET``) and its one-line refusals, and the capped holdout.

Refusals are tested with a low budget, never by exhausting the machine.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest
import torch

import prognos_torch.workflow.model as model_mod
from prognos_torch.cli import main
from prognos_torch.learners import LSSVR, FixedSizeLSSVR
from prognos_torch.workflow import fit_series, forecast, load_model, load_series, rul, save_model
from prognos_torch.workflow.memory import (
    DEFAULT_SUPPORT,
    FULL_LSSVR_MAX_ROWS,
    MemoryBudgetError,
    check_fit_memory,
    fit_bytes,
    lssvr_support,
    memory_budget,
    parse_bytes,
)
from prognos_torch.workflow.predict import HOLDOUT_FORECAST_STEPS


def _values(T: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = np.arange(T)
    a = np.zeros(T)
    e = 0.05 * rng.standard_normal(T)
    for i in range(1, T):
        a[i] = 0.8 * a[i - 1] + e[i]
    return 1.0 + 0.3 * np.sin(2 * np.pi * t / 48) + 0.2 * t / T + a


def _csv(path: Path, x: np.ndarray) -> Path:
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t", "rms"])
        for i, v in enumerate(x):
            w.writerow([i, repr(float(v))])
    return path


def _one_error_line(capsys, *patterns: str) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert err.startswith("error: ")
    for p in patterns:
        assert p in err, err
    return err


# --------------------------------------------------------------------------- policy and budget
def test_lssvr_support_policy():
    assert lssvr_support(FULL_LSSVR_MAX_ROWS, None) is None  # exact LS-SVR
    assert lssvr_support(FULL_LSSVR_MAX_ROWS + 1, None) == DEFAULT_SUPPORT
    assert lssvr_support(300, 300) is None
    assert lssvr_support(301, 300) == 300
    assert lssvr_support(10**6, 10**6) is None
    for bad in (0, -3, 2.5, True, "100"):
        with pytest.raises(ValueError, match="max_support must be a positive int or None"):
            lssvr_support(100, bad)


def test_parse_bytes_and_budget(monkeypatch):
    assert parse_bytes("1000") == 1000
    assert parse_bytes("512M") == 512 * 2**20
    assert parse_bytes("1.5GB") == int(1.5 * 2**30)
    assert parse_bytes(" 2 g ") == 2 * 2**30
    assert parse_bytes("4KiB") == 4096
    for bad in ("lots", "-1G", "0", "1.2.3M"):
        with pytest.raises(ValueError, match="PROGNOS_MEMORY_BUDGET"):
            parse_bytes(bad)
    monkeypatch.setenv("PROGNOS_MEMORY_BUDGET", "3M")
    assert memory_budget() == 3 * 2**20
    monkeypatch.delenv("PROGNOS_MEMORY_BUDGET")
    assert memory_budget() > 2**26


def test_fit_estimates_grow_as_expected():
    opts = {"max_support": None}
    full, what = fit_bytes("lssvr", "closed-form", 2000, 4, opts)
    assert "2,000 x 2,000 kernel matrix" in what and full > 3 * 8 * 2000**2
    big = fit_bytes("lssvr", "closed-form", 40000, 4, {"max_support": 40000})[0]
    assert big > 3 * 8 * 40000**2  # the exact LS-SVR forced on 40,000 rows: ~38 GB
    reduced = fit_bytes("lssvr", "closed-form", 100000, 10, opts)[0]
    assert reduced < 2**28  # the fixed-size LS-SVR on 10^5 rows: well under 256 MB
    elm = fit_bytes("elm", "closed-form", 100000, 10, {"n_hidden": 20})[0]
    assert 3 * 8 * 100000 * 20 < elm < 2**27
    anfis = fit_bytes("anfis", "closed-form", 1000, 5, {"n_mfs": 3})
    assert "243 rules" in anfis[1]


def test_refusal_message_names_the_options(monkeypatch):
    monkeypatch.setenv("PROGNOS_MEMORY_BUDGET", "100M")
    with pytest.raises(MemoryBudgetError) as info:
        check_fit_memory("lssvr", "closed-form", 20000, 4, {"max_support": 20000})
    msg = str(info.value)
    assert "\n" not in msg
    for part in ("20,000 x 20,000 kernel matrix", "100 MB", "PROGNOS_MEMORY_BUDGET",
                 "--max-support M", "--last N", "--learner elm"):  # fmt: skip
        assert part in msg, msg
    assert check_fit_memory("lssvr", "closed-form", 20000, 4, {"max_support": None}) < 2**27


# --------------------------------------------------------------------------- fixed-size LS-SVR
def test_fit_chooses_fixed_size_above_the_threshold_and_round_trips(tmp_path):
    s = load_series(_values(700))
    exact = fit_series(s, "lssvr", m=3, holdout=50)  # 650 training values <= 2,000: exact
    assert type(exact.learner) is LSSVR and "support" not in exact.config["train"]
    model = fit_series(s, "lssvr", m=3, holdout=50, learner_options={"max_support": 80})
    net = model.learner
    assert isinstance(net, FixedSizeLSSVR) and net.support_vectors.shape == (80, 3)
    sup = model.config["train"]["support"]
    assert sup == {"kind": "fixed-size", "n_support": 80, "selection": "renyi", "rank": net.rank}
    assert model.config["learner_options"]["max_support"] == 80
    # held-out one-step RMSE close to the exact LS-SVR's on the same split
    r_fs, r_ex = model.metrics["one_step_rmse"], exact.metrics["one_step_rmse"]
    assert abs(r_fs / r_ex - 1) < 0.05, (r_fs, r_ex)
    # deterministic (the selection's generator comes from the seed)
    again = fit_series(s, "lssvr", m=3, holdout=50, learner_options={"max_support": 80})
    assert torch.equal(again.learner.support_vectors, net.support_vectors)
    assert torch.equal(again.learner.alpha, net.alpha)
    # the model file rebuilds the same class; forecasts and RUL are bit-identical
    path = tmp_path / "fs.pt"
    save_model(model, path)
    loaded = load_model(path)
    assert type(loaded.learner) is FixedSizeLSSVR
    a = forecast(model, s, 20, filter="stpf", n_particles=50)
    b = forecast(loaded, s, 20, filter="stpf", n_particles=50)
    assert torch.equal(a.mean, b.mean) and torch.equal(a.samples, b.samples)
    threshold = float(s.values.max()) + 0.2
    r1 = rul(model, s, threshold, horizon=60, n_particles=50, filter="ekpf")
    r2 = rul(loaded, s, threshold, horizon=60, n_particles=50, filter="ekpf")
    assert torch.equal(r1.paths, r2.paths)


def test_iterative_optimiser_over_the_fixed_size_state():
    # M + 1 = 31 trainable parameters: the Kalman optimiser is allowed (N + 1 would be refused)
    s = load_series(_values(900))
    model = fit_series(s, "lssvr", "ekf", m=2, holdout=0, learner_options={"max_support": 30})
    assert isinstance(model.learner, FixedSizeLSSVR)
    assert math.isfinite(model.config["residual_rmse"]) and model.config["train"]["epochs"] == 1


def test_holdout_forecast_is_capped_one_step_uses_the_whole_tail():
    x = _values(HOLDOUT_FORECAST_STEPS + 400)
    s = load_series(x)
    n_hold = HOLDOUT_FORECAST_STEPS + 100
    model = fit_series(s, "elm", m=3, holdout=n_hold)
    mt = model.metrics
    assert mt["horizon"] == HOLDOUT_FORECAST_STEPS and mt["tail"] == n_hold
    n_train = len(s) - n_hold
    fc = forecast(model, s.head(n_train), HOLDOUT_FORECAST_STEPS)
    tail = s.values[n_train:]
    head = tail[:HOLDOUT_FORECAST_STEPS]
    assert mt["rmse"] == pytest.approx(float((fc.mean - head).square().mean().sqrt()))
    z = model.scaler.transform(s.values)
    with torch.no_grad():
        one = model.scaler.inverse_transform(model.learner(z.unfold(0, 3, 1)[n_train - 3 : -1]))
    assert mt["one_step_rmse"] == pytest.approx(float((one[:, 0] - tail).square().mean().sqrt()))


# --------------------------------------------------------------------------- error reporting
def test_select_embedding_reports_the_real_cause(monkeypatch):
    s = load_series(_values(200))

    def fails(*args, **kw):
        raise ValueError("Omega + I/C is not positive definite")

    monkeypatch.setattr(model_mod, "_closed_form", fails)
    with pytest.raises(ValueError) as info:
        fit_series(s, "lssvr")
    msg = str(info.value)
    assert "no embedding dimension gave a finite validation error" in msg
    assert "LSSVR failed for every m in [2, 3" in msg and "not positive definite" in msg

    def oom(*args, **kw):
        raise RuntimeError("[enforce fail at alloc_cpu.cpp:117] DefaultCPUAllocator: can't "
                           "allocate memory: you tried to allocate 327680000000 bytes.")  # fmt: skip

    monkeypatch.setattr(model_mod, "_closed_form", oom)
    with pytest.raises(MemoryBudgetError, match=r"out of memory .* --max-support M"):
        fit_series(s, "lssvr")


# --------------------------------------------------------------------------- command line
def test_cli_refuses_over_budget_with_one_line_and_writes_nothing(tmp_path, capsys, monkeypatch):
    data = _csv(tmp_path / "long.csv", _values(3000))
    out = tmp_path / "model.pt"
    monkeypatch.setenv("PROGNOS_MEMORY_BUDGET", "64M")
    base = ["fit", str(data), "--column", "rms", "--time-column", "t", "--out", str(out)]
    # the exact LS-SVR on 2,400 training values needs ~140 MB > 64 MB
    assert main(base + ["--learner", "lssvr", "--max-support", "5000"]) == 2
    _one_error_line(capsys, "kernel matrix", "64 MB", "--max-support M", "--last N", "elm")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["long.csv"]
    # the ELM's hidden layer: 2,400 x 20000 doubles
    args = base + ["--learner", "elm", "--learner-option", "n_hidden=20000"]
    assert main(args) == 2
    _one_error_line(capsys, "hidden-layer matrix", "fewer hidden nodes (n_hidden)")
    assert not out.exists()
    # --max-support only for the LS-SVR
    assert main(base + ["--learner", "elm", "--max-support", "10"]) == 2
    _one_error_line(capsys, "--max-support applies to --learner lssvr")
    # the default policy fits: a fixed-size LS-SVR on 50 support points
    assert main(base + ["--learner", "lssvr", "--embedding", "3"]) == 0
    text = capsys.readouterr().out
    assert f"support points  {DEFAULT_SUPPORT} (fixed-size LS-SVR" in text
    assert out.exists()
    # rul / forecast with a particle request over the budget
    png = tmp_path / "rul.png"
    rul_args = ["rul", str(out), str(data), "--threshold", "9", "--plot", str(png)]
    assert main(rul_args + ["--particles", "200000", "--horizon", "1000"]) == 2
    _one_error_line(capsys, "particle paths", "--particles", "--horizon")
    fc_args = ["forecast", str(out), str(data), "--horizon", "2000", "--filter", "pf"]
    assert main(fc_args + ["--particles", "100000", "--csv", str(tmp_path / "f.csv")]) == 2
    _one_error_line(capsys, "particle paths")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["long.csv", "model.pt"]


def test_cli_max_support_and_last(tmp_path, capsys):
    data = _csv(tmp_path / "s.csv", _values(1500))
    out = tmp_path / "m.pt"
    args = ["fit", str(data), "--column", "rms", "--learner", "lssvr", "--embedding", "2"]
    assert main(args + ["--max-support", "40", "--last", "600", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "rows            600 (training 480, held out 120)" in text
    assert "support points  40 (fixed-size LS-SVR, renyi selection" in text
    model = load_model(out)
    assert isinstance(model.learner, FixedSizeLSSVR)
    assert model.learner.support_vectors.shape == (40, 2)


def test_cli_help_states_the_policy(capsys):
    with pytest.raises(SystemExit):
        main(["fit", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert f"exact up to {FULL_LSSVR_MAX_ROWS} values, else {DEFAULT_SUPPORT} points" in text
    assert "PROGNOS_MEMORY_BUDGET" in text


def test_prognose_refuses_paths_beyond_the_budget_before_it_runs(monkeypatch):
    """n_paths had no bound: 10^9 paths ran until the process was killed for memory."""
    from prognos_torch.workflow import prognose
    from prognos_torch.workflow.memory import KERNEL_BLOCK_BYTES, PROGNOSE_VALUES_PER_PATH

    monkeypatch.setenv("PROGNOS_MEMORY_BUDGET", "100M")
    y = np.r_[np.ones(50), 1.0 + 0.1 * np.arange(1, 51)]
    with pytest.raises(MemoryBudgetError, match=r"n_paths = 1,000,000,000 sample paths need "
                       r"about 3.73 TB, more than the memory budget of 100 MB"):  # fmt: skip
        prognose(y, 20.0, n_paths=10**9)
    fits = (100 * 2**20 - KERNEL_BLOCK_BYTES) // (8 * PROGNOSE_VALUES_PER_PATH)
    assert fits > 2000  # the default fits a budget of 100 MB
    assert prognose(y, 20.0, n_paths=fits, method="linear").status == "ok"
    with pytest.raises(MemoryBudgetError):
        prognose(y, 20.0, n_paths=fits + 1, method="linear")


def test_forecast_refuses_a_horizon_beyond_the_budget_before_it_runs(monkeypatch):
    """forecast --horizon 1e6 ran for minutes at 1.8 GB and on (rul's paths were bounded)."""
    from prognos_torch.workflow import fit_series, forecast, load_series
    from prognos_torch.workflow.memory import FORECAST_VALUES_PER_STEP, KERNEL_BLOCK_BYTES

    model = fit_series(load_series(np.sin(np.arange(80) / 5.0)), "elm", None, 3)
    monkeypatch.setenv("PROGNOS_MEMORY_BUDGET", "100M")
    fits = (100 * 2**20 - KERNEL_BLOCK_BYTES) // (8 * FORECAST_VALUES_PER_STEP)
    with pytest.raises(MemoryBudgetError, match=f"a forecast of {fits + 1:,} steps needs about"):
        forecast(model, load_series(np.sin(np.arange(80) / 5.0)), fits + 1)
