"""The parts a forecaster matrix is built from: problems, filters, metrics and the training of
its learners by name, each against a closed form or a hand-computed case."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from prognos_torch.filters import GaussianFilter, ParticleFilter
from prognos_torch.learners import ELM
from prognos_torch.optim import StackedLearner
from prognos_torch.studies import (
    MatrixTraining,
    filter_factories,
    forecast_problem,
    matrix_metrics,
    not_applicable,
    persistence,
    train_forecasters,
)


def _settings(**kw) -> MatrixTraining:
    base = dict(
        elm_hidden=6, elm_lam=1e-3, lssvr_sigma=0.7, lssvr_C=50.0, anfis_mfs=2,
        kalman_R=1e-3, kalman_Q={"ELM": 0.0, "LSSVR": 0.0, "ANFIS": 1e-6},
        kalman_P0={"ELM": {"beta": 1.0}, "LSSVR": {"alpha": 1.0, "b": 1e-2},
                   "ANFIS": {"alpha": 1.0, "b": 1e-2, "beta": 1e-4}},
        kalman_batch={"P": 4}, adam_lr=1e-2, adam={"P": (2, 8)}, lssvr_kalman_max=30,
    )  # fmt: skip
    return MatrixTraining(**(base | kw))


def _problem(n: int = 40, m: int = 3):
    g = torch.Generator().manual_seed(5)
    z = (torch.linspace(0, 3, n + 20, dtype=torch.float64).sin() + 1) / 2
    z = z + 0.01 * torch.randn(n + 20, generator=g, dtype=torch.float64)
    return forecast_problem("P", z[: n + m], z, m, stride=4, s0=n + m)


def _gen(i: int) -> torch.Generator:
    return torch.Generator().manual_seed(100 + i)


def test_forecast_problem_by_hand():
    z = torch.arange(10, dtype=torch.float64) / 10
    days = 0.5 * torch.arange(10, dtype=torch.float64)
    p = forecast_problem(
        "P", z[:6], z, 3, stride=2, days=days, test_from=2.0, threshold=0.65, rul_times=(1.2, 3.0)
    )
    assert p.s0 == 4  # days[4] = 2.0 is the first >= 2.0
    assert p.t_eol == 3.5  # z[7] = 0.7 is the first >= 0.65
    assert p.rul_idx == (3, 6)  # days 1.5 and 3.0
    torch.testing.assert_close(p.X[0], torch.tensor([0.0, 0.1, 0.2], dtype=torch.float64))
    assert p.X.shape == (3, 3) and p.Y[:, 0].tolist() == pytest.approx([0.3, 0.4, 0.5])
    early = forecast_problem("P", z[:6], z, 3, stride=2, days=days, test_from=0.5)
    assert early.s0 == 3  # the first test target needs m values before it
    with pytest.raises(ValueError, match="s0"):
        forecast_problem("P", z[:6], z, 3, stride=2)
    with pytest.raises(ValueError, match="reaches"):
        forecast_problem("P", z[:6], z, 3, stride=2, days=days, test_from=1.0, threshold=2.0)


def test_persistence_is_the_newest_window_value():
    x = torch.tensor([[[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]])
    assert persistence(x).tolist() == [[[3.0], [6.0]]]


def test_not_applicable_rules():
    p, st = _problem(n=40), _settings()
    assert not_applicable("ANFIS", "closed", p, st) is not None
    assert not_applicable("LSSVR", "EKF", p, st) is not None  # 40 windows > 30
    assert not_applicable("LSSVR", "EKF", p, _settings(lssvr_kalman_max=40)) is None
    assert not_applicable("LSSVR", "Adam", p, st) is None
    assert not_applicable("ELM", "ImSRUKF", p, st) is None
    assert not_applicable("ANFIS", "closed", p, st, {"ANFIS-closed": "x"}) == "x"


def test_elm_closed_is_the_ridge_solution_per_run():
    p, st = _problem(), _settings()
    out = train_forecasters("ELM", "closed", p, st, runs=3, generator=_gen)
    assert isinstance(out, StackedLearner) and out.runs == 3
    pred = out(p.X.expand(3, *p.X.shape))
    for i in range(3):
        elm = ELM(p.m, st.elm_hidden, generator=_gen(i))  # run i's own hidden layer
        H = elm.hidden(p.X).numpy()
        beta = np.linalg.solve(H.T @ H + st.elm_lam * np.eye(H.shape[1]), H.T @ p.Y.numpy())
        np.testing.assert_allclose(pred[i].numpy(), H @ beta, rtol=1e-8, atol=1e-10)
    assert not torch.equal(pred[0], pred[1])


def test_elm_kalman_pass_equals_ridge():
    # Q = 0 and P0 = R / lambda: the posterior mean is the ridge solution
    st = _settings(kalman_P0={"ELM": {"beta": 1e-3 / 1e-3}})
    p = _problem()
    ridge = train_forecasters("ELM", "closed", p, st, runs=2, generator=_gen)
    kal = train_forecasters("ELM", "EKF", p, st, runs=2, generator=_gen)
    b_r, b_k = ridge.parameter_sets()["beta"], kal.parameter_sets()["beta"]
    torch.testing.assert_close(b_k, b_r, rtol=1e-6, atol=1e-6)


def test_lssvr_closed_solves_the_kkt_system():
    p, st = _problem(n=25), _settings()
    out = train_forecasters("LSSVR", "closed", p, st, runs=3, generator=_gen)
    X, y = p.X.numpy(), p.Y[:, 0].numpy()
    K = np.exp(-((X[:, None, :] - X[None, :, :]) ** 2).sum(-1) / (2 * st.lssvr_sigma**2))
    n = len(y)
    A = np.block(
        [[np.zeros((1, 1)), np.ones((1, n))], [np.ones((n, 1)), K + np.eye(n) / st.lssvr_C]]
    )
    sol = np.linalg.solve(A, np.concatenate([[0.0], y]))
    b, alpha = sol[0], sol[1:]
    w = p.windows().numpy()
    Kt = np.exp(-((w[:, None, :] - X[None, :, :]) ** 2).sum(-1) / (2 * st.lssvr_sigma**2))
    got = out(p.windows())[..., 0].detach().numpy()
    np.testing.assert_allclose(got, Kt @ alpha + b, rtol=1e-8, atol=1e-10)


def test_batched_trainers_return_runs():
    p, st = _problem(), _settings()
    for learner, trainer in (("ANFIS", "EKF"), ("ANFIS", "Adam"), ("ELM", "Adam")):
        out = train_forecasters(learner, trainer, p, st, runs=2, generator=_gen)
        y = out(p.X.expand(2, *p.X.shape))
        assert y.shape == (2, p.X.shape[0], 1) and torch.isfinite(y).all()
        assert not torch.allclose(y[0], y[1])  # each run its own initialisation
    with pytest.raises(ValueError, match="closed form"):
        train_forecasters("ANFIS", "closed", p, st, runs=2, generator=_gen)
    with pytest.raises(ValueError, match="unknown trainer"):
        train_forecasters("ELM", "LBFGS", p, st, runs=2, generator=_gen)


def test_settings_config_record():
    cfg = _settings().config()
    assert list(cfg) == ["elm", "lssvr", "anfis", "kalman", "adam"]
    assert cfg["elm"] == {"hidden": 6, "lambda": 1e-3, "activation": "sigmoid"}
    assert cfg["kalman"]["batch"] == {"P": 4} and cfg["kalman"]["passes"] == 1
    assert cfg["adam"] == {"lr": 1e-2, "epochs_batch": {"P": (2, 8)}}


def test_filter_factories_and_metrics():
    f = filter_factories(("none", "PF", "STPF", "SCKF"), 17)
    assert f["none"] is None
    pf, stpf, sckf = f["PF"](), f["STPF"](), f["SCKF"]()
    assert isinstance(pf, ParticleFilter) and pf.num_particles == 17 and pf.name == "PF"
    assert isinstance(stpf, ParticleFilter) and stpf.num_particles == 17
    assert isinstance(sckf, GaussianFilter)
    with pytest.raises(ValueError, match="unknown filter"):
        filter_factories(("none", "XKF"), 10)
    assert matrix_metrics(5) == [
        "RMSE_1", "MAE_1", "RMSE_5", "MAE_5", "RUL_MAE_d", "RUL_bias_d", "RUL_censored",
        "AL_mass", "alpha_lambda", "time_s",
    ]  # fmt: skip
