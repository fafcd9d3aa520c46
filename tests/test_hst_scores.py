"""The paper-004 error measures of the high-speed train: true noise and per-run RMSEs."""

from __future__ import annotations

import math

import pytest
import torch

from prognos_torch.metrics import rmse
from prognos_torch.systems import (
    hst_estimation_errors,
    hst_measurement_variance,
    hst_noise_variances,
    hst_process_variance,
)


def test_noise_variances_follow_eq_67_68_with_the_library_step_shift():
    q, r = hst_noise_variances(5000)
    assert q.shape == r.shape == (5000,) and q.dtype == torch.float64
    assert float(q[0]) == 1.0  # step 1 uses Q_0 = 1 + 0.5 sin(0)
    assert float(q[4999]) == pytest.approx(1.0 + 0.5 * math.sin(0.0003 * 4999), rel=1e-15)
    assert float(r[0]) == pytest.approx(1.1 + 0.08 * math.cos(0.0002), rel=1e-15)
    assert float(r[99]) == hst_measurement_variance(100)
    assert float(q[99]) == hst_process_variance(99)
    with pytest.raises(ValueError):
        hst_noise_variances(0)


def test_estimation_errors_against_direct_rmse():
    g = torch.Generator().manual_seed(0)
    T, B = 40, 2
    truth = torch.randn(T + 1, B, 12, generator=g, dtype=torch.float64)
    means = truth[1:] + 0.1 * torch.randn(T, B, 12, generator=g, dtype=torch.float64)
    q, r = hst_noise_variances(T)
    qs = 1e-4
    var_Q = torch.cat(
        [qs * q[:, None, None].expand(T, B, 9), torch.ones(T, B, 3, dtype=torch.float64)], -1
    )
    var_R = r[:, None, None].expand(T, B, 9) + 0.2  # R off by 0.2 everywhere
    e = hst_estimation_errors(means, var_Q, var_R, truth, q_scale=qs, skip=10)
    torch.testing.assert_close(e["state"], rmse(means[..., :9], truth[1:, :, :9], dim=0))
    torch.testing.assert_close(e["fault"], rmse(means[..., 9:], truth[1:, :, 9:], dim=0))
    torch.testing.assert_close(
        e["Q"], torch.zeros(B, 9, dtype=torch.float64), atol=1e-12, rtol=0
    )  # oracle Q
    torch.testing.assert_close(e["R"], torch.full((B, 9), 0.2, dtype=torch.float64))
    torch.testing.assert_close(e["R_late"], torch.full((B, 9), 0.2, dtype=torch.float64))
    # the late window: only the steps after skip
    var_R2 = var_R.clone()
    var_R2[:10] += 5.0
    e2 = hst_estimation_errors(means, var_Q, var_R2, truth, q_scale=qs, skip=10)
    torch.testing.assert_close(e2["R_late"], e["R_late"])
    assert bool((e2["R"] > 1.0).all())
    with pytest.raises(ValueError, match="truth"):
        hst_estimation_errors(means, var_Q, var_R, truth[:T], q_scale=qs)
    with pytest.raises(ValueError, match="var_Q"):
        hst_estimation_errors(means, var_Q[:5], var_R, truth, q_scale=qs)
