"""The lssvr-stpf study (paper 002) in quick mode, and the Gram-form LS-SVR evaluator it uses."""

from __future__ import annotations

import csv
import json
import math

import pytest
import torch

from prognos_torch.cli import main
from prognos_torch.learners import LSSVR
from prognos_torch.learners.lssvr_gram import LSSVRGram

F64 = torch.float64
METHODS = ("LS-SVR", "LS-SVR PF", "LS-SVR EKPF", "LS-SVR STPF")


# --------------------------------------------------------------------------- LSSVRGram
def _fitted(kernel="rbf", n=60, m=4, n_out=1, sigma=0.7, seed=0):
    g = torch.Generator().manual_seed(seed)
    X = torch.randn(n, m, generator=g, dtype=F64)
    y = torch.sin(X.sum(-1, keepdim=True)) + 0.1 * torch.randn(n, n_out, generator=g, dtype=F64)
    return LSSVR(kernel=kernel, sigma=sigma, C=50.0, n_out=n_out).fit(X, y), g


@pytest.mark.parametrize("n_out", [1, 2])
def test_lssvr_gram_matches_difference_form_and_autograd(n_out):
    lssvr, g = _fitted(n_out=n_out)
    fast = LSSVRGram(lssvr)
    x = torch.randn(17, 4, generator=g, dtype=F64)
    with torch.no_grad():
        ref = lssvr(x)
    torch.testing.assert_close(fast(x), ref, rtol=1e-12, atol=1e-12)
    # leading batch dims (particles, runs)
    xb = x.reshape(1, 17, 4).expand(3, 17, 4)
    torch.testing.assert_close(fast(xb), ref.expand(3, 17, n_out), rtol=1e-12, atol=1e-12)
    # Eq. 25 in closed form vs autograd through the difference form (LSSVR.input_gradient)
    torch.testing.assert_close(
        fast.input_gradient(x), lssvr.input_gradient(x).detach(), rtol=1e-10, atol=1e-12
    )


def test_lssvr_gram_gradient_matches_finite_differences():
    lssvr, g = _fitted()
    fast = LSSVRGram(lssvr)
    x = torch.randn(5, 4, generator=g, dtype=F64)
    h = 1e-6
    fd = torch.stack(
        [(fast(x + h * e) - fast(x - h * e))[:, 0] / (2 * h) for e in torch.eye(4, dtype=F64)],
        dim=-1,
    )
    torch.testing.assert_close(fast.input_gradient(x)[:, 0], fd, rtol=1e-6, atol=1e-8)


def test_lssvr_gram_rejects_bad_input():
    with pytest.raises(TypeError, match="LSSVR"):
        LSSVRGram(torch.nn.Linear(4, 1))
    with pytest.raises(ValueError, match="rbf"):
        LSSVRGram(_fitted(kernel="poly")[0])
    with pytest.raises(ValueError, match="not fitted"):
        LSSVRGram(LSSVR())
    fast = LSSVRGram(_fitted()[0])
    with pytest.raises(ValueError, match="n_in=4"):
        fast(torch.zeros(3, 5, dtype=F64))
    with pytest.raises(TypeError, match="dtype"):
        fast(torch.zeros(3, 4, dtype=torch.float32))
    with pytest.raises(ValueError, match=r"\(B, n_in\)"):
        fast.input_gradient(torch.zeros(2, 3, 4, dtype=F64))


# --------------------------------------------------------------------------- the study
@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("lssvr_stpf")
    rc = main(["study", "lssvr-stpf", "--quick", "--out", str(out), "--no-progress"])
    assert rc == 0
    return out / "lssvr-stpf"


def test_quick_outputs_complete(quick_run):
    for name in ("table.md", "results.csv", "run.json"):
        assert (quick_run / name).is_file()
    meta = json.loads((quick_run / "run.json").read_text())
    assert meta["study"] == "lssvr-stpf" and meta["paper"] == "002"
    assert len(meta["figures"]) >= 10
    for fig in meta["figures"]:
        data = (quick_run / fig).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n", fig
    # the paper's Table 1 and Table 2 numbers sit beside ours
    for metric in ("RMSE_1_12", "RMSE_10_12", "Accuracy", "RUL_RMSE", "alpha_lambda", "CRA"):
        assert set(meta["paper_numbers"]) == set(METHODS)
        assert all(metric in meta["paper_numbers"][m] for m in METHODS)
    table = (quick_run / "table.md").read_text()
    assert "RMSE_1_12 (paper)" in table and "QUICK MODE" in table


def test_quick_results_finite_and_in_range(quick_run):
    with open(quick_run / "results.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert {r["method"] for r in rows} == set(METHODS)
    assert sum(r["method"] == "LS-SVR" for r in rows) == 1  # deterministic: one row
    runs = sum(r["method"] == "LS-SVR STPF" for r in rows)
    assert runs >= 2
    meta = json.loads((quick_run / "run.json").read_text())
    n_part = meta["study_config"]["particles"]
    horizon_days = meta["study_config"]["horizon_steps"] * meta["study_config"]["dt_days"]
    for r in rows:
        pf = r["method"] != "LS-SVR"
        keys = ["RMSE_1_12", "RMSE_10_12", "Accuracy", "RUL_RMSE", "alpha_lambda", "CRA"]
        keys += ["censored", "time_s"]
        if pf:
            keys += ["filt_RMSE_1_12", "filt_RMSE_10_12", "Pf_10_11", "Pf_11_12", "ess"]
        v = {k: float(r[k]) for k in keys}
        assert all(math.isfinite(x) for x in v.values()), r
        assert v["RMSE_1_12"] > 0 and v["RMSE_10_12"] > 0
        # guaranteed ranges: probabilities, exponential accuracy, a bounded RUL estimate
        assert 0.0 < v["Accuracy"] <= 1.0
        assert v["alpha_lambda"] in (0.0, 1.0)
        assert 0.0 <= v["censored"] <= 1.0
        # every RUL estimate lies in (0, horizon] and every true RUL in (0, horizon)
        assert v["RUL_RMSE"] < horizon_days
        assert v["CRA"] <= 1.0  # RA <= 1 by definition
        if pf:
            assert 0.0 <= v["Pf_10_11"] <= 1.0 and 0.0 <= v["Pf_11_12"] <= 1.0
            assert 1.0 - 1e-9 <= v["ess"] <= n_part + 1e-9
