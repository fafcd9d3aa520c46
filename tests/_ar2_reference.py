"""A fitted linear learner, ``z' = 0.3 z_1 + 0.6 z_2 + 0.05`` on min-max scaled values, and its
closed-form Kalman forecast: the exact reference for the model-file forecasts and RULs."""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn

from prognos_torch.datasets.windows import MinMaxScaler
from prognos_torch.workflow.fitted import FittedModel


def ar2_model(sigma: float = 0.04) -> tuple[FittedModel, torch.Tensor]:
    """The AR(2) learner as a fitted model with residual std ``sigma``, and its 10 values."""
    lin = nn.Linear(2, 1).to(torch.float64)
    with torch.no_grad():
        lin.weight.copy_(torch.tensor([[0.3, 0.6]], dtype=torch.float64))
        lin.bias.fill_(0.05)
    x = torch.tensor([1.0, 2.0, 1.5, 3.0, 2.5, 2.8, 3.1, 2.9, 3.3, 3.0], dtype=torch.float64)
    scaler = MinMaxScaler((0.0, 1.0)).fit(x)
    return FittedModel(lin, scaler, {"m": 2, "residual_rmse": sigma, "seed": 0}), x


def ar2_kalman_forecast(z: np.ndarray, start: int, H: int, sigma: float):
    """Kalman filter of the AR(2) model from the window ``z[start:start+2]`` (std r), over
    ``z[start+2:]`` (NaN: predict only), then ``H`` predictions with ``q = r = sigma /
    sqrt(2)`` on the newest element: ``(H,)`` means and measurement stds (scaled units)."""
    A, b = np.array([[0.0, 1.0], [0.3, 0.6]]), np.array([0.0, 0.05])
    q = r = sigma / math.sqrt(2.0)
    Q, R, h = np.diag([0.0, q * q]), r * r, np.array([0.0, 1.0])
    mu, P = z[start : start + 2].copy(), np.eye(2) * r * r
    for y in z[start + 2 :]:
        mu, P = A @ mu + b, A @ P @ A.T + Q
        if not np.isnan(y):
            S = h @ P @ h + R
            K = P @ h / S
            mu, P = mu + K * (y - mu[-1]), P - np.outer(K, K) * S
    means, stds = [], []
    for _ in range(H):
        mu, P = A @ mu + b, A @ P @ A.T + Q
        means.append(mu[-1])
        stds.append(math.sqrt(P[-1, -1] + R))
    return np.array(means), np.array(stds)
