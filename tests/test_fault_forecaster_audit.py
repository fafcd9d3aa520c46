"""Audit of prognosis.fault, prognosis.particle_prediction and prognosis.forecaster.

Exact references: a plain NumPy Kalman filter run on the record and then on the
pseudo-measurements (rolling n-step fault prediction, time alignment, no leakage), the noise-free
recursion written out by hand (rolling particle prediction from the kept states), the closed-form
predictive moments of a linear-Gaussian model (Monte Carlo, within a stated tolerance), and the
generator's state (an argument refused before the first draw leaves it as it was).
"""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import torch

from prognos_torch.core import GaussianBelief, StateSpaceModel
from prognos_torch.filters import sckf, sir
from prognos_torch.learners import ELM
from prognos_torch.prognosis import (
    MeasurementForecaster,
    predict_fault_parameter,
    rolling_fault_prediction,
    rolling_particle_prediction,
)

F64 = torch.float64


def _close(got, want, tol=1e-12):
    """max |got - want| <= tol (torch.testing.assert_close imports torch.distributed: ~1 s)."""
    assert got.shape == want.shape, (got.shape, want.shape)
    err = float((got - want).abs().max())
    assert err <= tol, err


def _gen(seed=0):
    return torch.Generator().manual_seed(seed)


class _Persistence:
    """Forecaster: the last real measurement repeated (records what it was shown)."""

    def __init__(self):
        self.last = None
        self.seen = 0

    @property
    def initialized(self):
        return self.last is not None

    def copy(self):
        return copy.copy(self)

    def initialize(self, z0):
        self.last, self.seen = z0[-1], z0.shape[0]
        return self

    def update(self, z):
        self.last, self.seen = z, self.seen + 1
        return self

    def forecast(self, n):
        return self.last.unsqueeze(0).expand(n, *self.last.shape).clone()


# ----------------------------------------------------------------------------- fault.py
A = np.array([[0.9, 0.2], [0.0, 0.95]])
C = np.array([[1.0, 0.5]])
SQ = np.array([[0.1, 0.0], [0.05, 0.2]])
SR = np.array([[0.3]])
B = np.array([[0.5], [1.0]])


def _lin_model():
    """x_k = A x_{k-1} + B u_k + w_k, y_k = C x_k + v_k (batched: no vmap start-up cost)."""
    At, Bt, Ct = (torch.tensor(M) for M in (A, B, C))
    return StateSpaceModel(
        lambda x, u, k: x @ At.mT + u @ Bt.mT, lambda x, u, k: x @ Ct.mT, 2, 1,
        chol_Q=torch.tensor(SQ), chol_R=torch.tensor(SR), control_dim=1, batched=True,
    )  # fmt: skip


def _kf(m, P, ys, us):
    """Plain Kalman filter (covariance form) over (ys, us); returns the last mean/covariance."""
    for y, u in zip(ys, us):
        m = A @ m + B @ u
        P = A @ P @ A.T + SQ @ SQ.T
        S = C @ P @ C.T + SR @ SR.T
        K = P @ C.T @ np.linalg.inv(S)
        m = m + K @ (y - C @ m)
        P = P - K @ S @ K.T
    return m, P


def test_rolling_fault_prediction_equals_a_plain_kalman_filter_without_leakage():
    T, n, start = 10, 3, 4
    rng = np.random.default_rng(0)
    ys, us = rng.normal(size=(T, 1, 1)), rng.normal(size=(T + n, 1))
    m0, P0 = np.array([1.0, -1.0]), np.diag([0.5, 2.0])
    b0 = GaussianBelief(
        torch.tensor(m0).reshape(1, 2), torch.linalg.cholesky(torch.tensor(P0)).reshape(1, 2, 2)
    )
    res = rolling_fault_prediction(
        sckf(), _lin_model(), torch.tensor(ys), _Persistence(), n, start, init=b0,
        us=torch.tensor(us),
    )  # fmt: skip
    assert res.origin.tolist() == list(range(start, T + 1))
    assert res.target.tolist() == list(range(start + n, T + n + 1))
    assert res.forecaster.seen == T
    for i, k in enumerate(res.origin.tolist()):
        # made at k: the measurements z_1..z_k (ys[:k]) only, then z_k repeated n times
        m, P = _kf(m0, P0, ys[:k, 0], us[:k])
        np.testing.assert_allclose(res.filtered[k - 1, 0].numpy(), m, rtol=0, atol=1e-12)
        m, P = _kf(m, P, [ys[k - 1, 0]] * n, us[k : k + n])
        np.testing.assert_allclose(res.predicted[i, 0].numpy(), m, rtol=0, atol=1e-12)
        np.testing.assert_allclose(
            res.predicted_std[i, 0].numpy(), np.sqrt(np.diag(P)), rtol=0, atol=1e-12
        )


def _drift():
    model = StateSpaceModel(
        None, lambda x, u, k: x, 1, 1, chol_Q=0.1 * torch.eye(1, dtype=F64),
        chol_R=0.2 * torch.eye(1, dtype=F64), batched=True,
    )  # fmt: skip
    b0 = GaussianBelief(torch.zeros(2, 1, dtype=F64), torch.eye(1, dtype=F64).expand(2, 1, 1))
    ys = torch.randn(10, 2, 1, generator=_gen(), dtype=F64)
    return model, b0, ys


def test_rolling_fault_prediction_names_filter_model_and_forecaster():
    model, b0, ys = _drift()
    fc = _Persistence()
    with pytest.raises(TypeError, match=r"filt must be a GaussianFilter.*sckf\(\)"):
        rolling_fault_prediction(sckf, model, ys, fc, 2, 5, init=b0)  # the factory, uncalled
    with pytest.raises(TypeError, match="model must be a StateSpaceModel, got str"):
        rolling_fault_prediction(sckf(), "model", ys, fc, 2, 5, init=b0)
    with pytest.raises(TypeError, match="forecaster must have initialized, copy"):
        rolling_fault_prediction(sckf(), model, ys, object(), 2, 5, init=b0)
    with pytest.raises(TypeError, match="model must be a StateSpaceModel, got str"):
        predict_fault_parameter(sckf(), "model", sckf().init(model, b0), fc, 2, 5)


def test_rolling_fault_prediction_controls_checked_against_the_whole_horizon():
    model = _lin_model()
    ys = torch.randn(10, 2, 1, generator=_gen(), dtype=F64)
    b0 = GaussianBelief(torch.zeros(2, 2, dtype=F64), torch.eye(2, dtype=F64).expand(2, 2, 2))
    us = torch.zeros(12, 3, 1, dtype=F64)  # T + n rows, 3 runs for 2
    with pytest.raises(ValueError, match=r"us must have shape .* with T = 12, got \(12, 3, 1\)"):
        rolling_fault_prediction(sckf(), model, ys, _Persistence(), 2, 5, init=b0, us=us)


# ----------------------------------------------------------------------------- particles
def _tv_model(chol_q=0.0):
    """x_k = 0.9 x_{k-1} + 0.1 k + u_k, y_k = x_k: a step index or control off by one shows."""
    return StateSpaceModel(
        lambda x, u, k: 0.9 * x + 0.1 * k + u, lambda x, u, k: x, 1, 1,
        chol_Q=chol_q * torch.eye(1, dtype=F64), chol_R=0.5 * torch.eye(1, dtype=F64),
        control_dim=1, batched=True,
    )  # fmt: skip


def test_rolling_particle_prediction_without_noise_is_the_recursion_from_the_state_at_k_minus_1():
    T, H, k0, R, thr = 6, 3, 2, 2, 0.3
    us = 0.01 * torch.arange(T + H - 1, dtype=F64).reshape(-1, 1)
    b0 = GaussianBelief(torch.zeros(R, 1, dtype=F64), torch.eye(1, dtype=F64).expand(R, 1, 1))
    ys = torch.randn(T, R, 1, generator=_gen(1), dtype=F64)
    rp = rolling_particle_prediction(
        sir(30), _tv_model(), b0, ys, H, generator=_gen(), us=us, k0=k0,
        keep=range(k0, k0 + T + 1), threshold=thr,
    )  # fmt: skip
    for t in range(T):
        k = k0 + t + 1
        st = rp.states[k - 1]  # before y_k
        x, w = st.particles[..., 0], st.weights
        for j in range(1, H + 1):
            kk = k - 1 + j
            x = 0.9 * x + 0.1 * kk + us[kk - k0 - 1, 0]
            mean = (w * x).sum(-1)
            std = (w * (x - mean.unsqueeze(-1)) ** 2).sum(-1).sqrt()
            _close(rp.mean[t, :, j - 1], mean)
            _close(rp.std[t, :, j - 1], std)
            fault = (w * (x >= thr)).sum(-1)
            _close(rp.fault_probability[t, :, j - 1], fault)


def test_rolling_particle_prediction_monte_carlo_moments_match_the_closed_form():
    # first row: particles ~ N(m0, P0) at k0 propagated j steps of x = a x + w, y = x
    a, q, N, H = 0.8, 0.3, 20000, 3
    model = StateSpaceModel(
        lambda x, u, k: a * x, lambda x, u, k: x, 1, 1, chol_Q=q * torch.eye(1, dtype=F64),
        chol_R=0.5 * torch.eye(1, dtype=F64), batched=True,
    )  # fmt: skip
    m0, s0 = 1.5, 0.7
    b0 = GaussianBelief(torch.full((1, 1), m0, dtype=F64), torch.full((1, 1, 1), s0, dtype=F64))
    rp = rolling_particle_prediction(
        sir(N), model, b0, torch.zeros(1, 1, 1, dtype=F64), H, generator=_gen(3)
    )
    for j in range(1, H + 1):
        mean = a**j * m0
        var = a ** (2 * j) * s0**2 + sum(a ** (2 * i) * q**2 for i in range(j))
        # 5 standard errors of the sample mean and of the sample variance
        assert abs(float(rp.mean[0, 0, j - 1]) - mean) < 5 * math.sqrt(var / N)
        assert abs(float(rp.std[0, 0, j - 1]) ** 2 - var) < 5 * var * math.sqrt(2 / N)


def _pp_args(T=5):
    b0 = GaussianBelief(torch.zeros(2, 1, dtype=F64), torch.eye(1, dtype=F64).expand(2, 1, 1))
    us = torch.zeros(T + 1, 1, dtype=F64)
    return _tv_model(0.1), b0, torch.randn(T, 2, 1, generator=_gen(), dtype=F64), us


def test_rolling_particle_prediction_keep_named():
    model, b0, ys, us = _pp_args()
    for keep in (3, None, [1, "a"]):
        with pytest.raises(TypeError, match="keep must"):
            rolling_particle_prediction(
                sir(10), model, b0, ys, 2, generator=_gen(), us=us, keep=keep
            )
    rp = rolling_particle_prediction(
        sir(10), model, b0, ys, 2, generator=_gen(), us=us, keep=np.array([1, 1, 3])
    )
    assert sorted(rp.states) == [1, 3]


@pytest.mark.parametrize(
    "change, error, message",
    [
        ({"threshold": float("nan")}, ValueError, "threshold must be finite"),
        ({"threshold": "1"}, TypeError, "threshold must be a real number"),
        ({"channel": 3}, ValueError, r"channel must be an int in \[0, 1\)"),
        ({"ys_inf": True}, ValueError, "ys contains inf"),
        ({"us_nan": True}, ValueError, "us contains non-finite"),
        ({"init": (torch.zeros(2, 1), torch.ones(2, 1, 1))}, TypeError, "init must be a Gauss"),
    ],
)
def test_rolling_particle_prediction_refuses_before_drawing(change, error, message):
    model, b0, ys, us = _pp_args()
    if change.pop("ys_inf", False):
        ys = ys.clone()
        ys[3, 1, 0] = math.inf
    if change.pop("us_nan", False):
        us = us.clone()
        us[-1, 0] = math.nan  # a row the filter never reads: only the last prediction does
    kwargs = {"init": b0, **change}
    g = _gen(5)
    before = g.get_state()
    with pytest.raises(error, match=message):
        rolling_particle_prediction(
            sir(10), model, kwargs.pop("init"), ys, 2, generator=g, us=us, **kwargs
        )
    assert torch.equal(g.get_state(), before)


def test_rolling_particle_prediction_names_filter_and_model():
    model, b0, ys, us = _pp_args()
    with pytest.raises(TypeError, match="pf must be a ParticleFilter"):
        rolling_particle_prediction(sir, model, b0, ys, 2, generator=_gen(), us=us)
    with pytest.raises(TypeError, match="model must be a StateSpaceModel"):
        rolling_particle_prediction(sir(10), "model", b0, ys, 2, generator=_gen(), us=us)


# ----------------------------------------------------------------------------- forecaster
def test_forecaster_online_must_be_a_bool():
    elm = ELM(3, 5, generator=_gen())
    for bad in ("no", 0, 1.0):
        with pytest.raises(TypeError, match="online must be a bool"):
            MeasurementForecaster([elm], 3, online=bad)
    assert MeasurementForecaster([elm], 3, online=np.bool_(False)).online is False


def test_forecaster_learners_named():
    elm = ELM(3, 5, generator=_gen())
    with pytest.raises(TypeError, match=r"learners must be a sequence .*got ELM"):
        MeasurementForecaster(elm, 3)
    # a static learner of two outputs: its first output was used as the channel's forecast
    with pytest.raises(ValueError, match=r"learners\[0\] must map .* got n_out=2"):
        MeasurementForecaster([ELM(3, 5, 2, generator=_gen())], 3, online=False)
    assert MeasurementForecaster(torch.nn.ModuleList([elm]), 3).n_channels == 1
