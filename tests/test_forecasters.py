"""Evaluating one-step forecasters alone and inside prognostic filters; the forecaster matrix."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from _kalman_reference import kalman_filter
from torch import nn

from prognos_torch.filters import sckf, sir
from prognos_torch.optim import StackedLearner
from prognos_torch.studies import (
    ForecastProblem,
    ForecastProtocol,
    evaluate_alone,
    evaluate_filtered,
    healthy_runs,
    point_errors,
    residual_noise,
    rul_scores,
    run_forecaster_matrix,
)

F64 = torch.float64


def _problem(threshold=None, T=60, m=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    z = 0.5 + 0.05 * torch.randn(T, generator=g, dtype=F64).cumsum(0)
    X = z[:30].unfold(0, m, 1)[:-1]
    Y = z[m:30, None]
    days = torch.arange(T, dtype=F64)
    kw = dict(days=days, threshold=threshold, t_eol=55.0, rul_idx=(40, 50)) if threshold else {}
    return ForecastProblem("P", m, X.contiguous(), Y.contiguous(), z, 30, 5, **kw)


def _linear(R=2, m=3):
    mods = []
    for r in range(R):
        lin = nn.Linear(m, 1, bias=False, dtype=F64)
        with torch.no_grad():
            lin.weight.copy_(torch.tensor([[0.1, 0.2 + 0.1 * r, 0.6]], dtype=F64))
        mods.append(lin)
    return StackedLearner.from_modules(mods), mods


def test_alone_matches_a_direct_recursion_and_numpy_errors():
    p, pr = _problem(), ForecastProtocol(horizon=4)
    st, mods = _linear()
    out = evaluate_alone(st, p, 2, pr)
    z = p.z.numpy()
    for r, lin in enumerate(mods):
        w = lin.weight.detach().numpy()[0]
        one = np.array([z[t - 3 : t] @ w for t in range(30, 60)])
        e1 = one - z[30:]
        assert out["RMSE_1"][r].item() == pytest.approx(np.sqrt((e1**2).mean()), rel=1e-12)
        assert out["MAE_1"][r].item() == pytest.approx(np.abs(e1).mean(), rel=1e-12)
        errs = []
        for o in range(0, 30 - 4 + 1, 5):  # 4-step recursion from each origin
            win = list(z[30 + o - 3 : 30 + o])
            for _ in range(4):
                win.append(np.dot(win[-3:], w))
            errs.append(win[-1] - z[30 + o + 3])
        assert out["RMSE_4"][r].item() == pytest.approx(
            np.sqrt(np.mean(np.square(errs))), rel=1e-12
        )


def test_gaussian_evaluation_of_a_linear_learner_equals_a_kalman_filter():
    # a linear one-step learner makes the window model linear-Gaussian: the SCKF is exact
    p, pr = _problem(), ForecastProtocol(horizon=4)
    st, mods = _linear()
    SQ, SR, _ = residual_noise(st, p, 2, r_share=0.75, shift_std=0.5)
    out = evaluate_filtered(st, sckf(), p, 2, SQ, SR, torch.Generator().manual_seed(0), pr)
    z, y = p.z.numpy(), p.targets.numpy()
    for r, lin in enumerate(mods):
        F = np.eye(3, k=1)
        F[-1] = lin.weight.detach().numpy()[0]
        H = np.array([[0.0, 0.0, 1.0]])
        Q, R = (SQ @ SQ.T).numpy(), (SR @ SR.T).numpy()
        m0, P0 = z[27:30], float(SR[0, 0]) ** 2 * np.eye(3)
        means, _, _ = kalman_filter(F, H, Q, R, m0, P0, y[:, None])
        prior = np.vstack([m0, means[:-1]])
        pred1 = (prior @ F.T) @ H.T
        e1 = pred1[:, 0] - y
        assert out["RMSE_1"][r].item() == pytest.approx(np.sqrt((e1**2).mean()), rel=1e-10)


def test_particle_evaluation_approaches_the_kalman_filter():
    p, pr = _problem(), ForecastProtocol(horizon=4)
    st, _ = _linear(R=1)
    SQ, SR, _ = residual_noise(st, p, 1, r_share=0.75, shift_std=0.5)
    g = torch.Generator().manual_seed(1)
    pf = evaluate_filtered(st, sir(4000), p, 1, SQ, SR, g, pr)
    kf = evaluate_filtered(st, sckf(), p, 1, SQ, SR, g, pr)
    assert pf["RMSE_1"].item() == pytest.approx(kf["RMSE_1"].item(), rel=0.05)
    assert pf["RMSE_4"].item() == pytest.approx(kf["RMSE_4"].item(), rel=0.1)


def test_rul_scores_of_deterministic_paths():
    p, pr = _problem(threshold=1.0), ForecastProtocol(horizon=4, rul_horizon=30)
    # prediction times 40 and 50, true RUL 15 and 5: run 0's paths cross after 12 and 5 steps
    paths = torch.zeros(2, 2, 1, 30, dtype=F64)
    paths[0, 0, 0, 11:] = 2.0
    paths[0, 1, 0, 4:] = 2.0
    paths[1, :, 0, :] = 0.0  # run 1 never crosses: censored at both times
    out = rul_scores(paths, None, p, pr)
    assert out["RUL_MAE_d"].tolist()[0] == pytest.approx((3 + 0) / 2)
    assert out["RUL_bias_d"].tolist()[0] == pytest.approx(-1.5)
    assert out["RUL_censored"].tolist() == [0.0, 1.0] and math.isnan(out["RUL_MAE_d"][1])
    # t_lambda = 40 + 0.5 (55 - 40) = 47.5 -> the first time at or after it: 50, true RUL 5;
    # run 0's mass (a point at 5) lies in [3.5, 6.5]
    assert out["AL_mass"].tolist() == [1.0, 0.0] and out["alpha_lambda"].tolist() == [1.0, 0.0]
    bad = paths.clone()
    bad[1, 0, 0, 3] = math.nan
    assert math.isnan(rul_scores(bad, None, p, pr)["AL_mass"][1])


def test_point_errors_noise_and_health():
    p, pr = _problem(), ForecastProtocol(horizon=4)
    T = p.targets.shape[0]
    pred1 = p.targets.expand(2, T) + torch.tensor([[0.0], [0.1]], dtype=F64)
    predH = torch.zeros(2, len(p.origins(4)), 4, dtype=F64)
    e = point_errors(pred1, predH, p, pr)
    assert e["RMSE_1"].tolist() == pytest.approx([0.0, 0.1]) and set(e) == {
        "RMSE_1",
        "MAE_1",
        "RMSE_4",
        "MAE_4",
    }
    ident = StackedLearner.from_modules([nn.Linear(3, 1, dtype=F64)])
    with torch.no_grad():
        ident.parameter_sets()["weight"].copy_(torch.tensor([[[0.0, 0.0, 1.0]]]))
        ident.parameter_sets()["bias"].zero_()
    SQ, SR, s = residual_noise(ident, p, 1, r_share=0.75, shift_std=0.5)
    res = (p.X[:, -1:] - p.Y).square().mean().sqrt().item()
    assert s == pytest.approx(res, rel=1e-14) and SR.item() == pytest.approx(res * 0.75**0.5)
    torch.testing.assert_close(SQ.diagonal(), res * 0.5 * torch.tensor([0.5, 0.5, 1.0], dtype=F64))
    assert healthy_runs(ident, p, 1, max_rmse=1.0).tolist() == [True]
    assert healthy_runs(ident, p, 1, max_rmse=res / 2).tolist() == [False]


def test_forecaster_matrix_statuses_tables_and_heatmaps():
    p = _problem()

    def train(ln, tn, s):
        st, _ = _linear()
        if tn == "bad":  # every run diverges in training
            with torch.no_grad():
                st.parameter_sets()["weight"].mul_(1e6)
        return st

    res = run_forecaster_matrix(
        [p],
        ["LIN"],
        ["good", "bad", "never"],
        {"none": None, "SCKF": sckf, "PF": lambda: sir(50)},
        train,
        runs=2,
        protocol=ForecastProtocol(horizon=4),
        r_share=0.75,
        shift_std=0.5,
        max_rmse=1.0,
        shared_runs=1,
        seed=0,
        not_applicable=lambda ln, tn, s: "not here" if tn == "never" else None,
        skip=lambda ln, tn, f: "reduced" if f == "PF" and tn == "good" else None,
        references={"persistence": lambda x: x[..., -1:]},
        progress=False,
    )
    c = res.combo("P", "LIN", "good")
    assert res.cells[(c, "none")].status == "ok" and res.cells[(c, "PF")].status == "skipped"
    assert res.cells[(res.combo("P", "LIN", "never"), "SCKF")].status == "n/a"
    bad = res.combo("P", "LIN", "bad")
    assert res.cells[(bad, "SCKF")].status == "failed" and res.label(bad, "SCKF") == "div."
    assert res.info[bad]["diverged_runs"] == 2
    alone = evaluate_alone(_linear()[0], p, 2, ForecastProtocol(horizon=4))
    assert res.mean(c, "none", "RMSE_1") == pytest.approx(alone["RMSE_1"].mean().item())
    assert res.best("P", "RMSE_1", filters=("none",))[1] == c
    table = res.table(4)
    assert (
        "| P | LIN | never | SCKF | n/a [" in table and "| P | persistence | none | none |" in table
    )
    assert "\n[1] " in table and "\n[2] every run diverged" in table and "not here" in table
    piv = res.pivots()[0]
    assert "| LIN |" in piv and "| n/a |" in piv
    vals, rows, cols, labels = res.heatmap("P", "RMSE_1", alone=True, log=True)
    assert rows == ["LIN"] and cols == ["good", "bad", "never"]
    assert vals[0, 0] == pytest.approx(math.log10(res.mean(c, "none", "RMSE_1")))
    assert labels[0][1:] == ["div.", "n/a"]
    assert res.view("P")["LIN-good none"] == res.mean(c, "none", "RMSE_1")
